"""Soft-soft contact between plushies (docs/model.md §7): a smooth penalty derived from a potential.

Model. For every vertex p of object A near object B, let q be the closest point of B's surface and
s the signed distance (positive outside B). Each such vertex carries the energy

    U(p) = k_c / 2 * phi(delta - s)²,   phi(z) = softplus(beta z) / beta,   beta = 10 / delta,

a smooth ramp that starts about ``delta`` (the contact thickness) outside B and grows
quadratically inside. The force on p and on the three vertices of q's triangle is -dU/dx,
assembled in closed form (:func:`make_contact`; a test checks it against ``jax.grad`` of the
summed energy, :func:`make_contact_energy`); self-collision takes ``jax.grad`` of its energy.
The energy is translation and rotation invariant, so linear and angular momentum are conserved
to round-off. It is applied both ways (A's vertices against B's faces and B's vertices against
A's faces).

Sign (the inside test, the backstop for deep penetration): s = (p - a).n on the interior of the
closest face (smooth through zero); where the closest point lies on an edge or a vertex, s = +-|p - q|
with the sign of (p - q).N for the angle-weighted pseudo-normal N of that feature (Baerentzen and
Aanaes), which classifies inside and outside correctly at any depth, so a vertex that got deep
inside is still pushed out along the shortest way.

Candidates (static shapes, no N_A x F_B work):

1. broad phase per object pair: only vertices inside the other object's bounding box and bounding
   sphere, both inflated by ``2 delta + 1.5 x`` the longest rest edge (the force's reach) plus
   twice the skin s (:func:`skin_distance`, half the longest rest edge), take part; they are
   compacted into a list of fixed capacity (``jnp.nonzero(size=...)``);
2. narrow phase: each candidate vertex finds the nearest candidate vertex of the other object
   (a cap_A x cap_B distance table, its argmin one packed integer min). A candidate whose nearest
   vertex is farther than 2 delta + an edge + s cannot come within the force's reach before the
   next search (:func:`_near_limits`); the others, the queries, of every pair are compacted to
   the front of one list, which the force runs in blocks of :data:`QUERY_BLOCK`, only as many as
   hold queries (:func:`_blockwise`), so its cost follows the contact patch, not the capacities
   (the broad phase's box and sphere hold several times more vertices). The closest face is
   searched among the faces of that vertex's one-ring (the force, :func:`make_contact`), or
   among the faces touching that vertex or its one-ring (about 24; the reference energy,
   :func:`make_contact_energy`). On a fair mesh the closest face of any point within an edge
   length of the surface is among them.

Temporal coherence (Verlet lists). Rollouts carry the candidate lists from step to step
(:class:`ContactCache`, ``Simulator.internal.coherent``): they are rebuilt by the search above only once
some vertex near the contact has moved more than s/2 since the last build, which the skin makes exact (a vertex
now within reach of the other object's box and sphere was within reach + 2 s of them at the
build); between rebuilds each query's nearest vertex is walked to the nearest of itself and its
two-ring, which follows any sliding of less than an edge per step (a walk over the one-ring alone
can stop at a vertex nearer than its neighbours while the nearest vertex lies two rings away). Only the vertices in some
pair's broad phase at the build are watched: the others may move freely as long as none comes
near the other object's box and sphere as they are now (:meth:`CacheOps.stale`), so a membrane
fluttering far from the contact does not rebuild the lists every few steps. A resting or slowly
moving contact then costs only the narrow phase. Objects that are apart cost less still: the
distance tables of a pair are built only when both its objects have candidates, and the narrow
phase and the walk run no block while no pair has a query (the batched engine of
:mod:`jaxplush.stepping.batched` takes each block's branch once for the whole batch). ``make_simulator(..., coherent_contact=False)`` and the
single ``step_fn`` search every step (the same forces but for near-ties between faces).

The search over a vertex's ring runs on slot-major (K, Q) arrays, and values are gathered and
picked several at a time: XLA:CPU vectorises such elementwise loops, while its reductions over a
short leading axis, its 2-D concatenations and its atan2 run element by element, and each XLA
operation adds a fixed dispatch cost inside the step's loop (see benchmarks/RESULTS.md).

The cost is O(cap_A cap_B) per rebuild, set by the capacities (which follow the contact area, not
the meshes), and O(n K) per step for n queries. If more vertices than the capacity
fall in an overlap region the step cannot be exact: the force then uses the candidates that fit
(it stays finite), and the overflow is a status, not a NaN (as JAX-MD's neighbour-list overflow
flag): :class:`ContactCache` carries a per-object flag that stays set once an overflow is seen, the
rollout turns it into the object's health code ``diagnostics.CONTACT_OVERFLOW`` at the next saved
frame, and ``Simulator.status_fn`` reports it for a state whose fresh search overflows
(:func:`make_overflow_check`). :func:`jaxplush.simulate` then reruns with a larger capacity
(:func:`capacity_report` outside ``jit`` tells which pair overflowed and the capacity needed;
``with_capacity`` rebuilds).

Self-collision (``self_collision on``) is cloth-style: an unsigned-distance penalty between each
vertex and its own object's faces more than two rest edges away (inside/outside is not
meaningful against one's own far surface). It is O(N²) per object and meant for meshes of at most
about a thousand vertices.

Defaults (docs/model.md §6, §9.1): thickness delta = half the mean rest edge length of the pair's
finer object; stiffness k_c = kappa m omega_G² with omega_G² = 2 k n_max / m the Gershgorin bound
of the springs (docs/model.md §4), i.e. k_c = kappa 2 n_max min(k_A, k_B), kappa = 0.1: contact raises
omega_max² by at most about 10% (the stable dt drops by about 5%), and k_c scales with k, hence
with mass under the symmetry (k, c, nRT, M) -> lambda (k, c, nRT, M), unlike a fixed absolute
stiffness. ``contact_stiffness K`` (N/m) in a scene fixes it instead. With a per-edge stiffness
field, k_A is object A's mean over its edges (:func:`jaxplush.model.layout.object_stiffness`).
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxplush.model.layout import object_stiffness, scene_value, sum_rows as _sum_rows, vertex_mass

#: kappa of the default stiffness k_c = kappa * 2 * n_max * min(k_A, k_B).
STIFFNESS_FACTOR = 0.1
#: Default thickness, as a fraction of the pair's finer mean rest edge length.
THICKNESS_FACTOR = 0.5
#: Sharpness of the softplus ramp, beta * delta.
SHARPNESS = 10.0
#: Default candidate capacity per object and pair: max(MIN_CAPACITY, n / CAPACITY_DIVISOR), <= n
#: (two 2562-vertex balls pressed together need about 200, the skin included).
MIN_CAPACITY = 96
CAPACITY_DIVISOR = 12
#: Below the friction cone, contact friction removes at most this fraction of the relative sliding
#: velocity per step; each contact is seen from both objects, so 0.5 never reverses the sliding.
FRICTION_CLAMP = 0.5
#: Skin of the coherent candidate cache, as a fraction of the pair's longest rest edge.
SKIN_FACTOR = 0.5


@dataclasses.dataclass(frozen=True)
class ContactConfig:
    """Static soft-soft contact settings (hashable; part of :class:`jaxplush.model.forces.Terms`).

    Attributes:
      pairs: ((A, B), ...) object pairs with A < B that may touch.
      self_objects: objects with self-collision.
      thickness: ((A, B) -> delta) as a tuple aligned with ``pairs``, m; ``self_thickness`` per
        entry of ``self_objects``.
      stiffness: fixed k_c in N/m, or None for the default kappa 2 n_max min(k_A, k_B).
      capacity: (O,) candidate vertices per object and pair.
      friction: Coulomb coefficient between objects (0: frictionless, not compiled in).
    """

    pairs: tuple
    self_objects: tuple
    thickness: tuple
    self_thickness: tuple
    stiffness: float | None
    capacity: tuple
    friction: float = 0.0

    def __bool__(self):
        return bool(self.pairs or self.self_objects)


def config_for_scene(scene):
    """:class:`ContactConfig` from a scene's keywords, or None when nothing can touch.

    Soft-soft contact is on for every pair of a multi-object scene (``contact off`` disables it);
    self-collision only with ``self_collision on``.
    """
    n_obj = scene.n_objects
    want_pairs = n_obj > 1 and scene.contact
    selfs = tuple(range(n_obj)) if scene.self_collision else ()
    if not want_pairs and not selfs:
        return None
    mean_edge = []
    for o in scene.objects:
        f = scene.faces[o.face_slice[0]:o.face_slice[1]]
        e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
        mean_edge.append(float(np.linalg.norm(scene.vertices[e[:, 0]] - scene.vertices[e[:, 1]], axis=1).mean()))
    fixed = scene.contact_thickness
    pairs = tuple((a, b) for a in range(n_obj) for b in range(a + 1, n_obj)) if want_pairs else ()
    thick = tuple(fixed if fixed is not None else THICKNESS_FACTOR * min(mean_edge[a], mean_edge[b])
                  for a, b in pairs)
    self_thick = tuple(fixed if fixed is not None else THICKNESS_FACTOR * mean_edge[o] for o in selfs)
    cap = scene.contact_capacity
    capacity = tuple(min(o.n_vertices, cap if cap is not None else
                         max(MIN_CAPACITY, -(-o.n_vertices // CAPACITY_DIVISOR))) for o in scene.objects)
    return ContactConfig(pairs=pairs, self_objects=selfs, thickness=thick, self_thickness=self_thick,
                         stiffness=scene.contact_stiffness, capacity=capacity,
                         friction=float(scene.contact_friction) if pairs else 0.0)


def with_capacity(terms, capacity, sizes=None):
    """``terms`` with every object's candidate capacity raised to at least ``capacity`` (an int or
    (O,)), and at most its vertex count ``sizes[o]`` when given (an object cannot have more
    candidates than vertices, so that capacity never overflows; :func:`object_sizes`)."""
    cfg = terms.contact
    cap = np.broadcast_to(np.asarray(capacity, np.int64), (len(cfg.capacity),))
    top = (None,) * len(cap) if sizes is None else tuple(int(n) for n in sizes)
    return dataclasses.replace(terms, contact=dataclasses.replace(
        cfg, capacity=tuple(int(max(c, n)) if t is None else int(min(t, max(c, n)))
                            for c, n, t in zip(cfg.capacity, cap, top))))


def with_headroom(terms, sizes, factor=2, least=0):
    """``terms`` with every object's candidate capacity multiplied by ``factor`` (and at least
    ``least``), each at most its vertex count ``sizes[o]`` (:func:`object_sizes`); unchanged
    without soft-soft contact. A fit ranges over parameters that squash objects into each other
    far more than the scene's own values: headroom given once costs less than the reruns and
    compiles of growing on overflow. A capacity that comes within :data:`WHOLE_FRACTION` of its
    object's vertex count is the vertex count: it then costs about the same and cannot overflow
    (a 642-vertex object at 640 overflowed mid-fit, and the growth to 642 recompiled every
    rollout)."""
    if not terms.contact:
        return terms
    caps = [max(factor * c, least) for c in terms.contact.capacity]
    caps = [n if c >= WHOLE_FRACTION * n else c for c, n in zip(caps, sizes)]
    return with_capacity(terms, caps, sizes)


#: :func:`with_headroom` gives an object its whole vertex count from this fraction of it on.
WHOLE_FRACTION = 0.875


def object_sizes(scene):
    """(O,) the vertex count of each object of a scene (the largest useful capacity)."""
    return tuple(int(o.n_vertices) for o in scene.objects)


# --------------------------------------------------------------------------- static tables


@dataclasses.dataclass(frozen=True, eq=False)
class _Tables:
    faces: np.ndarray        # (F, 3)
    near_faces: np.ndarray   # (V, W) faces touching a vertex or its one-ring (padded by repetition)
    face_adj: np.ndarray     # (F, 3) face across edge (f[e], f[e+1])
    ring: np.ndarray         # (V, K) ordered one-ring (padded by repeating the last)
    margin: tuple            # per pair: broad-phase inflation, m
    self_exclude: tuple      # per self object: (n, n) bool, rest distance below two longest edges
    n_max: int               # largest valence


def _tables(topo, cfg):
    faces = np.asarray(topo.faces, np.int64)
    n_v = topo.n_vertices
    vf = [[] for _ in range(n_v)]
    for fi, f in enumerate(faces):
        for v in f:
            vf[v].append(fi)
    ring = np.asarray(topo.ring, np.int64)
    near = []
    for v in range(n_v):
        s = set(vf[v])
        for u in set(ring[v][topo.ring_mask[v]].tolist()):
            s.update(vf[u])
        near.append(sorted(s))
    w = max(len(s) for s in near)
    near_faces = np.array([s + [s[0]] * (w - len(s)) for s in near], np.int32)
    edge_face = {}
    for fi, f in enumerate(faces):
        for e in range(3):
            edge_face[(int(f[e]), int(f[(e + 1) % 3]))] = fi
    face_adj = np.array([[edge_face[(int(f[(e + 1) % 3]), int(f[e]))] for e in range(3)] for f in faces], np.int32)
    longest = _longest_edges(topo)
    margin = _tables_margin(topo, cfg)
    excl = []
    for o in cfg.self_objects:
        a, b = topo.vertex_slices[o]
        x0 = topo.x0[a:b]
        d2 = np.sum((x0[:, None] - x0[None]) ** 2, axis=-1)
        excl.append(d2 < (2.0 * longest[o]) ** 2)
    return _Tables(faces=faces.astype(np.int32), near_faces=near_faces, face_adj=face_adj,
                   ring=ring.astype(np.int32), margin=margin, self_exclude=tuple(excl),
                   n_max=int(topo.ring_mask.sum(axis=1).max()))


# --------------------------------------------------------------------------- geometry on (x, y, z) tuples


def _sub(u, v):
    return tuple(a - b for a, b in zip(u, v))


def _add(u, v):
    return tuple(a + b for a, b in zip(u, v))


def _scale(u, s):
    return tuple(a * s for a in u)


def _dot(u, v):
    return u[0] * v[0] + u[1] * v[1] + u[2] * v[2]


def _cross(u, v):
    return (u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0])


def _gather(x, idx):
    """x (3, V), idx int array of any shape -> tuple of 3 arrays of idx's shape (indices are valid by
    construction: no clamping, which costs XLA's CPU gathers several times over)."""
    return tuple(x[c].at[idx].get(mode="promise_in_bounds") for c in range(3))


