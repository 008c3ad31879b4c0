"""Per-frame losses and residuals between simulated positions and a target (pure jax; no IO).

* :func:`squared_distance`: mean squared vertex distance, for ``positions`` targets (the
  vertices correspond one to one).
* :func:`point_surface_distance2`: squared distance of every target point to the simulated
  surface, for ``points`` targets (a scan: M points with no correspondence to the V vertices).
* :func:`chamfer`: the symmetric vertex-to-point Chamfer distance (a loss of one's own).
* :func:`track_positions`: the simulated positions of tracked points (vertices, or points on
  faces by barycentric weights), for ``tracks`` targets: each observed track's squared
  distance to its simulated position (rows of NaN, tracks not seen, left out).

:func:`make_loss` builds the frame loss that :func:`jaxplush.fitting.gradients.rollout_loss` sums over
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

from jaxplush.fitting.kinds import TargetKind

#: matrix products ask for full float32 precision: a GPU's default (TF32 on NVIDIA) keeps 10 mantissa
#: bits, which leaves millimetres of error in |x|² + |p|² - 2 x.p
HIGHEST = jax.lax.Precision.HIGHEST


def squared_distance(x, y):
    """Mean over vertices of |x_i - y_i|² (m²); x, y: (V, 3)."""
    d = x - y
    return jnp.mean(jnp.sum(d * d, axis=-1))


def pairwise_sq_distances(x, p):
    """(V, M) squared distances between the rows of x (V, 3) and p (M, 3).

    Expanded as |x|² + |p|² - 2 x.p about the cloud's centroid (which keeps the cancellation
    small in float32: the operands are object-sized, not world-sized), clamped at 0.
    """
    c = jax.lax.stop_gradient(jnp.mean(p, axis=0))
    xc, pc = x - c, p - c
    cross = jnp.matmul(xc, pc.T, precision=HIGHEST)
    d2 = jnp.sum(xc * xc, axis=1)[:, None] + jnp.sum(pc * pc, axis=1)[None, :] - 2.0 * cross
    return jnp.maximum(d2, 0.0)


def observed_points(p):
    """(valid (M,) bool, p with its NaN rows, a point cloud's padding, put at the centroid of the
    observed points): the padding then takes part in no distance and no gradient (a NaN would reach
    both through ``jnp.where``'s untaken branch), and the cloud's centroid, about which
    :func:`pairwise_sq_distances` expands, is the observed points' own."""
    valid = jnp.all(jnp.isfinite(p), axis=-1)
    zeroed = jnp.where(valid[..., None], p, 0.0)
    centre = jnp.sum(zeroed, axis=-2, keepdims=True) / jnp.maximum(jnp.sum(valid, axis=-1), 1)[..., None, None]
    return valid, jnp.where(valid[..., None], p, centre)


def chamfer(x, p):
    """Symmetric Chamfer distance (m²): mean_i min_k |x_i - p_k|² + mean_k min_i |x_i - p_k|².

    Args:
      x: (V, 3) simulated vertex positions.
      p: (M, 3) target points (M unrelated to V); rows of NaN are absent (a frame's padding).
    """
    valid, p = observed_points(p)
    d2 = pairwise_sq_distances(x, p)
    near_point = jnp.min(jnp.where(valid[None, :], d2, jnp.inf), axis=1)
    near_vertex = jnp.min(d2, axis=0)
    return jnp.mean(near_point) + jnp.sum(jnp.where(valid, near_vertex, 0.0)) / jnp.sum(valid)


def track_positions(x, vertices, weights):
    """(M, 3) positions of tracked points: sum_k weights[:, k] x[vertices[:, k]] (jax or numpy).

    Args:
      x: (V, 3) vertex positions; vertices: (M, 3) int vertex indices of each track (a vertex
        track: [v, v, v]); weights: (M, 3) its barycentric weights (a vertex track: [1, 0, 0]).
    """
    return sum(weights[:, k, None] * x[vertices[:, k]] for k in range(3))


def track_distance2(vertices, weights, weight=1.0):
    """``(x (V, 3), y (M, 3)) -> sum over the observed tracks of |track_positions(x) - y|²`` times
    ``weight`` (m²); rows of NaN in y (not seen) take part in no value and no gradient."""
    vertices, weights = np.asarray(vertices, np.int32), np.asarray(weights, np.float64)

    def dist(x, y):
        valid = jnp.all(jnp.isfinite(y), axis=-1)
        d = track_positions(x, vertices, jnp.asarray(weights, x.dtype)) - jnp.where(valid[:, None], y, 0.0)
        return jnp.sum(jnp.where(valid, jnp.sum(d * d, axis=-1), 0.0)) * jnp.asarray(weight, x.dtype)
    return dist


def vertex_faces(faces, n_vertices):
    """(V, W) int32 faces around each vertex, padded by repeating the vertex's first face."""
    faces = np.asarray(faces, np.int64)
    around = [[] for _ in range(n_vertices)]
    for fi, f in enumerate(faces):
        for v in f:
            around[v].append(fi)
    w = max(len(a) for a in around)
    return np.array([a + [a[0]] * (w - len(a)) for a in around], np.int32)


def point_surface_distance2(x, p, faces, vfaces, near=None):
    """(M,) squared distance of every target point to the simulated surface (m²).

    The distance of p_k is to the closest of the faces around p_k's nearest vertex (exact for a
    point closer to the surface than about half an edge, which measured surface points are). At
    the true shape a noisy surface sample lies at its noise's normal component from the
    surface, so, unlike the distance to the nearest vertex (which cannot fall below the mesh's
    sampling spacing), this residual reaches the noise level.

    Args:
      x: (V, 3) simulated vertex positions; p: (M, 3) target points.
      faces: (F, 3) int faces; vfaces: (V, W) faces around each vertex (:func:`vertex_faces`).
      near: (M,) index of each point's nearest vertex, if known (:func:`nearest_vertices_walk`);
        default: found here by brute force (an (M, V) table).
    """
    if near is None:
        d2v = sum((x[:, None, c] - p[None, :, c]) ** 2 for c in range(3))   # (V, M); a K=3 dot is slower
        near = jnp.argmin(d2v, axis=0)                                      # (M,) nearest vertex
    return jnp.min(_candidate_faces(x, p, faces, vfaces, near)[1], axis=1)


def _candidate_faces(x, p, faces, vfaces, near):
    """(corners: 3 x (M, W, 3) positions of the faces around each point's nearest vertex,
    d2 (M, W): each point's squared distance to each of them)."""
    from jaxplush.model.contact import closest_point_distance2
    tri = jnp.asarray(faces)[jnp.asarray(vfaces)[near]]                 # (M, W, 3)
    corner = [x[tri[..., i]] for i in range(3)]                         # 3 x (M, W, 3)
    split = lambda a: tuple(a[..., c] for c in range(3))  # noqa: E731
    return corner, closest_point_distance2(split(p[:, None, :]), *(split(c) for c in corner))


def point_surface_signed_distance(x, p, faces, vfaces, near):
    """(M,) signed distance (m) of every target point to the simulated surface: the distance of
    :func:`point_surface_distance2`, positive outside (on the side the closest face's outward
    normal points to), negative inside.

    As a least-squares residual the signed distance is smooth where a point crosses the surface;
    the unsigned one has a kink there, so its difference Jacobian vanishes for the noisy samples
    that lie close to the surface, and the Gauss-Newton model of the loss is wrong near the optimum.

    Args: as :func:`point_surface_distance2` (``near`` required; faces wound outward).
    """
    corner, d2 = _candidate_faces(x, p, faces, vfaces, near)
    k = jnp.argmin(d2, axis=1)[:, None, None]                           # (M, 1, 1)
    a, b, c = (jnp.take_along_axis(v, k, axis=1)[:, 0] for v in corner)  # 3 x (M, 3)
    side = jnp.sum((p - a) * jnp.cross(b - a, c - a), axis=-1)
    dist = jnp.sqrt(jnp.take_along_axis(d2, k[..., 0], axis=1)[:, 0])
    return jnp.where(side < 0, -dist, dist)


def point_surface(faces, n_vertices, weight=None):
    """``(x (V, 3), p (M, 3)) -> mean squared point-to-surface distance`` (m²) for a mesh's faces.

    ``weight`` (for point clouds with NaN padding, frames of different sizes): the frame's value
    is instead the sum over its observed points times ``weight``; with weight T / N (N points
    observed over T frames), the mean over the frames weighs every observed point alike."""
    vf = vertex_faces(faces, n_vertices)
    faces = np.asarray(faces, np.int32)
    if weight is None:
        return lambda x, p: jnp.mean(point_surface_distance2(x, p, faces, vf))

    def ragged(x, p):
        valid, p = observed_points(p)
        d2 = point_surface_distance2(x, p, faces, vf)
        return jnp.sum(jnp.where(valid, d2, 0.0)) * jnp.asarray(weight, d2.dtype)
    return ragged


def _kind(target):
    """The :class:`~jaxplush.fitting.kinds.TargetKind` of a target (or of anything with a ``kind``
    name: a stand-in)."""
    return TargetKind(target.kind)


def point_weight(target, always=False):
    """T / N for a target's rows with NaN padding or rows not seen (N observed over T frames; see
    :func:`point_surface`), None where every row is observed (unless ``always``: a tracks target's
    distance is always a sum over its tracks)."""
    if _kind(target).compound:
        raise ValueError("a mixed target's terms are weighed each on its own (Target.parts)")
    observed = _kind(target).observed(target.data)
    if not always and observed.all():
        return None
    if not observed.any():
        raise ValueError(f"{target.path}: the target's frames hold no observation")
    return len(observed) / float(observed.sum())


class Loss(NamedTuple):
    """A frame loss ready for :func:`jaxplush.fitting.gradients.rollout_loss`.

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
    (:meth:`jaxplush.fitting.kinds.Kind.mean_sq`)."""
    return _kind(target).mean_sq(target, topology)


def components(kind):
    """Residual components per observation of a kind (:attr:`jaxplush.fitting.kinds.Kind.components`):
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


def coarse_vertices(x0, n):
    """Indices of ``n`` vertices spread over a mesh (farthest-point sampling of the rest shape
    x0 (V, 3), from vertex 0; numpy): the starts of :func:`nearest_vertices_walk`."""
    x0 = np.asarray(x0, np.float64)
    n = int(min(max(n, 1), len(x0)))
    chosen = [0]
    d2 = np.sum((x0 - x0[0]) ** 2, axis=1)
    for _ in range(n - 1):
        i = int(np.argmax(d2))
        chosen.append(i)
        d2 = np.minimum(d2, np.sum((x0 - x0[i]) ** 2, axis=1))
    return np.asarray(chosen, np.int32)


#: Steps of the walk from the nearest coarse vertex to the nearest vertex.
WALK_STEPS = 4


def nearest_vertices_walk(x, p, coarse, ring, steps=WALK_STEPS):
    """(M,) index of each point's nearest vertex: the nearest of the ``coarse`` vertices (an (M, S)
    table, S ~ V/8), then ``steps`` moves to the nearest of the current vertex and its one-ring
    (``ring`` (V, K)). Exact where the distance to the point has no other local minimum over the
    mesh's vertices nearby, as for points within an edge or so of the surface; about six times
    fewer distances than the (M, V) table.

    Args:
      x: (V, 3) vertex positions; p: (M, 3) points; coarse: (S,) vertex indices; ring: (V, K).
    """
    xc = x[jnp.asarray(coarse)]
    d2c = sum((xc[:, None, c] - p[None, :, c]) ** 2 for c in range(3))          # (S, M)
    cur = jnp.asarray(coarse)[jnp.argmin(d2c, axis=0)]                          # (M,)
    ring = jnp.asarray(ring)
    for _ in range(steps):
        cand = jnp.concatenate([cur[:, None], ring[cur]], axis=1)               # (M, K + 1)
        d2 = jnp.sum((x[cand] - p[:, None, :]) ** 2, axis=-1)
        cur = jnp.take_along_axis(cand, jnp.argmin(d2, axis=1)[:, None], axis=1)[:, 0]
    return cur


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


def curvature_tables(faces, n_vertices):
    """The stencil of :func:`vertex_mean_curvature` for a closed, outward-wound mesh: (faces
    (F, 3); wings (E, 4): per unique edge a-b, with c the third corner of the face running a -> b
    and d that of the face running b -> a; vertex_edges (V, K) and vertex_faces (V, K): each
    vertex's edges and faces, padded with E and F, which index an appended zero)."""
    faces = np.asarray(faces, np.int64)
    third = {}
    for f in faces:
        for i in range(3):
            third[(int(f[i]), int(f[(i + 1) % 3]))] = int(f[(i + 2) % 3])
    wings = np.asarray([(a, b, c, third[(b, a)]) for (a, b), c in third.items() if a < b and (b, a) in third],
                       np.int64).reshape(-1, 4)
    ve = [[] for _ in range(n_vertices)]
    for e, (a, b) in enumerate(wings[:, :2]):
        ve[a].append(e)
        ve[b].append(e)
    vf = [[] for _ in range(n_vertices)]
    for fi, f in enumerate(faces):
        for v in f:
            vf[int(v)].append(fi)

    def pad(rows, fill):
        k = max(1, max(len(r) for r in rows))
        return np.asarray([r + [fill] * (k - len(r)) for r in rows], np.int32)

    return faces.astype(np.int32), wings.astype(np.int32), pad(ve, len(wings)), pad(vf, len(faces))


def vertex_mean_curvature(x, tables):
    """(..., V) discrete mean curvature (1/m) of a closed mesh at every vertex of x (..., V, 3),
    positive where the surface is convex: a quarter of the sum over the vertex's edges of length x
    signed dihedral angle, over a third of the area of its faces (1/R on a sphere of radius R,
    1/(2R) on a cylinder; mean curvature is (k1 + k2) / 2).

    Each edge's angle and each face's area is computed once, and the sums over a vertex's edges
    and faces are gathers (a scatter is slow on a CPU). It runs on components laid out (3, V,
    frames), so that every gather moves rows of frames: on 1600 frames of a 642-vertex mesh,
    0.27 s against 0.66 s for the same arithmetic vmapped over frames (0.09 s of it without the
    transposes in and out).

    Args: x (..., V, 3) positions; tables: :func:`curvature_tables` of the mesh.
    """
    faces, wings, vertex_edges, vertex_faces_ = (np.asarray(t) for t in tables)
    lead = x.shape[:-2]
    comp = jnp.transpose(x.reshape((-1,) + x.shape[-2:]), (2, 1, 0))      # (3, V, N)
    xs = tuple(comp[k] for k in range(3))                                  # 3 x (V, N)

    def at(idx):
        return tuple(c[idx] for c in xs)

    def sub(u, v):
        return tuple(p - q for p, q in zip(u, v))

    def cross(u, v):
        return (u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0])

    def dot(u, v):
        return u[0] * v[0] + u[1] * v[1] + u[2] * v[2]

    a, b, c, d = (at(wings[:, i]) for i in range(4))
    e = sub(b, a)
    n1, n2 = cross(e, sub(c, a)), cross(sub(d, a), e)           # outward normals of the two wings
    length = jnp.sqrt(dot(e, e))
    theta = jnp.arctan2(dot(cross(n1, n2), e) / jnp.maximum(length, 1e-30), dot(n1, n2))  # > 0: convex
    zero = jnp.zeros((1,) + theta.shape[1:], x.dtype)
    w = jnp.concatenate([0.25 * length * theta, zero])
    p, q, r = (at(faces[:, i]) for i in range(3))
    n = cross(sub(q, p), sub(r, p))
    third = jnp.concatenate([jnp.sqrt(dot(n, n)) / 6.0, zero])          # a third of each face's area
    h = w[vertex_edges].sum(axis=1) / jnp.maximum(third[vertex_faces_].sum(axis=1), jnp.finfo(x.dtype).tiny)
    return jnp.moveaxis(h, -1, 0).reshape(lead + (x.shape[-2],))


