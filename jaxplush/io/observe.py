"""What a target observes of simulated frames, and how far they are from it: the geometry of
every built-in target kind's residual and loss term (:mod:`jaxplush.io.kinds` calls these; the
fit, :mod:`jaxplush.fitting.objective.losses`, builds its normalised loss on them). Pure JAX and
numpy; no IO.

* vertex positions: :func:`squared_distance`, :func:`vertex_residual`;
* a scan (points, no correspondence): each point's distance to the simulated surface
  (:func:`point_surface_distance2`, :func:`point_surface_signed_distance`, :func:`surface_residual`,
  with the noise's offset on a curved surface from :func:`vertex_mean_curvature`), and the
  symmetric :func:`chamfer` distance for a loss of one's own;
* tracked points (a vertex, or a fixed spot of a face): :func:`track_positions`,
  :func:`track_distance2`, :func:`track_residual`;
* the identifiability report's linearised residuals (:func:`nearest_point_residual`,
  :func:`track_linearised`, :func:`mixed_linearised`).

Rows of NaN are observations that are not there (a cloud's padding, a track not seen): they take
part in no value and no gradient.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

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
      near: (M,) index of each point's nearest vertex, if known; default: found here
        (:func:`nearest_vertices`, the mesh as one object).
    """
    if near is None:
        near = nearest_vertices(x, p, ((0, x.shape[0]),))[:, 0]
    return jnp.min(_candidate_faces(x, p, faces, vfaces, near)[1], axis=1)


def _candidate_faces(x, p, faces, vfaces, near):
    """(corners: 3 x (M, W, 3) positions of the faces around each point's nearest vertex,
    d2 (M, W): each point's squared distance to each of them). ``near`` (M,) or (M, O): with
    several vertices per point (the nearest on each object), the faces around all of them."""
    from jaxplush.model.contact import closest_point_distance2
    tri = jnp.asarray(faces)[jnp.asarray(vfaces)[near]]                 # (M, [O,] W, 3)
    tri = tri.reshape(tri.shape[0], -1, 3)                              # (M, W, 3)
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

    Args: as :func:`point_surface_distance2` (``near`` required; faces wound outward; (M, O):
      the nearest vertex on each of O objects, of which the closest face is taken).
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


#: the inner extent of :func:`nearest_vertices`'s table: reductions no longer than this fuse with
#: the distances they reduce (XLA:CPU splits longer ones through a table held in memory)
LANE = 32


def nearest_vertices(x, p, slices):
    """(M, O) int32: each point's nearest vertex on each of O objects, searched over every vertex
    of the object (``slices``: each object's (start, stop) vertex range; one object: ``((0, V),)``).

    Exact up to near-ties: squared distances are compared in float32 with their last
    b = ceil(log2 V_o) mantissa bits (V_o rounded up to a multiple of :data:`LANE`) replaced by
    the vertex's index within its object, so that a plain min-reduction yields the index (an
    argmin is a two-operand reduction, slower on CPU). Two vertices whose squared distances agree
    to about 2^(b - 23) of themselves (1.2e-4 for 1024 vertices) count as tied and the first wins;
    either is a nearest vertex for the faces around it. The table is laid out
    (M, V_o / LANE, LANE) and reduced over LANE first, which XLA:CPU fuses with the distances, so
    that at most 1/LANE of the table is held in memory. Reduced in one piece, the reduction is
    split and the whole (M, V_o) table is stored, per frame and per batch lane (2.4 times the
    peak memory, for a 32-lane batch of an 802-vertex scene).

    This replaced a greedy walk over the one-ring from a sparse set of starts, which can stop at a
    vertex nearer than its neighbours: on a deformed coarse torus it ended up to 36 mm farther than
    the nearest vertex, for 0.4% of a 2 mm scan's points, and it cost more (benchmarks/RESULTS.md,
    "The scan residual's nearest vertex")."""
    out = []
    for a, b in slices:
        n = b - a
        g = -(-n // LANE)
        bits = max(1, int(g * LANE - 1).bit_length())
        low = (1 << bits) - 1
        xo = jnp.concatenate([x[a:b], jnp.broadcast_to(x[a], (g * LANE - n, 3))]).reshape(g, LANE, 3)
        d2 = sum((p[:, None, None, k] - xo[None, :, :, k]) ** 2 for k in range(3))    # (M, G, LANE)
        key = jax.lax.bitcast_convert_type(d2.astype(jnp.float32), jnp.int32)          # ordered as d2
        key = (key & ~low) | jnp.arange(g * LANE, dtype=jnp.int32).reshape(g, LANE)[None]
        best = jnp.min(jnp.min(key, axis=2), axis=1) & low
        out.append(a + jnp.where(best < n, best, 0))         # a padding copy of vertex 0: only if NaN
    return jnp.stack(out, axis=1)


def nearest_of(x, p, cand):
    """(M,) for each point of p (M, 3), the nearest of its candidate vertices cand (M, O) of x."""
    if cand.shape[1] == 1:
        return cand[:, 0]
    d2 = jnp.sum((x[cand] - p[:, None, :]) ** 2, axis=-1)                       # (M, O)
    return jnp.take_along_axis(cand, jnp.argmin(d2, axis=1)[:, None], axis=1)[:, 0]


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


def vertex_residual(target):
    """The residual of a ``positions`` target (:meth:`jaxplush.fitting.targets.kinds.Kind.residual`):
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
    slices = tuple((int(a), int(b)) for a, b in topology.vertex_slices)

    # isotropic noise of sigma puts a sample of a curved surface outside it by sigma² H on
    # average (H the mean curvature there): each distance has that expected offset taken off,
    # with H of the simulated frame at the point's nearest vertex (else a convex shape's fit
    # leans to whatever inflates it or rounds it off)
    curv = curvature_tables(faces, topology.n_vertices)
    sigma2 = float(scale2) if normalisation == "noise" else 0.0

    def one(x, p, h):
        valid, p = observed_points(p)                                # padding: residual 0
        # the closest face around each object's nearest vertex: near the contact between two
        # objects, a point's nearest vertex can lie on one object and its nearest face on the other
        ends = nearest_vertices(x, p, slices)                                 # (M, O)
        d = point_surface_signed_distance(x, p, faces, vf, ends)
        d = d if h is None else d - jnp.asarray(sigma2, x.dtype) * h[nearest_of(x, p, ends)]
        return jnp.where(valid, d, 0.0)

    def frame_fn(frames, y):
        if sigma2:
            return jax.vmap(one)(frames, y, vertex_mean_curvature(frames, curv)).reshape(-1)
        return jax.vmap(lambda x, p: one(x, p, None))(frames, y).reshape(-1)

    def near_fn(frames, y):
        def one_near(x, p):
            return nearest_of(x, p, nearest_vertices(x, p, slices))
        return jax.vmap(one_near)(frames, observed_points(y)[1]).reshape(-1)
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
