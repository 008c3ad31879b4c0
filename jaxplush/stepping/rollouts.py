"""Rollouts: one ``jax.lax.scan`` over saved frames, an inner scan over the steps between them.

``rollout`` is jit-compiled once per (program, n_frames, save_every, checkpoint): a simulator
rebuilt for the same scene and settings compares equal to the first (``Simulator.key``) and
reuses its compiled code (:mod:`jaxplush.stepping.compiled`), as do new parameter values and initial
states. Health is checked at every saved
frame and carried as data (:mod:`jaxplush.stepping.diagnostics`); the carry also keeps the last healthy
state so a failure can be located to the exact step afterwards, outside ``jit``. A soft-soft
contact overflow at any step (the candidate cache's sticky per-object flag, or with
``coherent_contact=False`` a flag of the same check carried from step to step) becomes the
object's ``CONTACT_OVERFLOW`` code at the next saved frame; the positions stay finite.
"""

from __future__ import annotations

import functools
import math
import warnings
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxplush.errors import GradientWarning
from jaxplush.stepping import adjoint
from jaxplush.stepping import compiled
from jaxplush.stepping import diagnostics
from jaxplush.model import forces as model
from jaxplush.types import State


class Health(NamedTuple):
    """Carried health record of a rollout; a batched rollout (:mod:`jaxplush.stepping.batched`)
    carries the same record with a trailing batch axis B on every field.

    Attributes:
      code: (O,) or (O, B) int32 first failure code per object (diagnostics.OK if none).
      bad_step: (O,) or (O, B) int32 step at whose saved frame the failure was seen (-1: none).
      warn_step: (O,) or (O, B) int32 first saved step with the volume clamp active (-1: none).
      good_state: the last saved state at which every object was healthy (per point).
      good_step: () or (B,) int32 step number of ``good_state``.
    """

    code: jax.Array
    bad_step: jax.Array
    warn_step: jax.Array
    good_state: State
    good_step: jax.Array

    @property
    def failed(self):
        """bool (or (B,) bool, batched): a failure in any object."""
        f = np.asarray(self.bad_step).max(axis=0) >= 0
        return bool(f) if f.ndim == 0 else f

    def advance(self, code, step, state):
        """The record after a checked frame at ``step`` (scalar or (B,)) with codes ``code`` ((O,)
        or (O, B)) and ``state`` (any pytree whose leaves broadcast against the batch axis)."""
        new_bad = (code >= diagnostics.ERROR) & (self.bad_step < 0)
        new_warn = (code == diagnostics.VOLUME_CLAMPED) & (self.warn_step < 0)
        healthy = jnp.all(code < diagnostics.ERROR, axis=0) & jnp.all(self.bad_step < 0, axis=0)
        return Health(
            code=jnp.where(new_bad, code, self.code),
            bad_step=jnp.where(new_bad, step, self.bad_step),
            warn_step=jnp.where(new_warn, step, self.warn_step),
            good_state=jax.tree_util.tree_map(lambda a, b: jnp.where(healthy, a, b), state, self.good_state),
            good_step=jnp.where(healthy, step, self.good_step))


def initial_health(sim, state, step=0):
    o = sim.topology.n_objects
    if _traced((state, step)):
        neg = jnp.full((o,), -1, jnp.int32)
        return Health(jnp.zeros((o,), jnp.int32), neg, neg, state, jnp.asarray(step, jnp.int32))
    # concrete: the same arrays built on the host and put on the device, without the one-op
    # compiled programs (fill, conversion) that jnp dispatches for them
    neg = jax.device_put(np.full((o,), -1, np.int32))
    return Health(jax.device_put(np.zeros((o,), np.int32)), neg, neg, state, jax.device_put(_int32(step)))


def _int32(step):
    """``step`` as an int32 numpy scalar when it is a Python or numpy integer in int32's range
    (jit takes it as it is), else ``jnp.asarray(step, jnp.int32)`` (its errors, tracers)."""
    if isinstance(step, (int, np.integer)) and not isinstance(step, bool) and -2 ** 31 <= step < 2 ** 31:
        return np.int32(step)
    return jnp.asarray(step, jnp.int32)


