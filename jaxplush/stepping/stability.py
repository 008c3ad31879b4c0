"""Largest stable explicit time step (docs/model.md §4).

omega_max² = lambda_max(M^-1 K) with K = -df/dx the stiffness at the given positions (springs
and gas; soft-soft contact, which acts only where objects touch, is left out), found by power
iteration on the symmetric M^-1/2 K M^-1/2 with Jacobian-vector products of the force (no
matrix is formed). Velocity damping (dashpot, drag, the report's Verlet damping) tightens the limit: for the Verlet/symplectic update of a mode with frequency
omega and damping rate gamma the iteration matrix is stable iff dt² omega² + 2 dt gamma < 4,
so dt_max = (sqrt(gamma² + 4 omega²) - gamma) / omega², with gamma_max = lambda_max(M^-1 C)
(the report's per-step damping D enters as 4 - 2/D in place of 4, see _estimate_from)
found the same way from C = -df/dv.

Other integrators (:func:`integrator_limit`): the same worst mode (omega_max, gamma_max) is put
into each scheme's amplification factor R(h lambda), lambda = -gamma/2 ± sqrt(gamma²/4 - omega²),
and the largest h with |R| <= 1 is found by bisection: RK4 (undamped: h < 2 sqrt(2)/omega_max),
explicit Euler and Mesit's update (undamped: no stable h; damped: h < gamma/omega²), and
implicit Euler (no limit). All limits are per integrator (sub)step h = dt / substeps.
"""

from __future__ import annotations

import weakref
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxplush.stepping import compiled
from jaxplush.model import forces as model
from jaxplush.model.layout import vertex_stiffness_max
from jaxplush.types import GAS_CONSTANT, VOLUME_EPS


class StabilityEstimate(NamedTuple):
    """dt_max: largest stable explicit dt (s); omega_max (rad/s); gamma_max (1/s, all velocity
    damping, the report's D as its drag rate); dt_gershgorin: the always-safe bound
    sqrt(2 m / (k n_max)) (undamped, springs only); gamma_forces: the damping rate of the dashpot
    and drag alone (1/s)."""

    dt_max: float
    omega_max: float
    gamma_max: float
    dt_gershgorin: float
    gamma_forces: float = float("nan")


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
    k = model.object_stiffness(topo, np.asarray(params.k_structural, np.float64))
    for o, (a, b) in enumerate(topo.vertex_slices):
        l2 = float(np.sum(topo.rest_length[topo.edge_object == o] ** 2))
        if nrt[o] > 0 and k[o] > 0:
            s = 0.5 * (1 + np.sqrt(1 + 12 * nrt[o] / (k[o] * l2)))
            c = x[a:b].mean(axis=0)
            x[a:b] = c + s * (x[a:b] - c)
    return jnp.asarray(x, sim.dtype)


def _runner(sim, iters, seed):
    """jit(params, x) -> (lambda_max(M^-1 K), lambda_max(M^-1 C)) for ``sim``, compiled once per
    program (:mod:`jaxplush.stepping.compiled`), so repeated estimates (simulate's dt check, its failure
    hint, a rebuilt simulator of the same scene) compile once."""
    return compiled.get(sim, ("estimate", iters, seed), lambda: _build_runner(sim, iters, seed))


def _build_runner(sim, iters, seed):
    topo, dtype, damped = sim.topology, sim.dtype, sim.terms.dashpot or sim.terms.drag
    force_fn = _mesh_force_fn(sim)
    free = np.ones((topo.n_vertices, 1))
    free[topo.fixed] = 0.0

    def run(params, x):
        m = model.vertex_mass(topo, params)
        s = (free / jnp.sqrt(m)[:, None]).astype(dtype)  # M^-1/2, pinned vertices removed
        v0 = jnp.zeros_like(x)

        def stiff(z):
            _, df = jax.jvp(lambda y: force_fn(params, y, v0), (x,), (s * z,))
            return -s * df

        def damp(z):
            _, df = jax.jvp(lambda w: force_fn(params, x, w), (v0,), (s * z,))
            return -s * df

        key = jax.random.PRNGKey(seed)
        lam = _power(stiff, topo.n_vertices, dtype, iters, key)
        gam = _power(damp, topo.n_vertices, dtype, iters, key) if damped else 0.0
        return lam, gam

    return compiled.jit_once(run)          # (runs once or twice per estimate)