def _take(table, idx):
    """table[idx] for a static table and valid indices."""
    return jnp.asarray(table).at[idx].get(mode="promise_in_bounds")


def _pick(a, j):
    """a[i, j[i]] for a (Q, K) array and j (Q,)."""
    return jnp.take_along_axis(a, j[:, None], 1, mode="promise_in_bounds")[:, 0]


class _Closest(NamedTuple):
    d2: jax.Array       # squared unsigned distance
    inside: jax.Array   # the closest point is interior to the triangle
    plane: jax.Array    # signed plane distance (p - a).n
    e: jax.Array        # nearest edge (0: ab, 1: bc, 2: ca), used only where not ``inside``
    t: jax.Array        # parameter in [0, 1] of the closest point along edge e
    v: jax.Array        # barycentric weights of b and c of the projection on the plane
    w: jax.Array
    n: tuple            # unit outward plane normal
    r: tuple            # p minus the closest point of edge e


def _closest(p, a, b, c, tiny):
    """Closest point of triangles (a, b, c) to points p (all broadcastable tuples): a :class:`_Closest`.

    Interior: the plane projection (barycentric weights 1 - v - w, v, w); elsewhere the nearest
    point of the nearest edge. Unused fields cost nothing under ``jit`` (dead code).
    """
    ab, ac, ap = _sub(b, a), _sub(c, a), _sub(p, a)
    d00, d01, d11 = _dot(ab, ab), _dot(ab, ac), _dot(ac, ac)
    d20, d21 = _dot(ap, ab), _dot(ap, ac)
    den = jnp.maximum(d00 * d11 - d01 * d01, tiny)
    v = (d11 * d20 - d01 * d21) / den
    w = (d00 * d21 - d01 * d20) / den
    inside = (v >= 0) & (w >= 0) & (v + w <= 1)
    n = _scale(_cross(ab, ac), jax.lax.rsqrt(den))       # |ab x ac|² = d00 d11 - d01²
    plane = _dot(ap, n)
    best = None
    for e, (e0, e1) in enumerate(((a, b), (b, c), (c, a))):
        d = _sub(e1, e0)
        t = jnp.clip(_dot(_sub(p, e0), d) / jnp.maximum(_dot(d, d), tiny), 0.0, 1.0)
        r = _sub(p, _add(e0, _scale(d, t)))
        d2 = _dot(r, r)
        if best is None:
            best = (d2, jnp.zeros_like(d2, dtype=jnp.int32), t, r)
        else:
            closer = d2 < best[0]
            best = (jnp.where(closer, d2, best[0]), jnp.where(closer, e, best[1]), jnp.where(closer, t, best[2]),
                    tuple(jnp.where(closer, ri, bi) for ri, bi in zip(r, best[3])))
    d2 = jnp.where(inside, plane * plane, best[0])
    return _Closest(d2, inside, plane, best[1], best[2], v, w, n, best[3])


def closest_point_distance2(p, a, b, c):
    """Squared distance of points p to triangles (a, b, c), each a tuple of (x, y, z) arrays that
    broadcast against each other (the interior projection, else the nearest edge point)."""
    return _closest(p, a, b, c, jnp.finfo(p[0].dtype).tiny).d2


def _angle(y, x):
    """atan2(y, x) for y >= 0 (an angle in [0, pi]) by a minimax polynomial of atan on [0, 1]
    (error about 2e-6 rad in float32): plain arithmetic that XLA:CPU vectorises, where its atan2 runs
    element by element (about 15 ns each)."""
    ax = jnp.abs(x)
    hi, lo = jnp.maximum(y, ax), jnp.minimum(y, ax)
    t = lo / jnp.maximum(hi, jnp.finfo(y.dtype).tiny)
    t2 = t * t
    a = t * (0.99997726 + t2 * (-0.33262347 + t2 * (0.19354346 + t2 * (-0.11643287 + t2 * (0.05265332 + t2 * -0.01172120)))))
    a = jnp.where(y > ax, 0.5 * np.pi - a, a)
    return jnp.where(x < 0, np.pi - a, a)


