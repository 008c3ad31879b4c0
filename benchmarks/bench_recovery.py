"""Parameter recovery of the default fit, case by case, as a user runs it.

Scenes (``jaxplush.fitting.scenarios``), each dropped 0.2 m onto a floor, 0.12 kg, gas at 1800 Pa rest
pressure, k = 420 N/m:

* ``ball``: a 642-vertex icosphere with the report's per-step damping 2000;
* ``torus``: a 640-vertex torus lying flat, edge dashpot 0.1 N s/m;
* ``bean``: a 642-vertex bent ellipsoid dropped tilted by 30 degrees, edge dashpot 0.1 N s/m;
* ``ball2562``: the ball at 2562 vertices.

Targets: 3000 steps of 2e-4 s saved every 50 steps (``jaxplush simulate``), as positions, and as
point clouds of 400 points per frame with 2 mm noise. Starts: every corner of x0.5 / x2 in k,
the damping parameter and nmol. Every case runs ``jaxplush-fit START.obj TARGET.h5 --out
FIT.h5`` with no other options, in a fresh process (import and compile included, with the persistent
compilation cache off, as on a user's first fit of a scene); it passes when
the fit says converged (exit 0) and every parameter is within 1% (positions) or 3% (points) of
the truth, within 60 s (240 s at 2562 vertices). A failed case is listed, never dropped.

Usage: python benchmarks/bench_recovery.py [--scenes ball,torus,bean,ball2562] [--kinds positions,points]
           [--corners all|N] [--json results.jsonl]
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
import warnings

import h5py
import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

SCENES = {
    "ball": dict(shape="ball", subdivisions=3, damping=2000.0, dashpot=None),
    "torus": dict(shape="torus", subdivisions=3, damping=None, dashpot=0.1),
    "bean": dict(shape="bean", subdivisions=3, damping=None, dashpot=0.1, tilt_deg=30.0),
    "ball2562": dict(shape="ball", subdivisions=4, damping=2000.0, dashpot=None),
}
TOLERANCE = {"positions": 0.01, "points": 0.03}
TIME_LIMIT = {642: 60.0, 640: 60.0, 2562: 240.0}
STEPS, DT, SAVE_EVERY = 3000, 2e-4, 50


def _damp_name(spec):
    return "damping" if spec["damping"] is not None else "dashpot"


def make_case_files(d, name, kind):
    """Write the truth scene and the target of one scene and target kind; return (truth scene, target path)."""
    import jaxplush
    from jaxplush.fitting.scenarios import drop_scene_text
    from jaxplush.fitting.targets import make_target
    spec = dict(SCENES[name])
    text = drop_scene_text(spec.pop("shape"), spec.pop("subdivisions"), **spec)
    truth_path = os.path.join(d, f"{name}_truth.obj")
    with open(truth_path, "w") as fh:
        fh.write(text)
    truth = jaxplush.load_scene(truth_path)
    target = os.path.join(d, f"{name}_{kind}.h5")
    if kind == "positions":
        subprocess.run([sys.executable, "-m", "jaxplush", "simulate", truth_path, "--steps", str(STEPS), "--dt", str(DT),
                        "--save-every", str(SAVE_EVERY), "--out", target, "--quiet"], check=True, capture_output=True)
    else:
        make_target(truth, STEPS, DT, SAVE_EVERY, point_cloud=True, n_points=400, noise=0.002, seed=1).save(target, truth)
    return truth, target


def start_scene(d, name, truth, factors):
    from jaxplush.scene.write import format_scene
    from jaxplush.fitting.io import fitted_scene_text  # noqa: F401  (the same writer the fit uses)
    spec = SCENES[name]
    dn = _damp_name(spec)
    p = truth.params
    o = truth.objects[0]
    obj = dict(name=o.name, vertices=truth.vertices, faces=truth.faces, total_weight=float(p.total_weight[0]),
               k_structural=float(p.k_structural[0]) * factors[0], nmol=float(p.nmol[0]) * factors[2])
    obj[dn] = float(getattr(p, dn)[0]) * factors[1]
    text = format_scene([obj], gravity=truth.gravity, floor=truth.floor, temperature=truth.temperature,
                        header=f"{name}: start at k x{factors[0]:g}, {dn} x{factors[1]:g}, nmol x{factors[2]:g}")
    path = os.path.join(d, f"{name}_start_{'_'.join(f'{f:g}' for f in factors)}.obj")
    with open(path, "w") as fh:
        fh.write(text)
    return path


def run_case(d, name, kind, truth, target, factors):
    start = start_scene(d, name, truth, factors)
    out = os.path.join(d, "FIT.h5")
    if os.path.exists(out):
        os.remove(out)
    t = time.perf_counter()
    # cold: no persistent compilation cache, so every case compiles as a user's first fit does
    env = dict(os.environ, JAXPLUSH_CACHE_DIR="off")
    proc = subprocess.run([sys.executable, "-m", "jaxplush.fitting.cli", start, target, "--out", out, "--quiet"],
                          capture_output=True, text=True, env=env)
    wall = time.perf_counter() - t
    spec = SCENES[name]
    names = ("k_structural", _damp_name(spec), "nmol")
    row = dict(scene=name, kind=kind, vertices=truth.n_vertices, factors=list(factors), wall=wall,
               exit=proc.returncode)
    if not os.path.exists(out):
        row.update(status="no FIT.h5", errors={}, max_error=float("inf"), message=proc.stderr.strip()[-300:])
        return row
    with h5py.File(out, "r") as f:
        fitted = {n: float(f["params"][n][0]) for n in names}
        row["status"] = str(f.attrs["status"])
        row["message"] = str(f.attrs.get("reason", ""))
    errors = {n: fitted[n] / float(getattr(truth.params, n)[0]) - 1.0 for n in names}
    row.update(errors=errors, max_error=max(abs(e) for e in errors.values()))
    limit = TIME_LIMIT.get(truth.n_vertices, 60.0)
    row["passed"] = bool(row["exit"] == 0 and row["status"] == "converged" and row["max_error"] <= TOLERANCE[kind]
                         and wall <= limit)
    return row


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", default=",".join(SCENES))
    ap.add_argument("--kinds", default="positions,points")
    ap.add_argument("--corners", default="all", help="all, the first N corners, or indices I,J,... (0-7)")
    ap.add_argument("--json", default=None, help="append each case as a JSON line to this file")
    args = ap.parse_args(argv)
    corners = list(itertools.product((0.5, 2.0), repeat=3))
    if args.corners != "all":
        picked = [int(c) for c in args.corners.split(",")]
        corners = corners[:picked[0]] if len(picked) == 1 else [corners[i] for i in picked]
    print(f"# {platform.machine()}, {os.cpu_count()} cores, python {platform.python_version()}; "
          f"{time.strftime('%Y-%m-%d %H:%M')}", flush=True)
    print("| scene | target | start (k, damping, nmol) | wall s | exit | status | max error | errors |", flush=True)
    print("|---|---|---|---:|---:|---|---:|---|", flush=True)
    rows = []
    with tempfile.TemporaryDirectory() as d:
        for name in args.scenes.split(","):
            for kind in args.kinds.split(","):
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    truth, target = make_case_files(d, name, kind)
                for factors in corners:
                    row = run_case(d, name, kind, truth, target, factors)
                    rows.append(row)
                    errs = " ".join(f"{n.replace('k_structural', 'k')} {100 * e:+.3f}%" for n, e in row["errors"].items())
                    flag = "" if row.get("passed") else " **FAILED**"
                    print(f"| {name} | {kind} | x{factors[0]:g}, x{factors[1]:g}, x{factors[2]:g} | {row['wall']:.1f} | "
                          f"{row['exit']} | {row['status']}{flag} | {100 * row['max_error']:.3f}% | {errs} |", flush=True)
                    if args.json:
                        with open(args.json, "a") as fh:
                            fh.write(json.dumps(row) + "\n")
    passed = sum(bool(r.get("passed")) for r in rows)
    print(f"\n{passed} of {len(rows)} cases passed "
          f"(converged, within {100 * TOLERANCE['positions']:g}% / {100 * TOLERANCE['points']:g}%, in time)")
    for r in rows:
        if not r.get("passed"):
            print(f"FAILED: {r['scene']} {r['kind']} start x{r['factors']}: exit {r['exit']}, {r['status']}, "
                  f"max error {100 * r['max_error']:.3g}%, {r['wall']:.1f} s: {r.get('message', '')[:200]}")
    return 0 if passed == len(rows) else 1


if __name__ == "__main__":
    sys.exit(main())
