"""Per-frame losses and residuals between simulated positions and a target (pure jax; no IO).

* :func:`squared_distance`: mean squared vertex distance, for ``positions`` targets (the
  vertices correspond one to one).
* :func:`point_surface_distance2`: squared distance of every target point to the simulated
  surface, for ``points`` targets (a scan: M points with no correspondence to the V vertices).
* :func:`chamfer`: the symmetric vertex-to-point Chamfer distance (a loss of one's own).
* :func:`track_positions`: the simulated positions of tracked points (vertices, or points on
  faces by barycentric weights), for ``tracks`` targets: each observed track's squared
  distance to its simulated position (rows of NaN, tracks not seen, left out).

:func:`make_loss` builds the frame loss that :func:`jaxplush.fitting.objective.gradients.rollout_loss` sums over
the target frames, and :func:`make_residual` the same loss as a vector of residuals r with
sum(r²) = L (for Gauss-Newton and Levenberg-Marquardt). The loss is noise-aware:

    L = (1 / T) sum_j d_j / s²,

d_j the frame's mean squared distance (m²): per vertex |x_i - y_i|² for positions, per point its
squared distance to the surface for points, per observed track |track_positions(x) - y|² for
tracks (with tracks not seen, or a ragged cloud, every observation weighs alike: d_j is the
frame's sum times T / N, N observations over T frames). With a known measurement noise sigma per
coordinate, s² = 3 sigma² for positions and tracks and sigma² for points (a point's distance to the true
surface is its noise's normal component), so L ~ 1 when the model fits to the noise level;
otherwise (noise-free or unknown) s² is the same mean between the scene's rest shape and the
target, so L is the squared error relative to how far the target moves (L = 1 for "no better
than standing still"). :func:`rms_metres` turns a loss back into the RMS residual per
coordinate (positions, tracks) or per point distance (points), in metres, to compare with the noise.

A mixed target (a scan with tracked points on the same frames) weighs its two terms, each
normalised on its own as above, by the target's track weight w (:attr:`Target.track_weight`,
default 1):

    L = (L_points + w L_tracks) / (1 + w),

so neither term dominates by its count of points (a scan of thousands of points beside a dozen
markers), and L still ends near 1 at the noise level and is 1 for "no better than standing
still". With one noise sigma for both, the maximum-likelihood weighting (every coordinate's
residual counted alike) is w = 3 N_tracks / N_points (N the observations). Its normaliser s² (for
:func:`rms_metres`, per coordinate or point distance) is (1 + w) / (1 / s²_points + 3 w /
s²_tracks): sigma² at a known noise.

Frames whose objects are inverted (a gas object's volume <= 0, a blown-up rollout) get a NaN
loss, so the optimiser sees the failure instead of a finite but meaningless number.
"""

from __future__ import annotations

from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxplush.fitting.targets.kinds import TargetKind
# the geometry of the kinds' residuals and loss terms lives in the core (the kinds own it); named here too
from jaxplush.io.observe import (  # noqa: F401
    HIGHEST, _candidate_faces, chamfer,
    curvature_tables, mixed_linearised, nearest_point_residual, nearest_vertex,
    nearest_vertices, observed_points, pairwise_sq_distances, point_surface,
    point_surface_distance2,
    point_surface_signed_distance, squared_distance, surface_residual, track_distance2,
    track_linearised, track_positions, track_residual, vertex_faces, vertex_mean_curvature,
    vertex_residual)


class Loss(NamedTuple):
    """A frame loss ready for :func:`jaxplush.fitting.objective.gradients.rollout_loss`.

    Attributes:
      loss_fn: ``(x (V, 3), aux_j) -> scalar``: the frame's normalised contribution.
      aux: (T, V or M, 3) target frames (the pytree rollout_loss slices per frame).
      frame_steps: (T,) tuple of step indices.
      scale2: the normaliser s² (m²).
      normalisation: "noise" or "motion" (see the module docstring).
      kind: "positions", "points", "tracks" or "mixed".
      parts: a mixed target's terms, ((s², weight), ...) for its points and its tracks
        (:attr:`Target.parts`; weight 1 / (1 + w) and w / (1 + w)); () otherwise.
    """

    loss_fn: Callable
    aux: object
    frame_steps: tuple
    scale2: float
    normalisation: str
    kind: str
    parts: tuple = ()


