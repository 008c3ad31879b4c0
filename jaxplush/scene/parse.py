"""Parse the report's extended Wavefront OBJ scene format (numpy only; never traced).

A scene file holds one or more objects. Standard OBJ geometry (``v``, ``f``, ``o``, ``g``;
``vt``, ``vn``, ``vp``, ``s``, ``usemtl``, ``mtllib`` are accepted and ignored) plus keywords.
``o NAME`` starts an object. ``g NAME`` inside an object opened by ``o`` starts a face group (the
faces after it, up to the next ``g``, belong to group NAME; a bare ``g`` ends the group); before
an object's ``o`` (or in a file without ``o``) it only names the object, as it always has.

Per object (they apply to the object they stand in; ``END_OBJECT`` closes it; a file with a
single object, or with objects separated by ``o`` lines, may omit it):
  ``k_structural K``  spring stiffness of every unique edge, N/m (>= 0; default 100)
  ``k_region NAME K`` stiffness of the faces of group NAME (a ``g NAME`` of this object), N/m
                      (>= 0); an edge's stiffness is the mean of its two faces' (the object's
                      k_structural outside any region); may repeat, once per group
  ``k_edge I J K``    stiffness of the edge between vertices I and J (indices as in ``f`` lines),
                      N/m (>= 0), overriding the regions; may repeat, once per edge
  ``damping D``       the report's Verlet damping, factor f = 1/D per step (D >= 1; 0 or
                      absent: none). Its physical meaning changes with dt (docs/model.md §5).
  ``dashpot C``       edge dashpot, N s/m (>= 0; default 0), dt-independent
  ``drag G``          mass-proportional air drag, 1/s (>= 0; default 0), dt-independent
  ``total_weight M``  mass in kg (> 0; default 1), split evenly over the object's vertices
  ``nmol N``          moles of ideal gas inside (> 0; absent: no gas)
  ``scale S``         uniform scale about the object's coordinate origin (> 0; default 1)
  ``translate X Y Z`` translation in m, applied after scale
  ``fixed I``         pin vertex I (an index as in ``f`` lines); may repeat
  ``driven PATH I [I ...] [until T]``  vertices I ... follow the path in file PATH (relative to
                      the scene file's directory; CSV or HDF5, jaxplush.scene.paths), until the
                      release time T if given; may repeat (docs/formats.md §2.7)

Scene level (anywhere, at most once each):
  ``gravity GX GY GZ`` m/s² (default 0 -9.81 0; y is up)
  ``floor H``          a horizontal floor at y = H facing up (none unless given)
  ``temperature T``    K (> 0; default 293.15)
  ``floor_friction MU``     Coulomb friction coefficient of the floor (>= 0; default 0: none)
  ``floor_restitution E``   floor restitution (0 <= E <= 1; default 0: vertices stop on impact)
  ``floor_model M``         ``projection`` (default: vertices are put back on the floor, an exact
                            non-penetration constraint with kinks) or ``smooth`` (a smooth
                            penalty energy, see jaxplush.model.forces; the floor for fitting)
  ``floor_stiffness K``     smooth floor's penalty stiffness per vertex, N/m (> 0; default
                            0.1 x 2 n_max k_structural of the object, scaling with k and mass)
  ``contact on|off``        soft-soft contact between objects (default on when there are several)
  ``self_collision on|off`` each object against its own faces (default off; O(N²), small meshes)
  ``contact_friction MU``   Coulomb friction between objects in contact (>= 0; default 0: none)
  ``contact_stiffness K``   contact penalty stiffness, N/m (> 0; default 0.1 x 2 n_max min(k_A, k_B),
                            which scales with the objects' stiffness and mass, see jaxplush.model.contact)
  ``contact_thickness D``   contact thickness, m (> 0; default half the finer mean edge length)
  ``contact_capacity N``    candidate vertices per object and pair (integer >= 1; default
                            max(96, n/12)); jaxplush.simulate reruns with a larger one if needed

An object's vertices are the vertices its faces use; indices in ``f`` and ``fixed`` are
1-based and global to the file, or negative (relative to the vertices defined so far).
Every problem raises :class:`jaxplush.errors.SceneError` naming file, line and problem.

With any ``k_region`` or ``k_edge`` line, ``Scene.params.k_structural`` is an (E,) per-edge field
in the order of ``Scene.edges`` (:meth:`Scene.stiffness_field`; objects without either have their
k_structural on every edge); without, it is (O,), one value per object.

Format: docs/formats.md §2 (every keyword, unit, default, valid range and rule).
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import math
import os
import re
import stat
import warnings

import numpy as np

from jaxplush.model import mesh as _mesh
from jaxplush.errors import SceneError, SceneWarning
from jaxplush.types import GAS_CONSTANT, Params

DEFAULTS = dict(k_structural=100.0, damping=0.0, dashpot=0.0, drag=0.0, total_weight=1.0, nmol=0.0)
DEFAULT_GRAVITY = (0.0, -9.81, 0.0)
DEFAULT_TEMPERATURE = 293.15

# keyword -> (number of values, check, message)
_OBJECT_KEYS = {
    "k_structural": (1, lambda v: v >= 0, "must be >= 0"),
    "damping": (1, lambda v: v == 0 or v >= 1, "must be 0 (off) or >= 1 (factor f = 1/D per step)"),
    "dashpot": (1, lambda v: v >= 0, "must be >= 0"),
    "drag": (1, lambda v: v >= 0, "must be >= 0"),
    "total_weight": (1, lambda v: v > 0, "must be > 0"),
    "nmol": (1, lambda v: v > 0, "must be > 0 (omit it for an object without gas)"),
    "scale": (1, lambda v: v > 0, "must be > 0"),
    "translate": (3, None, None),
}
_SCENE_KEYS = {
    "gravity": (3, None, None),
    "floor": (1, None, None),
    "temperature": (1, lambda v: v > 0, "must be > 0"),
    "floor_friction": (1, lambda v: v >= 0, "must be >= 0"),
    "floor_restitution": (1, lambda v: 0 <= v <= 1, "must be between 0 and 1"),
    "contact_friction": (1, lambda v: v >= 0, "must be >= 0"),
    "contact_stiffness": (1, lambda v: v > 0, "must be > 0 (N/m)"),
    "contact_thickness": (1, lambda v: v > 0, "must be > 0 (m)"),
    "contact_capacity": (1, lambda v: v >= 1 and v == int(v) and v < 2 ** 31, "must be an integer >= 1"),
    "floor_stiffness": (1, lambda v: v > 0, "must be > 0 (N/m)"),
}
_SWITCH_KEYS = ("contact", "self_collision")
#: Scene keywords that take one word from a fixed set.
_CHOICE_KEYS = {"floor_model": ("projection", "smooth")}
FLOOR_MODELS = _CHOICE_KEYS["floor_model"]
_IGNORED = {"vt", "vn", "vp", "s", "usemtl", "mtllib"}
_MAX_COORD = 1e30  # larger coordinates overflow the mesh checks (and float32 simulation)
#: Largest vertex index a scene may use (int32 index tables).
MAX_INDEX = 2 ** 31 - 1
#: Largest scene file read (bytes); a bigger one is refused before it is read.
MAX_FILE_BYTES = 2 ** 30


@dataclasses.dataclass(frozen=True)
class SceneObject:
    """One object of a scene.

    Attributes:
      name: object name (from ``o``/``g``, else ``object<i>``).
      vertex_slice: (start, stop) of its vertices in the scene's vertex array.
      face_slice: (start, stop) of its faces in the scene's face array.
      fixed: global (0-based, compacted) indices of its pinned vertices.
      has_gas: whether ``nmol`` was given.
      line: line where the object starts.
      driven: its :class:`DrivenPath` entries (one per ``driven`` line), in file order.
    """

    name: str
    vertex_slice: tuple
    face_slice: tuple
    fixed: tuple
    has_gas: bool
    line: int
    driven: tuple = ()

    @property
    def n_vertices(self):
        return self.vertex_slice[1] - self.vertex_slice[0]

    @property
    def n_faces(self):
        return self.face_slice[1] - self.face_slice[0]


@dataclasses.dataclass(frozen=True, eq=False)
class DrivenPath:
    """One ``driven PATH I [I ...] [until T]`` line: vertices that follow a prescribed path.

    Attributes:
      source: PATH as written in the scene (relative to the scene file's directory, or absolute).
      file: the path file it resolved to (absolute).
      vertices: global (0-based, compacted) scene indices of the driven vertices, in line order.
      times: (S,) float64 strictly increasing sample times, s.
      positions: (S, D, 3) float64 world positions of the D vertices at the samples, m.
      until: release time T, s (after it the vertices move freely), or None (driven throughout).
      line: the scene line.
    """

    source: str
    file: str
    vertices: tuple
    times: np.ndarray
    positions: np.ndarray
    until: float | None
    line: int

    def position(self, t):
        """(D, 3) positions at time ``t`` (numpy; linear between samples, held outside them)."""
        return np.stack([np.stack([np.interp(t, self.times, self.positions[:, d, c]) for c in range(3)])
                         for d in range(len(self.vertices))])


@dataclasses.dataclass(frozen=True, eq=False)
class Scene:
    """A loaded scene: geometry (already scaled and translated), parameters and settings.

    Attributes:
      path: file the scene came from (or "<string>").
      text: the full scene text, so a trajectory file alone reproduces its run.
      objects: tuple of :class:`SceneObject`.
      vertices: (V, 3) float64 positions, objects' vertices concatenated in order.
      faces: (F, 3) int32 outward-wound faces, 0-based global indices.
      params: :class:`jaxplush.types.Params` of (O,) float64 numpy arrays.
      gravity: (3,) float64, m/s².
      floor: floor height (y) or None.
      temperature: gas temperature, K.
      floor_friction, floor_restitution: floor Coulomb coefficient and restitution (0: none).
      contact, self_collision: soft-soft contact between objects / of each object with itself.
      contact_stiffness (N/m), contact_thickness (m), contact_capacity: None for the defaults
        of :mod:`jaxplush.model.contact`; contact_friction: Coulomb coefficient between objects (0: none).
      floor_model: "projection" (default) or "smooth" (a penalty force, :mod:`jaxplush.model.forces`);
      floor_stiffness: the smooth floor's stiffness per vertex (N/m), None for the default.
      face_groups: (F,) int32 the face group of every face (an index into ``group_names``; -1:
        none), from the ``g`` lines inside objects opened by ``o``.
      group_names: (G,) the face groups' names, object by object in order of first appearance
        (two objects may each have a group of one name: two groups); group_object: (G,) their
        objects.
      k_object: (O,) float64 the objects' ``k_structural`` values (the stiffness of their faces
        outside any ``k_region``).
      k_region: (G,) float64 each group's ``k_region`` stiffness, NaN where it has none.
      k_edge: ((edge index, stiffness), ...) the ``k_edge`` lines, edges indexed as :attr:`edges`.

    With any ``k_region`` or ``k_edge`` line, ``params.k_structural`` is the (E,) per-edge field
    :meth:`stiffness_field` (in the order of :attr:`edges`); otherwise it is (O,) = ``k_object``.
    """

    path: str
    text: str
    objects: tuple
    vertices: np.ndarray
    faces: np.ndarray
    params: Params
    gravity: np.ndarray
    floor: float | None
    temperature: float
    floor_friction: float = 0.0
    floor_restitution: float = 0.0
    contact: bool = True
    self_collision: bool = False
    contact_stiffness: float | None = None
    contact_thickness: float | None = None
    contact_capacity: int | None = None
    contact_friction: float = 0.0
    floor_model: str = "projection"
    floor_stiffness: float | None = None
    face_groups: np.ndarray | None = None
    group_names: tuple = ()
    group_object: tuple = ()
    k_object: np.ndarray | None = None
    k_region: np.ndarray | None = None
    k_edge: tuple = ()

    @property
    def n_objects(self):
        return len(self.objects)

    @property
    def n_vertices(self):
        return len(self.vertices)

    @property
    def object_names(self):
        return tuple(o.name for o in self.objects)

    @property
    def object_id(self):
        """(V,) int32 object index of every vertex."""
        ids = np.zeros(self.n_vertices, np.int32)
        for i, o in enumerate(self.objects):
            ids[o.vertex_slice[0]:o.vertex_slice[1]] = i
        return ids

    @property
    def fixed(self):
        """(P,) int32 global indices of all pinned vertices."""
        idx = [i for o in self.objects for i in o.fixed]
        return np.asarray(sorted(set(idx)), np.int32)

    @property
    def driven(self):
        """Tuple of every object's :class:`DrivenPath` entries (objects in order)."""
        return tuple(d for o in self.objects for d in o.driven)

    @property
    def driven_vertices(self):
        """(D,) int32 global indices of all driven vertices (in the order of :attr:`driven`)."""
        return np.asarray([i for d in self.driven for i in d.vertices], np.int32)

    @property
    def has_gas(self):
        return any(o.has_gas for o in self.objects)

    def volumes(self, x=None):
        """(O,) signed volume of every object at positions ``x`` (default: the scene's)."""
        x = self.vertices if x is None else np.asarray(x, np.float64)
        return np.array([
            _mesh.signed_volume(x, self.faces[o.face_slice[0]:o.face_slice[1]]) for o in self.objects])

    def rest_pressure(self):
        """(O,) gas pressure nRT/V at the scene's geometry, Pa (0 without gas)."""
        return np.asarray(self.params.nmol) * GAS_CONSTANT * self.temperature / self.volumes()

    def replace(self, **kw):
        return dataclasses.replace(self, **kw)

    # ----------------------------------------------------------------- spring stiffness field

    @functools.cached_property
    def edges(self):
        """(E, 2) int64 the springs: sorted unique edges i < j (:func:`jaxplush.model.mesh.unique_edges`),
        the order of a per-edge stiffness field (and of the simulator topology's ``edges``)."""
        return _mesh.unique_edges(self.faces)

    @property
    def edge_object(self):
        """(E,) int32 the object of every edge."""
        return self.object_id[self.edges[:, 0]]

    @property
    def has_k_field(self):
        """Whether ``params.k_structural`` is an (E,) per-edge field (not one value per object)."""
        k = np.shape(self.params.k_structural)
        return len(k) == 1 and k[0] != self.n_objects

    def _face_groups(self):
        return np.full(len(self.faces), -1, np.int32) if self.face_groups is None else self.face_groups

    def region_edges(self):
        """(E, G) float64 averaging matrix from per-group values to per-edge values: entry (e, g)
        is the share of edge e's adjacent faces (two on a closed mesh) that lie in group g, so
        0, 1/2 or 1. An edge's stiffness is the mean of its faces' (docs/formats.md §2.4): with
        r (G,) the groups' stiffnesses and k_o each object's, the field is
        ``A @ r + (1 - A.sum(1)) * k_o[edge_object]``, then the ``k_edge`` overrides
        (:meth:`stiffness_field`)."""
        faces = np.asarray(self.faces, np.int64)
        edges = self.edges
        half = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
        e = _mesh.edge_index(edges, half[:, 0], half[:, 1])
        g = np.tile(self._face_groups(), 3)
        count = np.bincount(e, minlength=len(edges)).astype(np.float64)
        a = np.zeros((len(edges), len(self.group_names)))
        on = g >= 0
        np.add.at(a, (e[on], g[on]), 1.0 / count[e[on]])
        return a

    def stiffness_field(self, k_structural=None, k_region=None, xp=np):
        """(E,) the per-edge stiffness field, N/m, in the order of :attr:`edges`: every face has its
        group's ``k_region`` value, or its object's ``k_structural`` outside any region; an
        edge has the mean of its faces' values, unless a ``k_edge`` line sets it.

        Args:
          k_structural: (O,) the objects' values (default :attr:`k_object`).
          k_region: (G,) the groups' values (default :attr:`k_region`); NaN: the object's value.
          xp: the array module: ``numpy`` (default, the parser's exact rule), or ``jax.numpy`` to
            build the field from traced, differentiable values (a fit per region), through
            :meth:`region_edges`.
        """
        k_obj = self.k_object if k_structural is None else k_structural
        if k_obj is None:
            k_obj = self.params.k_structural
        r = self.k_region if k_region is None else k_region
        if r is None:
            r = np.full(len(self.group_names), np.nan)
        go = np.asarray(self.group_object, np.int64)
        eo = self.edge_object
        if xp is np:
            k_obj, r = np.asarray(k_obj, np.float64), np.asarray(r, np.float64)
            r = np.where(np.isnan(r), k_obj[go], r)
            fg = self._face_groups()
            kf = np.where(fg >= 0, r[np.maximum(fg, 0)] if len(r) else 0.0, k_obj[self.object_id[self.faces[:, 0]]])
            field = _mesh.edge_face_mean(self.faces, kf, self.edges)
            for e, v in self.k_edge:
                field[e] = v
            return field
        k_obj, r = xp.asarray(k_obj), xp.asarray(r)
        r = xp.where(xp.isnan(r), k_obj[go], r)
        a = self.region_edges()
        field = xp.asarray(a, r.dtype) @ r + xp.asarray(1.0 - a.sum(axis=1), r.dtype) * k_obj[eo]
        if self.k_edge:
            idx = np.asarray([e for e, _ in self.k_edge])
            field = field.at[idx].set(xp.asarray([v for _, v in self.k_edge], field.dtype))
        return field

    @functools.cached_property
    def fingerprint(self):
        """Hex digest of everything a compiled step takes from the scene: geometry, topology,
        pins, gas, floor, contact and gravity settings; not the parameter values, names, path
        or text (:mod:`jaxplush.stepping.compiled`)."""
        h = hashlib.sha1()
        for a in (self.vertices, self.faces):
            a = np.ascontiguousarray(a)
            h.update(repr((a.dtype.str, a.shape)).encode())
            h.update(a.tobytes())
        settings = (tuple((o.vertex_slice, o.face_slice, tuple(o.fixed), o.has_gas) for o in self.objects),
                    tuple(np.asarray(self.gravity, np.float64).tolist()), self.floor, self.temperature,
                    self.floor_friction, self.floor_restitution, self.contact, self.self_collision,
                    self.contact_stiffness, self.contact_thickness, self.contact_capacity,
                    self.contact_friction, self.floor_model, self.floor_stiffness)
        h.update(repr(settings).encode())
        for d in self.driven:                    # the paths are constants of the compiled step
            h.update(repr((d.vertices, d.until, d.times.shape, d.positions.shape)).encode())
            h.update(np.ascontiguousarray(d.times, np.float64).tobytes())
            h.update(np.ascontiguousarray(d.positions, np.float64).tobytes())
        return h.hexdigest()


