"""Timings of the fleet test bed (deploy/testbed/bgt_testbed.py) on this machine: the Debian
rootfs build (cold with --cold, else cached), booting the three hosts, and the wall time of the
first and second `ansible-playbook site.yml` run (the second must report changed=0).

    sudo python bench/fleet_testbed.py [--cold]

Needs root and the test bed's Debian packages; boots the hosts in a temporary state directory
and takes them down again. --cold rebuilds the cached rootfs (a few minutes, from the apt mirror
of this machine's own sources).
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests" / "support"))
from testbed_loader import load_testbed  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cold", action="store_true", help="rebuild the cached rootfs first")
    a = ap.parse_args()
    tb = load_testbed()
    why = tb.missing_capability()
    if why:
        print(f"cannot boot the test bed here: {why}")
        return 1
    t0 = time.monotonic()
    _path, took, built = tb.build_rootfs(force=a.cold)
    print(
        f"rootfs {'cold build' if built else 'cached'}: {took if built else time.monotonic() - t0:.1f} s"
    )
    state = Path(tempfile.mkdtemp(prefix="bgt-testbed-bench-"))
    tb.use_state(state)
    try:
        up = tb.up()
        print(f"boot of 3 hosts: {up['boot_s']:.1f} s")
        for label in ("first", "second"):
            r = tb.deploy([])
            changed = {h: c.get("changed") for h, c in r.recap.items()}
            print(
                f"playbook {label} run: {r.seconds:.1f} s, exit {r.returncode}, changed {changed}"
            )
            if r.returncode != 0:
                print(r.output[-3000:])
                return 1
    finally:
        tb.down()
        shutil.rmtree(state, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
