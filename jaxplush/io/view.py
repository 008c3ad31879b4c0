"""Interactive 3-D viewer of trajectories and fits in the browser, on viser (the extra ``viewer``).

:func:`view` shows a trajectory (a ``jaxplush simulate`` HDF5 file or a
:class:`jaxplush.Trajectory`) or a FIT.h5 of ``jaxplush-fit`` (its fitted rollout, against its
target): each object in its own colour, the floor, a timeline, play/pause and a playback speed;
optionally a target's points at the matching frame times and the edges coloured by stretch. It
either serves the view live on 127.0.0.1 (:class:`LiveView`) or writes it as one self-contained
HTML file (:class:`StaticView`: viser's scene recording inlined into viser's bundled web client,
which plays offline). Command line: ``jaxplush view``; guide: docs/viewer.md.

Importing this module needs neither viser nor JAX: without viser, :func:`view` raises
:class:`ViewerUnavailable`, whose message says how to install it.
"""

from __future__ import annotations

import contextlib
import dataclasses
import html as _html
import io
import math
import os
import socket
import threading
import time

import numpy as np

from jaxplush.errors import JaxplushError, TrajectoryError
from jaxplush.io.kinds import KINDS, TargetKind
from jaxplush.io.trajectory import atomic_path, check_output_path, open_hdf5

__all__ = ["view", "LiveView", "StaticView", "ViewerUnavailable", "TargetMismatch", "INSTALL_HINT", "COLORS",
           "SPEEDS"]

#: How to get the optional dependency.
INSTALL_HINT = 'pip install -e ".[viewer]" (in a checkout of jaxplush) or pip install "jaxplush[viewer]"'
#: ``color`` choices: one colour per object, or edges coloured by stretch (length / rest length).
COLORS = ("object", "strain")
#: Playback speeds of the live viewer (the static HTML offers viser's 0.5x-8x).
SPEEDS = ("0.1x", "0.25x", "0.5x", "1x", "2x", "4x")
#: Default most frames shown; a longer trajectory is subsampled (and says so).
MAX_FRAMES = 300

# Seaborn "deep", as jaxplush.io.render draws objects.
_PALETTE = ("#4C72B0", "#DD8452", "#55A868", "#C44E52", "#8172B3",
            "#937860", "#DA8BC3", "#8C8C8C", "#CCB974", "#64B5CD")
_TARGET_RGB = {"positions": (20, 20, 20), "points": (20, 20, 20), "tracks": (220, 0, 180), "mixed": (20, 20, 20)}
_STRAIN_MESH_RGB = (215, 215, 215)


class ViewerUnavailable(JaxplushError):
    """viser (the optional extra ``viewer``) is not installed."""


def require_viser():
    """Import and return :mod:`viser`, or raise :class:`ViewerUnavailable` with the install hint."""
    try:
        import viser
    except ImportError as e:
        raise ViewerUnavailable(f"the viewer needs the optional package viser ({e}); install it with "
                                f"{INSTALL_HINT}") from None
    return viser


# ----------------------------------------------------------------------------
# what is shown
# ----------------------------------------------------------------------------


@dataclasses.dataclass
class _Data:
    """Everything a view shows, read and checked before any server starts or file is written."""

    path: str
    kind: str                   # "trajectory" or "fit"
    n_frames: int               # frames in the input
    frames: np.ndarray          # (k,) the frames shown
    times: np.ndarray           # (k,) their times, s
    positions: np.ndarray       # (k, V, 3) float32
    faces: np.ndarray           # (F, 3)
    face_object: np.ndarray     # (F,)
    names: list
    floor: float | None
    rest: np.ndarray            # (V, 3) rest positions (the scene's vertices, else frame 0)
    rest_source: str            # which, in words
    object_id: np.ndarray | None = None   # (V,) each vertex's object, where the input records it
    names_recorded: bool = True  # False: ``names`` are defaults ("object 0", ...), not the file's
    scene_text: str | None = None  # the stored scene (a FIT.h5's, a trajectory's), for checking a target
    target: list | None = None  # per shown frame: (M, 3) float32 points, or None (no target frame then)
    target_kind: str | None = None
    target_path: str | None = None
    notes: list = dataclasses.field(default_factory=list)


