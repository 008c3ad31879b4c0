"""Soft-soft contact in the batched engine: the contact term's cost, its transposes, and the default
fit's Evaluator on a two-ball scene, batched against one point at a time.

1. Step cost of one 16-point chunk (``jaxplush.stepping.batched.rollout``, one core) of two 162-vertex balls
   pressed together (the batched engine with contact, without it, and with only the transposes
   that contact adds: positions (V, B) components -> (B, 3, V) and a (B, 3, V) force back).
2. The Evaluator (:class:`jaxplush.fitting.objective.evaluate.Evaluator`) on a fit of both balls' k to a
   target of ``--steps`` steps (frames every 25): ``--points`` points, batched (its default for
   the scene) and one at a time (``ev.batched = False``, the path such scenes took before),
   best of ``--repeats`` calls after a compiling call, in ms per point.

Usage: python benchmarks/bench_batched_contact.py [--sub 2] [--steps 300] [--points 32] [--repeats 3]
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import time
import warnings

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))
sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "tests"))
import jaxplush  # noqa: E402,F401  (before jax: it sets options jax reads when imported)
import jax  # noqa: E402
from jaxplush.stepping import batched  # noqa: E402
from jaxplush.fitting import fitter as F  # noqa: E402
from jaxplush.fitting.objective.evaluate import Evaluator  # noqa: E402
from jaxplush.fitting.targets import make_target  # noqa: E402
from test_contact import two_balls  # noqa: E402

DT = 2e-4
CHUNK = 16


def _best(fn, repeats):
    fn()
    best = np.inf
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t)
    return best


def step_costs(scene, steps, repeats):
    """us per point-step of a 16-point chunk: with contact, without, with the transposes alone."""
    full = batched.make_batched_simulator(scene, DT, CHUNK)
    variants = {"with contact": full,
                "no contact": batched.make_batched_simulator(scene, DT, CHUNK,
                                                             terms=dataclasses.replace(full.terms, contact=None))}
    real = batched._make_contact

    def transposes_only(topo, terms, h):
        def add(params, x, v, f, cache=None):
            g = batched._lanes(x).transpose(1, 2, 0) * 1e-30
            return tuple(fc + g[c] for c, fc in enumerate(f))
        return batched._Contact(add, None, None, None)

    batched._make_contact = transposes_only
    try:
        variants["transposes only"] = batched.make_batched_simulator(scene, DT, CHUNK)
    finally:
        batched._make_contact = real
    for label, bsim in variants.items():
        pb = bsim.params()
        st = bsim.init_fn(pb)
        wall = _best(lambda: jax.block_until_ready(batched.rollout(bsim, pb, st, 1, steps)[0].x), repeats)
        print(f"  {label:16s} {wall / steps / CHUNK * 1e6:7.2f} us/point-step", flush=True)


def evaluator_costs(scene, steps, n_points, repeats):
    """ms per point of the Evaluator, batched and one at a time, and the largest loss difference."""
    target = make_target(scene, steps, DT, 25)
    prob = F.build_problem(scene, target, ("k_structural",), objects=["a", "b"])
    rng = np.random.default_rng(0)
    thetas = np.asarray(prob.theta0)[None] + 0.3 * rng.standard_normal((n_points,) + np.shape(prob.theta0))
    loss = {}
    for mode in ("batched", "single"):
        ev = Evaluator(prob, calibrate=False)
        ev.batched = ev.batched and mode == "batched"
        wall = _best(lambda: loss.__setitem__(mode, ev(thetas).loss), repeats)
        print(f"  {mode:8s} {wall:6.2f} s for {n_points} points: {wall / n_points * 1e3:6.1f} ms/point", flush=True)
    rel = np.abs(loss["batched"] - loss["single"]) / np.abs(loss["single"])
    print(f"  largest relative loss difference {rel.max():.2g}")


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sub", type=int, default=2, help="icosphere subdivisions (2: 162 vertices per ball)")
    ap.add_argument("--steps", type=int, default=300)
    ap.add_argument("--points", type=int, default=32)
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    warnings.simplefilter("ignore")
    scene, n = two_balls(sub=args.sub, gap=-0.004, k=200.0)
    print(f"two {n}-vertex balls pressed together, dt {DT:g}, jax {jax.__version__}, {os.cpu_count()} cores")
    print(f"step cost, one {CHUNK}-point chunk ({args.steps} steps):")
    step_costs(scene, args.steps, args.repeats)
    print(f"Evaluator, {args.points} points, {args.steps} steps, frames every 25:")
    evaluator_costs(scene, args.steps, args.points, args.repeats)


if __name__ == "__main__":
    main()