def _mesh_force_fn(sim):
    """``force(params, x (V, 3), v (V, 3))``: the simulator's force without soft-soft contact.

    The estimate linearises the springs, the gas and the velocity damping (and a smooth floor)
    at the given positions; soft-soft contact is left out. Its penalty acts only where objects
    touch, as the floor projection does, so at the rest shape it adds nothing, and compiling its
    search and narrow phase into the power iteration's Jacobian-vector products cost several
    times the rest of the program (benchmarks/RESULTS.md, 2026-11-29)."""
    if not sim.terms.contact:
        return lambda params, x, v: sim.force_fn(params, x, v)[0]
    import dataclasses
    kernel = model.make_force_fn(sim.topology, dataclasses.replace(sim.terms, contact=None), sim.scene.temperature)
    return lambda params, x, v: kernel(params, x.T, v.T)[0].T


def estimate(sim, params, x=None, iters=100, seed=0):
    """Estimate the stable explicit dt of ``sim`` at positions ``x`` (default: rest).

    Args:
      sim: :class:`jaxplush.stepping.step.Simulator`.
      params: :class:`jaxplush.types.Params`.
      x: (V, 3) positions at which to linearise.
      iters: power iterations.

    Returns:
      :class:`StabilityEstimate`.
    """
    topo = sim.topology
    x = topo.x0 if x is None else x
    # a concrete x converted on the host (no one-op conversion program per dtype)
    x = jnp.asarray(x, sim.dtype) if isinstance(x, jax.Array) else jax.device_put(np.asarray(x, sim.dtype))
    run = _runner(sim, iters, seed)
    lam, gam = (float(a) for a in run(params, x))
    if sim.terms.gas:
        # The gas inflates the body, pre-tensioning its springs and raising omega_max: also
        # linearise at the uniform inflation s* that balances springs and gas (docs/model.md §8.5).
        lam = max(lam, float(run(params, inflated(sim, params, x))[0]))
    b = bound(sim, params, None if x is None else np.asarray(x, np.float64))
    if not (np.isfinite(lam) and np.isfinite(gam)) or (b.omega_max > 0 and not lam > (1e-3 * b.omega_max) ** 2):
        # absurd values (k 1e30, a mass of 1e-30 kg, ...) overflow the float32 power iteration
        # (to inf, or to a vector that vanishes): the closed-form bound (float64 numpy) still
        # gives a finite, safe answer
        return b
    return _estimate_from(sim, params, float(np.sqrt(max(lam, 0.0))), max(gam, 0.0))


def _estimate_from(sim, params, omega, gamma):
    """The :class:`StabilityEstimate` of a worst mode (omega, gamma from dashpot and drag), with
    the report's damping D: Verlet's velocity factor 1 - f per step (f = 1/D) makes the update
    stable iff h² omega² + 2 h gamma < 4 - 2 f (its characteristic polynomial), so D = 1 (f = 1)
    still has a finite limit; ``gamma_max`` adds D's drag rate -ln(1 - f) / dt (for the other
    integrators, which apply D as that rate)."""
    f = _verlet_damping_factor(params) if sim.terms.verlet_damping else 0.0
    rate = float(-np.log1p(-min(f, 1 - 1e-12)) / sim.dt) if f > 0 else 0.0
    with np.errstate(over="ignore", invalid="ignore"):
        if omega > 0 and np.isfinite(omega):
            dt_max = float((np.sqrt(gamma ** 2 + omega ** 2 * (4.0 - 2.0 * f)) - gamma) / omega ** 2)
        elif omega == 0:
            dt_max = float("inf") if gamma == 0 else float(2.0 / gamma)
        else:
            dt_max = 0.0
    return StabilityEstimate(dt_max=dt_max, omega_max=omega, gamma_max=gamma + rate,
                             dt_gershgorin=_gershgorin(sim.topology, params), gamma_forces=gamma)