def _read_input(source, max_frames):
    """:class:`_Data` of a trajectory file, a FIT.h5 or an in-memory trajectory."""
    from jaxplush.io.render import _select_frames
    if not isinstance(source, (str, os.PathLike)):
        if not (hasattr(source, "positions") and hasattr(source, "faces")):
            raise JaxplushError(f"view: expected a trajectory file, a FIT.h5 or a jaxplush.Trajectory, "
                                f"got {type(source).__name__}")
        pos = np.asarray(source.positions)
        times = np.asarray(getattr(source, "times", np.arange(len(pos))), np.float64)
        frames = _select_frames(times, max_frames)
        oid = np.asarray(getattr(source, "object_id", np.zeros(pos.shape[1], int)))
        faces = np.asarray(source.faces, np.int64)
        floor = getattr(source, "floor", None)
        scene_text = getattr(source, "scene_text", None)
        rest = _rest_from_text(scene_text, pos.shape[1])
        return _Data(path="<trajectory>", kind="trajectory", n_frames=len(pos), frames=frames, times=times[frames],
                     positions=pos[frames].astype(np.float32), faces=faces, face_object=oid[faces[:, 0]],
                     names=[str(n) for n in getattr(source, "object_names", ["object 0"])],
                     floor=None if floor is None or not math.isfinite(float(floor)) else float(floor),
                     rest=pos[0] if rest is None else rest, rest_source="frame 0" if rest is None else "the scene",
                     object_id=oid if hasattr(source, "object_id") else None,
                     names_recorded=hasattr(source, "object_names"), scene_text=scene_text or None)
    path = os.fspath(source)
    try:
        return _read_file(path, max_frames)
    except (OSError, RuntimeError, KeyError) as e:    # h5py on a damaged file, past its header
        raise TrajectoryError(path, f"not a readable trajectory or FIT.h5 (damaged HDF5: {e})") from None


def _read_file(path, max_frames):
    """:func:`_read_input` of a file (h5py's errors on a damaged file pass through)."""
    from jaxplush.io.render import _read_names
    with open_hdf5(path) as f:
        fit = "positions" not in f and ("fitted" in f or "checkpoint" in f)
        if fit and "fitted" not in f:
            status = f.attrs.get("status", "unknown")
            raise TrajectoryError(path, f"a FIT.h5 without a fitted rollout (status {status!r}: the fit has not "
                                        "finished); view it once the fit ends")
        scene_text = _text_attr(f, "scene")
        scene_path = _text_attr(f, "scene_path") or path
        target_path = _text_attr(f, "target_path") if fit else None
        names_recorded = bool(_read_names(f))
    if fit:
        return _read_fit(path, scene_text, scene_path, target_path, max_frames)
    from jaxplush.io.render import _read_objects, _read_trajectory
    t = _read_trajectory(path, None, max_frames)
    n_verts = t.positions.shape[1]
    rest = _rest_from_text(scene_text, n_verts, scene_path)
    with open_hdf5(path) as f:                      # read and checked by _read_trajectory already
        object_id = _read_objects(path, f, n_verts)[0] if "object_id" in f else None
    return _Data(path=path, kind="trajectory", n_frames=t.n_frames, frames=t.frames, times=t.times[t.frames],
                 positions=t.positions.astype(np.float32), faces=t.faces, face_object=t.face_object,
                 names=list(t.names), floor=t.floor if math.isfinite(t.floor) else None,
                 rest=t.positions[0] if rest is None else rest,      # frame 0 is always among those shown
                 rest_source="frame 0" if rest is None else "the stored scene",
                 object_id=object_id, names_recorded=names_recorded, scene_text=scene_text)


def _text_attr(f, name):
    v = f.attrs.get(name)
    if v is None:
        return None
    return v.decode("utf-8", "replace") if isinstance(v, bytes) else str(v)


def _scene_of(text, scene_path, path):
    from jaxplush.errors import SceneError
    from jaxplush.scene.parse import parse_scene
    try:
        return parse_scene(text, scene_path)
    except SceneError as e:
        raise TrajectoryError(path, f"its stored scene does not parse: {e}") from None


def _rest_from_text(text, n_verts, scene_path="<scene>"):
    """The stored scene's vertices (rest positions), or None when there is no usable scene."""
    if not text:
        return None
    try:
        from jaxplush.scene.parse import parse_scene
        x = np.asarray(parse_scene(text, scene_path).vertices, np.float64)
    except Exception:      # noqa: BLE001: a scene that does not parse only loses the rest lengths
        return None
    return x if x.shape == (n_verts, 3) else None


