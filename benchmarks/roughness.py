"""How rough is a fitting loss, and why: 1-D scans of a dropped ball's loss at small scales.

For a 642-vertex ball dropped 0.2 m onto a floor (jaxplush.fitting.scenarios; 3000 steps of 2e-4 s, 60
frames), the loss of a positions target made at the true values is scanned along each log-
parameter, at the truth and at a start x1.9 / x2 / x0.6 away: central differences at relative
steps 1e-5 ... 1e-2 against the exact directional derivative (autodiff, float64). A smooth loss
gives the same slope at every step; a rough one scatters. Four variants separate the causes:
the report's per-step damping (which damps every mode at one rate, so vertex-level modes excited
by the impact ring for the whole target) or an edge dashpot (which damps them), with the floor
projection or the smooth penalty floor (``floor_model smooth``).

Usage: python benchmarks/roughness.py
"""

from __future__ import annotations

import os
import sys
import time
import warnings

import jax
import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))
jax.config.update("jax_enable_x64", True)

STEPS = (1e-5, 1e-4, 1e-3, 1e-2)


def scan(damping, floor_model):
    import jaxplush
    from jaxplush.fitting import fitter as F
    from jaxplush.fitting.scenarios import drop_scene_text
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


def main():
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
