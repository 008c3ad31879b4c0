"""Step factory: ``make_simulator(scene, dt) -> Simulator(init_fn, step_fn, ...)``.

The step is built for its scene: topology is closed over as
constants, and only the terms the scene needs are traced (``Simulator.terms``). Parameters
(:class:`jaxplush.types.Params`) are the traced, differentiable inputs.

Integrators (:mod:`jaxplush.stepping.integrators`, chosen by name): ``verlet`` (default, the report's
damped Verlet carried as a half-step velocity), ``euler``, ``symplectic_euler``, ``rk4``,
``mesit`` (the report's unsound "simplified implicit" update, kept for comparison) and
``implicit_euler`` (Baraff-Witkin, matrix-free CG). Each runs ``substeps`` steps of
h = dt / substeps per call, on the internal component-major (3, V) state, and applies the
shared floor/pin hook (:mod:`jaxplush.stepping.constraints`) after every (sub)step.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxplush.stepping import compiled
from jaxplush.stepping import constraints
from jaxplush.stepping import diagnostics
from jaxplush.stepping import integrators
from jaxplush.model import forces as model
from jaxplush.types import Params

INTEGRATORS = integrators.INTEGRATORS


@dataclasses.dataclass(frozen=True, eq=False)
class Simulator:
    """A compiled-for-its-scene simulator.

    Attributes:
      init_fn: (params, x0=None, v0=None) -> state; defaults: rest positions, zero velocity.
      step_fn: (params, state, step=None) -> state, pure, one time step of length ``dt``
        (``substeps`` integrator steps of ``dt / substeps``). ``step``: the int index n of the
        state being advanced (t = n dt -> (n + 1) dt); required for a scene with driven vertices,
        ignored (and not traced) otherwise.
      status_fn: (params, state) -> (O,) int32 health code per object (see diagnostics); with
        soft-soft contact also ``CONTACT_OVERFLOW`` for an object whose contact candidates a fresh
        search at the state's positions would overflow.
      force_fn: (params, x, v) -> (internal force (V, 3), volume (O,) or None).
      velocity_fn: (params, state) -> (V, 3) velocity at the state's time (Verlet carries the
        half-step velocity; this returns v_n = u_n + a_n h/2).
      topology, terms, dt, integrator, substeps, scene, dtype: how it was built.
      internal: :class:`Internal`, the step on the internal layout (for rollouts, sweeps and
        gradients inside jaxplush; not needed to use a simulator).
      key: what the compiled program depends on (:mod:`jaxplush.stepping.compiled`): simulators with
        equal keys compare equal, so they share compiled code. Build variants with
        :func:`make_simulator`, not ``dataclasses.replace``, which would keep the key.

    Methods: :meth:`params` (the parameter pytree), :meth:`rollout` (a compiled run).
    """

    init_fn: Callable
    step_fn: Callable
    status_fn: Callable
    force_fn: Callable
    topology: model.Topology
    terms: model.Terms
    dt: float
    integrator: str
    scene: object
    dtype: object
    internal: "Internal" = None
    substeps: int = 1
    velocity_fn: Callable = None
    key: tuple = None

    def __eq__(self, other):
        if self is other:
            return True
        if not isinstance(other, Simulator) or self.key is None or other.key is None:
            return False
        return self.key == other.key

    def __hash__(self):
        return hash(self.key) if self.key is not None else object.__hash__(self)

    @property
    def h(self):
        """The integrator's (sub)step length dt / substeps, s."""
        return self.dt / self.substeps

    def rollout(self, params, state, n_frames, save_every=1, checkpoint=False, **kwargs):
        """``jaxplush.rollout(self, ...)``: (final state, frames (n_frames, V, 3), health);
        keywords (``gradient``, ``memory_budget``, ``health``, ``step0``) as there."""
        from jaxplush.stepping.rollouts import rollout
        return rollout(self, params, state, n_frames, save_every, checkpoint=checkpoint, **kwargs)

    def params(self, scene_params=None):
        """The scene's parameters (or ``scene_params``) as a pytree of jnp arrays of this dtype.

        Raises ValueError when a value above 0 goes to a term this simulator leaves out (say
        ``drag`` for a scene without drag), which would otherwise be ignored, or when a parameter
        is not (O,) (``k_structural`` may also be an (E,) per-edge field)."""
        p = self.scene.params if scene_params is None else scene_params
        # jnp.asarray(np.asarray(a), self.dtype) converts on the host too, then dispatches a
        # one-op compiled conversion: device_put the host array instead (the same array; no
        # program to trace, lower and load from the persistent cache in a fresh process)
        out = Params(*(jax.device_put(np.asarray(np.asarray(a), self.dtype)) for a in p))
        model.check_param_shapes(self.topology, out)
        model.check_params(self.terms, out)
        return out