def _read_fit(path, scene_text, scene_path, target_path, max_frames):
    from jaxplush.io.render import _positions_shape, _scan_positions, _select_frames
    if not scene_text:
        raise TrajectoryError(path, "a FIT.h5 without its 'scene' attribute: cannot tell the objects' faces")
    try:
        with open_hdf5(path) as f:
            g = f["fitted"]
            if "positions" not in g or "times" not in g:
                raise TrajectoryError(path, "'fitted' lacks 'positions' or 'times'")
            n_frames, n_verts = _positions_shape(path, g["positions"])
            times = np.asarray(g["times"][()], np.float64).reshape(-1)
            if times.shape != (n_frames,) or not np.all(np.isfinite(times)):
                raise TrajectoryError(path, f"'fitted/times' must hold {n_frames} finite times")
            frames = _select_frames(times, max_frames)
            positions = _scan_positions(path, g["positions"], frames, times)[0]
    except TrajectoryError:
        raise
    except (OSError, KeyError, ValueError, TypeError, RuntimeError) as e:
        raise TrajectoryError(path, f"could not read the fitted rollout ({type(e).__name__}: {e})") from None
    scene = _scene_of(scene_text, scene_path, path)
    if scene.n_vertices != n_verts:
        raise TrajectoryError(path, f"the fitted rollout has {n_verts} vertices, its scene {scene.n_vertices}")
    faces = np.asarray(scene.faces, np.int64)
    return _Data(path=path, kind="fit", n_frames=n_frames, frames=frames, times=times[frames],
                 positions=positions.astype(np.float32), faces=faces,
                 face_object=np.asarray(scene.object_id)[faces[:, 0]], names=list(scene.object_names),
                 floor=scene.floor, rest=np.asarray(scene.vertices, np.float64), rest_source="the stored scene",
                 target_path=target_path, object_id=np.asarray(scene.object_id, np.int64), scene_text=scene_text)


def _read_target(path):
    """(kind, times (T,), frames: list of (M_t, 3) float32 observed points, what the file records of
    its scene: a dict of ``names``, ``faces``, ``object_id``, ``scene`` (each None when absent),
    ``width`` (N of the kind's [T, N, 3]) and ``correspondence`` (True: it holds 'positions' or
    'tracks', which name the mesh's vertices or faces)) of a target file."""
    from jaxplush.io.render import _read_names, _read_times
    path = os.fspath(path)
    try:
        with open_hdf5(path) as f:
            have = [k for k in KINDS if not k.compound and k.value in f]       # in order of preference
            if not have:
                raise TrajectoryError(path, "no 'positions', 'points' or 'tracks' dataset: not a fit target")
            kind = have[0]
            ds = f[kind.value]
            if not hasattr(ds, "shape") or ds.ndim != 3 or ds.shape[2] != 3 or ds.shape[0] == 0:
                raise TrajectoryError(path, f"'{kind}' must have shape [T, N, 3]")
            if ds.dtype.kind not in "fiu":
                raise TrajectoryError(path, f"'{kind}' must be numeric, got dtype {ds.dtype}")
            data = np.asarray(ds[()], np.float32)
            times = _read_times(path, f, data.shape[0])
            rec = dict(names=_read_names(f) or None,
                       faces=_small_dataset(f, "faces", 2), object_id=_small_dataset(f, "object_id", 1),
                       scene=_text_attr(f, "scene"), width=int(data.shape[1]),
                       correspondence=any(k.material_points for k in have))
    except TrajectoryError:
        raise
    except (OSError, KeyError, ValueError, TypeError, RuntimeError) as e:
        raise TrajectoryError(path, f"could not read the target ({type(e).__name__}: {e})") from None
    frames = [d[np.isfinite(d).all(axis=1)] for d in data]      # NaN rows: padding, or a track not seen
    return kind, times, frames, rec


def _small_dataset(f, name, ndim):
    """A numeric dataset of ``ndim`` dimensions as an int64 array, or None (absent, or not such a dataset)."""
    ds = f.get(name)
    if ds is None or not hasattr(ds, "dtype") or ds.dtype.kind not in "iu" or ds.ndim != ndim:
        return None
    return np.asarray(ds[()], np.int64)


