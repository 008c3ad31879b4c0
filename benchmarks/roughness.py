"""How rough is a fitting loss, and why: 1-D scans of a dropped ball's loss at small scales.

For a 642-vertex ball dropped 0.2 m onto a floor (jaxplush.fitting.targets.scenarios; 3000 steps of 2e-4 s, 60
frames), the loss of a positions target made at the true values is scanned along each log-
parameter, at the truth and at a start x1.9 / x2 / x0.6 away: central differences at relative
steps 1e-5 ... 1e-2 against the exact directional derivative (autodiff, float64). A smooth loss
gives the same slope at every step; a rough one scatters. Four variants separate the causes:
the report's per-step damping (which damps every mode at one rate, so vertex-level modes excited
by the impact ring for the whole target) or an edge dashpot (which damps them), with the floor
projection or the smooth penalty floor (``floor_model smooth``).

``--case SEED INDEX`` scans one scene of ``bench_recovery.py --random N --seed SEED`` instead: the
per-frame central differences of all positions with respect to one object's log-parameter, at the
truth, for steps 2e-3, 4e-4, 8e-5 and 1.6e-5, and how far each disagrees with the next smaller
one (0: the positions are smooth at that scale; about 1: the difference quotient at that step says
nothing about the derivative). Variants (``--variants``): the scene as drawn, the object alone, the
contact thickness three times the thinnest pair's default, the smooth penalty floor, and both.

Usage: python benchmarks/roughness.py [--case SEED INDEX [--object O] [--param NAME] [--variants ...]]
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
import warnings

import jax
import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

STEPS = (1e-5, 1e-4, 1e-3, 1e-2)


def scan(damping, floor_model):
    import jaxplush
    from jaxplush.fitting import fitter as F
    from jaxplush.fitting.targets.scenarios import drop_scene_text
    from jaxplush.fitting.targets import make_target
    from jaxplush.gradcheck import roughness_scan
    kw = dict(damping=2000.0) if damping == "damping" else dict(damping=None, dashpot=0.1)
    if floor_model == "smooth":
        kw["floor_model"] = "smooth"
    truth = jaxplush.parse_scene(drop_scene_text("ball", 3, **kw), "truth")
    target = make_target(truth, 3000, 2e-4, 50)
    names = ("k_structural", damping, "nmol")
    p = truth.params
    rows = []
    for where, fac in (("truth", (1.0, 1.0, 1.0)), ("start", (1.9, 2.0, 0.6))):
        vals = {n: getattr(p, n) * f for n, f in zip(names, fac)}
        start = truth.replace(params=p._replace(**vals))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            prob = F.build_problem(start, target, names, noise_free=True)
        vg = jax.jit(jax.value_and_grad(prob.loss_fn))
        th = np.asarray(prob.theta0)
        _, g = vg(th)
        f = lambda t: float(vg(np.asarray(t).reshape(th.shape))[0])  # noqa: E731
        for i, n in enumerate(names):
            d = np.zeros(th.size)
            d[i] = 1.0
            r = roughness_scan(f, th.ravel(), d, STEPS, grad=np.asarray(g).ravel())
            rows.append((where, n, r["exact"], r["slopes"]))
    return rows


CASE_STEPS = (2e-3, 4e-4, 8e-5, 1.6e-5)
CASE_FRAMES = 50
VARIANTS = ("drawn", "alone", "thick", "smooth", "thick+smooth")


def _case_text(text, variant, obj, thickness):
    """The truth scene's text as drawn, with object ``obj`` alone, or with the contact thickness set."""
    if variant == "drawn":
        return text
    if variant.endswith("smooth"):
        lines = text.splitlines()
        at = next(i for i, line in enumerate(lines) if line.startswith("floor "))
        text = "\n".join(lines[:at + 1] + ["floor_model smooth"] + lines[at + 1:]) + "\n"
        variant = variant[:-len("smooth")].rstrip("+")
    if variant == "thick":
        return text.replace("\ncontact on\n", f"\ncontact on\ncontact_thickness {thickness:.6g}\n")
    if not variant:
        return text
    head, _, body = text.partition("\no ")
    blocks = [b for b in ("o " + body).split("END_OBJECT") if b.strip()]
    head = "\n".join(line for line in head.splitlines() if not line.startswith("contact"))
    # OBJ face indices count the file's vertices from 1: renumber the object's own
    offset = sum(line.startswith("v ") for b in blocks[:obj] for line in b.splitlines())
    lines = [("f " + " ".join(str(int(t.split("/")[0]) - offset) for t in line.split()[1:])
              if line.startswith("f ") else line) for line in blocks[obj].strip("\n").splitlines()]
    return head + "\n" + "\n".join(lines) + "\nEND_OBJECT\n"


