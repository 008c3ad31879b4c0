"""Batched parameter sweeps: one compiled, batched rollout over a grid of parameter values.

    result = sweep(scene, {"k": np.linspace(100, 1000, 16), "nmol": np.geomspace(1e-3, 1e-2, 8)},
                   steps=4000, dt=2.5e-4, target="target.h5")
    result.loss.reshape(result.shape)      # (16, 8) loss landscape
    result.best()                          # the parameters at the minimum
    result.save("SWEEP.h5"); result.plot("landscape.png")

It reads like ``jax.vmap`` over parameter points: every point is an independent simulation of
the scene with some parameters replaced. Under the hood the points run in chunks of a static
batch size B through :mod:`jaxplush.stepping.batched` (the batch on the last axis, for throughput, which a
plain ``vmap`` of the single-scene step does not give; see benchmarks/RESULTS.md, "Batch sweeps"),
so a grid of any size compiles once. A sweep larger than B runs in equal batches of whole
chunks (:func:`_outer_batch`); the last batch is padded by repeating its last point.

Parameter names are those of :data:`jaxplush.types.PARAM_NAMES` (``k`` is ``k_structural``).
A plain name applies to every object; ``name@object`` (object name or 0-based index) to one.
``grid`` takes the cartesian product of its axes (C order: the last axis varies fastest);
``points`` gives the points themselves (equal-length value lists, zipped).

Per point the result holds the parameters, the final positions, per object the final volume,
centroid height (y) and largest vertex displacement from the rest shape, the health record
(failure code and exact step, first volume-clamp step), and with a target the loss

    L = (1/T) sum_j d(x(t_j), y_j),

d the fit's frame distance (:meth:`jaxplush.fitting.targets.kinds.Kind.mean_sq`): the mean squared vertex
distance for a ``positions`` target, each observed point's squared distance to the simulated
surface for a ``points`` target (rows of NaN are a frame's padding), each seen track's squared
distance to its simulated position for a ``tracks`` target (every observation weighed alike), in
m²; a ``mixed`` target's two terms are weighed as the fit weighs them. L is the fit's loss times
its normaliser s², so a sweep's best point is the fit's. A point whose
rollout blew up keeps its last healthy state as final positions (``final_step`` says which
step), a NaN loss and summaries, and its failure is listed in ``fail_code``/``fail_step``; it is
never silently returned as NaN positions.

File schema of :meth:`SweepResult.save` (HDF5, written atomically; docs/formats.md §6), P points,
O objects, V vertices, A swept axes:

    attrs: format = "jaxplush-sweep", format_version = 1, kind ("grid" | "points"), shape [A or 1],
           labels [A] (e.g. "k_structural", "nmol@ball"), steps, dt, integrator, save_every
           (0: none), target_path ("" without a target), target_kind, jaxplush_version,
           scene (the full scene text), scene_path, wall_time
    axes/<label>          [n_a] grid values of each axis (grid) or [P] values (points)
    values                [P, A] the swept values of every point
    params/<name>         [P, O] every parameter of every point (PARAM_NAMES)
    final_positions       [P, V, 3] m
    final_step            [P] step of final_positions (steps, or the last healthy step)
    summary/volume        [P, O] m³          summary/centroid_height   [P, O] m
    summary/max_displacement [P, O] m
    failure/code          [P, O] int (jaxplush.stepping.diagnostics codes; 0 ok)  failure/step [P, O] (-1 none)
    failure/warn_step     [P, O] first step with the volume clamp active (-1 none)
    failure/messages      [n_codes] the message of each code (index = code)
    loss                  [P] m² (only with a target; NaN where the point failed)
    frames, frame_steps   [T, P, V, 3], [T] (only with save_every; a failed point's frames after
                          its final_step repeat its final_positions)
    faces [F, 3], object_id [V], object_names [O]
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import os
import re
import sys
import time
import warnings
from functools import lru_cache

import jax
import jax.numpy as jnp
import numpy as np

from jaxplush.stepping import batched
from jaxplush.stepping import diagnostics
from jaxplush.errors import JaxplushError, SimulationWarning, VolumeClampWarning
from jaxplush.fitting.targets.kinds import TargetKind
from jaxplush.progress import Progress
from jaxplush.types import PARAM_NAMES, Params

ALIASES = {"k": "k_structural"}
QUANTITIES = ("loss", "volume", "centroid_height", "max_displacement")
FORMAT = "jaxplush-sweep"
FORMAT_VERSION = 1


class SweepError(JaxplushError):
    """A bad sweep specification (unknown parameter or object, bad values, target mismatch)."""


# --------------------------------------------------------------------------- the grid

@dataclasses.dataclass(frozen=True)
class _Axis:
    label: str          # as given back to the user: canonical name, "@object" when per object
    name: str           # PARAM_NAMES entry
    objects: tuple      # object indices it applies to
    values: np.ndarray  # (n,) values


def canonical_label(scene, label):
    """Resolve ``name`` or ``name@object`` -> (label, name, object indices); SweepError if bad."""
    if not isinstance(label, str) or not label.strip():
        raise SweepError(f"parameter name must be a non-empty string, got {label!r}")
    name, at, obj = label.strip().partition("@")
    name = ALIASES.get(name.strip(), name.strip())
    if name not in PARAM_NAMES:
        raise SweepError(f"unknown parameter {label!r}; expected one of {', '.join(PARAM_NAMES)} "
                         f"(k = k_structural), optionally as name@object")
    if not at:
        return name, name, tuple(range(scene.n_objects))
    obj = obj.strip()
    if not obj:
        raise SweepError(f"{label!r}: no object after '@' (objects: {', '.join(scene.object_names)})")
    names = scene.object_names
    if obj in names:
        i = names.index(obj)
    elif obj.isdigit() and int(obj) < scene.n_objects:
        i = int(obj)
    else:
        raise SweepError(f"{label!r}: no object {obj!r} in the scene (objects: {', '.join(names)})")
    return f"{name}@{names[i]}", name, (i,)


def _check_values(scene, label, name, objects, values):
    try:
        v = np.asarray(values, np.float64)
    except (TypeError, ValueError):
        raise SweepError(f"{label}: values must be numbers, got {values!r}") from None
    if v.ndim == 0:
        v = v[None]
    if v.ndim != 1 or v.size == 0:
        raise SweepError(f"{label}: values must be a non-empty 1-D list, got shape {v.shape}")
    if not np.all(np.isfinite(v)):
        raise SweepError(f"{label}: values must be finite, got {v[~np.isfinite(v)][0]!r}")
    bad = {
        "k_structural": (v < 0, "must be >= 0"),
        "damping": ((v != 0) & (v < 1), "must be 0 (off) or >= 1 (factor f = 1/D per step)"),
        "dashpot": (v < 0, "must be >= 0"),
        "drag": (v < 0, "must be >= 0"),
        "total_weight": (v <= 0, "must be > 0"),
        "nmol": (v <= 0, "must be > 0"),
    }[name]
    if np.any(bad[0]):
        raise SweepError(f"{label}: {v[bad[0]][0]:g} {bad[1]}")
    if name == "nmol":
        no_gas = [scene.objects[o].name for o in objects if not scene.objects[o].has_gas]
        if no_gas:
            raise SweepError(f"{label}: object(s) {', '.join(no_gas)} have no gas (no 'nmol' in the scene); "
                             f"sweep nmol only for objects with gas")
    return v


def _axes(scene, spec, what):
    if not isinstance(spec, dict) or not spec:
        raise SweepError(f"{what} must be a non-empty dict of parameter name -> values")
    axes, seen = [], {}
    for label, values in spec.items():
        lab, name, objs = canonical_label(scene, label)
        if name == "k_structural" and getattr(scene, "has_k_field", False):
            raise SweepError(f"{label!r}: this scene's spring stiffness is a per-edge field (its k_region/k_edge "
                             f"lines), and a sweep sets one k per object; sweep its other parameters (every "
                             f"point keeps the field), or sweep scenes written with the fields you want")
        for o in objs:
            if (name, o) in seen:
                raise SweepError(f"{label!r} and {seen[(name, o)]!r} both set {name} of object "
                                 f"{scene.objects[o].name!r}")
            seen[(name, o)] = label
        v = _check_values(scene, lab, name, objs, values)
        if what == "grid" and len(np.unique(v)) < len(v):
            u, n = np.unique(v, return_counts=True)
            raise SweepError(f"{lab}: grid values must be distinct, {u[n > 1][0]:g} appears {n[n > 1][0]} times")
        axes.append(_Axis(lab, name, objs, v))
    return tuple(axes)


def _point_values(axes, kind):
    """(P, A) swept values of every point: the cartesian product (grid) or the zip (points)."""
    if kind == "grid":
        mesh = np.meshgrid(*(a.values for a in axes), indexing="ij")
        return np.stack([m.reshape(-1) for m in mesh], axis=1)
    n = {len(a.values) for a in axes}
    if len(n) != 1:
        raise SweepError(f"points: every parameter needs the same number of values, got "
                         f"{', '.join(f'{a.label}: {len(a.values)}' for a in axes)}")
    return np.stack([a.values for a in axes], axis=1)


def _point_params(scene, axes, values):
    """Params of (P, O) float64 arrays: the scene's values with the swept ones replaced."""
    n = len(values)
    out = {name: np.repeat(np.asarray(getattr(scene.params, name), np.float64)[None], n, axis=0)
           for name in PARAM_NAMES}
    for j, a in enumerate(axes):
        for o in a.objects:
            out[a.name][:, o] = values[:, j]
    return Params(**out)