def make_residual(target, topology, loss):
    """The :class:`Residual` of a :class:`Loss` built by :func:`make_loss` for the same target.

    A mixed target's residuals are, per frame, its points' and then its tracks' (per_frame =
    M_points + 3 M_tracks), and ``norm`` is (n,): each residual's own normalisation (the points'
    and the tracks' differ), so sum(r²) is the weighted loss; ``near_fn`` gives each residual's
    vertex (a point's nearest, a track's first)."""
    data = np.asarray(target.data, np.float64)
    t = data.shape[0]
    if not _kind(target).compound:
        norm = 1.0 / np.sqrt(_kind(target).observed(data).sum() * loss.scale2)   # t m, less a cloud's padding
        frame_fn, per_frame, near_fn = _part_residual(target, topology, loss.scale2, loss.normalisation)
    else:
        parts = target.parts
        (f_pts, n_pts, near_pts), (f_trk, n_trk, _) = (
            _part_residual(p, topology, s2, loss.normalisation) for p, (s2, _) in zip(parts, loss.parts))
        norms = [np.sqrt(c / (_kind(p).observed(p.data).sum() * s2)) for p, (s2, c) in zip(parts, loss.parts)]
        norm = np.tile(np.repeat(norms, [n_pts, n_trk]), t)
        cut = parts[0].points.shape[1]
        track_vertex = np.repeat(np.asarray(parts[1].track_vertices, np.int32)[:, 0], 3)   # (3 M_tracks,)

        def frame_fn(frames, y):
            c = frames.shape[0]
            rp = f_pts(frames, y[:, :cut]).reshape(c, n_pts)
            rt = f_trk(frames, y[:, cut:]).reshape(c, n_trk)
            return jnp.concatenate([rp, rt], axis=1).reshape(-1)

        def near_fn(frames, y):
            c = frames.shape[0]
            near = near_pts(frames, y[:, :cut]).reshape(c, n_pts)
            own = jnp.broadcast_to(jnp.asarray(track_vertex, near.dtype), (c, n_trk))
            return jnp.concatenate([near, own], axis=1).reshape(-1)
        per_frame = n_pts + n_trk

    def fn(frames):
        return frame_fn(frames, jnp.asarray(data, frames.dtype)) * jnp.asarray(norm, frames.dtype)
    return Residual(jax.jit(fn), t * per_frame, target.kind, loss.scale2, loss.normalisation, per_frame,
                    frame_fn=frame_fn, norm=float(norm) if np.ndim(norm) == 0 else norm, data=data, near_fn=near_fn)


