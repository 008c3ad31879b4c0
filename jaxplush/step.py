"""Step factory: ``make_simulator(scene, dt) -> Simulator(init_fn, step_fn, ...)``.

The step is built for its scene (../shared/style.md §2.3): topology is closed over as
constants, and only the terms the scene needs are traced (``Simulator.terms``). Parameters
(:class:`jaxplush.types.Params`) are the traced, differentiable inputs.

Integrator ``verlet``: the report's damped Verlet
    x_{n+1} = x_n + (1 - f)(x_n - x_{n-1}) + a_n dt²,   f = 1/damping,
carried as u_n = (x_n - x_{n-1}) / dt so that no difference of nearly equal positions is
ever rounded (the float32 advice of physics.md §5):
    u_{n+1} = (1 - f) u_n + a_n dt,   x_{n+1} = x_n + u_{n+1} dt.
Velocity-dependent forces (dashpot, drag) see u_n. Initialising u_0 = v_0 - a_0 dt / 2
(x_{-1} = x_0 - v_0 dt + a_0 dt²/2) makes free fall exact (physics.md §8.1).
The floor (y >= H) is a projection after the update that sets the vertex's vertical velocity
to the one that lands it on the floor: it only ever removes energy. Pinned vertices keep their
rest position with zero velocity.
"""

from __future__ import annotations

import dataclasses
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from jaxplush import constraints, diagnostics, model
from jaxplush.types import Params, State

INTEGRATORS = ("verlet",)


@dataclasses.dataclass(frozen=True, eq=False)
class Simulator:
    """A compiled-for-its-scene simulator.

    Attributes:
      init_fn: (params, x0=None, v0=None) -> State; defaults: rest positions, zero velocity.
      step_fn: (params, state) -> state, pure, one time step of length ``dt``.
      status_fn: (params, state) -> (O,) int32 health code per object (see diagnostics).
      force_fn: (params, x, v) -> (internal force (V, 3), volume (O,) or None).
      topology, terms, dt, integrator, scene, dtype: how it was built.
      internal_step, to_internal, to_public: the same step on the internal component-major
        (3, V) state, and the layout conversions; rollouts scan ``internal_step``.
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
    internal_step: Callable = None
    to_internal: Callable = None
    to_public: Callable = None

    def params(self, scene_params=None):
        """The scene's parameters (or ``scene_params``) as a pytree of jnp arrays of this dtype."""
        p = self.scene.params if scene_params is None else scene_params
        return Params(*(jnp.asarray(np.asarray(a), self.dtype) for a in p))


def make_simulator(scene, dt, integrator="verlet", assembly="ring", terms=None):
    """Build the step for a scene.

    Args:
      scene: :class:`jaxplush.scene.Scene`.
      dt: time step, s (static: a new dt builds a new step).
      integrator: one of :data:`INTEGRATORS`.
      assembly: force assembly, "ring" (default) or "segment" (see :mod:`jaxplush.model`).
      terms: override the automatic :class:`jaxplush.model.Terms` selection (e.g. to keep a
        term compiled in while sweeping its parameter through zero).

    Returns:
      :class:`Simulator`. The dtype is float64 when ``jax_enable_x64`` is on, else float32.
    """
    if integrator not in INTEGRATORS:
        raise ValueError(f"unknown integrator {integrator!r}; available: {', '.join(INTEGRATORS)}")
    dt = float(dt)
    if not (np.isfinite(dt) and dt > 0):
        raise ValueError(f"dt must be a positive number, got {dt!r}")
    dtype = jnp.result_type(float)
    topo = model.build_topology(scene)
    terms = model.Terms.for_scene(scene) if terms is None else terms
    kernel = model.make_force_fn(topo, terms, scene.temperature, assembly)
    gravity = np.asarray(scene.gravity, np.float64)[:, None]
    fixed = topo.fixed

    # Internally everything is component-major, (3, V): see model.make_force_fn.
    def accel(params, x, v):
        f, volume = kernel(params, x, v)
        a = f * (1.0 / model.vertex_mass(topo, params))
        if terms.gravity:
            with jax.named_scope("gravity"):
                a = a + jnp.asarray(gravity, x.dtype)
        return a, volume

    constrain = constraints.make_constrain(topo, terms, scene, dt)

    def internal_init(params, x0=None, v0=None):
        x = jnp.asarray(topo.x0 if x0 is None else x0, dtype).T
        v = jnp.zeros_like(x) if v0 is None else jnp.asarray(v0, dtype).T
        a0, _ = accel(params, x, v)
        u = v - 0.5 * dt * a0
        if terms.fixed:
            u = u.at[:, fixed].set(0.0)
        return State(x, u)

    def internal_step(params, state):
        x, u = state
        a, _ = accel(params, x, u)
        if terms.verlet_damping:
            with jax.named_scope("verlet_damping"):
                f = model.per_vertex(topo, _damping_factor(params.damping))
                u_new = (1.0 - f) * u + a * dt
        else:
            u_new = u + a * dt
        x_new = x + u_new * dt
        x_new, u_new = constrain(x, x_new, u_new)
        return State(x_new, u_new)

    def init_fn(params, x0=None, v0=None):
        return to_public(internal_init(params, x0, v0))

    def step_fn(params, state):
        return to_public(internal_step(params, to_internal(state)))

    def force_fn(params, x, v):
        f, volume = kernel(params, jnp.asarray(x).T, jnp.asarray(v).T)
        return f.T, volume

    def status_fn(params, state):
        return diagnostics.object_status(topo, terms, state.x)

    return Simulator(init_fn=init_fn, step_fn=step_fn, status_fn=status_fn, force_fn=force_fn,
                     topology=topo, terms=terms, dt=dt, integrator=integrator, scene=scene, dtype=dtype,
                     internal_step=internal_step, to_internal=to_internal, to_public=to_public)


def to_internal(state):
    """(V, 3) public state -> (3, V) internal layout."""
    return State(*(jnp.asarray(a).T for a in state))


def to_public(state):
    """(3, V) internal state -> (V, 3) public layout."""
    return State(*(a.T for a in state))


def _damping_factor(damping):
    """f = 1/D for D > 0, else 0 (no damping), with a gradient that is finite everywhere."""
    safe = jnp.where(damping > 0, damping, 1.0)
    return jnp.where(damping > 0, 1.0 / safe, 0.0)
