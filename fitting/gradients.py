"""Losses over rollouts and their gradients within bounded memory.

``rollout_loss(sim, params, state0, frame_steps, loss_fn, aux)`` runs the simulator from
``state0`` to step ``frame_steps[-1]`` and returns

    loss = sum_j loss_fn(x_j, aux_j),   x_j: (V, 3) positions at step frame_steps[j],

a scalar that ``jax.grad`` / ``jax.value_and_grad`` differentiate with respect to ``params``,
``state0`` (and ``aux`` or arrays ``loss_fn`` closes over), inside or outside ``jax.jit``.
Methods (all give the same value and gradient up to rounding; tests/test_gradients.py):

* ``"plain"``: reverse-mode autodiff through one ``lax.scan``; memory grows with every step's
  residuals (about 1 MB per step at 2562 vertices). The reference.
* ``"checkpoint"``: autodiff with two levels of ``jax.checkpoint``: segments of ``segment``
  steps are recomputed from their first state, and inside a segment only each step's input is
  kept. Memory: (steps/segment + segment) states. Any integrator (``sim.internal.step``).
* ``"adjoint"``: a hand-written adjoint of the damped Verlet step (``jax.custom_vjp``), one
  fused backward kernel per step (:func:`_make_force_vjp`). The forward pass keeps every step's
  positions (and velocities when dashpot, drag or Verlet damping need them) if that fits in
  ``memory_budget`` bytes, else it keeps a checkpoint every ``segment`` steps and recomputes one
  segment at a time; it also evaluates each frame loss's own gradient as it passes the frame
  and keeps it (one (V, 3) array per frame, plus the cotangents of ``aux``), so the backward
  pass is a plain loop of step VJPs. Supports springs, gas, gravity, Verlet damping, dashpot,
  drag, the floor, pins and soft-soft contact; not floor friction/restitution or substeps > 1.
* ``"auto"``: ``"adjoint"`` where supported (:func:`adjoint_supported`), else ``"checkpoint"``.

Soft-soft contact: the step searches its candidates afresh; a search that overflows the contact
capacity gives a finite but inexact force (:mod:`jaxplush.model.contact`), so every method also checks
the positions each step starts from and returns a NaN loss when one overflowed (``nan_on_overflow``), which
``fitting.fit`` takes as the signal to raise the capacity.

Cost: benchmarks/bench_fit.py compares the adjoint's value_and_grad with the forward loss and
the checkpointed autodiff (figures in benchmarks/RESULTS.md). Memory: unsegmented, the adjoint
stores steps x V x 3 positions (10,000 steps at 2562 vertices in float32: about 300 MB).
"""

from __future__ import annotations

import math
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxplush.stepping import integrators
from jaxplush.model import forces as model
from jaxplush.model import terms as T
from jaxplush.types import Params, State

METHODS = ("auto", "plain", "checkpoint", "adjoint")

#: Bytes the adjoint may spend keeping every step's state from the forward pass; beyond this it
#: keeps checkpoints and recomputes one segment at a time in the backward pass.
DEFAULT_MEMORY_BUDGET = 512 * 2 ** 20


# --------------------------------------------------------------------------- validation

def _frame_table(frame_steps):
    """Validate ``frame_steps`` (static) and return (steps tuple, (N+1,) int32 frame index or -1)."""
    try:
        steps = tuple(int(s) for s in frame_steps)
    except TypeError as e:
        raise TypeError(f"frame_steps must be a static sequence of ints, got {frame_steps!r}") from e
    if any(s != f for s, f in zip(steps, frame_steps)):
        raise ValueError(f"frame_steps must be integers, got {frame_steps!r}")
    if not steps:
        raise ValueError("frame_steps is empty: at least one frame is needed")
    if steps[0] < 0:
        raise ValueError(f"frame_steps must be >= 0, got {steps[0]}")
    if any(b <= a for a, b in zip(steps, steps[1:])):
        raise ValueError(f"frame_steps must be strictly increasing, got {steps}")
    table = np.full(steps[-1] + 1, -1, np.int32)
    table[list(steps)] = np.arange(len(steps), dtype=np.int32)
    return steps, table


