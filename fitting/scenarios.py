"""Drop scenarios for fitting benchmarks and tests: a plush dropped onto a floor.

:func:`drop_scene_text` writes a one-object scene (extended OBJ text): a ball (icosphere), a
torus lying flat, or an elongated, slightly bent bean dropped tilted, with its lowest point
``height`` above a floor at y = 0, at rest, with the report's per-step ``damping`` (or a dashpot
/ drag) and gas at a given rest pressure. ``benchmarks/bench_recovery.py`` fits these from
starts off by x0.5 / x2; the tests use small versions.
"""

from __future__ import annotations

import numpy as np

from jaxplush.types import GAS_CONSTANT

SHAPES = ("ball", "torus", "bean")
TEMPERATURE = 293.15


def shape_mesh(shape, subdivisions=3):
    """(vertices (V, 3), faces (F, 3)) of a shape about the origin, y up, about 0.2 m across.

    ``subdivisions`` sets the resolution like an icosphere's (level 3: 642 vertices; the torus
    has 32 x 20 = 640 at level 3 and 4x as many per level above).
    """
    import trimesh
    if shape == "ball":
        m = trimesh.creation.icosphere(subdivisions=int(subdivisions), radius=0.1)
        return np.asarray(m.vertices, np.float64), np.asarray(m.faces, np.int64)
    if shape == "torus":
        scale = 2 ** (int(subdivisions) - 3)
        m = trimesh.creation.torus(major_radius=0.08, minor_radius=0.035, major_sections=int(32 * scale),
                                   minor_sections=int(20 * scale))
        v = np.asarray(m.vertices, np.float64)[:, [0, 2, 1]]        # axis z -> y: lying flat
        f = np.asarray(m.faces, np.int64)[:, ::-1]                  # the swap mirrors: keep faces outward
        return v, f
    if shape == "bean":
        m = trimesh.creation.icosphere(subdivisions=int(subdivisions), radius=1.0)
        v = np.asarray(m.vertices, np.float64) * [0.12, 0.05, 0.06]
        v[:, 1] += 3.0 * v[:, 0] ** 2                                 # bent: a kidney bean
        return v, np.asarray(m.faces, np.int64)
    raise ValueError(f"unknown shape {shape!r}; expected one of {', '.join(SHAPES)}")


def _volume(v, f):
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    return float(np.sum(a * np.cross(b, c)) / 6.0)


def drop_scene_text(shape="ball", subdivisions=3, *, k_structural=420.0, damping=2000.0, dashpot=None, drag=None,
                    total_weight=0.12, pressure=1800.0, nmol=None, height=0.2, tilt_deg=0.0, floor_model=None,
                    name=None):
    """Scene text of a plush dropped onto a floor (y = 0).

    Args:
      shape: "ball", "torus" or "bean"; subdivisions: resolution (3: about 642 vertices).
      k_structural, damping, dashpot, drag, total_weight: the object's parameters (damping,
        dashpot or drag None: left out).
      pressure: rest gas pressure (Pa) that sets nmol = P V0 / (R T), unless ``nmol`` is given
        (both None: no gas).
      height: the lowest vertex's height above the floor at the start, m.
      tilt_deg: rotation about the z axis before the drop (a bean lands on one end first).
      floor_model: None (the scene default, projection) or a ``floor_model`` keyword value.
      name: object name (default: the shape).
    """
    from jaxplush.scene.write import format_scene
    v, f = shape_mesh(shape, subdivisions)
    if tilt_deg:
        t = np.radians(tilt_deg)
        rot = np.array([[np.cos(t), -np.sin(t), 0.0], [np.sin(t), np.cos(t), 0.0], [0.0, 0.0, 1.0]])
        v = v @ rot.T
    v = v - [0.0, v[:, 1].min() - height, 0.0]
    if nmol is None and pressure is not None:
        nmol = pressure * _volume(v, f) / (GAS_CONSTANT * TEMPERATURE)
    obj = dict(name=name or shape, vertices=v, faces=f, k_structural=float(k_structural),
               total_weight=float(total_weight), nmol=None if nmol is None else float(nmol))
    for key, val in (("damping", damping), ("dashpot", dashpot), ("drag", drag)):
        if val is not None:
            obj[key] = float(val)
    extra = {} if floor_model is None else {"floor_model": floor_model}
    return format_scene([obj], gravity=(0.0, -9.81, 0.0), floor=0.0, temperature=TEMPERATURE,
                        header=f"{shape} (level {int(subdivisions)}) dropped from {height:g} m onto a floor",
                        **extra)