#: The most points one sweep may have, whatever the memory (a bound of its own, so that a machine
#: whose free memory is unknown still refuses an absurd grid before building it).
MAX_POINTS = 2 ** 31 - 1


def point_bytes(scene, n_axes, n_frames=0, itemsize=4):
    """Host memory (bytes, an estimate) one sweep point needs: its swept values (three float64
    copies at the peak of the cartesian product), its parameters (six float64 per object), its
    final positions and ``n_frames`` saved frames (``itemsize`` bytes a coordinate, twice: the
    batches' results and their concatenation), its summaries, failure record and loss."""
    n_obj = max(1, len(getattr(scene, "objects", ()) or ()))
    shape = int(np.shape(scene.vertices)[0]) * 3 * int(itemsize)
    return 24 * int(n_axes) + 48 * n_obj + 2 * shape * (1 + int(n_frames)) + 64 * n_obj + 16


def available_memory():
    """Bytes of memory available to this process now (Linux: MemAvailable), or None if unknown."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return int(os.sysconf("SC_AVPHYS_PAGES")) * int(os.sysconf("SC_PAGE_SIZE"))
    except (AttributeError, OSError, ValueError):
        return None


def _fmt_bytes(n):
    for unit, size in (("TB", 1e12), ("GB", 1e9), ("MB", 1e6), ("kB", 1e3)):
        if n >= size:
            return f"{n / size:.3g} {unit}"
    return f"{int(n)} bytes"


def check_sweep_size(scene, n_points, n_axes, n_frames=0, itemsize=4):
    """Before anything is allocated: a :class:`SweepError` (saying how many points were asked
    and the limit) when ``n_points`` exceed :data:`MAX_POINTS` or their results
    (:func:`point_bytes` each) would not fit in the memory available now."""
    n_points = int(n_points)
    each = point_bytes(scene, n_axes, n_frames, itemsize)
    avail = available_memory()
    room = MAX_POINTS if avail is None else min(MAX_POINTS, avail // each)
    if n_points <= room:
        return
    need = f"{n_points:,} points would need about {_fmt_bytes(n_points * each)} of memory " \
           f"({_fmt_bytes(each)} a point" + (f", {n_frames} saved frames each" if n_frames else "") + ")"
    if avail is not None and avail // each < MAX_POINTS:
        raise SweepError(f"{need}; {_fmt_bytes(avail)} is available, room for at most {max(0, room):,} points")
    raise SweepError(f"{need}; a sweep has at most {MAX_POINTS:,} points")


def _n_points(axes, kind):
    """The number of points, from the axes' lengths (nothing allocated)."""
    if kind == "grid":
        return math.prod(len(a.values) for a in axes)
    return len(axes[0].values)


def _normalise_points(points):
    if isinstance(points, (list, tuple)):
        if not points or not all(isinstance(p, dict) for p in points):
            raise SweepError("points must be a dict of name -> values or a non-empty list of dicts")
        keys = list(points[0])
        for i, p in enumerate(points):
            if set(p) != set(keys):
                raise SweepError(f"points: every point must set the same parameters; point 0 sets "
                                 f"{', '.join(map(str, keys))}, point {i} sets {', '.join(map(str, p))}")
        return {k: [p[k] for p in points] for k in keys}
    return points


# --------------------------------------------------------------------------- targets and frames

def _load_target(target, scene, dt):
    """A jaxplush.fitting.targets.Target on the dt grid (a path is loaded and validated against the scene)."""
    if isinstance(target, (str, os.PathLike)):
        from jaxplush.fitting.targets import load_target
        return load_target(target, scene, dt)
    if hasattr(target, "on_grid") and float(getattr(target, "dt", dt)) != float(dt):
        return target.on_grid(dt)
    return target


def _target_frames(target, scene, steps):
    """(kind, steps (T,), data (T, N, 3)) of a target, checked against the scene and horizon.

    A tracks target's correspondence travels with its frames (through the rollout's ``aux``, so
    :func:`_observer` stays one cached function per kind): its data is (T, M, 10), per row the
    observed position (0 where not seen), the three vertex indices (as floats: exact below 2^24),
    the barycentric weights, and the row's weight in the loss (T / N for a seen row, N seen rows
    over T frames, else 0; see :func:`frame_loss`)."""
    pos = getattr(target, "positions", None)
    pts = getattr(target, "points", None)
    trk = getattr(target, "tracks", None)
    if pos is None and pts is not None and trk is not None:      # a scan with tracks: both, side by side
        _, tsteps, cloud = _target_frames(dataclasses.replace(target, tracks=None), scene, steps)
        _, _, rows = _target_frames(dataclasses.replace(target, points=None), scene, steps)
        if len(cloud) != len(rows):
            raise SweepError(f"target points have {len(cloud)} frames but its tracks {len(rows)}")
        pad = np.zeros(cloud.shape[:2] + (rows.shape[2] - cloud.shape[2],))
        return TargetKind.MIXED, tsteps, np.concatenate([np.concatenate([cloud, pad], axis=2), rows], axis=1)
    if pos is not None:
        kind, data = TargetKind.POSITIONS, np.asarray(pos, np.float64)
        if data.ndim != 3 or data.shape[1:] != (scene.n_vertices, 3):
            raise SweepError(f"target positions must have shape [T, {scene.n_vertices}, 3] for this scene, "
                             f"got {list(data.shape)}")
    elif pts is not None:
        kind, data = TargetKind.POINTS, np.asarray(pts, np.float64)
        if data.ndim != 3 or data.shape[2] != 3 or data.shape[1] < 1:
            raise SweepError(f"target points must have shape [T, M, 3], got {list(data.shape)}")
    elif trk is not None:
        kind, data = TargetKind.TRACKS, np.asarray(trk, np.float64)
        if data.ndim != 3 or data.shape[2] != 3 or data.shape[1] < 1:
            raise SweepError(f"target tracks must have shape [T, M, 3], got {list(data.shape)}")
    else:
        raise SweepError("the target has neither positions, points nor tracks")
    tsteps = np.asarray(target.steps, np.int64).reshape(-1)
    if len(tsteps) != len(data) or len(tsteps) == 0:
        raise SweepError(f"target: {len(tsteps)} frame steps for {len(data)} frames")
    if np.any(np.diff(tsteps) <= 0):
        raise SweepError(f"target frame steps must be strictly increasing, got {tsteps.tolist()}")
    if np.any(tsteps < 0) or tsteps.max() > steps:
        raise SweepError(f"target frames reach step {int(tsteps.max())} but the sweep runs {steps} steps; "
                         f"use steps >= {int(tsteps.max())}")
    pad = np.isnan(data).all(axis=2) if kind.padded else np.zeros(data.shape[:2], bool)
    if not np.all(np.isfinite(data[~pad])):
        raise SweepError("target frames contain non-finite values" + (
            f" (a {'track' if kind.material_points else 'point cloud'}'s absent points are rows of NaN in all three "
            "coordinates)" if kind.padded else ""))
    if kind is TargetKind.TRACKS:
        return kind, tsteps, _track_rows(target, scene, data, ~pad)
    empty = np.flatnonzero(pad.all(axis=1))
    if kind.every_vertex:
        return kind, tsteps, data
    if empty.size:
        raise SweepError(f"target frame {int(empty[0])} (step {int(tsteps[empty[0]])}) holds no points: "
                         "a frame's distance to the surface needs at least one; leave the frame out")
    # a cloud's rows as the fit weighs them: (x, y, z, T / N) per observed point (N over T frames),
    # NaN padding as (0, 0, 0, 0)
    rw = np.where(~pad, len(data) / float((~pad).sum()), 0.0)[..., None]
    return kind, tsteps, np.concatenate([np.where(~pad[..., None], data, 0.0), rw], axis=2)