def _check_aux(aux, n_frames):
    for leaf in jax.tree_util.tree_leaves(aux):
        shape = np.shape(leaf)
        if not shape or shape[0] != n_frames:
            raise ValueError(f"every aux leaf needs a leading axis of length len(frame_steps) = {n_frames}, "
                             f"got shape {shape}")


def _segment_length(segment, n_steps):
    if segment is None:
        return max(1, math.isqrt(max(n_steps, 1)))
    segment = int(segment)
    if segment < 1:
        raise ValueError(f"segment must be >= 1, got {segment}")
    return segment


def _take(aux, j):
    return jax.tree_util.tree_map(lambda a: a[j], aux)


# --------------------------------------------------------------------------- generic methods

def _overflow_check(sim, nan_on_overflow):
    """The soft-soft contact's fresh-search overflow check on internal positions (3, V) -> (O,)
    bool, or None (no contact between objects, or not asked for)."""
    return sim.internal.overflow if nan_on_overflow else None


def _nan_if(flag, dtype):
    """NaN where ``flag``, else 0, with no gradient: added to a loss it makes the value NaN and
    leaves the gradient as it is."""
    return jnp.where(flag, jnp.asarray(jnp.nan, dtype), jnp.zeros((), dtype))


def _step_index(sim, n, offset=0):
    """The step index the simulator's step reads: ``n + offset`` for a scene with driven vertices,
    None (nothing traced) otherwise."""
    return n + offset if sim.terms.driven else None


