"""Soft-soft contact with objects that hang close together and flutter: the cost of the carried
candidate lists in the batched engine.

The scene is the random generator's seed 13 case 5 at its truth (a 642-vertex capsule and two
642-vertex cushions hanging side by side, 1926 vertices, 2-7 cm apart, dt 1.25e-4): the default
fit's hardest kind of scene for time. Its cushions ring at about 1 kHz, so vertices move up to 4 mm
per step near the other object, and the candidate lists are rebuilt every few steps.

1. Rebuilds of the candidate lists over the first ``--steps`` steps of one run (the cache's own
   ``stale`` test replayed on the saved steps).
2. Step cost of one ``--batch``-point chunk of the batched engine (``jaxplush.stepping.batched.rollout``) at
   each contact capacity in ``--caps`` (the fit grows the capacity from the scene's 256 to 512 at
   its start and to 642 after an overflow), and without contact, best of ``--repeats`` after a
   compiling call, in microseconds per point-step.

Usage: python benchmarks/bench_contact_cache.py [--steps 1040] [--batch 8] [--caps 256,512,642] [--repeats 2]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
import warnings

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))
import jaxplush  # noqa: E402
from jaxplush.stepping import batched  # noqa: E402
from jaxplush.fitting.targets.scenarios import case_scene_text, draw_case  # noqa: E402
from jaxplush.model import contact  # noqa: E402

DT = 1.25e-4


def scene_text(capacity=256, contact_on=True):
    """The scene at its truth with ``contact_capacity`` (the benchmark's generator writes 256: the
    candidates need about 230)."""
    case = draw_case(np.random.default_rng([13, 5]))
    text = case_scene_text(dict(case, contact_capacity=capacity))
    assert f"contact_capacity {capacity}" in text
    if not contact_on:
        text = text.replace("contact on", "contact off")
    return text


def rebuilds(scene, steps):
    """(rebuilds, steps, mean queries) of the carried lists over ``steps`` steps of one run."""
    sim = jaxplush.make_simulator(scene, DT)
    p = sim.params()
    frames = np.asarray(sim.rollout(p, sim.init_fn(p), steps, 1)[1])
    _, ops = contact.make_contact(sim.topology, sim.terms.contact, DT)
    xs = jnp.asarray(frames.transpose(0, 2, 1), jnp.float32)

    def body(c, x):
        return ops.update(c, x), (ops.stale(c, x), jnp.sum(c.valid))
    _, (stale, n) = jax.jit(lambda x: jax.lax.scan(body, ops.init(x[0]), x[1:]))(xs)
    return int(np.sum(stale)), steps - 1, float(np.mean(n))


def step_cost(scene, batch, repeats, steps=320):
    bs = batched.make_batched_simulator(scene, DT, batch, chunk=batch)
    p = bs.params()
    s = jax.jit(bs.init_fn)(p)
    jax.block_until_ready(batched.rollout(bs, p, s, 2, steps // 2))
    best = np.inf
    for _ in range(repeats):
        t = time.perf_counter()
        jax.block_until_ready(batched.rollout(bs, p, s, 2, steps // 2))
        best = min(best, time.perf_counter() - t)
    return 1e6 * best / (batch * steps)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=1040)
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--caps", default="256,512,642")
    ap.add_argument("--repeats", type=int, default=2)
    a = ap.parse_args(argv)
    warnings.simplefilter("ignore")
    n_re, n_steps, queries = rebuilds(jaxplush.parse_scene(scene_text(), "<seed 13 case 5>"), a.steps)
    print(f"candidate lists rebuilt {n_re} times in {n_steps} steps (one every {n_steps / max(n_re, 1):.1f}); "
          f"{queries:.0f} queries on average")
    print("| batched chunk of %d points, 320 steps | us per point-step |" % a.batch)
    print("|---|---:|")
    for cap in [int(c) for c in a.caps.split(",")]:
        us = step_cost(jaxplush.parse_scene(scene_text(cap), "<seed 13 case 5>"), a.batch, a.repeats)
        print(f"| contact, capacity {cap} | {us:.0f} |", flush=True)
    us = step_cost(jaxplush.parse_scene(scene_text(contact_on=False), "<seed 13 case 5>"), a.batch, a.repeats)
    print(f"| no contact | {us:.0f} |")


if __name__ == "__main__":
    main()