class TargetMismatch(JaxplushError):
    """A target that does not belong to the trajectory or fit being viewed (:attr:`target`: its
    name; :attr:`reason`: what does not match)."""

    def __init__(self, target, reason):
        self.target, self.reason = target, reason
        super().__init__(f"target {target}: {reason}")


def _check_target(data, kind, rec, name):
    """Raise :class:`TargetMismatch` unless the target ``name`` (of ``kind``, recording ``rec``:
    :func:`_read_target`) belongs to what ``data`` shows: the checks a fit makes of a target against
    its scene, and the stored scenes' objects and rest shape where both files hold a scene."""
    what = os.path.basename(data.path) if data.path != "<trajectory>" else "the trajectory"
    n_verts = data.positions.shape[1]
    if TargetKind(kind).every_vertex and rec["width"] != n_verts:
        raise TargetMismatch(name, f"its 'positions' hold {rec['width']} vertices but {what} has {n_verts}: "
                                   "the target belongs to another scene")
    names = rec["names"]
    if names is not None and (data.names_recorded or data.object_id is not None):
        if len(names) != len(data.names) or (data.names_recorded and list(names) != list(data.names)):
            raise TargetMismatch(name, f"its objects {list(names)} differ from {what}'s {list(data.names)}: the "
                                       "target belongs to another scene")
    if rec["correspondence"]:
        if rec["faces"] is not None and not _same_faces(rec["faces"], data.faces):
            raise TargetMismatch(name, f"its 'faces' ({len(rec['faces'])} triangles) differ from {what}'s "
                                       f"({len(data.faces)}): the target was made from another mesh")
        oid = rec["object_id"]
        if oid is not None and data.object_id is not None and not np.array_equal(oid, data.object_id):
            raise TargetMismatch(name, f"its 'object_id' differs from {what}'s: its objects' vertices are "
                                       "numbered differently")
    if rec["scene"] and data.scene_text and rec["scene"] != data.scene_text:
        reason = _scene_difference(rec["scene"], data.scene_text, what)
        if reason:
            raise TargetMismatch(name, reason)


def _same_faces(a, b):
    """The same triangles, in any order and with any winding."""
    a, b = np.asarray(a, np.int64), np.asarray(b, np.int64)
    if a.ndim != 2 or a.shape != b.shape:
        return False
    key = lambda f: np.unique(np.sort(f, axis=1), axis=0)  # noqa: E731
    return np.array_equal(key(a), key(b))


#: A target's stored scene and the viewed file's place each object where the other does: the same
#: rest vertices within REST_TOLERANCE of the scene's extent when their meshes have the same vertex
#: counts, else (a point cloud of another mesh of the same objects) the same bounding box within
#: BOX_TOLERANCE of the object's size.
REST_TOLERANCE = 1e-6
BOX_TOLERANCE = 0.1


def _scene_difference(target_text, text, what):
    """Why a target's stored scene (text) is not the scene of what is viewed, or None (the same
    objects, at the same rest positions: parameters may differ, as a fit's start values do)."""
    import warnings
    from jaxplush.scene.parse import parse_scene

    def geometry(t):      # 'driven' lines name path files relative to a scene file: not geometry
        return "\n".join(line for line in t.splitlines() if line.split()[:1] != ["driven"])
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")     # unused vertices and the like: said when the scene was run
            a, b = parse_scene(geometry(target_text), "<target's scene>"), parse_scene(geometry(text), "<scene>")
    except Exception:      # noqa: BLE001: a scene that does not parse cannot be compared
        return None
    if list(a.object_names) != list(b.object_names):
        return (f"its stored scene has the objects {list(a.object_names)}, {what}'s {list(b.object_names)}: the "
                "target belongs to another scene")
    xa, xb = np.asarray(a.vertices, np.float64), np.asarray(b.vertices, np.float64)
    ia, ib = np.asarray(a.object_id), np.asarray(b.object_id)
    size = float(max(np.max(np.ptp(np.concatenate([xa, xb]), axis=0)), 1e-12))
    for o, obj in enumerate(a.object_names):
        pa, pb = xa[ia == o], xb[ib == o]
        if len(pa) == len(pb):
            off = float(np.max(np.linalg.norm(pa - pb, axis=1)))
            if off > REST_TOLERANCE * size:
                return (f"its stored scene places object {obj!r} elsewhere than {what}'s (rest vertices up to "
                        f"{off:.3g} m apart): the target belongs to another scene")
        else:
            box_a, box_b = np.stack([pa.min(axis=0), pa.max(axis=0)]), np.stack([pb.min(axis=0), pb.max(axis=0)])
            off = float(np.max(np.abs(box_a - box_b)))
            if off > BOX_TOLERANCE * float(max(np.max(np.ptp(pb, axis=0)), 1e-12)):
                return (f"its stored scene's object {obj!r} ({len(pa)} vertices) does not lie where {what}'s "
                        f"({len(pb)} vertices) does (bounding boxes {off:.3g} m apart): the target belongs to "
                        "another scene")
    return None


