"""Largest stable explicit time step (physics.md §4).

omega_max² = lambda_max(M^-1 K) with K = -df/dx the stiffness at the given positions (springs
and gas), found by power iteration on the symmetric M^-1/2 K M^-1/2 with Jacobian-vector
products of the force (no matrix is formed). Velocity damping (dashpot, drag, the report's
Verlet damping) tightens the limit: for the Verlet/symplectic update of a mode with frequency
omega and damping rate gamma the iteration matrix is stable iff dt² omega² + 2 dt gamma < 4,
so dt_max = (sqrt(gamma² + 4 omega²) - gamma) / omega², with gamma_max = lambda_max(M^-1 C)
found the same way from C = -df/dv.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxplush import model
from jaxplush.types import GAS_CONSTANT


class StabilityEstimate(NamedTuple):
    """dt_max: largest stable explicit dt (s); omega_max (rad/s); gamma_max (1/s);
    dt_gershgorin: the always-safe bound sqrt(2 m / (k n_max)) (undamped, springs only)."""

    dt_max: float
    omega_max: float
    gamma_max: float
    dt_gershgorin: float


def _power(op, n, dtype, iters, key):
    z = jax.random.normal(key, (n, 3), dtype)
    z = z / jnp.linalg.norm(z)

    def body(_, z):
        w = op(z)
        return w / (jnp.linalg.norm(w) + jnp.finfo(dtype).tiny)

    z = jax.lax.fori_loop(0, iters, body, z)
    return jnp.vdot(z, op(z))  # Rayleigh quotient


def inflated(sim, params, x):
    """x with each gas object scaled about its centroid by s* = (1 + sqrt(1 + 12 nRT/(k sum L²))) / 2."""
    topo = sim.topology
    x = np.array(x, np.float64)
    nrt = np.asarray(params.nmol, np.float64) * GAS_CONSTANT * sim.scene.temperature
    k = np.asarray(params.k_structural, np.float64)
    for o, (a, b) in enumerate(topo.vertex_slices):
        l2 = float(np.sum(topo.rest_length[topo.edge_object == o] ** 2))
        if nrt[o] > 0 and k[o] > 0:
            s = 0.5 * (1 + np.sqrt(1 + 12 * nrt[o] / (k[o] * l2)))
            c = x[a:b].mean(axis=0)
            x[a:b] = c + s * (x[a:b] - c)
    return jnp.asarray(x, sim.dtype)


def estimate(sim, params, x=None, iters=100, seed=0):
    """Estimate the stable explicit dt of ``sim`` at positions ``x`` (default: rest).

    Args:
      sim: :class:`jaxplush.step.Simulator`.
      params: :class:`jaxplush.types.Params`.
      x: (V, 3) positions at which to linearise.
      iters: power iterations.

    Returns:
      :class:`StabilityEstimate`.
    """
    topo = sim.topology
    dtype = sim.dtype
    x = jnp.asarray(topo.x0 if x is None else x, dtype)
    free = np.ones((topo.n_vertices, 1))
    free[topo.fixed] = 0.0
    v0 = jnp.zeros_like(x)

    @jax.jit
    def run(params, x):
        m = model.vertex_mass(topo, params)
        s = (free / jnp.sqrt(m)[:, None]).astype(dtype)  # M^-1/2, pinned vertices removed

        def stiff(z):
            _, df = jax.jvp(lambda y: sim.force_fn(params, y, v0)[0], (x,), (s * z,))
            return -s * df

        def damp(z):
            _, df = jax.jvp(lambda w: sim.force_fn(params, x, w)[0], (v0,), (s * z,))
            return -s * df

        key = jax.random.PRNGKey(seed)
        lam = _power(stiff, topo.n_vertices, dtype, iters, key)
        gam = _power(damp, topo.n_vertices, dtype, iters, key) if (sim.terms.dashpot or sim.terms.drag) else 0.0
        return lam, gam

    lam, gam = (float(a) for a in run(params, x))
    if sim.terms.gas:
        # The gas inflates the body, pre-tensioning its springs and raising omega_max: also
        # linearise at the uniform inflation s* that balances springs and gas (physics.md §8.5).
        lam = max(lam, float(run(params, inflated(sim, params, x))[0]))
    omega = float(np.sqrt(max(lam, 0.0)))
    gamma = max(gam, 0.0)
    if sim.terms.verlet_damping:
        d = np.asarray(params.damping)
        f = np.where(d > 0, 1.0 / np.where(d > 0, d, 1.0), 0.0).max()
        gamma += float(-np.log1p(-min(f, 1 - 1e-12)) / sim.dt)
    dt_max = float((np.sqrt(gamma ** 2 + 4 * omega ** 2) - gamma) / omega ** 2) if omega > 0 else float("inf")
    k = np.asarray(params.k_structural)[topo.vertex_object]
    m = np.asarray(params.total_weight)[topo.vertex_object] / topo.count[topo.vertex_object]
    val = topo.ring_mask.sum(axis=1)
    kn = k * val
    with np.errstate(divide="ignore"):
        dt_g = float(np.min(np.where(kn > 0, np.sqrt(2 * m / np.where(kn > 0, kn, 1)), np.inf)))
    return StabilityEstimate(dt_max=dt_max, omega_max=omega, gamma_max=gamma, dt_gershgorin=dt_g)