def _core(sim, params, state, health, step0, n_frames, save_every, checkpoint, record=None):
    """The rollout on the internal layout (:func:`rollout`). ``checkpoint``: False, True (each
    frame's steps in ``jax.checkpoint``) or "segments" (the checkpointed autodiff of ``gradient=
    "checkpoint"``: each frame's steps also in segments of about sqrt(save_every) steps, and
    each step, recomputed in the backward pass). ``record``: a :class:`jaxplush.stepping.adjoint._Plan`
    to also return the state buffers the fused adjoint reverses (:func:`_core_recorded`)."""
    step_fn = sim.internal.step
    state = sim.internal.to_internal(state)
    health = health._replace(good_state=sim.internal.to_internal(health.good_state))

    coherent = sim.internal.coherent
    check = sim.internal.overflow
    # one(c, n) advances the carry by step n (the state at t = n dt); only scenes with driven
    # vertices read n (and trace the step counter), the others ignore it
    driven = bool(sim.terms.driven)

    def at(n):
        return n if driven else None
    if coherent is not None:
        # soft-soft contact: the candidate lists ride along in the carry (temporal coherence),
        # with their sticky per-object overflow flags
        def one(c, n):
            return coherent.step(params, *c, at(n))
        carry0 = (state, coherent.init(state.x))

        def overflow(c):
            return c[1].overflow
    elif check is not None:
        # soft-soft contact searched afresh every step: a sticky flag of the same search's
        # overflow at the positions each step starts from rides along (where the step's force
        # is first evaluated: XLA can share the broad phase with it)
        def one(c, n):
            return step_fn(params, c[0], at(n)), c[1] | check(c[0].x)
        carry0 = (state, jnp.zeros((sim.topology.n_objects,), bool))

        def overflow(c):
            return c[1]
    else:
        def one(c, n):
            return (step_fn(params, c[0], at(n)),)
        carry0 = (state,)
        overflow = None

    if record is not None:
        # the fused adjoint's forward: also keep each state (or each segment's first) before its step
        keep = adjoint._recorder(record)

        def steps(cb, first):
            def body(cb, m):                       # m: the local index of the state c holds
                c, bufs = cb
                return (one(c, step0 + m if driven else None), keep(bufs, m, c[0])), None
            return jax.lax.scan(body, cb, first + jnp.arange(save_every, dtype=jnp.int32))[0]
        carry0 = (carry0, adjoint._state_buffers(record, state.x.shape, state.x.dtype))
        inner, outer = (lambda cb: cb[0]), (lambda i: i * save_every)
    else:
        inner, outer = (lambda c: c), (lambda i: step0 + i * save_every if driven else None)
        if driven:
            def steps(s, first):
                return jax.lax.scan(lambda c, n: (one(c, n), None), s, first + jnp.arange(save_every, dtype=jnp.int32))[0]
        else:
            def steps(s, first):
                return jax.lax.scan(lambda c, _: (one(c, None), None), s, None, length=save_every)[0]
        if checkpoint == "segments":
            steps = _segmented(one, save_every, driven)
        if checkpoint:
            steps = jax.checkpoint(steps)

    def frame(carry, i):
        cb, h = carry
        cb = steps(cb, outer(i))
        c = inner(cb)
        s = c[0]
        step = step0 + (i + 1) * save_every
        if overflow is None:
            code = sim.status_fn(params, sim.internal.to_public(s))
        else:
            # a contact overflow since the start of this rollout is the object's code
            code = diagnostics.with_overflow(diagnostics.object_status(sim.topology, sim.terms, s.x.T), overflow(c))
        return (cb, h.advance(code, step, s)), s.x

    (carry, health), frames = jax.lax.scan(frame, (carry0, health), jnp.arange(n_frames, dtype=jnp.int32))
    state = inner(carry)[0]
    health = health._replace(good_state=sim.internal.to_public(health.good_state))
    out = sim.internal.to_public(state), jnp.swapaxes(frames, 1, 2), health
    if record is None:
        return out
    bufs = carry[1]
    if record.store:
        bufs = keep(bufs, record.n_steps, state)
    return out, bufs