def _attach_target(data, target, report):
    """Put the target's frames on the shown frames whose times they match, once it is known to
    belong to what is shown (:func:`_check_target`: else :class:`TargetMismatch`; a FIT.h5's own
    target that does not belong is left out, with a note)."""
    located = target is None
    if target is None:
        if data.kind != "fit" or not data.target_path:
            return
        target = _locate_fit_target(data, report)
        if target is None:
            return
    if isinstance(target, (str, os.PathLike)):
        kind, times, frames, rec = _read_target(target)
        name = os.fspath(target)
        try:
            _check_target(data, kind, rec, name)
        except TargetMismatch as e:
            if not located:
                raise
            report(f"the fit's target {name} does not belong to {data.path} ({e.reason}); showing the fitted "
                   "rollout alone (--target names the right one)")
            return
    else:                                           # a jaxplush.fitting.Target
        kind, times, name = target.kind, np.asarray(target.times, np.float64), getattr(target, "path", "<target>")
        frames = [d[np.isfinite(d).all(axis=1)].astype(np.float32) for d in np.asarray(target.data)]
        if TargetKind(kind).every_vertex:
            _check_target(data, kind, dict(names=None, faces=None, object_id=None, scene=None, correspondence=True,
                                           width=int(np.shape(target.data)[1])), name)
    order = np.argsort(times, kind="stable")
    times, frames = np.asarray(times, np.float64)[order], [frames[i] for i in order]
    shown = data.times
    gaps = np.diff(shown)
    tol = 1e-6 * max(1.0, float(np.max(np.abs(shown)))) + (1e-3 * float(gaps[gaps > 0].min()) if (gaps > 0).any()
                                                            else 0.0)
    j = np.clip(np.searchsorted(times, shown), 0, len(times) - 1)
    j_prev = np.clip(j - 1, 0, len(times) - 1)
    j = np.where(np.abs(times[j_prev] - shown) < np.abs(times[j] - shown), j_prev, j)
    hit = np.abs(times[j] - shown) <= tol
    data.target = [frames[jj] if h else None for jj, h in zip(j, hit)]
    data.target_kind, data.target_path = kind, name
    report(f"target {name}: {len(times)} frames of {kind}; shown at {int(hit.sum())} of the {len(shown)} frames "
           "(those at a target frame's time)")


def _locate_fit_target(data, report):
    """A FIT.h5's target file: as recorded, else beside the FIT.h5; None (and a note) when missing."""
    p = data.target_path
    for cand in (p, os.path.join(os.path.dirname(os.path.abspath(data.path)), os.path.basename(p))):
        if os.path.isfile(cand):
            return cand
    report(f"the fit's target {p} is not found (nor beside {data.path}); showing the fitted rollout alone "
           "(--target names it)")
    return None


# ----------------------------------------------------------------------------
# the scene
# ----------------------------------------------------------------------------


def _rgb(hex_colour):
    h = hex_colour.lstrip("#")
    return tuple(int(h[i:i + 2], 16) for i in (0, 2, 4))


def _nice(x):
    """A round number (1, 2 or 5 times a power of ten) near ``x`` > 0."""
    e = 10.0 ** math.floor(math.log10(x))
    return min((1, 2, 5, 10), key=lambda m: abs(math.log(m * e / x))) * e


