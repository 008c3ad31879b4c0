"""The three hot paths side by side for two checkouts: forward step, batched sweep, gradient.

A refactor of the force model must not slow the code that runs it. This script times, for each
of two source trees (say the commit before a change and the working tree after it):

* ``step``: ``jaxplush.rollout`` of one scene, simulated steps/s (1000 steps, one compiled scan);
* ``sweep``: ``jaxplush.stepping.batched.rollout`` of B parameter points (chunks of 16, run
  concurrently, as ``sweep`` does), total point-steps/s;
* ``gradient``: the jitted ``jax.value_and_grad`` of a 500-step squared-distance loss with the
  fused adjoint (``rollout_loss(..., method="adjoint")``), gradients/s;

on the ball-drop plush of bench_step.py (642 vertices by default: springs, gas, gravity, a
floor; dt = 2e-4 s, halved per further subdivision) and on
the same ball with every term that the three paths share switched on (edge dashpot, air drag,
the report's Verlet damping). ``--cases step:contact,sweep:contact`` times the first two on
scenes/plush_pile.obj instead (soft-soft contact between three plushies). Each measurement runs in a fresh process that imports jaxplush
from the tree it is given; the trees alternate (A B A B ...) so that slow changes in machine
load hit both, and the table reports the best of the rounds and the ratio after / before.

Usage:
  python benchmarks/bench_hotpaths.py --before REV [--after PATH|REV] [--rounds 3] [--subdivisions 3]
  python benchmarks/bench_hotpaths.py --root PATH --case step:plain   (one measurement, JSON)

``--before``/``--after`` take a git revision (checked out into a temporary worktree) or a path
to a source tree; ``--after`` defaults to this checkout.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import statistics
import subprocess
import sys
import tempfile
import time

HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.dirname(HERE)
CASES = ("step:plain", "step:full", "sweep:plain", "sweep:full", "gradient:plain", "gradient:full")
#: Soft-soft contact (not in the default set): scenes/plush_pile.obj, three 642-vertex plushies
#: falling into a pile on a floor, dt 1e-4 s (the scene's own), 2000 steps from rest (step) or
#: 16 points of 1000 steps (sweep, one chunk), with the candidate lists carried from step to step.
CONTACT_CASES = ("step:contact", "sweep:contact")
UNITS = {"step": "steps/s", "sweep": "point-steps/s", "gradient": "gradients/s"}


# --------------------------------------------------------------------------- one measurement

def _scene(jaxplush, full, subdivisions=3):
    import trimesh
    m = trimesh.creation.icosphere(subdivisions=subdivisions, radius=0.1)
    lines = ["floor 0", "o ball", "k_structural 500", "total_weight 0.1", "nmol 0.0005"]
    if full:
        lines += ["dashpot 0.005", "drag 0.5", "damping 200"]
    lines += ["translate 0 0.3 0"]
    lines += [f"v {float(a)!r} {float(b)!r} {float(c)!r}" for a, b, c in m.vertices]
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in m.faces]
    return jaxplush.parse_scene("\n".join(lines) + "\n", f"<icosphere {subdivisions}>")


def _best(fn, repeats):
    import jax
    jax.block_until_ready(fn())                                    # compile
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - t0)
    return min(times)


def measure(case, repeats=5, subdivisions=3):
    """One case's throughput (see the module docstring) in this process. The step is 2e-4 s at
    642 vertices, halved with each further subdivision (the stable limit halves)."""
    import jaxplush  # first: it sets options that jax reads when it is imported
    import jax
    import jax.numpy as jnp
    import numpy as np
    kind, variant = case.split(":")
    if variant == "contact":
        scene, dt = jaxplush.load_scene(os.path.join(REPO, "scenes", "plush_pile.obj")), 1e-4
    else:
        scene = _scene(jaxplush, variant == "full", subdivisions)
        dt = 2e-4 * 0.5 ** (subdivisions - 3)
    if kind == "step":
        sim = jaxplush.make_simulator(scene, dt)
        p = sim.params()
        s = sim.init_fn(p)
        steps = 2000 if variant == "contact" else 1000
        return steps / _best(lambda: jaxplush.rollout(sim, p, s, 1, steps), repeats)
    if kind == "sweep":
        from jaxplush.stepping import batched
        b, steps = (16, 1000) if variant == "contact" else (64, 500)
        bsim = batched.make_batched_simulator(scene, dt, b)
        bp = bsim.params()
        k0 = np.asarray(bp.k_structural, np.float64)[:, :1]
        bp = bp._replace(k_structural=jnp.asarray(k0 * np.linspace(0.8, 1.2, b)[None, :], bsim.dtype))
        bs = bsim.init_fn(bp)
        return b * steps / _best(lambda: batched.rollout(bsim, bp, bs, 1, steps), repeats)
    if kind == "gradient":
        from jaxplush.fitting.objective import gradients
        sim = jaxplush.make_simulator(scene, dt)
        p = sim.params()
        steps = 500
        frames = tuple(range(50, steps + 1, 50))
        _, traj, _ = jaxplush.rollout(sim, p, sim.init_fn(p), len(frames), 50)
        target = jnp.asarray(traj) + 1e-3

        def loss(q):
            return gradients.rollout_loss(sim, q, sim.init_fn(q), frames,
                                          lambda x, t: jnp.sum((x - t) ** 2), target, method="adjoint")
        vg = jax.jit(jax.value_and_grad(loss))
        return 1.0 / _best(lambda: vg(p), repeats)
    raise ValueError(f"unknown case {case!r}")


# --------------------------------------------------------------------------- side by side

def _tree(spec, tmp, name):
    """A source tree for ``spec``: a path as it is, or a git revision checked out in ``tmp``."""
    if os.path.isdir(spec):
        return os.path.abspath(spec)
    path = os.path.join(tmp, name)
    subprocess.run(["git", "-C", REPO, "worktree", "add", "--detach", "-q", path, spec], check=True)
    return path


def _run_child(root, case, repeats, subdivisions):
    env = dict(os.environ, JAX_ENABLE_X64="0", JAX_COMPILATION_CACHE_DIR="")
    out = subprocess.run([sys.executable, os.path.abspath(__file__), "--root", root, "--case", case,
                          "--repeats", str(repeats), "--subdivisions", str(subdivisions)],
                         capture_output=True, text=True, env=env, cwd=root)
    if out.returncode:
        raise SystemExit(f"{case} in {root} failed:\n{out.stderr[-3000:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])["value"]


def compare(before, after, cases, rounds, repeats, subdivisions=3):
    tmp = tempfile.mkdtemp(prefix="jaxplush-hotpaths-")
    made = []
    try:
        trees = {}
        for name, spec in (("before", before), ("after", after)):
            trees[name] = _tree(spec, tmp, name)
            if not os.path.isdir(spec):
                made.append(trees[name])
        rows = []
        for case in cases:
            got = {"before": [], "after": []}
            for r in range(rounds):
                order = ("before", "after") if r % 2 == 0 else ("after", "before")
                for name in order:
                    got[name].append(_run_child(trees[name], case, repeats, subdivisions))
                    print(f"  {case:15s} {name:6s} round {r + 1}: {got[name][-1]:.4g}", file=sys.stderr, flush=True)
            b, a = max(got["before"]), max(got["after"])
            rows.append((case, b, a, a / b, statistics.median(x / y for x, y in zip(got["after"], got["before"]))))
        return rows
    finally:
        for path in made:
            subprocess.run(["git", "-C", REPO, "worktree", "remove", "--force", path], check=False)
        shutil.rmtree(tmp, ignore_errors=True)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--before", help="git revision or source tree of the baseline")
    ap.add_argument("--after", default=REPO, help="git revision or source tree (default: this checkout)")
    ap.add_argument("--cases", default=",".join(CASES))
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--subdivisions", type=int, default=3, help="icosphere subdivisions (3: 642 vertices, 4: 2562)")
    ap.add_argument("--root", help=argparse.SUPPRESS)
    ap.add_argument("--case", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.case:
        sys.path.insert(0, args.root)
        import jaxplush
        # The tree's fitting/ folder installs as jaxplush.fitting; found here from the source tree.
        jaxplush.__path__.append(args.root)
        print(json.dumps({"case": args.case, "value": measure(args.case, args.repeats, args.subdivisions)}))
        return 0
    if not args.before:
        ap.error("--before is required")
    cases = [c for c in args.cases.split(",") if c]
    unknown = sorted(set(cases) - set(CASES) - set(CONTACT_CASES))
    if unknown:
        ap.error(f"unknown case(s) {', '.join(unknown)}; choose from {', '.join(CASES + CONTACT_CASES)}")
    rows = compare(args.before, args.after, cases, args.rounds, args.repeats, args.subdivisions)
    n_vertices = 10 * 4 ** args.subdivisions + 2
    print(f"# {n_vertices} vertices; {platform.processor() or platform.machine()}, {os.cpu_count()} cores; "
          f"best of {args.rounds} rounds "
          f"x {args.repeats} repeats; before = {args.before}, after = {args.after}")
    print(f"| {'case':15s} | unit          | {'before':>10s} | {'after':>10s} | after/before (best) | "
          f"(median of rounds) |")
    print(f"|{'-' * 17}|---------------|{'-' * 12}|{'-' * 12}|---------------------|--------------------|")
    for case, b, a, ratio, med in rows:
        print(f"| {case:15s} | {UNITS[case.split(':')[0]]:13s} | {b:10.4g} | {a:10.4g} | {ratio:19.3f} | {med:18.3f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
