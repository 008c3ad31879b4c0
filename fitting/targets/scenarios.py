"""Drop scenarios for fitting benchmarks and tests: a plush dropped onto a floor.

:func:`drop_scene_text` writes a one-object scene (extended OBJ text): a ball (icosphere), a
torus lying flat, an elongated, slightly bent bean dropped tilted, a cushion (a flattened
rounded box) or a capsule lying on its side, with its lowest point
``height`` above a floor at y = 0, at rest, with the report's per-step ``damping`` (or a dashpot
/ drag) and gas at a given rest pressure. ``benchmarks/bench_recovery.py`` fits these from
starts off by x0.5 / x2; the tests use small versions.

:func:`draw_case` draws a random scene (the shape, level and placement of 1 to 3 objects, the
damping model, a pinned or floor setting, floor friction, masses, heights, tilts, the target kind
and the start factors) from a numpy generator, deterministically; :func:`case_scene_text` writes
its truth scene and :func:`case_start_text` its start scene (numpy only: nothing is compiled).
``benchmarks/bench_recovery.py --random N`` fits them.
"""

from __future__ import annotations

import numpy as np

from jaxplush.types import GAS_CONSTANT

SHAPES = ("ball", "torus", "bean", "cushion", "capsule")
TEMPERATURE = 293.15


def shape_mesh(shape, subdivisions=3):
    """(vertices (V, 3), faces (F, 3)) of a shape about the origin, y up, about 0.2 m across.

    ``subdivisions`` sets the resolution like an icosphere's (level 3: 642 vertices; the torus
    has 32 x 20 = 640 at level 3 and 4x as many per level above; the capsule as the icosphere).
    The cushion is an icosphere pushed out onto a superellipsoid (|x|^4 + |y|^4 + |z|^4 = 1: a cube
    with rounded edges and corners), scaled to 0.24 x 0.10 x 0.24 m; the capsule is a cylinder of
    radius 0.05 m and length 0.12 m with hemispherical caps, lying along x.
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
    if shape == "cushion":
        m = trimesh.creation.icosphere(subdivisions=int(subdivisions), radius=1.0)
        n = np.asarray(m.vertices, np.float64)
        n = n / np.sum(n ** 4, axis=1, keepdims=True) ** 0.25            # onto |x|^4 + |y|^4 + |z|^4 = 1
        return n * [0.12, 0.05, 0.12], np.asarray(m.faces, np.int64)
    if shape == "capsule":
        # an ellipsoid icosphere projected onto the capsule from its axis segment: near-uniform
        # triangles (trimesh.creation.capsule's latitude-longitude mesh has a single band of
        # 0.12 m long triangles along the cylinder and 1.5 mm edges at the poles)
        r, half = 0.05, 0.06
        m = trimesh.creation.icosphere(subdivisions=int(subdivisions), radius=1.0)
        p = np.asarray(m.vertices, np.float64) * [r + half, r, r]
        c = np.zeros_like(p)
        c[:, 0] = np.clip(p[:, 0], -half, half)
        d = p - c
        return c + r * d / np.linalg.norm(d, axis=1, keepdims=True), np.asarray(m.faces, np.int64)
    raise ValueError(f"unknown shape {shape!r}; expected one of {', '.join(SHAPES)}")


def _volume(v, f):
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    return float(np.sum(a * np.cross(b, c)) / 6.0)


def drop_scene_text(shape="ball", subdivisions=3, *, k_structural=420.0, damping=2000.0, dashpot=None, drag=None,
                    total_weight=0.12, pressure=1800.0, nmol=None, height=0.2, tilt_deg=0.0, floor_model=None,
                    name=None):
    """Scene text of a plush dropped onto a floor (y = 0).

    Args:
      shape: one of :data:`SHAPES`; subdivisions: resolution (3: about 642 vertices).
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


# --------------------------------------------------------------------------------------------
# Random scenes (benchmarks/bench_recovery.py --random N --seed S; tests/test_recovery_random.py)

