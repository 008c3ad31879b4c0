"""Position-level constraints applied after every integrator update: the floor and pinned vertices.

``make_constrain(topo, terms, scene, dt)`` returns ``constrain(x_old, x_new, v_new) -> (x, v)`` on
component-major (3, V) arrays, where ``v_new`` is the velocity the integrator carries
(``(x_new - x_old) / dt`` for Verlet's half-step velocity and the Euler-type schemes). Every
integrator calls it once per step, so floor response and pins live in one place.

Floor (y >= H): a projection that sets the vertex's vertical velocity to the one that lands it
on the floor; it only ever removes energy (docs/model.md §6). Pinned vertices keep their rest
position with zero velocity.

Optional floor response (scene keywords; absent = the plain projection above, not traced):

* ``floor_restitution E``: a vertex that hits the floor faster than v_rest = 2 |g_y| dt (Jolt's
  threshold, so resting vertices do not jitter) leaves it with E times its incoming normal speed.
  The switch is a sigmoid of width v_rest / 2 in the impact speed, so the response is smooth.
* ``floor_friction MU``: Coulomb friction in the projection (Jolt-style, docs/model.md §6). The
  projection changes a contacting vertex's normal velocity by dv_n >= 0; its tangential
  velocity v_t then loses at most MU dv_n: v_t <- v_t max(0, 1 - MU dv_n / sqrt(|v_t|² + eps²)),
  eps = 1e-3 v_rest, and its tangential displacement this step is reduced to match. A vertex at
  rest sticks while |g_t| < MU |g_n| (the friction angle) and slides otherwise.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np


def landing_velocity(y_old, height, h):
    """The floor projection's vertical velocity (H - y_old) / h: the one that lands a vertex that
    starts the step at height y_old exactly on the floor H after a step of h. Every engine's
    projection (this module's hook, the batched engine's written-out plain floor) uses it; the
    fused adjoint's floor mask is its transpose (d/dy_old = -1/h)."""
    return (height - y_old) / h


def make_constrain(topo, terms, scene, dt):
    """Build ``constrain(x_old, x_new, v_new) -> (x, v)`` for a scene (only needed parts traced)."""
    fixed = topo.fixed
    floor = scene.floor
    x0_soa = np.ascontiguousarray(topo.x0.T)
    mu = float(terms.floor_friction)
    restitution = float(terms.floor_restitution)
    v_rest = max(2.0 * abs(float(scene.gravity[1])) * dt, 1e-9)

    def constrain(x_old, x, v):
        if terms.floor:
            with jax.named_scope("floor"):
                below = x[1] < floor
                vy_in = v[1]
                vy = landing_velocity(x_old[1], floor, dt)
                if restitution:
                    with jax.named_scope("floor_restitution"):
                        speed = -vy_in
                        w = jax.nn.sigmoid((speed - v_rest) / (0.5 * v_rest))
                        vy = vy + w * (restitution * speed - vy)
                v = v.at[1].set(jnp.where(below, vy, vy_in))
                x = x.at[1].set(jnp.maximum(x[1], floor))
                if mu:
                    with jax.named_scope("floor_friction"):
                        dvn = jnp.maximum(vy - vy_in, 0.0)
                        vt2 = v[0] * v[0] + v[2] * v[2] + (1e-3 * v_rest) ** 2
                        keep = jnp.maximum(1.0 - mu * dvn * jax.lax.rsqrt(vt2), 0.0)
                        lose = jnp.where(below, 1.0 - keep, 0.0)       # fraction of v_t removed
                        for c in (0, 2):
                            x = x.at[c].add(-lose * v[c] * dt)
                            v = v.at[c].add(-lose * v[c])
        if terms.fixed:
            with jax.named_scope("fixed"):
                x = x.at[:, fixed].set(jnp.asarray(x0_soa[:, fixed], x.dtype))
                v = v.at[:, fixed].set(0.0)
        return x, v

    return constrain