def _face_distance2(ap, ab, ac, tiny):
    """Squared distance of points a + ap to triangles (a, a + ab, a + ac), for the search only: the
    interior test without divisions and each division used once (XLA:CPU materialises a division
    with several users as an operation of its own); the edge distances by |ap|² - (ap.d)²/|d|²,
    which loses relative precision for points very near an edge line (irrelevant to which face
    is nearest)."""
    d00, d01, d11 = _dot(ab, ab), _dot(ab, ac), _dot(ac, ac)
    d20, d21 = _dot(ap, ab), _dot(ap, ac)
    den = jnp.maximum(d00 * d11 - d01 * d01, tiny)
    nv, nw = d11 * d20 - d01 * d21, d00 * d21 - d01 * d20
    inside = (nv >= 0) & (nw >= 0) & (nv + nw <= den)
    cr = _cross(ab, ac)
    pl = _dot(ap, cr)
    best = None
    for o, e in ((ap, ab), (ap, ac), (_sub(ap, ab), _sub(ac, ab))):
        oo, oe, ee = _dot(o, o), _dot(o, e), jnp.maximum(_dot(e, e), tiny)
        de = jnp.where(oe <= 0, oo, jnp.where(oe >= ee, oo - 2 * oe + ee, oo - oe * oe / ee))
        best = de if best is None else jnp.minimum(best, de)
    return jnp.where(inside, pl * pl / den, jnp.maximum(best, 0.0))


def _argmin(d, axis):
    """First index of the minimum along ``axis`` (a min and an int min: XLA's CPU argmin, a
    variadic reduction, is slower)."""
    m = jnp.min(d, axis=axis, keepdims=True)
    iota = jax.lax.broadcasted_iota(jnp.int32, d.shape, axis % d.ndim)
    return jnp.min(jnp.where(d <= m, iota, d.shape[axis]), axis=axis).clip(0, d.shape[axis] - 1)


def _unit(u, tiny):
    return _scale(u, jax.lax.rsqrt(_dot(u, u) + tiny))


# --------------------------------------------------------------------------- energy


def make_contact_energy(topo, cfg):
    """Build ``energy(params, x) -> (U, overflow)`` on component-major x (3, V).

    U is the total contact energy (J); overflow a bool scalar, True when some pair had more
    candidate vertices than its capacity (the energy is then incomplete).
    """
    tab = _tables(topo, cfg)
    slices = topo.vertex_slices
    ring_next = np.roll(tab.ring, -1, axis=1)                    # next neighbour around the ring
    tiny_len = float(topo.length_eps)

    def energy(params, x):
        dtype = x.dtype
        params = _per_object_k(topo, params)
        tiny = jnp.asarray(tiny_len ** 2, dtype)        # a power of two (length_eps2), in the bucket
        total = jnp.zeros((), dtype)
        overflow = jnp.zeros((), bool)
        xs = jax.lax.stop_gradient(x)
        for (oa, ob), delta, margin in zip(cfg.pairs, cfg.thickness, tab.margin):
            (a0, a1), (b0, b1) = slices[oa], slices[ob]
            cap_a, cap_b = cfg.capacity[oa], cfg.capacity[ob]
            ia, ib, n_a, n_b, near_a, near_b = _pair_candidates(xs, (a0, a1), (b0, b1), cap_a, cap_b, margin)[:6]
            overflow = overflow | (n_a > cap_a) | (n_b > cap_b)
            va, vb = jnp.arange(cap_a) < n_a, jnp.arange(cap_b) < n_b
            kc = _energy_stiffness(params, cfg, tab, oa, ob, dtype)
            any_a, any_b = n_a > 0, n_b > 0
            delta = scene_value(delta, dtype)
            total = total + _directed_energy(x, a0 + ia, va & any_b, near_b, delta, kc, tab, ring_next, tiny)
            total = total + _directed_energy(x, b0 + ib, vb & any_a, near_a, delta, kc, tab, ring_next, tiny)
        for o, delta, excl in zip(cfg.self_objects, cfg.self_thickness, tab.self_exclude):
            total = total + _self_energy(params, x, o, scene_value(delta, dtype), excl, tiny, slices[o], cfg, tab)
        return total, overflow

    return energy


def _per_object_k(topo, params):
    """``params`` with one spring stiffness per object: the default contact stiffness follows each
    object's mean k (:func:`jaxplush.model.layout.object_stiffness`) when k is a per-edge field
    (``params`` itself otherwise)."""
    k = object_stiffness(topo, params.k_structural)
    return params if k is params.k_structural else params._replace(k_structural=k)


def _energy_stiffness(params, cfg, tab, a, b, dtype):
    """k_c of the object pair (a, b) in :func:`make_contact_energy`."""
    if cfg.stiffness is not None:
        return jnp.asarray(cfg.stiffness, dtype)
    k = params.k_structural
    return STIFFNESS_FACTOR * 2.0 * scene_value(tab.n_max, dtype) * jnp.minimum(k[a], k[b])


def _ramp_energy(s, delta, kc):
    """The penalty energy k_c / 2 phi(delta - s)² at signed distances s."""
    beta = SHARPNESS / delta
    phi = jax.nn.softplus(beta * (delta - s)) / beta
    return 0.5 * kc * phi * phi


def _vertex_pseudo_normal(x, v, ring, ring_next, tiny):
    """Angle-weighted normal of the surface at vertices v (any shape) from their one-rings."""
    c = _gather(x, v)
    d = _sub(_gather(x, jnp.asarray(ring)[v]), tuple(ci[..., None] for ci in c))
    dn = _gather(x, jnp.asarray(ring_next)[v])
    dn = _sub(dn, tuple(ci[..., None] for ci in c))
    cr = _cross(d, dn)
    sin = jnp.sqrt(_dot(cr, cr) + tiny)
    ang = jnp.arctan2(sin, _dot(d, dn))
    return tuple(jnp.sum(ang * ci / sin, axis=-1) for ci in cr)


def _signed_distance(x, p, f, tab, ring_next, tiny):
    """Signed distance (positive outside) of points p (tuple of (Q,)) to faces f (Q,)."""
    faces, face_adj = tab.faces, tab.face_adj
    tri = jnp.asarray(faces)[f]
    a, b, c = (_gather(x, tri[..., i]) for i in range(3))
    cl = _closest(p, a, b, c, tiny)
    inside, plane, e, t = cl.inside, cl.plane, cl.e, cl.t
    corners = (a, b, c)
    e0 = tuple(jnp.select([e == 0, e == 1], [a[i], b[i]], c[i]) for i in range(3))
    e1 = tuple(jnp.select([e == 0, e == 1], [b[i], c[i]], a[i]) for i in range(3))
    q = _add(e0, _scale(_sub(e1, e0), t))
    r = _sub(p, q)
    dist = jnp.sqrt(_dot(r, r) + tiny)
    # pseudo-normal of the closest feature (no gradient: only its sign is used)
    xs = jax.lax.stop_gradient(x)
    fa = jnp.asarray(face_adj)[f, e]
    ta = jnp.asarray(faces)[fa]
    ga, gb, gc = (_gather(xs, ta[..., i]) for i in range(3))
    sa, sb, sc = (jax.lax.stop_gradient(v_) for v_ in corners)
    n_edge = _add(_unit(_cross(_sub(sb, sa), _sub(sc, sa)), tiny),
                  _unit(_cross(_sub(gb, ga), _sub(gc, ga)), tiny))
    tri_s = jnp.asarray(faces)[f]
    vid = jnp.where(t <= 0.0, jnp.take_along_axis(tri_s, e[..., None], -1)[..., 0],
                    jnp.take_along_axis(tri_s, ((e + 1) % 3)[..., None], -1)[..., 0])
    n_vert = _vertex_pseudo_normal(xs, vid, tab.ring, ring_next, tiny)
    at_vertex = (t <= 0.0) | (t >= 1.0)
    n_feat = tuple(jnp.where(at_vertex, nv, ne) for nv, ne in zip(n_vert, n_edge))
    sign = jnp.where(_dot(jax.lax.stop_gradient(r), n_feat) >= 0, 1.0, -1.0)
    return jnp.where(inside, plane, sign * dist)


def _directed_energy(x, q_idx, q_valid, target, delta, kc, tab, ring_next, tiny):
    """Energy of query vertices q_idx against the faces near their nearest target vertices."""
    faces, near_faces = tab.faces, tab.near_faces
    xs = jax.lax.stop_gradient(x)
    ps = _gather(xs, q_idx)
    fset = jnp.asarray(near_faces)[target]                      # (Q, W)
    tri = jnp.asarray(faces)[fset]                              # (Q, W, 3)
    a, b, c = (_gather(xs, tri[..., i]) for i in range(3))
    d2, *_ = _closest(tuple(pi[:, None] for pi in ps), a, b, c, tiny)
    f = jnp.take_along_axis(fset, _argmin(d2, 1)[:, None], 1)[:, 0]
    s = _signed_distance(x, _gather(x, q_idx), f, tab, ring_next, tiny)
    return jnp.sum(jnp.where(q_valid, _ramp_energy(s, delta, kc), 0.0))


