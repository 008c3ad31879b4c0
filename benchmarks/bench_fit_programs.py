"""What a cold fit compiles: every XLA program of one default fit, its count and compile seconds.

A scene of N icospheres stacked 0.21 m apart on a floor (soft-soft contact on between every pair),
the truth's k = 100 N/m x (1, 1.3, 1.6, ...), the start's 60 N/m; the target is 400 steps of 5e-4 s
with every 20th saved, fitted noise-free by the default fit. Run it with an empty cache to see the
cold cost (the default: a fresh temporary cache directory), or ``--cache DIR`` a second time to see
what the persistent cache saves.

    python benchmarks/bench_fit_programs.py --objects 3 --subdivisions 2
"""

from __future__ import annotations

import argparse
import collections
import logging
import os
import re
import tempfile
import time
import warnings


def scene_text(n, subdivisions, k, variant=0):
    """The stack's scene; ``variant`` > 0: another scene of the same size bucket (the same mesh
    sizes), every object scaled by its own random factor (1.1 x (1 +- 5%)), 30% heavier, and
    placed elsewhere, so that no geometry-derived value is the first scene's."""
    import numpy as np
    import trimesh
    m = trimesh.creation.icosphere(subdivisions=subdivisions, radius=0.1)
    nv = len(m.vertices)
    rng = np.random.default_rng(variant)
    out = ["gravity 0.0 -9.81 0.0", "floor 0.0"]
    if subdivisions >= 2:
        out.append(f"contact_capacity {nv}")
    for i in range(n):
        scale = 1.1 * (1.0 + 0.05 * rng.standard_normal()) if variant else 1.0
        weight, dx, dz = (0.13, 0.01, 0.02) if variant else (0.1, 0.0, 0.0)
        out += [f"o b{i}", f"k_structural {k * (1 + 0.3 * i)!r}", f"total_weight {weight}", "damping 500.0",
                f"translate {0.05 * i + dx!r} {(0.15 + 0.21 * i) * (1.05 if variant else 1.0)!r} {dz}"]
        out += [f"v {float(a) * scale!r} {float(b) * scale!r} {float(c) * scale!r}" for a, b, c in m.vertices]
        out += [f"f {a + 1 + nv * i} {b + 1 + nv * i} {c + 1 + nv * i}" for a, b, c in m.faces]
        out.append("END_OBJECT")
    return "\n".join(out) + "\n"


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--objects", type=int, default=3)
    ap.add_argument("--subdivisions", type=int, default=2, help="icosphere level (1: 42 vertices, 2: 162)")
    ap.add_argument("--cache", default=None, help="persistent cache directory (default: a fresh, empty one)")
    ap.add_argument("--variant", type=int, default=0,
                    help="> 0: another scene of the same size bucket (scaled, heavier, moved; run it with "
                         "--cache DIR after a first run to see what a scene of its bucket fitted before saves)")
    args = ap.parse_args()
    os.environ["JAXPLUSH_CACHE_DIR"] = args.cache or tempfile.mkdtemp(prefix="jaxplush-bench-cache-")

    import jaxplush  # first: it sets options jax reads when imported
    import jax
    from jaxplush.fitting import fitter as F
    from jaxplush.fitting.targets import make_target

    recs = []

    class Catch(logging.Handler):
        def emit(self, record):
            m = re.match(r"Finished XLA compilation of (.*) in ([0-9.e-]+) sec", record.getMessage())
            if m:
                recs.append((m.group(1), float(m.group(2))))

    logger = logging.getLogger("jax")
    logger.addHandler(Catch())
    logger.setLevel(logging.DEBUG)
    jax.config.update("jax_log_compiles", True)

    truth = jaxplush.parse_scene(scene_text(args.objects, args.subdivisions, 100.0, args.variant), "<truth>")
    target = make_target(truth, 400, 5e-4, 20)
    recs.clear()                                 # the fit's programs only, not the target's
    start = jaxplush.parse_scene(scene_text(args.objects, args.subdivisions, 60.0, args.variant), "<start>")
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = F.fit(start, target, noise_free=True)
    wall = time.perf_counter() - t0
    count, secs = collections.Counter(), collections.defaultdict(float)
    for name, t in recs:
        count[name] += 1
        secs[name] += t
    print(f"{args.objects} x {truth.n_vertices // args.objects} vertices: fit {wall:.1f} s, XLA compiles "
          f"{sum(secs.values()):.1f} s in {len(recs)} programs; outcome {res.outcome.status}, "
          f"RMS {res.outcome.rms * 1e3:.3g} mm")
    print(f"the fit's own timing: {res.timing.text()}")
    print(f"| {'program':28s} | count | compile s |")
    print(f"|{'-' * 30}|------:|----------:|")
    for name in sorted(secs, key=lambda k: -secs[k]):
        print(f"| {name:28s} | {count[name]:5d} | {secs[name]:9.2f} |")


if __name__ == "__main__":
    main()