def _track_rows(target, scene, data, seen):
    """(T, M, 10) the rows of a tracks target as :func:`_target_frames` passes them on."""
    tv, tw = getattr(target, "track_vertices", None), getattr(target, "track_weights", None)
    tv = np.asarray(tv if tv is not None else [], np.int64)
    tw = np.asarray(tw if tw is not None else [], np.float64)
    m = data.shape[1]
    if tv.shape != (m, 3) or tw.shape != (m, 3):
        raise SweepError(f"target tracks need track_vertices and track_weights of shape [{m}, 3], got "
                         f"{list(tv.shape)} and {list(tw.shape)}")
    if tv.min() < 0 or tv.max() >= scene.n_vertices:
        raise SweepError(f"target track_vertices index vertices outside 0..{scene.n_vertices - 1}")
    if scene.n_vertices >= 2 ** 24:
        raise SweepError(f"a tracks target needs fewer than 2^24 vertices (the scene has {scene.n_vertices})")
    if not seen.any():
        raise SweepError("the target's tracks are never seen: every row is NaN")
    t = len(data)
    rw = np.where(seen, t / float(seen.sum()), 0.0)[..., None]
    rows = np.broadcast_to(np.concatenate([tv, tw], axis=1)[None], (t, m, 6))
    return np.concatenate([np.where(seen[..., None], data, 0.0), rows, rw], axis=2)


