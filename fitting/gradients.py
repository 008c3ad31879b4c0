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
  kept. Memory: (steps/segment + segment) states. Any integrator (``sim.internal_step``).
* ``"adjoint"``: a hand-written adjoint of the damped Verlet step (``jax.custom_vjp``), one
  fused backward kernel per step (:func:`_make_force_vjp`). The forward pass keeps every step's
  positions (and velocities when dashpot, drag or Verlet damping need them) if that fits in
  ``memory_budget`` bytes, else it keeps a checkpoint every ``segment`` steps and recomputes one
  segment at a time. Supports springs, gas, gravity, Verlet damping, dashpot, drag, the floor,
  pins and soft-soft contact; not floor friction/restitution or substeps > 1.
* ``"auto"``: ``"adjoint"`` where supported (:func:`adjoint_supported`), else ``"checkpoint"``.

Measured (benchmarks/bench_fit.py, benchmarks/RESULTS.md): the adjoint's value_and_grad costs
about 3.5-4x the forward loss on this CPU, against about 7x for the checkpointed autodiff; a
10,000-step horizon at 2562 vertices keeps about 300 MB of positions.
"""

from __future__ import annotations

import math
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxplush import model
from jaxplush.types import GAS_CONSTANT, VOLUME_EPS, Params, State

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

def _generic_loss(sim, params, state0, steps, table, loss_fn, aux, segment, checkpoint):
    """Autodiff through the rollout: one scan over segments of ``segment`` steps (padded)."""
    n_steps = steps[-1]
    state = sim.to_internal(state0)

    def frame_loss(x, j):
        return loss_fn(x.T, _take(aux, j))

    loss0 = frame_loss(state[0], 0) if steps[0] == 0 else jnp.zeros((), state[0].dtype)
    if n_steps == 0:
        return loss0
    table_j = jnp.asarray(table)

    step = sim.internal_step
    if checkpoint:
        # Two levels: segments are recomputed from their first state, and inside a segment
        # only each step's input state is kept (residuals of a whole segment of steps cost
        # more memory traffic than recomputing one step: 2x faster here).
        step = jax.checkpoint(step)

    def one_step(carry, n):
        s, acc = carry
        # Steps past the horizon (padding of the last segment) leave the carry unchanged.
        s = jax.lax.cond(n <= n_steps, lambda s: step(params, s), lambda s: s, s)
        j = table_j[jnp.minimum(n, n_steps)]
        hit = (j >= 0) & (n <= n_steps)
        acc = acc + jax.lax.cond(hit, lambda: frame_loss(s[0], jnp.maximum(j, 0)).astype(acc.dtype),
                                 lambda: jnp.zeros((), acc.dtype))
        return (s, acc), None

    seg = _segment_length(segment, n_steps) if checkpoint else n_steps
    n_seg = -(-n_steps // seg)

    def run_segment(carry, first):
        carry, _ = jax.lax.scan(one_step, carry, first + jnp.arange(1, seg + 1))
        return carry

    if checkpoint:
        run_segment = jax.checkpoint(run_segment)

    (_, loss), _ = jax.lax.scan(lambda c, first: (run_segment(c, first), None), (state, loss0),
                                jnp.arange(n_seg) * seg)
    return loss


# --------------------------------------------------------------------------- fused adjoint (Verlet)

_ADJOINT_TERMS = frozenset(("spring", "dashpot", "drag", "gas", "gravity", "floor", "fixed", "verlet_damping",
                            "contact"))


def _make_force_vjp(topo, terms, temperature):
    """``force_vjp(params, x, u, lam)``: the transposed linearisation of the internal force.

    For F = F(x, u; k, c, nmol) (springs, dashpot, gas, contact; (3, V) arrays) and a cotangent
    ``lam`` (3, V), returns (J_x^T lam, J_u^T lam, k_bar, c_bar, n_bar, f_dot, p_extra): (O,)
    cotangents of k_structural, dashpot and nmol, sum_o F.lam (for the mass), and the contact
    term's parameter cotangents (a Params, or None without contact).

    Written in the one-ring form of :func:`jaxplush.model.make_force_fn`: every term is a
    gather of a neighbour's value minus the vertex's own, so the transpose needs gathers only,
    never a scatter-add. The springs, the gas (gradient of -nRT ln V) and the dashpot's
    velocity part have symmetric Jacobians (J^T lam = J lam, a directional derivative); the
    dashpot's position Jacobian is not, and its transpose is written out. Per ring entry
    (i, j), with d = x_j - x_i, delta = lam_j - lam_i, t = d.delta, 1/l² = 1/(d.d + eps²):

      springs   J_x^T lam_i = sum_j k (1 - L/l) delta + k L/l³ t d
      dashpot   J_x^T lam_i = sum_j c/l² [(dv.d) delta + t dv - 2 (dv.d) t d / l²]
                J_u^T lam_i = sum_j c/l² t d
      gas       J_x^T lam   = P H_V lam + P'(V) (g.lam) g,   g = dV/dx

    The forces are linear in k, c and nmol, so their cotangents are sums the pass computes
    anyway: sum_i lam_i.f_i^spring = k sum_{ij} (1 - L/l)(lam_i.d) = -k/2 sum_{ij} (1 - L/l) t
    (each edge seen from both ends).
    """
    ring = np.ascontiguousarray(topo.ring.T)                  # (K, V), neighbour-major
    mask = np.ascontiguousarray(topo.ring_mask.T)
    ring_rest = np.ascontiguousarray(topo.ring_rest.T)
    all_real = bool(mask.all())
    rt = GAS_CONSTANT * temperature
    contact_force = None
    if getattr(terms, "contact", None):
        from jaxplush import contact as _contact
        contact_force = _contact.make_contact_force(topo, terms.contact)

    def gather(a):
        return a.at[ring].get(mode="promise_in_bounds")

    def cross(a, b):
        return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])

    def force_vjp(params, x, u, lam):
        dtype = x.dtype
        rest = jnp.asarray(ring_rest, dtype)
        d = [gather(x[c]) - x[c] for c in range(3)]                      # 3 x (K, V)
        dl = [gather(lam[c]) - lam[c] for c in range(3)]
        inv_l = jax.lax.rsqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2] + topo.length_eps ** 2)
        s = 1.0 - rest * inv_l
        t = d[0] * dl[0] + d[1] * dl[1] + d[2] * dl[2]
        if not all_real:
            t = jnp.where(mask, t, 0.0)
            s = jnp.where(mask, s, 0.0)
        k = model.per_vertex(topo, params.k_structural)
        w = k * s                                                        # spring tension / l
        coef = k * rest * inv_l * inv_l * inv_l                          # of t d
        k_dens = -0.5 * jnp.sum(s * t, axis=0)                           # (V,)
        zero = jnp.zeros((topo.n_objects,), dtype)
        c_bar = n_bar = zero
        ju = jnp.zeros_like(x)
        extra = None
        if terms.dashpot:
            dv = [gather(u[c]) - u[c] for c in range(3)]
            inv_l2 = inv_l * inv_l
            q = (dv[0] * d[0] + dv[1] * d[1] + dv[2] * d[2]) * inv_l2
            if not all_real:
                q = jnp.where(mask, q, 0.0)
            c = model.per_vertex(topo, params.dashpot)
            w = w + c * q
            coef = coef - 2.0 * c * q * inv_l2
            ct = c * inv_l2 * t
            ju = jnp.stack([jnp.sum(ct * d[i], axis=0) for i in range(3)])
            extra = [ct * dv[i] for i in range(3)]
            c_bar = model.per_object_sum(topo, -0.5 * jnp.sum(q * t, axis=0))
        jx = jnp.stack([jnp.sum(w * dl[i] + coef * t * d[i] + (extra[i] if extra else 0.0), axis=0)
                        for i in range(3)])
        k_bar = model.per_object_sum(topo, k_dens)
        f_dot = params.k_structural * k_bar
        if terms.dashpot:
            f_dot = f_dot + params.dashpot * c_bar
        if terms.gas:
            # m_k = d_{k+1} - d_{k-1} around the ring: g = 1/6 sum_k d_k x d_{k+1} = 1/12 sum_k d_k x m_k,
            # and its directional derivative 1/6 sum_k (delta_k x d_{k+1} + d_k x delta_{k+1})
            # = 1/6 sum_k delta_k x m_k (re-indexing the ring; padded entries repeat a neighbour).
            m = [jnp.roll(a, -1, axis=0) - jnp.roll(a, 1, axis=0) for a in d]
            g = jnp.stack([jnp.sum(a, axis=0) for a in cross(d, m)]) / 12.0
            h = jnp.stack([jnp.sum(a, axis=0) for a in cross(dl, m)]) / 6.0
            volume = _object_volumes(topo, x, g)
            v_clamp = VOLUME_EPS * jnp.asarray(topo.rest_volume, dtype)
            v_safe = jnp.maximum(volume, v_clamp)
            p = params.nmol * rt / v_safe
            # dP/dV, 0 on the clamp (and halved at a tie, as jnp.maximum's derivative)
            dp = jnp.where(volume > v_clamp, -p / v_safe, jnp.where(volume == v_clamp, -0.5 * p / v_safe, 0.0))
            g_lam = model.per_object_sum(topo, jnp.sum(g * lam, axis=0))  # dV.lam per object
            jx = jx + model.per_vertex(topo, p) * h + model.per_vertex(topo, dp * g_lam) * g
            n_bar = g_lam * rt / v_safe
            f_dot = f_dot + p * g_lam
        p_extra = None
        if contact_force is not None:
            # soft-soft contact (jaxplush.contact, -grad of a penalty energy on candidate lists):
            # its own VJP, parameters included.
            fc, vjp_c = jax.vjp(contact_force, params, x)
            p_extra, jxc = vjp_c(lam)
            jx = jx + jxc
            f_dot = f_dot + model.per_object_sum(topo, jnp.sum(fc * lam, axis=0))
        return jx, ju, k_bar, c_bar, n_bar, f_dot, p_extra

    return force_vjp


def _object_volumes(topo, x, g):
    """(O,) volumes V_o = 1/3 sum_i (x_i - r_o).g_i (as in jaxplush.model), x and g (3, V)."""
    if topo.n_objects == 1:
        return (jnp.sum((x - x[:, :1]) * g) / 3.0)[None]
    return jnp.stack([jnp.sum((x[:, a:b] - x[:, a:a + 1]) * g[:, a:b]) for a, b in topo.vertex_slices]) / 3.0


def _make_step_vjp(sim):
    """``step_vjp(params, x, u, x_next, x_bar, u_bar) -> (x_bar, u_bar, params_bar)``: the VJP of
    ``sim.internal_step`` at the state (x, u) (internal (3, V) layout), given the positions
    ``x_next`` it produced. The step (jaxplush.step, verlet)::

        a  = F(x, u)/m - drag u + g;   u' = (1 - f) u + a dt;   x' = x + u' dt;
        floor (y >= H): below = x'_y < H  ->  u'_y = (H - x_y)/dt, x'_y = H;  pins: x' = x0, u' = 0.

    The floor and pins are masks; ``below`` is read off ``x_next`` (projected vertices lie
    exactly on the floor), so no primal force needs recomputing.
    """
    topo, terms, dt = sim.topology, sim.terms, getattr(sim, "h", sim.dt)
    force_vjp = _make_force_vjp(topo, terms, sim.scene.temperature)
    floor = sim.scene.floor
    free = np.ones(topo.n_vertices)
    free[topo.fixed] = 0.0

    def step_vjp(params, x, u, x_next, x_bar, u_bar):
        dtype = x.dtype
        if terms.fixed:
            keep = jnp.asarray(free, dtype)
            x_bar, u_bar = x_bar * keep, u_bar * keep
        x_out = x_bar
        if terms.floor:
            below = x_next[1] <= floor
            uy = u_bar[1]
            x_bar = x_bar.at[1].set(jnp.where(below, 0.0, x_bar[1]))
            u_bar = u_bar.at[1].set(jnp.where(below, 0.0, uy))
            x_out = x_bar.at[1].add(jnp.where(below, -uy / dt, 0.0))
        ut = u_bar + dt * x_bar                                  # cotangent of u' (before x' = x + u' dt)
        a_bar = dt * ut
        mass = model.vertex_mass(topo, params)
        lam = a_bar / mass                                       # cotangent of the internal force
        jx, ju, k_bar, c_bar, n_bar, f_dot, p_extra = force_vjp(params, x, u, lam)
        zero = jnp.zeros((topo.n_objects,), dtype)
        d_bar = drag_bar = zero
        if terms.verlet_damping:
            fd = model.per_vertex(topo, _damping_factor(params.damping))
            u_out = (1.0 - fd) * ut + ju
            f_bar = -model.per_object_sum(topo, jnp.sum(u * ut, axis=0))
            d_bar = jax.vjp(_damping_factor, params.damping)[1](f_bar)[0]
        else:
            u_out = ut + ju
        if terms.drag:
            u_out = u_out - model.per_vertex(topo, params.drag) * a_bar
            drag_bar = -model.per_object_sum(topo, jnp.sum(u * a_bar, axis=0))
        m_bar = -f_dot / params.total_weight
        p_bar = Params(k_structural=k_bar, damping=d_bar, dashpot=c_bar, drag=drag_bar, nmol=n_bar,
                       total_weight=m_bar)
        if p_extra is not None:
            p_bar = jax.tree_util.tree_map(jnp.add, p_bar, p_extra)
        return x_out + jx, u_out, p_bar

    return step_vjp


def _damping_factor(damping):
    """f = 1/D for D > 0, else 0 (as jaxplush.step)."""
    safe = jnp.where(damping > 0, damping, 1.0)
    return jnp.where(damping > 0, 1.0 / safe, 0.0)


class _Plan(NamedTuple):
    """Static layout of an adjoint rollout: ``n_seg`` segments of ``seg`` steps (the last padded
    to cover ``n_steps``); ``store``: every state is kept from the forward pass (one segment),
    else each segment is recomputed from its checkpoint in the backward pass; ``keep_u``: the
    backward pass needs the velocities (dashpot, drag or Verlet damping)."""

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
    return _Plan(n_steps, seg, -(-n_steps // seg), False, keep_u)


def _adjoint_fn(sim, plan, steps, table, loss_fn):
    """The custom-VJP loss ``f(params, x0, u0, aux, consts)`` for one static configuration."""
    step_vjp = _make_step_vjp(sim)
    n_steps, seg, n_seg = plan.n_steps, plan.seg, plan.n_seg
    padded = n_seg * seg != n_steps
    table_j = np.asarray(table)
    first_frame = steps[0] == 0

    def frame_loss(x, aux, consts, j):
        return loss_fn(x.T, _take(aux, j), *consts)

    def frame_index(n):
        """(frame j clipped to a valid index, whether step n is a frame)."""
        nc = jnp.minimum(n, n_steps)
        j = jnp.asarray(table_j)[nc]
        hit = j >= 0
        if padded:
            hit = hit & (n <= n_steps)
        return jnp.maximum(j, 0), hit

    def advance(params, s, n):
        if padded:
            return jax.lax.cond(n <= n_steps, lambda s: sim.internal_step(params, s), lambda s: s, s)
        return sim.internal_step(params, s)

    def forward(params, x0, u0, aux, consts, keep):
        dtype = x0.dtype
        loss0 = frame_loss(x0, aux, consts, 0).astype(dtype) if first_frame else jnp.zeros((), dtype)

        def one_step(carry, n):
            s, acc = carry
            s_new = advance(params, s, n)
            j, hit = frame_index(n)
            acc = acc + jax.lax.cond(hit, lambda: frame_loss(s_new.x, aux, consts, j).astype(dtype),
                                     lambda: jnp.zeros((), dtype))
            out = (s.x, s.v if plan.keep_u else None) if keep else None
            return (s_new, acc), out

        def segment(carry, first):
            start = carry[0]
            carry, ys = jax.lax.scan(one_step, carry, first + jnp.arange(1, seg + 1))
            return carry, (start if not keep else None, ys)

        (s_end, loss), (ckpts, ys) = jax.lax.scan(segment, (State(x0, u0), loss0), jnp.arange(n_seg) * seg)
        return loss, s_end, ckpts, ys

    def split(tree):
        """Leaves of ``tree`` that carry cotangents (inexact dtypes), and a rebuild function."""
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

    @jax.custom_vjp
    def f(params, x0, u0, aux, consts):
        return forward(params, x0, u0, aux, consts, keep=False)[0]

    def fwd(params, x0, u0, aux, consts):
        loss, s_end, ckpts, ys = forward(params, x0, u0, aux, consts, keep=plan.store)
        return loss, (params, x0, s_end, ckpts, ys, aux, consts)

    def bwd(res, g):
        params, x0, s_end, ckpts, ys, aux, consts = res
        dtype = x0.dtype
        aux_d, aux_rebuild, aux_cot = split(aux)
        con_d, con_rebuild, con_cot = split(consts)

        def frame_vjp(x, j):
            """(x_bar, aux_j_bar, consts_bar) of g * loss_fn at frame j, x (3, V)."""
            aux_j = _take(aux, j)

            def h(x, a_d, c_d):
                a = aux_rebuild(a_d, aux_j)
                return loss_fn(x.T, a, *con_rebuild(c_d, consts)).astype(dtype) * g
            return jax.grad(h, argnums=(0, 1, 2))(x, [a[j] for a in aux_d], con_d)

        def frame_zero(x):
            return (jnp.zeros_like(x), [jnp.zeros(a.shape[1:], a.dtype) for a in aux_d],
                    [jnp.zeros_like(c) for c in con_d])

        def add_frame(carry, x, n):
            x_bar, p_bar, a_bar, c_bar = carry
            j, hit = frame_index(n)
            fx, fa, fc = jax.lax.cond(hit, lambda: frame_vjp(x, j), lambda: frame_zero(x))
            a_bar = [b.at[j].add(v) for b, v in zip(a_bar, fa)]
            c_bar = [b + v for b, v in zip(c_bar, fc)]
            return x_bar + fx, p_bar, a_bar, c_bar

        def back_segment(carry, k):
            """Reverse the ``seg`` steps of segment k. The state a step's VJP needs is read one
            iteration ahead into the carry: XLA then gathers from a loop buffer rather than
            fusing a dynamic slice of the stored trajectory into every gather (about 1.4x
            faster here)."""
            first = k * seg
            if plan.store:
                xs, us = ys[0][0], (ys[1][0] if plan.keep_u else None)
            else:
                xs, us = recompute(jax.tree_util.tree_map(lambda a: a[k], ckpts), first)

            def read(i):
                x = jax.lax.dynamic_index_in_dim(xs, i, keepdims=False)
                u = jax.lax.dynamic_index_in_dim(us, i, keepdims=False) if plan.keep_u else x
                return x, u

            def back_step(inner, i):
                (x_bar, u_bar, p_bar, a_bar, c_bar), x_next, x, u = inner
                n = first + i + 1                        # this iteration reverses step n: s_{n-1} -> s_n
                x_bar, p_bar, a_bar, c_bar = add_frame((x_bar, p_bar, a_bar, c_bar), x_next, n)

                def vjp(x_bar, u_bar):
                    return step_vjp(params, x, u, x_next, x_bar, u_bar)

                if padded:
                    zero_p = jax.tree_util.tree_map(jnp.zeros_like, p_bar)
                    x_bar, u_bar, pb = jax.lax.cond(n <= n_steps, vjp, lambda xb, ub: (xb, ub, zero_p),
                                                    x_bar, u_bar)
                else:
                    x_bar, u_bar, pb = vjp(x_bar, u_bar)
                p_bar = jax.tree_util.tree_map(jnp.add, p_bar, pb)
                return ((x_bar, u_bar, p_bar, a_bar, c_bar), x) + read(jnp.maximum(i - 1, 0)), None

            cots, x_next = carry
            inner, _ = jax.lax.scan(back_step, (cots, x_next) + read(seg - 1), jnp.arange(seg), reverse=True)
            return inner[:2], None

        def recompute(start, first):
            def body(s, n):
                return advance(params, s, n), (s.x, s.v if plan.keep_u else None)
            return jax.lax.scan(body, start, first + jnp.arange(1, seg + 1))[1]

        zeros = jnp.zeros_like(x0)
        p_zero = jax.tree_util.tree_map(jnp.zeros_like, params)
        init = ((zeros, zeros, p_zero, [jnp.zeros_like(a) for a in aux_d], [jnp.zeros_like(c) for c in con_d]),
                s_end.x)
        ((x_bar, u_bar, p_bar, a_bar, c_bar), _), _ = jax.lax.scan(back_segment, init, jnp.arange(n_seg),
                                                                  reverse=True)
        if first_frame:
            fx, fa, fc = frame_vjp(x0, 0)
            x_bar = x_bar + fx
            a_bar = [b.at[0].add(v) for b, v in zip(a_bar, fa)]
            c_bar = [b + v for b, v in zip(c_bar, fc)]
        return p_bar, x_bar, u_bar, aux_cot(a_bar), con_cot(c_bar)

    f.defvjp(fwd, bwd)
    return f


def _adjoint_loss(sim, params, state0, steps, table, loss_fn, aux, segment, memory_budget):
    x0, u0 = sim.to_internal(state0)
    dtype = jnp.result_type(x0)
    plan = _plan(sim, steps[-1], segment, memory_budget, np.dtype(dtype).itemsize)
    example_x = jax.ShapeDtypeStruct((sim.topology.n_vertices, 3), dtype)
    converted, consts = jax.closure_convert(loss_fn, example_x, _take(aux, 0))
    f = _adjoint_fn(sim, plan, steps, table, converted)
    return f(params, x0, u0, aux, tuple(consts))


# --------------------------------------------------------------------------- public API

def adjoint_supported(sim):
    """Whether the fused adjoint supports this simulator (its integrator and compiled terms)."""
    return (sim.integrator == "verlet" and getattr(sim, "substeps", 1) == 1
            and set(sim.terms.names()) <= _ADJOINT_TERMS)


def rollout_loss(sim, params, state0, frame_steps, loss_fn: Callable, aux, *, method="auto", segment=None,
                 memory_budget=DEFAULT_MEMORY_BUDGET):
    """Loss summed over frames of a rollout, differentiable with bounded memory.

    Args:
      sim: :class:`jaxplush.Simulator` (static: closed over by the compiled code).
      params: :class:`jaxplush.Params` of (O,) arrays, the differentiable input.
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

    Returns:
      scalar loss.

    Raises:
      ValueError: bad ``frame_steps``, ``aux`` shapes, ``method`` or ``segment`` (before tracing).
    """
    if method not in METHODS:
        raise ValueError(f"unknown method {method!r}; expected one of {', '.join(METHODS)}")
    steps, table = _frame_table(frame_steps)
    _check_aux(aux, len(steps))
    if method == "auto":
        method = "adjoint" if adjoint_supported(sim) else "checkpoint"
    if steps[-1] == 0:                     # no step to take: the loss of state0 alone
        method = "plain"
    if method == "adjoint":
        if not adjoint_supported(sim):
            raise ValueError(f"method='adjoint' is not supported for integrator {sim.integrator!r} "
                             f"with terms {sim.terms.names()}; use 'checkpoint'")
        return _adjoint_loss(sim, params, state0, steps, table, loss_fn, aux, segment, memory_budget)
    return _generic_loss(sim, params, state0, steps, table, loss_fn, aux, segment,
                         checkpoint=(method == "checkpoint"))


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
