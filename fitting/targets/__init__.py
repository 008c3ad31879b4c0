"""Fitting targets: read, validate and write target deformations (HDF5; numpy only, never traced).

A target is an HDF5 file in the trajectory schema of :mod:`jaxplush.io.trajectory`, so every
``jaxplush simulate`` output is one. It holds either

* ``positions`` float [T, V, 3]: the scene's vertices, in the scene's order, at T frames; or
* ``points`` float [T, M, 3]: a point cloud per frame (a scan; M unrelated to V, no
  correspondence), fitted (and swept) by each point's distance to the simulated surface
  (:mod:`jaxplush.fitting.objective.losses`). Frames may hold different
  numbers of points: a row of three NaNs is no point (padding), so a frame with fewer points
  ends in NaN rows (:func:`jaxplush.io.capture.depth_capture` writes captures this way). A row
  with some NaN coordinates, or an infinity, is an error; or
* ``tracks`` float [T, M, 3]: M tracked points with correspondence, each a vertex or a point
  on a face, with one of ``track_vertex`` int [M] (vertex indices), ``track_face`` int [M]
  with ``track_barycentric`` float [M, 3] (a face of the file's ``faces``, else of the scene's,
  and the point's barycentric coordinates: >= 0 and summing to 1, within
  :data:`BARYCENTRIC_TOLERANCE`), or ``track_vertices`` int [M, 3] with ``track_weights``
  float [M, 3] (any three vertices and weights; what :meth:`Target.save` writes for surface
  points). A row of three NaNs is a track not seen in that frame (occluded); a frame may see
  none, but every track must be seen in some frame; or
* ``points`` and ``tracks`` together (kind "mixed"): a scan with tracked points on the same
  frames, fitted by the two losses together (:func:`jaxplush.fitting.objective.losses.make_loss`; the
  tracks' share set by :attr:`Target.track_weight`),

and ``times`` float [T] (s, increasing). The frames may be any subset of the rollout (only the
final shape, say) and may be noisy. Optional: attribute ``dt`` (the target's time step, used
when no dt is given), attribute ``noise`` (the standard deviation of the measurement noise per
coordinate, m; used to normalise the loss), and ``faces``/``object_id``/``object_names`` (checked
against the scene when present), and the group ``controls`` (:class:`Controls`: the measured
path of driven vertices, ``controls/vertices`` int [D], ``controls/times`` float [S],
``controls/positions`` float [S, D, 3], attribute ``controls/until``), which
:func:`scene_with_controls` makes driven paths of the scene, as the scene keyword ``driven`` does.

:func:`load_target` validates everything against the scene *before* anything is traced: the file
is readable HDF5, the datasets exist and have the right shapes, vertex and object counts match
the scene (or points are given), track indices lie in the scene, the times lie on the dt grid,
and all values are finite. Each
problem raises :class:`jaxplush.errors.TrajectoryError` naming the file and the problem.

Format: docs/formats.md §4 (with an h5py example that writes a valid target).
"""

from __future__ import annotations

import dataclasses
import os

import h5py
import numpy as np

from jaxplush.errors import JaxplushError, TrajectoryError
from jaxplush.io.trajectory import atomic_path, open_hdf5
from jaxplush.fitting.targets.kinds import KINDS, TargetKind

#: Times must lie within this fraction of dt of a multiple of dt (float32-written times included).
GRID_TOLERANCE = 1e-3
#: A target farther than this many scene sizes from the scene's centre is refused (wrong units).
TARGET_FAR = 1e3
#: Barycentric coordinates of a track may be this far below 0, and their sum this far from 1.
BARYCENTRIC_TOLERANCE = 1e-6
#: The datasets of each kind's frames (:attr:`jaxplush.fitting.targets.kinds.TargetKind.datasets`).
KIND_DATASETS = {k: k.datasets for k in KINDS}
#: The ``source`` of the driven paths :func:`scene_with_controls` adds (whitespace: no scene line
#: can name such a path file).
CONTROLS_SOURCE = "<target controls>"


def observed_rows(kind, data):
    """(T, N) bool: the rows of a target's ``data`` (T, N, 3) that hold an observation: every
    vertex of ``positions``, the finite rows of ``points`` (NaN rows are padding), ``tracks``
    (NaN rows: not seen) and ``mixed`` (both)."""
    return TargetKind(kind).observed(data)


@dataclasses.dataclass(frozen=True, eq=False)
class Controls:
    """Measured positions of driven vertices (a gripper's or a hand's contact points), given with
    a target instead of a ``driven`` line of the scene; :func:`scene_with_controls` drives them.

    Attributes:
      vertices: (D,) int64 the driven vertices (0-based scene indices, as ``track_vertex``).
      times: (S,) float64 strictly increasing sample times, s.
      positions: (S, D, 3) float64 their world positions at the samples, m (linear between
        samples, held outside them, as a ``driven`` path).
      until: release time, s (after it the vertices move freely), or None (driven throughout).
    """

    vertices: np.ndarray
    times: np.ndarray
    positions: np.ndarray
    until: float | None = None

    def datasets(self):
        """dict name -> array of the ``controls`` group (as :meth:`Target.save` writes it)."""
        return {"vertices": np.asarray(self.vertices, np.int64), "times": np.asarray(self.times, np.float64),
                "positions": np.asarray(self.positions, np.float64)}