def _self_energy(params, x, o, delta, excl, tiny, vertex_slice, cfg, tab):
    """Self-collision energy of object o (its vertices ``vertex_slice``): each vertex against the
    nearest of its own faces outside the exclusion radius ``excl``."""
    faces, near_faces = tab.faces, tab.near_faces
    a0, a1 = vertex_slice
    n = a1 - a0
    xs = jax.lax.stop_gradient(x)
    xo = xs[:, a0:a1]
    d2 = sum((xo[c][:, None] - xo[c][None, :]) ** 2 for c in range(3))
    d2 = jnp.where(jnp.asarray(excl), jnp.inf, d2)
    target = a0 + _argmin(d2, 1)
    q_idx = np.arange(a0, a1)
    fset = jnp.asarray(near_faces)[target]                     # (n, W), faces of object o
    tri = jnp.asarray(faces)[fset]                             # (n, W, 3)
    # faces with a corner within the exclusion radius (at rest) of the query are its own
    own = jnp.any(jnp.asarray(excl)[np.arange(n)[:, None, None], tri - a0], axis=-1)
    ps = _gather(xs, q_idx)
    a, b, c = (_gather(xs, tri[..., i]) for i in range(3))
    d2f, *_ = _closest(tuple(pi[:, None] for pi in ps), a, b, c, tiny)
    d2f = jnp.where(own, jnp.inf, d2f)
    j = _argmin(d2f, 1)
    f = jnp.take_along_axis(fset, j[:, None], 1)[:, 0]
    valid = jnp.isfinite(jnp.take_along_axis(d2f, j[:, None], 1)[:, 0])
    p = _gather(x, q_idx)
    tri_f = jnp.asarray(faces)[f]
    fa, fb, fc = (_gather(x, tri_f[:, i]) for i in range(3))
    d2u, *_ = _closest(p, fa, fb, fc, tiny)
    s = jnp.sqrt(d2u + tiny)
    kc = (jnp.asarray(cfg.stiffness, x.dtype) if cfg.stiffness is not None
          else STIFFNESS_FACTOR * 2.0 * scene_value(tab.n_max, x.dtype) * params.k_structural[o])
    return jnp.sum(jnp.where(valid, _ramp_energy(s, delta, kc), 0.0))


def make_contact(topo, cfg, h=None):
    """Build ``(force, cache_ops)``: ``force(params, x, v=None, base=None, cache=None) -> f`` (3, V),
    the contact force -dU/dx, and the :class:`CacheOps` of its candidate cache (None without object
    pairs). On a capacity overflow the force is that of the candidates that fit (finite, inexact):
    the overflow is reported by the cache's flag (:class:`ContactCache`) or by
    :func:`make_overflow_check`, never by a NaN.

    The soft-soft part is assembled in closed form rather than by ``jax.grad`` of the energy (which
    adds a reverse pass through the gathers; see benchmarks/RESULTS.md): for a query vertex p whose
    closest point on its face is q = sum_i w_i x_i (barycentric weights w of the interior, edge or
    corner region), the signed distance s has ds/dp = n and ds/dx_i = -w_i n, n = (p - q) / |p - q|
    oriented outward (the plane normal on the interior) - the envelope theorem, since q minimises the
    distance over the triangle. The force on p is then -U'(s) n and on the corners +U'(s) w_i n: they
    sum to zero (sum w_i = 1) and have zero torque (p - q parallel to n), and they equal -dU/dx of
    :func:`make_contact_energy` (a test checks it). The expression is plain ``jax.numpy``, so
    rollouts stay differentiable through it (its derivative is the energy's Hessian where the
    closest feature does not change). Self-collision, an option for small meshes, keeps ``jax.grad``.

    Friction (``cfg.friction`` = mu > 0): with v_t the tangential part of the relative velocity of
    p and q, a force of magnitude min(mu F_n, m_eff |v_t| / (2 h)) opposes it (F_n the penalty
    force, m_eff = 1 / (1/m_p + sum w_i² / m_i) the effective mass of the pair, h the integrator's
    step): Coulomb sliding above the friction cone and, below it, a clamp that at most halves the
    sliding per step (each contact is seen from both objects), so it never reverses the motion and
    is stable at any h. It is applied equal and opposite (p, and the face corners by w_i), so
    momentum is conserved, and it only dissipates.

    Narrow phase: the closest face is searched among the faces around the query's nearest vertex
    v (its ordered one-ring, gathered once per query), which also give, without further gathers, the
    pseudo-normals of v and of the spokes (v, ring_k) - the only vertex and edge features that can
    be closest when v is the nearest vertex on a fair mesh (a point closest to a rim edge of v's
    ring is nearer to that edge's ends than to v). A rim edge falls back to its face's normal. All
    pairs and both directions run as one batch of queries.
    """
    tab = _tables(topo, cfg)
    ring_t, valence = _ring_slot_tables(topo, tab)
    tiny_len = float(topo.length_eps)
    n_v = topo.n_vertices
    self_energy = (make_contact_energy(topo, dataclasses.replace(cfg, pairs=(), thickness=()))
                   if cfg.self_objects else None)
    friction = float(cfg.friction)
    if friction > 0 and h is None:
        raise ValueError("contact friction needs the integrator step h")

    skin = skin_distance(topo, cfg) if cfg.pairs else 0.0

    near_limit = _near_limits(topo, cfg)

    def search(xs):
        return _search(xs, topo, cfg, tab.margin, skin, near_limit)

    def add_block(params, x, v, f, cache, i):
        """f (3, V) plus the force of the queries in block i of the cache's list (slots
        i B .. (i + 1) B, B = QUERY_BLOCK)."""
        dtype = x.dtype
        mass = vertex_mass(topo, params) if friction > 0 else None
        tiny = jnp.asarray(tiny_len ** 2, dtype)        # a power of two (length_eps2), in the bucket
        take = lambda a: jax.lax.dynamic_slice_in_dim(a, i * QUERY_BLOCK, QUERY_BLOCK)   # noqa: E731
        pair = take(cache.pair)
        kc = _take(_pair_stiffnesses(_per_object_k(topo, params), cfg, tab, dtype), pair)
        delta = _take(jnp.asarray(cfg.thickness, dtype), pair)
        idx, rows = _narrow(x, v, mass, take(cache.q_idx), take(cache.valid), take(cache.target),
                            delta, kc, tiny, ring_t, valence, friction, h)
        return jnp.stack([fc.at[idx].add(rc, mode="promise_in_bounds") for fc, rc in zip(f, rows)])

    # jit: inlined under an outer jit; outside one (e.g. an eager init_fn) it compiles once
    # instead of dispatching hundreds of small operations one by one.
    @jax.jit
    def force(params, x, v=None, base=None, cache=None):
        """Contact force (3, V), added to ``base`` (3, V) when given (saves a buffer). With a
        ``cache`` (:class:`ContactCache`) its candidate lists and nearest vertices are used
        instead of searching."""
        dtype = x.dtype
        if friction > 0 and v is None:
            raise ValueError("contact friction needs the velocities")
        f = jnp.zeros((3, n_v), dtype) if base is None else base
        if cfg.pairs:
            if cache is None:
                cache = search(jax.lax.stop_gradient(x))
            # on an overflow the lists hold the candidates that fit: the force stays finite (and
            # inexact); the overflow is reported by the cache's flag, not here
            f = _blockwise(cache.valid, f, lambda f, i: add_block(params, x, v, f, cache, i))
        if self_energy is not None:
            f = f - jax.grad(lambda y: self_energy(params, y)[0])(x)
        return f

    def force_lanes(params, x, v, cache):
        """The pair force of B independent points at once (the batched engine's layout): params
        with objects on axis 0 and points on axis 1, x and v (B, 3, V) (v None without friction),
        ``cache`` a batched :class:`ContactCache`; returns (B, 3, V). A block of queries runs
        where any point has a valid query in it (one ``lax.cond`` for the whole batch: under
        ``vmap`` a per-point cond would run both branches)."""
        f = jnp.zeros(x.shape, x.dtype)

        def add(f, i):
            one = lambda p, xl, vl, fl, c: add_block(p, xl, vl, fl, c, i)         # noqa: E731
            return jax.vmap(one, in_axes=(1, 0, None if v is None else 0, 0, 0))(params, x, v, f, cache)
        if cfg.pairs:
            f = _blockwise(cache.valid, f, add)
        if self_energy is not None:
            f = f - jax.vmap(lambda p, y: jax.grad(lambda z: self_energy(p, z)[0])(y), in_axes=(1, 0))(params, x)
        return f

    force.lanes = force_lanes

    ops = _cache_ops(topo, cfg, tab.ring, search) if cfg.pairs else None
    return force, ops


