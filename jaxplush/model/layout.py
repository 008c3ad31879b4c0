"""Layout helpers shared by the model's terms: per-object values spread to vertices, per-object
sums, vertex masses, and sums over a ring table's rows. Shapes follow :mod:`jaxplush.types`;
per-object arrays are (O,), or (O, B) for a batch of B parameter points (the batched engine's
layout, batch last), and the per-vertex results are then (V,) or (V, B)."""

from __future__ import annotations

import jax
import jax.numpy as jnp


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