def _frame_mean_sq(target, topology):
    """``(x (V, 3), y) -> d_j``: the frame's mean squared distance (m²) for a target: its kind's
    (:meth:`jaxplush.fitting.targets.kinds.Kind.mean_sq`)."""
    return _kind(target).mean_sq(target, topology)


def components(kind):
    """Residual components per observation of a kind (:attr:`jaxplush.fitting.targets.kinds.Kind.components`):
    positions and tracks give (x, y, z) per vertex or track, points one distance; a mixed target's
    s² is per coordinate or point distance alike."""
    return TargetKind(kind).components


def part_weights(target):
    """(1 / (1 + w), w / (1 + w)): the weights of a mixed target's points and tracks terms
    (w its :attr:`Target.track_weight`)."""
    w = float(target.track_weight)
    if not (np.isfinite(w) and w > 0):
        raise ValueError(f"{target.path}: the track weight must be a finite number > 0, got {w!r}")
    return 1.0 / (1.0 + w), w / (1.0 + w)


def combined_scale2(target, scales):
    """A mixed target's normaliser (per coordinate or point distance) from its parts' ``scales``
    [s²_points, s²_tracks]: 1 / sum_k weight_k C_k / s²_k (module docstring); 0 where a part's is 0."""
    terms = [c * components(p.kind) / s2 if s2 > 0 else np.inf
             for p, s2, c in zip(target.parts, scales, part_weights(target))]
    return float(1.0 / sum(terms))


def rest_distance(target, topology):
    """Mean over the target's frames of the frame distance (m²) between the rest shape
    (``topology.x0``) and the target (float64); for a mixed target the parts' combined as its
    normaliser is (:func:`combined_scale2`)."""
    if _kind(target).compound:
        return combined_scale2(target, [rest_distance(p, topology) for p in target.parts])
    x_rest = np.asarray(topology.x0, np.float64)
    if _kind(target).every_vertex:         # in numpy: nothing to compile for the commonest kind
        d = np.asarray(target.data, np.float64) - x_rest[None]
        return float(np.mean(np.sum(d * d, axis=-1)))
    with jax.enable_x64(True):
        f = jax.jit(jax.vmap(_frame_mean_sq(target, topology), in_axes=(None, 0)))
        return float(np.mean(np.asarray(f(jnp.asarray(x_rest, jnp.float64), jnp.asarray(target.data, jnp.float64)))))


def loss_scale(target, topology, noise=None, noise_free=False):
    """(s², "noise" or "motion", sigma or None): the normaliser of the loss (module docstring)."""
    if _kind(target).compound:
        parts = [loss_scale(p, topology, noise, noise_free) for p in target.parts]
        return combined_scale2(target, [s2 for s2, _, _ in parts]), parts[0][1], parts[0][2]
    sigma = None if noise_free else (target.noise if noise is None else float(noise))
    if sigma is not None and sigma > 0:
        return components(target.kind) * sigma * sigma, "noise", sigma
    scale2 = rest_distance(target, topology)
    if not scale2 > 0:  # the target is the rest shape itself: any positive scale will do
        scale2 = float(np.mean(np.var(topology.x0, axis=0)))
    return scale2, "motion", None


def residual_samples(prob):
    """How many residual samples a problem's RMS is over: observed coordinates (positions,
    tracks) or point distances (points); a mixed target's smaller part."""
    t = prob.target
    return min(int(p.observed.sum()) * int(p.kind.components) for p in t.parts)


def rms_metres(loss, scale2, kind):
    """RMS residual in metres of a (normalised) loss: per coordinate for positions and tracks, per
    point distance for points (each comparable with the noise sigma)."""
    return float(np.sqrt(max(loss, 0.0) * scale2 / components(kind)))


