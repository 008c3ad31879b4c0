"""Write jaxplush scenes in the extended Wavefront OBJ format (numpy only, no jax).

The format (read by :func:`jaxplush.load_scene`; reference: docs/formats.md §2):

* Standard OBJ lines: ``v x y z``, ``f a b c`` (1-based vertex indices, *global* to the
  file), ``o NAME`` starts an object, ``#`` starts a comment. y is up.
* Per-object keywords, inside the object's block (``o NAME`` ... ``END_OBJECT``):
  ``k_structural K``, ``damping D``, ``dashpot C``, ``drag G``, ``total_weight M``,
  ``nmol N``, ``scale S``, ``translate X Y Z``, ``fixed I`` (1-based global index, may
  repeat), ``driven PATH I [I ...] [until T]`` (may repeat), ``k_region NAME K`` (one per face
  group), ``k_edge I J K`` (one per edge). ``g NAME`` lines between the ``f`` lines group the faces
  that follow (a bare ``g`` ends a group). ``END_OBJECT`` closes the object.
* Scene keywords, written at the top: ``gravity GX GY GZ``, ``floor H``, ``temperature T``,
  and the floor and contact keywords ``floor_model projection|smooth``, ``floor_stiffness K``,
  ``floor_friction MU``, ``floor_restitution E``, ``contact on|off``,
  ``self_collision on|off``, ``contact_stiffness K``, ``contact_thickness D``,
  ``contact_capacity N``, ``contact_friction MU`` (see :mod:`jaxplush.scene.parse`).

Objects are given in their own coordinates with 0-based *local* face and fixed indices;
:func:`format_scene` offsets them to 1-based global indices. Every float is written with
``repr`` (shortest round-trip form), so reading a file back gives bit-identical float64
values, and the rest lengths a simulator derives from it are exactly those intended here.

Each object block is laid out as: ``o NAME``, its parameters (``k_region`` lines last), its
``v`` lines, its ``f`` lines (with ``g`` lines where the face group changes), its ``k_edge`` lines,
its ``fixed`` lines, its ``driven`` lines, ``END_OBJECT``; a parser that needs vertices to exist
before ``fixed`` refers to them is therefore satisfied.

The writer checks what it can check cheaply (shapes, finite values, index ranges, parameter
signs, unknown keys) and raises ``ValueError``. It does **not** check that meshes are closed
and oriented; that is the parser's job (and ``scenes/make_scenes.py`` checks its own output).
"""

from __future__ import annotations

import math
import os
import tempfile
from collections.abc import Iterable, Mapping, Sequence

import numpy as np

__all__ = ["format_scene", "write_scene", "stiffness_keys", "OBJECT_KEYS"]

# Scalar per-object parameters in the order they are written, with the admissible range the
# parser (jaxplush.scene.parse) enforces: (key, check, message).
_SCALAR_PARAMS: tuple[tuple[str, object, str], ...] = (
    ("total_weight", lambda v: v > 0, "> 0"),
    ("k_structural", lambda v: v >= 0, ">= 0"),
    ("dashpot", lambda v: v >= 0, ">= 0"),
    ("drag", lambda v: v >= 0, ">= 0"),
    # Verlet damping: factor f = 1/D per step needs D >= 1; 0 means off.
    ("damping", lambda v: v == 0 or v >= 1, "0 (off) or >= 1"),
    ("nmol", lambda v: v > 0, "> 0 (leave nmol out, or None, for no gas)"),
    ("scale", lambda v: v > 0, "> 0"),
)

#: Every key an object dict may carry.
OBJECT_KEYS = frozenset(
    {"name", "vertices", "faces", "translate", "fixed", "driven", "groups", "k_region", "k_edge"}
    | {k for k, _, _ in _SCALAR_PARAMS}
)


def _num(x) -> str:
    """Shortest string that parses back to exactly ``float(x)``."""
    x = float(x)
    if not math.isfinite(x):
        raise ValueError(f"non-finite value {x!r}")
    return repr(x)