@dataclasses.dataclass(frozen=True, eq=False)
class Target:
    """A validated fitting target (numpy).

    Attributes:
      positions: (T, V, 3) target vertex positions (m), or None for another kind.
      points: (T, M, 3) target point clouds (m), or None for another kind.
      steps: (T,) int64 step index of each frame on the ``dt`` grid (strictly increasing).
      times: (T,) frame times, s (as stored).
      dt: time step of the grid, s.
      path: file the target came from ("<memory>" for one built in memory).
      noise: measurement noise standard deviation per coordinate (m) if known, else None.
      params: dict name -> (O,) parameter values stored with the target (a simulated target
        records its true parameters), possibly empty.
      tracks: (T, M, 3) tracked points (m; NaN rows: not seen in that frame), or None.
      track_vertices: (M, 3) int64 the vertices each track interpolates (a vertex track: [v, v, v]).
      track_weights: (M, 3) float64 their weights (barycentric; a vertex track: [1, 0, 0]).
      track_weight: a mixed target's weight w of its tracks against its scan: the loss is
        (L_points + w L_tracks) / (1 + w), each term normalised on its own (default 1: the two
        count alike, however many points each holds; :func:`jaxplush.fitting.objective.losses.make_loss`).
      controls: :class:`Controls` of driven vertices, or None.
      custom_kind: a target of a kind of one's own (a :class:`jaxplush.fitting.targets.kinds.Kind`
        subclass; :meth:`of_kind`), else None. custom_data: its (T, M, D) frames.
    """

    positions: np.ndarray | None
    points: np.ndarray | None
    steps: np.ndarray
    times: np.ndarray
    dt: float
    path: str
    noise: float | None = None
    params: dict = dataclasses.field(default_factory=dict)
    tracks: np.ndarray | None = None
    track_vertices: np.ndarray | None = None
    track_weights: np.ndarray | None = None
    track_weight: float = 1.0
    controls: Controls | None = None
    custom_kind: TargetKind | None = None
    custom_data: np.ndarray | None = None

    @classmethod
    def of_kind(cls, kind, data, times, dt, *, steps=None, path="<memory>", noise=None, params=None):
        """A target of a kind of one's own: ``kind`` a :class:`jaxplush.fitting.targets.kinds.Kind`
        instance, ``data`` (T, M, D) its frames (NaN rows: not observed), ``times`` (T,) s on the
        grid of ``dt`` (or ``steps``, their step indices)."""
        times = np.asarray(times, np.float64).reshape(-1)
        steps = (_grid_steps(path, times, float(dt), times.dtype) if steps is None
                 else np.asarray(steps, np.int64).reshape(-1))
        data = np.asarray(data, np.float64)
        if not isinstance(kind, TargetKind):
            raise TypeError(f"kind must be a jaxplush.fitting.targets.kinds.Kind, got {type(kind).__name__}")
        if data.ndim != 3 or len(data) != len(steps):
            raise ValueError(f"{path}: a target's frames must be [T, M, D] with T = {len(steps)} frames, "
                             f"got {list(data.shape)}")
        return cls(None, None, steps, times, float(dt), path, noise=noise, params=dict(params or {}),
                   custom_kind=kind, custom_data=data)

    @property
    def kind(self):
        """Its :class:`jaxplush.fitting.targets.kinds.TargetKind` (equal to "positions", "points", "tracks"
        or "mixed": points and tracks; or the kind of one's own it was made with)."""
        if self.custom_kind is not None:
            return self.custom_kind
        if self.positions is not None:
            return TargetKind.POSITIONS
        if self.tracks is not None:
            return TargetKind.MIXED if self.points is not None else TargetKind.TRACKS
        return TargetKind.POINTS

    @property
    def data(self):
        """(T, V or M, 3) the target's frames, whichever kind (mixed: the points, then the tracks,
        (T, M_points + M_tracks, 3))."""
        if self.custom_kind is not None:
            return self.custom_data
        if self.kind.compound:
            return np.concatenate([np.asarray(self.points), np.asarray(self.tracks)], axis=1)
        return getattr(self, self.kind.value)

    @property
    def parts(self):
        """The single-kind targets this one is made of: (points, tracks) for a mixed target (same
        frames), else (self,)."""
        if not self.kind.compound:
            return (self,)
        return (dataclasses.replace(self, tracks=None, track_vertices=None, track_weights=None),
                dataclasses.replace(self, points=None))

    @property
    def n_frames(self):
        return len(self.steps)

    @property
    def observed(self):
        """(T, V or M) bool: the rows that hold an observation (False: a point cloud's NaN padding)."""
        return self.kind.observed(self.data)

    @property
    def ragged(self):
        """True for a point cloud whose frames hold different numbers of points (NaN padding)."""
        return self.kind is TargetKind.POINTS and not bool(self.observed.all())

    def select(self, frames):
        """A target with only the given frames (indices or a boolean mask, in order)."""
        idx = np.arange(self.n_frames)[frames]
        if idx.size == 0:
            raise ValueError("a target needs at least one frame")
        sel = lambda a: None if a is None else a[idx]  # noqa: E731
        return dataclasses.replace(self, positions=sel(self.positions), points=sel(self.points),
                                   tracks=sel(self.tracks), custom_data=sel(self.custom_data),
                                   steps=self.steps[idx], times=self.times[idx])

    def on_grid(self, dt):
        """This target with its frame steps recomputed for time step ``dt`` (validated)."""
        dt = float(dt)
        if dt == self.dt:
            return self
        steps = _grid_steps(self.path, self.times, dt, self.times.dtype)
        return dataclasses.replace(self, steps=steps, dt=dt)

    def save(self, path, scene=None, extra=None):
        """Write the target to ``path`` atomically in the trajectory schema.

        With ``scene``, its faces, object ids and names and its scene text are stored too. A
        tracks (or mixed) target writes ``track_vertex`` when every track is a vertex, else
        ``track_vertices`` and ``track_weights`` (exactly as held); a mixed target writes
        ``points`` and ``tracks``; controls go to the group ``controls``. ``extra``: more
        datasets to write alongside (dict name -> array).
        """
        with atomic_path(path, ".h5") as tmp:
            with h5py.File(tmp, "w") as f:
                for name in self.kind.datasets or (self.kind.value,):
                    f.create_dataset(name, data=np.asarray(self.custom_data if self.custom_kind is not None
                                                           else getattr(self, name)),
                                     compression="gzip", compression_opts=1)
                if self.tracks is not None:
                    for name, val in _track_datasets(self.track_vertices, self.track_weights).items():
                        f.create_dataset(name, data=val)
                if self.controls is not None:
                    g = f.create_group("controls")
                    for name, val in self.controls.datasets().items():
                        g.create_dataset(name, data=val)
                    if self.controls.until is not None:
                        g.attrs["until"] = float(self.controls.until)
                for name, val in (extra or {}).items():
                    f.create_dataset(name, data=np.asarray(val))
                f.create_dataset("times", data=np.asarray(self.times, np.float64))
                f.attrs["dt"] = float(self.dt)
                f.attrs["steps"] = int(self.steps[-1])
                if self.noise is not None:
                    f.attrs["noise"] = float(self.noise)
                for name, val in self.params.items():
                    f.attrs[name] = np.asarray(val, np.float64)
                if scene is not None:
                    f.create_dataset("faces", data=np.asarray(scene.faces, np.int32))
                    f.create_dataset("object_id", data=np.asarray(scene.object_id, np.int32))
                    f.create_dataset("object_names", data=np.asarray(scene.object_names, dtype=object),
                                     dtype=h5py.string_dtype("utf-8"))
                    f.attrs["scene"] = scene.text
        return os.fspath(path)


