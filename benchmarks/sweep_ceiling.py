"""How far batching can go on XLA:CPU: a diagnosis of the batched sweep step (issue 3's 5x target).

Scene and settings as benchmarks/bench_sweep.py (the 642-vertex ball: springs, gas, gravity,
floor; dt 2e-4; 1000-step rollouts; best of repeats). It measures

1. ``unbatched``: ``jaxplush.rollout`` of one scene, the reference of the 5x target;
2. ``one chunk, one core``: one 16-point chunk (:func:`jaxplush.stepping.batched.rollout`) in a child
   process confined to a single core before JAX starts. XLA then compiles with a parallelism of
   one (no kernel split into parallel partitions) and runs every kernel of the step on that core:
   the cost of the batched kernels themselves, with no thread in their way;
3. ``one chunk, all cores``: the same chunk alone in this process. XLA:CPU splits the larger loop
   kernels into two partitions (``outer_dimension_partitions`` in the optimised HLO) and runs
   independent kernels on its worker threads, so consecutive kernels of one step land on
   different cores, and each hop moves the chunk's working set (about 1.5 MB) between the cores'
   private L2 caches;
4. ``64 points, as sweep runs them``: four 16-point chunks, one in flight per core.

and prints, per row, steps/s (total over the batch), CPU us per point-step, the cores used and the
number of split kernels in the compiled chunk. The last line is the ceiling: the batch-64
throughput if every core ran chunks at row 2's cost with perfect scaling, as a multiple of the
unbatched steps/s. Row 2 is itself bound by memory traffic: XLA:CPU materialises every
intermediate of the step (the gathered one-ring rows, inverse lengths, dV/dx, ...) and streams
about 7 MB through L2 per chunk step.

Usage: python benchmarks/sweep_ceiling.py [--steps 1000] [--repeats 5]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time

# Keep this import-light: the child process confines itself to one core before JAX is imported.
HERE = os.path.dirname(os.path.abspath(__file__))


def _measure(fn, repeats):
    import jax
    jax.block_until_ready(fn())
    best = (float("inf"), float("nan"))
    for _ in range(repeats):
        c0, t0 = time.process_time(), time.perf_counter()
        jax.block_until_ready(fn())
        t, c = time.perf_counter() - t0, time.process_time() - c0
        best = min(best, (t, c))
    return best


def _split_kernels(bsim, params, state):
    """Kernels of the compiled chunk rollout that XLA:CPU splits into parallel partitions."""
    import jax.numpy as jnp
    from jaxplush.stepping import batched
    health = batched.initial_health(bsim, state, 0)
    compiled = batched._core_jit.lower(bsim, params, state, health, jnp.zeros((bsim.batch,), jnp.int32), None,
                                       n_frames=1, save_every=10, observe=None).compile()
    return compiled.as_text().count("outer_dimension_partitions")


def _chunk(batch, steps, repeats, dt):
    import jax.numpy as jnp
    import numpy as np
    sys.path.insert(0, os.path.join(HERE, ".."))
    sys.path.insert(0, HERE)
    from bench_step import ball_scene
    from jaxplush.stepping import batched
    scene = ball_scene(3)
    bsim = batched.make_batched_simulator(scene, dt, batch)
    ks = np.linspace(0.8, 1.2, batch) * float(scene.params.k_structural[0])
    params = bsim.params()._replace(k_structural=jnp.asarray(ks[None, :], bsim.dtype))
    state = bsim.init_fn(params)
    wall, cpu = _measure(lambda: batched.rollout(bsim, params, state, 1, steps), repeats)
    return dict(steps_per_s=batch * steps / wall, cpu_us=cpu / (batch * steps) * 1e6, cores=cpu / wall,
                split=_split_kernels(bsim, params, state) if bsim.chunk == batch else None)


def _child(args):
    print(json.dumps(_chunk(16, args.steps, args.repeats, args.dt)))


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--steps", type=int, default=1000)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--dt", type=float, default=2e-4)
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        return _child(args)
    cpus = sorted(os.sched_getaffinity(0))
    out = subprocess.run([sys.executable, os.path.abspath(__file__), "--child", "--steps", str(args.steps),
                          "--repeats", str(args.repeats), "--dt", str(args.dt)],
                         preexec_fn=lambda: os.sched_setaffinity(0, {cpus[0]}), capture_output=True, text=True)
    if out.returncode:
        sys.exit(f"the one-core child failed:\n{out.stderr}")
    pinned = json.loads(out.stdout.strip().splitlines()[-1])

    import jax
    import jaxplush
    sys.path.insert(0, HERE)
    from bench_step import ball_scene
    sim = jaxplush.make_simulator(ball_scene(3), args.dt)
    p = sim.params()
    s = sim.init_fn(p)
    wall, cpu = _measure(lambda: jaxplush.rollout(sim, p, s, 1, args.steps), args.repeats)
    ref = dict(steps_per_s=args.steps / wall, cpu_us=cpu / args.steps * 1e6, cores=cpu / wall, split=None)
    alone = _chunk(16, args.steps, args.repeats, args.dt)
    sweep = _chunk(64, args.steps, args.repeats, args.dt)

    print(f"# jaxplush {jaxplush.__version__}, jax {jax.__version__}, {len(cpus)} cores, "
          f"{platform.processor() or platform.machine()}; 642 vertices, {args.steps}-step rollouts, best of "
          f"{args.repeats}, XLA_FLAGS={os.environ.get('XLA_FLAGS', '')!r}")
    print("| run | total steps/s | vs unbatched | CPU us per point-step | cores used | split kernels |")
    print("|---|---:|---:|---:|---:|---:|")
    for name, r in (("unbatched (reference)", ref), ("one 16-point chunk, one core", pinned),
                    ("one 16-point chunk, all cores", alone), ("64 points as sweep runs them (4 x 16)", sweep)):
        split = "" if r["split"] is None else r["split"]
        print(f"| {name} | {r['steps_per_s']:,.0f} | {r['steps_per_s'] / ref['steps_per_s']:.2f}x | "
              f"{r['cpu_us']:.2f} | {r['cores']:.2f} | {split} |")
    ceiling = len(cpus) * ref["cpu_us"] / pinned["cpu_us"]
    print(f"\nCeiling with perfect scaling over {len(cpus)} cores at the one-core chunk cost: "
          f"{ceiling:.2f}x the unbatched steps/s (reached: {sweep['steps_per_s'] / ref['steps_per_s']:.2f}x).")


if __name__ == "__main__":
    main()
