"""Layout helpers shared by the model's terms: per-object values spread to vertices, per-object
sums, vertex masses, sums over a ring table's rows, and the spring stiffness as a per-object value
or a per-edge field. Shapes follow :mod:`jaxplush.types`; per-object arrays are (O,), or (O, B)
for a batch of B parameter points (the batched engine's layout, batch last), and the per-vertex
results are then (V,) or (V, B).

Spring stiffness: ``Params.k_structural`` is either (O,) per object or an (E,) field per edge, in
the order of ``topo.edges`` (:func:`jaxplush.model.mesh.unique_edges` of the scene's faces). Its
shape decides which, statically (E > O: a closed object has at least 6 edges):
:func:`is_field`. The force kernels read it through :func:`ring_stiffness` (ring slots) or
:func:`edge_stiffness` (edges); terms that need one value per object (the default contact and
smooth-floor stiffnesses) through :func:`object_stiffness`, the mean over the object's edges; the
stability bounds through :func:`vertex_stiffness_max`, the stiffest edge at each vertex. A scene
without a field never reaches the field's code (the same program as before fields existed)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np


def scene_value(value, dtype):
    """A number derived from a scene's geometry (a contact margin, a valence),
    as a traced scalar of ``dtype``, not a literal of the compiled program.

    Inside a trace it enters as a one-element array constant, which JAX hoists out of the program
    into its arguments (:func:`jaxplush._xla.hoist_constants`), as it does the topology's tables:
    two scenes that differ only in such values lower to the same program, and the second loads it
    from the persistent compilation cache (docs/cli.md, "Programs shared by scenes of one size")."""
    return jnp.asarray(np.asarray([value], dtype=jnp.dtype(dtype)))[0]


def length_eps2(topo, dtype):
    """The squared softening length of edge lengths, eps² (:attr:`Topology.length_eps`, a power
    of two: :func:`jaxplush.model.forces.softening_length`), as a constant of the program: the
    one geometry value that is not a :func:`scene_value`, since the spring kernel's rsqrt runs
    5-25% slower on XLA:CPU with a runtime value in it. Its power of two is part of the program's
    bucket (:class:`jaxplush.stepping.compiled.Bucket`)."""
    return jnp.asarray(topo.length_eps ** 2, dtype)


def per_vertex(topo, values):
    """Spread an (O,) per-object array to (V,), or an (O, B) one to (V, B). A single object's
    values broadcast instead: (V,) from (1,), and (1, B) from (1, B), which broadcasts against
    (V, B) without being materialised."""
    if topo.n_objects == 1:
        if values.ndim == 1:
            return jnp.broadcast_to(values[0], (topo.n_vertices,))
        return values[:1]
    return values[topo.vertex_object]


def per_object_sum(topo, values):
    """(O, ...) sums of a (V, ...) array over each object's contiguous vertex range."""
    if topo.n_objects == 1:
        return jnp.sum(values, axis=0)[None]
    return jnp.stack([jnp.sum(values[a:b], axis=0) for a, b in topo.vertex_slices])


def vertex_mass(topo, params):
    """(V,) vertex masses, kg (per :func:`per_vertex` for batched (O, B) parameters)."""
    w = params.total_weight
    if w.ndim == 1:
        return per_vertex(topo, w / topo.count)
    return per_vertex(topo, w / jnp.asarray(topo.count, w.dtype).reshape((-1,) + (1,) * (w.ndim - 1)))


def sum_rows(ops):
    """Sums over axis 0 of several equal-shape (K, V) arrays as ONE variadic reduction.

    XLA then emits a single loop over V that evaluates every operand per neighbour slot and
    keeps the K-sums in registers, instead of one reduction (and one pass over the gathered
    table) per output component.
    """
    zero = jnp.zeros((), ops[0].dtype)
    return jax.lax.reduce(tuple(ops), (zero,) * len(ops),
                          lambda a, b: tuple(ai + bi for ai, bi in zip(a, b)), (0,))


# --------------------------------------------------------------------------- spring stiffness

def is_field(topo, k):
    """Whether the spring stiffness ``k`` (``Params.k_structural``) is an (E,) per-edge field
    rather than (O,) per object (or (O, B) batched). Static: decided from the shape alone."""
    shape = np.shape(k)
    return len(shape) == 1 and shape[0] == topo.n_edges and topo.n_edges != topo.n_objects


def _xp(a):
    return np if isinstance(a, (np.ndarray, np.generic)) else jnp


def edge_stiffness(topo, k):
    """(E,) stiffness of every edge, N/m: the field itself, or each edge's object's value
    (``k[edge_object]``; numpy in, numpy out)."""
    if is_field(topo, k):
        return k
    return k[topo.edge_object]


def object_stiffness(topo, k):
    """(O,) one stiffness per object, N/m: ``k`` itself when it is per object (the same array,
    (O,) or (O, B)), else the mean of the field over each object's edges (numpy in, numpy out)."""
    if not is_field(topo, k):
        return k
    xp = _xp(k)
    return xp.stack([xp.mean(k[a:b]) for a, b in topo.edge_slices])


def object_stiffness_max(topo, k):
    """(O,) the stiffest edge of each object, N/m (``k`` itself when it is per object)."""
    if not is_field(topo, k):
        return k
    xp = _xp(k)
    return xp.stack([xp.max(k[a:b]) for a, b in topo.edge_slices])


def ring_stiffness(topo, k):
    """The spring stiffness seen from each ring slot, for the one-ring kernels on (K, V) tables:
    :func:`per_vertex` (V,) or (V, B) of a per-object ``k`` (it broadcasts against (K, V)), or the
    (K, V) table ``k[ring_edge]`` of a field (padded slots name a real edge; kernels mask them)."""
    if not is_field(topo, k):
        return per_vertex(topo, k)
    table = np.ascontiguousarray(topo.ring_edge.T)
    if isinstance(k, (np.ndarray, np.generic)):
        return k[table]
    return jnp.asarray(k).at[table].get(mode="promise_in_bounds")


def vertex_stiffness_max(topo, k):
    """(V,) numpy: the stiffest spring at each vertex, N/m (its object's value for a per-object
    ``k``); the stability bounds scale with it."""
    k = np.asarray(k, np.float64)
    if not is_field(topo, k):
        return k[topo.vertex_object]
    return np.max(np.where(topo.ring_mask, k[topo.ring_edge], -np.inf), axis=1, initial=0.0)