def _vec3(value, what: str) -> np.ndarray:
    arr = np.asarray(value, dtype=np.float64)
    if arr.shape != (3,):
        raise ValueError(f"{what} must be 3 numbers, got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{what} must be finite, got {arr.tolist()}")
    return arr


def _check_name(name, i: int) -> str:
    if not isinstance(name, str) or not name:
        raise ValueError(f"object {i}: 'name' must be a non-empty string, got {name!r}")
    if any(c.isspace() for c in name) or "#" in name:
        raise ValueError(f"object {i}: name {name!r} must not contain whitespace or '#'")
    return name


def _check_object(obj: Mapping, i: int):
    """Validate one object dict; return (name, vertices (n,3) f64, faces (f,3) i64, fixed list)."""
    if not isinstance(obj, Mapping):
        raise ValueError(f"object {i}: expected a dict, got {type(obj).__name__}")
    unknown = set(obj) - OBJECT_KEYS
    if unknown:
        raise ValueError(f"object {i}: unknown keys {sorted(unknown)}; allowed: {sorted(OBJECT_KEYS)}")
    for key in ("name", "vertices", "faces"):
        if obj.get(key) is None:
            raise ValueError(f"object {i}: missing required key {key!r}")
    name = _check_name(obj["name"], i)

    vertices = np.asarray(obj["vertices"], dtype=np.float64)
    if vertices.ndim != 2 or vertices.shape[1] != 3 or vertices.shape[0] == 0:
        raise ValueError(f"object {name!r}: vertices must have shape (n, 3) with n > 0, got {vertices.shape}")
    if not np.all(np.isfinite(vertices)):
        raise ValueError(f"object {name!r}: vertices contain non-finite values")

    faces_in = np.asarray(obj["faces"])
    if faces_in.ndim != 2 or faces_in.shape[1] != 3 or faces_in.shape[0] == 0:
        raise ValueError(f"object {name!r}: faces must have shape (f, 3) with f > 0, got {faces_in.shape}")
    if not np.issubdtype(faces_in.dtype, np.integer):
        raise ValueError(f"object {name!r}: faces must be integers, got dtype {faces_in.dtype}")
    faces = faces_in.astype(np.int64)
    n = vertices.shape[0]
    if faces.min() < 0 or faces.max() >= n:
        raise ValueError(
            f"object {name!r}: face indices must be 0-based local indices in [0, {n}), "
            f"got range [{faces.min()}, {faces.max()}]"
        )

    fixed = obj.get("fixed")
    fixed_list: list[int] = []
    if fixed is not None:
        for j in np.atleast_1d(np.asarray(fixed)).ravel().tolist():
            if isinstance(j, bool) or int(j) != j:
                raise ValueError(f"object {name!r}: fixed indices must be integers, got {j!r}")
            j = int(j)
            if not 0 <= j < n:
                raise ValueError(f"object {name!r}: fixed index {j} outside [0, {n}) (0-based local)")
            fixed_list.append(j)

    for key, check, msg in _SCALAR_PARAMS:
        val = obj.get(key)
        if val is None:
            continue
        try:
            fval = float(val)
        except (TypeError, ValueError):
            raise ValueError(f"object {name!r}: {key} must be a number, got {val!r}") from None
        if not (math.isfinite(fval) and check(fval)):
            raise ValueError(f"object {name!r}: {key} must be finite and {msg}, got {val!r}")
    if obj.get("translate") is not None:
        _vec3(obj["translate"], f"object {name!r}: translate")
    _check_driven(obj.get("driven"), name, n)
    _check_stiffness(obj, name, faces)
    return name, vertices, faces, fixed_list