class _Scene:
    """The viser scene nodes of a view, and :meth:`show` to put frame ``k`` on them."""

    def __init__(self, server, data, color, report):
        self.data = data
        sc = server.scene
        sc.set_up_direction("+y")
        pts = data.positions.reshape(-1, 3)
        lo, hi = pts.min(axis=0), pts.max(axis=0)
        centre, size = (lo + hi) / 2, float(max(np.max(hi - lo), 1e-3))
        server.initial_camera.look_at = tuple(float(c) for c in centre)
        server.initial_camera.position = tuple(float(c) for c in centre + size * np.array([0.7, 0.5, 1.3]))
        if data.floor is not None:
            cell = _nice(size / 8)
            width = 2 * cell * math.ceil(1.5 * size / cell)
            sc.add_grid("/floor", width=width, height=width, plane="xz", cell_size=cell, section_size=5 * cell,
                        plane_color=(230, 230, 230), plane_opacity=0.6,
                        position=(float(centre[0]), data.floor, float(centre[2])))
        self.meshes = []
        x0 = data.positions[0]
        for o, name in enumerate(data.names):
            faces = data.faces[data.face_object == o]
            if not len(faces):
                continue
            vids = np.unique(faces)
            rgb = _STRAIN_MESH_RGB if color == "strain" else _rgb(_PALETTE[o % len(_PALETTE)])
            h = sc.add_mesh_simple(f"/objects/{o}", vertices=x0[vids], faces=np.searchsorted(vids, faces),
                                   color=rgb, side="double")
            self.meshes.append((h, vids))
        self.strain = None
        if color == "strain":
            self._init_strain(sc, report)
        self.cloud = None
        if data.target is not None:
            kind = data.target_kind
            first = next((t for t in data.target if t is not None and len(t)), None)
            self.cloud = sc.add_point_cloud("/target", points=np.zeros((1, 3), np.float32) if first is None else first,
                                            colors=_TARGET_RGB[kind], point_size=size / 80, point_shape="circle",
                                            visible=False)
        self.k = None
        self.show(0)

    def _init_strain(self, sc, report):
        from matplotlib import colormaps
        from jaxplush.model.mesh import unique_edges
        d = self.data
        edges = np.asarray(unique_edges(d.faces), np.int64)
        rest = np.linalg.norm(d.rest[edges[:, 0]] - d.rest[edges[:, 1]], axis=1)
        rest = np.where(rest > 0, rest, np.nan)
        seg = d.positions[:, edges]                                            # (k, E, 2, 3)
        ratio = np.linalg.norm(seg[:, :, 0] - seg[:, :, 1], axis=-1) / rest   # (k, E)
        span = float(np.nanmax(np.abs(ratio - 1))) if np.isfinite(ratio).any() else 0.0
        span = max(_nice(span) if span > 0 else 0.01, 0.01)
        cmap = colormaps["coolwarm"]
        rgb = (cmap(np.clip((np.nan_to_num(ratio, nan=1.0) - 1) / (2 * span) + 0.5, 0, 1))[..., :3] * 255)
        self.strain_points = seg
        self.strain_colors = np.repeat(rgb.astype(np.uint8)[:, :, None, :], 2, axis=2)   # (k, E, 2, 3)
        self.strain = sc.add_line_segments("/strain", points=seg[0], colors=self.strain_colors[0], thickness=2.5)
        report(f"strain colours (edge length / rest length): blue {1 - span:.3g} (compressed), white 1, "
               f"red {1 + span:.3g} (stretched) or beyond; rest lengths from {d.rest_source}")

    def show(self, k):
        """Put shown frame ``k`` on the scene nodes."""
        if k == self.k:
            return
        self.k = k
        x = self.data.positions[k]
        for h, vids in self.meshes:
            h.vertices = x[vids]
        if self.strain is not None:
            self.strain.points = self.strain_points[k]
            self.strain.colors = self.strain_colors[k]
        if self.cloud is not None:
            t = self.data.target[k]
            if t is None or not len(t):
                self.cloud.visible = False
            else:
                self.cloud.points = t
                self.cloud.visible = True


# ----------------------------------------------------------------------------
# live and static views
# ----------------------------------------------------------------------------


@contextlib.contextmanager
def _quiet():
    """viser's banner and "Server stopped" (rich: on stdout, or as display output in a notebook) go nowhere."""
    import rich
    import rich.console
    saved = getattr(rich, "_console", None)
    rich._console = rich.console.Console(file=io.StringIO(), force_jupyter=False)
    try:
        with contextlib.redirect_stdout(io.StringIO()):
            yield
    finally:
        rich._console = saved


def _server(viser, port):
    """A viser server on 127.0.0.1:``port`` (0: a free one), without viser's banner."""
    with _quiet():
        return viser.ViserServer(host="127.0.0.1", port=port, verbose=False)


def _stop(server):
    with _quiet():
        server.stop()


