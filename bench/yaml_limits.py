"""Bench: what a hostile YAML file costs now that every YAML file goes through safe_yaml.

1. `annotator track` on an experiment whose camera calibration is a 342-byte "billion laughs"
   (nine levels of nine aliases; before safe_yaml such a file grew the process to 5.4 GB):
   exit code, the one line printed, wall time and the process's peak RSS.
2. safe_yaml.load_file alone on the same file, in a bare child process.
3. The largest document accepted (MAX_NODES - 1 values) and one of 16x that, refused: seconds
   and peak RSS of a bare child process each.

Peak RSS is the child's ru_maxrss (os.wait4). Run from the repository root:

    python bench/yaml_limits.py
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tempfile
import textwrap
import time
from pathlib import Path

from bgt_core.safe_yaml import MAX_NODES
from bgt_core.sites import site_dir

BILLION_LAUGHS = 'a: &a ["lol","lol","lol","lol","lol","lol","lol","lol","lol"]\n' + "".join(
    f"{n}: &{n} [{','.join(['*' + p] * 9)}]\n" for p, n in zip("abcdefgh", "bcdefghi", strict=True)
)

RIG = """\
cameras:
  front:
    calibration: front.yaml
    R_bundle_camera: [[0, 0, 1], [-1, 0, 0], [0, -1, 0]]
    t_bundle_camera: [0.04, 0.0, 0.0]
"""
EXPERIMENT = """\
markers: {file: marker_positions.dat, dictionary: DICT_6X6_50, length: 0.298}
rig: rig.yaml
videos: {front: front.mp4}
sync: {mode: manual, video_start: {front: 1700000000.0}}
"""

CHILD = textwrap.dedent("""\
    import sys, time
    from bgt_core.safe_yaml import YamlError, load_file
    t = time.monotonic()
    try:
        load_file(sys.argv[1])
        outcome = "loaded"
    except YamlError as e:
        outcome = "refused: " + str(e)
    print(f"{time.monotonic() - t:.4f}|{outcome}")
""")


def run_measured(cmd: list[str]) -> tuple[int, float, float, str, str]:
    """(exit code, wall seconds, peak RSS MiB, stdout, stderr) of one child process."""
    with tempfile.TemporaryFile("w+") as out, tempfile.TemporaryFile("w+") as err:
        t = time.monotonic()
        p = subprocess.Popen(cmd, stdout=out, stderr=err)
        _, status, usage = os.wait4(p.pid, 0)
        wall = time.monotonic() - t
        p.returncode = os.waitstatus_to_exitcode(status)
        out.seek(0)
        err.seek(0)
        return p.returncode, wall, usage.ru_maxrss / 1024, out.read(), err.read()


def main() -> None:
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        (d / "front.yaml").write_text(BILLION_LAUGHS)
        (d / "rig.yaml").write_text(RIG)
        shutil.copy(site_dir("tetam") / "marker_positions.dat", d / "marker_positions.dat")
        (d / "front.mp4").write_bytes(b"")
        (d / "experiment.yaml").write_text(EXPERIMENT)
        print(f"billion-laughs calibration: {len(BILLION_LAUGHS)} bytes")

        code, wall, peak, _, err = run_measured(
            [
                sys.executable,
                "-m",
                "annotator.cli",
                "track",
                str(d / "experiment.yaml"),
                "--out",
                str(d / "out"),
            ]
        )
        lines = err.strip().splitlines()
        print(
            f"annotator track: exit {code} in {wall:.2f} s, peak RSS {peak:.0f} MiB, "
            f"{len(lines)} line(s) on stderr: {lines[0] if lines else ''}"
        )

        for name, path in [("billion laughs", d / "front.yaml")]:
            code, wall, peak, out, _ = run_measured([sys.executable, "-c", CHILD, str(path)])
            secs, outcome = out.strip().split("|", 1)
            print(
                f"safe_yaml, {name}: {outcome} ({secs} s to decide; child peak RSS {peak:.0f} MiB)"
            )

        for n in (MAX_NODES - 1, 16 * MAX_NODES):
            p = d / f"list_{n}.yaml"
            p.write_text("[" + ",".join(["1"] * n) + "]\n")
            code, wall, peak, out, _ = run_measured([sys.executable, "-c", CHILD, str(p)])
            secs, outcome = out.strip().split("|", 1)
            print(
                f"safe_yaml, list of {n} values ({p.stat().st_size / 2**20:.1f} MiB): "
                f"{outcome.split(':')[0]} in {secs} s, child peak RSS {peak:.0f} MiB"
            )


if __name__ == "__main__":
    main()