def make_loss(target, topology, dtype, *, noise=None, noise_free=False, check_volume=True):
    """Build the normalised frame loss for a target.

    Args:
      target: :class:`jaxplush.fitting.targets.Target`.
      topology: the simulator's :class:`jaxplush.model.forces.Topology` (rest shape, faces, objects).
      dtype: float dtype of the simulation.
      noise: measurement noise sigma per coordinate (m); default: the target's, if known.
      noise_free: treat the target as exact (normalise by its motion, ignore any noise value).
      check_volume: make the loss NaN at frames where an object's volume is <= 0 (for scenes
        with gas; an inverted mesh is a blow-up).

    Returns:
      :class:`Loss`.
    """
    n = target.n_frames
    if _kind(target).compound:
        scales = [loss_scale(p, topology, noise, noise_free) for p in target.parts]
        scale2, how = combined_scale2(target, [s2 for s2, _, _ in scales]), scales[0][1]
        dist, parts = _mixed_distance(target, topology, [s2 for s2, _, _ in scales])
        inv = 1.0 / n
    else:
        scale2, how, _ = loss_scale(target, topology, noise, noise_free)
        dist, parts = _frame_mean_sq(target, topology), ()
        inv = 1.0 / (n * scale2)
    volumes = None
    if check_volume:
        from jaxplush.model.forces import face_volumes
        volumes = lambda x: face_volumes(topology, x)  # noqa: E731

    def loss_fn(x, y):
        d = dist(x, y) * jnp.asarray(inv, x.dtype)
        if volumes is not None:
            d = jnp.where(jnp.all(volumes(x) > 0), d, jnp.nan)
        return d

    aux = jax.device_put(np.asarray(target.data, dtype))     # converted on the host: no conversion program
    # jitted: a direct call (a notebook's, a test's) is one program, not one per operation; inside
    # the fit's own jit it is inlined
    return Loss(jax.jit(loss_fn), aux, tuple(int(s) for s in target.steps), float(scale2), how, target.kind, parts)


def _mixed_distance(target, topology, scales):
    """(``(x (V, 3), y (M_points + M_tracks, 3)) -> sum_k weight_k d_k / s²_k``, the parts
    ((s²_k, weight_k), ...)) of a mixed target: its points' and its tracks' frame distances, each
    over its own columns of the frame and normalised by its own ``scales`` s²_k."""
    parts = target.parts
    weights = part_weights(target)
    dists = [_frame_mean_sq(p, topology) for p in parts]
    cut = parts[0].points.shape[1]
    cols = (slice(0, cut), slice(cut, None))
    factors = [c / s2 for c, s2 in zip(weights, scales)]

    def dist(x, y):
        return sum(d(x, y[c]) * jnp.asarray(f, x.dtype) for d, c, f in zip(dists, cols, factors))
    return dist, tuple((float(s2), float(c)) for s2, c in zip(scales, weights))


class Residual(NamedTuple):
    """The loss of :func:`make_loss` as a residual vector (for least-squares methods).

    Attributes:
      fn: ``frames (T, V, 3) -> (n,)`` normalised residuals with sum(r²) = the loss (jax).
      n: number of residuals; kind, scale2, normalisation: as in :class:`Loss`.
      per_frame: residuals per frame (3 V for positions, M for points, 3 M for tracks, M_points +
        3 M_tracks for mixed: the points' first).
      frame_fn: ``(frames (C, V, 3), data (C, M, 3)) -> (C * per_frame,)`` the same residuals of any
        C frames against their target data, before the normalisation (m): frames are independent,
        so residuals of a target's frames in chunks are the residuals of the whole (one compiled
        function serves every horizon of a fit).
      norm: the normalisation, 1 / sqrt(N s²) (N observed rows: T V, less a cloud's padding or the
        tracks not seen); for a mixed target (n,), each residual's (its points' and its tracks'
        terms, each with its weight); data: (T, M, 3) float64 target frames.
      near_fn: points and mixed only (else None): ``(frames (C, V, 3), data (C, M, 3)) -> (C *
        per_frame,)`` int32, the vertex each residual is measured from (a point's nearest vertex,
        as ``frame_fn`` finds it; a track's first vertex): the residual depends on that vertex's
        object alone.
    """

    fn: Callable
    n: int
    kind: str
    scale2: float
    normalisation: str
    per_frame: int
    frame_fn: Callable = None
    norm: float = 1.0
    data: object = None
    near_fn: Callable = None


