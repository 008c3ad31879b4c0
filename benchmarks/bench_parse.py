"""Scene parsing time by size: one big sphere (vertices) and many small objects (objects).

Each scene is written to a temporary file (icospheres from trimesh; the small objects are
icosahedra of 12 vertices) and loaded with ``jaxplush.load_scene`` (read, parse, mesh checks,
orientation), then ``jaxplush.make_simulator`` builds its topology (one-ring tables); median of
``--repeats``.

Usage: python benchmarks/bench_parse.py [--repeats 3] [--sizes 4,5,6,7] [--objects 1000,5000,20000] [--no-mixed]
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import sys
import tempfile
import time
import warnings

import numpy as np
import trimesh

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))
import jaxplush  # noqa: E402


def sphere_text(subdivisions):
    m = trimesh.creation.icosphere(subdivisions=subdivisions, radius=0.1)
    lines = ["o big", "k_structural 100", "total_weight 1", "nmol 0.001"]
    lines += ["v %r %r %r" % tuple(map(float, v)) for v in m.vertices]
    lines += ["f %d %d %d" % tuple(f + 1) for f in m.faces]
    return "\n".join(lines + ["END_OBJECT"]) + "\n", len(m.vertices)


def mixed_text():
    """About 240k vertices in one scene: icospheres of levels 7, 6 and 6 (245,766 vertices)."""
    out, off = [], 0
    for i, sub in enumerate((7, 6, 6)):
        m = trimesh.creation.icosphere(subdivisions=sub, radius=0.1)
        out += [f"o sphere{i}", "k_structural 100", "total_weight 1", "nmol 0.001", f"translate {0.3 * i} 0 0"]
        out += ["v %r %r %r" % tuple(map(float, v)) for v in m.vertices]
        out += ["f %d %d %d" % tuple(f + 1 + off) for f in m.faces]
        out.append("END_OBJECT")
        off += len(m.vertices)
    return "\n".join(out) + "\n", off


def many_text(n):
    m = trimesh.creation.icosahedron()
    out = []
    for i in range(n):
        c = np.array([i % 100, (i // 100) % 100, i // 10000], float) * 3
        out.append(f"o ball{i}")
        out += ["v %r %r %r" % tuple(map(float, v + c)) for v in m.vertices]
        out += ["f %d %d %d" % tuple(f + 1 + 12 * i) for f in m.faces]
        out.append("END_OBJECT")
    return "\n".join(out) + "\n", 12 * n


def timed(text, repeats, topology):
    with tempfile.TemporaryDirectory() as d:
        path = os.path.join(d, "scene.obj")
        with open(path, "w") as fh:
            fh.write(text)
        loads, builds = [], []
        for _ in range(repeats):
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                t = time.perf_counter()
                scene = jaxplush.load_scene(path)
                loads.append(time.perf_counter() - t)
                if topology:
                    t = time.perf_counter()
                    jaxplush.model.forces.build_topology(scene)
                    builds.append(time.perf_counter() - t)
        return statistics.median(loads), (statistics.median(builds) if builds else float("nan")), len(text)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--sizes", default="4,5,6,7")
    ap.add_argument("--objects", default="1000,5000,20000")
    ap.add_argument("--no-mixed", dest="mixed", action="store_false",
                    help="skip the 245,766-vertex scene of three icospheres")
    args = ap.parse_args(argv)
    print(f"# {platform.machine()}, {os.cpu_count()} cores, python {platform.python_version()}; "
          f"median of {args.repeats}")
    print("| scene | vertices | objects | file MB | load_scene s | topology s |")
    print("|---|---:|---:|---:|---:|---:|")
    for sub in (int(s) for s in args.sizes.split(",") if s):
        text, nv = sphere_text(sub)
        load, topo, size = timed(text, args.repeats, True)
        print(f"| icosphere level {sub} | {nv:,} | 1 | {size / 1e6:.1f} | {load:.2f} | {topo:.2f} |", flush=True)
    if args.mixed:
        text, nv = mixed_text()
        load, topo, size = timed(text, args.repeats, True)
        print(f"| icospheres of levels 7, 6, 6 | {nv:,} | 3 | {size / 1e6:.1f} | {load:.2f} | {topo:.2f} |", flush=True)
    for n in (int(s) for s in args.objects.split(",") if s):
        text, nv = many_text(n)
        load, _, size = timed(text, args.repeats, False)
        print(f"| {n:,} icosahedra | {nv:,} | {n:,} | {size / 1e6:.1f} | {load:.2f} | - |", flush=True)


if __name__ == "__main__":
    main()