class Internal(NamedTuple):
    """A simulator's step on the internal, component-major (3, V) layout.

    step: (params, state, step=None) -> state on that layout (rollouts scan it; ``step`` as in
    ``Simulator.step_fn``); to_internal, to_public:
    the layout conversions of a state; coherent: for scenes with soft-soft contact, a
    :class:`CoherentStep` (the step with the contact candidate lists carried from step to step,
    which rollouts scan instead), None otherwise; overflow: for scenes with soft-soft contact
    between objects, ``overflow(x) -> (O,) bool`` at internal positions x (3, V), the objects whose
    candidates a fresh search there would overflow (:func:`jaxplush.model.contact.make_overflow_check`;
    for paths that carry no candidate cache), None otherwise.
    """

    step: Callable
    to_internal: Callable
    to_public: Callable
    coherent: object = None
    overflow: object = None


class CoherentStep(NamedTuple):
    """The step with soft-soft contact candidates carried between steps (temporal coherence).

    ``init(x) -> cache`` searches the candidate lists at internal positions x (3, V);
    ``step(params, state, cache, step=None) -> (state, cache)`` (``step`` as in
    ``Simulator.step_fn``) advances one step with the cached lists and
    updates them after every substep (:func:`jaxplush.model.contact.make_contact`: rebuilt once a vertex
    has moved half the skin, otherwise each query's nearest vertex is walked along the mesh).
    """

    init: Callable
    step: Callable


def make_simulator(scene, dt, integrator="verlet", assembly="ring", terms=None, substeps=1, cg_tol=None,
                   cg_maxiter=integrators.CG_MAXITER, coherent_contact=True):
    """Build the step for a scene.

    Args:
      scene: :class:`jaxplush.scene.parse.Scene`.
      dt: time step, s (static: a new dt builds a new step).
      integrator: one of :data:`INTEGRATORS` (see :mod:`jaxplush.stepping.integrators` for order,
        stability and damping of each).
      assembly: force assembly, "ring" (default) or "segment" (see :mod:`jaxplush.model.forces`).
      terms: override the automatic :class:`jaxplush.model.forces.Terms` selection (e.g. to keep a
        term compiled in while sweeping its parameter through zero).
      substeps: integrator steps per ``step_fn`` call, each of length h = dt / substeps (static).
        The floor and pins are applied after every substep; the report's damping D keeps its
        meaning per time step dt (each substep multiplies the velocity by (1 - 1/D)^(1/substeps)).
      cg_tol, cg_maxiter: ``implicit_euler`` only: relative CG residual (default 1e-5 in
        float32, 1e-10 in float64) and the static cap on CG iterations per step.
      coherent_contact: with soft-soft contact, let rollouts carry the contact candidate lists
        from step to step (``Simulator.internal.coherent``; default). False: every step searches afresh
        (the same forces up to the rare step where the two disagree on a query's nearest vertex).

    Returns:
      :class:`Simulator`. The dtype is float64 when ``jax_enable_x64`` is on, else float32.
    """
    dt, substeps = _checked_step_args(integrator, dt, substeps)
    h = dt / substeps
    dtype = jnp.result_type(float)
    topo = compiled.topology(scene)
    model.check_precision(topo, dtype, scene.path, getattr(scene, "driven", ()))
    terms = model.Terms.for_scene(scene) if terms is None else terms
    kernel, cache_ops = model.make_force_fn(topo, terms, scene.temperature, assembly, h=h, with_cache=True)
    drive = constraints.Drive(scene, h) if terms.driven else None
    system = integrators.System(
        topo=topo, terms=terms, kernel=kernel, gravity=np.asarray(scene.gravity, np.float64)[:, None],
        constrain=constraints.make_constrain(topo, terms, scene, h, drive=drive), h=h, temperature=scene.temperature,
        substeps=substeps, drive=drive)
    scheme = integrators.build(integrator, system, cg_tol=cg_tol, cg_maxiter=cg_maxiter)
    coherent = None
    if cache_ops is not None and coherent_contact:
        coherent = _coherent_step(system, kernel, cache_ops, integrator, substeps, cg_tol, cg_maxiter)

    # Internally everything is component-major, (3, V): see model.make_force_fn.
    internal_step = _indexed(integrators.repeat_substeps(scheme.step, substeps, indexed=drive is not None),
                             drive is not None)

    overflow = None
    if terms.contact:
        from jaxplush.model import contact as _contact
        overflow = _contact.make_overflow_check(topo, terms.contact)
    fns = _public_fns(topo, terms, dtype, scheme, internal_step, kernel, overflow)

    key = (scene.fingerprint, dt, integrator, assembly, terms, substeps, np.dtype(dtype).str, cg_tol, int(cg_maxiter),
           bool(coherent_contact))
    return Simulator(**fns, topology=topo, terms=terms, dt=dt, integrator=integrator, scene=scene, dtype=dtype,
                     internal=Internal(internal_step, to_internal, to_public, coherent, overflow),
                     substeps=substeps, key=key)