def _check_stiffness(obj, name, faces):
    """Validate an object's face ``groups`` (one name or None per face), ``k_region`` (group name
    -> stiffness) and ``k_edge`` (one stiffness per edge of :func:`jaxplush.model.mesh.unique_edges`
    of its faces)."""
    groups = obj.get("groups")
    names = set()
    if groups is not None:
        groups = list(groups)
        if len(groups) != len(faces):
            raise ValueError(f"object {name!r}: groups must name a group (or None) for each of its {len(faces)} "
                             f"faces, got {len(groups)}")
        for g in groups:
            if g is None:
                continue
            if not isinstance(g, str) or not g or any(c.isspace() for c in g) or "#" in g:
                raise ValueError(f"object {name!r}: face group name {g!r} must be a non-empty string without "
                                 "whitespace or '#'")
            names.add(g)
    for g, v in (obj.get("k_region") or {}).items():
        if g not in names:
            raise ValueError(f"object {name!r}: k_region names {g!r}, which is not one of its face groups")
        if not (math.isfinite(float(v)) and float(v) >= 0):
            raise ValueError(f"object {name!r}: k_region {g!r} must be finite and >= 0, got {v!r}")
    if obj.get("k_edge") is not None:
        from jaxplush.model.mesh import unique_edges
        k = np.asarray(obj["k_edge"], np.float64)
        n_e = len(unique_edges(faces))
        if k.shape != (n_e,):
            raise ValueError(f"object {name!r}: k_edge must hold one stiffness per edge ({n_e},), got {k.shape}")
        if not (np.all(np.isfinite(k)) and np.all(k >= 0)):
            raise ValueError(f"object {name!r}: k_edge values must be finite and >= 0")


def _check_driven(driven, name, n):
    """Validate an object's ``driven`` entries: dicts with ``path`` (str without whitespace),
    ``vertices`` (0-based local indices) and optionally ``until`` (> 0)."""
    for d in driven or ():
        if not isinstance(d, Mapping) or set(d) - {"path", "vertices", "until"} or "path" not in d:
            raise ValueError(f"object {name!r}: each driven entry must be a dict with 'path', 'vertices' and "
                             f"optionally 'until', got {d!r}")
        path = os.fspath(d["path"])
        if not path or any(c.isspace() for c in path) or "#" in path:
            raise ValueError(f"object {name!r}: driven path {path!r} must be non-empty, without whitespace or '#'")
        idx = np.atleast_1d(np.asarray(d.get("vertices"))).ravel().tolist()
        if not idx:
            raise ValueError(f"object {name!r}: a driven entry needs at least one vertex")
        for j in idx:
            if isinstance(j, bool) or int(j) != j or not 0 <= int(j) < n:
                raise ValueError(f"object {name!r}: driven index {j!r} outside [0, {n}) (0-based local)")
        until = d.get("until")
        if until is not None and not (math.isfinite(float(until)) and float(until) > 0):
            raise ValueError(f"object {name!r}: driven 'until' must be finite and > 0, got {until!r}")


