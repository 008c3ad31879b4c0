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
  fused backward kernel per step (:mod:`jaxplush.stepping.adjoint`, which is also the gradient of
  :func:`jaxplush.rollout`; its reverse sweep :func:`jaxplush.stepping.adjoint.backward` is shared).
  The forward pass keeps every step's
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

from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from jaxplush.model import forces as model
from jaxplush.stepping import adjoint as A
from jaxplush.stepping.adjoint import (  # noqa: F401  (the fused adjoint's parts, used by tests and benchmarks)
    _ADJOINT_TERMS, DEFAULT_MEMORY_BUDGET, _make_step_dens_vjp, _make_step_vjp, _plan, _recorder, _reduce_dens,
    _segment_length, _state_buffers, adjoint_supported)
from jaxplush.types import State

METHODS = ("auto", "plain", "checkpoint", "adjoint")


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
    """The backward pass ``bwd(res, g)`` of :func:`_adjoint_fn`: :func:`jaxplush.stepping.adjoint.backward`
    with each frame's position cotangent (the frame loss's gradient, scaled by ``g``) added at
    its step, from a zero final-state cotangent."""
    table_np = np.asarray(table, np.int32)                  # (n_steps + 1,) frame index or -1

    def bwd(res, g):
        params, s_end, bufs, gx, ga, gc, aux, consts = res
        dtype = s_end.x.dtype
        _, _, aux_cot = _split(aux)
        _, _, con_cot = _split(consts)
        frame_of = jnp.asarray(table_np)
        gx = gx * g.astype(dtype)

        def add_frame(x_bar, n):
            j = frame_of[n]
            hit = (j >= 0).astype(dtype)
            return x_bar + hit * jax.lax.dynamic_index_in_dim(gx, jnp.maximum(j, 0), keepdims=False)

        zeros = jnp.zeros_like(s_end.x)
        p_bar, x_bar, u_bar = A.backward(sim, plan, params, bufs, add_frame, zeros, zeros, step0)
        g_ = g.astype(dtype)
        return (p_bar, x_bar, u_bar, aux_cot([a * g_ for a in ga]), con_cot([c * g_ for c in gc]))

    return bwd


def _adjoint_loss(sim, params, state0, steps, table, loss_fn, aux, segment, memory_budget, check=None, step0=0):
    x0, u0 = sim.internal.to_internal(state0)
    dtype = jnp.result_type(x0)
    plan = _plan(sim, steps[-1], segment, memory_budget, np.dtype(dtype).itemsize)
    example_x = jax.ShapeDtypeStruct((sim.topology.n_vertices, 3), dtype)
    converted, consts = jax.closure_convert(loss_fn, example_x, _take(aux, 0))
    f = _adjoint_fn(sim, plan, steps, table, converted, check, step0)
    return f(params, x0, u0, aux, tuple(consts))


# --------------------------------------------------------------------------- public API

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