def _frame_period(steps, required):
    """Steps per checked frame: divides every required step (target frames, saves); health and
    progress are checked at least every steps/50 steps where the required steps allow it."""
    cap = max(1, steps // 50)
    req = [int(s) for s in required if 0 < s]
    if not req:
        return cap
    g = math.gcd(*req)
    if g <= cap:
        return g
    return max(d for d in range(1, cap + 1) if g % d == 0)


@lru_cache(maxsize=None)
def _observer(kind, keep_positions):
    """The static per-frame ``observe`` of :func:`jaxplush.stepping.batched.rollout` for a sweep: the
    loss contribution of target frames (a ``lax.cond``: other frames cost nothing) and,
    optionally, the positions."""

    def observe(params, i, x, aux):
        out = {}
        if kind is not None:
            j = aux["table"][aux["frame0"] + i]
            b = x[0].shape[1]
            out["loss"] = jax.lax.cond(j >= 0, lambda: frame_loss(kind, x, aux["data"][jnp.maximum(j, 0)],
                                                                  aux.get("surface")),
                                       lambda: jnp.zeros((b,), x[0].dtype))
        if keep_positions:
            out["x"] = batched.positions_observer(params, i, x, aux)
        return out

    return observe


def frame_loss(kind, x, y, surface=None):
    """(B,) the fit's frame distance d_j (m², :meth:`jaxplush.fitting.targets.kinds.Kind.mean_sq`) of every
    batch point's positions x (tuple of 3 (V, B)) to a target frame y, in the rows
    :func:`_target_frames` lays out: the mean squared vertex distance (y (V, 3)); for a scan (y
    (M, 4): a point and its weight T / N) the sum of each point's squared distance to the
    simulated surface times its weight (``surface``: (faces, vertex_faces) of the scene); for
    tracks (y (M, 10)) the weighted sum of the seen tracks' squared distances to their simulated
    positions. A mixed target's kind is ("mixed", M_points, f_points, f_tracks) and y its points'
    rows then its tracks' (M_points + M_tracks, 10): f_points d_points + f_tracks d_tracks, the
    fit's weights of its two terms (each over its own normaliser) times the fit's combined
    normaliser, so a sweep's loss is the fit's loss times its s², in m²."""
    if isinstance(kind, tuple):
        _, cut, fp, ft = kind
        return fp * frame_loss(TargetKind.POINTS, x, y[:cut, :4], surface) + ft * frame_loss(TargetKind.TRACKS, x, y[cut:])
    kind = TargetKind(kind)
    if kind.every_vertex:
        return sum((x[c] - y[:, c][:, None]) ** 2 for c in range(3)).mean(axis=0)
    if kind.material_points:
        idx = y[:, 3:6].astype(jnp.int32)                              # (M, 3)
        d2 = sum((sum(y[:, 6 + k, None] * x[c][idx[:, k]] for k in range(3)) - y[:, c, None]) ** 2
                 for c in range(3))                                    # (M, B)
        return jnp.sum(y[:, 9, None] * d2, axis=0)
    from jaxplush.fitting.objective.losses import point_surface_distance2
    faces, vfaces = surface
    pts = jnp.stack(x, axis=-1).transpose(1, 0, 2)                    # (B, V, 3)
    return jax.lax.map(lambda xb: jnp.sum(y[:, 3] * point_surface_distance2(xb, y[:, :3], faces, vfaces)), pts)


# --------------------------------------------------------------------------- result

@dataclasses.dataclass(frozen=True, eq=False)
class SweepResult:
    """The outcome of :func:`sweep` (numpy). P points, O objects, V vertices, A swept axes.

    Attributes:
      kind: "grid" (cartesian product) or "points".
      labels: (A,) swept parameter labels ("k_structural", "nmol@ball", ...).
      axes: dict label -> values: the grid axes (grid) or each point's values (points).
      shape: grid shape (n_1, ..., n_A), or (P,) for points; ``reshape(q)`` maps a (P, ...)
        quantity onto it.
      values: (P, A) swept values of every point.
      params: :class:`jaxplush.types.Params` of (P, O) arrays: every parameter of every point.
      final_positions: (P, V, 3) positions at ``final_step`` (the last step, or the last
        healthy checked step of a point that failed).
      final_step: (P,) int.
      volume, centroid_height, max_displacement: (P, O) at ``final_positions``: enclosed volume
        (m³), mean vertex height y (m), largest vertex distance from the rest shape (m).
      fail_code, fail_step: (P, O) first failure (:mod:`jaxplush.stepping.diagnostics` code, exact step;
        0 / -1 where none). ``failed`` (P,) is True where any object failed.
      warn_step: (P, O) first checked step with the volume clamp active (-1: none).
      loss: (P,) loss against the target (m²; NaN where failed), or None without a target.
      target_kind, target_path: "positions", "points", "tracks" or "mixed" and the target's path
        (None without).
      frames, frame_steps: (T, P, V, 3) saved positions and their (T,) steps (with save_every);
        a failed point's frames after its ``final_step`` repeat its final (last healthy) positions.
      steps, dt, integrator, save_every, scene_text, scene_path, faces, object_id,
      object_names, wall_time.
    """

    kind: str
    labels: tuple
    axes: dict
    shape: tuple
    values: np.ndarray
    params: Params
    final_positions: np.ndarray
    final_step: np.ndarray
    volume: np.ndarray
    centroid_height: np.ndarray
    max_displacement: np.ndarray
    fail_code: np.ndarray
    fail_step: np.ndarray
    warn_step: np.ndarray
    loss: np.ndarray | None
    target_kind: str | None
    target_path: str | None
    frames: np.ndarray | None
    frame_steps: np.ndarray | None
    steps: int
    dt: float
    integrator: str
    save_every: int | None
    scene_text: str
    scene_path: str
    faces: np.ndarray
    object_id: np.ndarray
    object_names: tuple
    wall_time: float

    @property
    def n_points(self):
        return len(self.values)

    @property
    def failed(self):
        """(P,) bool: points where any object failed."""
        return np.any(self.fail_step >= 0, axis=1)

    def reshape(self, q):
        """A (P, ...) per-point array reshaped to the grid, (n_1, ..., n_A, ...)."""
        q = np.asarray(q)
        return q.reshape(tuple(self.shape) + q.shape[1:])

    def quantity(self, name="loss", obj=0):
        """(P,) a summary quantity per point: "loss" or one of volume, centroid_height,
        max_displacement of object ``obj`` (index or name); NaN where the point failed."""
        if name == "loss":
            if self.loss is None:
                raise ValueError("this sweep has no target, hence no loss; plot 'volume', "
                                 "'centroid_height' or 'max_displacement'")
            return self.loss
        if name not in QUANTITIES:
            raise ValueError(f"unknown quantity {name!r}; expected one of {', '.join(QUANTITIES)}")
        if isinstance(obj, str):
            if obj not in self.object_names:
                raise ValueError(f"no object {obj!r} in this sweep (objects: {', '.join(self.object_names)})")
            o = self.object_names.index(obj)
        else:
            o = int(obj)
            if not 0 <= o < len(self.object_names):
                raise ValueError(f"object index {obj} out of range: the sweep has {len(self.object_names)} "
                                 f"object(s)")
        return np.where(self.failed, np.nan, getattr(self, name)[:, o])

    def best(self):
        """dict label -> value of the point with the smallest loss (plus "loss" and "index")."""
        loss = self.quantity("loss")
        if np.all(np.isnan(loss)):
            raise ValueError("every point of the sweep failed; there is no best point")
        i = int(np.nanargmin(loss))
        out = {lab: float(v) for lab, v in zip(self.labels, self.values[i])}
        out.update(loss=float(loss[i]), index=i)
        return out

    def save(self, path):
        """Write the sweep to ``path`` (HDF5, atomically; schema in the module docstring)."""
        return _save(self, path)

    def plot(self, where=None, quantity=None, obj=0, log=None):
        """Plot the loss landscape (or a summary quantity): a curve for one axis, a heat map for
        a 2-D grid, a coloured scatter for 2-parameter points. Failed points are marked ×.

        Args:
          where: a file path (the figure is written there atomically; returns the path), a
            matplotlib Axes to draw into (returns it), or None (a new figure; returns its Axes).
          quantity: "loss" (default with a target) or volume / centroid_height /
            max_displacement (default "volume" without a target).
          obj: object (index or name) for the summary quantities.
          log: colour (2-D) or y (1-D) axis on a log scale; default: when the values span more
            than two decades.
        """
        return _plot(self, where, quantity, obj, log)

    def table(self, n=10):
        """A text table of up to ``n`` points (the best by loss with a target), and the failures."""
        return _table(self, n)


# --------------------------------------------------------------------------- the sweep

def sweep(scene, grid=None, *, points=None, steps, dt, save_every=None, target=None, integrator="verlet",
          progress=True, batch=None, checkpoint=None):
    """Simulate a scene at every point of a parameter grid, in compiled batches.

    Args:
      scene: :class:`jaxplush.scene.parse.Scene`.
      grid: dict parameter label -> 1-D values; the sweep runs their cartesian product. Labels
        are :data:`jaxplush.types.PARAM_NAMES` (``k`` = ``k_structural``), applied to every
        object, or ``name@object`` for one object (name or index).
      points: instead of ``grid``: dict label -> equal-length values (the points are zipped),
        or a list of dicts.
      steps: time steps per point.
      dt: time step, s.
      save_every: also keep every point's positions every ``save_every`` steps (and the last
        step) in ``frames`` (memory: T x P x V x 3).
      target: a target file path (loaded with :func:`jaxplush.fitting.targets.load_target` on this dt)
        or a :class:`jaxplush.fitting.targets.Target`; the loss of each point is computed against it.
      integrator: only "verlet" is batched.
      progress: draw a progress bar on stderr.
      batch: at most this many points simulated together (static; one compilation for any
        number of points; a larger sweep runs in equal batches, each whole rollout chunks).
        Default :func:`default_batch`: 64 on a CPU, 1024 on a GPU.
      checkpoint: a directory that keeps every finished batch (each written atomically), so
        that a sweep killed part-way, even by SIGKILL, resumes from its finished batches when
        run again with the same directory and settings (:class:`_Checkpoint`); None: nothing
        kept. Required when several processes share the sweep (``jax.distributed``): each runs
        every P-th batch, writes it there (a filesystem every process sees), and all read the
        others' batches after a barrier, so each returns the whole result.

    Returns:
      :class:`SweepResult`; the same for one process or several, for a fresh or a resumed run.

    Raises:
      SweepError: bad parameter names, objects or values.
      TrajectoryError: a bad target file.
      NotImplementedError: the scene needs a term the batched simulator does not implement.
    """
    t_start = time.perf_counter()
    plan = _plan_sweep(scene, grid, points, steps, dt, save_every, target, integrator, batch, progress)
    n_points, batch = plan.n_points, plan.batch
    n_batches = -(-n_points // batch)
    n_proc, rank = jax.process_count(), jax.process_index()
    if n_proc > 1 and checkpoint is None:
        raise SweepError(f"a sweep shared by {n_proc} processes needs a checkpoint directory on a filesystem "
                         "every process sees (the processes exchange their batches there)")
    store = None if checkpoint is None else _Checkpoint(checkpoint, _fingerprint(scene, plan), n_batches)
    out = _Collector(scene, n_points, plan.steps, plan.keep, plan.save_every, plan.frame_steps,
                     0 if plan.tsteps is None else len(plan.tsteps))
    parts = {} if store is None else store.finished()
    todo = [c for c in range(rank, n_batches, n_proc) if c not in parts]
    if store is not None and parts and progress and rank == 0:
        print(f"sweep: resuming from {len(parts)} of {n_batches} finished batches in {store.path}", file=sys.stderr)
    live = sum(min(batch, n_points - c * batch) for c in todo)
    with Progress(live * plan.steps, "sweep", enabled=progress, unit="point-steps") as bar:
        for c in todo:
            parts[c] = _run_chunk(plan, c, out, bar)
            if store is not None:
                store.save(c, parts[c])
    if n_proc > 1:
        store.barrier("finished")
        parts.update(store.finished(exclude=parts))
    res = out.finish([parts[c] for c in range(n_batches)], plan.tsteps)
    wall = time.perf_counter() - t_start
    _warn_failures(res, n_points)
    return _sweep_result(scene, plan, res, wall)


@dataclasses.dataclass
class _SweepPlan:
    """A validated sweep: its points, batched simulator, target frames and frame grid (period
    steps per frame, ``n_full`` frames then ``rem`` steps), and what each rollout call observes."""

    kind: str
    axes: list
    values: np.ndarray
    pparams: tuple
    steps: int
    dt: float
    save_every: int | None
    batch: int
    tgt: object
    tkind: str | None
    lkind: object
    tsteps: np.ndarray | None
    tdata: np.ndarray | None
    bsim: object
    period: int
    n_full: int
    rem: int
    frame_steps: np.ndarray
    aux: dict | None
    keep: bool
    observe: object
    per_call: int
    integrator: str

    @property
    def n_points(self):
        return len(self.values)


#: Default points per compiled batch: on XLA:CPU 64 (4 chunks of 16, two per core on 2 cores);
#: on an accelerator 1024, where throughput still grows with the width (425x one scene at 1024
#: points on an H200; benchmarks/RESULTS.md).
DEFAULT_BATCH = {"cpu": 64}
DEFAULT_ACCELERATOR_BATCH = 1024


def default_batch():
    """Points a sweep simulates together by default on this backend (:data:`DEFAULT_BATCH`)."""
    return DEFAULT_BATCH.get(jax.default_backend(), DEFAULT_ACCELERATOR_BATCH)


def _plan_sweep(scene, grid, points, steps, dt, save_every, target, integrator, batch, progress):
    """Validate everything before tracing; the batched simulator and the frame grid: target frames
    and saves land on frames, a remainder call ends the run."""
    if (grid is None) == (points is None):
        raise SweepError("give exactly one of grid (a cartesian product) or points")
    kind = "grid" if grid is not None else "points"
    axes = _axes(scene, grid if grid is not None else _normalise_points(points), kind)
    steps = _positive_int(steps, "steps")
    dt = float(dt)
    if not (np.isfinite(dt) and dt > 0):
        raise SweepError(f"dt must be a positive number, got {dt!r}")
    if save_every is not None:
        save_every = _positive_int(save_every, "save_every")
    try:                                 # before the points are made: a MemoryError is no answer
        check_sweep_size(scene, _n_points(axes, kind), len(axes),
                         0 if save_every is None else steps // save_every + 2,
                         8 if jax.config.jax_enable_x64 else 4)
    except SweepError as e:
        raise SweepError(f"{kind}: {e}") from None
    values = _point_values(axes, kind)
    pparams = _point_params(scene, axes, values)
    batch = default_batch() if batch is None else _positive_int(batch, "batch")
    tgt = tkind = tsteps = tdata = None
    if target is not None:
        tgt = _load_target(target, scene, dt)
        # a target's controls drive their vertices in every point, as in a fit
        # (jaxplush.fitting.targets.scene_with_controls)
        from jaxplush.fitting.targets import scene_with_controls
        scene = scene_with_controls(scene, tgt)
        tkind, tsteps, tdata = _target_frames(tgt, scene, steps)
    n_points = len(values)
    batch = _outer_batch(n_points, batch)
    terms = batched.terms_for(scene, pparams)
    bsim = batched.make_batched_simulator(scene, dt, batch, integrator, terms=terms)

    required = list(tsteps if tsteps is not None else []) + (
        list(range(save_every, steps + 1, save_every)) if save_every else [])
    period = _frame_period(steps, required)
    n_full, rem = divmod(steps, period)
    frame_steps = np.arange(1, n_full + 1) * period
    aux = None
    # the frame loss's static kind: a mixed target's with where its tracks start and the fit's
    # factors of its two terms
    lkind = ((TargetKind.MIXED.value, int(np.shape(tgt.points)[1])) + _mixed_factors(tgt, bsim.topology)
             if tkind is TargetKind.MIXED else tkind)
    surface = _surface(bsim.topology) if tkind is not None and not tkind.material_points else None
    scan_kind = lkind if tkind is not None and np.any(tsteps > 0) else None   # step-0 frames: on the host
    if scan_kind is not None:
        later = tsteps > 0
        table = np.full(n_full + 1, -1, np.int32)       # frame index -> target frame, -1: none
        table[tsteps[later] // period - 1] = np.arange(int(later.sum()), dtype=np.int32)
        aux = dict(table=jnp.asarray(table), data=jnp.asarray(tdata[later], bsim.dtype),
                   frame0=jnp.asarray(0, jnp.int32))
        if surface is not None:
            aux["surface"] = tuple(jnp.asarray(a) for a in surface)
    keep = save_every is not None
    observe = _observer(scan_kind, keep) if (scan_kind is not None or keep) else None
    per_call = _frames_per_call(n_full, n_points, batch, progress)
    return _SweepPlan(kind=kind, axes=axes, values=values, pparams=pparams, steps=steps, dt=dt,
                      save_every=save_every, batch=batch, tgt=tgt, tkind=tkind, lkind=lkind, tsteps=tsteps,
                      tdata=tdata,
                      bsim=bsim, period=period, n_full=n_full, rem=rem, frame_steps=frame_steps, aux=aux,
                      keep=keep, observe=observe, per_call=per_call, integrator=integrator)


def _surface(topology):
    """(faces (F, 3), vertex_faces (V, W)) int32 of a scene: a scan's distance to the surface."""
    from jaxplush.fitting.objective.losses import vertex_faces
    faces = np.asarray(topology.faces, np.int32)
    return faces, vertex_faces(faces, topology.n_vertices)


def _mixed_factors(target, topology):
    """(f_points, f_tracks): a mixed target's terms weighed as the fit weighs them, each over its
    own normaliser, times the fit's combined normaliser (:func:`jaxplush.fitting.objective.losses.make_loss`)."""
    from jaxplush.fitting.objective import losses
    scales = [losses.loss_scale(p, topology)[0] for p in target.parts]
    s2 = losses.combined_scale2(target, scales)
    return tuple(float(s2 * c / s) for c, s in zip(losses.part_weights(target), scales))


def _run_chunk(plan, c, out, bar):
    """Simulate batch ``c`` of the points (the last padded with its last point): its results,
    a dict of numpy arrays (:meth:`_Collector.part`)."""
    bsim, batch, n_points, aux, period = plan.bsim, plan.batch, plan.n_points, plan.aux, plan.period
    idx = np.arange(c * batch, (c + 1) * batch)
    live = idx < n_points
    idx = np.minimum(idx, n_points - 1)           # pad the last chunk with its last point
    p = bsim.params(Params(*(a[idx].T for a in plan.pparams)))
    state = bsim.init_fn(p)
    health = batched.initial_health(bsim, state)
    loss = np.zeros(batch) if plan.tkind is not None else None
    kept = []
    done = 0
    while done < plan.n_full:
        n = min(plan.per_call, plan.n_full - done)
        if aux is not None:
            aux["frame0"] = jnp.asarray(done, jnp.int32)
        state, obs, health = batched.rollout(bsim, p, state, n, period, health=health,
                                             step0=done * period, observe=plan.observe, aux=aux)
        if obs is not None and "loss" in obs:
            loss += np.asarray(obs["loss"], np.float64).sum(axis=0)
        if plan.keep:
            kept.append(np.asarray(obs["x"]))
        done += n
        bar.update(int(live.sum()) * n * period)
    if plan.rem:
        state, _, health = batched.rollout(bsim, p, state, 1, plan.rem, health=health,
                                           step0=plan.n_full * period)
        bar.update(int(live.sum()) * plan.rem)
    if plan.tkind is not None and np.any(plan.tsteps == 0):
        x0 = bsim.init_fn(p).x
        for y in plan.tdata[plan.tsteps == 0]:
            surface = None if plan.tkind.material_points else tuple(jnp.asarray(a) for a in _surface(bsim.topology))
            loss += np.asarray(frame_loss(plan.lkind, x0, jnp.asarray(y, bsim.dtype), surface), np.float64)
    return out.part(bsim, p, state, health, loss, kept, live)


def _warn_failures(res, n_points):
    """Warn (for the caller of :func:`sweep`) about failed points and points with the volume clamp."""
    if res["failed"].any():
        nf = int(res["failed"].sum())
        warnings.warn(f"{nf} of {n_points} sweep point(s) failed (blow-up); see fail_code/fail_step "
                      f"(their loss is NaN, their final positions the last healthy ones)", SimulationWarning, stacklevel=3)
        over = np.any(res["fail_code"] == diagnostics.CONTACT_OVERFLOW, axis=1)
        if over.any():
            # a sweep reports it per point, as any failure (the fit's Evaluator grows the capacity)
            warnings.warn(f"{int(over.sum())} of them: {diagnostics.MESSAGES[diagnostics.CONTACT_OVERFLOW]}",
                          SimulationWarning, stacklevel=3)
    clamp = np.any(res["warn_step"] >= 0, axis=1) & ~res["failed"]
    if clamp.any():
        warnings.warn(f"{int(clamp.sum())} sweep point(s): {diagnostics.MESSAGES[diagnostics.VOLUME_CLAMPED]} "
                      f"(see warn_step)", VolumeClampWarning, stacklevel=3)


def _sweep_result(scene, plan, res, wall):
    kind, axes, values, tgt = plan.kind, plan.axes, plan.values, plan.tgt
    shape = tuple(len(a.values) for a in axes) if kind == "grid" else (plan.n_points,)
    axes_out = {a.label: (a.values if kind == "grid" else values[:, j]) for j, a in enumerate(axes)}
    return SweepResult(
        kind=kind, labels=tuple(a.label for a in axes), axes=axes_out, shape=shape, values=values,
        params=plan.pparams, final_positions=res["positions"], final_step=res["final_step"], volume=res["volume"],
        centroid_height=res["centroid_height"], max_displacement=res["max_displacement"],
        fail_code=res["fail_code"], fail_step=res["fail_step"], warn_step=res["warn_step"],
        loss=res["loss"], target_kind=None if plan.tkind is None else TargetKind(plan.tkind).value,
        target_path=None if tgt is None else str(getattr(tgt, "path", "")),
        frames=res["frames"], frame_steps=res["frame_steps"], steps=plan.steps, dt=plan.dt,
        integrator=plan.integrator, save_every=plan.save_every, scene_text=scene.text, scene_path=scene.path,
        faces=scene.faces, object_id=scene.object_id, object_names=scene.object_names, wall_time=wall)


def _positive_int(v, what):
    if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
        raise SweepError(f"{what} must be a positive integer, got {v!r}")
    return int(v)


def _outer_batch(n_points, batch):
    """Points per compiled batch: at most ``batch``, the points spread evenly over the fewest
    batches, each a whole number of rollout chunks. (Padding the last of ceil(P / batch) full
    batches with copies of its last point could simulate almost twice the points asked for:
    65 points in batches of 64 ran 128 simulations, now 2 x 48.)"""
    batch = min(batch, n_points)
    n_outer = -(-n_points // batch)
    if n_outer == 1:
        return batch
    per = -(-n_points // n_outer)
    chunk = batched.default_chunk(per)
    return min(batch, -(-per // chunk) * chunk)


def _frames_per_call(n_full, n_points, batch, progress):
    """Frames per compiled call: all of them, or (with a progress bar and few chunks) an equal
    split into about 20 updates in all, when n_full has a divisor near that size (one compile)."""
    if n_full == 0:
        return 1
    n_chunks = -(-n_points // batch)
    calls = max(1, 20 // n_chunks) if progress else 1
    if calls == 1:
        return n_full
    want = -(-n_full // calls)
    d = max(d for d in range(1, want + 1) if n_full % d == 0)
    return d if 4 * d >= want else n_full


class _Collector:
    """Gathers each chunk's results on the host (numpy)."""

    def __init__(self, scene, n_points, steps, keep, save_every, frame_steps, n_target):
        self.scene, self.n, self.steps = scene, n_points, steps
        self.keep, self.save_every = keep, save_every
        self.frame_steps, self.n_target = frame_steps, n_target

    def part(self, bsim, p, state, health, loss, kept, live):
        """The results of one batch's live points, a dict of numpy arrays."""
        fstep, fcode = batched.locate_failures(bsim, p, health)
        failed = np.any(fstep >= 0, axis=0)
        pos = batched.positions(state)
        good = batched.positions(health.good_state)
        final_step = np.where(failed, np.asarray(health.good_step), self.steps)
        pos = np.where(failed[:, None, None], good, pos)
        if loss is not None:
            loss = np.where(failed, np.nan, loss / self.n_target)
        frames = np.concatenate(kept, axis=0) if self.keep and kept else None
        sel = live
        return dict(
            positions=pos[sel], final_step=final_step[sel], fail_step=fstep.T[sel], fail_code=fcode.T[sel],
            warn_step=np.asarray(health.warn_step).T[sel], loss=None if loss is None else loss[sel],
            frames=None if frames is None else frames[:, sel])

    def finish(self, parts, tsteps):
        """Every point's results from the batches' parts, in order."""
        cat = lambda k: np.concatenate([q[k] for q in parts], axis=0)  # noqa: E731
        out = {k: cat(k) for k in ("positions", "final_step", "fail_step", "fail_code", "warn_step")}
        out["loss"] = cat("loss") if parts[0]["loss"] is not None else None
        out["failed"] = np.any(out["fail_step"] >= 0, axis=1)
        out["fail_code"] = np.where(out["fail_step"] >= 0, out["fail_code"], diagnostics.OK)
        out.update(_summaries(self.scene, out["positions"]))
        out["frames"] = out["frame_steps"] = None
        if self.keep:
            frames = np.concatenate([q["frames"] for q in parts], axis=1)           # (n_full, P, V, 3)
            sel = self.frame_steps % self.save_every == 0
            frames, fsteps = frames[sel], self.frame_steps[sel]
            x0 = np.broadcast_to(self.scene.vertices, (self.n,) + self.scene.vertices.shape)[None]
            frames = np.concatenate([x0, frames], axis=0)
            fsteps = np.concatenate([[0], fsteps])
            if fsteps[-1] != self.steps:
                frames = np.concatenate([frames, out["positions"][None]], axis=0)
                fsteps = np.concatenate([fsteps, [self.steps]])
            # A failed point's frames after its last healthy step would hold the blown-up (NaN)
            # state: they repeat its final (last healthy) positions instead, as final_positions.
            after = fsteps[:, None] > out["final_step"][None, :]                     # (T, P)
            if after.any():
                frames = np.where(after[:, :, None, None], out["positions"][None], frames)
            out["frames"], out["frame_steps"] = frames, fsteps
        return out


CHECKPOINT_FORMAT = "jaxplush-sweep-checkpoint"
#: The files of a checkpoint directory (a killed write leaves a ``.tmpPID`` file).
_CHECKPOINT_FILE = re.compile(r"(plan\.json|batch_\d{6,}\.npz)(\.tmp\d+)?")


def _fingerprint(scene, plan):
    """A hash of everything that decides a sweep's batches: the scene, the points, the steps,
    the target, the batching and the float width (a resumed run must be the same sweep)."""
    h = hashlib.sha256()
    for item in (scene.text, plan.kind, repr([a.label for a in plan.axes]), plan.steps, repr(plan.dt),
                 plan.save_every, plan.integrator, plan.batch, str(np.dtype(plan.bsim.dtype)), plan.lkind):
        h.update(repr(item).encode() + b"\0")
    for a in (plan.values, plan.tsteps, plan.tdata) + tuple(plan.pparams):
        if a is not None:
            a = np.ascontiguousarray(a)
            h.update(str(a.dtype).encode() + repr(a.shape).encode() + a.tobytes())
    return h.hexdigest()


class _Checkpoint:
    """A sweep's finished batches on disk: ``DIR/plan.json`` (the sweep's fingerprint and batch
    count) and one ``DIR/batch_NNNNNN.npz`` per finished batch, each written to a temporary file
    and renamed, so a kill at any moment leaves only whole batches. With several processes,
    process 0 writes the plan and the others wait for it (a barrier over ``jax.distributed``)."""

    def __init__(self, path, fingerprint, n_batches):
        self.path = os.fspath(path)
        plan = dict(format=CHECKPOINT_FORMAT, fingerprint=fingerprint, n_batches=int(n_batches))
        where = os.path.join(self.path, "plan.json")
        if jax.process_index() == 0:
            if os.path.exists(self.path) and not os.path.isdir(self.path):
                raise SweepError(f"{self.path}: the checkpoint must be a directory, this is a file")
            try:
                os.makedirs(self.path, exist_ok=True)
                if not os.path.exists(where):
                    self._write(where, lambda f: f.write(json.dumps(plan).encode()))
            except OSError as e:         # a file on the way, no permission, a read-only filesystem
                raise SweepError(f"{self.path}: cannot create the checkpoint directory: "
                                 f"{e.strerror or e}") from None
        self.barrier("plan")
        try:
            with open(where) as f:
                found = json.load(f)
        except (OSError, ValueError) as e:
            raise SweepError(f"{where}: cannot read the checkpoint's plan: {e}") from None
        if found != plan:
            raise SweepError(f"{self.path}: holds the finished batches of another sweep (a different scene, "
                             "points, steps, target or batch); delete it, or give another checkpoint directory")

    @staticmethod
    def _write(path, write):
        tmp = f"{path}.tmp{os.getpid()}"
        with open(tmp, "wb") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)

    def _file(self, c):
        return os.path.join(self.path, f"batch_{c:06d}.npz")

    def save(self, c, part):
        arrays = {k: v for k, v in part.items() if v is not None}
        self._write(self._file(c), lambda f: np.savez(f, **arrays))

    def finished(self, exclude=()):
        """{batch: part} of every finished batch on disk (but those in ``exclude``)."""
        out = {}
        for name in sorted(os.listdir(self.path)):
            if not (name.startswith("batch_") and name.endswith(".npz")):
                continue                                  # the plan, a killed write's temporary file
            c = int(name[6:-4])
            if c in exclude:
                continue
            try:
                with np.load(os.path.join(self.path, name)) as z:
                    part = {k: z[k] for k in z.files}
            except (OSError, ValueError) as e:
                raise SweepError(f"{os.path.join(self.path, name)}: unreadable finished batch ({e}); "
                                 "delete it to run that batch again") from None
            part.setdefault("loss", None)
            part.setdefault("frames", None)
            out[c] = part
        return out

    @staticmethod
    def barrier(name):
        if jax.process_count() > 1:
            from jax.experimental import multihost_utils
            multihost_utils.sync_global_devices(f"jaxplush-sweep-{name}")



def remove_checkpoint(path):
    """Delete a sweep's checkpoint directory once its result is written (with several processes:
    after every process got there, by process 0)."""
    _Checkpoint.barrier("remove")
    if jax.process_index() != 0:
        return
    path = os.fspath(path)
    for name in os.listdir(path):         # only what a checkpoint writes: never a user's other files
        if _CHECKPOINT_FILE.fullmatch(name):
            os.remove(os.path.join(path, name))
    try:
        os.rmdir(path)
    except OSError:                       # something else lives there: leave it
        pass


def _summaries(scene, pos):
    """Final volume, centroid height and max displacement from rest, each (P, O)."""
    rest = scene.vertices
    vol = np.stack([scene.volumes(x) for x in pos]) if len(pos) else np.zeros((0, scene.n_objects))
    cy, md = [], []
    for o in scene.objects:
        a, b = o.vertex_slice
        cy.append(pos[:, a:b, 1].mean(axis=1))
        md.append(np.linalg.norm(pos[:, a:b] - rest[None, a:b], axis=2).max(axis=1))
    return dict(volume=vol, centroid_height=np.stack(cy, axis=1), max_displacement=np.stack(md, axis=1))


# --------------------------------------------------------------------------- save / plot / table

def _save(res, path):
    import h5py

    from jaxplush import __version__
    from jaxplush.io.trajectory import atomic_path
    with atomic_path(path, ".h5") as tmp:
        with h5py.File(tmp, "w") as f:
            a = f.attrs
            a["format"] = FORMAT
            a["format_version"] = FORMAT_VERSION
            a["kind"] = res.kind
            a["shape"] = np.asarray(res.shape, np.int64)
            a["labels"] = np.asarray(res.labels, dtype=object).astype(h5py.string_dtype("utf-8")) \
                if res.labels else np.zeros(0, h5py.string_dtype("utf-8"))
            a["steps"] = int(res.steps)
            a["dt"] = float(res.dt)
            a["integrator"] = res.integrator
            a["save_every"] = int(res.save_every or 0)
            a["target_path"] = res.target_path or ""
            a["target_kind"] = res.target_kind or ""
            a["jaxplush_version"] = __version__
            a["scene"] = res.scene_text
            a["scene_path"] = res.scene_path
            a["wall_time"] = float(res.wall_time)
            g = f.create_group("axes")
            for lab, v in res.axes.items():
                g.create_dataset(lab, data=np.asarray(v, np.float64))
            f.create_dataset("values", data=np.asarray(res.values, np.float64))
            g = f.create_group("params")
            for name, v in zip(Params._fields, res.params):
                g.create_dataset(name, data=np.asarray(v, np.float64))
            f.create_dataset("final_positions", data=np.asarray(res.final_positions), compression="gzip",
                             compression_opts=1)
            f.create_dataset("final_step", data=np.asarray(res.final_step, np.int64))
            g = f.create_group("summary")
            for name in ("volume", "centroid_height", "max_displacement"):
                g.create_dataset(name, data=np.asarray(getattr(res, name), np.float64))
            g = f.create_group("failure")
            g.create_dataset("code", data=np.asarray(res.fail_code, np.int32))
            g.create_dataset("step", data=np.asarray(res.fail_step, np.int64))
            g.create_dataset("warn_step", data=np.asarray(res.warn_step, np.int64))
            msgs = [diagnostics.MESSAGES[k] for k in sorted(diagnostics.MESSAGES)]
            g.create_dataset("messages", data=np.asarray(msgs, dtype=object), dtype=h5py.string_dtype("utf-8"))
            if res.loss is not None:
                f.create_dataset("loss", data=np.asarray(res.loss, np.float64))
            if res.frames is not None:
                f.create_dataset("frames", data=np.asarray(res.frames), compression="gzip", compression_opts=1)
                f.create_dataset("frame_steps", data=np.asarray(res.frame_steps, np.int64))
            f.create_dataset("faces", data=np.asarray(res.faces, np.int32))
            f.create_dataset("object_id", data=np.asarray(res.object_id, np.int32))
            f.create_dataset("object_names", data=np.asarray(res.object_names, dtype=object),
                             dtype=h5py.string_dtype("utf-8"))
    return os.fspath(path)


def load_sweep(path):
    """Read a sweep file written by :meth:`SweepResult.save` into a dict (numpy arrays and attrs)."""
    import h5py

    from jaxplush.errors import TrajectoryError
    from jaxplush.io.trajectory import open_hdf5
    path = os.fspath(path)
    with open_hdf5(path) as f:
        if f.attrs.get("format") != FORMAT:
            raise TrajectoryError(path, f"not a sweep file (attribute format != {FORMAT!r})")
        out = {"attrs": {k: f.attrs[k] for k in f.attrs}}

        def visit(name, obj):
            if isinstance(obj, h5py.Dataset):
                out[name] = obj[()]
        f.visititems(visit)
    return out


def _geometric(v):
    v = np.asarray(v, np.float64)
    if len(v) < 3 or np.any(v <= 0):
        return False
    r = np.diff(np.log(v))
    return bool(np.allclose(r, r[0], rtol=1e-6) and not np.allclose(np.diff(v), np.diff(v)[0], rtol=1e-6))


def _plot(res, where, quantity, obj, log):
    quantity = quantity or ("loss" if res.loss is not None else "volume")
    q = res.quantity(quantity, obj)                                   # validates quantity and obj
    if len(res.labels) > 2:
        raise ValueError(f"plot shows one or two swept parameters, this sweep has {len(res.labels)} "
                         f"({', '.join(res.labels)}); plot a slice with your own matplotlib code")
    from matplotlib import colors
    if where is None or isinstance(where, (str, os.PathLike)):
        import matplotlib.pyplot as plt
        fig, ax = plt.subplots(figsize=(6.4, 4.8))
    else:
        ax = where
        fig = ax.figure
    unit = {"loss": "m²", "volume": "m³", "centroid_height": "m", "max_displacement": "m"}[quantity]
    oname = res.object_names[obj] if isinstance(obj, (int, np.integer)) else obj
    qlabel = f"loss ({unit})" if quantity == "loss" else f"{quantity} of {oname} ({unit})"
    finite = q[np.isfinite(q)]
    if log is None:
        log = bool(finite.size and finite.min() > 0 and finite.max() / finite.min() > 100)
    failed = res.failed
    if len(res.labels) == 1:
        x = res.values[:, 0]
        order = np.argsort(x)
        ax.plot(x[order], q[order], "o-", ms=3)
        if failed.any():
            ax.plot(x[failed], np.full(failed.sum(), np.nanmin(q) if finite.size else 0.0), "x", color="red",
                    label=f"failed ({int(failed.sum())})")
            ax.legend()
        if quantity == "loss" and finite.size:
            i = int(np.nanargmin(q))
            ax.plot([x[i]], [q[i]], "*", ms=12, color="C3")
        ax.set_xlabel(res.labels[0])
        ax.set_ylabel(qlabel)
        if res.kind == "grid" and _geometric(res.axes[res.labels[0]]):
            ax.set_xscale("log")
        if log:
            ax.set_yscale("log")
    else:
        norm = colors.LogNorm() if log else None
        if res.kind == "grid":
            xa, ya = (np.asarray(res.axes[lab]) for lab in res.labels)
            z = res.reshape(q).T                                           # rows: second axis
            # pcolormesh takes cell centres in increasing order: sort axes given in any order
            ox, oy = np.argsort(xa, kind="stable"), np.argsort(ya, kind="stable")
            xa, ya, z = xa[ox], ya[oy], z[np.ix_(oy, ox)]
            mesh = ax.pcolormesh(xa, ya, np.ma.masked_invalid(z), shading="nearest", norm=norm, cmap="viridis")
            if _geometric(xa):
                ax.set_xscale("log")
            if _geometric(ya):
                ax.set_yscale("log")
        else:
            mesh = ax.scatter(res.values[:, 0], res.values[:, 1], c=q, norm=norm, cmap="viridis")
        fig.colorbar(mesh, ax=ax, label=qlabel)
        if failed.any():
            ax.plot(res.values[failed, 0], res.values[failed, 1], "x", color="red", ms=8,
                    label=f"failed ({int(failed.sum())})")
            ax.legend(loc="upper right")
        if quantity == "loss" and finite.size:
            i = int(np.nanargmin(q))
            ax.plot([res.values[i, 0]], [res.values[i, 1]], "*", ms=14, color="white", mec="black",
                    label="minimum")
        ax.set_xlabel(res.labels[0])
        ax.set_ylabel(res.labels[1])
    title = "loss landscape" if quantity == "loss" else quantity.replace("_", " ")
    ax.set_title(f"{title}: {res.n_points} points, {res.steps} steps of {res.dt:g} s")
    if where is None or not isinstance(where, (str, os.PathLike)):
        return ax
    import matplotlib.pyplot as plt

    from jaxplush.io.trajectory import atomic_path
    try:
        with atomic_path(where) as tmp:
            fig.savefig(tmp, dpi=120, bbox_inches="tight", format=os.path.splitext(os.fspath(where))[1][1:] or None)
    finally:
        plt.close(fig)
    return os.fspath(where)


def _fmt(v):
    return f"{v:.4g}" if np.isfinite(v) else "nan"


def _table(res, n=10):
    lines = []
    has_loss = res.loss is not None
    if has_loss and np.any(np.isfinite(res.loss)):
        order = np.argsort(np.where(np.isfinite(res.loss), res.loss, np.inf))
    else:
        order = np.arange(res.n_points)
    order = [i for i in order if not res.failed[i]][:n]
    head = ["#"] + list(res.labels) + (["loss (m²)"] if has_loss else []) + [
        f"volume {nm} (cm³)" for nm in res.object_names] + [f"height {nm} (m)" for nm in res.object_names]
    rows = []
    for i in order:
        rows.append([str(i)] + [_fmt(v) for v in res.values[i]] + ([_fmt(res.loss[i])] if has_loss else [])
                    + [_fmt(v * 1e6) for v in res.volume[i]] + [_fmt(v) for v in res.centroid_height[i]])
    widths = [max(len(h), *(len(r[j]) for r in rows)) if rows else len(h) for j, h in enumerate(head)]
    what = f"best {len(rows)} by loss" if has_loss else f"first {len(rows)}"
    lines.append(f"{res.n_points} points ({what} shown):")
    lines.append("  ".join(h.rjust(w) for h, w in zip(head, widths)))
    for r in rows:
        lines.append("  ".join(c.rjust(w) for c, w in zip(r, widths)))
    nf = int(res.failed.sum())
    if nf:
        lines.append(f"{nf} point(s) failed:")
        for i in np.nonzero(res.failed)[0][:n]:
            o = int(np.argmax(np.where(res.fail_step[i] >= 0, -res.fail_step[i], -np.inf)))
            vals = ", ".join(f"{lab}={v:.4g}" for lab, v in zip(res.labels, res.values[i]))
            lines.append(f"  #{i} ({vals}): step {int(res.fail_step[i, o])}, object {res.object_names[o]!r}: "
                         f"{diagnostics.MESSAGES[int(res.fail_code[i, o])]}")
        if nf > n:
            lines.append(f"  ... and {nf - n} more")
    if has_loss and np.any(np.isfinite(res.loss)):
        b = res.best()
        lines.append("minimum: " + ", ".join(f"{lab} = {b[lab]:.6g}" for lab in res.labels)
                     + f", loss {b['loss']:.4g} m²")
    return "\n".join(lines)
