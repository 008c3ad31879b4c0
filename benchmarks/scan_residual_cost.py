"""What the scan residual costs, and what it reads at the truth.

For random recovery cases with point-cloud targets (``bench_recovery.py``'s draw), this script
simulates the truth with ``jaxplush.simulate``, builds the fit's residual of the target
(``jaxplush.io.observe.surface_residual``, with the target's known noise), and reports:

* the residual at the truth: its RMS (at the true values it should be the scan's noise) and its
  largest entry;
* the time of one compiled call over a batch of lanes (the truth's frames repeated, as the fit's
  evaluator calls it: every frame of every lane in one piece), best of repeats, and its compile;
* the peak memory of the process (``ru_maxrss``) after those calls.

    python benchmarks/scan_residual_cost.py --random 40 --seed 1001 --cases 25 --lanes 32
    python benchmarks/scan_residual_cost.py ... --root TREE      (another source tree, e.g. a worktree)

Run each tree in its own process (peak memory is the process's). Figures in benchmarks/RESULTS.md
("The scan residual's nearest vertex").
"""

from __future__ import annotations

import argparse
import os
import resource
import sys
import time
import warnings

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--random", type=int, default=40)
    ap.add_argument("--seed", type=int, default=1001)
    ap.add_argument("--cases", required=True, help="comma-separated case indices (point-cloud cases)")
    ap.add_argument("--lanes", type=int, default=32, help="batch lanes per call (the fit's batch: 32)")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--root", help="import jaxplush from this source tree")
    args = ap.parse_args(argv)
    if args.root:
        sys.path.insert(0, args.root)
        import jaxplush
        jaxplush.__path__.append(args.root)
    sys.path.insert(0, HERE)
    warnings.simplefilter("ignore")
    import bench_recovery as br
    import jax
    import jax.numpy as jnp
    import jaxplush
    from jaxplush.fitting.targets.scenarios import describe_case
    from jaxplush.io import observe as ob
    print(f"# jaxplush from {os.path.dirname(jaxplush.__file__)}; {args.lanes} lanes")
    print("| case | vertices | frames x points | RMS at the truth (mm) | largest (mm) | compile (s) | call (ms) | peak RSS (GB) |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|")
    cases = br.draw_cases(args.random, args.seed, max_vertices=None, max_objects=3, kinds=("positions", "points"))
    for i in (int(c) for c in args.cases.split(",")):
        case = cases[i]
        at_truth = br.cloud_case_at_truth(case)
        if at_truth is None:
            print(f"case {i}: {describe_case(case)}: not a point-cloud target")
            continue
        target, frames, topo = at_truth
        points = np.asarray(target.points, np.float32)
        sigma = float(target.noise)
        frame_fn, _, _ = ob.surface_residual(target, topo, sigma ** 2, "noise")
        fn = jax.jit(jax.vmap(frame_fn, in_axes=(0, None)))
        x = jnp.asarray(np.repeat(frames[None], args.lanes, axis=0))
        y = jnp.asarray(points)
        t = time.perf_counter()
        r = np.asarray(fn(x, y).block_until_ready())[0]
        compile_s = time.perf_counter() - t
        times = []
        for _ in range(args.repeats):
            t = time.perf_counter()
            fn(x, y).block_until_ready()
            times.append(time.perf_counter() - t)
        valid = np.all(np.isfinite(points), axis=-1).reshape(-1)
        r = r[valid]
        rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2 ** 20
        print(f"| {i} {describe_case(case)} | {topo.n_vertices} | {points.shape[0]} x {points.shape[1]} | "
              f"{1e3 * np.sqrt(np.mean(r ** 2)):.3f} | {1e3 * np.abs(r).max():.2f} | {compile_s:.2f} | "
              f"{1e3 * min(times):.0f} | {rss:.2f} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
