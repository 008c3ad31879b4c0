"""Where the fused adjoint's time goes: the forward, the forward that records states, the backward
alone and value-and-gradient, each against the forward (issue 29 item 3).

The problem is bench_fit.py's: the ball-drop plush (springs, gas, gravity, floor, and the edge
dashpot unless ``--no-dashpot``) of 642 / 2562 vertices, or ``--scene FILE``, float32, a
squared-distance loss against 10 frames over ``--steps`` steps. Each jitted function is timed on
its own, best of ``--repeats`` after compiling:

* forward: the loss alone (the adjoint's forward pass without recording);
* forward + recording: the same pass keeping every state the backward pass reads;
* backward: the reverse sweep alone, from the recorded states;
* value-and-gradient: ``jax.value_and_grad`` of ``rollout_loss(..., method="adjoint")``.

``--reduction-demo`` times, in two fresh processes, one ring reduction of the form the kernels
use: a stacked gather of 6 components over the one-ring (2562 vertices), a softened inverse
length, and 3 ring sums, as a ``lax.reduce`` over the ring axis. XLA:CPU emits such a reduction
as a loop over vertices around an inner loop over the K ring slots; LLVM vectorises the vertex
loop only where it unrolls the inner loop completely, which its unroll threshold allows only for
a short per-slot body. The second process raises that threshold
(``XLA_FLAGS=--xla_backend_extra_options=-unroll-threshold=5000``); the difference between the
two is what a vectorised reduction would be worth. (jaxplush does not set that flag: it is
process-wide and slowed the adjoint's own backward pass; benchmarks/RESULTS.md.)

Usage: python benchmarks/bench_adjoint_split.py [--sizes 3,4] [--scene FILE ...] [--steps 1000]
       [--repeats 7] [--no-dashpot] [--reduction-demo]
"""

from __future__ import annotations

import argparse
import os
import platform
import subprocess
import sys

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))
sys.path.insert(0, os.path.dirname(__file__))
import jaxplush  # noqa: E402,F401  (sets jaxplush's XLA flags before jax starts)
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402

UNROLL_FLAG = "--xla_backend_extra_options=-unroll-threshold=5000"


def _best(fn, arg, repeats):
    """Best wall time of ``fn(arg)`` in ms over ``repeats`` runs after compiling (bench_fit's timer)."""
    from bench_fit import _time
    return 1e3 * _time(fn, arg, repeats)[1]


def split(sim, p, frames, target, repeats):
    """(forward, forward + recording, backward, value-and-gradient) wall times in ms."""
    from bench_fit import _sq_loss
    from jaxplush.fitting.objective import gradients as G
    from jaxplush.stepping import adjoint as A

    x0, u0 = sim.internal.to_internal(sim.init_fn(p))
    itemsize = np.dtype(x0.dtype).itemsize
    plan = A._plan(sim, frames[-1], None, A.DEFAULT_MEMORY_BUDGET, itemsize)
    table = np.full(frames[-1] + 1, -1)
    table[list(frames)] = np.arange(len(frames))
    example = jax.ShapeDtypeStruct((sim.topology.n_vertices, 3), x0.dtype)
    loss, consts = jax.closure_convert(_sq_loss, example, target[0])
    consts = tuple(consts)
    fwd = G._adjoint_forward(sim, plan, frames, loss, None)
    bwd = G._adjoint_backward(sim, plan, table)
    f_plain = jax.jit(lambda q: fwd(q, x0, u0, target, consts, grads=False)[0])
    f_rec = jax.jit(lambda q: fwd(q, x0, u0, target, consts, grads=True))
    value, s_end, bufs, (gx, ga), gc = f_rec(p)
    res = (p, s_end, bufs, gx, ga, gc, target, consts)
    f_bwd = jax.jit(lambda r: bwd(r, jnp.ones((), x0.dtype)))
    f_vg = jax.jit(jax.value_and_grad(
        lambda q: G.rollout_loss(sim, q, sim.init_fn(q), frames, _sq_loss, target, method="adjoint")))
    return tuple(_best(f, a, repeats) for f, a in
                 ((f_plain, p), (f_rec, p), (f_bwd, res), (f_vg, p)))