def _part_residual(target, topology, scale2, normalisation):
    """(frame_fn, per_frame, near_fn) of :class:`Residual` for a single-kind target whose loss has
    the normaliser ``scale2`` and ``normalisation``: its kind's
    (:meth:`jaxplush.fitting.kinds.Kind.residual`)."""
    return _kind(target).residual(target, topology, scale2, normalisation)


def vertex_residual(target):
    """The residual of a ``positions`` target (:meth:`jaxplush.fitting.kinds.Kind.residual`):
    every vertex's simulated minus observed position."""
    m = np.shape(target.data)[1]

    def frame_fn(frames, y):
        return (frames - y).reshape(-1)
    return frame_fn, 3 * m, None


def track_residual(target):
    """The residual of a ``tracks`` target: each seen track's simulated minus observed position
    (0 for a track not seen)."""
    m = np.shape(target.data)[1]
    tv, tw = np.asarray(target.track_vertices, np.int32), np.asarray(target.track_weights, np.float64)

    def one_track(x, y):
        valid = jnp.all(jnp.isfinite(y), axis=-1)                   # not seen: residual 0
        d = track_positions(x, tv, jnp.asarray(tw, x.dtype)) - jnp.where(valid[:, None], y, 0.0)
        return jnp.where(valid[:, None], d, 0.0)

    def frame_fn(frames, y):
        return jax.vmap(one_track)(frames, y).reshape(-1)
    return frame_fn, 3 * m, None