def calibrated_limit(sim, params, c_omega=1.0, c_gamma=1.0):
    """The closed-form :func:`bound` with its omega and damping rate scaled by calibration factors
    (e.g. exact / bound at a reference point): a cheap estimate of the stable step, s."""
    b = bound(sim, params)
    return _estimate_from(sim, params, c_omega * b.omega_max, c_gamma * b.gamma_forces).dt_max


def _ring_neighbours(topo):
    """(V, K) index of the next and previous real ring entry of each slot (wrapping within the
    vertex's valence), and the valence (V,)."""
    val = topo.ring_mask.sum(axis=1)
    k = np.arange(topo.ring.shape[1])[None, :]
    safe = np.maximum(val, 1)[:, None]
    return (k + 1) % safe, (k - 1) % safe, val


class _Geometry(NamedTuple):
    """Per-vertex geometric factors of the bound at a configuration x (numpy, float64).

    lam_s: lambda_max(sum_j d d^T) over the ring; off: sum_j ||K_ij|| / k (max(1, |1 - L/l|) each);
    diag: lambda_max(K_ii) / k; curv: sum_j |x_c - x_c'| / 6 (the gas curvature blocks / P);
    g: |dV/dx_i|; g_sum: (O,) sum of |g| over each object; volume: (O,) signed volumes."""

    lam_s: np.ndarray
    off: np.ndarray
    diag: np.ndarray
    curv: np.ndarray
    g: np.ndarray
    g_sum: np.ndarray
    volume: np.ndarray


def _geometry(topo, x):
    ring, mask = topo.ring, topo.ring_mask
    nxt, prv, _ = _ring_neighbours(topo)
    rows = np.arange(topo.n_vertices)[:, None]
    d = x[ring] - x[:, None, :]                                      # (V, K, 3)
    length = np.sqrt(np.sum(d * d, axis=-1) + topo.length_eps ** 2)
    dh = d / length[..., None]
    tau = np.where(mask, 1.0 - topo.ring_rest / length, 0.0)        # transverse stiffness factor 1 - L/l
    outer = np.where(mask[..., None, None], dh[..., :, None] * dh[..., None, :], 0.0)
    # spring blocks K_e = k [d d^T + tau (I - d d^T)]: ||K_e|| = k max(1, |tau|)
    k_e = outer + tau[..., None, None] * (np.eye(3) - outer) * mask[..., None, None]
    diag = np.linalg.eigvalsh(k_e.sum(axis=1))[:, -1]
    lam_s = np.linalg.eigvalsh(outer.sum(axis=1))[:, -1]
    off = np.sum(np.where(mask, np.maximum(1.0, np.abs(tau)), 0.0), axis=1)
    # P d²V/dx_a dx_b for a neighbour b: (P/6) [x_c - x_c'] (c, c' the vertices opposite edge ab)
    opp = x[ring[rows, nxt]] - x[ring[rows, prv]]
    curv = np.sum(np.where(mask, np.sqrt(np.sum(opp * opp, axis=-1)) / 6.0, 0.0), axis=1)
    g = np.sum(np.where(mask[..., None], np.cross(d, d[rows, nxt]), 0.0), axis=1) / 6.0
    gn = np.sqrt(np.sum(g * g, axis=-1))
    g_sum = np.array([gn[a:b].sum() for a, b in topo.vertex_slices])
    volume = np.array([scene_volume(topo, x, o) for o in range(topo.n_objects)])
    return _Geometry(lam_s, off, diag, curv, gn, g_sum, volume)