class _Groups:
    """Face groups of the objects read so far (:meth:`_Parser.object_groups`): per object its faces'
    group numbers (scene-wide, -1: none); every group's name, object and ``k_region`` (NaN: none);
    the ``k_edge`` lines (scene vertices)."""

    def __init__(self):
        self.faces, self.names, self.object, self.k, self.k_edge = [], [], [], [], []


class _Obj:
    """Parser state of one object while its block is read."""

    def __init__(self, line):
        self.line = line
        self.name = None
        self.o_line = None    # line of its 'o', if any
        self.faces = []       # (tokens, line, vertices before it), or blocks ((m, 3) 0-based, lines, -)
        self.blocks = False   # whether faces holds blocks read in bulk
        self.keys = {}        # keyword -> (values, line)
        self.fixed = []       # (0-based global index, line)
        self.driven = []      # (path token, [0-based global indices], until or None, line)
        self.groups = []      # face groups: ('g' line, name or None), in file order (after its 'o')
        self.k_region = {}    # group name -> (stiffness, line)
        self.k_edge = []      # (0-based global i, j, stiffness, line)


def load_scene(path):
    """Read and validate a scene file.

    Args:
      path: path of an extended-OBJ scene.

    Returns:
      :class:`Scene`.

    Raises:
      SceneError: naming file, line and problem.
    """
    path = os.fspath(path)
    try:
        st = os.stat(path)
        if stat.S_ISDIR(st.st_mode):
            raise IsADirectoryError
        if not stat.S_ISREG(st.st_mode):
            # a device (/dev/zero, /dev/urandom), a FIFO or a socket: reading it may never end
            raise SceneError(path, None, "not a regular file (a device, pipe or socket); give a scene file")
        if st.st_size > MAX_FILE_BYTES:
            raise SceneError(path, None, f"too large ({st.st_size / 2 ** 20:.0f} MiB; at most "
                                         f"{MAX_FILE_BYTES / 2 ** 20:.0f} MiB)")
        with open(path, "rb") as fh:
            data = fh.read(MAX_FILE_BYTES + 1)
    except FileNotFoundError:
        raise SceneError(path, None, "no such file") from None
    except IsADirectoryError:
        raise SceneError(path, None, "is a directory, not a scene file") from None
    except OSError as e:
        raise SceneError(path, None, f"cannot read: {e.strerror}") from None
    return parse_scene(data, path)