class LiveView:
    """A view served live on 127.0.0.1: :attr:`url`, :meth:`wait` (until Ctrl-C), :meth:`stop`.

    In a notebook it shows inline as an IFrame of :attr:`url` (the kernel's machine must be the
    browser's: the server listens on 127.0.0.1 only)."""

    def __init__(self, viser, data, color, port, report):
        self.data = data
        self.server = _server(viser, port)
        self.url = f"http://127.0.0.1:{self.server.get_port()}/"
        self._scene = _Scene(self.server, data, color, report)
        self._lock = threading.Lock()
        self._playing = False
        self._stopped = threading.Event()
        self._gui()
        self._thread = threading.Thread(target=self._play_loop, name="jaxplush-view-playback", daemon=True)
        self._thread.start()

    def _gui(self):
        d, gui = self.data, self.server.gui
        legend = ", ".join(f"<span style='color:{_PALETTE[o % len(_PALETTE)]}'>&#9632;</span> {_html.escape(n)}"
                           for o, n in enumerate(d.names))
        shown = (f"all {d.n_frames} frames" if len(d.frames) == d.n_frames
                 else f"{len(d.frames)} of {d.n_frames} frames")
        gui.add_markdown(f"**{_html.escape(os.path.basename(d.path))}** ({shown})  \n{legend}")
        self.slider = gui.add_slider("frame", min=0, max=max(len(d.frames) - 1, 1), step=1, initial_value=0,
                                     disabled=len(d.frames) < 2)
        self.clock = gui.add_markdown(self._time_text(0))
        self.button = gui.add_button("Play", disabled=len(d.frames) < 2)
        self.speed = gui.add_dropdown("speed", SPEEDS, initial_value="1x")
        self._t = float(d.times[0])

        @self.slider.on_update
        def _(_event):
            k = int(min(max(self.slider.value, 0), len(d.frames) - 1))
            with self._lock:
                self._scene.show(k)
                if _event.client is not None or not self._playing:     # moved by hand: play on from there
                    self._t = float(d.times[k])
            self.clock.content = self._time_text(k)

        @self.button.on_click
        def _(_event):
            self.set_playing(not self._playing)

    def _time_text(self, k):
        d = self.data
        return f"t = {d.times[k]:.4g} s (frame {int(d.frames[k])} of {d.n_frames})"

    def set_playing(self, playing):
        """Start (True) or pause (False) the playback."""
        with self._lock:
            self._playing = bool(playing)
        self.button.label = "Pause" if playing else "Play"

    def _play_loop(self):
        d = self.data
        t0, t1 = float(d.times[0]), float(d.times[-1])
        last = time.perf_counter()
        while not self._stopped.wait(1 / 60):
            now = time.perf_counter()
            wall, last = now - last, now
            if not self._playing or len(d.times) < 2:
                continue
            self._t += wall * float(self.speed.value.rstrip("x"))
            if self._t > t1:
                self._t = t0
            k = int(np.searchsorted(d.times, self._t, side="right") - 1)
            if k != self.slider.value:
                self.slider.value = max(k, 0)

    def wait(self):
        """Block until Ctrl-C (KeyboardInterrupt, re-raised after stopping the server)."""
        try:
            while not self._stopped.wait(0.5):
                pass
        finally:
            self.stop()

    def stop(self):
        """Stop the playback and the server (idempotent)."""
        if not self._stopped.is_set():
            self._stopped.set()
            _stop(self.server)

    def __repr__(self):
        return f"LiveView({self.url!r}{', stopped' if self._stopped.is_set() else ''})"

    def _repr_html_(self):
        if self._stopped.is_set():
            return f"<p>viewer at {self.url}: stopped</p>"
        return f'<iframe src="{self.url}" width="100%" height="500" style="border:1px solid #ddd"></iframe>'


@dataclasses.dataclass(repr=False)
class StaticView:
    """A view as one self-contained HTML document (:attr:`html`), written to :attr:`path` (or None).

    Its player (viser's) plays it in any browser, offline: play/pause, a timeline, 0.5x-8x. In a
    notebook it shows inline (an iframe whose ``srcdoc`` is the document: kept in the saved
    notebook, no server needed)."""

    html: str
    path: str | None = None

    def __repr__(self):
        return f"StaticView(path={self.path!r}, {len(self.html) / 2 ** 20:.1f} MiB of HTML)"

    def _repr_html_(self):
        return (f'<iframe srcdoc="{_html.escape(self.html, quote=True)}" width="100%" height="500" '
                'style="border:1px solid #ddd"></iframe>')