#: The damping models a random case draws from: the report's per-step ``damping``, the edge
#: ``dashpot``, air ``drag``, and mixes of two.
DAMPING_MODELS = ("damping", "dashpot", "drag", "damping+drag", "dashpot+drag", "damping+dashpot")
#: Target kinds: vertex positions (exact), or point clouds with 2 mm noise.
KINDS = ("positions", "points")
#: Mesh levels drawn (2: about 162 vertices, 3: about 642).
LEVELS = (2, 3)
#: Settings: dropped onto a floor (stacked when several objects), or hanging from a pinned vertex.
SETTINGS = ("floor", "pinned")
#: Ranges drawn, log-uniformly for the positive scale parameters.
RANGES = dict(k_structural=(250.0, 800.0), damping=(500.0, 4000.0), dashpot=(0.03, 0.2), drag=(0.5, 4.0),
              total_weight=(0.05, 0.3), pressure=(1000.0, 3000.0), start=(0.5, 2.0))
#: The fitted parameters of a case, in the order jaxplush-fit's default lists them.
_ORDER = ("k_structural", "damping", "dashpot", "drag", "nmol")

_MESHES = {}


def _mesh(shape, level):
    key = (shape, int(level))
    if key not in _MESHES:
        _MESHES[key] = shape_mesh(shape, level)
    return _MESHES[key]


def mesh_vertices(shape, level):
    """Vertex count of ``shape_mesh(shape, level)``."""
    return len(_mesh(shape, level)[0])


def _rotation(tilt_deg, yaw_deg):
    """Tilt about z, then yaw about y (a 3 x 3 matrix applied as v @ R.T)."""
    t, y = np.radians(tilt_deg), np.radians(yaw_deg)
    rz = np.array([[np.cos(t), -np.sin(t), 0.0], [np.sin(t), np.cos(t), 0.0], [0.0, 0.0, 1.0]])
    ry = np.array([[np.cos(y), 0.0, np.sin(y)], [0.0, 1.0, 0.0], [-np.sin(y), 0.0, np.cos(y)]])
    return ry @ rz


def _placed(obj):
    """The object's vertices as placed in the scene (rotated, then translated) and its faces."""
    v, f = _mesh(obj["shape"], obj["level"])
    return v @ _rotation(obj["tilt_deg"], obj["yaw_deg"]).T + obj["position"], f


def _r(x, digits=4):
    return float(f"{float(x):.{digits}g}")


def draw_case(rng, *, max_vertices=None, max_objects=3, kinds=KINDS, shapes=SHAPES, levels=LEVELS,
              settings=SETTINGS, damping_models=DAMPING_MODELS):
    """Draw one random case (a JSON-able dict) from the numpy generator ``rng``.

    The draw: a setting (a floor with probability 3/4, else hanging from pinned vertices), 1 to
    ``max_objects`` objects (uniformly), a damping model for the scene, a target kind, and per
    object a shape, a mesh level (among ``levels`` whose mesh has at most ``max_vertices``
    vertices), k_structural, the damping model's parameters, the mass and the gas pressure (drawn
    log-uniformly over :data:`RANGES`), a tilt (half the objects, up to 40 degrees) and a yaw. On
    a floor (floor friction 0.2-1 in half the cases) the objects are stacked: the lowest 2-25 cm
    above the floor, each next one 2-6 cm above the one below, its centre shifted by up to 3 cm,
    so that they land on each other; pinned objects hang in a row along x, 3-8 cm apart, each
    from its topmost vertex. Objects never overlap at the start (their bounding boxes are apart).
    Every fitted parameter (the scene's material parameters that are switched on: k_structural,
    the damping model's, nmol) of every object gets a start factor drawn log-uniformly in
    x0.5..x2. ``duration`` (s) is long enough for the top object to land and bounce.
    """
    shapes, levels = tuple(shapes), tuple(levels)
    setting = str(rng.choice(settings, p=[0.75, 0.25] if tuple(settings) == SETTINGS else None))
    n_obj = int(rng.integers(1, max_objects + 1))
    model = str(rng.choice(damping_models))
    kind = str(rng.choice(tuple(kinds)))
    friction = _r(rng.uniform(0.2, 1.0), 3) if setting == "floor" and rng.random() < 0.5 else None

    def logu(name):
        lo, hi = RANGES[name]
        return _r(np.exp(rng.uniform(np.log(lo), np.log(hi))))

    objects = []
    for i in range(n_obj):
        shape = str(rng.choice(shapes))
        ok = [lv for lv in levels if max_vertices is None or mesh_vertices(shape, lv) <= max_vertices]
        if not ok:
            raise ValueError(f"no mesh level of {shape} has at most {max_vertices} vertices (levels {levels})")
        level = int(rng.choice(ok))
        obj = dict(name=f"{shape}{i}", shape=shape, level=level, vertices=mesh_vertices(shape, level),
                   k_structural=logu("k_structural"), total_weight=logu("total_weight"),
                   pressure=_r(rng.uniform(*RANGES["pressure"])))
        for part in model.split("+"):
            obj[part] = logu(part)
        obj["tilt_deg"] = _r(rng.uniform(0.0, 40.0), 3) if rng.random() < 0.5 else 0.0
        obj["yaw_deg"] = _r(rng.uniform(0.0, 360.0), 3)
        obj["position"] = [0.0, 0.0, 0.0]
        objects.append(obj)
    # placement, from the rotated meshes' bounding boxes
    below = None
    for i, obj in enumerate(objects):
        v, _ = _placed(obj)
        lo, hi = v.min(0), v.max(0)
        centre = 0.5 * (lo + hi)
        if setting == "floor":
            base = rng.uniform(0.02, 0.25) if below is None else below + rng.uniform(0.02, 0.06)
            shift = (np.zeros(2) if i == 0 else rng.uniform(-0.03, 0.03, 2))
            pos = [shift[0] - centre[0], base - lo[1], shift[1] - centre[2]]
        else:
            left = 0.0 if below is None else below + rng.uniform(0.03, 0.08)
            pos = [left - lo[0], 0.5 - hi[1], -centre[2]]
        obj["position"] = [round(float(c), 4) for c in pos]
        v, _ = _placed(obj)
        below = float(v[:, 1].max() if setting == "floor" else v[:, 0].max())
        if setting == "pinned":
            obj["fixed"] = int(np.argmax(v[:, 1]))
    names = [n for n in _ORDER if n == "k_structural" or n == "nmol" or n in model.split("+")]
    start = {n: [_r(np.exp(rng.uniform(np.log(RANGES["start"][0]), np.log(RANGES["start"][1]))), 3)
                 for _ in objects] for n in names}
    if setting == "floor":
        top = max(_placed(o)[0][:, 1].min() for o in objects)
        duration = round(float(np.sqrt(2.0 * top / 9.81)) + 0.3, 2)
    else:
        duration = 0.5
    return dict(setting=setting, n_objects=n_obj, damping_model=model, kind=kind, floor_friction=friction,
                objects=objects, params=names, start=start, duration=duration, contact_capacity=None)