#: Rest-shape geometry of the bound per topology (computed once; the bound is then O(V) numpy).
_GEOMETRY = weakref.WeakKeyDictionary()


def _rest_geometry(topo):
    if topo not in _GEOMETRY:
        _GEOMETRY[topo] = _geometry(topo, np.asarray(topo.x0, np.float64))
    return _GEOMETRY[topo]


def _rates(topo, terms, params, temperature, geo, scale=None):
    """(omega² bound, gamma bound): block Gershgorin on M^-1/2 K M^-1/2 and M^-1/2 C M^-1/2 at the
    configuration of ``geo``, or at the rest shape scaled uniformly by ``scale`` (O,) about each
    object's centroid (then every factor follows by its power of the scale)."""
    obj = topo.vertex_object
    k = np.asarray(params.k_structural, np.float64)
    k_v = vertex_stiffness_max(topo, k)          # the stiffest spring at each vertex (a field's too)
    k = model.object_stiffness(topo, k)          # one per object: the defaults of the floor and contact
    m = (np.asarray(params.total_weight, np.float64) / topo.count)[obj]
    val = topo.ring_mask.sum(axis=1)
    s = np.ones(topo.n_objects) if scale is None else np.asarray(scale, np.float64)
    if scale is None:
        spring = geo.diag + geo.off
    else:                                  # tau = 1 - 1/s on every edge: K_ii = (1 - tau) S + tau n I
        tau = (1.0 - 1.0 / s)[obj]
        spring = (1.0 - tau) * geo.lam_s + tau * val + np.maximum(1.0, np.abs(tau)) * val
    w2 = k_v * spring / m
    if terms.gas:
        nrt = np.asarray(params.nmol, np.float64) * GAS_CONSTANT * temperature
        vol = geo.volume * s ** 3
        pressure = nrt / np.maximum(vol, VOLUME_EPS * topo.rest_volume)
        w2 = w2 + pressure[obj] * s[obj] * geo.curv / m                       # curvature scales with s
        # the rank-one part (P/V) g g^T, dense within an object: |g| scales with s²
        rank1 = (pressure / np.maximum(vol, 1e-300) * s ** 4)[obj] * geo.g * geo.g_sum[obj]
        w2 = w2 + rank1 / m
    floor = terms.floor_smooth
    if floor:
        # U'' of the softplus penalty is at most 1.05 k_f (max over the contact depth)
        w2 = w2 + 1.05 * np.asarray(model.smooth_floor_stiffness(floor, k))[obj] / m
    contact = terms.contact
    if contact:
        kc = contact.stiffness if contact.stiffness is not None else 0.1 * 2 * int(val.max()) * k[obj]
        w2 = w2 + 3.0 * kc / m      # a vertex against a face (the vertex and the face's corners)
    free = np.ones(topo.n_vertices, bool)
    free[topo.fixed] = False
    omega2 = float(np.max(w2[free])) if free.any() else 0.0
    gamma = 0.0
    if terms.dashpot:
        c = np.asarray(params.dashpot, np.float64)[obj]
        gamma = max(gamma, float(np.max((c * (geo.lam_s + val) / m)[free], initial=0.0)))
    if terms.drag:
        gamma += float(np.max(np.asarray(params.drag, np.float64)))
    return omega2, gamma


def _inflation(topo, params, temperature):
    """(O,) the uniform inflation s* = (1 + sqrt(1 + 12 nRT/(k sum L²))) / 2 of each object (1 without gas)."""
    nrt = np.asarray(params.nmol, np.float64) * GAS_CONSTANT * temperature
    k = model.object_stiffness(topo, np.asarray(params.k_structural, np.float64))
    l2 = np.array([np.sum(topo.rest_length[topo.edge_object == o] ** 2) for o in range(topo.n_objects)])
    with np.errstate(divide="ignore", invalid="ignore"):
        s = 0.5 * (1 + np.sqrt(1 + 12 * nrt / (k * l2)))
    return np.where((nrt > 0) & (k > 0) & np.isfinite(s), s, 1.0)


