"""Driven vertices in the batched engine: what a driven vertex costs a batched rollout.

The ball-drop plush of ``jaxplush.fitting.targets.scenarios.drop_scene_text`` (springs, gas, floor; 642
vertices at ``--sub 3``), and the same plush with its top vertex driven up 15 cm over 0.3 s and
released at 0.5 s. Each runs as one batched chunk of ``--batch`` points and as one scene
(``jaxplush.rollout``, jitted), ``--steps`` steps of 2.5e-4 s saved every 100. Throughput is
point-steps (steps for one scene) per second of wall time and of process CPU time, each the
best of ``--repeats`` after compiling.

Usage: python benchmarks/bench_driven.py [--sub 3] [--batch 16] [--steps 1000] [--repeats 3]
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time

import jax
import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))
import jaxplush  # noqa: E402
from jaxplush.stepping import batched  # noqa: E402
from jaxplush.fitting.targets.scenarios import drop_scene_text  # noqa: E402

DT = 2.5e-4


def scenes(sub, tmp):
    """(plain scene, the same with its top vertex driven up and released)."""
    text = drop_scene_text("ball", sub)
    plain = jaxplush.parse_scene(text, "<ball>")
    top = int(np.argmax(plain.vertices[:, 1]))
    x, y, z = (float(a) for a in plain.vertices[top])
    with open(os.path.join(tmp, "lift.csv"), "w") as fh:
        fh.write(f"t,x,y,z\n0,{x!r},{y!r},{z!r}\n0.3,{x!r},{y + 0.15!r},{z!r}\n")
    driven = jaxplush.parse_scene(text.replace("END_OBJECT", f"driven lift.csv {top + 1} until 0.5\nEND_OBJECT"),
                                  os.path.join(tmp, "driven.obj"))
    return plain, driven


def best(fn, repeats):
    """(best wall seconds, best process CPU seconds) of ``repeats`` calls after a first one."""
    jax.block_until_ready(fn())
    wall = cpu = np.inf
    for _ in range(repeats):
        t, c = time.perf_counter(), time.process_time()
        jax.block_until_ready(fn())
        wall, cpu = min(wall, time.perf_counter() - t), min(cpu, time.process_time() - c)
    return wall, cpu


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sub", type=int, default=3, help="icosphere subdivisions (3: 642 vertices)")
    ap.add_argument("--batch", type=int, default=16)
    ap.add_argument("--steps", type=int, default=1000)
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args(argv)
    every = 100
    frames = max(1, args.steps // every)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for name, scene in zip(("plain", "driven"), scenes(args.sub, tmp)):
            bsim = batched.make_batched_simulator(scene, DT, args.batch)
            p = bsim.params()
            s0 = bsim.init_fn(p)
            wall, cpu = best(lambda: batched.rollout(bsim, p, s0, frames, every), args.repeats)
            rows.append((name, f"batched, {args.batch} points", args.batch * frames * every, wall, cpu))
            sim = jaxplush.make_simulator(scene, DT)
            q = sim.params()
            s1 = sim.init_fn(q)
            run = jax.jit(lambda q, s: jaxplush.rollout(sim, q, s, frames, every)[1])
            wall, cpu = best(lambda: run(q, s1), args.repeats)
            rows.append((name, "one scene", frames * every, wall, cpu))
        n_v = scene.n_vertices
    print(f"# {n_v} vertices, {frames * every} steps of {DT} s; jax {jax.__version__}, {os.cpu_count()} cores")
    print("| scene | engine | point-steps/s (wall) | per CPU second |")
    print("|---|---|---:|---:|")
    for name, engine, n, wall, cpu in rows:
        print(f"| {name} | {engine} | {n / wall:,.0f} | {n / cpu:,.0f} |")


if __name__ == "__main__":
    main()