def case_scan(seed, index, obj, param, variant):
    """Rows (frame, time, lowest vertex, |dX/dlog p|, disagreements between successive steps)."""
    import jax.numpy as jnp
    import jaxplush
    from jaxplush.model import contact
    from jaxplush.model import forces
    sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
    import bench_recovery as B
    case = B.redraw(index, seed, 0)
    with tempfile.TemporaryDirectory() as d, warnings.catch_warnings():
        warnings.simplefilter("ignore")
        truth, _, _ = B.random_case_files(d, case)
    base_cfg = contact.config_for_scene(truth)
    thick = 3.0 * min(base_cfg.thickness) if base_cfg.pairs else 0.0
    if variant.startswith("thick") and not base_cfg.pairs or variant.endswith("smooth") and truth.floor is None:
        return None
    scene = jaxplush.parse_scene(_case_text(truth.text, variant, obj, thick), f"case{index:03d}_{variant}")
    o = 0 if variant == "alone" else obj
    terms = forces.Terms.for_scene(scene)
    if scene.n_objects > 1:
        terms = contact.with_headroom(terms, contact.object_sizes(scene))
    sim = jaxplush.make_simulator(scene, case["dt"], terms=terms)
    p0 = sim.params()
    state = sim.init_fn(p0)
    every = max(1, case["steps"] // CASE_FRAMES)
    run = jax.jit(lambda p: jaxplush.rollout(sim, p, state, CASE_FRAMES, every)[1])

    def frames(h):
        a = np.asarray(getattr(p0, param), np.float64).copy()
        a[o] *= np.exp(h)
        return np.asarray(run(p0._replace(**{param: jnp.asarray(a, sim.dtype)})), np.float64)

    base = frames(0.0)
    D = [(frames(h) - frames(-h)) / (2 * h) for h in CASE_STEPS]
    norm = [np.linalg.norm(d.reshape(CASE_FRAMES, -1), axis=1) for d in D]
    gaps = [np.linalg.norm((a - b).reshape(CASE_FRAMES, -1), axis=1) / np.maximum(nb, 1e-300)
            for a, b, nb in zip(D, D[1:], norm[1:])]
    return [(f, (f + 1) * every * case["dt"], float(base[f, :, 1].min()), float(norm[-1][f]),
             [float(g[f]) for g in gaps]) for f in range(CASE_FRAMES)]


def case_main(args):
    seed, index = args.case
    print(f"# {time.strftime('%Y-%m-%d')}, float64; bench_recovery --random --seed {seed}, case {index}; "
          f"d positions / d log {args.param}[{args.object}] by central differences at the truth")
    pairs = [f"{a:g} vs {b:g}" for a, b in zip(CASE_STEPS, CASE_STEPS[1:])]
    print("| variant | frame | t (s) | lowest vertex (m) | norm of dX/dlog p (m) | " + " | ".join(pairs) + " |")
    print("|---|---:|---:|---:|---:|" + "---:|" * len(pairs))
    for variant in args.variants:
        rows = case_scan(seed, index, args.object, args.param, variant)
        if rows is None:
            print(f"| {variant} | (this scene has no contact between objects or no floor) |")
            continue
        for f, t, low, nd, gaps in rows:
            if f % args.every == 0 or f == len(rows) - 1:
                print(f"| {variant} | {f} | {t:.3f} | {low:.4f} | {nd:.3g} | "
                      + " | ".join(f"{g:.3f}" for g in gaps) + " |", flush=True)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--case", nargs=2, type=int, metavar=("SEED", "INDEX"),
                    help="scan one random scene of bench_recovery.py instead of the dropped ball")
    ap.add_argument("--object", type=int, default=0, help="the object whose parameter is varied (default 0)")
    ap.add_argument("--param", default="k_structural", help="the parameter varied (default k_structural)")
    ap.add_argument("--variants", nargs="+", default=list(VARIANTS),
                    choices=VARIANTS, help="which scenes to scan (default all)")
    ap.add_argument("--every", type=int, default=3, help="print every this many frames (default 3)")
    args = ap.parse_args(argv)
    jax.config.update("jax_enable_x64", True)
    if args.case:
        return case_main(args)
    print(f"# {time.strftime('%Y-%m-%d')}, float64; directional slopes d loss / d log p by central differences")
    print("| damping | floor | at | parameter | exact | " + " | ".join(f"h = {h:g}" for h in STEPS)
          + " | spread (h <= 1e-3) |")
    print("|---|---|---|---|---:|" + "---:|" * len(STEPS) + "---:|")
    for damping in ("damping", "dashpot"):
        for floor in ("projection", "smooth"):
            for where, n, exact, slopes in scan(damping, floor):
                # at the truth (a minimum, slope 0) the differences only show the curvature
                spread = "n/a" if where == "truth" else f"{float(np.max(np.abs(slopes[:3] - exact)) / abs(exact)):.2g}"
                print(f"| {damping} | {floor} | {where} | {n} | {exact:+.4g} | "
                      + " | ".join(f"{s:+.4g}" for s in slopes) + f" | {spread} |", flush=True)


if __name__ == "__main__":
    main()
