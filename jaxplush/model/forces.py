"""The physical model: static topology, which terms a scene compiles, the force kernel and the
energies (docs/model.md §1, §5).

The terms themselves (spring, dashpot, gas, drag, smooth floor) are defined once in
:mod:`jaxplush.model.terms`; this module assembles them into the single-scene force kernel,
per vertex from its ordered one-ring, with no scatter:

* spring and dashpot: f_i = sum_j w_ij d_ij, d_ij = x_j - x_i, w from
  :func:`~jaxplush.model.terms.spring_weight` and :func:`~jaxplush.model.terms.dashpot_weight`;
* gas: f_i = P_o dV/dx_i, dV/dx_i = 1/6 sum_k d_k x d_{k+1} around the ordered ring
  (:func:`~jaxplush.model.terms.fan`), V_o from :func:`~jaxplush.model.terms.object_volumes`;
* air drag and the smooth floor, per vertex.

Every term is built only when the scene needs it and wrapped in a ``jax.named_scope`` so a
test can see that absent terms are not compiled. An alternative assembly by ``segment_sum``
over edges and faces (``assembly="segment"``) is kept for benchmarks and cross-checks; it calls
the same term functions. :func:`potential_energy` is written independently, per edge and per
face, so that tests can check f = -dU/dx.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from jaxplush.model import contact as _contact
from jaxplush.model import mesh as _mesh
from jaxplush.model import terms as T
from jaxplush.model.layout import (  # noqa: F401
    edge_stiffness, is_field, length_eps2, object_stiffness, per_object_sum, per_vertex, ring_stiffness,
    sum_rows as _sum_rows, vertex_mass)
from jaxplush.model.terms import (  # noqa: F401  (the terms' public names, also reachable from here)
    FLOOR_KAPPA, pressure, smooth_floor_energy, smooth_floor_force, smooth_floor_push, smooth_floor_stiffness)
from jaxplush.types import GAS_CONSTANT, VOLUME_EPS

#: Softening of edge lengths, relative to the shortest rest edge: l = sqrt(|d|² + eps²) keeps
#: gradients finite at zero length (docs/model.md §8).
LENGTH_EPS = 1e-6


def softening_length(shortest_edge):
    """The softening length eps of a mesh whose shortest rest edge is ``shortest_edge`` (m):
    LENGTH_EPS times it, rounded to the nearest power of two. The rounding lets every scene of
    about one scale (within a factor sqrt 2) compile eps into its programs as the same constant
    (:class:`jaxplush.stepping.compiled.Bucket`): passed as a runtime value instead, it slowed the
    spring kernel's rsqrt by 5-25% on XLA:CPU. eps is 1e-6 of an edge or less, so its rounding
    moves no force by more than about 1e-12 relative."""
    return float(2.0 ** np.round(np.log2(LENGTH_EPS * float(shortest_edge))))


@dataclasses.dataclass(frozen=True, eq=False)
class Topology:
    """Static mesh data, closed over by the compiled step (numpy; never traced).

    Attributes:
      n_vertices, n_objects: counts.
      faces: (F, 3) int32 outward faces.
      edges: (E, 2) int32 unique edges i < j; edge_object (E,) their object; rest_length (E,).
      ring: (V, K) int32 ordered one-ring neighbours, padded by repeating the last one.
      ring_mask: (V, K) bool, True for real neighbours; ring_rest: (V, K) rest lengths.
      ring_edge: (V, K) int32 the index into ``edges`` of each ring slot's edge (padded slots
        name their repeated neighbour's edge): a per-edge stiffness field reaches the ring
        kernels through it (:func:`jaxplush.model.layout.ring_stiffness`).
      edge_slices: per-object (start, stop) of its edges (edges are sorted, so each object's are
        contiguous).
      vertex_object: (V,) int32; vertex_slices / face_slices: per-object (start, stop).
      count: (O,) vertices per object; rest_volume: (O,) signed volume at the rest geometry.
      fixed: (P,) int32 pinned vertices; x0: (V, 3) rest positions.
      length_eps: softening length for edge lengths.
    """

    n_vertices: int
    n_objects: int
    faces: np.ndarray
    edges: np.ndarray
    edge_object: np.ndarray
    rest_length: np.ndarray
    ring: np.ndarray
    ring_mask: np.ndarray
    ring_rest: np.ndarray
    vertex_object: np.ndarray
    vertex_slices: tuple
    face_slices: tuple
    count: np.ndarray
    rest_volume: np.ndarray
    fixed: np.ndarray
    x0: np.ndarray
    length_eps: float
    ring_edge: np.ndarray
    edge_slices: tuple

    @property
    def n_edges(self):
        return len(self.edges)


def build_topology(scene):
    """Build the static :class:`Topology` of a :class:`jaxplush.scene.parse.Scene`."""
    x0 = scene.vertices
    faces = scene.faces
    edges = _mesh.unique_edges(faces).astype(np.int32)
    rest = np.linalg.norm(x0[edges[:, 0]] - x0[edges[:, 1]], axis=1)
    nbr, mask, _ = _mesh.ring_tables(faces, len(x0))
    ring_rest = np.linalg.norm(x0[nbr] - x0[:, None, :], axis=2)
    ring_rest = np.where(mask, ring_rest, 1.0)
    vobj = scene.object_id
    eobj = vobj[edges[:, 0]]
    bounds = np.searchsorted(eobj, np.arange(scene.n_objects + 1))
    return Topology(
        n_vertices=len(x0), n_objects=scene.n_objects, faces=faces, edges=edges,
        edge_object=eobj, rest_length=rest, ring=nbr, ring_mask=mask,
        ring_rest=ring_rest, vertex_object=vobj,
        vertex_slices=tuple(o.vertex_slice for o in scene.objects),
        face_slices=tuple(o.face_slice for o in scene.objects),
        count=np.array([o.n_vertices for o in scene.objects], np.float64),
        rest_volume=scene.volumes(), fixed=scene.fixed, x0=x0,
        length_eps=softening_length(rest.min()), ring_edge=_mesh.ring_edges(edges, nbr),
        edge_slices=tuple((int(a), int(b)) for a, b in zip(bounds[:-1], bounds[1:])))


#: The smooth floor's softplus sharpness: beta = FLOOR_SHARPNESS / delta, delta half the object's mean
#: rest edge length (as soft-soft contact's beta = 10 / thickness).
FLOOR_SHARPNESS = 10.0


@dataclasses.dataclass(frozen=True)
class SmoothFloor:
    """Static settings of the smooth (penalty) floor, ``floor_model smooth`` (hashable; in Terms).

    Every vertex carries the energy U(s) = k_f / 2 * (softplus(-beta s) / beta)², s = y - height,
    so the floor pushes up with f_y = k_f phi(s) sigmoid(-beta s), phi = softplus(-beta s) / beta:
    C-infinity in y, zero well above the floor, k_f |s| well below it. Its trajectories are smooth
    functions of the parameters, unlike the projection's (a loss through the projection has a
    kink wherever a vertex's contact starts or ends at another step).

    Attributes:
      height: floor height y, m.
      beta: (O,) softplus sharpness per object, 1/m (10 / half the mean rest edge length).
      stiffness: fixed k_f (N/m), or None for FLOOR_KAPPA * 2 n_max * k_structural of the object.
      n_max: (O,) largest valence per object (for the default stiffness).
    """

    height: float
    beta: tuple
    stiffness: float | None
    n_max: tuple


def smooth_floor_for_scene(scene, topo=None):
    """:class:`SmoothFloor` of a scene with ``floor_model smooth``, else None."""
    if scene.floor is None or scene.floor_model != "smooth":
        return None
    beta, n_max = [], []
    edges = _mesh.unique_edges(scene.faces)
    length = np.linalg.norm(scene.vertices[edges[:, 0]] - scene.vertices[edges[:, 1]], axis=1)
    eobj = scene.object_id[edges[:, 0]]
    mask = topo.ring_mask if topo is not None else _mesh.ring_tables(scene.faces, scene.n_vertices)[1]
    for o in range(scene.n_objects):
        beta.append(FLOOR_SHARPNESS / (0.5 * float(length[eobj == o].mean())))
        a, b = scene.objects[o].vertex_slice
        n_max.append(int(mask[a:b].sum(axis=1).max()))
    return SmoothFloor(height=float(scene.floor), beta=tuple(beta), stiffness=scene.floor_stiffness,
                       n_max=tuple(n_max))


#: The simulation's position resolution must be this fine against the shortest rest edge.
PRECISION_FRACTION = 1e-3


def check_precision(topo, dtype, path="<scene>", driven=()):
    """Refuse a scene whose coordinates ``dtype`` cannot resolve: the spacing of floats at the
    largest coordinate must be at most PRECISION_FRACTION of the shortest rest edge. (In float32
    an object 1e7 m from the origin cannot move at all, and 1e10 m away its edges collapse.)
    The positions of the driven paths (``driven``, the scene's
    :class:`jaxplush.scene.parse.DrivenPath` entries) are held to the same rule: a vertex driven
    1e29 m away would tear its object apart.

    Raises:
      JaxplushError: naming the file, the magnitudes and the remedies.
    """
    from jaxplush.errors import JaxplushError
    scale = float(np.max(np.abs(topo.x0))) if topo.n_vertices else 0.0
    edge = float(np.min(topo.rest_length)) if len(topo.rest_length) else 0.0
    ulp = scale * float(np.finfo(np.dtype(dtype)).eps)
    if edge > 0 and ulp > PRECISION_FRACTION * edge:
        name = np.dtype(dtype).name
        raise JaxplushError(
            f"{path}: coordinates up to {scale:.3g} m with edges as short as {edge:.3g} m: {name} resolves only "
            f"{ulp:.3g} m at that distance from the origin, too coarse to simulate; translate the scene near "
            "the origin" + (", or run in float64 (--x64)" if name == "float32" else ""))
    from jaxplush.errors import driven_path_error
    for d in driven:
        far = float(np.max(np.abs(d.positions))) if np.size(d.positions) else 0.0
        ulp = far * float(np.finfo(np.dtype(dtype)).eps)
        if edge > 0 and ulp > PRECISION_FRACTION * edge:
            name = np.dtype(dtype).name
            what = f"'driven' path file {d.source!r}" if d.line else "dataset 'controls/positions'"
            raise driven_path_error(
                d, path, f"{what}: positions up to {far:.3g} m from the origin, with edges as short as {edge:.3g} m: "
                f"{name} resolves only {ulp:.3g} m there, too coarse to simulate; keep the path near the scene")


@dataclasses.dataclass(frozen=True)
class Terms:
    """Which force terms a scene compiles in (static; decided from the scene, not values)."""

    spring: bool = True
    dashpot: bool = False
    drag: bool = False
    gas: bool = False
    gravity: bool = False
    #: the floor projection (``floor_model projection``, the default); see also floor_smooth
    floor: bool = False
    fixed: bool = False
    verlet_damping: bool = False
    #: soft-soft contact (:class:`jaxplush.model.contact.ContactConfig`), None: not compiled in
    contact: object = None
    #: floor Coulomb friction coefficient mu and restitution e (0: not compiled in)
    floor_friction: float = 0.0
    floor_restitution: float = 0.0
    #: the smooth penalty floor (:class:`SmoothFloor`, ``floor_model smooth``), None: not compiled in
    floor_smooth: object = None
    #: driven vertices (scene keyword ``driven``; :class:`jaxplush.stepping.constraints.Drive`)
    driven: bool = False
    #: the spring stiffness is an (E,) per-edge field (scene keywords ``k_region``/``k_edge``), not
    #: one value per object. The kernels follow the parameter's shape; this flag only gates the
    #: engines that take (O, B) parameters (:mod:`jaxplush.stepping.batched` refuses a field).
    k_field: bool = False

    @classmethod
    def for_scene(cls, scene, params=None):
        """The terms ``scene`` needs; with ``params`` (a Params of arrays, e.g. a run's override or
        a sweep's (O, B) batch) also the dashpot, drag and Verlet damping wherever any of its
        values switches them on (a term compiled in with a zero coefficient changes nothing), and
        ``k_field`` where its k_structural is a per-edge field."""

        def on(key):
            return bool(np.any(np.asarray(getattr(scene.params, key)) > 0)) or (
                params is not None and bool(np.any(np.asarray(getattr(params, key)) > 0)))
        smooth = smooth_floor_for_scene(scene)
        has_floor = scene.floor is not None and smooth is None
        return cls(spring=True,
                   dashpot=on("dashpot"),
                   drag=on("drag"),
                   gas=scene.has_gas,
                   gravity=bool(np.any(scene.gravity != 0)),
                   floor=has_floor,
                   floor_smooth=smooth,
                   fixed=len(scene.fixed) > 0,
                   verlet_damping=on("damping"),
                   contact=_contact.config_for_scene(scene),
                   floor_friction=float(scene.floor_friction) if has_floor else 0.0,
                   floor_restitution=float(scene.floor_restitution) if has_floor else 0.0,
                   driven=len(getattr(scene, "driven", ())) > 0,
                   k_field=_field_shape(scene, scene.params.k_structural) or (
                       params is not None and _field_shape(scene, params.k_structural)))

    def names(self):
        out = tuple(f.name for f in dataclasses.fields(self) if getattr(self, f.name))
        if self.contact and self.contact.friction > 0:
            out += ("contact_friction",)
        return out


def _field_shape(scene, k):
    """Whether ``k`` has the shape of a per-edge stiffness field of ``scene`` (1-D, not (O,))."""
    shape = np.shape(k)
    return len(shape) == 1 and shape[0] != scene.n_objects


def check_param_shapes(topo, params):
    """Raise ValueError unless every parameter is (O,) (``k_structural`` may also be the (E,)
    per-edge field, :mod:`jaxplush.model.layout`). Shapes only (traced values pass too); called
    before tracing by the entry points (``Simulator.params``, ``rollout``, ``rollout_loss``)."""
    o, e = topo.n_objects, topo.n_edges
    for name, value in zip(type(params)._fields, params):
        shape = np.shape(value)
        if shape == (o,) or (name == "k_structural" and shape == (e,)):
            continue
        allowed = f"({o},) per object" + (f" or ({e},) per edge (a stiffness field)" if name == "k_structural" else "")
        raise ValueError(f"parameter {name} has shape {shape}; expected {allowed}")


#: Parameters whose values only act through a term that a scene may leave out: (field, term).
SWITCHED = (("dashpot", "dashpot"), ("drag", "drag"), ("damping", "verlet_damping"), ("nmol", "gas"))


def check_params(terms, params):
    """Raise ValueError when ``params`` gives a value above 0 to a term ``terms`` leaves out,
    which would be ignored without a trace (the term is not compiled in). Checked on concrete
    values only, outside jit; traced values pass unchecked."""
    import jax
    for field, term in SWITCHED:
        value = getattr(params, field)
        if isinstance(value, jax.core.Tracer) or getattr(terms, term):
            continue
        if np.any(np.asarray(value) > 0):
            how = ("give the object an nmol line in its scene (a scene without gas compiles no gas)"
                   if term == "gas" else
                   f"build it with make_simulator(scene, dt, terms=Terms.for_scene(scene, params)), or give "
                   f"the scene a {field} above 0")
            raise ValueError(f"{field} = {np.asarray(value).tolist()} would be ignored: this simulator has no "
                             f"{term} term compiled in; {how}")


def _dot(a, b):
    return jnp.sum(a * b, axis=-1)


def make_force_fn(topo, terms, temperature, assembly="ring", h=None, with_cache=False):
    """Build the force kernel ``force_fn(params, x, v) -> (f, volume)`` on component-major arrays.

    The kernel works on (3, V) arrays (x, y, z rows): every gather then moves single floats
    through a 1-D index table, which XLA's CPU backend runs faster than gathering (V, 3) rows
    (see benchmarks/RESULTS.md). :func:`jaxplush.stepping.step.make_simulator` keeps its state in
    this layout and exposes (V, 3) views to users.

    Args:
      topo: :class:`Topology`.
      terms: :class:`Terms`; only the selected terms are traced. Gravity, the floor, pinned
        vertices and the report's Verlet damping belong to the integrator, not here. Soft-soft
        contact (``terms.contact``, :mod:`jaxplush.model.contact`) is added to the internal force.
      temperature: gas temperature (K), a Python float.
      assembly: "ring" (per-vertex one-ring gathers, default) or "segment" (per-edge and
        per-face terms scattered with ``segment_sum``).
      h: the integrator's step, s; needed only by contact friction (which at most stops the
        relative sliding within one step).
      with_cache: also return the soft-soft contact's :class:`jaxplush.model.contact.CacheOps` (None
        without contact); the kernel then takes an optional ``cache`` (a
        :class:`jaxplush.model.contact.ContactCache`) as a fourth argument.

    Returns:
      force_fn: (params, x (3, V), v (3, V)) -> (f (3, V) internal forces in N, volume (O,) or
      None when the scene has no gas); with ``with_cache``, (force_fn, cache_ops).
    """
    if assembly == "ring":
        kernel = _ring_force_fn(topo, terms, temperature)
    elif assembly == "segment":
        kernel = _segment_force_fn(topo, terms, temperature)
    else:
        raise ValueError(f"unknown assembly {assembly!r}; expected 'ring' or 'segment'")
    if not terms.contact:
        return (kernel, None) if with_cache else kernel
    contact_force, cache_ops = _contact.make_contact(topo, terms.contact, h)

    def force_fn(params, x, v, cache=None):
        f, volume = kernel(params, x, v)
        with jax.named_scope("contact"):
            f = contact_force(params, x, v, base=f, cache=cache)
        return f, volume

    return (force_fn, cache_ops) if with_cache else force_fn


def _ring_force_fn(topo, terms, temperature):
    # Neighbour-major tables: row j of the (K+1, V) index table holds every vertex's j-th ring
    # neighbour and row K repeats row 0, so "the next neighbour" of slot j is row j+1. One
    # gather -> (3 or 6, K(+1), V) (velocities stacked under positions for the dashpot) feeds
    # variadic reductions over the rows (_sum_rows), each one fused, vectorised loop over V
    # that reads the gathered table. XLA fuses a gather with a single consumer into it, and a
    # reduction with a fused gather is not vectorised (much slower), so the table always has two
    # consumers: the spring and gas reductions, or, without gas, the spring force split into
    # (x, y) and (z) reductions (benchmarks/RESULTS.md).
    ring = np.ascontiguousarray(topo.ring.T)                            # (K, V)
    n_slots = ring.shape[0]
    table = np.ascontiguousarray(np.concatenate([ring, ring[:1]], axis=0)) if terms.gas else ring
    mask = np.ascontiguousarray(topo.ring_mask.T)
    ring_rest = np.ascontiguousarray(topo.ring_rest.T)
    all_real = bool(mask.all())

    def force_fn(params, x, v):
        dtype = x.dtype
        rest = jnp.asarray(ring_rest, dtype)
        eps2 = length_eps2(topo, dtype)
        with jax.named_scope("spring"):
            src = jnp.concatenate([x, v]) if terms.dashpot else x
            t = src.at[:, table].get(mode="promise_in_bounds")          # indices valid by construction
            de = [t[c] - x[c] for c in range(3)]                        # 3 x (K(+1), V)
            d = [dc[:n_slots] for dc in de]                             # 3 x (K, V)
            inv_l = T.inv_length(d, eps2)
            w = T.edge_weight(terms, lambda field: ring_stiffness(topo, params.k_structural)
                              if field == "k_structural" else per_vertex(topo, getattr(params, field)),
                              rest, d, inv_l, dv=lambda: [t[3 + c, :n_slots] - v[c] for c in range(3)])
            if not all_real:
                w = jnp.where(mask, w, 0.0)
            fs = [w * d[c] for c in range(3)]
            f = _sum_rows(fs) if terms.gas else _sum_rows(fs[:2]) + _sum_rows(fs[2:])
        f, volume = vertex_terms(topo, terms, temperature, params, x, v, f,
                                 lambda: _sum_rows(T.fan(d, [dc[1:] for dc in de])))
        return jnp.stack(f), volume

    return force_fn


def vertex_terms(topo, terms, temperature, params, x, v, f, fan_sums):
    """Add the per-vertex terms (air drag, the smooth floor, the gas) to the edge forces ``f``.

    Every force kernel ends with this: the single-scene ring and segment assemblies (on (V,)
    components) and the batched engine (on (V, B) components, with (O, B) parameters).

    Args:
      x, v, f: positions, velocities and the edge forces so far, each three components (x, y, z)
        of shape (V,) or (V, B) (a (3, V) array works for x and v).
      fan_sums: ``() -> [3 arrays]`` the ring sums of :func:`jaxplush.model.terms.fan` at every
        vertex (called only when the scene has gas).

    Returns:
      (f as a list of three components, volume (O,) or (O, B), or None without gas).
    """
    f = list(f)
    if terms.drag:
        with jax.named_scope("drag"):
            gamma, m = per_vertex(topo, params.drag), vertex_mass(topo, params)
            f = [fc + T.drag_force(gamma, m, v[c]) for c, fc in enumerate(f)]
    if terms.floor_smooth:
        with jax.named_scope("floor_smooth"):
            f[1] = f[1] + T.smooth_floor_force(topo, terms.floor_smooth, params, x[1])
    volume = None
    if terms.gas:
        with jax.named_scope("gas"):
            g = T.volume_gradient(fan_sums())
            volume = T.object_volumes(topo, x, g)
            p = per_vertex(topo, T.pressure(topo, params, volume, temperature))
            f = [fc + p * gc for fc, gc in zip(f, g)]
    return f, volume


def _segment_force_fn(topo, terms, temperature):
    e0, e1 = topo.edges[:, 0], topo.edges[:, 1]
    n = topo.n_vertices
    faces = topo.faces

    def scatter(vals, idx):
        return jax.ops.segment_sum(vals, idx, num_segments=n)

    def per_edge(values):
        if is_field(topo, values):          # a per-edge stiffness field: already per edge
            return values
        return values[topo.edge_object] if topo.n_objects > 1 else values[0]

    def force_fn(params, x, v):
        dtype = x.dtype
        rest = jnp.asarray(topo.rest_length, dtype)
        with jax.named_scope("spring"):
            d = x[:, e1] - x[:, e0]                                     # (3, E)
            inv_l = T.inv_length(d, length_eps2(topo, dtype))
            w = T.edge_weight(terms, lambda field: per_edge(getattr(params, field)), rest, d, inv_l,
                              dv=lambda: v[:, e1] - v[:, e0])
            fe = w * d
            f = [scatter(fe[c], e0) - scatter(fe[c], e1) for c in range(3)]

        def fan_sums():
            # per face: 2 A n = (b - a) x (c - a), a third of it to each corner (the ring's fan
            # sums, face by face: docs/model.md §1)
            corners = [x[:, faces[:, i]] for i in range(3)]
            an = T.cross(corners[1] - corners[0], corners[2] - corners[0])
            return [scatter(a, faces[:, 0]) + scatter(a, faces[:, 1]) + scatter(a, faces[:, 2]) for a in an]

        f, volume = vertex_terms(topo, terms, temperature, params, x, v, f, fan_sums)
        return jnp.stack(f), volume

    return force_fn


def potential_energy(topo, params, x, temperature, gravity=None, gas=True, floor=None):
    """Total potential energy (J): springs + gas (-nRT ln V, clamped as the force) + gravity
    (+ the smooth floor's energy, with ``floor`` a :class:`SmoothFloor`).

    Written independently of the force functions (per edge, per face) so tests can check
    f = -dU/dx with ``jax.grad``.
    """
    d = x[topo.edges[:, 0]] - x[topo.edges[:, 1]]
    l = jnp.sqrt(_dot(d, d) + length_eps2(topo, x.dtype))
    k = edge_stiffness(topo, params.k_structural)
    u = jnp.sum(0.5 * k * (l - topo.rest_length) ** 2)
    if gas:
        u = u + jnp.sum(gas_energy(topo, params, x, temperature))
    if gravity is not None:
        height = jnp.matmul(x, jnp.asarray(gravity, x.dtype), precision=jax.lax.Precision.HIGHEST)
        u = u - jnp.sum(vertex_mass(topo, params) * height)
    if floor is not None:
        u = u + smooth_floor_energy(topo, floor, params, x[:, 1])
    return u


def gas_energy(topo, params, x, temperature):
    """(O,) gas energy -nRT ln V, continued linearly below eps V0 (the clamp's potential)."""
    vol = face_volumes(topo, x)
    nrt = params.nmol * GAS_CONSTANT * temperature
    vc = VOLUME_EPS * jnp.asarray(topo.rest_volume, x.dtype)
    safe = jnp.maximum(vol, vc)
    return jnp.where(vol >= vc, -nrt * jnp.log(safe), -nrt * (jnp.log(vc) + (vol - vc) / vc))


def face_volumes(topo, x):
    """(O,) signed volumes from faces (sum of signed tetrahedra about each object's centroid), x (V, 3)."""
    return object_face_volumes(topo, x.T)


def object_face_volumes(topo, xs):
    """(O, ...) signed volumes from faces, as :func:`face_volumes`, of component-major positions:
    ``xs`` three (V, ...) arrays, say a (3, V) array or the batched engine's three (V, B)."""
    out = []
    for (a, b), (fa, fb) in zip(topo.vertex_slices, topo.face_slices):
        faces = topo.faces[fa:fb]
        rel = [xs[c] - jnp.mean(xs[c][a:b], axis=0) for c in range(3)]
        p, q, r = ([rel[c][faces[:, i]] for c in range(3)] for i in range(3))
        out.append(jnp.sum(T.dot(p, T.cross(q, r)), axis=0) / 6.0)
    return jnp.stack(out)


def kinetic_energy(topo, params, v):
    """Kinetic energy (J) of velocities v (V, 3)."""
    return 0.5 * jnp.sum(vertex_mass(topo, params) * _dot(v, v))