def _segmented(one, save_every, driven):
    """A frame's steps for checkpointed autodiff: segments of ``seg`` steps (the divisor of
    ``save_every`` nearest sqrt(save_every) from below), each recomputed from its first state in
    the backward pass, and each step in it from its input (``one`` in ``jax.checkpoint``): the
    backward pass of a frame holds save_every / seg + seg states and one step's residuals."""
    seg = max(d for d in range(1, math.isqrt(save_every) + 1) if save_every % d == 0)
    step = jax.checkpoint(one)

    def segment(c, first):
        if driven:
            return jax.lax.scan(lambda c, n: (step(c, n), None), c, first + jnp.arange(seg, dtype=jnp.int32))[0]
        return jax.lax.scan(lambda c, _: (step(c, None), None), c, None, length=seg)[0]
    segment = jax.checkpoint(segment)

    def steps(s, first):
        starts = (first + seg * jnp.arange(save_every // seg, dtype=jnp.int32)) if driven else None
        return jax.lax.scan(lambda c, f: (segment(c, f), None), s, starts, length=save_every // seg)[0]
    return steps


def _core_jit(sim, params, state, health, step0, *, n_frames, save_every, checkpoint):
    fn = compiled.get(sim, "rollout", lambda: jax.jit(functools.partial(_core, sim),
                                                       static_argnames=("n_frames", "save_every", "checkpoint")))
    return fn(params, state, health, step0, n_frames=n_frames, save_every=save_every, checkpoint=checkpoint)


#: How :func:`rollout` is differentiated (``gradient=``).
GRADIENTS = ("auto", "adjoint", "checkpoint", "autodiff")

#: The reasons :func:`rollout`'s gradient fell back to checkpointed autodiff, each warned of once.
_WARNED = set()


def rollout(sim, params, state, n_frames, save_every=1, checkpoint=False, health=None, step0=0, *,
            gradient="auto", memory_budget=None):
    """Run ``n_frames * save_every`` steps, saving positions every ``save_every`` steps.

    Differentiable with respect to ``params`` and ``state``, in reverse mode (``jax.grad``,
    ``jax.value_and_grad``, ``jax.vjp``, ``jax.jacrev``) and forward mode (``jax.jvp``,
    ``jax.jacfwd``), under ``jax.jit`` and ``jax.vmap``. By default (``gradient="auto"``) reverse
    mode takes the fused adjoint (:mod:`jaxplush.stepping.adjoint`): the forward run also keeps
    every step's state within ``memory_budget`` (else a checkpoint every about sqrt(steps)
    steps, recomputed segment by segment), and the backward pass is one fused kernel per step:
    the value and gradient cost about 3.5-5 forward runs, where JAX's own reverse mode through the
    scan (``gradient="autodiff"``) costs 20-30 and keeps every step's residuals
    (benchmarks/bench_fit.py; benchmarks/RESULTS.md). A simulator the adjoint does not cover
    (contact or floor friction, restitution, the smooth floor, another integrator than Verlet,
    substeps) is differentiated by checkpointed autodiff instead, with a warning the first time.
    Forward mode is JAX's own (a tangent run beside a forward run). Not differentiated, the
    program is the plain rollout's. ``health`` carries no derivative (its ``good_state``'s is
    zero). Second derivatives (``jax.hessian``, reverse over reverse) need ``gradient="autodiff"``.

    Args:
      sim: :class:`jaxplush.stepping.step.Simulator`.
      params: :class:`jaxplush.types.Params` pytree.
      state: initial :class:`jaxplush.types.State` (from ``sim.init_fn``).
      n_frames: number of saved frames (static).
      save_every: steps between saved frames (static).
      checkpoint: the gradient of JAX's autodiff through the scan (``gradient="autodiff"``; True
        selects it) with each frame's steps in ``jax.checkpoint``, so that its memory grows with
        frames, not steps.
      health: a :class:`Health` to continue (for chunked runs); default fresh.
      step0: step number of ``state`` (for chunked runs).
      gradient: how reverse mode differentiates the rollout (static): "auto" (the fused adjoint
        where it applies, :func:`jaxplush.stepping.adjoint.adjoint_supported`, else
        "checkpoint" with a warning once per reason), "adjoint" (an error where it does not
        apply), "checkpoint" (JAX's autodiff, each frame's steps recomputed in segments of
        about sqrt(save_every), each step from its input) or "autodiff" (JAX's autodiff through
        the scan, every step's residuals kept: the reference).
      memory_budget: bytes the fused adjoint may spend keeping every step's state (default
        :data:`jaxplush.stepping.adjoint.DEFAULT_MEMORY_BUDGET`, 512 MiB); beyond it, one
        checkpoint every about sqrt(steps) steps, the segments recomputed in the backward pass.
        Per rollout: under ``jax.vmap`` each batch member keeps its own.

    Returns:
      (final_state, frames (n_frames, V, 3) positions after each block, health).

    Raises:
      ValueError: ``params`` (concrete, outside jit) gives a value above 0 to a term the
        simulator leaves out (:func:`jaxplush.model.forces.check_params`), or a parameter's shape
        is not (O,) (k_structural: or (E,), :func:`jaxplush.model.forces.check_param_shapes`);
        an unknown ``gradient``, "adjoint" for a simulator it does not cover, or ``checkpoint``
        with a ``gradient`` other than "auto" or "autodiff".
    """
    if n_frames < 1 or save_every < 1:
        raise ValueError(f"n_frames and save_every must be >= 1, got {n_frames} and {save_every}")
    if gradient not in GRADIENTS:
        raise ValueError(f"unknown gradient {gradient!r}; expected one of {', '.join(GRADIENTS)}")
    if checkpoint:
        if gradient not in ("auto", "autodiff"):
            raise ValueError(f"checkpoint=True is JAX's autodiff with each frame checkpointed (gradient='autodiff'); "
                             f"it does not go with gradient={gradient!r}")
        gradient = "autodiff"
    if gradient == "adjoint" and not adjoint.adjoint_supported(sim):
        raise ValueError(f"gradient='adjoint': the fused adjoint does not cover {_not_covered(sim)}; "
                         "use gradient='checkpoint' or 'auto'")
    model.check_param_shapes(sim.topology, params)
    model.check_params(sim.terms, params)
    if health is None:
        health = initial_health(sim, state, step0)
    traced = _traced((params, state, health))
    step0 = jnp.asarray(step0, jnp.int32) if traced else _int32(step0)
    static = dict(n_frames=int(n_frames), save_every=int(save_every), checkpoint=bool(checkpoint))
    if gradient == "autodiff" or not traced:
        # concrete inputs (an eager run) cannot be differentiated: the plain call, without
        # custom_jvp's dispatch (a few hundred microseconds a call)
        return _core_jit(sim, params, state, health, step0, **static)
    warn = gradient == "auto" and not adjoint.adjoint_supported(sim)
    if gradient == "auto":
        gradient = "checkpoint" if warn else "adjoint"
    budget = adjoint.DEFAULT_MEMORY_BUDGET if memory_budget is None else int(memory_budget)
    fn = compiled.get(sim, ("rollout_gradient", static["n_frames"], static["save_every"], gradient, budget, warn),
                      lambda: _differentiable(sim, static["n_frames"], static["save_every"], gradient, budget, warn))
    return fn(params, state, health, step0)


def _traced(tree):
    """Whether any leaf of ``tree`` is a tracer (under jit, grad, vmap, ...)."""
    return any(isinstance(a, jax.core.Tracer) for a in jax.tree_util.tree_leaves(tree))


def _not_covered(sim):
    """What of ``sim`` the fused adjoint does not cover, in words."""
    out = [n for n in sim.terms.names() if n not in adjoint._ADJOINT_TERMS]
    if sim.integrator != "verlet":
        out.append(f"the {sim.integrator} integrator")
    if sim.substeps != 1:
        out.append(f"substeps={sim.substeps}")
    return ", ".join(out)


def _differentiable(sim, n_frames, save_every, gradient, memory_budget, warn=False):
    """``f(params, state, health, step0)``: the rollout, whose derivative is the fused adjoint's
    (``gradient="adjoint"``) or checkpointed autodiff's ("checkpoint").

    A ``jax.custom_jvp`` whose primal is the plain rollout (:func:`_core_jit`: not
    differentiated, nothing changes). Its JVP, for "adjoint", runs the forward pass that also
    records the states (:func:`_core_recorded`) and returns the tangents as a
    ``jax.custom_derivatives.linear_call``: a linear map of the input tangents whose forward is
    JAX's own JVP of the rollout (forward mode) and whose transpose, which reverse mode calls, is
    :func:`jaxplush.stepping.adjoint.backward` on the recorded states. So ``jax.grad`` and
    ``jax.jvp`` both work, and they are transposes of each other (up to rounding, and near-ties
    of soft-soft contact faces: the rollout carries its contact candidates, the adjoint's step
    searches afresh). Only the tangents that are not symbolic zeros enter the linear map (a
    known zero would not transpose). For "checkpoint" the JVP is JAX's own of the rollout with
    its steps checkpointed (:func:`_segmented`), so reverse mode is checkpointed autodiff;
    ``warn``: say so once (:func:`_warn_fallback`) when first differentiated.
    """
    static = dict(n_frames=n_frames, save_every=save_every)
    primal = functools.partial(_core_jit, sim, checkpoint=False, **static)

    @jax.custom_jvp
    def f(params, state, health, step0):
        return primal(params, state, health, step0)

    if gradient == "checkpoint":
        segmented = functools.partial(_core_jit, sim, checkpoint="segments", **static)

        def jvp(primals, tangents):
            params, state, health, step0 = primals
            if warn:
                _warn_fallback(sim)
            t_params, t_state = (jax.tree_util.tree_map(_instantiate, t) for t in tangents[:2])
            (final, frames, health_out), (t_final, t_frames) = _jvp_outputs(
                lambda p, s: segmented(p, s, health, step0), (params, state), (t_params, t_state))
            return (final, frames, health_out), (t_final, t_frames, _zero_like(health_out))

        f.defjvp(jvp, symbolic_zeros=True)
        return f

    forward = jax.jit(functools.partial(_core_recorded, sim, **static), static_argnames=("plan",))
    tangent_run = jax.jit(lambda params, state, health, step0, t_params, t_state: _jvp_outputs(
        lambda p, s: primal(p, s, health, step0), (params, state), (t_params, t_state))[1])
    transpose_run = jax.jit(functools.partial(_transpose, sim, save_every), static_argnames=("plan",))

    def jvp(primals, tangents):
        params, state, health, step0 = primals
        dtype = jnp.result_type(state.x)
        plan = adjoint._plan(sim, n_frames * save_every, None, memory_budget, np.dtype(dtype).itemsize)
        (final, frames, health_out), bufs = forward(params, state, health, step0, plan=plan)
        leaves, tree = jax.tree_util.tree_flatten(tuple(tangents[:2]))
        live = [not isinstance(t, jax.custom_derivatives.SymbolicZero) for t in leaves]
        zero_out = _zero_like(health_out)
        if not any(live):
            return (final, frames, health_out), (_zero_like(final), _zero_like(frames), zero_out)

        def full(lin):
            """The input tangents, the live ones from ``lin``, zeros for the others."""
            it = iter(lin)
            return jax.tree_util.tree_unflatten(tree, [next(it) if a else jnp.zeros(t.shape, t.dtype)
                                                       for a, t in zip(live, leaves)])

        def tangent_map(res, lin):                                     # forward mode
            params, state, health, step0, _ = res
            return tuple(tangent_run(params, state, health, step0, *full(lin)))

        def transpose_map(res, ct):                                    # reverse mode
            params, state, health, step0, bufs = res
            cot = transpose_run(params, bufs, step0, *ct, plan=plan)
            return [c for a, c in zip(live, jax.tree_util.tree_leaves(cot)) if a]

        res = (params, state, health, step0, bufs)
        t_final, t_frames = jax.custom_derivatives.linear_call(
            tangent_map, transpose_map, res, [t for a, t in zip(live, leaves) if a])
        return (final, frames, health_out), (t_final, t_frames, zero_out)

    f.defjvp(jvp, symbolic_zeros=True)
    return f


def _core_recorded(sim, params, state, health, step0, *, n_frames, save_every, plan):
    """The rollout (:func:`_core`) that also returns the state buffers of ``plan``."""
    return _core(sim, params, state, health, step0, n_frames, save_every, False, record=plan)


def _transpose(sim, save_every, params, bufs, step0, ct_final, ct_frames, *, plan):
    """(params cotangent, state cotangent) of a rollout for the cotangents of its final state and
    frames: the fused adjoint's reverse sweep (:func:`jaxplush.stepping.adjoint.backward`) from
    the final state's cotangent, each frame's added at its step."""
    dtype = bufs[0].dtype
    gx = jnp.swapaxes(ct_frames, 1, 2).astype(dtype)                  # (n_frames, 3, V)
    ct = sim.internal.to_internal(ct_final)                            # the transpose of to_public

    def add_frame(x_bar, n):
        j = n // save_every - 1                                        # frame j is at step (j + 1) save_every
        hit = jnp.asarray((n % save_every == 0) & (j >= 0), dtype)
        return x_bar + hit * jax.lax.dynamic_index_in_dim(gx, jnp.maximum(j, 0), keepdims=False)

    p_bar, x_bar, u_bar = adjoint.backward(sim, plan, params, bufs, add_frame, ct.x.astype(dtype),
                                           ct.v.astype(dtype), step0)
    return p_bar, sim.internal.to_public(type(ct_final)(x_bar, u_bar))


def _jvp_outputs(fn, primals, tangents):
    """((final, frames, health), (final's tangent, frames' tangent)) of ``jax.jvp(fn, ...)``."""
    out, t_out = jax.jvp(fn, primals, tangents)
    return out, (t_out[0], t_out[1])


def _instantiate(t):
    return jnp.zeros(t.shape, t.dtype) if isinstance(t, jax.custom_derivatives.SymbolicZero) else t


def _zero_like(tree):
    """Symbolic zero tangents for ``tree`` (float0 for its integer leaves)."""
    return jax.tree_util.tree_map(jax.custom_derivatives.SymbolicZero.from_primal_value, tree)


def _warn_fallback(sim):
    """Say once per process per reason that the gradient is checkpointed autodiff."""
    reason = _not_covered(sim)
    if reason not in _WARNED:
        _WARNED.add(reason)
        warnings.warn(f"jaxplush.rollout: the fused adjoint does not cover {reason}; this rollout's gradient is "
                      "checkpointed autodiff instead (several times slower; gradient='checkpoint' says so "
                      "without this warning)", GradientWarning, stacklevel=4)


def rerun_from_good(sim, params, health):
    """Re-run from the last healthy state one step at a time, at least up to the first failure.

    Returns (start step, frames (span, V, 3): the positions after steps start + 1, ...,
    start + span, health of the re-run); span >= first bad step - start.
    """
    bad = np.asarray(health.bad_step)
    start = int(health.good_step)
    span = max(int(bad[bad >= 0].min()) - start, 1) if (bad >= 0).any() else 1
    span = 1 << (span - 1).bit_length()   # a power of two: repeated searches reuse one compile
    _, frames, h = _core_jit(sim, params, health.good_state, initial_health(sim, health.good_state, start),
                             jnp.asarray(start, jnp.int32), n_frames=span, save_every=1, checkpoint=False)
    return start, frames, h


def locate_failure(sim, params, health, rerun=None):
    """Re-run from the last healthy state one step at a time to find the exact failing step.

    ``rerun``: the result of :func:`rerun_from_good` for this health, if already at hand.
    Returns (step, object, code) of the first step whose state is unhealthy, or None.
    """
    bad = np.asarray(health.bad_step)
    if not (bad >= 0).any():
        return None
    _, _, h = rerun if rerun is not None else rerun_from_good(sim, params, health)
    b = np.asarray(h.bad_step)
    # none: a contact overflow of candidate lists the re-run rebuilt at other steps (a step is
    # deterministic otherwise); fall back to the frame record
    if not (b >= 0).any():
        b, code = bad, np.asarray(health.code)
    else:
        code = np.asarray(h.code)
    cand = np.where(b >= 0, b, np.iinfo(np.int32).max)
    o = int(np.argmin(cand))
    return int(b[o]), o, int(code[o])