def load_target(path, scene, dt=None, kind=None):
    """Read a target file and validate it against a scene.

    Args:
      path: HDF5 file with ``positions`` [T, V, 3], ``points`` [T, M, 3] and/or ``tracks`` [T, M, 3]
        (with its correspondence), and ``times`` [T]; optionally the group ``controls``.
      scene: the :class:`jaxplush.scene.parse.Scene` that will be fitted.
      dt: the fit's time step (s); default: the file's ``dt`` attribute. Every frame time must
        be a multiple of it.
      kind: "positions", "mixed", "points" or "tracks", to choose when a file holds several
        (default: positions; else, with both points and tracks, mixed; else whichever it holds).

    Returns:
      :class:`Target`.

    Raises:
      TrajectoryError: naming the file and the problem.
    """
    path = os.fspath(path)
    fh = open_hdf5(path)
    try:
        with fh:
            raw = _read(path, fh, kind)
    except JaxplushError:
        raise
    except (OSError, KeyError, ValueError, TypeError, RuntimeError) as e:  # a damaged file part-way through
        raise TrajectoryError(path, f"cannot read: {e}") from None
    return _validate(path, raw, scene, dt)


def _dataset(path, fh, name, required=True):
    if name not in fh:
        if required:
            raise TrajectoryError(path, f"missing dataset '{name}'")
        return None
    obj = fh[name]
    if not isinstance(obj, h5py.Dataset):
        raise TrajectoryError(path, f"'{name}' is a group, expected a dataset")
    return obj


def _read(path, fh, kind):
    if kind not in (None,) + KINDS:
        raise ValueError(f"kind must be 'positions', 'mixed', 'points' or 'tracks', got {kind!r}")
    have = [k for k in KINDS if not k.compound and k.value in fh]
    if not have:
        raise TrajectoryError(path, "missing dataset 'positions' (or 'points' for a point-cloud target, "
                                    "'tracks' for tracked points)")
    kind = TargetKind(kind) if kind is not None else next(
        k for k in KINDS if set(k.datasets) <= {h.value for h in have})        # the kinds in preference order
    for name in kind.datasets:
        if name not in have:
            raise TrajectoryError(path, f"missing dataset '{name}'" + (
                " (a mixed target holds both 'points' and 'tracks')" if kind.compound else ""))
    out = {"kind": kind}
    names = [(n, True) for n in KIND_DATASETS[kind]]
    names += [("times", True), ("faces", False), ("object_id", False), ("object_names", False)]
    if kind.tracked:
        names += [(n, False) for n in TRACK_DATASETS]
    for name, required in names:
        ds = _dataset(path, fh, name, required)
        if ds is not None:
            if ds.dtype.kind not in "fiu" and name != "object_names":
                raise TrajectoryError(path, f"'{name}' must be numeric, got dtype {ds.dtype}")
            out[name] = ds[()]
    out["controls"] = _read_controls(path, fh)
    attrs = fh.attrs
    out["dt_attr"] = attrs["dt"] if "dt" in attrs else None
    out["noise"] = attrs["noise"] if "noise" in attrs else None
    out["params"] = {n: np.asarray(attrs[n], np.float64) for n in
                     ("k_structural", "damping", "dashpot", "drag", "nmol", "total_weight") if n in attrs}
    return out