def format_scene(
    objects: Sequence[Mapping],
    *,
    gravity: Iterable[float] | None = None,
    floor: float | None = None,
    temperature: float | None = None,
    header: str | None = None,
    floor_friction: float | None = None,
    floor_restitution: float | None = None,
    contact: bool | None = None,
    self_collision: bool | None = None,
    contact_stiffness: float | None = None,
    contact_thickness: float | None = None,
    contact_capacity: int | None = None,
    contact_friction: float | None = None,
    floor_model: str | None = None,
    floor_stiffness: float | None = None,
) -> str:
    """Return the text of a scene file.

    Args:
      objects: list of dicts. Required keys: ``name`` (str without whitespace),
        ``vertices`` ((n, 3) floats, object coordinates), ``faces`` ((f, 3) ints, 0-based
        local). Optional keys (``None`` or absent = not written): ``k_structural``,
        ``damping``, ``dashpot``, ``drag``, ``total_weight``, ``nmol``, ``scale``,
        ``translate`` (3 floats), ``fixed`` (0-based local vertex indices), ``driven`` (a list
        of dicts ``path`` (the path file as the scene should name it: relative to the scene
        file's directory, or absolute), ``vertices`` (0-based local indices) and optionally
        ``until`` (release time, s)), ``groups`` (one face group name, or None, per face),
        ``k_region`` (a dict group name -> stiffness), ``k_edge`` ((E_o,) the stiffness of every
        edge of the object, in the order of :func:`jaxplush.model.mesh.unique_edges` of its
        faces; a ``k_edge`` line is written for each edge whose value differs from what
        k_structural and k_region give it). :func:`stiffness_keys` makes the last four from a
        scene and a (per-object or per-edge) k. Ranges are
        those the parser accepts: ``nmol > 0`` (omit it for no gas), ``damping`` 0 or >= 1.
      gravity: scene gravity (3 floats), or None to leave the parser's default.
      floor: height of the floor plane y = floor, or None for no floor.
      temperature: gas temperature in K, or None for the parser's default.
      header: free text written first, each line prefixed with ``# ``.
      floor_friction, floor_restitution: floor Coulomb coefficient (>= 0) and restitution
        (in [0, 1]); they need a ``floor``.
      contact, self_collision: write ``contact on|off`` / ``self_collision on|off``.
      contact_stiffness (N/m, > 0), contact_thickness (m, > 0), contact_capacity (int >= 1):
        override the contact defaults. None leaves any of these out (the parser's default).
      contact_friction: Coulomb coefficient between objects (>= 0).
      floor_model: "projection" or "smooth" (needs a ``floor``); floor_stiffness: the smooth
        floor's stiffness per vertex (N/m, > 0).

    Returns:
      The file contents (ends with a newline).

    Raises:
      ValueError: on malformed input (shapes, indices, non-finite or out-of-range values,
        unknown keys, duplicate object names).
    """
    if isinstance(objects, Mapping):
        raise ValueError("objects must be a list of dicts, not a single dict")
    objects = list(objects)
    if not objects:
        raise ValueError("a scene needs at least one object")

    lines = _header_lines(header)
    scene_lines = _scene_lines(
        gravity=gravity, floor=floor, temperature=temperature, floor_friction=floor_friction,
        floor_restitution=floor_restitution, contact=contact, self_collision=self_collision,
        contact_stiffness=contact_stiffness, contact_thickness=contact_thickness,
        contact_capacity=contact_capacity, contact_friction=contact_friction, floor_model=floor_model,
        floor_stiffness=floor_stiffness)
    if scene_lines:
        lines.extend(scene_lines)
        lines.append("")

    seen: set[str] = set()
    offset = 0  # number of vertices written so far (global index base)
    for i, obj in enumerate(objects):
        name, vertices, faces, fixed = _check_object(obj, i)
        if name in seen:
            raise ValueError(f"duplicate object name {name!r}")
        seen.add(name)
        lines.extend(_object_lines(obj, name, vertices, faces, fixed, offset))
        offset += vertices.shape[0]

    return "\n".join(lines).rstrip("\n") + "\n"


def _header_lines(header) -> list[str]:
    """The header's lines as comments, then a blank line (none without a header)."""
    lines: list[str] = []
    if header:
        for hl in header.splitlines():
            hl = hl.rstrip()
            lines.append(f"# {hl}" if hl else "#")
        lines.append("")
    return lines


