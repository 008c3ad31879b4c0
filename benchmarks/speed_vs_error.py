"""Speed against error for every integrator (issue 4): which integrator and dt for a target accuracy.

For three standard scenes (a free spinning ball, a ball dropped on the floor, a hanging plush)
every integrator runs at a range of dt, given as fractions of the explicit limit
h_c = 2/omega_max (:func:`jaxplush.estimate_stable_dt`). Each float32 run is compared with a
float64 reference (RK4 at h_c/20): the error is the largest, over saved frames, RMS vertex
distance (m). Speed is wall time per simulated second (compile excluded, median of repeats,
one compiled ``jaxplush.rollout``). A run that blows up is listed as unstable.

Output: a markdown table, a work-precision plot per scene (error against wall time,
``speed_vs_error_<scene>.png`` in --out-dir, written atomically), and a recommendation: for
each target error, the fastest (integrator, dt/h_c) whose error meets it on every scene.

Usage: python benchmarks/speed_vs_error.py [--small] [--out-dir benchmarks] [--repeats 3]
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import sys
import time

import jax
import numpy as np
import trimesh

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))
import jaxplush  # noqa: E402
from jaxplush.progress import Progress  # noqa: E402

#: dt / h_c tried per integrator (full size; --small keeps fewer).
FACTORS = {
    "euler": (0.02, 0.05, 0.1, 0.2),
    "symplectic_euler": (0.05, 0.1, 0.2, 0.4, 0.8),
    "rk4": (0.1, 0.2, 0.4, 0.8, 1.2),
    "verlet": (0.05, 0.1, 0.2, 0.4, 0.8),
    "mesit": (0.02, 0.05, 0.1, 0.2),
    "implicit_euler": (0.2, 0.5, 1.0, 2.0, 5.0, 10.0),
}
SMALL_FACTORS = {"euler": (0.05,), "symplectic_euler": (0.5,), "rk4": (0.5,), "verlet": (0.5,), "mesit": (0.05,),
                 "implicit_euler": (2.0,)}
#: Never recommended: explicit Euler gains energy at any dt, Mesit's update is unsound (docs/model.md §2).
NOT_RECOMMENDED = ("euler", "mesit")
TARGETS = (1e-3, 1e-4, 1e-5)   # m, RMS vertex error (the ball radius is 0.1 m)


def _ball_lines(subdivisions, header, body):
    m = trimesh.creation.icosphere(subdivisions=subdivisions, radius=0.1)
    lines = list(header) + ["o ball", "k_structural 300", "total_weight 0.1", "nmol 1e-3"] + list(body)
    lines += [f"v {float(a)!r} {float(b)!r} {float(c)!r}" for a, b, c in m.vertices]
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in m.faces]
    return m, lines


def scenes(subdivisions):
    """{name: (scene, x0 or None, v0 or None)} of the three standard scenes."""
    out = {}
    m, lines = _ball_lines(subdivisions, ["gravity 0 -9.81 0"], [])
    free = jaxplush.parse_scene("\n".join(lines) + "\n", "<free ball>")
    x = free.vertices
    out["free_ball"] = (free, x * np.array([1.06, 0.95, 1.0]), np.cross([1.0, 4.0, 0.5], x) + [0.3, 1.0, 0.0])
    _, lines = _ball_lines(subdivisions, ["gravity 0 -9.81 0", "floor 0"], ["dashpot 0.002", "translate 0 0.13 0"])
    out["ball_on_floor"] = (jaxplush.parse_scene("\n".join(lines) + "\n", "<ball on floor>"), None,
                            np.tile([0.4, -1.0, 0.0], (len(m.vertices), 1)))
    top = int(np.argmax(m.vertices[:, 1]))
    _, lines = _ball_lines(subdivisions, ["gravity 0 -9.81 0"], ["dashpot 0.005", "drag 1"])
    lines.append(f"fixed {top + 1}")
    out["hanging_plush"] = (jaxplush.parse_scene("\n".join(lines) + "\n", "<hanging plush>"), None, None)
    return out


def _frames(scene, integrator, dt, steps, n_frames, x0, v0, repeats=0):
    """(frames (n_frames, V, 3) float64 or None if it blew up, median wall s of ``repeats`` runs)."""
    sim = jaxplush.make_simulator(scene, dt, integrator)
    p = sim.params()
    s0 = sim.init_fn(p, x0, v0)
    out = jaxplush.rollout(sim, p, s0, n_frames, steps // n_frames)
    jax.block_until_ready(out)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(jaxplush.rollout(sim, p, s0, n_frames, steps // n_frames))
        times.append(time.perf_counter() - t0)
    frames = np.asarray(out[1], np.float64)
    ok = not out[2].failed and np.isfinite(frames).all()
    return (frames if ok else None), (statistics.median(times) if times else float("nan"))


def run(small=False, repeats=3, progress=True):
    """Run the benchmark; returns a list of row dicts (scene, integrator, dt, factor, error, wall_per_s)."""
    subdivisions, t_end, n_frames = (1, 0.05, 10) if small else (2, 0.25, 25)
    factors = SMALL_FACTORS if small else FACTORS
    jobs = sum(len(f) for f in factors.values())
    rows = []
    all_scenes = scenes(subdivisions)
    with Progress(jobs * len(all_scenes), "speed vs error", enabled=progress, unit="runs") as bar:
        for name, (scene, x0, v0) in all_scenes.items():
            sim = jaxplush.make_simulator(scene, 1e-4)
            hc = jaxplush.estimate_stable_dt(sim, sim.params()).dt_max
            # float64 reference: RK4 at about h_c / 20, a whole number of steps per frame.
            per_frame = int(np.ceil(t_end / n_frames / (hc / 20)))
            with jax.enable_x64(True):
                ref, _ = _frames(scene, "rk4", t_end / (n_frames * per_frame), n_frames * per_frame, n_frames, x0, v0)
            assert ref is not None, f"{name}: the float64 reference blew up"
            for integrator, fs in factors.items():
                for f in fs:
                    per_frame = max(1, int(round(t_end / n_frames / (f * hc))))
                    dt = t_end / (n_frames * per_frame)
                    frames, wall = _frames(scene, integrator, dt, n_frames * per_frame, n_frames, x0, v0, repeats)
                    err = (float(np.sqrt(np.mean(np.sum((frames - ref) ** 2, axis=-1), axis=1)).max())
                           if frames is not None else float("inf"))
                    rows.append(dict(scene=name, integrator=integrator, dt=dt, factor=dt / hc, nominal=f, h_c=hc, error=err,
                                     wall_per_s=(wall / t_end if frames is not None else float("nan")),
                                     vertices=scene.n_vertices))
                    bar.update(1, f"{name} {integrator}")
    return rows


def table(rows):
    """Markdown table of the rows."""
    out = ["| scene | integrator | dt (s) | dt / h_c | error (m, RMS) | wall s per simulated s |",
           "|---|---|---:|---:|---:|---:|"]
    for r in rows:
        err = "unstable" if not np.isfinite(r["error"]) else f"{r['error']:.2e}"
        wall = "-" if not np.isfinite(r["wall_per_s"]) else f"{r['wall_per_s']:.3g}"
        out.append(f"| {r['scene']} | {r['integrator']} | {r['dt']:.3g} | {r['factor']:.2f} | {err} | {wall} |")
    return "\n".join(out)


def recommend(rows, targets=TARGETS):
    """For each target, the fastest sound (integrator, dt/h_c) meeting it on every scene (text lines)."""
    scenes_ = sorted({r["scene"] for r in rows})
    combos = {}
    for r in rows:
        if r["integrator"] not in NOT_RECOMMENDED:
            combos.setdefault((r["integrator"], r["nominal"]), {})[r["scene"]] = r
    lines = []
    for target in targets:
        best = None
        for (integrator, factor), by_scene in combos.items():
            if set(by_scene) != set(scenes_) or any(not (r["error"] <= target) for r in by_scene.values()):
                continue
            cost = sum(r["wall_per_s"] for r in by_scene.values())
            if best is None or cost < best[0]:
                best = (cost, integrator, factor, max(r["error"] for r in by_scene.values()))
        if best is None:
            lines.append(f"target {target:.0e} m: no run met it on every scene (use rk4 at a smaller dt)")
        else:
            cost, integrator, factor, err = best
            lines.append(f"target {target:.0e} m: {integrator} at dt = {factor:.2f} h_c (worst error {err:.1e} m, "
                         f"{cost / len(scenes_):.3g} s wall per simulated s on average)")
    return lines


def plot(rows, scene, path=None, ax=None):
    """Work-precision plot of one scene: error against wall time per simulated second."""
    import matplotlib
    if ax is None and path is not None:
        matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    own = ax is None
    if own:
        fig, ax = plt.subplots(figsize=(6.4, 4.6))
    for integrator in jaxplush.INTEGRATORS:
        rs = [r for r in rows if r["scene"] == scene and r["integrator"] == integrator and np.isfinite(r["error"])]
        if not rs:
            continue
        rs.sort(key=lambda r: r["wall_per_s"])
        line, = ax.loglog([r["wall_per_s"] for r in rs], [r["error"] for r in rs], "o-", label=integrator)
        for r in rs:
            ax.annotate(f"{r['factor']:.2g}", (r["wall_per_s"], r["error"]), fontsize=7, color=line.get_color(),
                        textcoords="offset points", xytext=(3, 3))
    n = next(r["vertices"] for r in rows if r["scene"] == scene)
    ax.set_xlabel("wall time per simulated second (s)")
    ax.set_ylabel("max RMS vertex error vs float64 RK4 (m)")
    ax.set_title(f"{scene.replace('_', ' ')} ({n} vertices); labels: dt / h_c")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    if own and path is not None:
        from jaxplush.io.trajectory import atomic_path
        with atomic_path(path, ".png") as tmp:
            fig.savefig(tmp, dpi=110, bbox_inches="tight", format="png")
        plt.close(fig)
    return ax


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--small", action="store_true", help="quick run: 42 vertices, 0.05 s, one dt per integrator")
    ap.add_argument("--out-dir", default=os.path.dirname(os.path.abspath(__file__)), help="where the PNGs go")
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args(argv)
    if not os.path.isdir(args.out_dir):
        print(f"speed_vs_error: error: --out-dir {args.out_dir} does not exist", file=sys.stderr)
        return 2
    print(f"# jaxplush {jaxplush.__version__}, jax {jax.__version__}, {jax.devices()[0].device_kind}, "
          f"{os.cpu_count()} cores, {platform.processor() or platform.machine()}; runs float32, reference "
          f"float64 RK4 at h_c/20; wall time median of {args.repeats}, compile excluded")
    rows = run(small=args.small, repeats=args.repeats)
    print(table(rows))
    for scene in sorted({r["scene"] for r in rows}, key=[r["scene"] for r in rows].index):
        path = os.path.join(args.out_dir, f"speed_vs_error_{scene}.png")
        plot(rows, scene, path)
        print(f"wrote {path}")
    print("\nRecommendation (fastest integrator and dt meeting the target on every scene; euler and mesit excluded):")
    for line in recommend(rows):
        print(f"- {line}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
