"""Fitting benchmarks: gradient cost and memory through rollouts (jaxplush.fitting.objective.gradients), and (lead's
section) time to fit and sweep throughput.

Gradient section. The ball-drop plush (springs, gas, gravity, floor; ``--dashpot`` adds the
edge dashpot) of 642 / 2562 vertices (or ``--scene FILE``), float32, a squared-distance loss
against 10 target frames spread over the horizon. ``forward`` is the jitted loss alone
(``rollout_loss(..., method="plain")`` outside any grad); each method's figure is the jitted
``jax.value_and_grad`` of the same loss; ``ratio`` = value_and_grad time / forward time. Methods
``adjoint``, ``checkpoint`` and ``plain`` are ``rollout_loss``'s; ``rollout`` is the same loss
written by hand on the frames of ``jaxplush.rollout(sim, p, s, 10, steps // 10)`` (what a user
writes; its gradient is the fused adjoint by default), ``rollout-autodiff`` that loss with
``gradient="autodiff"`` (JAX's reverse mode through the scan, the default before issue 29), and
``forward (rollout)`` that loss's forward alone. Compile
time is reported apart; times are the minimum of repeats, wall clock and process CPU time (the
CPU ratio is steadier on a shared machine; XLA's CPU backend runs these loops on one thread).

Memory section. A 10,000-step horizon at 2562 vertices: XLA's static buffer analysis of the
compiled value_and_grad (``jaxplush.fitting.objective.gradients.compiled_memory``: temporaries + arguments +
outputs; no run needed), and, for the bounded methods, the measured peak resident memory of a
fresh process that compiles and runs it once (``ru_maxrss``), next to the same process's
peak when it only compiles and runs the forward loss.

Usage: python benchmarks/bench_fit.py [--sizes 3,4] [--steps 1000] [--repeats 3] [--dashpot]
       [--skip-memory] [--memory-steps 10000]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))
sys.path.insert(0, os.path.dirname(__file__))
import jaxplush  # noqa: E402
from bench_step import ball_scene  # noqa: E402
from jaxplush.fitting.objective import gradients  # noqa: E402

METHODS = ("adjoint", "checkpoint", "plain", "rollout", "rollout-autodiff")


def _sq_loss(x, target):
    return jnp.sum((x - target) ** 2)


def _problem(subdivisions, steps, dashpot, dt=1e-4, scene=None):
    scene = ball_scene(subdivisions, dashpot) if scene is None else jaxplush.load_scene(scene)
    sim = jaxplush.make_simulator(scene, dt)
    p = sim.params()
    frames = tuple(int(s) for s in np.linspace(0, steps, 11)[1:])
    target = jnp.broadcast_to(jnp.asarray(sim.topology.x0, sim.dtype) - jnp.asarray([0.0, 0.01, 0.0], sim.dtype),
                              (len(frames), sim.topology.n_vertices, 3))
    return sim, p, frames, target


def _loss_fn(sim, frames, target, method, segment=None):
    if method.startswith("rollout"):
        every = frames[0]
        assert frames == tuple(every * (j + 1) for j in range(len(frames)))
        gradient = "autodiff" if method == "rollout-autodiff" else "auto"

        def g(p):
            _, xs, _ = jaxplush.rollout(sim, p, sim.init_fn(p), len(frames), every, gradient=gradient)
            return jnp.sum((xs - target) ** 2)
        return g

    def f(p):
        return gradients.rollout_loss(sim, p, sim.init_fn(p), frames, _sq_loss, target, method=method,
                                      segment=segment)
    return f


def _time(fn, arg, repeats):
    """(compile s, best wall s, best process CPU s) over ``repeats`` runs after the first."""
    t0 = time.perf_counter()
    jax.block_until_ready(fn(arg))
    compile_s = time.perf_counter() - t0
    wall = cpu = float("inf")
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        jax.block_until_ready(fn(arg))
        wall, cpu = min(wall, time.perf_counter() - t0), min(cpu, time.process_time() - c0)
    return compile_s, wall, cpu


def gradient_ratio(sizes, steps, repeats, dashpot, methods=METHODS, scene=None):
    """Table rows: per mesh size, forward time and each method's value_and_grad time and ratio."""
    rows = []
    for sub in sizes:
        sim, p, frames, target = _problem(sub, steps, dashpot, scene=scene)
        fwd = jax.jit(_loss_fn(sim, frames, target, "plain"))
        c_f, t_f, u_f = _time(fwd, p, repeats)
        rows.append(dict(vertices=sim.topology.n_vertices, method="forward (loss only)", compile_s=c_f, ms=1e3 * t_f,
                         ratio=1.0, cpu_ms=1e3 * u_f, cpu_ratio=1.0))
        if any(m.startswith("rollout") for m in methods):
            c, t, u = _time(jax.jit(_loss_fn(sim, frames, target, "rollout")), p, repeats)
            rows.append(dict(vertices=sim.topology.n_vertices, method="forward (rollout)", compile_s=c, ms=1e3 * t,
                             ratio=t / t_f, cpu_ms=1e3 * u, cpu_ratio=u / u_f))
        for m in methods:
            if m in ("plain", "rollout-autodiff") and sim.topology.n_vertices > 1000 and steps > 1000:
                continue                          # residuals of every step: several GB
            vg = jax.jit(jax.value_and_grad(_loss_fn(sim, frames, target, m)))
            c, t, u = _time(vg, p, repeats)
            rows.append(dict(vertices=sim.topology.n_vertices, method=m, compile_s=c, ms=1e3 * t, ratio=t / t_f,
                             cpu_ms=1e3 * u, cpu_ratio=u / u_f))
            print(f"  {sim.topology.n_vertices} {m}: {1e3 * t:.1f} ms, ratio {t / t_f:.2f} (cpu {u / u_f:.2f})",
                  file=sys.stderr, flush=True)
    return rows