def _validate(path, raw, scene, dt):
    kind = raw["kind"]
    names = KIND_DATASETS[kind]
    frames = {}
    for name in names:
        frames[name] = np.asarray(raw[name])
        _check_data_shape(path, name, frames[name], scene)
    if kind.compound and len(frames["points"]) != len(frames["tracks"]):
        raise TrajectoryError(path, f"'tracks' has {len(frames['tracks'])} frames but 'points' has "
                                    f"{len(frames['points'])}: a mixed target's scan and tracks share the frames "
                                    "of 'times'")
    n_frames = len(frames[names[0]])
    _check_object_names(path, raw.get("object_names"), scene)
    if kind.material_points or kind.compound:       # (a scan alone has no vertex numbering to check)
        _check_object_id(path, raw.get("object_id"), scene, scene.n_vertices)
        faces = raw.get("faces")
        if faces is not None and not _same_faces(np.asarray(faces), scene.faces):
            raise TrajectoryError(path, f"'faces' differ from the scene {scene.path}'s: the target was "
                                        "made from a different mesh")
    corr = (_track_correspondence(path, raw, scene, frames["tracks"].shape[1]) if "tracks" in frames
            else (None, None))
    times = _check_times(path, raw["times"], n_frames, "' and '".join(names))
    dt = _target_dt(path, raw["dt_attr"], dt)
    steps = _grid_steps(path, times, dt, raw["times"].dtype)
    for name in names:
        frames[name] = frames[name].astype(np.float64)
        _check_data_values(path, name, frames[name], scene)
    noise = _noise_attr(path, raw["noise"])
    params = {k: v for k, v in raw["params"].items() if v.shape == (scene.n_objects,)}
    controls = None
    if raw.get("controls") is not None:
        controls = _check_controls(path, raw["controls"], scene)
        _check_control_conflicts(path, controls, scene)
    return Target(positions=frames.get("positions"), points=frames.get("points"),
                  steps=steps, times=times, dt=dt, path=path, noise=noise, params=params,
                  tracks=frames.get("tracks"), track_vertices=corr[0], track_weights=corr[1], controls=controls)


#: The datasets of the ``controls`` group (docs/formats.md §4).
CONTROL_DATASETS = ("vertices", "times", "positions")


def _read_controls(path, fh):
    """The raw ``controls`` group (dict of arrays and ``until``), or None without one."""
    if "controls" not in fh:
        return None
    g = fh["controls"]
    if not isinstance(g, h5py.Group):
        raise TrajectoryError(path, "'controls' must be a group holding the datasets 'controls/vertices', "
                                    "'controls/times' and 'controls/positions'")
    out = {}
    for name in CONTROL_DATASETS:
        if name not in g:
            raise TrajectoryError(path, f"missing dataset 'controls/{name}'")
        ds = g[name]
        if not isinstance(ds, h5py.Dataset):
            raise TrajectoryError(path, f"'controls/{name}' is a group, expected a dataset")
        if ds.dtype.kind not in "fiu":
            raise TrajectoryError(path, f"'controls/{name}' must be numeric, got dtype {ds.dtype}")
        out[name] = ds[()]
    out["until"] = g.attrs["until"] if "until" in g.attrs else None
    return out


def _check_controls(path, raw, scene):
    """:class:`Controls` from the raw ``controls`` group, checked (indices of the scene's vertices,
    each once; times finite and strictly increasing; positions [S, D, 3] finite and near the scene;
    ``until`` a number > 0)."""
    v = np.asarray(raw["vertices"])
    n = scene.n_vertices
    if v.ndim != 1 or v.size == 0:
        raise TrajectoryError(path, f"'controls/vertices' must have shape [D] (D >= 1 driven vertices), "
                                    f"got {list(v.shape)}")
    bad = ~(np.isfinite(v) & (v == np.rint(v)) & (v >= 0) & (v < n))
    if bad.any():
        i = int(np.argmax(bad))
        raise TrajectoryError(path, f"'controls/vertices' has {v[i]:g} at entry {i}: not an index of the scene's "
                                    f"{n} vertices (0..{n - 1}, 0-based as 'track_vertex')")
    v = v.astype(np.int64)
    uniq, counts = np.unique(v, return_counts=True)
    if (counts > 1).any():
        j = int(uniq[np.argmax(counts > 1)])
        at = np.flatnonzero(v == j)
        raise TrajectoryError(path, f"'controls/vertices' lists vertex {j} twice (entries {at[0]} and {at[1]})")
    times = np.asarray(raw["times"], np.float64)
    if times.ndim != 1 or times.size == 0:
        raise TrajectoryError(path, f"'controls/times' must have shape [S] (S >= 1 samples), got {list(times.shape)}")
    if not np.isfinite(times).all():
        raise TrajectoryError(path, f"'controls/times' has a non-finite value at sample "
                                    f"{int(np.argmin(np.isfinite(times)))}")
    if len(times) > 1 and not (np.diff(times) > 0).all():
        i = int(np.argmin(np.diff(times) > 0)) + 1
        raise TrajectoryError(path, f"'controls/times' must be strictly increasing; sample {i} (t = {times[i]:g} s) "
                                    f"follows t = {times[i - 1]:g} s")
    pos = np.asarray(raw["positions"], np.float64)
    if pos.shape != (len(times), len(v), 3):
        raise TrajectoryError(path, f"'controls/positions' must have shape [S, D, 3] = [{len(times)}, {len(v)}, 3] "
                                    f"('controls/times' and 'controls/vertices'), got {list(pos.shape)}")
    if not np.isfinite(pos).all():
        s, d = (int(a[0]) for a in np.nonzero(~np.isfinite(pos).all(axis=2)))
        raise TrajectoryError(path, f"'controls/positions' has non-finite values (first at sample {s}, "
                                    f"driven vertex {d})")
    extent = float(max(np.max(np.ptp(scene.vertices, axis=0)), 1e-6))
    far = float(np.max(np.abs(pos - scene.vertices.mean(axis=0))))
    if far > TARGET_FAR * extent:
        raise TrajectoryError(path, f"'controls/positions' reaches {far:.3g} m from the scene's centre, "
                                    f"{far / extent:.3g} times the scene's size ({extent:.3g} m): wrong units?")
    until = raw.get("until")
    if until is not None:
        try:
            until = float(np.asarray(until, np.float64).reshape(()))
        except (TypeError, ValueError):
            raise TrajectoryError(path, f"attribute 'controls/until' must be a number (s), got {until!r}") from None
        if not (np.isfinite(until) and until > 0):
            raise TrajectoryError(path, f"attribute 'controls/until' (the release time) must be a finite "
                                        f"number > 0 s, got {until!r}")
    return Controls(vertices=v, times=times, positions=pos, until=until)