def _ring_slot_tables(topo, tab):
    """(ring_t, valence) of the narrow phase (:func:`_narrow`). ring_t: the neighbour-major ring
    table (K + 1, V): row j holds every vertex's j-th ring neighbour and row K repeats row 0, so
    "the next neighbour" of slot j is row j + 1 (as in model._ring_force_fn); valence (V,) int32."""
    ring = tab.ring
    valence = np.asarray(topo.ring_mask.sum(axis=1), np.int32)
    # padded rings repeat their last neighbour: real slots are 0 .. valence-2 and K-1 (the wrap)
    assert np.all(ring[:, -1] == ring[np.arange(len(ring)), valence - 1])
    ring_t = np.ascontiguousarray(np.concatenate([ring.T, ring.T[:1]], axis=0))
    return ring_t, valence


def _query_layout(cfg):
    """(Q,) int32 the pair of each query slot of the broad phase's lists, laid out as [A of pair 0,
    B of pair 0, A of pair 1, ...] (:func:`_search` compacts them)."""
    if not cfg.pairs:
        return np.zeros(0, np.int32)
    return np.concatenate([np.full(cfg.capacity[o], i, np.int32) for i, (oa, ob) in enumerate(cfg.pairs)
                           for o in (oa, ob)])


#: Queries per block of the narrow phase (:func:`_blockwise`).
QUERY_BLOCK = 64


def _blockwise(valid, f, add):
    """f (any pytree: a force, the queries' targets) with ``add(f, i)`` applied for each block i of
    QUERY_BLOCK query slots that holds a valid query. A search compacts the valid queries of all
    pairs to the front of the list (:func:`_search`), so the blocks run are the first ceil(n / QUERY_BLOCK) for n valid queries
    (the most of any point when ``valid`` is batched, (B, Q)): the narrow phase costs what the
    contact needs, not the capacities. A loop of static length over ``lax.cond`` (one compiled
    block; differentiable in both modes)."""
    n_blocks = valid.shape[-1] // QUERY_BLOCK
    count = jnp.max(jnp.sum(valid, axis=-1))

    def body(i, f):
        return jax.lax.cond(i * QUERY_BLOCK < count, lambda f: add(f, i), lambda f: f, f)
    return jax.lax.fori_loop(0, n_blocks, body, f)


def _pair_stiffnesses(params, cfg, tab, dtype):
    """(P,) k_c of every object pair of :func:`make_contact`."""
    if cfg.stiffness is not None:
        return jnp.full((len(cfg.pairs),), cfg.stiffness, dtype)
    k = params.k_structural
    return STIFFNESS_FACTOR * 2.0 * scene_value(tab.n_max, dtype) * jnp.stack([jnp.minimum(k[a], k[b]) for a, b in cfg.pairs])


def _narrow(x, v, mass, q_idx, q_valid, target, delta, kc, tiny, ring_t, valence, friction, h):
    """(indices (4Q,), force rows 3 x (4Q,)) of query vertices q_idx against the faces around
    their nearest vertices ``target``.

    The search over v's ring works on slot-major (K, Q) arrays, so each operation is one
    vectorised loop over all slots and queries; values are gathered and picked several at a
    time (each XLA operation adds a fixed dispatch cost in the step's loop)."""
    P, A, rk, val, d0, d1, k = _ring_search(x, q_idx, target, ring_t, valence, tiny)
    corners, normals = _ring_normals(rk, val, d0, d1, k, tiny)
    n, w, mag, vec = _penalty(x, P, A, corners, normals, q_valid, delta, kc, tiny)
    idx = jnp.concatenate([q_idx, target, corners[0], corners[1]])        # (4Q,)
    if friction > 0:
        vec = _friction(v, mass, idx, n, w, mag, vec, friction, h, tiny)
    return idx, tuple(jnp.concatenate([vi] + [-wi * vi for wi in w]) for vi in vec)


def _ring_search(x, q_idx, target, ring_t, valence, tiny):
    """The closest of the K faces around each query's nearest vertex v = ``target`` (no gradient):
    (P, A: the query's and v's positions, rk (K + 1, Q) v's ring, val (Q,) v's valence, d0, d1:
    the spokes j and j + 1 (K, Q), k (Q,) the closest face's slot)."""
    n_k = ring_t.shape[0] - 1
    rk = jnp.asarray(ring_t).at[:, target].get(mode="promise_in_bounds")    # (K + 1, Q)
    val = _take(valence, target)                                          # (Q,)
    pa = x.at[:, jnp.stack([q_idx, target])].get(mode="promise_in_bounds")   # (3, 2, Q)
    P, A = tuple(pa[c, 0] for c in range(3)), tuple(pa[c, 1] for c in range(3))
    # the search (no gradient)
    xs = jax.lax.stop_gradient(x)
    g = xs.at[:, rk].get(mode="promise_in_bounds")                        # (3, K + 1, Q)
    As = tuple(jax.lax.stop_gradient(ai)[None] for ai in A)
    ps = tuple(jax.lax.stop_gradient(pi)[None] for pi in P)
    d = tuple(g[c] - As[c] for c in range(3))                            # (K + 1, Q) spokes
    d0, d1 = tuple(dc[:n_k] for dc in d), tuple(dc[1:] for dc in d)       # spokes j and j + 1
    slot = jnp.arange(n_k)[:, None]
    real = (slot < val[None] - 1) | (slot == n_k - 1)                     # padded slots are degenerate
    # the distances to the K faces around v, ending in a square root: XLA:CPU does not copy an
    # expensive operation into each of its consumers, so the (K, Q) table is computed once, in
    # one vectorised loop, and the minimum over its rows is a short elementwise chain (a
    # reduction over the leading axis would be a scalar loop)
    dist = jnp.sqrt(jnp.where(real, _face_distance2(_sub(ps, As), d0, d1, tiny), jnp.inf))
    best, k = dist[0], jnp.zeros(dist.shape[1:], jnp.int32)              # (Q,) the closest face
    for j in range(1, n_k):
        closer = dist[j] < best
        best, k = jnp.where(closer, dist[j], best), jnp.where(closer, j, k)
    return P, A, rk, val, d0, d1, k


def _ring_normals(rk, val, d0, d1, k, tiny):
    """The corners (2, Q) (ring_k, ring_k+1) of the closest face k of :func:`_ring_search` and the
    pseudo-normals (no gradient) of its features: (n_vertex, n_spoke0, n_spoke2, n_face)."""
    n_k = rk.shape[0] - 1
    cr = _cross(d0, d1)
    sin = jnp.sqrt(_dot(cr, cr) + tiny)
    ang = _angle(sin, _dot(d0, d1))
    inv = 1.0 / sin
    unit = tuple(ci * inv for ci in cr)                                   # (K, Q); degenerate slots ~0
    n_vertex = _sum_rows(tuple(ang * u for u in unit))                   # angle-weighted normal of v
    # the unit normals of face k and of the real slots before and after it (the faces across
    # its spokes), and its corners, in one pick: slot k_prev is k - 1 but K - 1 for k = 0 and
    # valence - 2 for the wrap slot K - 1; k_next is k + 1 but 0 for K - 1 and K - 1 for
    # valence - 2
    kp = jnp.where(k == 0, n_k - 1, jnp.where(k == n_k - 1, val - 2, k - 1))
    kn = jnp.where(k == n_k - 1, 0, jnp.where(k == val - 2, n_k - 1, k + 1))
    picked = jnp.take_along_axis(jnp.stack(unit), jnp.stack([k, kp, kn])[None], 1,
                                 mode="promise_in_bounds")               # (3, 3, Q)
    n_face, n_prev, n_next = (tuple(picked[c, i] for c in range(3)) for i in range(3))
    corners = jnp.take_along_axis(rk, jnp.stack([k, k + 1]), 0, mode="promise_in_bounds")
    n_spoke0 = _add(n_face, n_prev)                                      # edge (v, ring_k)
    n_spoke2 = _add(n_face, n_next)                                      # edge (ring_k+1, v)
    return corners, (n_vertex, n_spoke0, n_spoke2, n_face)


