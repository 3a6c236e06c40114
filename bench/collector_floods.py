"""One misbehaving agent against `collector serve` on loopback, while two honest agents record.

    python bench/collector_floods.py [--scenario macs|maxsize|both] [--macs 5000] [--seconds 20]
                                     [--nofile 1024] [--streams-per-agent N] [--streams-total N]
                                     [--mtls]

Scenarios (issue 11):
  macs     the flooder publishes one batch on each of `--macs` distinct sensor MACs, under a
           RLIMIT_NOFILE of `--nofile` for the collector;
  maxsize  the flooder publishes maximum-size batches (100,000 readings) as fast as the
           collector takes them for `--seconds`.
Meanwhile two honest agents publish 10 batches/s of 10 readings each and re-send whatever is
not acknowledged, as a real agent's spool does. With --mtls every party has its own certificate
from a throw-away site CA and the collector enforces the ACL deploy/ generates.

Prints per scenario: the collector's peak RSS (VmRSS sampled every 50 ms, and VmHWM), honest
readings lost and duplicated in the run files, the time from the end of the flood until every
honest batch is acknowledged (drain), the time `collector stop` took, the refused-stream and
rejected counts from `collector status`, and the size of that status reply.

The flood itself lives in tests/support/flood_harness.py, shared with the tests that assert
on it (tests/collector/test_collector_limits.py).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

TESTS = Path(__file__).resolve().parent.parent / "tests"
sys.path.insert(0, str(TESTS / "support"))
from flood_harness import make_site_pki, run_flood  # noqa: E402 - on the test path above


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--scenario", choices=("macs", "maxsize", "both"), default="both")
    ap.add_argument("--macs", type=int, default=5000)
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--nofile", type=int, default=1024)
    ap.add_argument(
        "--streams-per-agent",
        type=int,
        default=0,
        help="limits.streams_per_agent (default: the collector's)",
    )
    ap.add_argument(
        "--streams-total",
        type=int,
        default=0,
        help="limits.streams_total (default: the collector's)",
    )
    ap.add_argument("--mtls", action="store_true", help="mutual TLS and the generated ACL")
    args = ap.parse_args()
    limits = {}
    if args.streams_per_agent:
        limits["streams_per_agent"] = args.streams_per_agent
    if args.streams_total:
        limits["streams_total"] = args.streams_total
    for name in ("macs", "maxsize") if args.scenario == "both" else (args.scenario,):
        work = Path(tempfile.mkdtemp(prefix="bgt-flood-"))
        pki_dir = make_site_pki(work / "pki") if args.mtls else None
        r = run_flood(
            name,
            work,
            macs=args.macs,
            seconds=args.seconds,
            nofile=args.nofile if name == "macs" else None,
            limits=limits,
            pki_dir=pki_dir,
        )
        st = r.status
        print(f"{name}: {r.flood} (flood {r.flood_s} s){' over mTLS' if args.mtls else ''}")
        print(
            f"  collector RSS peak {r.rss_peak_kib / 1024:.1f} MiB (sampled every 50 ms), "
            f"VmHWM {r.hwm_kib / 1024:.1f} MiB"
        )
        for a, h in r.honest.items():
            print(
                f"  honest {a}: {h.readings} readings, lost {h.lost}, duplicated {h.dup}, foreign {h.foreign}"
            )
        print(
            f"  drain (flood end -> every honest batch acknowledged) {r.drain_s} s"
            f"{'' if r.settled else ' (NOT settled)'}; collector stop {r.stop_s} s; "
            f"SIGINT to exit {r.shutdown_s} s (exit code {r.returncode})"
        )
        print(
            f"  refused streams {st['refused_streams']}; rejected {st['rejected_payloads']}; "
            f"queue overflow {st['queue_overflow']}; flooder files {r.flood_files}; "
            f"open files {st['streams']['open_files']}; status reply {r.status_bytes} bytes"
        )


if __name__ == "__main__":
    main()