def _check_control_conflicts(path, controls, scene):
    """No controlled vertex is pinned or driven by the scene already."""
    fixed = set(np.asarray(scene.fixed).tolist())
    lines = {i: d.line for d in scene.driven for i in d.vertices}
    for j, i in enumerate(np.asarray(controls.vertices).tolist()):
        if i in lines:
            raise TrajectoryError(path, f"'controls/vertices' entry {j} drives vertex {i}, which the scene "
                                        f"{scene.path} already drives ('driven' on line {lines[i]}): drive it "
                                        "in one place only (remove the line, or leave it out of the controls)")
        if i in fixed:
            raise TrajectoryError(path, f"'controls/vertices' entry {j} drives vertex {i}, which the scene "
                                        f"{scene.path} pins ('fixed'): a vertex is either pinned or driven")


def scene_with_controls(scene, target):
    """The scene with a target's :class:`Controls` as driven paths (the semantics of the scene
    keyword ``driven``: kinematic, linear between samples, released at ``until``), one
    :class:`jaxplush.scene.parse.DrivenPath` per object that holds controlled vertices (source
    :data:`CONTROLS_SOURCE`, file the target's path, line 0); the scene itself when the target
    has none. A controlled vertex the scene pins or drives already is a
    :class:`jaxplush.errors.TrajectoryError` naming the target file."""
    from jaxplush.scene.parse import DrivenPath
    c = getattr(target, "controls", None)
    if c is None:
        return scene
    path = os.fspath(target.path)
    v = np.asarray(c.vertices, np.int64)
    if v.ndim != 1 or v.size == 0 or v.min() < 0 or v.max() >= scene.n_vertices:
        raise TrajectoryError(path, f"'controls/vertices' must index the scene's {scene.n_vertices} vertices")
    _check_control_conflicts(path, c, scene)
    oid = np.asarray(scene.object_id)[v]
    file = path if path.startswith("<") else os.path.abspath(path)
    objects = list(scene.objects)
    for o in np.unique(oid):
        cols = np.flatnonzero(oid == o)
        d = DrivenPath(source=CONTROLS_SOURCE, file=file, vertices=tuple(int(i) for i in v[cols]),
                       times=np.asarray(c.times, np.float64), positions=np.asarray(c.positions, np.float64)[:, cols],
                       until=None if c.until is None else float(c.until), line=0)
        objects[o] = dataclasses.replace(objects[o], driven=tuple(objects[o].driven) + (d,))
    return scene.replace(objects=tuple(objects))


def from_controls(driven_path):
    """Whether a :class:`jaxplush.scene.parse.DrivenPath` came from a target's controls
    (:func:`scene_with_controls`), not from a ``driven`` line."""
    return driven_path.line == 0 and driven_path.source == CONTROLS_SOURCE


def controls_of_scene(scene):
    """:class:`Controls` of every driven vertex of a scene (its ``driven`` paths merged: sampled at
    the union of their sample times, where each is linear between its own samples, so the merged
    path is the same path), or None when the scene drives none. Raises ValueError when the paths
    have different release times (one ``until`` per controls group)."""
    paths = scene.driven
    if not paths:
        return None
    until = {d.until for d in paths}
    if len(until) > 1:
        raise ValueError(f"the scene's driven paths have different release times "
                         f"({', '.join('none' if u is None else f'{u:g} s' for u in until)}); a target's controls "
                         "hold one")
    times = np.unique(np.concatenate([np.asarray(d.times, np.float64) for d in paths]))
    pos = np.concatenate([np.stack([d.position(t) for t in times]) if not np.array_equal(d.times, times)
                          else np.asarray(d.positions, np.float64) for d in paths], axis=1)
    return Controls(vertices=np.asarray(scene.driven_vertices, np.int64), times=times, positions=pos,
                    until=until.pop())


#: The correspondence datasets of a tracks target (docs/formats.md §4).
TRACK_DATASETS = ("track_vertex", "track_face", "track_barycentric", "track_vertices", "track_weights")