def _scene_lines(*, gravity, floor, temperature, floor_friction, floor_restitution, contact, self_collision,
                 contact_stiffness, contact_thickness, contact_capacity, contact_friction, floor_model,
                 floor_stiffness) -> list[str]:
    """The checked scene keyword lines of :func:`format_scene` (its arguments of the same names)."""
    scene_lines = []
    if gravity is not None:
        g = _vec3(gravity, "gravity")
        scene_lines.append("gravity " + " ".join(_num(c) for c in g))
    if floor is not None:
        scene_lines.append(f"floor {_num(floor)}")
    if temperature is not None:
        t = float(temperature)
        if not (math.isfinite(t) and t > 0):
            raise ValueError(f"temperature must be finite and > 0 K, got {temperature!r}")
        scene_lines.append(f"temperature {_num(t)}")
    for key, val, ok, msg in (
            ("floor_friction", floor_friction, lambda v: v >= 0, ">= 0"),
            ("floor_restitution", floor_restitution, lambda v: 0 <= v <= 1, "in [0, 1]"),
            ("contact_stiffness", contact_stiffness, lambda v: v > 0, "> 0"),
            ("contact_thickness", contact_thickness, lambda v: v > 0, "> 0"),
            ("contact_friction", contact_friction, lambda v: v >= 0, ">= 0"),
            ("floor_stiffness", floor_stiffness, lambda v: v > 0, "> 0")):
        if val is None:
            continue
        v = float(val)
        if not (math.isfinite(v) and ok(v)):
            raise ValueError(f"{key} must be finite and {msg}, got {val!r}")
        if key.startswith("floor_") and floor is None:
            raise ValueError(f"{key} needs a floor")
        scene_lines.append(f"{key} {_num(v)}")
    if floor_model is not None:
        if floor_model not in ("projection", "smooth"):
            raise ValueError(f"floor_model must be 'projection' or 'smooth', got {floor_model!r}")
        if floor is None:
            raise ValueError("floor_model needs a floor")
        scene_lines.append(f"floor_model {floor_model}")
    if contact_capacity is not None:
        if isinstance(contact_capacity, bool) or int(contact_capacity) != contact_capacity or contact_capacity < 1:
            raise ValueError(f"contact_capacity must be an integer >= 1, got {contact_capacity!r}")
        scene_lines.append(f"contact_capacity {int(contact_capacity)}")
    for key, val in (("contact", contact), ("self_collision", self_collision)):
        if val is not None:
            scene_lines.append(f"{key} {'on' if val else 'off'}")
    return scene_lines


def _object_lines(obj: Mapping, name: str, vertices, faces, fixed, offset: int) -> list[str]:
    """One checked object's block (``o NAME`` ... ``END_OBJECT`` and a blank line), its vertices
    numbered from ``offset`` + 1."""
    lines = [f"o {name}"]
    for key, _, _ in _SCALAR_PARAMS:
        if obj.get(key) is not None:
            lines.append(f"{key} {_num(obj[key])}")
    if obj.get("translate") is not None:
        t = _vec3(obj["translate"], "translate")
        lines.append("translate " + " ".join(_num(c) for c in t))
    for g, v in (obj.get("k_region") or {}).items():
        lines.append(f"k_region {g} {_num(v)}")
    lines.extend(f"v {_num(x)} {_num(y)} {_num(z)}" for x, y, z in vertices.tolist())
    groups = obj.get("groups")
    if groups is None:
        lines.extend(f"f {a} {b} {c}" for a, b, c in (faces + (offset + 1)).tolist())
    else:
        current = None
        for g, (a, b, c) in zip(groups, (faces + (offset + 1)).tolist()):
            if g != current:
                lines.append("g" if g is None else f"g {g}")
                current = g
            lines.append(f"f {a} {b} {c}")
    lines.extend(_k_edge_lines(obj, faces, offset))
    lines.extend(f"fixed {j + offset + 1}" for j in fixed)
    for d in obj.get("driven") or ():
        idx = " ".join(str(int(j) + offset + 1) for j in np.atleast_1d(np.asarray(d["vertices"])).ravel().tolist())
        until = f" until {_num(d['until'])}" if d.get("until") is not None else ""
        lines.append(f"driven {os.fspath(d['path'])} {idx}{until}")
    lines.append("END_OBJECT")
    lines.append("")
    return lines


def _implied_field(obj, faces):
    """(E,) the stiffness an object's ``k_structural``, ``groups`` and ``k_region`` give its edges
    (the parser's rule: each edge the mean of its two faces')."""
    from jaxplush.model.mesh import edge_face_mean
    from jaxplush.scene.parse import DEFAULTS
    base = float(obj["k_structural"]) if obj.get("k_structural") is not None else DEFAULTS["k_structural"]
    region = {g: float(v) for g, v in (obj.get("k_region") or {}).items()}
    groups = obj.get("groups")
    groups = [None] * len(faces) if groups is None else list(groups)
    kf = np.asarray([region.get(g, base) if g is not None else base for g in groups], np.float64)
    return edge_face_mean(faces, kf)


