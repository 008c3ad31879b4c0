"""Forward step throughput: simulated steps/s for icosphere plushies of 642, 2562 and 10242 vertices.

Each measurement is a 1000-step ``jaxplush.rollout`` (one compiled scan), compile time reported
apart, median of repeats. The model is the ball-drop plush: springs, gas, gravity, a floor,
k = 500 N/m, 0.1 kg, radius 0.1 m. ``real-time x`` = steps/s x dt_stable (the largest stable
explicit dt of that mesh): >= 1 means the simulation runs faster than real time at the largest
stable dt.

Usage: python benchmarks/bench_step.py [--sizes 3,4,5] [--repeats 5] [--assembly ring,segment]
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import sys
import time

import trimesh

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))
import jaxplush  # noqa: E402  (before jax: it sets options jax reads when imported)
import jax  # noqa: E402


def ball_scene(subdivisions, dashpot=False):
    m = trimesh.creation.icosphere(subdivisions=subdivisions, radius=0.1)
    lines = ["floor 0", "o ball", "k_structural 500", "total_weight 0.1", "nmol 0.0005"]
    if dashpot:
        lines.append("dashpot 0.005")
    lines += ["translate 0 0.3 0"]
    lines += [f"v {float(a)!r} {float(b)!r} {float(c)!r}" for a, b, c in m.vertices]
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in m.faces]
    return jaxplush.parse_scene("\n".join(lines) + "\n", f"<icosphere {subdivisions}>")


def bench(scene, assembly, steps=1000, repeats=5, dt=None):
    sim0 = jaxplush.make_simulator(scene, 1e-4, assembly=assembly)
    est = jaxplush.estimate_stable_dt(sim0, sim0.params())
    dt = dt or 0.5 * est.dt_max
    sim = jaxplush.make_simulator(scene, dt, assembly=assembly)
    p = sim.params()
    s = sim.init_fn(p)
    t0 = time.perf_counter()
    jax.block_until_ready(jaxplush.rollout(sim, p, s, 1, steps))
    compile_s = time.perf_counter() - t0
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = jaxplush.rollout(sim, p, s, 1, steps)
        jax.block_until_ready(out)
        times.append(time.perf_counter() - t0)
        assert not out[2].failed
    med = statistics.median(times)
    return dict(vertices=scene.n_vertices, assembly=assembly, compile_s=compile_s, steps_per_s=steps / med,
                dt_stable=est.dt_max, realtime=steps / med * est.dt_max)


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--sizes", default="3,4,5", help="icosphere subdivisions (3,4,5 = 642, 2562, 10242 vertices)")
    ap.add_argument("--assembly", default="ring,segment")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--dashpot", action="store_true", help="also compile the edge dashpot")
    args = ap.parse_args(argv)
    print(f"# jaxplush {jaxplush.__version__}, jax {jax.__version__}, {jax.devices()[0].device_kind}, "
          f"{os.cpu_count()} cores, {platform.processor() or platform.machine()}; float32; 1000-step rollouts, "
          f"median of {args.repeats}")
    print("| vertices | assembly | compile (s) | steps/s | dt_stable (s) | real-time x |")
    print("|---:|---|---:|---:|---:|---:|")
    for sub in [int(s) for s in args.sizes.split(",")]:
        scene = ball_scene(sub, args.dashpot)
        for assembly in args.assembly.split(","):
            r = bench(scene, assembly, repeats=args.repeats)
            print(f"| {r['vertices']} | {r['assembly']} | {r['compile_s']:.2f} | {r['steps_per_s']:,.0f} | "
                  f"{r['dt_stable']:.3g} | {r['realtime']:.2f} |", flush=True)


if __name__ == "__main__":
    main()
