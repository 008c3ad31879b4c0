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
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxplush.stepping import compiled
from jaxplush.stepping import diagnostics
from jaxplush.model import forces as model
from jaxplush.types import State


class Health(NamedTuple):
    """Carried health record of a rollout; a batched rollout (:mod:`jaxplush.fitting.batched`)
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
    neg = jnp.full((o,), -1, jnp.int32)
    return Health(jnp.zeros((o,), jnp.int32), neg, neg, state, jnp.asarray(step, jnp.int32))


def _core(sim, params, state, health, step0, n_frames, save_every, checkpoint):
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

    if driven:
        def steps(s, first):
            return jax.lax.scan(lambda c, n: (one(c, n), None), s, first + jnp.arange(save_every, dtype=jnp.int32))[0]
    else:
        def steps(s, first):
            return jax.lax.scan(lambda c, _: (one(c, None), None), s, None, length=save_every)[0]

    if checkpoint:
        steps = jax.checkpoint(steps)

    def frame(carry, i):
        c, h = carry
        c = steps(c, step0 + i * save_every if driven else None)
        s = c[0]
        step = step0 + (i + 1) * save_every
        if overflow is None:
            code = sim.status_fn(params, sim.internal.to_public(s))
        else:
            # a contact overflow since the start of this rollout is the object's code
            code = diagnostics.with_overflow(diagnostics.object_status(sim.topology, sim.terms, s.x.T), overflow(c))
        return (c, h.advance(code, step, s)), s.x

    (carry, health), frames = jax.lax.scan(frame, (carry0, health), jnp.arange(n_frames, dtype=jnp.int32))
    state = carry[0]
    health = health._replace(good_state=sim.internal.to_public(health.good_state))
    return sim.internal.to_public(state), jnp.swapaxes(frames, 1, 2), health


def _core_jit(sim, params, state, health, step0, *, n_frames, save_every, checkpoint):
    fn = compiled.get(sim, "rollout", lambda: jax.jit(functools.partial(_core, sim),
                                                       static_argnames=("n_frames", "save_every", "checkpoint")))
    return fn(params, state, health, step0, n_frames=n_frames, save_every=save_every, checkpoint=checkpoint)


def rollout(sim, params, state, n_frames, save_every=1, checkpoint=False, health=None, step0=0):
    """Run ``n_frames * save_every`` steps, saving positions every ``save_every`` steps.

    Differentiable with respect to ``params`` and ``state`` (reverse and forward mode).

    Args:
      sim: :class:`jaxplush.stepping.step.Simulator`.
      params: :class:`jaxplush.types.Params` pytree.
      state: initial :class:`jaxplush.types.State` (from ``sim.init_fn``).
      n_frames: number of saved frames (static).
      save_every: steps between saved frames (static).
      checkpoint: wrap each frame's steps in ``jax.checkpoint`` so reverse-mode memory grows
        with frames, not steps.
      health: a :class:`Health` to continue (for chunked runs); default fresh.
      step0: step number of ``state`` (for chunked runs).

    Returns:
      (final_state, frames (n_frames, V, 3) positions after each block, health).

    Raises:
      ValueError: ``params`` (concrete, outside jit) gives a value above 0 to a term the
        simulator leaves out (:func:`jaxplush.model.forces.check_params`), or a parameter's shape
        is not (O,) (k_structural: or (E,), :func:`jaxplush.model.forces.check_param_shapes`).
    """
    if n_frames < 1 or save_every < 1:
        raise ValueError(f"n_frames and save_every must be >= 1, got {n_frames} and {save_every}")
    model.check_param_shapes(sim.topology, params)
    model.check_params(sim.terms, params)
    if health is None:
        health = initial_health(sim, state, step0)
    return _core_jit(sim, params, state, health, jnp.asarray(step0, jnp.int32),
                     n_frames=int(n_frames), save_every=int(save_every), checkpoint=bool(checkpoint))


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