def _track_correspondence(path, raw, scene, m):
    """(vertices (M, 3) int64, weights (M, 3) float64) of a tracks target's correspondence, checked
    against the scene: one of track_vertex, track_face + track_barycentric, or track_vertices +
    track_weights."""
    given = [n for n in TRACK_DATASETS if n in raw]
    forms = [f for f in (("track_vertex",), ("track_face", "track_barycentric"), ("track_vertices", "track_weights"))
             if any(n in raw for n in f)]
    if not forms:
        raise TrajectoryError(path, "'tracks' needs its correspondence: dataset 'track_vertex' [M], or "
                                    "'track_face' [M] with 'track_barycentric' [M, 3]")
    if len(forms) > 1:
        raise TrajectoryError(path, f"'tracks' has two correspondences ({', '.join(given)}): give either "
                                    "'track_vertex' or 'track_face' with 'track_barycentric'")
    form = forms[0]
    for n in form:
        if n not in raw:
            raise TrajectoryError(path, f"missing dataset '{n}' (it goes with '{(set(form) - {n}).pop()}')")
    if form == ("track_vertex",):
        v = _index_dataset(path, "track_vertex", raw["track_vertex"], (m,), scene.n_vertices, "vertices")
        return np.repeat(v[:, None], 3, axis=1), np.tile(np.array([1.0, 0.0, 0.0]), (m, 1))
    if form[0] == "track_face":
        faces = np.asarray(raw["faces"] if "faces" in raw else scene.faces, np.int64)
        f = _index_dataset(path, "track_face", raw["track_face"], (m,), len(faces), "faces")
        vertices, weights = faces[f], _weights_dataset(path, "track_barycentric", raw["track_barycentric"], m)
    else:
        vertices = _index_dataset(path, "track_vertices", raw["track_vertices"], (m, 3), scene.n_vertices, "vertices")
        weights = _weights_dataset(path, "track_weights", raw["track_weights"], m)
    return vertices, weights


def _index_dataset(path, name, raw, shape, n, what):
    """(shape) int64 indices in [0, n) from dataset ``name``."""
    a = np.asarray(raw)
    if a.shape != shape:
        raise TrajectoryError(path, f"'{name}' must have shape {list(shape)} (one per track), got {list(a.shape)}")
    bad = ~(np.isfinite(a) & (a == np.rint(a)) & (a >= 0) & (a < n)) if a.size else np.zeros(shape, bool)
    if bad.any():
        i = tuple(int(k[0]) for k in np.nonzero(bad))
        raise TrajectoryError(path, f"'{name}' has {a[i]:g} at track {i[0]}: not an index of the scene's "
                                    f"{n} {what} (0..{n - 1})")
    return a.astype(np.int64)


def _weights_dataset(path, name, raw, m):
    """(M, 3) float64 barycentric weights from dataset ``name``: >= 0 and summing to 1 (within
    BARYCENTRIC_TOLERANCE)."""
    w = np.asarray(raw, np.float64)
    if w.shape != (m, 3):
        raise TrajectoryError(path, f"'{name}' must have shape [{m}, 3] (one row per track), got {list(w.shape)}")
    tol = BARYCENTRIC_TOLERANCE
    bad = ~np.isfinite(w).all(axis=1) | (w < -tol).any(axis=1) | (np.abs(w.sum(axis=1) - 1.0) > tol)
    if bad.any():
        i = int(np.argmax(bad))
        raise TrajectoryError(path, f"'{name}' row {i} ({', '.join(f'{x:.9g}' for x in w[i])}) is not barycentric: "
                                    f"weights must be >= 0 and sum to 1 (within {tol:g})")
    return w


def _track_datasets(vertices, weights):
    """The datasets that store a correspondence: ``track_vertex`` where every track is a vertex
    ([v, v, v] with weights [1, 0, 0]), else ``track_vertices`` and ``track_weights``."""
    v, w = np.asarray(vertices, np.int64), np.asarray(weights, np.float64)
    if np.all(v == v[:, :1]) and np.array_equal(w, np.tile([1.0, 0.0, 0.0], (len(w), 1))):
        return {"track_vertex": v[:, 0]}
    return {"track_vertices": v, "track_weights": w}


def _check_data_shape(path, kind, data, scene):
    kind = TargetKind(kind)
    if data.ndim != 3 or data.shape[2] != 3:
        raise TrajectoryError(path, f"'{kind}' must have shape {kind.shape_text}, got {list(data.shape)}")
    n_frames, n = data.shape[:2]
    if n_frames == 0:
        raise TrajectoryError(path, f"'{kind}' holds no frames")
    if n == 0:
        raise TrajectoryError(path, f"'{kind}' holds no points")
    if kind.every_vertex and n != scene.n_vertices:
        raise TrajectoryError(path, f"'positions' has {n} vertices but the scene {scene.path} has "
                                    f"{scene.n_vertices}")


def _check_object_names(path, names, scene):
    if names is None:
        return
    names = [x.decode() if isinstance(x, bytes) else str(x) for x in np.atleast_1d(names)]
    if len(names) != scene.n_objects:
        raise TrajectoryError(path, f"the target has {len(names)} object(s) {names} but the scene "
                                    f"{scene.path} has {scene.n_objects} {list(scene.object_names)}")
    if names != list(scene.object_names):
        raise TrajectoryError(path, f"'object_names' {names} differ from the scene {scene.path}'s "
                                    f"{list(scene.object_names)}: the target's objects are other objects "
                                    "or in another order")


def _check_object_id(path, oid, scene, n):
    if oid is None:
        return
    oid = np.asarray(oid)
    if oid.shape != (n,):
        raise TrajectoryError(path, f"'object_id' must have shape [{n}], got {list(oid.shape)}")
    if oid.size and not (np.all(np.isfinite(oid)) and np.all(oid == np.rint(oid)) and oid.min() >= 0):
        raise TrajectoryError(path, "'object_id' must hold integers >= 0 (an object index per vertex)")
    oid = oid.astype(np.int64)
    n_obj = int(oid.max()) + 1 if oid.size else 0
    if n_obj != scene.n_objects:
        raise TrajectoryError(path, f"'object_id' describes {n_obj} object(s) but the scene "
                                    f"{scene.path} has {scene.n_objects}")
    if not np.array_equal(oid, scene.object_id):
        raise TrajectoryError(path, f"'object_id' does not match the scene {scene.path}: its "
                                    "objects' vertices are numbered differently")