def _nmol(obj):
    v, f = _mesh(obj["shape"], obj["level"])
    return obj["pressure"] * _volume(v, f) / (GAS_CONSTANT * TEMPERATURE)


def case_truth(case):
    """{name: [value per object]} of the case's fitted parameters at the truth."""
    return {n: [_nmol(o) if n == "nmol" else float(o[n]) for o in case["objects"]] for n in case["params"]}


def describe_case(case):
    """One line: shapes and vertex counts, setting, friction, damping model, target kind."""
    objs = "+".join(f"{o['shape']}{o['vertices']}" for o in case["objects"])
    where = "pinned" if case["setting"] == "pinned" else "floor"
    if case.get("floor_friction"):
        where += f" mu {case['floor_friction']:g}"
    return f"{objs} {where} {case['damping_model']} {case['kind']}"


def case_scene_text(case, factors=None):
    """The scene text of ``case`` at its truth, or with each fitted parameter times ``factors``
    ({name: [factor per object]}, e.g. ``case["start"]``: the start scene)."""
    from jaxplush.scene.write import format_scene
    objects = []
    for j, o in enumerate(case["objects"]):
        v, f = _placed(o)
        obj = dict(name=o["name"], vertices=v, faces=f, k_structural=float(o["k_structural"]),
                   total_weight=float(o["total_weight"]), nmol=_nmol(o))
        for part in ("damping", "dashpot", "drag"):
            if part in o:
                obj[part] = float(o[part])
        if "fixed" in o:
            obj["fixed"] = [int(o["fixed"])]
        for n, fs in (factors or {}).items():
            obj[n] = obj[n] * float(fs[j])
        objects.append(obj)
    floor = 0.0 if case["setting"] == "floor" else None
    several = len(objects) > 1
    what = "start" if factors else "truth"
    return format_scene(objects, gravity=(0.0, -9.81, 0.0), floor=floor, temperature=TEMPERATURE,
                        floor_friction=case.get("floor_friction"), contact=True if several else None,
                        contact_capacity=case.get("contact_capacity") if several else None,
                        header=f"random case ({what}): {describe_case(case)}")


def case_start_text(case):
    """The scene text of ``case`` at its start values (every fitted parameter times its factor)."""
    return case_scene_text(case, case["start"])