def surface_residual(target, topology, scale2, normalisation):
    """The residual of a ``points`` target: each point's signed distance to the simulated surface
    (0 for padding), less the offset a known noise puts it at on a curved surface."""
    m = np.shape(target.data)[1]
    faces = np.asarray(topology.faces, np.int32)
    vf = vertex_faces(faces, topology.n_vertices)
    coarse = coarse_vertices(topology.x0, -(-topology.n_vertices // 8))
    ring = np.asarray(topology.ring, np.int32)

    # isotropic noise of sigma puts a sample of a curved surface outside it by sigma² H on
    # average (H the mean curvature there): each distance has that expected offset taken off,
    # with H of the simulated frame at the point's nearest vertex (else a convex shape's fit
    # leans to whatever inflates it or rounds it off)
    curv = curvature_tables(faces, topology.n_vertices)
    sigma2 = float(scale2) if normalisation == "noise" else 0.0

    def one(x, p, h):
        valid, p = observed_points(p)                                # padding: residual 0
        near = nearest_vertices_walk(x, p, coarse, ring)
        d = point_surface_signed_distance(x, p, faces, vf, near)
        d = d if h is None else d - jnp.asarray(sigma2, x.dtype) * h[near]
        return jnp.where(valid, d, 0.0)

    def frame_fn(frames, y):
        if sigma2:
            return jax.vmap(one)(frames, y, vertex_mean_curvature(frames, curv)).reshape(-1)
        return jax.vmap(lambda x, p: one(x, p, None))(frames, y).reshape(-1)

    def near_fn(frames, y):
        return jax.vmap(lambda x, p: nearest_vertices_walk(x, p, coarse, ring))(
            frames, observed_points(y)[1]).reshape(-1)
    return frame_fn, m, near_fn


def nearest_vertex(x, p):
    """(M,) int64 the nearest vertex of x (V, 3) to each point of p (M, 3) (numpy, chunked; a
    cloud's NaN padding is measured from the origin, and its residual is 0 anyway)."""
    p = np.where(np.isfinite(p), p, 0.0)
    near = np.empty(len(p), np.int64)
    for a in range(0, len(p), 512):
        d2 = np.sum((p[a:a + 512, None, :] - x[None, :, :]) ** 2, axis=-1)
        near[a:a + 512] = np.argmin(d2, axis=1)
    return near


def nearest_point_residual(frames, clouds):
    """(T V 3,) per frame, the vector from each vertex to its nearest observed point (numpy,
    chunked; NaN padding left out): a scan's residual for the identifiability report, whose
    Jacobian is the frames' own."""
    out = []
    for x, p in zip(np.asarray(frames, np.float64), np.asarray(clouds, np.float64)):
        p = p[np.isfinite(p).all(axis=1)]
        r = np.empty_like(x)
        for a in range(0, len(x), 512):
            d2 = ((x[a:a + 512, None, :] - p[None, :, :]) ** 2).sum(-1)
            r[a:a + 512] = x[a:a + 512] - p[np.argmin(d2, axis=1)]
        out.append(r.reshape(-1))
    return np.concatenate(out)


def track_linearised(target, frames, jac):
    """(residual (3 N,), jac (3 N, P)) of a tracks target's N observations: each seen track's
    simulated minus observed position, and the frames' Jacobian (3 T V, P) mapped to the tracks'
    positions (linear in the vertices) with the rows of tracks not seen left out."""
    t, v = frames.shape[:2]
    tv, tw = np.asarray(target.track_vertices), np.asarray(target.track_weights, np.float64)
    seen = target.observed                                              # (T, M)
    sim = np.stack([track_positions(x, tv, tw) for x in np.asarray(frames, np.float64)])   # (T, M, 3)
    j = np.asarray(jac, np.float64).reshape(t, v, 3, -1)
    jt = np.stack([track_positions(x, tv, tw[..., None]) for x in j])   # (T, M, 3, P)
    return (sim - target.tracks)[seen].reshape(-1), jt[seen].reshape(-1, j.shape[-1])


def mixed_linearised(target, loss, frames, jac):
    """(residual, jac) of a mixed target: its scan's rows (each vertex to its nearest point, m, with
    the frames' Jacobian) and its tracks' (:func:`track_linearised`), the tracks' rows scaled to
    weigh against the scan's as in the loss: per squared metre, w / (N_tracks s²_tracks) against
    1 / (T V s²_points) (``loss.parts``), so the report's residual RMS is in the scan's metres."""
    points, tracks = target.parts
    (s2_p, c_p), (s2_t, c_t) = loss.parts
    r_p = nearest_point_residual(frames, points.points)
    r_t, j_t = track_linearised(tracks, frames, jac)
    scale = np.sqrt((c_t / (int(tracks.observed.sum()) * s2_t)) / (c_p / (r_p.size / 3 * s2_p)))
    return (np.concatenate([r_p, r_t * scale]),
            np.concatenate([np.asarray(jac, np.float64).reshape(r_p.size, -1), j_t * scale]))