def _k_edge_lines(obj, faces, offset):
    """``k_edge I J K`` lines for the edges whose ``k_edge`` value differs from what the object's
    k_structural and regions give it (written with repr: read back bit for bit)."""
    if obj.get("k_edge") is None:
        return []
    from jaxplush.model.mesh import unique_edges
    k = np.asarray(obj["k_edge"], np.float64)
    edges = unique_edges(faces)
    differ = np.nonzero(k != _implied_field(obj, faces))[0]
    return [f"k_edge {edges[e, 0] + offset + 1} {edges[e, 1] + offset + 1} {_num(k[e])}" for e in differ.tolist()]


def stiffness_keys(scene, i, k=None):
    """The object dict keys (``k_structural``, ``groups``, ``k_region``, ``k_edge``) that write
    object ``i`` of a :class:`jaxplush.scene.parse.Scene` with the spring stiffness ``k`` (default
    the scene's ``params.k_structural``): (O,) per object, or an (E,) field over ``scene.edges``.

    Face groups carry over. For a field, the object's k_structural and each group's k_region are
    the values most of the edges inside them have (the scene's own where no edge lies wholly
    inside), and ``k_edge`` holds the field, so :func:`format_scene` writes a ``k_edge`` line for
    each edge that differs from them: reading the file back gives the field bit for bit.
    """
    k = np.asarray(scene.params.k_structural if k is None else k, np.float64)
    fa, fb = scene.objects[i].face_slice
    fg = (np.full(fb - fa, -1) if scene.face_groups is None else np.asarray(scene.face_groups[fa:fb]))
    names = scene.group_names
    out = dict(groups=[names[g] if g >= 0 else None for g in fg.tolist()] if (fg >= 0).any() else None)
    if k.shape == (scene.n_objects,):
        out["k_structural"] = float(k[i])
        return out
    if k.shape != (len(scene.edges),):
        raise ValueError(f"k_structural of shape {k.shape}: expected ({scene.n_objects},) per object or "
                         f"({len(scene.edges)},) per edge")
    eo = scene.edge_object
    a, b = int(np.searchsorted(eo, i)), int(np.searchsorted(eo, i, side="right"))
    field = k[a:b]
    share = scene.region_edges()[a:b]                       # (E_i, G)
    own = scene.k_object[i] if scene.k_object is not None else float(np.mean(field))
    out["k_structural"] = _mode(field[share.sum(axis=1) == 0], own)
    region = {}
    for g in sorted(set(fg[fg >= 0].tolist())):
        scene_k = scene.k_region[g] if scene.k_region is not None else np.nan
        v = _mode(field[share[:, g] == 1.0], None if np.isnan(scene_k) else float(scene_k))
        if v is not None and (v != out["k_structural"] or not np.isnan(scene_k)):
            region[names[g]] = v
    out["k_region"] = region or None
    out["k_edge"] = field
    return out


def _mode(values, default):
    """The most common of ``values`` (the smallest on a tie), or ``default`` when there are none."""
    if not len(values):
        return default
    u, n = np.unique(values, return_counts=True)
    return float(u[np.argmax(n)])


def write_scene(path, objects: Sequence[Mapping], **kw) -> None:
    """Write :func:`format_scene` ``(objects, **kw)`` to ``path`` atomically.

    The text is formatted first (so invalid input never touches the disk), written to a
    temporary file in the destination directory, flushed and fsynced, then moved over
    ``path`` with ``os.replace``. Readers see either the old file or the complete new one.
    """
    text = format_scene(objects, **kw)
    path = os.fspath(path)
    directory = os.path.dirname(os.path.abspath(path))
    fd, tmp = tempfile.mkstemp(prefix="." + os.path.basename(path) + ".", suffix=".tmp", dir=directory)
    try:
        with os.fdopen(fd, "w", encoding="utf-8", newline="\n") as fh:
            fh.write(text)
            fh.flush()
            os.fsync(fh.fileno())
        # mkstemp creates the file 0600; give it the permissions a plain open() would.
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise
