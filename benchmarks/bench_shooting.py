"""Single against multiple shooting on sensitive motions (issue 25, item 2).

For each case a noise-free position target is simulated from the scene (float32, as ``jaxplush
simulate`` writes it), and the default fit starts from k x1.6, damping x0.7, nmol x1.4 with
``--shooting off`` (one rollout), ``--shooting auto`` (what the plan chooses) and
``--shooting N`` (segments of the measured horizon's length). Printed: wall time, status, each
parameter's relative error, and what ``auto`` chose and why.

    python benchmarks/bench_shooting.py [--cases tumble,torus,bean,hang] [--modes off,auto,horizon]
"""

from __future__ import annotations

import argparse
import time
import warnings

import jax
import numpy as np

import jaxplush
from jaxplush.fitting import fitter
from jaxplush.fitting.objective import shooting
from jaxplush.fitting.targets.scenarios import drop_scene_text
from jaxplush.fitting.targets import make_target

FACTORS = (1.6, 0.7, 1.4)


def case(name):
    """(scene, steps, dt, save_every, fitted names)."""
    if name == "tumble":       # 162-vertex bean tumbling onto the floor, report's damping, 4 ms frames
        return (jaxplush.parse_scene(drop_scene_text("bean", 2, tilt_deg=30.0), "<tumble>"), 1000, 4e-4, 10,
                ["k_structural", "nmol"])
    if name in ("torus", "bean"):   # 642 vertices dropped with the report's damping 1500, 10 ms frames
        text = drop_scene_text(name, 3, damping=1500.0, tilt_deg=0.0 if name == "torus" else 30.0)
        return jaxplush.parse_scene(text, f"<{name}>"), 3000, 2e-4, 50, ["k_structural", "damping", "nmol"]
    if name == "hang":              # 642-vertex bean hanging from one pinned vertex, no floor
        text = drop_scene_text("bean", 3, damping=1500.0, tilt_deg=20.0).replace("floor 0.0", "")
        sc = jaxplush.parse_scene(text, "<hang>")
        i = int(np.argmax(sc.vertices[:, 0]))
        sc = jaxplush.parse_scene(text.replace("END_OBJECT", f"fixed {i + 1}\nEND_OBJECT"), "<hang>")
        return sc, 3000, 2e-4, 50, ["k_structural", "damping", "nmol"]
    raise SystemExit(f"unknown case {name}")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--cases", default="tumble,torus,bean,hang")
    ap.add_argument("--modes", default="off,auto,horizon")
    a = ap.parse_args(argv)
    warnings.simplefilter("ignore")
    rows = []
    for name in a.cases.split(","):
        scene, steps, dt, every, names = case(name)
        target = make_target(scene, steps, dt, every)
        truth = {n: float(np.asarray(getattr(scene.params, n))[0]) for n in names}
        start = {n: truth[n] * f for n, f in zip(names, FACTORS)}
        for mode in a.modes.split(","):
            setting = mode
            if mode == "horizon":
                prob = fitter.measure_predictability(fitter.build_problem(scene, target, names, noise_free=True))
                setting = shooting.segment_frames_for(prob) or "off"
            lines = []
            t0 = time.perf_counter()
            r = fitter.fit(scene, target, names, noise_free=True, start=start, shooting=setting, report=lines.append,
                           identifiability=False)
            wall = time.perf_counter() - t0
            errs = " ".join(f"{n.replace('_structural', '')} {100 * (float(np.asarray(r.values[n])[0]) / truth[n] - 1):+.2f}%"
                            for n in names)
            how = next((x[len("shooting: "):] for x in lines if x.startswith("shooting: ")), "")
            rows.append((name, str(setting), f"{wall:.1f}", r.status, errs, how))
            print(" | ".join(rows[-1]), flush=True)
    print()
    print("| case | --shooting | wall s | status | errors | what the fit said |")
    print("|---|---|---|---|---|---|")
    for r in rows:
        print("| " + " | ".join(r) + " |")


if __name__ == "__main__":
    main()