def _penalty(x, P, A, corners, normals, q_valid, delta, kc, tiny):
    """The penalty force of queries P against their faces (A, corners): (n: the unit outward
    normal, w: the closest point's barycentric weights, mag: -dU/ds, vec: the force on P)."""
    n_vertex, n_spoke0, n_spoke2, n_face = normals
    # differentiable part: closest point on the face (v, i1, i2) and its barycentric weights
    bc = x.at[:, corners].get(mode="promise_in_bounds")                   # (3, 2, Q)
    p, a = P, A
    b, c = tuple(bc[ci, 0] for ci in range(3)), tuple(bc[ci, 1] for ci in range(3))
    cl = _closest(p, a, b, c, tiny)
    inside, plane, n_plane, e, t, r = cl.inside, cl.plane, cl.n, cl.e, cl.t, cl.r
    bv, bw, dist2 = cl.v, cl.w, cl.d2                       # dist2 is the edge distance where not inside
    dist = jnp.sqrt(dist2 + tiny)
    # sign of the edge and corner regions from the closest feature's pseudo-normal
    at_v = ((e == 0) & (t <= 0.0)) | ((e == 2) & (t >= 1.0))
    n_feat = tuple(jnp.where(at_v, nv, jnp.where((e == 0) & (t < 1.0), s0, jnp.where((e == 2) & (t > 0.0), s2, nf)))
                   for nv, s0, s2, nf in zip(n_vertex, n_spoke0, n_spoke2, n_face))
    sign = jnp.where(_dot(jax.lax.stop_gradient(r), n_feat) >= 0, 1.0, -1.0)
    s = jnp.where(inside, plane, sign * dist)
    num = tuple(jnp.where(inside, npl, sign * ri) for npl, ri in zip(n_plane, r))
    den_n = jnp.where(inside, 1.0, dist)
    n = tuple(ni / den_n for ni in num)                                  # unit outward normal
    one_t = 1.0 - t
    we = (jnp.where(e == 0, one_t, jnp.where(e == 2, t, 0.0)),
          jnp.where(e == 1, one_t, jnp.where(e == 0, t, 0.0)),
          jnp.where(e == 2, one_t, jnp.where(e == 1, t, 0.0)))
    w = (jnp.where(inside, 1.0 - bv - bw, we[0]), jnp.where(inside, bv, we[1]), jnp.where(inside, bw, we[2]))
    beta = SHARPNESS / delta
    z = beta * (delta - s)
    # -dU/ds = k_c phi(delta - s) sigmoid(beta (delta - s)), phi = softplus(z) / beta
    mag = jnp.where(q_valid, kc * jax.nn.softplus(z) / beta * jax.nn.sigmoid(z), 0.0)
    # force on p, written to end in a division: XLA:CPU then computes it once instead of
    # re-deriving it for every row of the scattered (3, 4Q) table
    vec = tuple((mag * ni) / den_n for ni in num)
    return n, w, mag, vec


def _friction(v, mass, idx, n, w, mag, vec, friction, h, tiny):
    """``vec`` (the force on the queries) less the friction force of :func:`make_contact`; idx
    (4Q,): the queries and their faces' corners."""
    vv = v.at[:, idx].get(mode="promise_in_bounds").reshape(3, 4, -1)
    vq, va, vb, vc = (tuple(vv[ci, i] for ci in range(3)) for i in range(4))
    rel = _sub(vq, _add(_add(_scale(va, w[0]), _scale(vb, w[1])), _scale(vc, w[2])))
    vt = _sub(rel, _scale(n, _dot(rel, n)))
    speed = jnp.sqrt(_dot(vt, vt) + tiny)
    mp, ma, mb, mc = _take(mass, idx).reshape(4, -1)
    m_eff = 1.0 / (1.0 / mp + w[0] ** 2 / ma + w[1] ** 2 / mb + w[2] ** 2 / mc)
    ft = jnp.minimum(friction * mag, FRICTION_CLAMP * m_eff * speed / h) / speed
    return _sub(vec, _scale(vt, ft))


def _search(xs, topo, cfg, margins, skin, _near_limits):
    """The candidate queries of every pair and direction at positions xs (no gradient): a
    :class:`ContactCache`. The broad phase's candidates (:func:`_pair_candidates`) are kept as
    queries where their nearest vertex of the other object lies within the pair's
    :func:`_near_limits`, and the queries of all pairs are compacted to the front of one list of
    :func:`_list_length` slots (:func:`_blockwise` runs only the blocks that hold them). The
    vertices in some pair's broad phase are the cache's ``watch`` set (:meth:`CacheOps.stale`)."""
    slices = topo.vertex_slices
    qs, valids, targets, counts = [], [], [], []
    watch = [jnp.zeros(b - a, bool) for a, b in slices]
    for (oa, ob), margin, near in zip(cfg.pairs, margins, _near_limits):
        (a0, a1), (b0, b1) = slices[oa], slices[ob]
        cap_a, cap_b = cfg.capacity[oa], cfg.capacity[ob]
        ia, ib, n_a, n_b, near_a, near_b, in_a, in_b = _pair_candidates(xs, (a0, a1), (b0, b1), cap_a, cap_b, margin)
        counts.append((n_a, n_b))
        watch[oa] = watch[oa] | in_a
        watch[ob] = watch[ob] | in_b
        for q, t, n, cap, other in ((a0 + ia, near_b, n_a, cap_a, n_b), (b0 + ib, near_a, n_b, cap_b, n_a)):
            d2 = sum((pc - tc) ** 2 for pc, tc in zip(_gather(xs, q), _gather(xs, t)))
            qs.append(q)
            targets.append(t)
            near2 = scene_value(near * near, xs.dtype)
            valids.append((jnp.arange(cap) < n) & (other > 0) & (d2 <= near2))
    pair_of_query = _query_layout(cfg)
    valid = jnp.concatenate(valids)
    length = _list_length(cfg)
    order = jnp.nonzero(valid, size=length, fill_value=0)[0]
    return ContactCache(_take(jnp.concatenate(qs).astype(jnp.int32), order),
                        jnp.arange(length) < jnp.sum(valid),
                        _take(jnp.concatenate(targets).astype(jnp.int32), order), xs,
                        _overflow_flags(cfg, topo.n_objects, counts),
                        scene_value((0.5 * skin) ** 2, xs.dtype),
                        _take(jnp.asarray(pair_of_query), order),
                        jnp.concatenate(watch))


