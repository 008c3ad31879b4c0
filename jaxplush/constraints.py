"""Position-level constraints applied after every integrator update: the floor and pinned vertices.

``make_constrain(topo, terms, scene, dt)`` returns ``constrain(x_old, x_new, v_new) -> (x, v)`` on
component-major (3, V) arrays, where ``v_new`` is the velocity the integrator carries
(``(x_new - x_old) / dt`` for Verlet's half-step velocity and the Euler-type schemes). Every
integrator calls it once per step, so floor response and pins live in one place.

Floor (y >= H): a projection that sets the vertex's vertical velocity to the one that lands it
on the floor; it only ever removes energy (physics.md §6). Pinned vertices keep their rest
position with zero velocity.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np


def make_constrain(topo, terms, scene, dt):
    """Build ``constrain(x_old, x_new, v_new) -> (x, v)`` for a scene (only needed parts traced)."""
    fixed = topo.fixed
    floor = scene.floor
    x0_soa = np.ascontiguousarray(topo.x0.T)

    def constrain(x_old, x, v):
        if terms.floor:
            with jax.named_scope("floor"):
                below = x[1] < floor
                v = v.at[1].set(jnp.where(below, (floor - x_old[1]) / dt, v[1]))
                x = x.at[1].set(jnp.maximum(x[1], floor))
        if terms.fixed:
            with jax.named_scope("fixed"):
                x = x.at[:, fixed].set(jnp.asarray(x0_soa[:, fixed], x.dtype))
                v = v.at[:, fixed].set(0.0)
        return x, v

    return constrain