def _checked_step_args(integrator, dt, substeps):
    """(dt as a float, substeps as an int), or ValueError for an unknown integrator, a dt that is
    not a positive number or substeps that is not a positive integer."""
    if integrator not in INTEGRATORS:
        raise ValueError(f"unknown integrator {integrator!r}; available: {', '.join(INTEGRATORS)}")
    dt = float(dt)
    if not (np.isfinite(dt) and dt > 0):
        raise ValueError(f"dt must be a positive number, got {dt!r}")
    if isinstance(substeps, bool) or int(substeps) != substeps or substeps < 1:
        raise ValueError(f"substeps must be a positive integer, got {substeps!r}")
    return dt, int(substeps)


def _indexed(repeated, driven):
    """The internal step ``(params, state, step=None)`` from ``repeated``: without driven vertices
    ``repeated(params, state)`` (``step`` ignored, nothing traced for it); with them
    ``repeated(params, state, step)``, and a missing ``step`` is an error."""
    if not driven:
        return lambda params, state, step=None: repeated(params, state)

    def step_at(params, state, step=None):
        if step is None:
            raise constraints.missing_step_error()
        return repeated(params, state, step)
    return step_at


def _coherent_step(system, kernel, cache_ops, integrator, substeps, cg_tol, cg_maxiter):
    """The :class:`CoherentStep` of a scheme with soft-soft contact: ``substeps`` integrator steps,
    the force kernel reading the carried candidate lists, the lists updated after each."""
    def coherent_substep(params, state, cache, k=None):
        # the same scheme, its force kernel reading the carried candidate lists
        sys_c = dataclasses.replace(system, kernel=functools.partial(kernel, cache=cache))
        state = integrators.build(integrator, sys_c, cg_tol=cg_tol, cg_maxiter=cg_maxiter).step(params, state, k)
        return state, cache_ops.update(cache, state.x)

    driven = system.drive is not None
    if driven:
        repeated = integrators.repeat_substeps(lambda params, c, k: coherent_substep(params, *c, k), substeps,
                                               indexed=True)
    else:
        repeated = integrators.repeat_substeps(lambda params, c: coherent_substep(params, *c), substeps)
    step = _indexed(repeated, driven)
    return CoherentStep(init=cache_ops.init,
                        step=lambda params, state, cache, step_index=None: step(params, (state, cache), step_index))


def _public_fns(topo, terms, dtype, scheme, internal_step, kernel, overflow):
    """The :class:`Simulator`'s functions on the public (V, 3) layout: init_fn, step_fn,
    status_fn, force_fn and velocity_fn (a dict of them)."""
    def internal_init(params, x0=None, v0=None):
        x = jnp.asarray(topo.x0 if x0 is None else x0, dtype).T
        v = jnp.zeros_like(x) if v0 is None else jnp.asarray(v0, dtype).T
        return scheme.init(params, x, v)

    def init_fn(params, x0=None, v0=None):
        return to_public(internal_init(params, x0, v0))

    def step_fn(params, state, step=None):
        return to_public(internal_step(params, to_internal(state), step))

    def force_fn(params, x, v):
        f, volume = kernel(params, jnp.asarray(x).T, jnp.asarray(v).T)
        return f.T, volume

    def status_fn(params, state):
        code = diagnostics.object_status(topo, terms, state.x)
        if overflow is not None:
            code = diagnostics.with_overflow(code, overflow(jnp.asarray(state.x).T))
        return code

    def velocity_fn(params, state):
        return scheme.velocity(params, to_internal(state)).T

    # Each is jitted: called directly (a notebook's first ``sim.init_fn(p)``, a test's force check)
    # it is one compiled program instead of about a hundred one-op programs run eagerly, each
    # compiled on its first call (4.3 s against 0.23 s for a 162-vertex ball, cold; benchmarks/RESULTS.md);
    # inside a user's own jit, grad or vmap it is inlined as before.
    # (a scene without driven vertices ignores ``step``: it is dropped before the compiled step, so
    # passing one or not is the same program)
    jit_step = jax.jit(step_fn)
    if not terms.driven:
        def public_step(params, state, step=None):
            return jit_step(params, state)
    else:
        public_step = jit_step
    return dict(init_fn=jax.jit(init_fn), step_fn=public_step, status_fn=jax.jit(status_fn),
                force_fn=jax.jit(force_fn), velocity_fn=jax.jit(velocity_fn))


def to_internal(state):
    """(V, 3) public state -> (3, V) internal layout (any integrator's state NamedTuple)."""
    return type(state)(*(jnp.asarray(a).T for a in state))


def to_public(state):
    """(3, V) internal state -> (V, 3) public layout (any integrator's state NamedTuple)."""
    return type(state)(*(a.T for a in state))