def _memory_child(spec):
    """Run in a fresh process: compile and run once; print peak RSS (MiB) as JSON.

    The peak is /proc/self/status VmHWM (reset by exec), not ru_maxrss, which Linux carries
    over from the parent across exec."""
    sub, steps, method, segment, dashpot, forward_only = spec
    sim, p, frames, target = _problem(sub, steps, dashpot)
    f = _loss_fn(sim, frames, target, method if not forward_only else "plain", segment)
    fn = jax.jit(f) if forward_only else jax.jit(jax.value_and_grad(f))
    out = jax.block_until_ready(fn(p))
    assert np.isfinite(np.asarray(out[0] if not forward_only else out)).all()
    with open("/proc/self/status") as fh:
        hwm_kib = next(int(line.split()[1]) for line in fh if line.startswith("VmHWM:"))
    print(json.dumps(dict(peak_rss_mib=hwm_kib / 1024)))


def _measured_rss(spec):
    cmd = [sys.executable, __file__, "--_child", json.dumps(spec)]
    res = subprocess.run(cmd, capture_output=True, text=True, check=True)
    return json.loads(res.stdout.strip().splitlines()[-1])["peak_rss_mib"]


def memory(steps, dashpot, sub=4):
    """Rows: compiled memory of value_and_grad per method at ``steps`` steps, and measured RSS."""
    sim, p, frames, target = _problem(sub, steps, dashpot)
    state_mib = 2 * 3 * sim.topology.n_vertices * 4 / 2 ** 20
    rows = []
    cases = [("adjoint", None, "stores every step's positions (fits the default 512 MiB budget)"),
             ("rollout", None, "jax.value_and_grad of a loss on jaxplush.rollout: the same fused adjoint"),
             ("adjoint", 100, "checkpoints every 100 steps, recomputes one segment at a time"),
             ("checkpoint", None, "jax.checkpoint: segments of 100 steps, per-step inside"),
             ("plain", None, "autodiff through one scan (static analysis only, not run)")]
    fwd_rss = _measured_rss([sub, steps, "plain", None, dashpot, True])
    for method, seg, note in cases:
        mem = gradients.compiled_memory(jax.value_and_grad(_loss_fn(sim, frames, target, method, seg)), p)
        rss = None if method == "plain" else _measured_rss([sub, steps, method, seg, dashpot, False])
        rows.append(dict(method=method, segment=seg, note=note, compiled_mib=mem["peak"] / 2 ** 20,
                         temp_mib=mem["temp"] / 2 ** 20, rss_mib=rss))
        print(f"  memory {method} seg={seg}: {mem['peak'] / 2 ** 20:.0f} MiB compiled, rss {rss}", file=sys.stderr,
              flush=True)
    return rows, fwd_rss, state_mib, sim.topology.n_vertices


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--sizes", default="3,4", help="icosphere subdivisions (3, 4 = 642, 2562 vertices)")
    ap.add_argument("--steps", type=int, default=1000, help="horizon of the cost-ratio runs")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--dashpot", action="store_true", help="also compile the edge dashpot")
    ap.add_argument("--scene", default=None, help="a scene file instead of the generated ball (one size)")
    ap.add_argument("--methods", default=",".join(METHODS))
    ap.add_argument("--skip-memory", action="store_true")
    ap.add_argument("--memory-steps", type=int, default=10_000)
    ap.add_argument("--skip-fit", action="store_true", help="skip the time-to-fit runs")
    ap.add_argument("--skip-point-cloud", action="store_true", help="skip the point-cloud time-to-fit run")
    ap.add_argument("--skip-sweep", action="store_true", help="skip the sweep throughput run")
    ap.add_argument("--skip-gradients", action="store_true", help="skip the gradient cost table")
    ap.add_argument("--_child", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args._child:
        return _memory_child(json.loads(args._child))

    print(f"# jaxplush {jaxplush.__version__}, jax {jax.__version__}, {jax.devices()[0].device_kind}, "
          f"{os.cpu_count()} cores, {platform.processor() or platform.machine()}; float32; "
          f"{args.scene or 'springs+gas+gravity+floor' + (' +dashpot' if args.dashpot else '')}")
    print(f"\n## Gradient cost: value_and_grad / forward, {args.steps}-step horizon, 10 target frames, "
          f"min of {args.repeats}\n")
    print("| vertices | method | compile (s) | wall (ms) | ratio to forward | CPU (ms) | CPU ratio |")
    print("|---:|---|---:|---:|---:|---:|---:|")
    rows = [] if args.skip_gradients else gradient_ratio(
        [int(s) for s in args.sizes.split(",")][:1 if args.scene else None], args.steps, args.repeats, args.dashpot,
        tuple(args.methods.split(",")), args.scene)
    for r in rows:
        print(f"| {r['vertices']} | {r['method']} | {r['compile_s']:.1f} | {r['ms']:.1f} | {r['ratio']:.2f} | "
              f"{r['cpu_ms']:.1f} | {r['cpu_ratio']:.2f} |", flush=True)

    if not args.skip_memory:
        mrows, fwd_rss, state_mib, n = memory(args.memory_steps, args.dashpot)
        print(f"\n## Memory: value_and_grad over {args.memory_steps:,} steps at {n} vertices\n")
        print(f"One state (x, u) is {state_mib:.3f} MiB. Peak RSS of a process that only compiles and runs "
              f"the forward loss: {fwd_rss:.0f} MiB.\n")
        print("| method | segment | compiled buffers (MiB) | of which temporaries | peak RSS (MiB) | how |")
        print("|---|---:|---:|---:|---:|---|")
        for r in mrows:
            rss = "-" if r["rss_mib"] is None else f"{r['rss_mib']:.0f}"
            seg = "auto" if r["segment"] is None else r["segment"]
            print(f"| {r['method']} | {seg} | {r['compiled_mib']:.0f} | {r['temp_mib']:.0f} | {rss} | {r['note']} |",
                  flush=True)

    if not args.skip_fit:
        from jaxplush.fitting.fitter import synthetic_recovery
        print("\n## Time to fit: synthetic recovery at 642 vertices (k, damping, nmol from x2 / x0.5 starts, "
              "L-BFGS)\n")
        print("| target | k error | damping error | nmol error | iterations | fit wall time (s) |")
        print("|---|---:|---:|---:|---:|---:|")
        for label, noise, cloud in (("positions, noise-free", 0.0, False), ("positions, 1 mm noise", 1e-3, False),
                                    ("point cloud, noise-free", 0.0, True)):
            if cloud and args.skip_point_cloud:
                continue
            r = synthetic_recovery(3, noise=noise, point_cloud=cloud, progress=False)
            e = r["errors"]
            print(f"| {label} | {100 * e['k_structural']:+.4f}% | {100 * e['damping']:+.4f}% | "
                  f"{100 * e['nmol']:+.4f}% | {r['iterations']} | {r['wall_time']:.1f} |", flush=True)

    if not args.skip_sweep:
        import bench_sweep
        print("\n## Sweep throughput (642 vertices, 1000 steps; total simulated steps/s over the batch)\n")
        print("| batch | method | total steps/s | vs unbatched |")
        print("|---:|---|---:|---:|")
        scene = bench_sweep.ball_scene(3) if hasattr(bench_sweep, "ball_scene") else None
        for r in bench_sweep.bench(scene, 2e-4, [64], 1000, args.repeats, vmap=False):
            print(f"| {r['batch']} | {r['method']} | {r['steps_per_s']:,.0f} | {r['speedup']:.2f}x |", flush=True)


if __name__ == "__main__":
    main()
