"""Synthetic recovery: fit a scene to a target simulated with known parameters.

:func:`recovery_scene_text` writes the scenario (a soft pressurised ball hanging from one pinned
vertex), and :func:`synthetic_recovery` fits it from a start off the truth and reports how close
the fit came (the issue's acceptance run; benchmarks/bench_fit.py).
"""

from __future__ import annotations

import time
import warnings

import numpy as np

import jaxplush


# --------------------------------------------------------------------------- synthetic recovery

#: The recovery scenario's true parameters (docs/model.md §9.4: dynamics determine k, damping and
#: nmol): a soft pressurised ball hanging from one pinned top vertex, released undeformed; it
#: inflates, sags and rings on its pin, damped by the Verlet damping.
RECOVERY_TRUTH = dict(k_structural=50.0, damping=1000.0, inflation=1.05, total_weight=0.1, radius=0.1)


def recovery_scene_text(subdivisions=2, k_structural=50.0, damping=1000.0, nmol=None, *, inflation=1.05,
                        total_weight=0.1, radius=0.1, height=1.0):
    """Scene text of the recovery scenario: an icosphere ball (radius 0.1 m) pinned at its top.

    ``nmol`` defaults to the gas that inflates the free ball to ``inflation`` x its size
    (docs/model.md §8.5: n = k s (s - 1) sum L² / (3 R T)).
    """
    import trimesh
    from jaxplush.scene.write import format_scene
    from jaxplush.types import GAS_CONSTANT
    mesh = trimesh.creation.icosphere(subdivisions=int(subdivisions), radius=radius)
    v = np.asarray(mesh.vertices, np.float64)
    f = np.asarray(mesh.faces, np.int64)
    if nmol is None:
        e = mesh.edges_unique
        sum_l2 = float(np.sum((v[e[:, 0]] - v[e[:, 1]]) ** 2))
        nmol = k_structural * inflation * (inflation - 1) * sum_l2 / (3 * GAS_CONSTANT * 293.15)
    obj = dict(name="ball", vertices=v, faces=f, k_structural=float(k_structural), damping=float(damping),
               nmol=float(nmol), total_weight=float(total_weight), translate=(0.0, float(height), 0.0),
               fixed=[int(np.argmax(v[:, 1]))])
    return format_scene([obj], gravity=(0.0, -9.81, 0.0), temperature=293.15,
                        header=f"fitting recovery scenario: level-{int(subdivisions)} icosphere ball pinned at its top")


def synthetic_recovery(subdivisions=3, noise=0.0, point_cloud=False, progress=True, *, factors=(2.0, 0.5, 2.0),
                       optimizer="lbfgs", iterations=60, steps=1600, save_every=20, dt=5e-4, seed=0, n_points=None,
                       checkpoint_path=None):
    """Recover k_structural, damping and nmol from a synthetic target (the issue's acceptance run).

    A target is simulated with known parameters (:data:`RECOVERY_TRUTH`), optionally with
    Gaussian noise of ``noise`` m per coordinate or as a point cloud sampled on the surface;
    the fit starts from the truth times ``factors`` (k x2, damping x0.5, nmol x2 by default).

    Returns:
      dict: true, start and fitted values, relative errors, wall time of the fit (s), loss,
      iterations, the identifiability summary, and the :class:`FitResult` ("result").
    """
    from jaxplush import fitting      # (fitting.fit: the package's lazy name, no import cycle)
    truth = recovery_scene_text(subdivisions)
    scene_true = jaxplush.parse_scene(truth, "<recovery truth>")
    t0 = time.perf_counter()
    target = _make_recovery_target(scene_true, steps, dt, save_every, noise, point_cloud, n_points, seed)
    t_target = time.perf_counter() - t0
    true_vals = {n: float(getattr(scene_true.params, n)[0]) for n in ("k_structural", "damping", "nmol")}
    start_vals = {n: v * f for (n, v), f in zip(true_vals.items(), factors)}
    scene = jaxplush.parse_scene(recovery_scene_text(subdivisions, start_vals["k_structural"], start_vals["damping"],
                                                     start_vals["nmol"]), "<recovery start>")
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = fitting.fit(scene, target, ("k_structural", "damping", "nmol"), optimizer=optimizer, iterations=iterations,
                  noise_free=not noise, progress=progress, checkpoint_path=checkpoint_path, check_dt=False)
    wall = time.perf_counter() - t0
    fitted = {n: float(res.values[n][0]) for n in true_vals}
    errors = {n: fitted[n] / true_vals[n] - 1.0 for n in true_vals}
    return dict(vertices=scene.n_vertices, noise=noise, point_cloud=point_cloud, true=true_vals, start=start_vals,
                fitted=fitted, errors=errors, max_error=max(abs(e) for e in errors.values()), wall_time=wall,
                target_time=t_target, loss=res.loss, iterations=res.iterations, rejected=res.rejected,
                converged=res.converged, reason=res.reason, frames=target.n_frames, steps=steps, dt=dt,
                identifiability=res.identifiability.summary() if res.identifiability else "", result=res)


def _make_recovery_target(scene, steps, dt, save_every, noise, point_cloud, n_points, seed):
    from jaxplush.fitting.targets import make_target
    return make_target(scene, steps, dt, save_every, noise=noise, point_cloud=point_cloud,
                       n_points=n_points or (2 * scene.n_vertices if point_cloud else None), seed=seed)