def make_residual(target, topology, loss):
    """The :class:`Residual` of a :class:`Loss` built by :func:`make_loss` for the same target.

    A single kind's residuals are its kind's (:meth:`jaxplush.fitting.targets.kinds.Kind.residual`).
    A compound kind's (``Target.parts``, as a mixed target's scan and tracks) are its parts', per
    frame one part's after the other's (per_frame = the sum of the parts'), and ``norm`` is (n,):
    each residual's own normalisation (the parts' differ), so sum(r²) is the weighted loss;
    ``near_fn`` gives each residual's vertex (from a part's own ``near_fn``, else its fixed
    :meth:`~jaxplush.fitting.targets.kinds.Kind.residual_vertices`)."""
    data = np.asarray(target.data, np.float64)
    t = data.shape[0]
    if not _kind(target).compound:
        norm = 1.0 / np.sqrt(_kind(target).observed(data).sum() * loss.scale2)   # t m, less a cloud's padding
        frame_fn, per_frame, near_fn = _part_residual(target, topology, loss.scale2, loss.normalisation)
    else:
        frame_fn, per_frame, near_fn, norm = _compound_residual(target, topology, loss)

    def fn(frames):
        return frame_fn(frames, jnp.asarray(data, frames.dtype)) * jnp.asarray(norm, frames.dtype)
    return Residual(jax.jit(fn), t * per_frame, target.kind, loss.scale2, loss.normalisation, per_frame,
                    frame_fn=frame_fn, norm=float(norm) if np.ndim(norm) == 0 else norm, data=data, near_fn=near_fn)


def _compound_residual(target, topology, loss):
    """(frame_fn, per_frame, near_fn, norm (n,)) of a compound target: its parts' residuals, each
    part's data a slice of the target's rows (in the parts' order), each weighed as the loss
    weighs that part (``loss.parts``: its normaliser and factor)."""
    parts = target.parts
    made = [_part_residual(p, topology, s2, loss.normalisation) for p, (s2, _) in zip(parts, loss.parts)]
    sizes = [n for _, n, _ in made]
    norms = [np.sqrt(c / (_kind(p).observed(p.data).sum() * s2)) for p, (s2, c) in zip(parts, loss.parts)]
    norm = np.tile(np.repeat(norms, sizes), target.n_frames)
    cuts = np.cumsum([0] + [np.shape(p.data)[1] for p in parts])
    fixed = []
    for p, (_, n, near) in zip(parts, made):        # a part whose residuals' vertices do not move
        rows = None if near is not None else _kind(p).residual_vertices(p, topology)
        fixed.append(None if near is not None else
                     (np.full(n, -1, np.int32) if rows is None else np.asarray(rows[:n], np.int32)))

    def frame_fn(frames, y):
        c = frames.shape[0]
        return jnp.concatenate([f(frames, y[:, a:b]).reshape(c, n) for (f, n, _), a, b
                                in zip(made, cuts[:-1], cuts[1:])], axis=1).reshape(-1)

    def near_fn(frames, y):
        c = frames.shape[0]
        cols = []
        for (_, n, near), own, a, b in zip(made, fixed, cuts[:-1], cuts[1:]):
            cols.append(near(frames, y[:, a:b]).reshape(c, n) if near is not None else
                        jnp.broadcast_to(jnp.asarray(own), (c, n)))
        return jnp.concatenate(cols, axis=1).reshape(-1)
    return frame_fn, int(sum(sizes)), near_fn, norm


def _kind(target):
    """The :class:`~jaxplush.fitting.targets.kinds.TargetKind` of a target (or of anything with a
    ``kind`` name: a stand-in)."""
    return TargetKind(target.kind)


def _part_residual(target, topology, scale2, normalisation):
    """(frame_fn, per_frame, near_fn) of :class:`Residual` for a single-kind target whose loss has
    the normaliser ``scale2`` and ``normalisation``: its kind's
    (:meth:`jaxplush.fitting.targets.kinds.Kind.residual`)."""
    return _kind(target).residual(target, topology, scale2, normalisation)