def scene_volume(topo, x, o):
    """Signed volume of object ``o`` at positions x (V, 3) (numpy, float64)."""
    a, b = topo.face_slices[o]
    f = topo.faces[a:b]
    c = x[topo.vertex_slices[o][0]:topo.vertex_slices[o][1]].mean(axis=0)
    p, q, r = x[f[:, 0]] - c, x[f[:, 1]] - c, x[f[:, 2]] - c
    return float(np.sum(p * np.cross(q, r)) / 6.0)


def bound(sim, params, x=None):
    """A closed-form, always-safe stability limit (numpy; nothing is compiled or traced).

    Block Gershgorin bounds on omega_max² = lambda_max(M^-1 K) and on the damping rate
    gamma_max = lambda_max(M^-1 C), for the springs (with their pre-tension), the gas (its
    curvature term P d²V and its rank-one term (P/V) g g^T), soft-soft contact, the smooth floor
    and the velocity damping (dashpot, drag, the report's Verlet damping), evaluated at the rest
    geometry (or ``x``) and, with gas, at the uniform inflation s* as :func:`estimate` does. Each
    bound is at least the true value, so ``dt_max`` is at most the true limit (on icospheres,
    0.7-0.85 of it): a dt below it is stable; a dt above it needs :func:`estimate` to decide.
    The rest-shape geometry is computed once per topology; each call is then O(V) numpy.

    Args:
      sim: :class:`jaxplush.stepping.step.Simulator` (its topology, terms, step and temperature).
      params: :class:`jaxplush.types.Params`; x: (V, 3) positions (default: rest).

    Returns:
      :class:`StabilityEstimate` with the bound's omega_max, gamma_max and dt_max.
    """
    topo, terms, temp = sim.topology, sim.terms, sim.scene.temperature
    if x is None:
        geo = _rest_geometry(topo)
        w2, gam = _rates(topo, terms, params, temp, geo)
        if terms.gas:
            a, b = _rates(topo, terms, params, temp, geo, scale=_inflation(topo, params, temp))
            w2, gam = max(w2, a), max(gam, b)
    else:
        x0 = np.asarray(x, np.float64)
        w2, gam = _rates(topo, terms, params, temp, _geometry(topo, x0))
        if terms.gas:
            xi = np.asarray(inflated(sim, params, x0), np.float64)
            a, b = _rates(topo, terms, params, temp, _geometry(topo, xi))
            w2, gam = max(w2, a), max(gam, b)
    with np.errstate(over="ignore", invalid="ignore"):
        omega = float(np.sqrt(max(w2, 0.0)))
    return _estimate_from(sim, params, omega, gam)


def _verlet_damping_factor(params):
    """The largest per-step factor f = 1/D of the report's damping over the objects (0: none)."""
    d = np.asarray(params.damping, np.float64)
    with np.errstate(divide="ignore"):
        return float(np.where(d > 0, 1.0 / np.where(d > 0, d, 1.0), 0.0).max())


def _gershgorin(topo, params):
    """The springs-only bound sqrt(2 m / (k n_max)) of the lightest, stiffest vertex."""
    k = vertex_stiffness_max(topo, params.k_structural)
    m = np.asarray(params.total_weight, np.float64)[topo.vertex_object] / topo.count[topo.vertex_object]
    kn = k * topo.ring_mask.sum(axis=1)
    with np.errstate(divide="ignore"):
        return float(np.min(np.where(kn > 0, np.sqrt(2 * m / np.where(kn > 0, kn, 1)), np.inf)))


#: Integrators with no step-size limit (unconditionally stable on the linearised system).
UNCONDITIONAL = ("implicit_euler",)