def reduction_kernel(repeats, long_body=True):
    """The demo's kernel (run in a child process): microseconds per step of 100 steps. The long
    per-slot body has two more products than the short one (t dl and t / l)."""
    import trimesh
    from jaxplush.model import mesh as M
    from jaxplush.model import terms as T
    from jaxplush.model.layout import sum_rows

    ico = trimesh.creation.icosphere(subdivisions=4)
    n = len(ico.vertices)
    nbr, _, _ = M.ring_tables(np.asarray(ico.faces, np.int32), n)
    ring = np.ascontiguousarray(nbr.T)
    k = ring.shape[0]
    table = np.concatenate([ring, ring[:1]], 0)
    rng = np.random.default_rng(0)
    x = jnp.asarray(np.asarray(ico.vertices, np.float32).T)
    lam = jnp.asarray(rng.normal(size=(3, n)).astype(np.float32))

    def body(_, carry):
        x, lam = carry
        tab = jnp.concatenate([x, lam]).at[:, table].get(mode="promise_in_bounds")    # (6, K+1, V)
        d = [tab[c, :k] - x[c] for c in range(3)]
        dl = [tab[3 + c, :k] - lam[c] for c in range(3)]
        inv_l = T.inv_length(d, 1e-12)
        t = T.dot(d, dl)
        if long_body:
            w, coef = 1.0 - inv_l, inv_l * inv_l * inv_l * t + t * inv_l
            ring_sums = sum_rows([w * dl[i] + coef * d[i] + t * dl[i] for i in range(3)])
        else:
            w, coef = 1.0 - inv_l, inv_l * inv_l * inv_l * t
            ring_sums = sum_rows([w * dl[i] + coef * d[i] for i in range(3)])
        fan = sum_rows(T.cross(d, [tab[c, 1:] - x[c] for c in range(3)]))   # a second reader of the table
        return x, lam + 1e-3 * (jnp.stack(ring_sums) + jnp.stack(fan))

    f = jax.jit(lambda xl: jax.lax.fori_loop(0, 100, body, xl)[1])
    return _best(f, (x, lam), repeats) * 10.0              # ms per 100 steps -> us per step


def reduction_demo(repeats):
    rows = []
    for body, label, extra in (("short", "default", ""), ("long", "default", ""),
                               ("long", "unroll threshold 5000", UNROLL_FLAG)):
        env = dict(os.environ)
        env["XLA_FLAGS"] = " ".join(f for f in (env.get("XLA_FLAGS", ""), extra) if f)
        env.pop("JAXPLUSH_CACHE_DIR", None)               # a cache would serve the other variant's code
        out = subprocess.run([sys.executable, __file__, "--_kernel", body, "--repeats", str(repeats)], env=env,
                             capture_output=True, text=True, check=True).stdout.strip().splitlines()[-1]
        rows.append((body, label, float(out)))
    print("\nOne ring reduction (2562 vertices, 6-component gather, 3 ring sums), us per step:\n")
    print("| per-slot body | LLVM | us/step |")
    print("|---|---|---:|")
    for body, label, us in rows:
        print(f"| {body} | {label} | {us:.1f} |")


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="3,4", help="icosphere subdivisions of the bench ball (3: 642, 4: 2562)")
    ap.add_argument("--scene", action="append", default=[], help="a scene file instead of the bench ball")
    ap.add_argument("--steps", type=int, default=1000)
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--no-dashpot", action="store_true")
    ap.add_argument("--reduction-demo", action="store_true")
    ap.add_argument("--_kernel", choices=("short", "long"), help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args._kernel:
        print(f"{reduction_kernel(args.repeats, args._kernel == 'long'):.3f}")
        return
    from bench_fit import _problem

    print(f"# {platform.processor() or platform.machine()}, {os.cpu_count()} cores, jax {jax.__version__}, "
          f"{args.steps} steps, best of {args.repeats}\n")
    print("| problem | vertices | forward (ms) | forward + recording | backward | value-and-gradient |")
    print("|---|---:|---:|---:|---:|---:|")
    cases = [(f"bench ball{'' if args.no_dashpot else ' + dashpot'}", int(s), None)
             for s in args.sizes.split(",") if s] + [(path, None, path) for path in args.scene]
    for label, sub, path in cases:
        sim, p, frames, target = _problem(sub or 3, args.steps, not args.no_dashpot, scene=path)
        f, r, b, vg = split(sim, p, frames, target, args.repeats)
        print(f"| {label} | {sim.topology.n_vertices} | {f:.1f} | {r / f:.2f}x | {b / f:.2f}x | {vg / f:.2f}x |",
              flush=True)
    if args.reduction_demo:
        reduction_demo(args.repeats)


if __name__ == "__main__":
    main()