# --------------------------------------------------------------------------------------------
# A plush sewn from panels, one patch of them stiff (benchmarks/bench_real_capture.py,
# tests/test_kfield_fit.py, docs/fitting.md "A stiffness field")

#: Panels of :func:`panel_ball`: the faces of the icosahedron the icosphere is subdivided from.
N_PANELS = 20


def panel_ball(subdivisions=3, radius=0.1):
    """(vertices (V, 3), faces (F, 3), panel (F,)) of an icosphere whose faces are grouped into the
    20 panels of the icosahedron it subdivides (each face on the base face its centroid lies over:
    4**subdivisions faces a panel), the faces sorted by panel, so that each panel is one block of
    ``f`` lines under its ``g`` line."""
    import trimesh
    m = trimesh.creation.icosphere(subdivisions=int(subdivisions), radius=float(radius))
    v, f = np.asarray(m.vertices, np.float64), np.asarray(m.faces, np.int64)
    c = v[f].mean(axis=1)
    panel = np.argmax(c @ _icosahedron_normals().T, axis=1)
    order = np.argsort(panel, kind="stable")
    return v, f[order], panel[order]


def _icosahedron_normals():
    import trimesh
    return np.asarray(trimesh.creation.icosahedron().face_normals, np.float64)


def patch_panels(direction=(0.0, 0.0, 1.0)):
    """The 4 panels of a contiguous patch covering 20% of the surface: the panel that faces
    ``direction`` and its three neighbours (sorted)."""
    import trimesh
    n = _icosahedron_normals()
    d = np.asarray(direction, np.float64)
    first = int(np.argmax(n @ (d / np.linalg.norm(d))))
    adj = trimesh.creation.icosahedron().face_adjacency
    return sorted([first] + [int(b if a == first else a) for a, b in adj if first in (a, b)])


def panel_scene_text(subdivisions=3, radius=0.1, *, k_soft=60.0, stiff=5.0, patch=(0.0, 0.0, 1.0),
                     total_weight=0.1, zeta=0.25, inflation=1.05, height=0.0, driven=None, name="plush",
                     header=None):
    """Scene text of a plush ball sewn from :func:`panel_ball`'s 20 panels (``g panelNN``), resting
    with its lowest point ``height`` above a floor at y = 0, with gas and an edge dashpot.

    Args:
      k_soft: the stiffness of the soft panels, N/m; ``stiff``: the patch's factor (the panels of
        :func:`patch_panels` of ``patch`` get ``k_region`` k_soft x stiff; 1 or None: no
        ``k_region`` lines, every panel at k_soft).
      total_weight: kg; zeta: the dashpot's damping ratio per soft spring, c = zeta sqrt(2 k_soft m);
      inflation: the free inflated size s* that sets nmol from k_soft (docs/model.md §8.5).
      driven: None, or a dict (path, until) that drives the top vertex along the path file.
    """
    from jaxplush.model.mesh import unique_edges
    from jaxplush.scene.write import format_scene
    v, f, panel = panel_ball(subdivisions, radius)
    edges = unique_edges(f)
    rest = np.linalg.norm(v[edges[:, 0]] - v[edges[:, 1]], axis=1)
    s = float(inflation)
    nmol = float(k_soft) * float(np.sum(rest ** 2)) * s * (s - 1.0) / (3.0 * GAS_CONSTANT * TEMPERATURE)
    dashpot = float(zeta) * float(np.sqrt(2.0 * k_soft * total_weight / len(v)))
    obj = dict(name=name, vertices=v, faces=f, total_weight=float(total_weight), k_structural=float(k_soft),
               dashpot=dashpot, nmol=nmol, translate=[0.0, float(height - v[:, 1].min()), 0.0],
               groups=[f"panel{p:02d}" for p in panel])
    if stiff is not None and stiff != 1:
        obj["k_region"] = {f"panel{p:02d}": float(k_soft * stiff) for p in patch_panels(patch)}
    if driven is not None:
        obj["driven"] = [dict(path=driven["path"], vertices=[int(np.argmax(v[:, 1]))], until=driven.get("until"))]
    text = header or (f"a plush ball of {len(v)} vertices sewn from {N_PANELS} panels"
                      + (f", the 4 facing {tuple(patch)} {stiff:g}x stiffer" if obj.get("k_region") else ""))
    return format_scene([obj], gravity=(0.0, -9.81, 0.0), floor=0.0, temperature=TEMPERATURE, header=text)
