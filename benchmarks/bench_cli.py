"""A newcomer's first commands, timed as whole processes: the quick start's simulate, ``info``
(closed-form bound and ``--exact``) and ``render`` (the default real-time GIF and a 200-frame GIF).

Each command runs as a fresh process (``python -m jaxplush ...``), so import and compile times
are included, as a user sees them. Median of ``--repeats`` runs.

Usage: python benchmarks/bench_cli.py [--repeats 3]
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time

ROOT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..")


def _run(args, cwd):
    t = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "jaxplush", *args], cwd=cwd, capture_output=True, text=True)
    wall = time.perf_counter() - t
    if proc.returncode != 0:
        raise SystemExit(f"{' '.join(args)} failed:\n{proc.stderr}")
    return wall, proc.stdout


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args(argv)
    scene = os.path.join(ROOT, "scenes", "ball_drop.obj")
    rows = []
    with tempfile.TemporaryDirectory() as d:
        cases = [
            ("simulate (quick start, 16000 steps, 642 vertices)",
             ["simulate", scene, "--steps", "16000", "--dt", "1.25e-4", "--save-every", "80", "--out", "ball_drop.h5",
              "--quiet"]),
            ("info (closed-form bound)", ["info", scene]),
            ("info --exact (power iteration)", ["info", scene, "--exact"]),
            ("render ball_drop.gif (default: real time)", ["render", "ball_drop.h5", "--out", "ball_drop.gif"]),
            ("render 200 frames (--fps 30)", ["render", "ball_drop.h5", "--out", "b200.gif", "--fps", "30"]),
        ]
        for name, cmd in cases:
            walls, out = [], ""
            for _ in range(args.repeats):
                w, out = _run(cmd, d)
                walls.append(w)
            extra = ""
            if cmd[0] == "render":
                extra = f"{os.path.getsize(os.path.join(d, cmd[3])) / 1e6:.2f} MB; " + out.splitlines()[0]
            rows.append((name, statistics.median(walls), extra))
    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores; python {platform.python_version()}")
    print(f"{'command':<52} {'wall s':>7}  notes")
    for name, wall, extra in rows:
        print(f"{name:<52} {wall:>7.2f}  {extra}")


if __name__ == "__main__":
    main()
