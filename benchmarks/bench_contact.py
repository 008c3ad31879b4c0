"""Soft-soft contact cost: two plushies pressed together, with and without contact compiled in.

Two icosphere plushies (k = 500 N/m, 0.1 kg, radius 0.1 m, gas, no gravity) pressed together,
timed from two starts: "inflating" (touching at rest size, they inflate into each other: the
surfaces move at up to ~4 m/s, so the candidate lists are rebuilt every few steps) and
"resting" (first settled for ``--settle`` s with strong air drag, then timed from rest: a
resting contact). The same scene is timed with contact (the default for several objects; the
rollout carries the candidate lists between steps), with ``terms.contact = None``, and with
``coherent_contact=False`` (a full search every step). Throughput is the median of repeated
``jaxplush.rollout`` runs of ``--steps`` steps (one compiled scan); compile time reported apart.
Target (issue 5): contact at no less than half the steps/s.

Usage: python benchmarks/bench_contact.py [--sizes 2,3,4] [--steps 500] [--repeats 3]
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import platform
import statistics
import sys
import time

import numpy as np
import trimesh

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))
import jaxplush  # noqa: E402  (before jax: it sets options jax reads when imported)
import jax  # noqa: E402
from jaxplush.model import contact  # noqa: E402


def pair_scene(subdivisions, gap=0.0, drag=0.0):
    m = trimesh.creation.icosphere(subdivisions=subdivisions, radius=0.1)
    lines = ["gravity 0 0 0"]
    for i, (name, x) in enumerate((("a", -0.1 - gap / 2), ("b", 0.1 + gap / 2))):
        off = i * len(m.vertices)
        lines += [f"o {name}", "k_structural 500", "total_weight 0.1", "nmol 0.0005", f"translate {x!r} 0 0"]
        lines += [f"drag {drag!r}"] if drag else []
        lines += [f"v {float(a)!r} {float(b)!r} {float(c)!r}" for a, b, c in m.vertices]
        lines += [f"f {a + 1 + off} {b + 1 + off} {c + 1 + off}" for a, b, c in m.faces]
        lines.append("END_OBJECT")
    return jaxplush.parse_scene("\n".join(lines) + "\n", f"<pair {subdivisions}>")


def settled(sim, subdivisions, seconds):
    """Positions after ``seconds`` of the pair with strong air drag (its inflation transient damped
    out): the start of the resting-contact timing."""
    damped = jaxplush.make_simulator(pair_scene(subdivisions, drag=200.0), sim.dt, terms=dataclasses.replace(
        sim.terms, drag=True))
    n = int(round(seconds / sim.dt))
    damped = grown(damped, n)
    p = damped.params()
    state, _, health = jaxplush.rollout(damped, p, damped.init_fn(p), 1, n)
    assert not health.failed, "settling run failed"
    return np.asarray(state.x)


def bench(sim, steps, repeats, x0=None):
    p = sim.params()
    s = sim.init_fn(p, x0)
    t0 = time.perf_counter()
    out = jaxplush.rollout(sim, p, s, 1, steps)
    jax.block_until_ready(out)
    compile_s = time.perf_counter() - t0
    assert not out[2].failed, "run failed"
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(jaxplush.rollout(sim, p, s, 1, steps))
        times.append(time.perf_counter() - t0)
    return compile_s, steps / statistics.median(times), out[0]


def grown(sim, steps, x0=None):
    """The simulator with its contact capacity raised as jaxplush.simulate would (1.25x the need,
    rounded up to 32) until the run does not overflow."""
    for _ in range(4):
        p = sim.params()
        state, _, health = jaxplush.rollout(sim, p, sim.init_fn(p, x0), 1, steps)
        if not health.failed:
            return sim
        need = contact.needed_capacity(sim, np.asarray(health.good_state.x))
        if np.isfinite(np.asarray(state.x)).all():
            need = max(need, contact.needed_capacity(sim, np.asarray(state.x)))
        cap = contact.grown_capacity(need)
        sim = jaxplush.make_simulator(sim.scene, sim.dt, terms=contact.with_capacity(sim.terms, cap))
    return sim


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="2,3,4", help="icosphere subdivisions (2: 162, 3: 642, 4: 2562 vertices)")
    ap.add_argument("--steps", type=int, default=500)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--dt", type=float, default=1e-4)
    ap.add_argument("--settle", type=float, default=0.05, help="seconds of damped settling before the resting case")
    args = ap.parse_args(argv)
    print(f"# jax {jax.__version__}, {jax.devices()[0].device_kind}, {platform.machine()}, "
          f"{os.cpu_count()} cores; {args.steps}-step rollouts, median of {args.repeats}")
    print("| vertices per plush | start | capacity | candidates at end | compile with / without (s) "
          "| steps/s without contact | steps/s with contact | ratio | searching every step: steps/s (ratio) |")
    print("|---:|---|---:|---:|---:|---:|---:|---:|---:|")
    for sub in (int(s) for s in args.sizes.split(",")):
        scene = pair_scene(sub)
        base = jaxplush.make_simulator(scene, args.dt)
        for start in ("inflating", "resting"):
            x0 = settled(base, sub, args.settle) if start == "resting" else None
            sim = grown(base, args.steps, x0)
            bare = jaxplush.make_simulator(scene, args.dt, terms=dataclasses.replace(sim.terms, contact=None))
            search = jaxplush.make_simulator(scene, args.dt, terms=sim.terms, coherent_contact=False)
            c0, r0, _ = bench(bare, args.steps, args.repeats, x0)
            c1, r1, final = bench(sim, args.steps, args.repeats, x0)
            _, r2, _ = bench(search, args.steps, args.repeats, x0)
            counts = contact.candidate_counts(sim, np.asarray(final.x))[0]
            print(f"| {scene.objects[0].n_vertices} | {start} | {sim.terms.contact.capacity[0]} | {counts[1]}, {counts[2]} "
                  f"| {c1:.1f} / {c0:.1f} | {r0:,.0f} | {r1:,.0f} | {r1 / r0:.2f} | {r2:,.0f} ({r2 / r0:.2f}) |",
                  flush=True)


if __name__ == "__main__":
    main()