def _list_length(cfg):
    """Slots of the query list: every pair's capacities in both directions, rounded up to whole
    blocks of QUERY_BLOCK."""
    n = sum(cfg.capacity[a] + cfg.capacity[b] for a, b in cfg.pairs)
    return -(-n // QUERY_BLOCK) * QUERY_BLOCK


def _near_limits(topo, cfg):
    """Per pair: how near its nearest vertex of the other object a candidate must be at the search
    to be a query, 2 delta + the longest rest edge + the skin s. A point within 2 delta of a face
    (beyond that the force is below e^-20 of its scale) is within an edge of one of its corners,
    and until the next search the point and the corner each move at most s/2."""
    longest = _longest_edges(topo)
    skin = skin_distance(topo, cfg)
    return tuple(2.0 * d + max(longest[a], longest[b]) + skin for (a, b), d in zip(cfg.pairs, cfg.thickness))


def two_ring_width(ring):
    """Slots of the walk's table (:func:`two_rings`) for one-rings ``ring`` (V, K): the largest
    two-ring (the vertex itself included), and at least 1 + 3 K (19 for K = 6, the two-ring of a
    vertex of valence 6 among vertices of valence 6), so that meshes of valence at most 6 share
    one width whatever their size (:class:`jaxplush.stepping.compiled.Bucket`)."""
    return int(max(two_rings(ring, 0).shape[1], 1 + 3 * np.shape(ring)[1]))


def two_rings(ring, width=None):
    """(V, W) int32: each vertex, then the other vertices of its one- and two-ring (ascending),
    padded by repeating the vertex (``width`` None: :func:`two_ring_width`; 0: as wide as the
    largest). ``ring`` (V, K): one-rings padded by repeating a neighbour."""
    ring = np.asarray(ring, np.int64)
    n_v, k = ring.shape
    me = np.arange(n_v)[:, None]
    cand = np.concatenate([ring, ring[ring].reshape(n_v, k * k)], axis=1)
    cand = np.sort(np.where(cand == me, n_v, cand), axis=1)              # the vertex itself last
    dup = np.concatenate([np.zeros((n_v, 1), bool), cand[:, 1:] == cand[:, :-1]], axis=1)
    cand = np.sort(np.where(dup, n_v, cand), axis=1)                      # each other vertex once
    count = (cand < n_v).sum(axis=1)
    w = 1 + int(count.max()) if width in (None, 0) else int(width)
    if width is None:
        w = max(w, 1 + 3 * k)
    cand = np.where(cand[:, :w - 1] < n_v, cand[:, :w - 1], me)
    if cand.shape[1] < w - 1:
        cand = np.concatenate([cand, np.broadcast_to(me, (n_v, w - 1 - cand.shape[1]))], axis=1)
    return np.ascontiguousarray(np.concatenate([me, cand], axis=1).astype(np.int32))


def _cache_ops(topo, cfg, ring, search):
    """The :class:`CacheOps` of :func:`make_contact`'s candidate cache (ring: the (V, K) one-rings;
    ``search(xs)``: a fresh :class:`ContactCache`)."""
    # the walk's table: each vertex and its two-ring. A walk over the one-ring alone can stop at a
    # vertex nearer than all its neighbours while the nearest vertex lies two rings away (a query
    # almost equidistant from two vertices of a coarse mesh), and the force then reads the faces
    # around the wrong vertex until the next rebuild (benchmarks/contact_lists_check.py; the
    # carried lists then departed from a fresh search by 5% of the contact force for 3 steps)
    ring_ext = two_rings(ring)
    slices = topo.vertex_slices
    skin = skin_distance(topo, cfg)
    # the region a vertex outside the watch set must not enter: where the force can act and the
    # one-ring search is exact (2 delta + 1.5 edges), plus a skin for good measure
    entry = tuple(m - skin for m in _tables_margin(topo, cfg))

    def walk_block(target, q_idx, xs, i):
        """``target`` with the queries of block i (slots i B .. (i + 1) B, B = QUERY_BLOCK) moved
        to the nearest of their target and its two-ring."""
        t = jax.lax.dynamic_slice_in_dim(target, i * QUERY_BLOCK, QUERY_BLOCK)
        q = jax.lax.dynamic_slice_in_dim(q_idx, i * QUERY_BLOCK, QUERY_BLOCK)
        rk = _take(ring_ext, t)                                              # (B, W)
        p, n = _gather(xs, q), _gather(xs, rk)
        d2 = sum((nc - pc[:, None]) ** 2 for nc, pc in zip(n, p))
        return jax.lax.dynamic_update_slice_in_dim(target, _pick(rk, _packed_argmin(d2, 1)), i * QUERY_BLOCK, 0)

    def walk(cache, xs):
        """Each query's target moved to the nearest of the target and its two-ring (one step of a
        greedy descent of the vertex distance: the nearest vertex follows a sliding contact), in
        blocks of QUERY_BLOCK, only those that hold queries (:func:`_blockwise`)."""
        return cache._replace(target=_blockwise(cache.valid, cache.target,
                                                lambda t, i: walk_block(t, cache.q_idx, xs, i)))

    def walk_lanes(cache, xs):
        """:func:`walk` of B points at once (a batched cache, xs (B, 3, V)): a block runs where
        any point has a query in it (one ``lax.cond`` for the batch, as the force's)."""
        def add(t, i):
            return jax.vmap(walk_block, in_axes=(0, 0, 0, None))(t, cache.q_idx, xs, i)
        return cache._replace(target=_blockwise(cache.valid, cache.target, add))

    def rebuild(cache, xs):
        """A fresh search, its overflow flags OR-ed with the cache's (they stay set)."""
        new = search(xs)
        return new._replace(overflow=new.overflow | cache.overflow)

    def stale(cache, x):
        """bool: the lists may no longer be exact. Either a vertex of the watch set (those in some
        pair's broad phase at the build) has moved more than half the skin since then, or a
        vertex outside it has come within :func:`_tables_margin` less a skin of the other
        object's box and sphere as they are now. While neither holds, any two vertices of a pair
        now within 2 delta + an edge of each other were both watched and had each moved at most
        s/2, so they were within 2 delta + an edge + s at the build: candidates of each other,
        and the query's nearest vertex within the near limit (:func:`_near_limits`). Vertices
        far from the other object move freely: a fluttering membrane away from the contact does
        not rebuild the lists."""
        xs = jax.lax.stop_gradient(x)
        moved = jnp.max(jnp.where(cache.watch, jnp.sum((xs - cache.x_ref) ** 2, axis=0), 0.0)) > cache.limit2
        entered = jnp.zeros((), bool)
        for (oa, ob), margin in zip(cfg.pairs, entry):
            (a0, a1), (b0, b1) = slices[oa], slices[ob]
            in_a, in_b = _broad_phase(xs[:, a0:a1], xs[:, b0:b1], margin)
            entered = entered | jnp.any(in_a & ~cache.watch[a0:a1]) | jnp.any(in_b & ~cache.watch[b0:b1])
        return moved | entered

    def update(cache, x):
        """The cache for positions x: rebuilt (:func:`search`) once it is stale (:func:`stale`),
        else the targets walked. The overflow flags are sticky: once set they stay set, so an
        overflow between saved frames is not lost."""
        xs = jax.lax.stop_gradient(x)
        return jax.lax.cond(stale(cache, xs), lambda: rebuild(cache, xs), lambda: walk(cache, xs))

    return CacheOps(init=lambda x: search(jax.lax.stop_gradient(x)), update=update, stale=stale,
                    walk=lambda cache, x: walk(cache, jax.lax.stop_gradient(x)),
                    walk_lanes=lambda cache, x: walk_lanes(cache, jax.lax.stop_gradient(x)))


class ContactCache(NamedTuple):
    """Soft-soft candidate lists carried between steps (:func:`make_contact`); Q query slots
    (:func:`_list_length`), the valid queries of every pair first (:func:`_search`).

    Attributes:
      q_idx: (Q,) int32 global index of each query vertex (padded slots repeat a valid index).
      valid: (Q,) bool, the slot holds a query: a broad-phase candidate near the other object (a
        prefix of the list).
      target: (Q,) int32 global index of the query's nearest vertex of the other object.
      x_ref: (3, V) positions at the last build.
      overflow: (O,) bool per object: at some build since the cache was made (:meth:`CacheOps.init`),
        the object had more candidates in some pair than its capacity. Sticky: ``update`` never
        clears it. The force then used the candidates that fit (inexact, finite); rollouts turn
        the flag into the object's ``diagnostics.CONTACT_OVERFLOW`` health code.
      limit2: () the squared displacement of a watched vertex since the build past which the
        lists are rebuilt: (s/2)², s the skin.
      pair: (Q,) int32 the object pair of each query (an index into ``ContactConfig.pairs``).
      watch: (V,) bool the vertices in some pair's broad phase at the build (their motion is
        watched, :meth:`CacheOps.stale`; every other vertex only may not come near the other object).
    """

    q_idx: jax.Array
    valid: jax.Array
    target: jax.Array
    x_ref: jax.Array
    overflow: jax.Array
    limit2: jax.Array
    pair: jax.Array
    watch: jax.Array


class CacheOps(NamedTuple):
    """``init(x) -> ContactCache`` (a full search) and ``update(cache, x) -> ContactCache`` (rebuild
    once stale, else walk the nearest vertices); x internal (3, V). ``update``'s parts, for callers
    that decide the rebuild for many caches at once (the batched engine,
    :mod:`jaxplush.stepping.batched`): ``stale(cache, x) -> bool`` (a rebuild is due; under
    ``jax.vmap``), ``walk(cache, x) -> ContactCache`` (the targets walked, no rebuild) and
    ``walk_lanes(cache, xs) -> ContactCache``, the walk of a batched cache (xs (B, 3, V)) that
    runs only the blocks of queries some point holds."""

    init: object
    update: object
    stale: object = None
    walk: object = None
    walk_lanes: object = None


def _overflow_flags(cfg, n_objects, counts):
    """(O,) bool: the objects whose candidate count exceeds their capacity in some pair, from
    ``counts`` [(n_A, n_B), ...] aligned with ``cfg.pairs``."""
    flags = [jnp.zeros((), bool)] * n_objects
    for (oa, ob), (n_a, n_b) in zip(cfg.pairs, counts):
        flags[oa] = flags[oa] | (n_a > cfg.capacity[oa])
        flags[ob] = flags[ob] | (n_b > cfg.capacity[ob])
    return jnp.stack(flags)


def make_overflow_check(topo, cfg):
    """``overflow(x) -> (O,) bool`` at internal positions x (3, V): the objects whose candidates
    in some pair would overflow their capacity in a fresh search at x (the broad phase's counts
    only, O(V) per pair: no distance table), or None when ``cfg`` has no object pairs.

    For the paths that carry no :class:`ContactCache`: ``Simulator.status_fn``, rollouts built with
    ``coherent_contact=False`` and :func:`jaxplush.fitting.judge.identifiability.frames_at_steps`."""
    if not cfg or not cfg.pairs:
        return None
    slices = topo.vertex_slices
    margins = _tables_margin(topo, cfg)

    def overflow(x):
        xs = jax.lax.stop_gradient(x)
        counts = []
        for (oa, ob), margin in zip(cfg.pairs, margins):
            (a0, a1), (b0, b1) = slices[oa], slices[ob]
            in_a, in_b = _broad_phase(xs[:, a0:a1], xs[:, b0:b1], margin)
            counts.append((jnp.sum(in_a), jnp.sum(in_b)))
        return _overflow_flags(cfg, topo.n_objects, counts)

    return overflow


def make_contact_force(topo, cfg, h=None):
    """:func:`make_contact`'s force alone: ``force(params, x, v=None, base=None, cache=None)``."""
    return make_contact(topo, cfg, h)[0]


def _broad_phase(xa, xb, margin):
    """(in_a, in_b) bool masks of the vertices of each object near the other: inside its bounding
    box and its bounding sphere (about the vertex mean), both inflated by ``margin``. Works on
    (3, n) jax arrays and on numpy (for the checks outside jit)."""
    mod = jnp if isinstance(xa, jax.Array) else np
    if mod is jnp:
        margin = scene_value(margin, xa.dtype)

    def near(p, q):
        lo, hi = q.min(axis=1, keepdims=True), q.max(axis=1, keepdims=True)
        centre = q.mean(axis=1, keepdims=True)
        radius = mod.sqrt(mod.max(mod.sum((q - centre) ** 2, axis=0)))
        in_box = mod.all((p >= lo - margin) & (p <= hi + margin), axis=0)
        return in_box & (mod.sum((p - centre) ** 2, axis=0) <= (radius + margin) ** 2)

    return near(xa, xb), near(xb, xa)


def _pair_candidates(xs, sa, sb, cap_a, cap_b, margin):
    """Broad phase and nearest-vertex search of one object pair (no gradient).

    Returns (ia, ib, n_a, n_b, near_a, near_b, in_a, in_b): candidate indices local to each object
    (padded), their counts, for each candidate the global index of the nearest candidate of the
    other, and the broad phase's masks (:func:`_broad_phase`).
    """
    (a0, a1), (b0, b1) = sa, sb
    xa, xb = xs[:, a0:a1], xs[:, b0:b1]
    in_a, in_b = _broad_phase(xa, xb, margin)
    n_a, n_b = jnp.sum(in_a), jnp.sum(in_b)
    ia = jnp.nonzero(in_a, size=cap_a, fill_value=0)[0]
    ib = jnp.nonzero(in_b, size=cap_b, fill_value=0)[0]

    def nearest():
        return _nearest_tiled(_gather(xa, ia), _gather(xb, ib), n_a, n_b)

    # the tables only where both objects have candidates (else no query is valid)
    ja, jb = jax.lax.cond((n_a > 0) & (n_b > 0), nearest,
                          lambda: (jnp.zeros(cap_b, jnp.int32), jnp.zeros(cap_a, jnp.int32)))
    return ia, ib, n_a, n_b, a0 + _take(ia, ja), b0 + _take(ib, jb), in_a, in_b


#: Rows and columns of one tile of a pair's nearest-vertex tables (:func:`_nearest_tiled`).
NEAR_TILE = 64


def _nearest_tiled(pa, pb, n_a, n_b):
    """(ja (cap_b,), jb (cap_a,)) int32: for each of the first n_b points of pb (3, cap_b) the
    index of its nearest among the first n_a of pa (3, cap_a), and the other way round (entries
    past the counts are arbitrary). The squared-distance tables are built in tiles of
    NEAR_TILE x NEAR_TILE, only those within both counts (a ``lax.cond`` per tile): the search
    costs what the candidates need, n_a x n_b, not the capacities' cap_a x cap_b (a grown
    capacity of 642 searched 10 times slower than one of 256 for the same 200 candidates). Each
    tile is built once per direction and reduced along its rows (XLA's CPU column reductions
    are slow); the running minimum is kept as packed keys (:func:`_packed_argmin`)."""
    t = NEAR_TILE
    cap_a, cap_b = pa[0].shape[0], pb[0].shape[0]
    n_a, n_b = jnp.minimum(n_a, cap_a), jnp.minimum(n_b, cap_b)     # an overflow fills the lists, no more
    ta, tb = -(-cap_a // t), -(-cap_b // t)
    pad = lambda p, m: tuple(jnp.pad(c, (0, m * t - c.shape[0])) for c in p)   # noqa: E731
    pa, pb = pad(pa, ta), pad(pb, tb)
    itype = jnp.int32 if pa[0].dtype == jnp.float32 else jnp.int64
    bits_a, bits_b = max(1, int(ta * t - 1).bit_length()), max(1, int(tb * t - 1).bit_length())
    iota = jax.lax.broadcasted_iota(itype, (t, t), 1)
    rows = jnp.arange(t)

    def keys(p, q, i, j, n_p, n_q, bits):
        """(t,) packed nearest keys of the rows of tile (i of p, j of q): q's global index in the bits."""
        pp = tuple(jax.lax.dynamic_slice_in_dim(c, i * t, t) for c in p)
        qq = tuple(jax.lax.dynamic_slice_in_dim(c, j * t, t) for c in q)
        d2 = sum((pc[:, None] - qc[None, :]) ** 2 for pc, qc in zip(pp, qq))
        ok = ((i * t + rows) < n_p)[:, None] & ((j * t + rows) < n_q)[None, :]
        return jnp.min(_packed_keys(jnp.where(ok, d2, jnp.inf), iota + itype(j) * t, bits), axis=1)

    def tile(carry, i, j):
        ka, kb = carry
        ka = jax.lax.dynamic_update_slice_in_dim(
            ka, jnp.minimum(jax.lax.dynamic_slice_in_dim(ka, i * t, t), keys(pa, pb, i, j, n_a, n_b, bits_b)), i * t, 0)
        kb = jax.lax.dynamic_update_slice_in_dim(
            kb, jnp.minimum(jax.lax.dynamic_slice_in_dim(kb, j * t, t), keys(pb, pa, j, i, n_b, n_a, bits_a)), j * t, 0)
        return ka, kb

    def row(i, carry):
        def col(j, c):
            return jax.lax.cond(j * t < n_b, lambda c: tile(c, i, j), lambda c: c, c)
        return jax.lax.cond(i * t < n_a, lambda c: jax.lax.fori_loop(0, tb, col, c), lambda c: c, carry)

    top = jnp.iinfo(itype).max
    ka, kb = jax.lax.fori_loop(0, ta, row, (jnp.full(ta * t, top, itype), jnp.full(tb * t, top, itype)))
    ja = (kb[:cap_b] & ((1 << bits_a) - 1)).astype(jnp.int32)
    jb = (ka[:cap_a] & ((1 << bits_b) - 1)).astype(jnp.int32)
    return ja, jb


def _packed_argmin(d2, axis):
    """argmin of non-negative float32/64 values along ``axis`` as one integer min reduction: the
    index replaces the lowest mantissa bits of the value's bit pattern (which orders like the value
    for non-negative floats), so ties within 2^-(mantissa bits - index bits) relative pick the lower
    index. Cheaper than a min followed by a masked iota min on XLA's CPU backend."""
    n = d2.shape[axis]
    bits = max(1, int(n - 1).bit_length())
    itype = jnp.int32 if d2.dtype == jnp.float32 else jnp.int64
    iota = jax.lax.broadcasted_iota(itype, d2.shape, axis % d2.ndim)
    return (jnp.min(_packed_keys(d2, iota, bits), axis=axis) & ((1 << bits) - 1)).astype(jnp.int32)


def _packed_keys(d2, index, bits):
    """Integer keys of non-negative values d2 that order like them, with ``index`` (of the key's
    integer type, < 2**bits) in their lowest ``bits`` bits: their minimum's low bits are the index
    of the least value (:func:`_packed_argmin`)."""
    itype = index.dtype.type
    return (jax.lax.bitcast_convert_type(d2, itype) & ~itype((1 << bits) - 1)) | index


# --------------------------------------------------------------------------- outside jit


def candidate_counts(sim, x):
    """Candidate vertices per (pair, object) at public positions x (V, 3), numpy; for checks.

    Returns a list of ((A, B), n_A, n_B, cap_A, cap_B).
    """
    cfg = sim.terms.contact
    topo = sim.topology
    x = np.asarray(x, np.float64)
    tab_margin = _tables_margin(topo, cfg)
    out = []
    for (oa, ob), margin in zip(cfg.pairs, tab_margin):
        (a0, a1), (b0, b1) = topo.vertex_slices[oa], topo.vertex_slices[ob]
        xa, xb = x[a0:a1], x[b0:b1]
        in_a, in_b = _broad_phase(xa.T, xb.T, margin)
        n_a, n_b = int(in_a.sum()), int(in_b.sum())
        out.append(((oa, ob), n_a, n_b, cfg.capacity[oa], cfg.capacity[ob]))
    return out


def _longest_edges(topo):
    return [float(topo.rest_length[topo.edge_object == o].max()) for o in range(topo.n_objects)]


def skin_distance(topo, cfg):
    """The Verlet-list skin s of the candidate cache (m): SKIN_FACTOR x the shortest of the pairs'
    longest rest edges. Candidate lists are rebuilt once some vertex has moved s/2 since the last
    build (:func:`make_contact`)."""
    longest = _longest_edges(topo)
    return SKIN_FACTOR * min((max(longest[a], longest[b]) for a, b in cfg.pairs), default=0.0)


def _tables_margin(topo, cfg):
    """Per pair: the broad phase's inflation, 2 delta + 1.5 x the longest rest edge (the region
    where the force can act and the one-ring search is exact) plus twice the skin (so lists built
    up to s/2 of motion ago still hold every vertex of that region)."""
    longest = _longest_edges(topo)
    skin = skin_distance(topo, cfg)
    return tuple(2.0 * d + 1.5 * max(longest[a], longest[b]) + 2.0 * skin
                 for (a, b), d in zip(cfg.pairs, cfg.thickness))


def needed_capacity(sim, x):
    """The largest candidate count of any object in any pair at positions x (V, 3)."""
    return max((max(n_a, n_b) for _, n_a, n_b, _, _ in candidate_counts(sim, x)), default=0)


def grown_capacity(need):
    """The capacity :func:`jaxplush.simulate` reruns with after an overflow: 1.25 x the need,
    rounded up to a multiple of 32."""
    return -(-int(1.25 * need) // 32) * 32


def capacity_report(sim, x):
    """None if every pair's candidates fit at positions x (V, 3); else a message naming the pair
    and the capacity needed (for a :class:`jaxplush.errors.SimulationError` hint)."""
    if sim.terms.contact is None:
        return None
    names = sim.scene.object_names
    for (oa, ob), n_a, n_b, cap_a, cap_b in candidate_counts(sim, x):
        if n_a > cap_a or n_b > cap_b:
            return (f"contact candidates of objects {names[oa]!r}/{names[ob]!r} overflowed "
                    f"({n_a}/{cap_a} and {n_b}/{cap_b}): raise 'contact_capacity' to at least "
                    f"{max(n_a, n_b)}")
    return None
