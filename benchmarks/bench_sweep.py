"""Batch-sweep throughput: total simulated steps/s of B parameter points against one scene alone.

Scene: the ball-drop plush of bench_step.py (springs, gas, gravity, floor; k = 500 N/m, 0.1 kg,
radius 0.1 m), 642 vertices by default, k_structural spread over the batch. For each batch size
B it times a ``steps``-step rollout (one compiled scan, compile time apart, min of repeats) of

* ``unbatched``: ``jaxplush.rollout`` of one scene (the reference, steps/s);
* ``vmap``: ``jax.vmap`` of that rollout over B parameter points (batch on the leading axis);
* ``batched, 1 call``: :func:`jaxplush.stepping.batched.rollout` with the whole batch in one compiled
  call (``chunk=B``; batch on the last axis);
* ``batched``: :func:`jaxplush.stepping.batched.rollout` as ``sweep`` uses it: the batch cut into chunks
  of ``default_chunk(B)`` points (16 at B = 64) that run concurrently, one per core;

and prints total steps/s (B x steps / best time), the speed-up over ``unbatched`` (the median,
over the repeats, of the ratio to an unbatched run timed just before, so that changes in the
load of a shared machine cancel; on a quiet machine it equals the ratio of the best times), and
the process CPU time per simulated step (all threads; the cores used are CPU time / wall time).

Usage: python benchmarks/bench_sweep.py [--subdivisions 3] [--batches 1,8,16,64] [--steps 1000]
       [--repeats 5] [--no-vmap] [--no-one-call] [--dashpot]
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))
sys.path.insert(0, os.path.dirname(__file__))
import jaxplush  # noqa: E402  (before jax: it sets options jax reads when imported)
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
from jaxplush.stepping import batched  # noqa: E402
from bench_step import ball_scene  # noqa: E402


def _compile(fn):
    t0 = time.perf_counter()
    jax.block_until_ready(fn())
    return time.perf_counter() - t0


def _once(fn, cpu=False):
    c0, t0 = time.process_time(), time.perf_counter()
    jax.block_until_ready(fn())
    t, c = time.perf_counter() - t0, time.process_time() - c0
    return (t, c) if cpu else t


def _paired(fn, ref, repeats):
    """Best time of ``fn``, the median ratio ref_time / fn_time over interleaved repeats (each
    ``fn`` run right after a run of the reference, so slow drifts in machine load cancel) and the
    CPU time of the best run."""
    best, cpu, ratios = np.inf, np.nan, []
    for _ in range(repeats):
        r = _once(ref)
        t, c = _once(fn, cpu=True)
        if t < best:
            best, cpu = t, c
        ratios.append(r / t)
    return best, float(np.median(ratios)), cpu


def bench(scene, dt, batches, steps, repeats, vmap=True, one_call=True):
    sim = jaxplush.make_simulator(scene, dt)
    p = sim.params()
    s = sim.init_fn(p)
    ref = lambda: jaxplush.rollout(sim, p, s, 1, steps)  # noqa: E731
    c1 = _compile(ref)
    t1, cpu1 = min(_once(ref, cpu=True) for _ in range(repeats))
    rows = [dict(batch=1, method="unbatched", compile_s=c1, steps_per_s=steps / t1, speedup=1.0,
                 cpu_us=cpu1 / steps * 1e6)]
    for b in batches:
        ks = np.linspace(0.8, 1.2, b) * float(p.k_structural[0])
        fns = []
        if vmap:
            pb = jax.tree_util.tree_map(lambda a: jnp.broadcast_to(a, (b,) + a.shape), p)
            pb = pb._replace(k_structural=jnp.asarray(ks, sim.dtype)[:, None])
            run = jax.jit(jax.vmap(lambda q: jaxplush.rollout(sim, q, sim.init_fn(q), 1, steps)[0].x))
            fns.append(("vmap", lambda run=run, pb=pb: run(pb)))
        for name, chunk in (("batched, 1 call", b), ("batched", None)):
            if name != "batched" and (not one_call or batched.default_chunk(b) == b):
                continue
            bsim = batched.make_batched_simulator(scene, dt, b, chunk=chunk)
            bp = bsim.params()._replace(k_structural=jnp.asarray(ks[None, :], bsim.dtype))
            bs = bsim.init_fn(bp)
            fns.append((name if chunk else f"batched ({-(-b // bsim.chunk)} x {bsim.chunk})",
                        lambda bsim=bsim, bp=bp, bs=bs: batched.rollout(bsim, bp, bs, 1, steps)))
        for name, fn in fns:
            c = _compile(fn)
            if name.startswith("batched"):
                assert not fn()[2].failed.any()
            t, ratio, cpu = _paired(fn, ref, repeats)
            rows.append(dict(batch=b, method=name, compile_s=c, steps_per_s=b * steps / t, speedup=b * ratio,
                             cpu_us=cpu / (b * steps) * 1e6))
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--subdivisions", type=int, default=3, help="icosphere subdivisions (3: 642 vertices)")
    ap.add_argument("--batches", default="1,8,16,64")
    ap.add_argument("--steps", type=int, default=1000)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--dt", type=float, default=2e-4)
    ap.add_argument("--no-vmap", action="store_true", help="skip the jax.vmap comparison")
    ap.add_argument("--dashpot", action="store_true", help="also compile the edge dashpot")
    ap.add_argument("--no-one-call", action="store_true", help="skip the one-call batched comparison")
    args = ap.parse_args(argv)
    scene = ball_scene(args.subdivisions, args.dashpot)
    print(f"# jaxplush {jaxplush.__version__}, jax {jax.__version__}, {jax.devices()[0].device_kind}, "
          f"{os.cpu_count()} cores, {platform.processor() or platform.machine()}; "
          f"{jnp.result_type(float).__name__ if hasattr(jnp.result_type(float), '__name__') else 'float32'}; "
          f"{scene.n_vertices} vertices, {args.steps}-step rollouts, min of {args.repeats}, "
          f"XLA_FLAGS={os.environ.get('XLA_FLAGS', '')!r}")
    print("| batch | method | compile (s) | total steps/s (best) | vs unbatched (paired median) | "
          "CPU us per step | cores used |")
    print("|---:|---|---:|---:|---:|---:|---:|")
    for r in bench(scene, args.dt, [int(b) for b in args.batches.split(",")], args.steps, args.repeats,
                   vmap=not args.no_vmap, one_call=not args.no_one_call):
        print(f"| {r['batch']} | {r['method']} | {r['compile_s']:.2f} | {r['steps_per_s']:,.0f} | "
              f"{r['speedup']:.2f}x | {r['cpu_us']:.2f} | {r['cpu_us'] * r['steps_per_s'] / 1e6:.2f} |", flush=True)


if __name__ == "__main__":
    main()
