"""Does the scan residual find each point's nearest vertex?

A point-cloud target's residual measures each point to the faces around its nearest vertex on
each object (``jaxplush.io.observe.nearest_vertices``). This script simulates random recovery
cases (``bench_recovery.py``'s draw) at the truth with ``jaxplush.simulate`` and counts, over every
frame, the target points whose vertex is farther than the nearest vertex of the scene (brute
force, float64), and by how much.

    python benchmarks/scan_nearest_check.py --random 40 --seed 1001 --cases 1,21,25

Until commit ba4ba39 the residual walked to the nearest vertex from a sparse set of starts; that
commit's version of this script (``scan_walk_check.py``) measured the walk. Figures in
benchmarks/RESULTS.md ("The scan residual's nearest vertex").
"""

from __future__ import annotations

import argparse
import os
import sys
import warnings

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--random", type=int, default=40)
    ap.add_argument("--seed", type=int, default=1001)
    ap.add_argument("--cases", required=True, help="comma-separated case indices (point-cloud cases)")
    args = ap.parse_args(argv)
    sys.path.insert(0, HERE)
    warnings.simplefilter("ignore")
    import bench_recovery as br
    import jax
    import jax.numpy as jnp
    from jaxplush.fitting.targets.scenarios import describe_case
    from jaxplush.io import observe as ob
    cases = br.draw_cases(args.random, args.seed, max_vertices=None, max_objects=3, kinds=("positions", "points"))
    for i in (int(c) for c in args.cases.split(",")):
        case = cases[i]
        at_truth = br.cloud_case_at_truth(case)
        if at_truth is None:
            print(f"case {i}: {describe_case(case)}: not a point-cloud target")
            continue
        target, frames, topo = at_truth
        slices = tuple((int(a), int(b)) for a, b in topo.vertex_slices)
        search = jax.jit(lambda x, p: ob.nearest_of(x, p, ob.nearest_vertices(x, p, slices)))
        points = np.asarray(target.points)
        missed = total = 0
        worst = 0.0
        for t in range(len(points)):
            x, p = frames[t], points[t]
            p = p[np.all(np.isfinite(p), axis=1)]
            w = np.asarray(search(jnp.asarray(x, jnp.float32), jnp.asarray(p, jnp.float32)))
            d2 = np.sum((x[None].astype(np.float64) - p[:, None]) ** 2, axis=-1)
            dw, db = np.sqrt(d2[np.arange(len(p)), w]), np.sqrt(d2.min(axis=1))
            miss = dw > db * (1 + 1e-4) + 1e-9             # the search's float32 tie resolution
            missed += int(miss.sum())
            total += len(p)
            worst = max(worst, float((dw - db).max()))
        print(f"case {i}: {describe_case(case)}: {missed} of {total} points ({100 * missed / max(total, 1):.2f}%) "
              f"measured from a vertex farther than the nearest; the worst {1e3 * worst:.2f} mm farther", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
