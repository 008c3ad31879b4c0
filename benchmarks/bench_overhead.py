"""Per-call overhead: what a ``simulate`` call costs beyond its compiled rollout, the first call's
compile, a second process's start with the persistent compilation cache, and what a user-written
loss reaches under jax.jit, jax.grad and jax.vmap against ``rollout``.

1. Repeated ``jaxplush.simulate(scene, steps=1000, dt=5e-5, save_every=1000)`` calls in one
   process (median of the calls after the first) against the same rollout, compiled, alone.
2. The first ``simulate`` call of a fresh process (import excluded), 642 vertices.
3. Two ``jaxplush simulate`` processes on one scene sharing a fresh ``JAXPLUSH_CACHE_DIR``: the
   wall time of each, and of a bare ``python -c "import jax, jaxplush"`` for reference.
4. Steps per second of a user loss on ``sim.step_fn`` in ``lax.scan``: jitted, its gradient,
   and vmapped over 8 parameter sets, against ``jaxplush.rollout`` of the same steps.

Usage: python benchmarks/bench_overhead.py [--sizes 642,2562,10242] [--repeats 5]
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time

ROOT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..")
sys.path.insert(0, ROOT)

SUBDIVISIONS = {162: 2, 642: 3, 2562: 4, 10242: 5}
STEPS, DT = 1000, 5e-5
#: a smaller step where the finer mesh needs it (its explicit limit is 3.5e-5 s)
DT_AT = {10242: 2e-5}


def _scene_text(n):
    from jaxplush.fitting.targets.scenarios import drop_scene_text
    return drop_scene_text("ball", SUBDIVISIONS[n], dashpot=0.1)


def _timed(fn, repeats):
    out = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        out.append(time.perf_counter() - t)
    return statistics.median(out)


def repeated_calls(n, repeats):
    import jax
    import jaxplush
    scene = jaxplush.parse_scene(_scene_text(n), f"<ball {n}>")
    dt = DT_AT.get(n, DT)
    t = time.perf_counter()
    jaxplush.simulate(scene, STEPS, dt, save_every=STEPS)
    first = time.perf_counter() - t
    call = _timed(lambda: jaxplush.simulate(scene, STEPS, dt, save_every=STEPS), repeats)
    sim = jaxplush.make_simulator(scene, dt)
    p = sim.params()
    s = sim.init_fn(p)
    jax.block_until_ready(sim.rollout(p, s, 1, STEPS))
    roll = _timed(lambda: jax.block_until_ready(sim.rollout(p, s, 1, STEPS)), repeats)
    return first, call, roll


def first_call_process(n):
    code = ("import time, jaxplush, sys; sys.path.insert(0, %r); from benchmarks.bench_overhead import _scene_text; "
            "s = jaxplush.parse_scene(_scene_text(%d), 'x'); t = time.perf_counter(); "
            "jaxplush.simulate(s, %d, %g, save_every=%d); print(time.perf_counter() - t)" % (ROOT, n, STEPS, DT, STEPS))
    env = dict(os.environ, JAXPLUSH_CACHE_DIR="off")
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    return float(out.stdout.strip().splitlines()[-1])


def two_processes(n):
    with tempfile.TemporaryDirectory() as d:
        path = os.path.join(d, "ball.obj")
        with open(path, "w") as fh:
            fh.write(_scene_text(n))
        env = dict(os.environ, JAXPLUSH_CACHE_DIR=os.path.join(d, "xla"))
        walls = []
        for i in range(2):
            t = time.perf_counter()
            subprocess.run([sys.executable, "-m", "jaxplush", "simulate", path, "--steps", "200", "--dt", str(DT),
                            "--out", os.path.join(d, f"o{i}.h5"), "--quiet"], env=env, check=True, capture_output=True)
            walls.append(time.perf_counter() - t)
        t = time.perf_counter()
        subprocess.run([sys.executable, "-c", "import jax, jaxplush, h5py"], check=True)
        bare = time.perf_counter() - t
    return walls[0], walls[1], bare


def composed(n, repeats, steps=400, batch=8):
    import jax
    import jax.numpy as jnp
    import jaxplush
    scene = jaxplush.parse_scene(_scene_text(n), f"<ball {n}>")
    sim = jaxplush.make_simulator(scene, DT)
    p0 = sim.params()

    def height(k):
        p = p0._replace(k_structural=k)
        state, _ = jax.lax.scan(lambda s, _: (sim.step_fn(p, s), None), sim.init_fn(p), None, length=steps)
        return jnp.mean(state.x[:, 1])

    k = p0.k_structural
    ks = k * jnp.linspace(0.5, 2.0, batch)[:, None]
    s0 = sim.init_fn(p0)
    cases = {
        "rollout": (lambda: sim.rollout(p0, s0, 1, steps), steps),
        "jit(loss)": (jax.jit(height), steps),
        "jit(grad(loss))": (jax.jit(jax.grad(height)), steps),
        f"jit(vmap(loss)), {batch} sets": (jax.jit(jax.vmap(height)), steps * batch),
    }
    rows = []
    for name, (fn, work) in cases.items():
        arg = ks if "vmap" in name else k
        call = (lambda fn=fn: fn()) if name == "rollout" else (lambda fn=fn, arg=arg: fn(arg))
        jax.block_until_ready(call())
        t = _timed(lambda: jax.block_until_ready(call()), repeats)
        rows.append((name, work / t))
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="642,2562,10242")
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args(argv)
    sizes = [int(s) for s in args.sizes.split(",")]
    print(f"# {platform.machine()}, {os.cpu_count()} cores, python {platform.python_version()}; "
          f"{time.strftime('%Y-%m-%d %H:%M')}")
    print(f"\n## simulate(scene, steps={STEPS}, dt={DT:g} (2e-5 at 10242), save_every={STEPS}): repeated calls in one process\n")
    print("| vertices | first call s | repeated call ms | compiled rollout ms | overhead ms |")
    print("|---:|---:|---:|---:|---:|")
    for n in sizes:
        first, call, roll = repeated_calls(n, args.repeats)
        print(f"| {n} | {first:.2f} | {1e3 * call:.1f} | {1e3 * roll:.1f} | {1e3 * (call - roll):.1f} |")
    print("\n## the first simulate call of a fresh process (import excluded), 642 vertices\n")
    print(f"first call: {first_call_process(642):.2f} s")
    print("\n## two `jaxplush simulate` processes (200 steps, 642 vertices), one fresh persistent cache\n")
    a, b, bare = two_processes(642)
    print("| process | wall s |\n|---|---:|")
    print(f"| first (empty cache) | {a:.2f} |\n| second (cache filled) | {b:.2f} |\n"
          f"| `python -c 'import jax, jaxplush, h5py'` | {bare:.2f} |")
    print("\n## a user-written loss on sim.step_fn (lax.scan, 400 steps), 642 vertices\n")
    rows = composed(642, args.repeats)
    base = rows[0][1]
    print("| run | steps/s | vs rollout |\n|---|---:|---:|")
    for name, rate in rows:
        print(f"| {name} | {rate:,.0f} | {rate / base:.2f}x |")


if __name__ == "__main__":
    main()