def _check_times(path, raw_times, n_frames, kind):
    """(T,) float64 frame times: one per frame, finite, >= 0, strictly increasing."""
    times = np.asarray(raw_times, np.float64)
    if times.shape != (n_frames,):
        raise TrajectoryError(path, f"'times' must have shape [{n_frames}] (one per frame of '{kind}'), "
                                    f"got {list(times.shape)}")
    if not np.all(np.isfinite(times)):
        raise TrajectoryError(path, f"'times' has non-finite values (first at frame "
                                    f"{int(np.argmin(np.isfinite(times)))})")
    if times[0] < 0:
        raise TrajectoryError(path, f"'times' must be >= 0, got {times[0]:g} at frame 0")
    if n_frames > 1 and np.any(np.diff(times) <= 0):
        i = int(np.argmax(np.diff(times) <= 0)) + 1
        raise TrajectoryError(path, f"'times' must be strictly increasing; frame {i} (t = {times[i]:g} s) "
                                    f"follows t = {times[i - 1]:g} s")
    return times


def _target_dt(path, dt_attr, dt):
    """The fit's time step: ``dt``, else the target's 'dt' attribute; a positive float."""
    if dt is None:
        if dt_attr is None:
            raise TrajectoryError(path, "no 'dt' attribute: give the fit's time step (--dt)")
        dt = dt_attr
        where = "the target's 'dt' attribute"
    else:
        where = "dt"
    try:
        dt = float(np.asarray(dt).reshape(()))
    except (TypeError, ValueError):
        raise TrajectoryError(path, f"{where} must be a number, got {dt!r}") from None
    if not (np.isfinite(dt) and dt > 0):
        raise TrajectoryError(path, f"{where} must be a positive number, got {dt!r}")
    return dt


def _check_data_values(path, kind, data, scene):
    """Finite values (points, tracks: or rows of three NaNs, padding or not seen), within TARGET_FAR
    scene sizes of the scene's centre; every track seen in some frame."""
    kind = TargetKind(kind)
    pad = np.isnan(data).all(axis=2) if kind.padded else np.zeros(data.shape[:2], bool)
    bad = ~np.isfinite(data).all(axis=2) & ~pad
    if bad.any():
        t, i = (int(a[0]) for a in np.nonzero(bad))
        what = kind.unit
        raise TrajectoryError(path, f"'{kind}' has non-finite values (first at frame {t}, {what} {i})"
                              + (f"; a {what} that is absent must be NaN in all three coordinates"
                                 if kind.padded and np.isnan(data[t, i]).any() else ""))
    if pad.all():
        raise TrajectoryError(path, "'tracks' holds no points: every row is NaN (no track is ever seen)"
                              if kind.material_points else "'points' holds no points: every row is NaN padding")
    if kind is TargetKind.TRACKS and pad.all(axis=0).any():
        i = int(np.argmax(pad.all(axis=0)))
        raise TrajectoryError(path, f"'tracks' never sees track {i}: it is NaN in every frame (leave it out)")
    extent = float(max(np.max(np.ptp(scene.vertices, axis=0)), 1e-6))
    far = float(np.max(np.abs(data[~pad] - scene.vertices.mean(axis=0))))
    if far > TARGET_FAR * extent:
        raise TrajectoryError(path, f"'{kind}' reaches {far:.3g} m from the scene's centre, {far / extent:.3g} times "
                                    f"the scene's size ({extent:.3g} m): wrong units, or a target of another scene?")


def _noise_attr(path, noise):
    """The target's 'noise' attribute as a float >= 0, or None."""
    if noise is None:
        return None
    try:
        noise = float(np.asarray(noise, np.float64).reshape(()))
    except (TypeError, ValueError):
        raise TrajectoryError(path, f"attribute 'noise' must be a number (m), got {noise!r}") from None
    if not (np.isfinite(noise) and noise >= 0):
        raise TrajectoryError(path, f"attribute 'noise' must be a finite number >= 0, got {noise!r}")
    return noise


def _grid_steps(path, times, dt, stored_dtype):
    """(T,) int64 step of every frame time on the dt grid; TrajectoryError when off the grid."""
    ratio = np.asarray(times, np.float64) / dt
    if ratio[-1] > 2 ** 31:
        raise TrajectoryError(path, f"the last frame at t = {times[-1]:.9g} s is {ratio[-1]:.3g} steps of dt = "
                                    f"{dt:g} s: too many steps to simulate (times in seconds?)")
    steps = np.rint(ratio)
    eps = np.finfo(stored_dtype if np.dtype(stored_dtype).kind == "f" else np.float64).eps
    off = np.abs(ratio - steps) > GRID_TOLERANCE + 8 * eps * np.abs(ratio)
    if off.any():
        i = int(np.argmax(off))
        raise TrajectoryError(path, f"frame {i} at t = {times[i]:.9g} s is not on the dt = {dt:g} s grid "
                                    f"({ratio[i]:.6g} steps); resample the target or give a dt that "
                                    "divides every frame time")
    steps = steps.astype(np.int64)
    if len(steps) > 1 and np.any(np.diff(steps) <= 0):
        i = int(np.argmax(np.diff(steps) <= 0)) + 1
        raise TrajectoryError(path, f"frames {i - 1} and {i} fall on the same step of the dt = {dt:g} s grid")
    return steps