def _amplification(integrator, z):
    """|R(z)| of the scheme on y' = lambda y, z = h lambda (complex numpy)."""
    if integrator == "rk4":
        return np.abs(1 + z + z ** 2 / 2 + z ** 3 / 6 + z ** 4 / 24)
    if integrator in ("euler", "mesit"):  # mesit is explicit Euler with a lag (docs/model.md §2)
        return np.abs(1 + z)
    raise ValueError(f"no amplification factor for {integrator!r}")


def _largest_stable_h(integrator, lam):
    """Largest h with |R(h t lambda)| <= 1 for t in (0, 1] (grid scan, then bisection)."""
    scale = abs(lam)
    grid = np.linspace(0.0, 4.0, 4001)[1:] / scale          # h |lambda| up to 4 (beyond RK4's 2.83)
    bad = _amplification(integrator, grid * lam) > 1 + 1e-12
    if not bad.any():
        return float(grid[-1])
    i = int(np.argmax(bad))
    lo, hi = (0.0 if i == 0 else grid[i - 1]), grid[i]
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        if _amplification(integrator, mid * lam) > 1 + 1e-12:
            hi = mid
        else:
            lo = mid
    return float(lo)


def integrator_limit(est, integrator):
    """Largest stable (sub)step h of ``integrator`` for the worst mode of a :class:`StabilityEstimate`.

    Args:
      est: :class:`StabilityEstimate` (from :func:`estimate`).
      integrator: one of :data:`jaxplush.INTEGRATORS`.

    Returns:
      h_max in s: ``est.dt_max`` for ``verlet`` and ``symplectic_euler``; the bisected limit of
      the test mode for ``rk4``, ``euler`` and ``mesit`` (0.0 when undamped: Euler-type updates
      gain energy at any h); ``inf`` for ``implicit_euler``.
    """
    if integrator in ("verlet", "symplectic_euler"):
        return float(est.dt_max)
    if integrator in UNCONDITIONAL:
        return float("inf")
    omega, gamma = float(est.omega_max), float(est.gamma_max)
    if omega <= 0 and gamma <= 0:
        return float("inf")
    root = np.sqrt(complex(gamma ** 2 / 4 - omega ** 2))
    modes = [-gamma / 2 + root, -gamma / 2 - root] + ([complex(-gamma)] if gamma > 0 else [])
    return min(_largest_stable_h(integrator, lam) for lam in modes if lam != 0)


def dt_warning(est, integrator, dt, substeps=1):
    """A warning message when dt / substeps exceeds ``integrator``'s limit, else None."""
    h = dt / substeps
    limit = integrator_limit(est, integrator)
    if h <= limit:
        return None
    per = f"dt/substeps = {h:g} s" if substeps > 1 else f"dt = {dt:g} s"
    if integrator in ("euler", "mesit") and limit < 1e-3 * est.dt_max:
        why = ("explicit Euler" if integrator == "euler" else "Mesit's update (explicit Euler with a lag)")
        return (f"{per}: {why} has no stable step for this scene (its undamped modes gain energy every "
                f"step; estimated limit {limit:.3g} s); expect a blow-up, use verlet or implicit_euler")
    return (f"{per} exceeds the estimated explicit stability limit {limit:.3g} s of {integrator} "
            f"(omega_max = {est.omega_max:.4g} rad/s); expect a blow-up, use dt <= {0.9 * limit * substeps:.3g} s")


def check_dt(sim, params):
    """The dt warning of :func:`dt_warning` for ``sim``'s step, or None when the step is stable.

    Decided by the closed-form :func:`bound` where it suffices (nothing compiled); only a step
    above the bound is checked with :func:`estimate` (a power iteration, compiled once per
    simulator)."""
    if sim.integrator in UNCONDITIONAL:
        return None
    substeps = sim.substeps
    if dt_warning(bound(sim, params), sim.integrator, sim.dt, substeps) is None:
        return None
    return dt_warning(estimate(sim, params), sim.integrator, sim.dt, substeps)
