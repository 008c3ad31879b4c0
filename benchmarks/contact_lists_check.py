"""Do the carried contact candidate lists give the force of a fresh search, step by step?

Runs one scene with soft-soft contact through the single-scene coherent step (the candidate lists
carried from step to step, as every rollout does) in a Python loop, and at every step from
``--from`` on compares the contact force read from the carried lists with the force of a fresh
search at the same positions (the model's definition). Prints every step where they differ by
more than ``--tol`` of the largest contact force, with the vertex, and, at the first steps of each
episode, the query's nearest vertex in the carried lists against the one a fresh search finds.

    python benchmarks/contact_lists_check.py                      # seed 1001's case 8 (its truth)
    python benchmarks/contact_lists_check.py --scene S.obj --steps 3000 --dt 1e-4

Findings in benchmarks/RESULTS.md ("The carried contact lists can miss the nearest vertex").
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import warnings

import numpy as np


def case_scene(n, seed, index):
    sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
    import bench_recovery as br
    case = br.draw_cases(n, seed, max_vertices=None, max_objects=3, kinds=("positions", "points"))[index]
    with tempfile.TemporaryDirectory() as d:
        truth, _, _ = br.random_case_files(d, case)
    return truth, case["dt"]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", help="a scene file (default: bench_recovery.py --random 40 --seed 1001, case 8)")
    ap.add_argument("--dt", type=float, default=None)
    ap.add_argument("--steps", type=int, default=3000)
    ap.add_argument("--from", dest="start", type=int, default=2600, help="first step compared")
    ap.add_argument("--tol", type=float, default=1e-3, help="relative to the largest contact force")
    args = ap.parse_args(argv)
    warnings.simplefilter("ignore")
    import jax
    import jaxplush
    from jaxplush.model import contact as C
    if args.scene:
        scene, dt = jaxplush.load_scene(args.scene), args.dt or 1e-4
    else:
        scene, dt = case_scene(40, 1001, 8)
        dt = args.dt or dt
    sim = jaxplush.make_simulator(scene, dt)
    coh = sim.internal.coherent
    if coh is None:
        print("the scene has no soft-soft contact between objects")
        return 1
    force, ops = C.make_contact(sim.topology, sim.terms.contact, dt)
    p = scene.params
    state = sim.internal.to_internal(sim.init_fn(p))
    cache = coh.init(state.x)
    step = jax.jit(lambda s, c: coh.step(p, s, c))
    # the velocities the step's force reads (contact friction needs them)
    carried = jax.jit(lambda x, v, c: force(p, x, v, cache=c))
    fresh = jax.jit(lambda x, v: force(p, x, v))
    search = jax.jit(ops.init)
    bad, shown = 0, set()
    for n in range(args.steps):
        if n >= args.start:
            a, b = np.asarray(carried(state.x, state.v, cache)), np.asarray(fresh(state.x, state.v))
            scale = float(np.abs(b).max())
            diff = np.abs(a - b)
            if scale > 0 and diff.max() > args.tol * scale:
                bad += 1
                v = int(np.unravel_index(diff.argmax(), diff.shape)[1])
                line = f"step {n}: vertex {v}: carried lists' force off by {diff.max():.3g} N ({diff.max() / scale:.1%} of the largest)"
                if v not in shown:
                    shown.add(v)
                    x = np.asarray(state.x)
                    for name, c in (("carried", cache), ("fresh", search(state.x))):
                        q, ok, t = (np.asarray(c.q_idx), np.asarray(c.valid), np.asarray(c.target))
                        slots = np.nonzero((q == v) & ok)[0]
                        if slots.size:
                            j = int(t[slots[0]])
                            line += f"; {name}: nearest vertex {j} at {1e3 * np.linalg.norm(x[:, v] - x[:, j]):.3f} mm"
                        else:
                            line += f"; {name}: not a query"
                print(line, flush=True)
        state, cache = step(state, cache)
    print(f"{bad} of {max(args.steps - args.start, 0)} steps compared differ by more than {args.tol:g} of the largest contact force")
    return 0


if __name__ == "__main__":
    sys.exit(main())