def parse_scene(data, path="<string>"):
    """Parse scene text (str or bytes). See :func:`load_scene`."""
    if isinstance(data, bytes):
        nul = data.find(b"\0")
        if nul >= 0:
            raise SceneError(path, data.count(b"\n", 0, nul) + 1,
                             f"binary data (NUL byte at offset {nul}); not a text OBJ scene")
        try:
            text = data.decode("utf-8")
        except UnicodeDecodeError as e:
            raise SceneError(path, data.count(b"\n", 0, e.start) + 1,
                             f"not UTF-8 text (byte 0x{data[e.start]:02x} at offset {e.start}); "
                             "not a text OBJ scene") from None
    else:
        text = data
    if text.startswith("\ufeff"):
        text = text[1:]
    return _Parser(path, text).run()


def _number(path, lineno, key, tok):
    try:
        v = float(tok)
    except ValueError:
        raise SceneError(path, lineno, f"'{key}' expects a number, got {tok!r}") from None
    if not math.isfinite(v):
        raise SceneError(path, lineno, f"'{key}' value {tok!r} is not finite")
    return v


class _Parser:
    def __init__(self, path, text):
        self.path = path
        self.text = text
        # vertices in file order, as chunks: ("t", [token lists], [lines]) from the line-by-line
        # path (converted in build()), ("a", (m, 3) float64, (m,) lines) from the bulk path
        self.vchunks = []
        self.nv = 0
        self.objects = []
        self.cur = None
        self.scene_keys = {}

    def err(self, line, msg):
        return SceneError(self.path, line, msg)

    def obj(self, line):
        if self.cur is None:
            self.cur = _Obj(line)
        return self.cur

    def close(self, line):
        if self.cur is None:
            return
        if not self.cur.faces:
            what = f" ({self.cur.name!r}, begun on line {self.cur.line})" if self.cur.name else ""
            raise self.err(self.cur.line if line is None else line, "object has no faces" + what)
        self.objects.append(self.cur)
        self.cur = None

    def resolve(self, tok, key, lineno, n_defined=None):
        """0-based index of an OBJ vertex index token (negative: relative to the ``n_defined``
        vertices defined before its line, default all so far)."""
        n_defined = self.nv if n_defined is None else n_defined
        try:
            i = int(tok)
        except ValueError:
            raise self.err(lineno, f"'{key}' expects a vertex index, got {tok!r}") from None
        if i == 0:
            raise self.err(lineno, f"'{key}': vertex index 0 is invalid (OBJ indices start at 1)")
        if abs(i) > MAX_INDEX:
            raise self.err(lineno, f"'{key}': vertex index {i} out of range (a scene holds at most {MAX_INDEX} "
                                   "vertices)")
        if i < 0:
            j = n_defined + i
            if j < 0:
                raise self.err(lineno, f"'{key}': relative index {i} points before the first vertex "
                                       f"(only {n_defined} defined so far)")
            return j
        return i - 1

    def face_indices(self, o):
        """(F, 3) int64 0-based global indices of an object's faces (polygons fan-triangulated) and
        (F,) their lines, in file order. Blocks read by :meth:`bulk` are arrays already; the rest
        go through :meth:`_face_entries`."""
        if not o.blocks:
            return self._face_entries(o.faces)
        parts, part_lines, slow = [], [], []
        for entry in o.faces + [None]:
            if entry is None or isinstance(entry[0], np.ndarray):
                if slow:
                    a, ln = self._face_entries(slow)
                    parts.append(a)
                    part_lines.append(ln)
                    slow = []
                if entry is not None:
                    parts.append(entry[0])
                    part_lines.append(entry[1])
            else:
                slow.append(entry)
        if len(parts) == 1:
            return parts[0], part_lines[0]
        return np.concatenate(parts), np.concatenate(part_lines)

    def _face_entries(self, entries):
        """face_indices of line-by-line entries (tokens, line, vertices defined before it). Plain
        triangles convert in bulk; anything else (v/vt/vn forms, polygons, relative indices, bad
        tokens) line by line, with the exact error."""
        toks = [a for a, _, _ in entries]
        lines = np.asarray([ln for _, ln, _ in entries], np.int64)
        if all(len(a) == 3 for a in toks):
            try:
                arr = np.array(toks, dtype=np.int64)
            except (ValueError, OverflowError):
                arr = None
            if arr is not None and (arr > 0).all() and (arr <= MAX_INDEX).all():
                return arr - 1, lines
        out, out_lines = [], []
        for args, ln, n_def in entries:
            idx = [self.resolve(t.split("/")[0], "f", ln, n_def) for t in args]
            for k in range(1, len(idx) - 1):  # fan-triangulate polygons
                out.append((idx[0], idx[k], idx[k + 1]))
                out_lines.append(ln)
        return np.asarray(out, np.int64).reshape(-1, 3), np.asarray(out_lines, np.int64)

    def vertex_array(self):
        """(N, 3) float64 of every 'v' line, converted in bulk (a bad value: its line's error)."""
        out = []
        for kind, data, lines in self.vchunks:
            if kind == "a":
                out.append(data)
                continue
            try:
                raw = np.array(data, dtype=np.float64).reshape(-1, 3)
            except ValueError:
                raw = None
            if raw is None or not np.isfinite(raw).all():
                for toks, ln in zip(data, lines):
                    for t in toks:
                        _number(self.path, ln, "v", t)          # raises with the line
            out.append(raw)
        return np.concatenate(out) if out else np.zeros((0, 3))

    def vertex_lines(self):
        """(N,) int64 line of every vertex."""
        return np.concatenate([np.asarray(lines, np.int64) for _, _, lines in self.vchunks] or [np.zeros(0, np.int64)])

    def bulk(self, lines, a, b, key):
        """Read lines[a:b], every one starting with ``key`` ('v' or 'f') and a blank, as one block:
        plain 'v x y z' or 'f i j k' (positive indices) lines only, converted with Python's own
        float/int, so the values are those of the line-by-line path. Returns False, having stored
        nothing, for anything else in the block (comments, other token counts, v/vt/vn forms,
        relative or huge indices, bad or non-finite numbers): the block is then read line by
        line, which reports the exact line and problem."""
        m = b - a
        joined = " ".join(lines[a:b])
        if "#" in joined:
            return False
        toks = joined.split()
        if len(toks) != 4 * m or toks[0::4].count(key) != m:
            return False
        try:
            if key == "v":
                cols = [np.fromiter(map(float, toks[c::4]), np.float64, m) for c in (1, 2, 3)]
            else:
                cols = [np.fromiter(map(int, toks[c::4]), np.int64, m) for c in (1, 2, 3)]
        except (ValueError, OverflowError):
            return False
        arr = np.stack(cols, axis=1)
        line_nos = np.arange(a + 1, b + 1, dtype=np.int64)
        if key == "v":
            if not np.isfinite(arr).all():
                return False
            self.vchunks.append(("a", arr, line_nos))
            self.nv += m
        else:
            if not ((arr > 0).all() and (arr <= MAX_INDEX).all()):
                return False
            o = self.cur or self.obj(a + 1)
            o.faces.append((arr - 1, line_nos, self.nv))
            o.blocks = True
        return True

    #: Runs of at least this many 'v' (or 'f') lines are read as blocks (:meth:`bulk`).
    BULK_MIN = 32

    def segments(self, lines):
        """(start, end, key) covering lines in order: runs of >= BULK_MIN lines starting "v " or
        "f " (key 'v' or 'f', for :meth:`bulk`) and what lies between them (key None)."""
        n = len(lines)
        runs = []
        if n >= self.BULK_MIN and "\r" not in self.text:
            # the first two characters of every line, from the UTF-8 bytes (a newline byte never
            # occurs inside a multi-byte character, so the lines are the same)
            b = np.frombuffer(self.text.encode("utf-8", "surrogatepass") + b"\0\0", np.uint8)
            starts = np.concatenate([[0], np.flatnonzero(b == 10) + 1])
            c0, c1 = b[starts], b[starts + 1]
            for key in ("v", "f"):
                flag = (c0 == ord(key)) & (c1 == 32)
                edges = np.diff(np.concatenate([[0], flag.astype(np.int8), [0]]))
                runs += [(int(a), int(b), key) for a, b in zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1))
                         if b - a >= self.BULK_MIN]
        out, pos = [], 0
        for a, b, key in sorted(runs):
            if a > pos:
                out.append((pos, a, None))
            out.append((a, b, key))
            pos = b
        if pos < n or not out:
            out.append((pos, n, None))
        return out

    def run(self):
        # Only \n, \r\n and \r end a line (str.splitlines would also split at form feeds, \x1c-\x1e,
        # U+0085, U+2028..., even inside comments, and so miscount lines).
        text = self.text
        lines = text.split("\n") if "\r" not in text else re.split(r"\r\n|\r|\n", text)
        vertices, vertex_line = [], []
        for seg_start, seg_end, run_key in self.segments(lines):
            if run_key is not None:
                if vertices and run_key == "v":         # keep file order: the line-by-line ones first
                    self.vchunks.append(("t", vertices, vertex_line))
                    vertices, vertex_line = [], []
                if self.bulk(lines, seg_start, seg_end, run_key):
                    continue
            self.read_lines(lines, seg_start, seg_end, vertices, vertex_line)
        if vertices:
            self.vchunks.append(("t", vertices, vertex_line))
        self.finish()
        return self.build()

    def read_lines(self, lines, start, end, vertices, vertex_line):
        """Read lines[start:end] line by line: the tokens of 'v' lines go to ``vertices`` (their
        line numbers to ``vertex_line``), 'f' lines to the current object, the rest to
        :meth:`keyword`."""
        add_vertex, add_vertex_line = vertices.append, vertex_line.append
        faces = None
        for lineno, raw in enumerate(lines[start:end], start + 1):
            if "#" in raw:
                raw = raw.split("#", 1)[0]
            toks = raw.split()
            if not toks:
                continue
            key = toks[0]
            # 'v' and 'f' lines are most of a file: stored as text, converted in bulk in build()
            if key == "v":
                n = len(toks)
                if n == 4:
                    del toks[0]
                    add_vertex(toks)
                elif n in (5, 7, 8):
                    add_vertex(toks[1:4])
                else:
                    raise self.err(lineno, f"'v' expects 3 coordinates, got {n - 1} value(s)")
                add_vertex_line(lineno)
                self.nv += 1
                continue
            if key == "f":
                if len(toks) < 4:
                    raise self.err(lineno, f"'f' needs at least 3 vertices, got {len(toks) - 1}")
                if faces is None or self.cur is None or faces is not self.cur.faces:
                    faces = (self.cur or self.obj(lineno)).faces
                del toks[0]
                faces.append((toks, lineno, self.nv))
                continue
            self.keyword(key, toks[1:], lineno)

    def keyword(self, key, args, lineno):
        """Apply one line other than 'v' and 'f': its keyword ``key`` and values ``args``."""
        if key == "g" and self.cur is not None and self.cur.o_line is not None:
            # inside an object opened by 'o': a face group (before any 'o': names the object)
            self.cur.groups.append((lineno, " ".join(args) if args else None))
        elif key in ("o", "g"):
            self.start_object(key, args, lineno)
        elif key == "k_region":
            self.k_region_line(args, lineno)
        elif key == "k_edge":
            self.k_edge_line(args, lineno)
        elif key == "END_OBJECT":
            if args:
                raise self.err(lineno, "'END_OBJECT' takes no values")
            if self.cur is None:
                raise self.err(lineno, "'END_OBJECT' without an open object (no faces since the last one)")
            self.close(lineno)
        elif key in _OBJECT_KEYS:
            vals = self.values(key, args, _OBJECT_KEYS[key], lineno)
            o = self.obj(lineno)
            if key in o.keys:
                raise self.err(lineno, f"'{key}' given twice for one object (first on line {o.keys[key][1]})")
            o.keys[key] = (vals, lineno)
        elif key == "fixed":
            if len(args) != 1:
                raise self.err(lineno, f"'fixed' expects 1 vertex index, got {len(args)} value(s)")
            self.obj(lineno).fixed.append((self.resolve(args[0], "fixed", lineno), lineno))
        elif key == "driven":
            self.driven_line(args, lineno)
        elif key in _SCENE_KEYS or key in _SWITCH_KEYS or key in _CHOICE_KEYS:
            self.scene_keyword(key, args, lineno)
        elif key not in _IGNORED:
            raise self.err(lineno, f"unknown keyword {key!r}")

    def k_region_line(self, args, lineno):
        """A ``k_region NAME K`` line: stored on the open object; the group is checked in
        :meth:`object_groups`."""
        if len(args) < 2:
            raise self.err(lineno, f"'k_region' expects a face group name and a stiffness (k_region NAME K), "
                                   f"got {len(args)} value(s)")
        value = _number(self.path, lineno, "k_region", args[-1])
        if not value >= 0:
            raise self.err(lineno, f"'k_region' {args[-1]} must be >= 0")
        name = " ".join(args[:-1])
        o = self.obj(lineno)
        if name in o.k_region:
            raise self.err(lineno, f"'k_region' of group {name!r} given twice for one object "
                                   f"(first on line {o.k_region[name][1]})")
        o.k_region[name] = (value, lineno)

    def k_edge_line(self, args, lineno):
        """A ``k_edge I J K`` line: stored on the open object; checked to be one of its edges in
        :meth:`stiffness_field`."""
        if len(args) != 3:
            raise self.err(lineno, f"'k_edge' expects 2 vertex indices and a stiffness (k_edge I J K), "
                                   f"got {len(args)} value(s)")
        i, j = (self.resolve(a, "k_edge", lineno) for a in args[:2])
        value = _number(self.path, lineno, "k_edge", args[2])
        if not value >= 0:
            raise self.err(lineno, f"'k_edge' {args[2]} must be >= 0")
        self.obj(lineno).k_edge.append((i, j, value, lineno))

    def driven_line(self, args, lineno):
        """A ``driven PATH I [I ...] [until T]`` line: stored on the open object; the file is read
        and the indices checked against the object in :meth:`object_driven`."""
        until = None
        if len(args) >= 2 and args[-2] == "until":
            until = _number(self.path, lineno, "driven", args[-1])
            if not until > 0:
                raise self.err(lineno, f"'driven' release time 'until {args[-1]}' must be > 0 s")
            args = args[:-2]
        if len(args) < 2:
            raise self.err(lineno, "'driven' expects a path file and at least 1 vertex index "
                                   "(driven PATH I [I ...] [until T])")
        idx = [self.resolve(a, "driven", lineno) for a in args[1:]]
        self.obj(lineno).driven.append((args[0], idx, until, lineno))

    def start_object(self, key, args, lineno):
        """An 'o' or 'g' line: a new 'o' after faces starts the next object; the name is set."""
        name = " ".join(args) if args else None
        if key == "o" and self.cur is not None:
            if self.cur.faces:
                self.close(lineno)  # a new 'o' after faces starts the next object
            elif self.cur.o_line is not None:  # else its keywords would silently go to the next one
                raise self.err(self.cur.o_line, f"object has no faces ({self.cur.name!r}: the next 'o' "
                                                f"on line {lineno} comes before any 'f' line)")
        o = self.obj(lineno)
        if key == "o":
            o.o_line = lineno
        if name and (o.name is None or key == "o"):
            o.name = name

    def scene_keyword(self, key, args, lineno):
        """A scene-level keyword line (numbers, an on/off switch or a choice), at most once each."""
        if key in _SCENE_KEYS:
            vals = self.values(key, args, _SCENE_KEYS[key], lineno)
            if key in self.scene_keys:
                raise self.err(lineno, f"'{key}' given twice (first on line {self.scene_keys[key][1]})")
            self.scene_keys[key] = (vals, lineno)
        elif key in _SWITCH_KEYS:
            if len(args) != 1 or args[0].lower() not in ("on", "off"):
                raise self.err(lineno, f"'{key}' expects 'on' or 'off', got {' '.join(args)!r}")
            if key in self.scene_keys:
                raise self.err(lineno, f"'{key}' given twice (first on line {self.scene_keys[key][1]})")
            self.scene_keys[key] = ([args[0].lower() == "on"], lineno)
        else:
            choices = _CHOICE_KEYS[key]
            if len(args) != 1 or args[0].lower() not in choices:
                raise self.err(lineno, f"'{key}' expects {' or '.join(repr(c) for c in choices)}, "
                                       f"got {' '.join(args)!r}")
            if key in self.scene_keys:
                raise self.err(lineno, f"'{key}' given twice (first on line {self.scene_keys[key][1]})")
            self.scene_keys[key] = ([args[0].lower()], lineno)

    def finish(self):
        """At the end of the text: close the last object; raise if there is none."""
        if self.cur is not None:
            if self.cur.faces:
                self.close(None)
            elif self.objects:
                raise self.err(self.cur.line, "keywords after the last END_OBJECT belong to no object "
                                              "(no faces follow)")
            else:
                self.close(None)
        if not self.objects:
            raise self.err(None, "empty scene: no objects (no 'f' lines)" if not self.nv
                           else "no faces: the scene defines vertices but no 'f' lines")

    def check_meshes(self, xs, faces, lines, objs):
        """Every object closed, manifold, orientable, one piece, with volume: all objects at once
        (:func:`jaxplush.model.mesh.orient_all`); an object with a defect is checked again on its own
        (:func:`jaxplush.model.mesh.check_and_orient`) for the exact face, line and message. Returns
        the (F, 3) global faces wound outward."""
        x = np.concatenate(xs)
        f = np.concatenate(faces)
        fo = np.repeat(np.arange(len(faces)), [len(a) for a in faces])
        out, bad = _mesh.orient_all(x, f, fo, len(faces))
        for oi in np.nonzero(bad)[0]:
            name, used, line = objs[oi]
            start = int(sum(len(a) for a in xs[:oi]))
            try:
                _mesh.check_and_orient(xs[oi], faces[oi] - start, labels=used + 1)
            except _mesh.MeshProblem as p:
                raise self.err(int(lines[oi][p.face]) if p.face is not None else line,
                                f"object {name!r}: {p.reason}") from None
            raise self.err(line, f"object {name!r}: the mesh is not a closed, manifold, consistently oriented "
                                 "surface enclosing a volume")
        return out

    def values(self, key, args, spec, lineno):
        count, check, msg = spec
        if len(args) != count:
            raise self.err(lineno, f"'{key}' expects {count} value(s), got {len(args)}")
        vals = [_number(self.path, lineno, key, t) for t in args]
        if check is not None and not check(vals[0]):
            raise self.err(lineno, f"'{key}' {args[0]} {msg}")
        return vals

    def build(self):
        nv = self.nv
        raw = self.vertex_array()
        vertex_line = self.vertex_lines()
        owner = np.full(nv, -1)
        all_x, all_local, all_lines, pending, objs = [], [], [], [], []
        params = {k: [] for k in DEFAULTS}
        vstart = fstart = 0
        groups = _Groups()
        for oi, o in enumerate(self.objects):
            name = o.name or f"object{oi}"
            idx, flines, used = self.object_faces(o, oi, name, owner, objs)
            local = np.searchsorted(used, idx)
            x = self.object_positions(o, name, raw, used, vertex_line)
            fixed = self.object_fixed(o, name, used, vstart)
            driven = self.object_driven(o, name, used, vstart, fixed)
            self.object_groups(o, oi, name, flines, groups)
            groups.k_edge += [(vstart + self.object_vertex(o, name, used, g, ln, "k_edge"),
                               vstart + self.object_vertex(o, name, used, h, ln, "k_edge"), v, ln, name, g + 1, h + 1)
                              for g, h, v, ln in o.k_edge]
            for k, d in DEFAULTS.items():
                params[k].append(o.keys[k][0][0] if k in o.keys else d)
            objs.append(SceneObject(name=name, vertex_slice=(vstart, vstart + len(used)),
                                    face_slice=(fstart, fstart + len(local)),
                                    fixed=tuple(sorted(set(fixed))), has_gas="nmol" in o.keys, line=o.line,
                                    driven=driven))
            pending.append((name, used, o.line))
            all_x.append(x)
            all_local.append(local + vstart)
            all_lines.append(flines)
            vstart += len(used)
            fstart += len(local)
        all_f = self.check_meshes(all_x, all_local, all_lines, pending)
        unused = int((owner < 0).sum())
        if unused:
            first = int(vertex_line[int(np.argmax(owner < 0))])
            warnings.warn(f"{self.path}:{first}: {unused} vertex/vertices not used by any face were ignored",
                          SceneWarning, stacklevel=3)
        first_use = {}
        for i, o in enumerate(objs):
            if o.name in first_use:
                src = self.objects[i]
                raise self.err(src.o_line or src.line, f"object name {o.name!r} used by more than one object")
            first_use[o.name] = i
        vertices = np.concatenate(all_x)
        settings = self.scene_settings(objs, vertices)
        params = {k: np.asarray(v, np.float64) for k, v in params.items()}
        k_object = params["k_structural"]
        face_groups = np.concatenate(groups.faces).astype(np.int32)
        k_edge = self.edge_overrides(all_f, groups.k_edge)
        scene = Scene(path=self.path, text=self.text, objects=tuple(objs), vertices=vertices,
                      faces=all_f.astype(np.int32), params=Params(**params), face_groups=face_groups,
                      group_names=tuple(groups.names), group_object=tuple(groups.object),
                      k_object=k_object, k_region=np.asarray(groups.k, np.float64), k_edge=k_edge, **settings)
        if len(k_edge) or not np.all(np.isnan(scene.k_region)):
            # k_region or k_edge lines: the stiffness is a field over the edges
            scene = scene.replace(params=scene.params._replace(k_structural=scene.stiffness_field()))
        return scene

    def object_vertex(self, o, name, used, g, ln, key):
        """The index among an object's vertices ``used`` of the file's vertex ``g`` (0-based), or
        an error on line ``ln`` naming ``key``."""
        j = np.searchsorted(used, g)
        if j >= len(used) or used[j] != g:
            raise self.err(ln, f"'{key}' vertex {g + 1} is not a vertex of object {name!r}")
        return int(j)

    def object_groups(self, o, oi, name, flines, groups):
        """Append object ``oi``'s face groups to ``groups`` (:class:`_Groups`): its faces' group
        numbers (their lines ``flines`` after which 'g' line), the groups' names and its
        ``k_region`` values, each checked to name one of its groups."""
        names = []
        for _, g in o.groups:
            if g is not None and g not in names:
                names.append(g)
        base = len(groups.names)
        if o.groups:
            starts = np.asarray([ln for ln, _ in o.groups], np.int64)
            ids = np.asarray([base + names.index(g) if g is not None else -1 for _, g in o.groups], np.int64)
            at = np.searchsorted(starts, np.asarray(flines, np.int64), side="right") - 1
            groups.faces.append(np.where(at >= 0, ids[np.maximum(at, 0)], -1))
        else:
            groups.faces.append(np.full(len(flines), -1, np.int64))
        for g, (_, ln) in o.k_region.items():
            if g not in names:
                have = (f"its groups: {', '.join(repr(n) for n in names)}" if names
                        else "it has no 'g' lines after its 'o' line")
                raise self.err(ln, f"'k_region': object {name!r} has no face group {g!r} ({have})")
        groups.names += names
        groups.object += [oi] * len(names)
        groups.k += [o.k_region[g][0] if g in o.k_region else np.nan for g in names]

    def edge_overrides(self, faces, entries):
        """((edge index, stiffness), ...) of the ``k_edge`` lines ``entries`` (scene vertex i, j,
        stiffness, line, object name, the file's 1-based i, j), each checked to be an edge of the
        scene's ``faces``, once."""
        if not entries:
            return ()
        edges = _mesh.unique_edges(faces)
        idx = _mesh.edge_index(edges, [e[0] for e in entries], [e[1] for e in entries])
        first = {}
        for e, (_, _, _, ln, name, a, b) in zip(idx.tolist(), entries):
            if e < 0:
                raise self.err(ln, f"'k_edge': vertices {a} and {b} are not joined by an edge of object {name!r}")
            if e in first:
                raise self.err(ln, f"'k_edge' of the edge between vertices {a} and {b} given twice "
                                   f"(first on line {first[e]})")
            first[e] = ln
        return tuple((int(e), float(entry[2])) for e, entry in zip(idx.tolist(), entries))

    def object_faces(self, o, oi, name, owner, objs):
        """(idx (F, 3) 0-based global indices of object ``oi``'s faces, their (F,) lines, used: the
        sorted vertices they use), after checking that the indices are in range and the vertices
        no earlier object's (``owner`` (V,): each vertex's object so far, -1 for none; updated)."""
        nv = self.nv
        idx, flines = self.face_indices(o)
        bad = idx >= nv
        if bad.any():
            r = int(np.argmax(bad.any(axis=1)))
            raise self.err(int(flines[r]), f"face index {int(idx[r][bad[r]][0]) + 1} out of range "
                                      f"(the file defines {nv} vertices)")
        used = np.unique(idx)
        shared = used[owner[used] >= 0]
        if len(shared):
            r = int(np.argmax((idx == shared[0]).any(axis=1)))
            raise self.err(int(flines[r]), f"object {name!r} uses vertex {shared[0] + 1}, which already "
                                      f"belongs to object {objs[owner[shared[0]]].name!r}")
        owner[used] = oi
        return idx, flines, used

    def object_positions(self, o, name, raw, used, vertex_line):
        """The positions of an object's vertices ``used`` (rows of ``raw``), scaled and translated,
        checked to stay below _MAX_COORD."""
        x = raw[used].copy()
        with np.errstate(over="ignore", invalid="ignore"):  # overflow is reported just below
            if "scale" in o.keys:
                x *= o.keys["scale"][0][0]
            if "translate" in o.keys:
                x += np.asarray(o.keys["translate"][0])
        huge = ~(np.abs(x) < _MAX_COORD)  # also catches overflow to inf; squares must stay finite
        if huge.any():
            i = int(np.argmax(huge.any(axis=1)))
            if not (np.abs(raw[used[i]]) < _MAX_COORD).all():
                raise self.err(int(vertex_line[used[i]]), f"vertex {used[i] + 1}: coordinate too large "
                                                          f"(|value| must be < {_MAX_COORD:g} m)")
            key = "scale" if "scale" in o.keys else "translate"
            raise self.err(o.keys[key][1], f"object {name!r}: coordinates too large after scale/translate "
                                           f"(|value| must be < {_MAX_COORD:g} m)")
        return x

    def object_fixed(self, o, name, used, vstart):
        """Scene indices of an object's 'fixed' vertices (its vertices ``used`` start at ``vstart``)."""
        fixed = []
        for g, ln in o.fixed:
            j = np.searchsorted(used, g)
            if j >= len(used) or used[j] != g:
                raise self.err(ln, f"'fixed' vertex {g + 1} is not a vertex of object {name!r}")
            fixed.append(vstart + int(j))
        return fixed

    def object_driven(self, o, name, used, vstart, fixed):
        """The :class:`DrivenPath` entries of an object: indices its own, no vertex both fixed and
        driven or driven twice, every path file read and checked (:func:`jaxplush.scene.paths.read_path`)."""
        from jaxplush.scene import paths
        out, seen = [], {}
        fixed = set(fixed)
        real = not (self.path.startswith("<") and self.path.endswith(">"))
        base = os.path.dirname(os.path.abspath(self.path)) if real else os.getcwd()
        for source, idx, until, ln in o.driven:
            verts = []
            for g in idx:
                j = np.searchsorted(used, g)
                if j >= len(used) or used[j] != g:
                    raise self.err(ln, f"'driven' vertex {g + 1} is not a vertex of object {name!r}")
                i = vstart + int(j)
                if i in fixed:
                    raise self.err(ln, f"'driven' vertex {g + 1} is also 'fixed' (a vertex is either pinned or driven)")
                if i in seen:
                    raise self.err(ln, f"'driven' vertex {g + 1} is driven twice (also on line {seen[i]})")
                seen[i] = ln
                verts.append(i)
            file = os.path.normpath(os.path.join(base, os.path.expanduser(source)))
            try:
                times, positions = paths.read_path(file, len(verts))
            except paths.PathFileError as e:
                raise self.err(ln, f"'driven' path file {source!r} ({file}): {e}") from None
            out.append(DrivenPath(source=source, file=file, vertices=tuple(verts), times=times,
                                  positions=positions, until=until, line=ln))
        return tuple(out)

    def scene_settings(self, objs, vertices):
        """The Scene fields set by scene keywords (gravity, floor, temperature and the floor and
        contact keywords given), checked against each other and the objects' positions."""
        gravity = np.asarray(self.scene_keys.get("gravity", (DEFAULT_GRAVITY, 0))[0], np.float64)
        floor = self.scene_keys["floor"][0][0] if "floor" in self.scene_keys else None
        temperature = self.scene_keys.get("temperature", ((DEFAULT_TEMPERATURE,), 0))[0][0]
        if floor is None:
            for key in ("floor_friction", "floor_restitution", "floor_model", "floor_stiffness"):
                if key in self.scene_keys:
                    raise self.err(self.scene_keys[key][1], f"'{key}' needs a 'floor'")
        smooth = self.scene_keys.get("floor_model", (["projection"], 0))[0][0] == "smooth"
        if smooth:
            for key in ("floor_friction", "floor_restitution"):
                if key in self.scene_keys and self.scene_keys[key][0][0] != 0:
                    raise self.err(self.scene_keys[key][1], f"'{key}' acts in the floor projection: it needs "
                                                            "'floor_model projection' (the smooth floor has neither)")
        elif "floor_stiffness" in self.scene_keys:
            raise self.err(self.scene_keys["floor_stiffness"][1], "'floor_stiffness' needs 'floor_model smooth'")
        extra = {k: self.scene_keys[k][0][0] for k in ("floor_friction", "floor_restitution", "contact",
                                                        "self_collision", "contact_stiffness",
                                                        "contact_thickness", "contact_friction", "floor_model",
                                                        "floor_stiffness")
                 if k in self.scene_keys}
        if "contact_capacity" in self.scene_keys:
            extra["contact_capacity"] = int(self.scene_keys["contact_capacity"][0][0])
        if floor is not None:
            for o in objs:
                lo = vertices[o.vertex_slice[0]:o.vertex_slice[1], 1].min()
                if lo < floor:
                    raise self.err(self.scene_keys["floor"][1],
                                   f"object {o.name!r} starts below the floor (lowest y = {lo:.6g} < floor {floor:.6g})")
        return dict(gravity=gravity, floor=floor, temperature=float(temperature), **extra)
