"""Every physical force term of the model, written once (docs/model.md §1, §5, §6).

A term here is a handful of elementwise functions of per-edge (one ring slot) or per-vertex
quantities, with its transpose for the fused adjoint written beside its forward. They are
layout-free: a *vector* is three component arrays (x, y, z) of one shape, or a (3, ...) array,
and every argument broadcasts, so the same functions serve

* the single-scene ring kernel, on (K, V) ring tables (:func:`jaxplush.model.forces.make_force_fn`);
* its segment assembly, on (E,) edges and (F,) faces;
* the batched sweep, on (V, B) arrays per ring slot (:mod:`jaxplush.stepping.batched`);
* the fused adjoint's hand VJP (:mod:`jaxplush.stepping.adjoint`), from the ``*_vjp`` functions;
* the implicit integrator's Jacobian products (:mod:`jaxplush.stepping.integrators`).

An assembly gathers neighbour values, calls these functions and sums over the ring; none of
them restates a formula. The edge terms are summed in one place, :func:`edge_weight`, which
every kernel calls on its layout (:data:`EDGE_TERMS` lists them). Per-object values reach vertices through
:func:`jaxplush.model.layout.per_vertex`, which takes (O,) or batched (O, B) arrays; the spring
stiffness, which may be an (E,) per-edge field, through :func:`jaxplush.model.layout.ring_stiffness`.

Notation, per ring entry (i, j) of vertex i: d = x_j - x_i, l = sqrt(|d|² + eps²), L the rest
length, dv = v_j - v_i; for a force cotangent lam: delta = lam_j - lam_i and t = d.delta. Every
edge term acts on i as w d (a weight times the edge vector), so f_i = sum_j w_ij d_ij.

Where each term lives (this module unless named):

=====================  ==========================================  ============================
term                   forward                                     transpose (fused adjoint)
=====================  ==========================================  ============================
spring                 :func:`spring_weight`                       :func:`spring_vjp`
dashpot                :func:`dashpot_weight`                      :func:`dashpot_vjp`
gas                    :func:`fan`, :func:`object_volumes`,        :func:`fan_tangent`,
                       :func:`pressure`                            :func:`pressure_slopes`
drag                   :func:`drag_force`                          :func:`drag_vjp`
floor (smooth)         :func:`smooth_floor_force`                  none (autodiff paths)
gravity                ``stepping.integrators.System.accel``       constant: no cotangent
floor (projection)     ``stepping.constraints``                    ``stepping.adjoint`` (mask)
pins                   ``stepping.constraints``                    ``stepping.adjoint`` (mask)
Verlet damping         ``stepping.integrators.damping_keep``,      ``stepping.adjoint``
                       ``verlet_kick``
soft-soft contact      ``model.contact``                           ``jax.vjp`` of its forward
=====================  ==========================================  ============================

:data:`REGISTRY` records the same per :class:`jaxplush.model.forces.Terms` switch, with which
engines implement it; the batched engine and the fused adjoint take their gates from it.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from jaxplush.model.layout import object_stiffness, per_object_sum, per_vertex
from jaxplush.types import GAS_CONSTANT, VOLUME_EPS


# --------------------------------------------------------------------------- vectors

def dot(a, b):
    """a.b of two vectors (three components each), elementwise over their shape."""
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def cross(a, b):
    """a x b as a list of three components."""
    return [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]


def inv_length(d, eps2):
    """1 / l = 1 / sqrt(|d|² + eps²): the softened inverse edge length (finite at d = 0)."""
    return jax.lax.rsqrt(dot(d, d) + eps2)


# --------------------------------------------------------------------------- spring

def spring_weight(k, rest, inv_l):
    """T / l = k (1 - L/l): the Hooke spring pulls vertex i by (T/l) d toward j (T = k (l - L))."""
    return k * (1.0 - rest * inv_l)


def spring_vjp(k, rest, inv_l, t):
    """The spring's transpose per ring entry. Its Jacobian is symmetric, so for a cotangent lam

        J_x^T lam_i = sum_j (T/l) delta + k L/l³ t d,

    and the force is linear in k: sum_i lam_i.f_i = -1/2 sum_ij k (1 - L/l) t (each edge is seen
    from both ends). Returns (T/l, the coefficient k L/l³ of t d, the k density -1/2 (1 - L/l) t).
    """
    s = 1.0 - rest * inv_l
    return k * s, k * rest * inv_l * inv_l * inv_l, -0.5 * s * t


def spring_jacobian(k, rest, inv_l):
    """The spring's stiffness split as K_e = a I + b d^ d^^T per ring entry (d^ = d / l), with the
    transverse part clamped at zero for compressed springs so that K_e stays positive
    semi-definite (the implicit integrator's linear solve needs that). Returns (a, b) with
    a = k max(0, 1 - L/l) and b = k - a."""
    transverse = k * jnp.maximum(1.0 - rest * inv_l, 0.0)
    return transverse, k - transverse


# --------------------------------------------------------------------------- dashpot

def dashpot_weight(c, dv, d, inv_l):
    """The edge dashpot's share of the edge weight: c (dv.d)/l², a force c ((dv).d^) d^ on i."""
    return c * dot(dv, d) * inv_l * inv_l


def dashpot_vjp(c, dv, d, inv_l, t):
    """The dashpot's transpose per ring entry, for the weight :func:`dashpot_weight`:

        J_x^T lam_i = sum_j c/l² [(dv.d) delta + t dv - 2 (dv.d) t d / l²],
        J_u^T lam_i = sum_j c/l² t d.

    Returns (its weight c q, its coefficient of t d -2 c q / l², the coefficient c t / l² of d in
    J_u^T lam (and of dv in J_x^T lam), the c density -1/2 q t), q = (dv.d)/l².
    """
    inv_l2 = inv_l * inv_l
    q = dot(dv, d) * inv_l2
    return c * q, -2.0 * c * q * inv_l2, c * inv_l2 * t, -0.5 * q * t


# --------------------------------------------------------------------------- the edge terms, assembled once

#: Every per-edge term: (its :class:`jaxplush.model.forces.Terms` switch, the Params field of its
#: coefficient), in the order :func:`edge_weight` sums them. A new edge term is a line here, a
#: branch in :func:`edge_weight` and its transpose in the fused adjoint; the engines' assemblies
#: need no change (each spreads any field named here to its layout).
EDGE_TERMS = (("spring", "k_structural"), ("dashpot", "dashpot"))


def edge_fields(terms):
    """The Params fields of the per-edge terms ``terms`` switches on (:data:`EDGE_TERMS`)."""
    return tuple(field for name, field in EDGE_TERMS if getattr(terms, name))


def edge_weight(terms, coefficient, rest, d, inv_l, dv=None):
    """The summed weight w of every switched-on per-edge term at each edge entry (the force on
    vertex i is w d, d = x_j - x_i): the one assembly of the edge terms, which every engine's
    kernel calls on its own layout (the single-scene ring kernel on (K, V) tables, its segment
    assembly on (E,) edges, the batched kernel on (V, B) slots).

    Args:
      terms: the :class:`jaxplush.model.forces.Terms` switches.
      coefficient: ``coefficient(field) -> array``: the Params field (of :data:`EDGE_TERMS`)
        spread to the engine's layout, broadcasting against ``d``'s components.
      rest: rest lengths L; d: the edge vector (three components); inv_l: 1/l
        (:func:`inv_length`).
      dv: ``() -> vector``, the relative velocity v_j - v_i, called only by a term that needs it.
    """
    w = spring_weight(coefficient("k_structural"), rest, inv_l)
    if terms.dashpot:
        with jax.named_scope("dashpot"):
            w = w + dashpot_weight(coefficient("dashpot"), dv(), d, inv_l)
    return w


# --------------------------------------------------------------------------- gas

def fan(d, d_next):
    """One ring slot's share of 6 dV/dx_i: d_k x d_{k+1} for consecutive ring neighbours. Summed
    around the closed ring and divided by 6 (:func:`volume_gradient`) it is dV/dx_i, the sum of
    A_f n_f / 3 over the faces at i."""
    return cross(d, d_next)


def fan_tangent(d, d_next, delta, delta_next):
    """The directional derivative of :func:`fan` along lam: delta_k x d_{k+1} + d_k x delta_{k+1}
    (summed and divided by 6: H_V lam, the volume's Hessian times lam, symmetric)."""
    return [a + b for a, b in zip(cross(delta, d_next), cross(d, delta_next))]


def volume_gradient(fan_sums):
    """dV/dx from the ring sums of :func:`fan` (or :func:`fan_tangent`): a sixth of them (a
    (3, ...) array, or a list of three components)."""
    if isinstance(fan_sums, (list, tuple)):
        return [s / 6.0 for s in fan_sums]
    return fan_sums / 6.0


def object_volumes(topo, x, g):
    """(O, ...) object volumes V_o = 1/3 sum_i (x_i - r_o).g_i, with g = dV/dx (a vector of (V, ...)
    arrays) and r_o the object's first vertex: V is homogeneous of degree 3 in x - r_o."""
    if topo.n_objects == 1:
        rel = [x[c] - x[c][:1] for c in range(3)]
    else:
        counts = np.asarray(topo.count, np.int64)
        rel = [x[c] - jnp.repeat(jnp.stack([x[c][a] for a, _ in topo.vertex_slices]), counts, axis=0,
                                 total_repeat_length=topo.n_vertices) for c in range(3)]
    return per_object_sum(topo, dot(rel, g)) / 3.0


def _per_object(values, like):
    """An (O,) numpy constant shaped to broadcast against ``like`` ((O,) or (O, B)), its dtype."""
    a = jnp.asarray(values, like.dtype)
    return a.reshape(a.shape + (1,) * (like.ndim - 1))


def pressure(topo, params, volume, temperature):
    """(O, ...) gas pressure nRT / max(V, eps V0): a C¹, conservative continuation below eps V0
    (docs/model.md §1). ``volume`` and ``params.nmol`` are (O,) or batched (O, B)."""
    v0 = _per_object(topo.rest_volume, volume)
    return params.nmol * (GAS_CONSTANT * temperature) / jnp.maximum(volume, VOLUME_EPS * v0)


def pressure_slopes(topo, params, volume, temperature):
    """(P, dP/dV, dP/dnmol) of :func:`pressure` at ``volume``: dP/dV = -P/V above the clamp, 0 on
    it (halved at a tie, as the derivative of jnp.maximum), dP/dnmol = RT / max(V, eps V0)."""
    v_clamp = VOLUME_EPS * _per_object(topo.rest_volume, volume)
    v_safe = jnp.maximum(volume, v_clamp)
    p = pressure(topo, params, volume, temperature)
    dp = jnp.where(volume > v_clamp, -p / v_safe, jnp.where(volume == v_clamp, -0.5 * p / v_safe, 0.0))
    return p, dp, (GAS_CONSTANT * temperature) / v_safe


# --------------------------------------------------------------------------- air drag

def drag_force(gamma, mass, v):
    """Air drag on a vertex: -gamma m v (gamma in 1/s, per-vertex mass m)."""
    return -(gamma * mass) * v


def drag_vjp(gamma, v, a_bar):
    """The drag's transpose in the acceleration a += -gamma v: (its velocity cotangent
    -gamma a_bar, the gamma density -v.a_bar per vertex, summed over vertices and steps)."""
    return -gamma * a_bar, -jnp.sum(v * a_bar, axis=0)


# --------------------------------------------------------------------------- smooth floor

#: Default smooth-floor stiffness: k_f = FLOOR_KAPPA * 2 n_max k_structural per vertex (the same rule
#: as the soft-soft contact's default, jaxplush.model.contact): it raises omega_max² by about 10% at most.
FLOOR_KAPPA = 0.1


def smooth_floor_stiffness(cfg, k_structural):
    """k_f of every object (N/m per vertex): the fixed ``floor_stiffness`` or FLOOR_KAPPA 2 n_max k.

    ``k_structural`` is (O,) or (O, B) (a batch of parameter points), one value per object (of a
    stiffness field, :func:`jaxplush.model.layout.object_stiffness`); the result has its shape."""
    k = jnp.asarray(k_structural)
    if cfg.stiffness is not None:
        return jnp.full_like(k, cfg.stiffness)
    factor = jnp.asarray([FLOOR_KAPPA * 2.0 * n for n in cfg.n_max], k.dtype).reshape((-1,) + (1,) * (k.ndim - 1))
    return factor * k


def smooth_floor_push(y, height, k_f, beta):
    """Upward force (N) of the smooth floor on vertices at heights y: k_f phi sigmoid(-beta s),
    phi = softplus(-beta s) / beta, s = y - height (elementwise; any matching shapes)."""
    z = -beta * (y - height)
    return k_f * (jax.nn.softplus(z) / beta) * jax.nn.sigmoid(z)


def _smooth_floor_fields(topo, cfg, params, y):
    k = object_stiffness(topo, params.k_structural)
    beta = per_vertex(topo, _per_object(cfg.beta, k).astype(y.dtype))
    k_f = per_vertex(topo, smooth_floor_stiffness(cfg, k))
    return beta, k_f, jnp.asarray(cfg.height, y.dtype)


def smooth_floor_force(topo, cfg, params, y):
    """Upward force of the smooth floor (:class:`jaxplush.model.forces.SmoothFloor` ``cfg``) on
    every vertex at heights y: (V,), or (V, B) with batched (O, B) parameters; N."""
    beta, k_f, height = _smooth_floor_fields(topo, cfg, params, y)
    return smooth_floor_push(y, height, k_f, beta)


def smooth_floor_energy(topo, cfg, params, y):
    """Total energy (J) of the smooth floor at heights y (V,): sum of k_f/2 (softplus(-beta s)/beta)²."""
    beta, k_f, height = _smooth_floor_fields(topo, cfg, params, y)
    phi = jax.nn.softplus(-beta * (y - height)) / beta
    return jnp.sum(0.5 * k_f * phi * phi)


# --------------------------------------------------------------------------- registry

@dataclasses.dataclass(frozen=True)
class TermSpec:
    """One switch of :class:`jaxplush.model.forces.Terms` (or ``contact_friction``, which
    ``Terms.names()`` adds): where the term is defined and which engines run it.

    Attributes:
      name: the Terms field (as in ``Terms.names()``).
      forward: where its forward is written (module.function).
      batched: :mod:`jaxplush.stepping.batched` implements it.
      adjoint: the fused adjoint of :mod:`jaxplush.stepping.adjoint` implements its transpose.
    """

    name: str
    forward: str
    batched: bool
    adjoint: bool


#: Every term, once. A Terms field without an entry fails tests/test_terms.py; an engine refuses a
#: scene that switches on a term whose entry does not list it (before anything is traced).
REGISTRY = (
    TermSpec("spring", "jaxplush.model.terms.spring_weight", batched=True, adjoint=True),
    TermSpec("dashpot", "jaxplush.model.terms.dashpot_weight", batched=True, adjoint=True),
    TermSpec("drag", "jaxplush.model.terms.drag_force", batched=True, adjoint=True),
    TermSpec("gas", "jaxplush.model.terms.pressure", batched=True, adjoint=True),
    TermSpec("gravity", "jaxplush.stepping.integrators.System.accel", batched=True, adjoint=True),
    TermSpec("floor", "jaxplush.stepping.constraints.landing_velocity", batched=True, adjoint=True),
    TermSpec("fixed", "jaxplush.stepping.constraints.make_constrain", batched=True, adjoint=True),
    TermSpec("verlet_damping", "jaxplush.stepping.integrators.damping_keep", batched=True, adjoint=True),
    TermSpec("contact", "jaxplush.model.contact.make_contact", batched=True, adjoint=True),
    TermSpec("contact_friction", "jaxplush.model.contact.make_contact", batched=True, adjoint=False),
    TermSpec("floor_friction", "jaxplush.stepping.constraints.make_constrain", batched=True, adjoint=False),
    TermSpec("floor_restitution", "jaxplush.stepping.constraints.make_constrain", batched=True, adjoint=False),
    TermSpec("floor_smooth", "jaxplush.model.terms.smooth_floor_force", batched=True, adjoint=False),
    TermSpec("driven", "jaxplush.stepping.constraints.Drive", batched=True, adjoint=True),
    TermSpec("k_field", "jaxplush.model.layout.edge_stiffness", batched=True, adjoint=True),
)


def supported(engine):
    """frozenset of the term names that ``engine`` ("batched" or "adjoint") implements."""
    return frozenset(s.name for s in REGISTRY if getattr(s, engine))


def unsupported(terms, engine):
    """The names of the terms ``terms`` (a Terms) switches on that ``engine`` does not implement."""
    have = supported(engine)
    return [n for n in terms.names() if n not in have]