def _same_faces(a, b):
    if a.ndim != 2 or a.shape != b.shape:
        return False
    key = lambda f: np.unique(np.sort(f.astype(np.int64), axis=1), axis=0)  # noqa: E731
    return np.array_equal(key(a), key(b))


def make_target(scene, steps, dt, save_every, *, params=None, frames=None, noise=0.0, point_cloud=False,
                n_points=None, tracks=None, seed=0, sim=None, controls=False):
    """Simulate a synthetic target with known parameters (for tests, notebooks and benchmarks).

    Args:
      scene: :class:`jaxplush.scene.parse.Scene`.
      steps, dt, save_every: the rollout: ``steps`` steps of ``dt``, a frame every ``save_every``
        steps (and at the last step), frame 0 the initial state.
      params: :class:`jaxplush.types.Params` of the truth (default: the scene's).
      frames: which saved frames to keep (indices into the saved frames, frame 0 = step 0;
        default all but the initial one).
      noise: standard deviation (m) of Gaussian noise added to every coordinate.
      point_cloud: store ``points`` instead of ``positions``: per frame ``n_points`` points drawn
        uniformly (by area) on the simulated surface, then noised; no correspondence with vertices.
      n_points: points per frame (default: the vertex count).
      tracks: an int M: store ``tracks`` instead of ``positions``: M points drawn once uniformly
        (by area) on the rest surface, as (face, barycentric coordinates), followed through
        every frame, then noised. With ``point_cloud`` too: a mixed target (both, same frames).
      seed: random seed of the noise and the samples.
      sim: a prebuilt simulator for ``scene`` and ``dt``.
      controls: store the scene's driven paths as the target's :class:`Controls`
        (:func:`controls_of_scene`; fit it with the scene without its ``driven`` lines).

    Returns:
      :class:`Target` with ``path`` "<memory>" (``.save(path, scene)`` writes it).
    """
    import jax
    import jaxplush
    from jaxplush.stepping import diagnostics
    from jaxplush.errors import SimulationError
    from jaxplush.fitting.judge.identifiability import frames_at_steps
    steps, save_every = int(steps), int(save_every)
    if controls and not scene.driven:
        raise ValueError(f"controls=True: the scene {scene.path} drives no vertices (no 'driven' line)")
    if steps < 1 or save_every < 1:
        raise ValueError(f"steps and save_every must be >= 1, got {steps} and {save_every}")
    saved = list(range(0, steps + 1, save_every))
    if saved[-1] != steps:
        saved.append(steps)
    sim = sim or jaxplush.make_simulator(scene, dt)
    p = sim.params(params)
    pos, codes = jax.jit(lambda q: frames_at_steps(sim, q, sim.init_fn(q), saved))(p)
    bad = diagnostics.first_failure(np.asarray(codes))
    if bad is not None:
        t, o, c = bad
        raise SimulationError(saved[t], o, scene.object_names[o], diagnostics.MESSAGES[c])
    pos = np.asarray(pos, np.float64)
    idx = np.arange(1, len(pos)) if frames is None else np.arange(len(pos))[frames]
    pos, steps_kept = pos[idx], np.asarray(saved, np.int64)[idx]
    rng = np.random.default_rng(seed)
    tv = tw = trk = cloud = None
    if tracks is not None:
        if isinstance(tracks, bool) or int(tracks) != tracks or int(tracks) < 1:
            raise ValueError(f"tracks must be an int >= 1, got {tracks!r}")
        face, tw = sample_barycentric(np.asarray(scene.vertices, np.float64), scene.faces, int(tracks), rng)
        tv = np.asarray(scene.faces, np.int64)[face]
        trk = np.einsum("mk,tmkc->tmc", tw, pos[:, tv])
    if point_cloud:
        cloud = np.stack([sample_surface(x, scene.faces, n_points or scene.n_vertices, rng) for x in pos])
    if noise:          # the cloud's noise first, then the tracks' (a single kind draws as before)
        if cloud is not None:
            cloud = cloud + rng.normal(0.0, noise, cloud.shape)
        if trk is not None:
            trk = trk + rng.normal(0.0, noise, trk.shape)
        if cloud is None and trk is None:
            pos = pos + rng.normal(0.0, noise, pos.shape)
    truth = {n: np.asarray(v, np.float64) for n, v in zip(p._fields, p.as_numpy())}
    return Target(positions=pos if cloud is None and trk is None else None, points=cloud,
                  steps=steps_kept, times=steps_kept * float(dt), dt=float(dt), path="<memory>",
                  noise=float(noise) if noise else 0.0, params=truth,
                  tracks=trk, track_vertices=tv, track_weights=tw,
                  controls=controls_of_scene(scene) if controls else None)


def sample_surface(x, faces, n, rng):
    """(n, 3) points drawn uniformly by area on the triangle mesh (x (V, 3), faces (F, 3))."""
    f, w = sample_barycentric(x, faces, n, rng)
    a, b, c = (x[faces[f, k]] for k in range(3))
    return w[:, 0, None] * a + w[:, 1, None] * b + w[:, 2, None] * c


def sample_barycentric(x, faces, n, rng):
    """(face (n,) int64, barycentric (n, 3)) of n points drawn uniformly by area on the triangle
    mesh (x (V, 3), faces (F, 3))."""
    from jaxplush.io.capture import sample_barycentric as draw
    return draw(x, faces, n, rng)