def _generic_loss(sim, params, state0, steps, table, loss_fn, aux, segment, checkpoint, check=None, step0=0):
    """Autodiff through the rollout: one scan over segments of ``segment`` steps (padded). With
    ``check`` (:func:`_overflow_check`) the loss is NaN where a step's contact candidates overflowed."""
    n_steps = steps[-1]
    state = sim.internal.to_internal(state0)

    def frame_loss(x, j):
        return loss_fn(x.T, _take(aux, j))

    loss0 = frame_loss(state[0], 0) if steps[0] == 0 else jnp.zeros((), state[0].dtype)
    if n_steps == 0:
        return loss0
    table_j = jnp.asarray(table)

    step = sim.internal.step
    if checkpoint:
        # Two levels: segments are recomputed from their first state, and inside a segment
        # only each step's input state is kept (residuals of a whole segment of steps cost
        # more memory traffic than recomputing one step; benchmarks/RESULTS.md).
        step = jax.checkpoint(step)

    def one_step(carry, n):
        s, acc, flag = carry
        if check is not None:
            flag = flag | (jnp.any(check(s[0])) & (n <= n_steps))
        # Steps past the horizon (padding of the last segment) leave the carry unchanged.
        s = jax.lax.cond(n <= n_steps, lambda s: step(params, s, _step_index(sim, n, step0 - 1)), lambda s: s, s)
        j = table_j[jnp.minimum(n, n_steps)]
        hit = (j >= 0) & (n <= n_steps)
        acc = acc + jax.lax.cond(hit, lambda: frame_loss(s[0], jnp.maximum(j, 0)).astype(acc.dtype),
                                 lambda: jnp.zeros((), acc.dtype))
        return (s, acc, flag), None

    seg = _segment_length(segment, n_steps) if checkpoint else n_steps
    n_seg = -(-n_steps // seg)

    def run_segment(carry, first):
        carry, _ = jax.lax.scan(one_step, carry, first + jnp.arange(1, seg + 1))
        return carry

    if checkpoint:
        run_segment = jax.checkpoint(run_segment)

    (_, loss, flag), _ = jax.lax.scan(lambda c, first: (run_segment(c, first), None),
                                      (state, loss0, jnp.zeros((), bool)),
                                      jnp.arange(n_seg) * seg)
    return loss + _nan_if(flag, jnp.result_type(loss)) if check is not None else loss


# --------------------------------------------------------------------------- fused adjoint (Verlet)

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
        inv_l = T.inv_length(d, topo.length_eps ** 2)
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


def _make_step_dens_vjp(sim):
    """``step_vjp(params, x, u, x_next, x_bar, u_bar) -> (x_bar, u_bar, dens)``: the VJP of
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

    def step_vjp(params, x, u, x_next, x_bar, u_bar, k=None):
        dtype = x.dtype
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
        a_bar = dt * ut
        mass = model.vertex_mass(topo, params)
        lam = a_bar / mass                                       # cotangent of the internal force
        jx, ju, dens = force_vjp(params, x, u, lam)
        if terms.verlet_damping:
            fd = model.per_vertex(topo, _damping_factor(params.damping))
            u_out = (1.0 - fd) * ut + ju
            dens = dens._replace(damp=jnp.sum(u * ut, axis=0))
        else:
            u_out = ut + ju
        if terms.drag:
            u_drag, drag_density = T.drag_vjp(model.per_vertex(topo, params.drag), u, a_bar)
            u_out = u_out + u_drag
            dens = dens._replace(drag=drag_density)
        return x_out + jx, u_out, dens

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


def _split(tree):
    """Leaves of ``tree`` that carry cotangents (inexact dtypes), and functions to rebuild the
    tree with them replaced and to build its cotangent (float0 zeros for the other leaves)."""
    leaves, treedef = jax.tree_util.tree_flatten(tree)
    idx = [i for i, a in enumerate(leaves) if jnp.issubdtype(jnp.result_type(a), jnp.inexact)]

    def rebuild(diff, like):
        """``like`` (a tree of ``tree``'s structure) with its differentiable leaves replaced."""
        out = jax.tree_util.tree_leaves(like)
        for i, a in zip(idx, diff):
            out[i] = a
        return jax.tree_util.tree_unflatten(treedef, out)

    def cotangent(diff_bar):
        out = [np.zeros(np.shape(a), jax.dtypes.float0) for a in leaves]
        for i, a in zip(idx, diff_bar):
            out[i] = a
        return jax.tree_util.tree_unflatten(treedef, out)

    return [leaves[i] for i in idx], rebuild, cotangent


def _adjoint_fn(sim, plan, steps, table, loss_fn, check=None, step0=0):
    """The custom-VJP loss ``f(params, x0, u0, aux, consts)`` for one static configuration.

    Forward (:func:`_adjoint_forward`): one scan over the frames, each running the steps up to
    its frame in a loop with (static-table) dynamic bounds, so no step is wrapped in a per-step
    ``cond``; with gradients it also evaluates each frame loss's own VJP there (the cotangents of
    its position, aux slice and closed-over constants, to be scaled by the output cotangent), and
    records the states (every one, or one checkpoint per segment) into preallocated buffers.
    Backward (:func:`_adjoint_backward`): segments in reverse, each a loop of fused step VJPs that
    adds a frame's position cotangent where one lies and accumulates per-vertex parameter
    densities, reduced once at the end. With ``check`` (:func:`_overflow_check`) the forward's
    loss is NaN where a step's contact candidates overflowed (the gradient is left as computed).
    """
    forward = _adjoint_forward(sim, plan, steps, loss_fn, check, step0)

    @jax.custom_vjp
    def f(params, x0, u0, aux, consts):
        return forward(params, x0, u0, aux, consts, grads=False)[0]

    def fwd(params, x0, u0, aux, consts):
        loss, s_end, bufs, (gx, ga), gc = forward(params, x0, u0, aux, consts, grads=True)
        return loss, (params, s_end, bufs, gx, ga, gc, aux, consts)

    f.defvjp(fwd, _adjoint_backward(sim, plan, table, step0))
    return f


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


def _adjoint_forward(sim, plan, steps, loss_fn, check, step0=0):
    """``forward(params, x0, u0, aux, consts, grads) -> (loss, final state, state buffers, per-frame
    (position, aux) loss cotangents, the constants' cotangents)`` of :func:`_adjoint_fn` (without
    ``grads``: the loss and the final state only)."""
    n_frames = len(steps)
    hi = np.asarray(steps, np.int32)
    lo = np.concatenate([[0], hi[:-1]]).astype(np.int32)
    record = _recorder(plan)

    def frame_loss(x, aux, consts, j):
        return loss_fn(x.T, _take(aux, j), *consts)

    def forward(params, x0, u0, aux, consts, grads):
        dtype = x0.dtype
        if grads:
            aux_d, aux_rebuild, _ = _split(aux)
            con_d, con_rebuild, _ = _split(consts)
        bufs = _state_buffers(plan, x0.shape, dtype) if grads else None

        def one_step(n, carry):                         # step n: state n - 1 -> state n
            s, bufs, flag = carry
            if grads:
                bufs = record(bufs, n - 1, s)
            if check is not None:
                flag = flag | jnp.any(check(s.x))
            return sim.internal.step(params, s, _step_index(sim, n, step0 - 1)), bufs, flag

        def frame(carry, j):
            s, bufs, acc, c_acc, flag = carry
            s, bufs, flag = jax.lax.fori_loop(jnp.asarray(lo)[j] + 1, jnp.asarray(hi)[j] + 1, one_step,
                                              (s, bufs, flag))
            if not grads:
                return (s, bufs, acc + frame_loss(s.x, aux, consts, j).astype(dtype), c_acc, flag), None
            aux_j = _take(aux, j)

            def h(x, a_d, c_d):
                return loss_fn(x.T, aux_rebuild(a_d, aux_j), *con_rebuild(c_d, consts)).astype(dtype)
            val, (gx, ga, gc) = jax.value_and_grad(h, argnums=(0, 1, 2))(s.x, [a[j] for a in aux_d], con_d)
            c_acc = [a + b for a, b in zip(c_acc, gc)]
            return (s, bufs, acc + val, c_acc, flag), (gx, ga)

        c0 = [jnp.zeros_like(c) for c in con_d] if grads else []
        (s_end, bufs, loss, c_acc, flag), outs = jax.lax.scan(
            frame, (State(x0, u0), bufs, jnp.zeros((), dtype), c0, jnp.zeros((), bool)), jnp.arange(n_frames))
        if grads and plan.store:
            bufs = record(bufs, plan.n_steps, s_end)
        if check is not None:
            loss = loss + _nan_if(flag, dtype)
        return loss, s_end, bufs, outs, c_acc

    return forward


def _adjoint_backward(sim, plan, table, step0=0):
    """The backward pass ``bwd(res, g)`` of :func:`_adjoint_fn`: the steps reversed
    (:func:`_reverse_steps`) over the stored states, or segment by segment from their checkpoints
    (:func:`_reverse_segments`); the densities reduced to a Params cotangent at the end."""
    step_vjp = _make_step_dens_vjp(sim)
    table_np = np.asarray(table, np.int32)                  # (n_steps + 1,) frame index or -1

    def bwd(res, g):
        params, s_end, (xs, us), gx, ga, gc, aux, consts = res
        dtype = s_end.x.dtype
        _, _, aux_cot = _split(aux)
        _, _, con_cot = _split(consts)
        frame_of = jnp.asarray(table_np)
        gx = gx * g.astype(dtype)

        def add_frame(x_bar, n):
            j = frame_of[n]
            hit = (j >= 0).astype(dtype)
            return x_bar + hit * jax.lax.dynamic_index_in_dim(gx, jnp.maximum(j, 0), keepdims=False)

        reverse = _reverse_steps(step_vjp, params, add_frame, step0 if sim.terms.driven else None)
        zeros = jnp.zeros_like(s_end.x)
        carry = (zeros, zeros, _zero_dens(sim, params, dtype))
        if plan.store:
            carry = reverse(carry, lambda n: _read_state(plan, xs, us, n), 0, plan.n_steps)
        else:
            carry = _reverse_segments(sim, plan, params, reverse, carry, xs, us, step0)
        x_bar, u_bar, dens = carry
        x_bar = add_frame(x_bar, 0)
        p_bar = _reduce_dens(sim.topology, params, dens)
        g_ = g.astype(dtype)
        return (p_bar, x_bar, u_bar, aux_cot([a * g_ for a in ga]), con_cot([c * g_ for c in gc]))

    return bwd


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


def _reverse_steps(step_vjp, params, add_frame, step0=None):
    """``reverse(carry, states, first, last)``: reverse steps last, ..., first + 1, with
    ``states(n)`` -> (x_n, u_n) for first <= n <= last; carry (x_bar, u_bar, dens). The state a
    step's VJP needs is read one iteration ahead into the carry: XLA then gathers from a loop
    buffer rather than fusing a dynamic slice of the stored trajectory into every gather (faster;
    see benchmarks/RESULTS.md). ``step0``: the step index of state 0 (scenes with driven
    vertices; None otherwise)."""

    def reverse(carry, states, first, last):
        x_bar, u_bar, dens = carry

        def body(i, inner):
            (x_bar, u_bar, dens), x_next, x, u = inner
            n = last - i                              # reverses step n: state n - 1 -> state n
            x_bar = add_frame(x_bar, n)
            k = None if step0 is None else n - 1 + step0      # driven vertices only: the step index
            x_bar, u_bar, d = step_vjp(params, x, u, x_next, x_bar, u_bar, k)
            dens = jax.tree_util.tree_map(jnp.add, dens, d)
            return ((x_bar, u_bar, dens), x) + states(jnp.maximum(n - 2, first))

        init = ((x_bar, u_bar, dens), states(last)[0]) + states(last - 1)
        out = jax.lax.fori_loop(0, last - first, body, init)
        return out[0]

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


def _adjoint_loss(sim, params, state0, steps, table, loss_fn, aux, segment, memory_budget, check=None, step0=0):
    x0, u0 = sim.internal.to_internal(state0)
    dtype = jnp.result_type(x0)
    plan = _plan(sim, steps[-1], segment, memory_budget, np.dtype(dtype).itemsize)
    example_x = jax.ShapeDtypeStruct((sim.topology.n_vertices, 3), dtype)
    converted, consts = jax.closure_convert(loss_fn, example_x, _take(aux, 0))
    f = _adjoint_fn(sim, plan, steps, table, converted, check, step0)
    return f(params, x0, u0, aux, tuple(consts))


# --------------------------------------------------------------------------- public API

def adjoint_supported(sim):
    """Whether the fused adjoint supports this simulator (its integrator and compiled terms)."""
    return (sim.integrator == "verlet" and sim.substeps == 1
            and set(sim.terms.names()) <= _ADJOINT_TERMS)


def rollout_loss(sim, params, state0, frame_steps, loss_fn: Callable, aux, *, method="auto", segment=None,
                 memory_budget=DEFAULT_MEMORY_BUDGET, nan_on_overflow=True, step0=0):
    """Loss summed over frames of a rollout, differentiable with bounded memory.

    Args:
      sim: :class:`jaxplush.Simulator` (static: closed over by the compiled code).
      params: :class:`jaxplush.Params` of (O,) arrays (k_structural: or an (E,) per-edge field,
        whose gradient is then (E,)), the differentiable input.
      state0: public :class:`jaxplush.State` ((V, 3) arrays), e.g. ``sim.init_fn(params)``;
        gradients flow into it as well.
      frame_steps: static, strictly increasing step indices (0 = ``state0``) at which the loss is
        evaluated; the rollout runs ``frame_steps[-1]`` steps.
      loss_fn: pure jax function ``(x (V, 3), aux_j) -> scalar``.
      aux: pytree whose leaves have a leading axis of length ``len(frame_steps)``; frame ``j``
        sees the ``j``-th slice (e.g. target positions (T, V, 3) and weights, or point clouds
        (T, M, 3)).
      method: "auto", "plain", "checkpoint" or "adjoint" (module docstring).
      segment: steps per checkpointed segment. "checkpoint": default about
        sqrt(frame_steps[-1]). "adjoint": None keeps every step when it fits in
        ``memory_budget`` (else about sqrt(frame_steps[-1])); an int always recomputes segments.
      memory_budget: bytes the adjoint may spend on stored states (default 512 MiB, so that a
        10,000-step horizon at 2562 vertices stays under 1 GiB in all with velocities stored too).
      nan_on_overflow: with soft-soft contact between objects, return a NaN loss when the fresh
        candidate search of some step (at the positions it starts from) overflows the contact
        capacity (the steps were then inexact: :mod:`jaxplush.model.contact`); the forces and
        the gradient stay finite, so only the value says it. ``fitting.fit`` rejects such a point
        and raises the capacity. False: the loss of the inexact run.
      step0: static int, the step index of ``state0`` (it is at t = step0 dt): only scenes with
        driven vertices read it (their paths depend on time); a rollout that starts at a later
        step passes it. ``frame_steps`` still count from ``state0``.

    Returns:
      scalar loss.

    Raises:
      ValueError: bad ``frame_steps``, ``aux`` or parameter shapes, ``method`` or ``segment`` (before
        tracing).
    """
    if method not in METHODS:
        raise ValueError(f"unknown method {method!r}; expected one of {', '.join(METHODS)}")
    model.check_param_shapes(sim.topology, params)
    steps, table = _frame_table(frame_steps)
    _check_aux(aux, len(steps))
    if method == "auto":
        method = "adjoint" if adjoint_supported(sim) else "checkpoint"
    if steps[-1] == 0:                     # no step to take: the loss of state0 alone
        method = "plain"
    check = _overflow_check(sim, nan_on_overflow)
    if method == "adjoint":
        if not adjoint_supported(sim):
            raise ValueError(f"method='adjoint' is not supported for integrator {sim.integrator!r} "
                             f"with terms {sim.terms.names()}; use 'checkpoint'")
        return _adjoint_loss(sim, params, state0, steps, table, loss_fn, aux, segment, memory_budget, check,
                             int(step0))
    return _generic_loss(sim, params, state0, steps, table, loss_fn, aux, segment,
                         checkpoint=(method == "checkpoint"), check=check, step0=int(step0))


def value_and_grad_rollout(sim, params, state0, frame_steps, loss_fn, aux, *, method="auto", segment=None,
                           memory_budget=DEFAULT_MEMORY_BUDGET, argnums=0):
    """``jax.value_and_grad`` of :func:`rollout_loss` w.r.t. ``params`` (argnums=0), ``state0``
    (argnums=1) or both ((0, 1)). Not jitted: wrap it (or its caller) in ``jax.jit``."""
    def f(p, s):
        return rollout_loss(sim, p, s, frame_steps, loss_fn, aux, method=method, segment=segment,
                            memory_budget=memory_budget)
    return jax.value_and_grad(f, argnums=argnums)(params, state0)


def compiled_memory(fn, *args, **kwargs):
    """Memory of ``jax.jit(fn)(*args, **kwargs)`` from XLA's compiled ``memory_analysis()``.

    Returns a dict of bytes: ``temp`` (XLA's buffer-assignment temporaries: residuals, scan
    stacks), ``argument``, ``output``, ``alias`` and ``peak`` = temp + argument + output - alias,
    an upper bound on the compiled program's live device buffers (static analysis, no run).
    """
    compiled = jax.jit(fn).lower(*args, **kwargs).compile()
    m = compiled.memory_analysis()
    out = dict(temp=int(m.temp_size_in_bytes), argument=int(m.argument_size_in_bytes),
               output=int(m.output_size_in_bytes), alias=int(m.alias_size_in_bytes))
    out["peak"] = out["temp"] + out["argument"] + out["output"] - out["alias"]
    return out


def peak_rss_bytes():
    """This process's peak resident memory so far (Linux ``/proc/self/status`` VmHWM), bytes; None
    where unavailable. Measured, and it includes everything the process did (imports, compiles):
    run the gradient in a fresh process to attribute it (benchmarks/bench_fit.py does)."""
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return None
