"""The fused adjoint of the damped Verlet step: the reverse sweep of a rollout within a memory budget.

The gradient of :func:`jaxplush.rollout` (:mod:`jaxplush.stepping.rollouts`) and of
``jaxplush.fitting.objective.gradients.rollout_loss`` both run on this module: a forward pass that records
the states (:func:`plan`, :func:`recorder`: every step's if they fit in the memory budget, else a
checkpoint every ``seg`` steps), then :func:`backward`, one fused backward kernel per step
(:func:`_make_step_dens_vjp`, assembled from the terms' ``*_vjp`` functions in
:mod:`jaxplush.model.terms`) that adds a saved frame's position cotangent where one lies and
accumulates per-vertex parameter densities, reduced to a Params cotangent once at the end
(:func:`_reduce_dens`). Supported: springs (per object or an (E,) per-edge field), gas, gravity,
Verlet damping, dashpot, drag, the projection floor, pins, driven vertices and soft-soft contact
without friction (:data:`_ADJOINT_TERMS`, from :data:`jaxplush.model.terms.REGISTRY`); the
Verlet integrator with one substep (:func:`adjoint_supported`).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxplush.stepping import integrators
from jaxplush.model import forces as model
from jaxplush.model import terms as T
from jaxplush.types import Params, State

#: Bytes the adjoint may spend keeping every step's state from the forward pass; beyond this it
#: keeps checkpoints and recomputes one segment at a time in the backward pass.
DEFAULT_MEMORY_BUDGET = 512 * 2 ** 20


def _segment_length(segment, n_steps):
    if segment is None:
        return max(1, math.isqrt(max(n_steps, 1)))
    segment = int(segment)
    if segment < 1:
        raise ValueError(f"segment must be >= 1, got {segment}")
    return segment


#: Terms the fused adjoint implements (:data:`jaxplush.model.terms.REGISTRY`, ``adjoint``).
_ADJOINT_TERMS = T.supported("adjoint")


def _ring_sum(a):
    """Sum of a (K, V) array over the ring axis as K - 1 row additions. XLA's CPU backend lowers
    ``jnp.sum(a, axis=0)`` over this short leading axis to a reduction kernel that costs more than
    the elementwise work around it; row additions fuse into their producers instead."""
    out = a[0]
    for r in range(1, a.shape[0]):
        out = out + a[r]
    return out


def _around(term, *vectors):
    """sum_k term(a_k, b_{k+1}, c_k, d_{k+1}, ...) around the ring (wrapping): ``vectors`` are lists
    of three (K, V) arrays, taken at slot k in even positions and at the next slot k + 1 in odd
    ones, by static row slices rather than a materialised ``jnp.roll``. ``term`` is
    :func:`jaxplush.model.terms.fan` (a, b) or :func:`jaxplush.model.terms.fan_tangent` (d, d, delta, delta)."""
    inner = term(*([v[:-1] for v in a] if i % 2 == 0 else [v[1:] for v in a] for i, a in enumerate(vectors)))
    wrap = term(*([v[-1] for v in a] if i % 2 == 0 else [v[0] for v in a] for i, a in enumerate(vectors)))
    return [_ring_sum(p) + q for p, q in zip(inner, wrap)]


class _Dens(NamedTuple):
    """One backward step's parameter cotangents, kept per vertex where they are sums over vertices of
    per-vertex terms (reduced once, at the end of the backward pass): ``k`` (V,) with
    k_bar = per_object_sum(k), or (K, V) per ring slot for a per-edge stiffness field (reduced per
    edge: each edge's two slots summed); ``c`` (V,) the dashpot's; ``damp`` (V,) sum of u.u_bar (the damping
    factor's cotangent is minus its per-object sum); ``drag`` (V,) the drag's density -u.a_bar
    (:func:`jaxplush.model.terms.drag_vjp`); ``nmol`` (O,) the
    gas's nmol cotangent; ``f_gas`` (O,) the gas's and contact's share of sum F.lam (for the mass
    cotangent; the springs' and dashpot's shares are k k_bar and c c_bar); ``extra`` contact's
    Params or None."""

    k: object
    c: object
    damp: object
    drag: object
    nmol: object
    f_gas: object
    extra: object


def _make_force_vjp(topo, terms, temperature):
    """``force_vjp(params, x, u, lam) -> (jx, ju, dens)``: the transposed linearisation of the
    internal force F = F(x, u; k, c, nmol) (springs, dashpot, gas, contact; (3, V) arrays) for a
    cotangent ``lam`` (3, V): J_x^T lam, J_u^T lam and the parameter cotangents as a
    :class:`_Dens` (``damp`` and ``drag`` None: they belong to the integrator).

    Assembled in the one-ring form of :func:`jaxplush.model.forces.make_force_fn` from each
    term's transpose, written beside its forward in :mod:`jaxplush.model.terms`
    (:func:`~jaxplush.model.terms.spring_vjp`, :func:`~jaxplush.model.terms.dashpot_vjp`,
    :func:`~jaxplush.model.terms.fan_tangent` and :func:`~jaxplush.model.terms.pressure_slopes`
    for the gas: J_x^T lam = P H_V lam + P'(V) (g.lam) g). Every term is a gather of a
    neighbour's value minus the vertex's own, so the transpose needs gathers only, never a
    scatter-add. The forces are linear in k, c and nmol, so their cotangents are sums the pass
    computes anyway (the terms' densities, reduced per object at the end of the backward pass).
    """
    ring = np.ascontiguousarray(topo.ring.T)                  # (K, V), neighbour-major
    mask = np.ascontiguousarray(topo.ring_mask.T)
    ring_rest = np.ascontiguousarray(topo.ring_rest.T)
    all_real = bool(mask.all())
    contact_force = None
    if terms.contact:
        from jaxplush.model import contact as _contact
        contact_force = _contact.make_contact_force(topo, terms.contact)

    def gather(a):
        return a.at[ring].get(mode="promise_in_bounds")

    def masked(a):
        return a if all_real else jnp.where(mask, a, 0.0)

    def force_vjp(params, x, u, lam):
        dtype = x.dtype
        rest = jnp.asarray(ring_rest, dtype)
        d = [gather(x[c]) - x[c] for c in range(3)]                      # 3 x (K, V)
        dl = [gather(lam[c]) - lam[c] for c in range(3)]
        inv_l = T.inv_length(d, model.length_eps2(topo, dtype))
        t = masked(T.dot(d, dl))
        w, coef, dens = T.spring_vjp(model.ring_stiffness(topo, params.k_structural), rest, inv_l, t)
        # k's density: per vertex (V,), reduced per object at the end; for a per-edge field kept per
        # ring slot (K, V) (masked slots are zero: t is) and reduced per edge at the end
        dens_k = dens if model.is_field(topo, params.k_structural) else _ring_sum(dens)
        zero = jnp.zeros((topo.n_objects,), dtype)
        dens_c = extra = None
        n_bar = f_gas = zero
        ju = jnp.zeros_like(x)
        if terms.dashpot:
            dv = [gather(u[c]) - u[c] for c in range(3)]
            w_c, coef_c, ct, dens = T.dashpot_vjp(model.per_vertex(topo, params.dashpot), dv, d, inv_l, t)
            w, coef, dens_c = w + w_c, coef + coef_c, _ring_sum(dens)
            ju = jnp.stack([_ring_sum(ct * d[i]) for i in range(3)])
            extra = [ct * dv[i] for i in range(3)]
        w = masked(w)
        ctt = coef * t
        jx = jnp.stack([_ring_sum(w * dl[i] + ctt * d[i] + (extra[i] if extra else 0.0)) for i in range(3)])
        if terms.gas:
            jx_p, jx_dp, n_bar, f_gas = _gas_vjp(topo, params, x, lam, d, dl, temperature)
            jx = jx + jx_p + jx_dp
        p_extra = None
        if contact_force is not None:
            # soft-soft contact (jaxplush.model.contact, -grad of a penalty energy on candidate lists):
            # its own VJP, parameters included.
            fc, vjp_c = jax.vjp(contact_force, params, x)
            p_extra, jxc = vjp_c(lam)
            jx = jx + jxc
            f_gas = f_gas + model.per_object_sum(topo, jnp.sum(fc * lam, axis=0))
        return jx, ju, _Dens(dens_k, dens_c, None, None, n_bar, f_gas, p_extra)

    return force_vjp


def _gas_vjp(topo, params, x, lam, d, dl, temperature):
    """The gas's share of :func:`_make_force_vjp`: J_x^T lam as its two terms P H_V lam and
    P'(V) (g.lam) g, the nmol cotangent and the gas's share of sum F.lam per object."""
    # stacked, then scaled: one fusion (scaling the three rows apart is measurably slower)
    g = T.volume_gradient(jnp.stack(_around(T.fan, d, d)))
    h = T.volume_gradient(jnp.stack(_around(T.fan_tangent, d, d, dl, dl)))
    volume = T.object_volumes(topo, x, g)
    p, dp, dp_dn = T.pressure_slopes(topo, params, volume, temperature)
    g_lam = model.per_object_sum(topo, jnp.sum(g * lam, axis=0))  # dV.lam per object
    return (model.per_vertex(topo, p) * h, model.per_vertex(topo, dp * g_lam) * g, g_lam * dp_dn, p * g_lam)


_Y_ROW = np.arange(3)[:, None] == 1                # (3, 1): the vertical component


def _make_step_dens_vjp_parts(sim):
    """``(head, tail)``: the two halves of :func:`_make_step_dens_vjp`. ``head(params, x_next,
    x_bar, u_bar, k) -> (x_out, ut, lam)`` takes the cotangents of the new state through the pins,
    the driven vertices and the floor to the cotangent ``lam`` of the internal force;
    ``tail(params, x, u, x_out, ut, lam) -> (x_bar, u_bar, dens)`` transposes the force and the
    integrator's damping. The reverse sweep computes each step's head at the end of the step
    before it, so ``lam`` enters the force's gathers as a loop buffer: fused into them, the
    head's masks were recomputed for every gathered neighbour (2x the backward's time with a
    floor and a dashpot; benchmarks/RESULTS.md).

    The VJP itself, ``step_vjp(params, x, u, x_next, x_bar, u_bar) -> (x_bar, u_bar, dens)``, of
    ``sim.internal.step`` at the state (x, u) (internal (3, V) layout), given the positions
    ``x_next`` it produced, with the parameter cotangents as per-vertex densities
    (:class:`_Dens`, reduced by :func:`_reduce_dens`). The step (jaxplush.stepping.step, verlet):

        a  = F(x, u)/m - drag u + g;   u' = (1 - f) u + a dt;   x' = x + u' dt;
        floor (y >= H): below = x'_y < H  ->  u'_y = (H - x_y)/dt, x'_y = H;  pins: x' = x0, u' = 0;
        driven (in step k): x' = p(t_{k+1}), u' = (p(t_{k+1}) - p(t_k))/dt, constants.

    The floor, pins and driven vertices are masks (``k``, the step index, is read only with
    driven vertices that have a release time); ``below`` is read off ``x_next`` (projected vertices lie
    exactly on the floor), so no primal force needs recomputing.
    """
    topo, terms, dt = sim.topology, sim.terms, sim.h
    force_vjp = _make_force_vjp(topo, terms, sim.scene.temperature)
    floor = sim.scene.floor
    free = np.ones(topo.n_vertices)
    free[topo.fixed] = 0.0
    drive = None
    if terms.driven:
        from jaxplush.stepping.constraints import Drive
        drive = Drive(sim.scene, dt)

    def head(params, x_next, x_bar, u_bar, k=None):
        dtype = x_next.dtype
        if terms.fixed or terms.driven:
            # pinned and driven vertices: their new position and velocity are constants
            keep = jnp.asarray(free, dtype)
            if drive is not None:
                keep = keep * drive.free(k, topo.n_vertices, dtype)
            x_bar, u_bar = x_bar * keep, u_bar * keep
        x_out = x_bar
        if terms.floor:
            # (3, V) masks rather than row updates: one elementwise fusion, no dynamic-update-slice
            below = (x_next[1] <= floor)[None] & _Y_ROW
            uy = u_bar[1][None]
            x_bar = jnp.where(below, 0.0, x_bar)
            u_bar = jnp.where(below, 0.0, u_bar)
            x_out = x_bar + jnp.where(below, -uy / dt, 0.0)
        ut = u_bar + dt * x_bar                                  # cotangent of u' (before x' = x + u' dt)
        lam = dt * ut / model.vertex_mass(topo, params)          # cotangent of the internal force
        return x_out, ut, lam

    def tail(params, x, u, x_out, ut, lam):
        jx, ju, dens = force_vjp(params, x, u, lam)
        if terms.verlet_damping:
            fd = model.per_vertex(topo, _damping_factor(params.damping))
            u_out = (1.0 - fd) * ut + ju
            dens = dens._replace(damp=jnp.sum(u * ut, axis=0))
        else:
            u_out = ut + ju
        if terms.drag:
            u_drag, drag_density = T.drag_vjp(model.per_vertex(topo, params.drag), u, dt * ut)
            u_out = u_out + u_drag
            dens = dens._replace(drag=drag_density)
        return x_out + jx, u_out, dens

    return head, tail


def _make_step_dens_vjp(sim):
    """``step_vjp(params, x, u, x_next, x_bar, u_bar, k=None) -> (x_bar, u_bar, dens)``: one
    step's VJP (:func:`_make_step_dens_vjp_parts`), its two halves in one call."""
    head, tail = _make_step_dens_vjp_parts(sim)

    def step_vjp(params, x, u, x_next, x_bar, u_bar, k=None):
        return tail(params, x, u, *head(params, x_next, x_bar, u_bar, k))

    return step_vjp


def _reduce_dens(topo, params, dens):
    """Params cotangent from (sums over steps of) :class:`_Dens` densities."""
    zero = jnp.zeros_like(params.total_weight)

    def obj(a):
        return zero if a is None else model.per_object_sum(topo, a)

    k = params.k_structural
    field = model.is_field(topo, k)
    if field:
        # each edge is two ring slots, one from each end: the sum of their densities
        slot_edge = np.ascontiguousarray(topo.ring_edge.T).reshape(-1)
        k_bar = jax.ops.segment_sum(dens.k.reshape(-1), slot_edge, num_segments=topo.n_edges)
    else:
        k_bar = obj(dens.k)
    c_bar = obj(dens.c)
    d_bar = zero
    if dens.damp is not None:
        d_bar = jax.vjp(_damping_factor, params.damping)[1](-obj(dens.damp))[0]
    if field:                                   # sum F.lam of the springs, per object
        kk = k * k_bar
        f_dot_k = jnp.stack([jnp.sum(kk[a:b]) for a, b in topo.edge_slices])
    else:
        f_dot_k = k * k_bar
    f_dot = f_dot_k + params.dashpot * c_bar + dens.f_gas
    p_bar = Params(k_structural=k_bar, damping=d_bar, dashpot=c_bar, drag=obj(dens.drag), nmol=dens.nmol,
                   total_weight=-f_dot / params.total_weight)
    if dens.extra is not None:
        p_bar = jax.tree_util.tree_map(jnp.add, p_bar, dens.extra)
    return p_bar


def _make_step_vjp(sim):
    """``step_vjp(params, x, u, x_next, x_bar, u_bar) -> (x_bar, u_bar, params_bar)``: one step's
    VJP (:func:`_make_step_dens_vjp`) with its parameter cotangents reduced to a Params."""
    step_vjp = _make_step_dens_vjp(sim)

    def f(params, x, u, x_next, x_bar, u_bar, k=None):
        x_bar, u_bar, dens = step_vjp(params, x, u, x_next, x_bar, u_bar, k)
        return x_bar, u_bar, _reduce_dens(sim.topology, params, dens)

    return f


_damping_factor = integrators.damping_factor


class _Plan(NamedTuple):
    """Static layout of an adjoint rollout: ``n_seg`` segments of ``seg`` steps (the last one
    possibly shorter); ``store``: every state is kept from the forward pass (one segment), else
    each segment is recomputed from its checkpoint in the backward pass; ``keep_u``: the
    velocities are kept: the backward pass needs them (dashpot, drag or Verlet damping), or a
    recomputed segment restarts from its checkpoint's velocity (always, unless ``store``)."""

    n_steps: int
    seg: int
    n_seg: int
    store: bool
    keep_u: bool


def _plan(sim, n_steps, segment, memory_budget, itemsize):
    t = sim.terms
    keep_u = bool(t.dashpot or t.drag or t.verlet_damping)
    per_step = (2 if keep_u else 1) * 3 * sim.topology.n_vertices * itemsize
    if segment is None and n_steps * per_step <= memory_budget:
        return _Plan(n_steps, max(n_steps, 1), 1, True, keep_u)
    if segment is None:
        # Fewest recomputed-segment states plus checkpoints: seg ~ sqrt(n_steps).
        segment = max(1, math.isqrt(n_steps))
    seg = min(_segment_length(segment, n_steps), max(n_steps, 1))
    # recomputing a segment steps on from its checkpoint's state, velocity included
    return _Plan(n_steps, seg, -(-n_steps // seg), False, True)


def _recorder(plan):
    """``record(bufs, n, s)``: keep state ``n`` (every one, or the first of each segment, the
    others into a scratch slot) in the (positions, velocities or None) buffers."""
    seg, n_seg = plan.seg, plan.n_seg

    def record(bufs, n, s):
        if plan.store:
            i = n
        else:
            i = jnp.where(n % seg == 0, n // seg, n_seg)
        xs, us = bufs
        xs = jax.lax.dynamic_update_index_in_dim(xs, s.x, i, 0)
        if plan.keep_u:
            us = jax.lax.dynamic_update_index_in_dim(us, s.v, i, 0)
        return xs, us

    return record


def _state_buffers(plan, shape, dtype):
    """Zeroed (positions, velocities or None) buffers for :func:`_recorder`: every state, or one
    checkpoint per segment and a scratch slot."""
    n_buf = plan.n_steps + 1 if plan.store else plan.n_seg + 1
    return jnp.zeros((n_buf,) + shape, dtype), jnp.zeros((n_buf,) + shape, dtype) if plan.keep_u else None


def _zero_dens(sim, params, dtype):
    """Zero :class:`_Dens` accumulators for the terms the simulator has."""
    topo, terms = sim.topology, sim.terms
    per_v = jnp.zeros((topo.n_vertices,), dtype)
    per_o = jnp.zeros((topo.n_objects,), dtype)
    per_k = jnp.zeros(topo.ring.T.shape, dtype) if model.is_field(topo, params.k_structural) else per_v
    return _Dens(per_k, per_v if terms.dashpot else None, per_v if terms.verlet_damping else None,
                 per_v if terms.drag else None, per_o, per_o,
                 jax.tree_util.tree_map(jnp.zeros_like, params) if terms.contact else None)


def _read_state(plan, buf_x, buf_u, i):
    """State ``i`` of the buffers: (x, u), u = x as a placeholder where velocities are not kept."""
    x = jax.lax.dynamic_index_in_dim(buf_x, i, keepdims=False)
    u = jax.lax.dynamic_index_in_dim(buf_u, i, keepdims=False) if plan.keep_u else x
    return x, u


def _reverse_steps(parts, params, add_frame, step0=None, ahead=True):
    """``reverse(carry, states, first, last)``: reverse steps last, ..., first + 1, with
    ``states(n)`` -> (x_n, u_n) for first <= n <= last; carry (x_bar, u_bar, dens). ``parts``:
    the step VJP's (head, tail) (:func:`_make_step_dens_vjp_parts`). Two things are read one
    iteration ahead into the loop's carry, so that XLA gathers from loop buffers rather than
    fusing their producers into every gather (faster; see benchmarks/RESULTS.md): the state a
    step's VJP needs (not a dynamic slice of the stored trajectory), and the step's head (the
    force's cotangent, not the floor's masks recomputed per neighbour). ``ahead`` False computes
    each head in its own step: cheaper where the head is a few multiplications (no floor, pins or
    driven vertices). ``step0``: the step index of state 0 (scenes with driven vertices; None
    otherwise)."""
    head, tail = parts

    def prepare(x_bar, u_bar, x_next, n):
        # the head of step n (state n - 1 -> n): the frame's cotangent added first
        k = None if step0 is None else n - 1 + step0      # driven vertices only: the step index
        return head(params, x_next, add_frame(x_bar, n), u_bar, k)

    def reverse(carry, states, first, last):
        x_bar, u_bar, dens = carry
        if not ahead:
            def body_here(i, inner):
                (x_bar, u_bar, dens), x_next, x, u = inner
                n = last - i                          # reverses step n: state n - 1 -> state n
                x_bar, u_bar, d = tail(params, x, u, *prepare(x_bar, u_bar, x_next, n))
                dens = jax.tree_util.tree_map(jnp.add, dens, d)
                return ((x_bar, u_bar, dens), x) + states(jnp.maximum(n - 2, first))

            init = ((x_bar, u_bar, dens), states(last)[0]) + states(last - 1)
            return jax.lax.fori_loop(0, last - first, body_here, init)[0]

        def body(i, inner):
            (x_bar, u_bar, dens, h), x, u = inner
            n = last - i                              # reverses step n: state n - 1 -> state n
            x_bar, u_bar, d = tail(params, x, u, *h)
            dens = jax.tree_util.tree_map(jnp.add, dens, d)
            h = prepare(x_bar, u_bar, x, n - 1)       # step n - 1's head (unused after the last)
            return ((x_bar, u_bar, dens, h),) + states(jnp.maximum(n - 2, first))

        init = ((x_bar, u_bar, dens, prepare(x_bar, u_bar, states(last)[0], last)),) + states(last - 1)
        out = jax.lax.fori_loop(0, last - first, body, init)
        return out[0][:3]

    return reverse


def _reverse_segments(sim, plan, params, reverse, carry, xs, us, step0=0):
    """The backward pass segment by segment, last first: each segment's states recomputed from
    its checkpoint (in (seg + 1) buffers), then its steps reversed."""
    seg, n_steps = plan.seg, plan.n_steps
    shape, dtype = carry[0].shape, carry[0].dtype

    def recompute(k):
        """States first, ..., last of segment k, from its checkpoint, in (seg + 1) buffers."""
        first = k * seg
        last = jnp.minimum(first + seg, n_steps)
        s0 = State(*_read_state(plan, xs, us, k))
        bx = jnp.zeros((seg + 1,) + shape, dtype).at[0].set(s0.x)
        bu = jnp.zeros((seg + 1,) + shape, dtype).at[0].set(s0.v) if plan.keep_u else None

        def body(i, c):
            s, bx, bu = c
            s = sim.internal.step(params, s, (first + i + (step0 - 1)) if sim.terms.driven else None)
            bx = jax.lax.dynamic_update_index_in_dim(bx, s.x, i, 0)
            if plan.keep_u:
                bu = jax.lax.dynamic_update_index_in_dim(bu, s.v, i, 0)
            return s, bx, bu
        _, bx, bu = jax.lax.fori_loop(1, last - first + 1, body, (s0, bx, bu))
        return first, last, bx, bu

    def back_segment(carry, k):
        first, last, bx, bu = recompute(k)
        return reverse(carry, lambda n: _read_state(plan, bx, bu, n - first), first, last), None

    carry, _ = jax.lax.scan(back_segment, carry, jnp.arange(plan.n_seg), reverse=True)
    return carry


def backward(sim, plan, params, bufs, add_frame, x_bar, u_bar, step0=0):
    """The reverse sweep of a recorded rollout: ``(params_bar, x0_bar, u0_bar)``.

    ``bufs``: the forward's (positions, velocities or None) state buffers (:func:`_state_buffers`,
    filled by :func:`_recorder`, the final state included when ``plan.store``); ``x_bar``,
    ``u_bar``: the cotangents of the final state (x, u) on the internal (3, V) layout (zeros for a
    loss on frames alone); ``add_frame(x_bar, n)``: ``x_bar`` plus the cotangent of the positions
    at step n (a saved frame's, or nothing), called for n = n_steps, ..., 0 before each step is
    reversed. The steps are reversed over the stored states, or segment by segment from their
    checkpoints (:func:`_reverse_segments`); the densities are reduced to a Params cotangent at
    the end. ``step0``: the step index of state 0 (read by scenes with driven vertices only; may
    be traced)."""
    xs, us = bufs
    dtype = x_bar.dtype
    t = sim.terms
    ahead = bool(t.floor or t.fixed or t.driven)        # a head with masks: computed a step ahead
    reverse = _reverse_steps(_make_step_dens_vjp_parts(sim), params, add_frame, step0 if t.driven else None,
                             ahead=ahead)
    carry = (x_bar, u_bar, _zero_dens(sim, params, dtype))
    if plan.store:
        carry = reverse(carry, lambda n: _read_state(plan, xs, us, n), 0, plan.n_steps)
    else:
        carry = _reverse_segments(sim, plan, params, reverse, carry, xs, us, step0)
    x_bar, u_bar, dens = carry
    return _reduce_dens(sim.topology, params, dens), add_frame(x_bar, 0), u_bar


def _batch_linear_call(axis_data, args, dims, *, callee, transpose_thunk, num_callee_consts, num_res):
    """A batching rule for ``jax.custom_derivatives.linear_call``, which jax 0.10.2 lacks (so that
    ``jax.vmap`` of :func:`jaxplush.rollout`'s gradient works): the same linear call of the
    vmapped function and the vmapped transpose, every linear input and output batched on axis 0."""
    from jax.custom_derivatives import linear_call
    from jax.extend import core as jex_core
    from jax._src.interpreters import batching

    n_res = num_callee_consts + num_res
    moved = [a if d is None else batching.moveaxis(a, d, 0) for a, d in zip(args, dims)]
    res, lin = moved[:n_res], moved[n_res:]
    res_axes = [None if d is None else 0 for d in dims[:n_res]]
    lin = [a if d is not None else batching.broadcast(a, axis_data.size, 0, None) for a, d in zip(lin, dims[n_res:])]

    def fun(r, x):
        return jax.vmap(lambda r, x: jex_core.jaxpr_as_fun(callee)(*r, *x), in_axes=(res_axes, 0))(r, x)

    def fun_transpose(r, ct):
        # the transpose takes its own constants, then the residuals without the callee's constants
        jaxpr, consts = transpose_thunk()
        k = num_callee_consts
        return jax.vmap(lambda r, c: jex_core.jaxpr_as_fun(jaxpr)(*consts, *r, *c),
                        in_axes=(res_axes[k:], 0))(r[k:], ct)

    out = linear_call(fun, fun_transpose, res, lin)
    return out, [0] * len(out)


def _register_linear_call_rules():
    """Install :func:`_batch_linear_call` unless this jax has a rule of its own, and make the
    derivative of a linear call with respect to its residuals (a second derivative of
    :func:`jaxplush.rollout`: ``jax.hessian``, forward over reverse) a clear error rather than
    jax's bare ``AssertionError``. Nothing is installed where jax's internals differ."""
    try:
        from jax._src.custom_derivatives import linear_call_p
        from jax._src.interpreters import ad, batching
    except ImportError:                                # pragma: no cover - another jax's layout
        return
    if linear_call_p not in batching.fancy_primitive_batchers:
        batching.fancy_primitive_batchers[linear_call_p] = _batch_linear_call
    rule = ad.primitive_jvps.get(linear_call_p)
    if rule is None or getattr(rule, "_jaxplush", False):
        return

    def jvp(primals, tangents, **params):
        n_res = params["num_callee_consts"] + params["num_res"]
        if not all(type(t) is ad.Zero for t in tangents[:n_res]):
            raise NotImplementedError(
                "a second derivative of jaxplush.rollout (jax.hessian, or any derivative of a derivative) does not "
                "go through its fused adjoint; pass gradient='autodiff' to rollout for one")
        return rule(primals, tangents, **params)
    jvp._jaxplush = True
    ad.primitive_jvps[linear_call_p] = jvp


_register_linear_call_rules()


def adjoint_supported(sim):
    """Whether the fused adjoint supports this simulator (its integrator and compiled terms)."""
    return (sim.integrator == "verlet" and sim.substeps == 1
            and set(sim.terms.names()) <= _ADJOINT_TERMS)