def _record(viser, data, color, report):
    """The static HTML document: frame 0, then each shown frame after its simulated time gap."""
    server = _server(viser, 0)
    try:
        scene = _Scene(server, data, color, report)
        rec = server.get_scene_serializer()         # holds frame 0 (the scene so far)
        times = data.times
        for k in range(1, len(times)):
            rec.insert_sleep(max(float(times[k] - times[k - 1]), 0.0))
            scene.show(k)
        if len(times) > 1:                          # the last frame stays up a mean gap before the loop
            rec.insert_sleep(max(float(times[-1] - times[0]) / (len(times) - 1), 0.0))
        return rec.as_html()
    finally:
        _stop(server)


# ----------------------------------------------------------------------------
# the entry point
# ----------------------------------------------------------------------------


def view(trajectory, *, target=None, color="object", max_frames=MAX_FRAMES, html=None, port=0, report=print):
    """Show a trajectory or a fit in the browser (viser).

    Args:
      trajectory: a trajectory HDF5 file (``jaxplush simulate``), a FIT.h5 (``jaxplush-fit``: its
        fitted rollout, with its target when the recorded target file is found) or a
        :class:`jaxplush.Trajectory`.
      target: a fit target file (``positions``, ``points`` or ``tracks``) or a
        :class:`jaxplush.fitting.Target`, drawn as points at the shown frames whose times it has.
        It must belong to what is shown (:class:`TargetMismatch` otherwise): a ``positions``
        target has its vertex count; recorded objects, ``faces`` and ``object_id`` match (as a
        fit checks a target against its scene); and where both files store a scene, the two
        hold the same objects at the same rest positions (parameters may differ).
      color: "object" (one colour per object) or "strain" (edges coloured by edge length / rest
        length; the rest lengths are the stored scene's, else frame 0's).
      max_frames: most frames shown; a longer trajectory is subsampled evenly (first and last
        kept) and ``report`` says so.
      html: a path: write the view there as one self-contained HTML file (atomically) and serve
        nothing; True: make the document in memory only; None: serve it live.
      port: the live server's port on 127.0.0.1 (0: a free one).
      report: callable taking one line of text (what is shown); None: silent.

    Returns:
      :class:`StaticView` (with ``html``) or a running :class:`LiveView`; both show inline in a
      notebook.

    Raises:
      ViewerUnavailable: viser is not installed. TrajectoryError: an input file is missing or
      unreadable (named). TargetMismatch: ``target`` belongs to another scene (a FIT.h5's own
      target that does not is left out, with a note). JaxplushError: a bad argument.
    """
    report = report or (lambda _line: None)
    if color not in COLORS:
        raise JaxplushError(f"color must be one of {', '.join(COLORS)}, got {color!r}")
    if isinstance(max_frames, bool) or not isinstance(max_frames, (int, np.integer)) or max_frames < 2:
        raise JaxplushError(f"max_frames must be a whole number >= 2, got {max_frames!r}")
    if html not in (None, True):
        check_output_path(html, (".html", ".htm"))
    elif html is None and not (isinstance(port, (int, np.integer)) and 0 <= port <= 65535):
        raise JaxplushError(f"port must be 0 (a free one) to 65535, got {port!r}")
    viser = require_viser()
    data = _read_input(trajectory, int(max_frames))
    if len(data.frames) < data.n_frames:
        report(f"showing {len(data.frames)} of {data.n_frames} frames (evenly spaced, first and last kept; "
               f"max_frames {max_frames})")
    _attach_target(data, target, report)
    if html is None:
        _check_port(port)
        return LiveView(viser, data, color, int(port), report)
    doc = _record(viser, data, color, report)
    if html is True:
        return StaticView(doc)
    out = os.fspath(html)
    with atomic_path(out, os.path.splitext(out)[1]) as tmp:
        with open(tmp, "w", encoding="utf-8") as fh:
            fh.write(doc)
    return StaticView(doc, out)


def _check_port(port):
    """A given port must be free on 127.0.0.1 (viser would quietly take the next one)."""
    if not port:
        return
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        try:
            s.bind(("127.0.0.1", int(port)))
        except OSError as e:
            raise JaxplushError(f"port {port} on 127.0.0.1 is not free ({e.strerror}); choose another "
                                "or leave it out for a free one") from None
