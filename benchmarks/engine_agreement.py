"""How far the fit's engine is from the target at the truth, against two runs that differ by rounding.

For random recovery cases (``bench_recovery.py``'s draw) with positions targets, this runs the
fit's own evaluator (the batched engine, float32, as a default fit runs it) at the true parameter
values, with three more lanes whose values differ by 1e-6 (log space, a rounding-level
perturbation), and prints per case the RMS distance of the frames from the target (which
``jaxplush.simulate`` made) and from those lanes, at the last frame and over all frames, and the
fit's loss at the truth. Where the engine follows ``simulate`` to rounding, the distance from the
target is of the size of the lanes' spread.

    python benchmarks/engine_agreement.py --random 40 --seed 1001 --cases 4,5,8,9
    python benchmarks/engine_agreement.py ... --root TREE     (another source tree, e.g. a worktree)

Figures in benchmarks/RESULTS.md ("The carried contact lists can miss the nearest vertex").
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import warnings

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--random", type=int, default=40)
    ap.add_argument("--seed", type=int, default=1001)
    ap.add_argument("--cases", required=True, help="comma-separated case indices")
    ap.add_argument("--root", help="import jaxplush from this source tree")
    args = ap.parse_args(argv)
    if args.root:
        sys.path.insert(0, args.root)
        import jaxplush
        jaxplush.__path__.append(args.root)
    sys.path.insert(0, HERE)
    warnings.simplefilter("ignore")
    import bench_recovery as br
    from jaxplush.fitting.objective.evaluate import Evaluator
    from jaxplush.fitting.objective.problem import build_problem
    from jaxplush.fitting.targets import load_target
    from jaxplush.fitting.targets.scenarios import case_truth, describe_case
    import jaxplush
    cases = br.draw_cases(args.random, args.seed, max_vertices=None, max_objects=3, kinds=("positions", "points"))
    print("| case | scene | last frame: from the target / lanes' spread (um) | all frames (um) | loss at the truth |")
    print("|---|---|---|---|---|")
    for i in (int(c) for c in args.cases.split(",")):
        case = cases[i]
        with tempfile.TemporaryDirectory() as d:
            truth, target_path, start_path = br.random_case_files(d, case)
            scene = jaxplush.load_scene(start_path)
            target = load_target(target_path, scene)
            names = tuple(case["params"])
            prob = build_problem(scene, target, params=names, noise_free=target.noise in (None, 0))
            values = case_truth(case)
            theta = np.log(np.stack([np.asarray(values[n], np.float64) for n in names]))
            rng = np.random.default_rng(0)
            pts = [theta] + [theta + 1e-6 * rng.standard_normal(theta.shape) for _ in range(3)]
            ev = Evaluator(prob)(np.asarray(pts), keep_frames=True)
            fr = np.asarray(ev.frames)
            tp = np.asarray(target.positions) if target.positions is not None else None
        if tp is None:
            print(f"| {i} | {describe_case(case)} | (a point-cloud target: not compared) | | |")
            continue
        rms = lambda a, b: np.sqrt(np.mean((a - b) ** 2, axis=(-2, -1)))       # noqa: E731
        last_t, all_t = 1e6 * rms(fr[0], tp)[-1], 1e6 * np.sqrt(np.mean(rms(fr[0], tp) ** 2))
        lanes_last = [1e6 * rms(fr[0], fr[j])[-1] for j in range(1, len(pts))]
        lanes_all = [1e6 * np.sqrt(np.mean(rms(fr[0], fr[j]) ** 2)) for j in range(1, len(pts))]
        print(f"| {i} | {describe_case(case)} | {last_t:.3g} / {min(lanes_last):.2g}-{max(lanes_last):.2g} | "
              f"{all_t:.3g} / {min(lanes_all):.2g}-{max(lanes_all):.2g} | {ev.loss[0]:.3g} |", flush=True)
        print("JSON " + json.dumps(dict(case=i, last=last_t, all=all_t, lanes_last=lanes_last, lanes_all=lanes_all,
                                        loss=float(ev.loss[0]))), file=sys.stderr, flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
