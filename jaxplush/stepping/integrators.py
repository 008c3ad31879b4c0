"""Time integrators on the internal component-major (3, V) layout (docs/model.md §2-§5).

Every integrator is a :class:`Scheme` of three pure functions built for one scene by
:func:`build`:

* ``init(params, x, v) -> state``: the integrator's carry from positions and velocities (3, V);
* ``step(params, state, k=None) -> state``: one (sub)step of length ``h``; ``k`` is the (int32)
  index of the substep, t_k = k h -> t_{k+1}, needed only with driven vertices;
* ``velocity(params, state) -> v``: the velocity (3, V) at the state's time (for energies).

States are NamedTuples whose first field is the positions ``x`` (3, V) and whose every field is
a (3, V) array, so :func:`jaxplush.stepping.step.to_public` transposes any of them to (V, 3), and
rollouts, health checks, ``vmap`` and ``grad`` treat them alike. Every step ends with exactly
one call of the shared floor/pin hook ``constrain(x_old, x_new, v_new)``
(:func:`jaxplush.stepping.constraints.make_constrain`) on the velocity the scheme carries.

=================  =====  ===================  ============================  ===================
name               order  state                stable (undamped, per step)   effect on damping
=================  =====  ===================  ============================  ===================
euler              1      State(x, v)          never: energy grows           adds negative
                                                                             damping ~omega² h/2
symplectic_euler   1      State(x, v)          h omega < 2                   none on average
rk4                4      State(x, v)          h omega < 2 sqrt(2)           small, ~omega⁶ h⁵/144
verlet (default)   2      State(x, u), u the   h omega < 2 (damped:          none; the report's
                          half-step velocity   h² omega² + 2 h gamma < 4)    D is per step
mesit              1      MesitState(x, v,     unsound: gains energy at      pumps energy
                          dv previous change)  any h (docs/model.md §2)
implicit_euler     1      State(x, v)          any h (linearised, one        adds ~omega² h/2
                                                Newton step per step)        (docs/model.md §3)
=================  =====  ===================  ============================  ===================

The report's per-step Verlet damping D (``Params.damping``) multiplies Verlet's velocity by
1 - 1/D every time step dt (with substeps, by (1 - 1/D)^(1/substeps) every substep, so D keeps
its meaning per dt). The other schemes apply it as the equivalent drag rate
gamma_D = -ln(1 - 1/D) / dt (docs/model.md §5), which decays a velocity by the same factor per
time step: like Verlet's, its physical strength depends on dt (not on the substeps). Pinned vertices get zero acceleration
inside the non-Verlet schemes (so RK4's stages see them fixed) and are reset by ``constrain``.
Driven vertices (:class:`jaxplush.stepping.constraints.Drive`) likewise: zero acceleration in the
stages (implicit Euler: filtered out of the solve), then set from their path by ``constrain``
(docs/model.md §10).
"""

from __future__ import annotations

import dataclasses
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxplush.model import forces as model
from jaxplush.model import terms as T
from jaxplush.types import State

INTEGRATORS = ("euler", "symplectic_euler", "rk4", "verlet", "mesit", "implicit_euler")
DEFAULT = "verlet"

#: Default relative CG residual of the implicit solve, and its static iteration cap.
CG_TOL = {np.dtype("float32"): 1e-5, np.dtype("float64"): 1e-10}
CG_MAXITER = 200


class MesitState(NamedTuple):
    """Carry of the ``mesit`` scheme: positions, velocities and the previous velocity change,
    each (3, V) internally and (V, 3) in public."""

    x: object
    v: object
    dv: object


class Scheme(NamedTuple):
    """An integrator built for one scene: ``init``, ``step`` and ``velocity`` (see the module doc)."""

    init: Callable
    step: Callable
    velocity: Callable


@dataclasses.dataclass(frozen=True, eq=False)
class System:
    """What every integrator needs of a scene (all static; closed over by the compiled step).

    Attributes:
      topo: :class:`jaxplush.model.forces.Topology`.
      terms: :class:`jaxplush.model.forces.Terms`.
      kernel: internal force kernel ``(params, x (3, V), v (3, V)) -> (f (3, V), volume (O,) | None)``.
      gravity: (3, 1) numpy gravity, m/s².
      constrain: ``(x_old, x_new, v_new) -> (x, v)``, the floor/pin hook for steps of length ``h``.
      h: (sub)step length, s.
      temperature: gas temperature, K.
      substeps: (sub)steps per time step dt = h * substeps; the report's damping D is per dt.
      drive: :class:`jaxplush.stepping.constraints.Drive` of the driven vertices, or None.
    """

    topo: model.Topology
    terms: model.Terms
    kernel: Callable
    gravity: np.ndarray
    constrain: Callable
    h: float
    temperature: float
    substeps: int = 1
    drive: object = None

    @property
    def dt(self):
        """The time step dt = h * substeps, s (the report's damping D acts per dt)."""
        return self.h * self.substeps

    def accel(self, params, x, v):
        """(a (3, V), volume): internal force / mass + gravity; exactly Verlet's computation."""
        f, volume = self.kernel(params, x, v)
        a = f * (1.0 / model.vertex_mass(self.topo, params))
        if self.terms.gravity:
            with jax.named_scope("gravity"):
                a = a + jnp.asarray(self.gravity, x.dtype)
        return a, volume

    def rate(self, params, x, v, k=None):
        """Acceleration for the non-Verlet schemes: :meth:`accel`, the report's damping as the
        drag rate gamma_D, and zero at pinned vertices (and at vertices driven in substep ``k``)."""
        a, _ = self.accel(params, x, v)
        if self.terms.verlet_damping:
            with jax.named_scope("verlet_damping"):
                a = a - model.per_vertex(self.topo, damping_rate(params.damping, self.dt)) * v
        if self.terms.fixed:
            a = a.at[:, self.topo.fixed].set(0.0)
        if self.drive is not None:
            a = self.drive.hold(a, k)
        return a

    def pin_velocity(self, v):
        if self.terms.fixed:
            v = v.at[:, self.topo.fixed].set(0.0)
        return v

    def constrained(self, x_old, x, v, k=None):
        """``constrain`` (the floor/pin hook) after a (sub)step; the substep index ``k`` is passed
        only with driven vertices (a hook without them takes (x_old, x, v))."""
        if self.drive is None:
            return self.constrain(x_old, x, v)
        return self.constrain(x_old, x, v, k)

    def start(self, x, v):
        """(x, v) at t = 0 with pins (zero velocity) and driven vertices (at their path) applied."""
        v = self.pin_velocity(v)
        if self.drive is not None:
            x, v = self.drive.start(x, v)
        return x, v


def damping_factor(damping):
    """f = 1/D for D > 0, else 0 (no damping), with a gradient that is finite everywhere."""
    safe = jnp.where(damping > 0, damping, 1.0)
    return jnp.where(damping > 0, 1.0 / safe, 0.0)


def damping_rate(damping, dt):
    """gamma_D = -ln(1 - 1/D) / dt (1/s): the drag rate that decays a velocity by Verlet's
    per-step factor 1 - 1/D over one time step dt (docs/model.md §5); 0 for D = 0."""
    f = damping_factor(damping)
    return -jnp.log1p(-jnp.minimum(f, 1.0 - jnp.finfo(f.dtype).eps)) / dt


def damping_keep(damping, substeps=1):
    """Verlet's velocity factor per (sub)step for the report's damping D, which is defined per time
    step dt: 1 - 1/D with one step per dt, (1 - 1/D)^(1/substeps) with substeps, so the decay per
    dt (and the physical damping) does not change when a run is substepped. ``substeps``: an int,
    or a traced integer scalar (a count that is data of the compiled program)."""
    f = damping_factor(damping)
    given = isinstance(substeps, (int, np.integer))
    if given and substeps == 1:
        return 1.0 - f
    n = substeps if given else jnp.asarray(substeps).astype(f.dtype)
    many = jnp.exp(jnp.log1p(-jnp.minimum(f, 1.0 - jnp.finfo(f.dtype).eps)) / n)
    # a count given as data (the batched engine's runtime substeps): one substep keeps 1 - f exactly,
    # as a static count of one does
    return many if given else jnp.where(n == 1, 1.0 - f, many)


def repeat_substeps(step, substeps, indexed=False):
    """``substeps`` applications of ``step(params, carry) -> carry`` as one step (one
    ``lax.fori_loop``; ``step`` itself for one substep). The carry is the state, or a tuple such as
    (state, contact cache). ``indexed`` (driven vertices): ``step(params, carry, k)`` takes the
    substep index and the result is ``repeated(params, carry, n)`` for time step n (substep j of
    it is k = n substeps + j)."""
    if indexed:
        def repeated_at(params, carry, n):
            n = jnp.asarray(n, jnp.int32)
            if substeps == 1:
                return step(params, carry, n)
            return jax.lax.fori_loop(0, substeps, lambda j, c: step(params, c, n * substeps + j), carry)
        return repeated_at
    if substeps == 1:
        return step

    def repeated(params, carry):
        return jax.lax.fori_loop(0, substeps, lambda _, c: step(params, c), carry)
    return repeated


def verlet_start(v, a, h):
    """Verlet's first half-step velocity u_0 = v_0 - a_0 h/2 (makes free fall exact)."""
    return v - (0.5 * h) * a


def verlet_kick(u, a, h, keep=None):
    """Verlet's half-step velocity update u' = keep u + a h, with ``keep`` = 1 - 1/D the report's
    damping factor (:func:`damping_keep`; None: undamped)."""
    return (u if keep is None else keep * u) + a * h


def verlet_drift(x, u, h):
    """Verlet's position update x' = x + u' h from the new half-step velocity u'."""
    return x + u * h


def build(name, system, cg_tol=None, cg_maxiter=CG_MAXITER):
    """Build integrator ``name`` (one of :data:`INTEGRATORS`) for ``system``.

    Args:
      name: integrator name.
      system: :class:`System`.
      cg_tol: ``implicit_euler`` only: relative CG residual (default :data:`CG_TOL` by dtype).
      cg_maxiter: ``implicit_euler`` only: static cap on CG iterations per step.

    Returns:
      :class:`Scheme`.
    """
    if name not in INTEGRATORS:
        raise ValueError(f"unknown integrator {name!r}; available: {', '.join(INTEGRATORS)}")
    if name == "implicit_euler":
        return implicit_euler(system, cg_tol, cg_maxiter)
    return globals()[name](system)


def _plain_init(system):
    def init(params, x, v):
        return State(*system.start(x, v))
    return init


def _velocity_field(params, state):
    return state.v


# --------------------------------------------------------------------------- explicit schemes

def verlet(system):
    """The report's damped Verlet (default). Order 2; state State(x, u), u the half-step velocity.

        u_{n+1} = (1 - f) u_n + a(x_n, u_n) h,   x_{n+1} = x_n + u_{n+1} h,   f = 1/D,

    the difference form of x_{n+1} = x_n + (1 - f)(x_n - x_{n-1}) + a h² (no rounding drift in
    float32, docs/model.md §5); u_0 = v_0 - a_0 h/2 makes free fall exact (docs/model.md §8.1).
    Stable for h² omega² + 2 h gamma < 4 (undamped: h < 2/omega_max). Adds no numerical
    damping; D damps at gamma ~ 1/(D h), so its physical strength changes with h. Velocity-
    dependent forces (dashpot, drag) see u_n, half a step old, which makes the scheme first
    order when they are on.
    """
    topo, terms, h = system.topo, system.terms, system.h
    fixed = topo.fixed

    def init(params, x, v):
        if system.drive is not None:
            x, v = system.drive.start(x, v)
        a0, _ = system.accel(params, x, v)
        u = verlet_start(v, a0, h)
        if terms.fixed:
            u = u.at[:, fixed].set(0.0)
        if system.drive is not None:      # the path's velocity, as it carries after every step
            u = system.drive.start(x, u)[1]
        return State(x, u)

    gravity = [float(g) for g in np.asarray(system.gravity).reshape(3)]

    def step(params, state, k=None):
        # system.accel's arithmetic, written row by row (x, y, z) and stacked at the end: XLA
        # then fuses the update into fewer loops over V (faster; benchmarks/RESULTS.md).
        x, u = state
        f, _ = system.kernel(params, x, u)
        inv_m = 1.0 / model.vertex_mass(topo, params)
        keep = None
        if terms.verlet_damping:
            with jax.named_scope("verlet_damping"):
                keep = model.per_vertex(topo, damping_keep(params.damping, system.substeps))
        xs, us = [], []
        for c in range(3):
            a = f[c] * inv_m
            if terms.gravity:
                with jax.named_scope("gravity"):
                    a = a + jnp.asarray(gravity[c], x.dtype)
            uc = verlet_kick(u[c], a, h, keep)
            us.append(uc)
            xs.append(verlet_drift(x[c], uc, h))
        x_new, u_new = system.constrained(x, jnp.stack(xs), jnp.stack(us), k)
        return State(x_new, u_new)

    def velocity(params, state):
        a, _ = system.accel(params, state.x, state.v)
        return state.v + 0.5 * h * a

    return Scheme(init, step, velocity)


def euler(system):
    """Explicit (forward) Euler: x_{n+1} = x_n + h v_n, v_{n+1} = v_n + h a(x_n, v_n).

    Order 1; state State(x, v). Unstable for every h on an undamped oscillation: each step
    multiplies a mode's energy by 1 + h² omega², i.e. negative numerical damping of rate
    ~omega² h/2; with damping rate gamma it is stable only for h < gamma/omega². Kept as the
    textbook baseline; never use it for production runs.
    """
    h = system.h

    def step(params, state, k=None):
        x, v = state
        a = system.rate(params, x, v, k)
        x_new = x + h * v
        v_new = v + h * a
        x_new, v_new = system.constrained(x, x_new, v_new, k)
        return State(x_new, v_new)

    return Scheme(_plain_init(system), step, _velocity_field)


def symplectic_euler(system):
    """Semi-implicit (symplectic) Euler: v_{n+1} = v_n + h a(x_n, v_n), x_{n+1} = x_n + h v_{n+1}.

    Order 1 (the same update as Verlet started from u_0 = v_0, which costs a global error of
    g h t / 2 in free fall, docs/model.md §8.1); state State(x, v). Stable for h omega < 2 (damped:
    h² omega² + 2 h gamma < 4, as Verlet); energy error bounded, no drift, no numerical damping.
    """
    h = system.h

    def step(params, state, k=None):
        x, v = state
        a = system.rate(params, x, v, k)
        v_new = v + h * a
        x_new = x + h * v_new
        x_new, v_new = system.constrained(x, x_new, v_new, k)
        return State(x_new, v_new)

    return Scheme(_plain_init(system), step, _velocity_field)


def rk4(system):
    """Classical fourth-order Runge-Kutta on (x, v). Order 4; state State(x, v); four force
    evaluations per step. Stable for h omega < 2 sqrt(2) (undamped); it dissipates a mode's
    energy slowly, by a factor ~1 - (h omega)⁶/72 per step (numerical damping ~omega⁶ h⁵/144).
    The floor and pins are applied once after the full step (floor contact is then first order).
    """
    h = system.h

    def step(params, state, k=None):
        x, v = state
        a1 = system.rate(params, x, v, k)
        x2, v2 = x + 0.5 * h * v, v + 0.5 * h * a1
        a2 = system.rate(params, x2, v2, k)
        x3, v3 = x + 0.5 * h * v2, v + 0.5 * h * a2
        a3 = system.rate(params, x3, v3, k)
        x4, v4 = x + h * v3, v + h * a3
        a4 = system.rate(params, x4, v4, k)
        x_new = x + (h / 6.0) * (v + 2.0 * v2 + 2.0 * v3 + v4)
        v_new = v + (h / 6.0) * (a1 + 2.0 * a2 + 2.0 * a3 + a4)
        x_new, v_new = system.constrained(x, x_new, v_new, k)
        return State(x_new, v_new)

    return Scheme(_plain_init(system), step, _velocity_field)


def _safe_unit(a):
    """(a / |a|, |a|) per vertex of a (3, V) array; 0 and 0 where a = 0, with finite gradients."""
    s = jnp.sum(a * a, axis=0)
    nz = s > 0
    inv = jax.lax.rsqrt(jnp.where(nz, s, 1.0))
    return jnp.where(nz, a * inv, 0.0), jnp.where(nz, s * inv, 0.0)


def mesit(system):
    """Mesit et al.'s "simplified implicit" update, as the report describes it (docs/model.md §2).

        dv_i = F_i/|F_i| * h (|F_i| + k h n_i |dv_i^prev|) / (m + k h² n_i),
        v <- v + dv,   x <- x + h v,

    F_i the total force on vertex i, k its object's spring constant, n_i its number of springs
    and dv^prev the previous step's velocity change. State MesitState(x, v, dv). Order 1.

    **Unsound; kept only so the report's scheme keeps its row.** With the current |dv| on the
    right it solves to dv = h F/m: it is explicit Euler with a one-step lag, uses no Jacobian
    direction and no h² (df/dx) v term, so it cannot be unconditionally stable; the lag
    re-applies an old magnitude along the new force direction and so pumps energy every half
    period. tests/test_integrators.py measures the evidence: a dropped body's first step
    accelerates at m/(m + k h² n) ~ 0.29 g instead of g; on an undamped pressurised 162-vertex
    ball at a quarter of the explicit limit its ringing energy grows more than tenfold in 2000
    steps where symplectic Euler stays within 10%; tests/test_hard_cases.py: it blows up at 0.9x
    the explicit limit where Verlet is stable.
    """
    topo, h = system.topo, system.h
    valence = topo.ring_mask.sum(axis=1).astype(np.float64)

    def init(params, x, v):
        x, v = system.start(x, v)
        return MesitState(x, v, jnp.zeros_like(x))

    def step(params, state, k=None):
        x, v, dv_prev = state
        m = model.vertex_mass(topo, params)
        force = m * system.rate(params, x, v, k)
        kn = _stiffness_sum(topo, params.k_structural, valence, x.dtype)
        direction, _ = _safe_unit(force)
        _, prev = _safe_unit(dv_prev)
        dv = (h * force + direction * (kn * h * h * prev)) / (m + kn * h * h)
        v_new = v + dv
        x_new = x + h * v_new
        x_new, v_new = system.constrained(x, x_new, v_new, k)
        return MesitState(x_new, v_new, dv)

    return Scheme(init, step, _velocity_field)


def _stiffness_sum(topo, k, valence, dtype):
    """(V,) sum of the spring constants at each vertex: k n_i for a per-object k, the sum over the
    vertex's edges for a per-edge field."""
    if not model.is_field(topo, k):
        return model.per_vertex(topo, k) * jnp.asarray(valence, dtype)
    table = model.ring_stiffness(topo, k)                                   # (K, V)
    return jnp.sum(jnp.where(np.ascontiguousarray(topo.ring_mask.T), table, 0.0), axis=0)


# --------------------------------------------------------------------------- implicit Euler

def implicit_euler(system, cg_tol=None, cg_maxiter=CG_MAXITER):
    """Linearised backward Euler after Baraff and Witkin (docs/model.md §3).

    One Newton step per time step:
        (M - h df/dv - h² df/dx) dv = h (f_0 + h (df/dx) v_0),   v_1 = v_0 + dv,   x_1 = x_0 + h v_1,
    with df/dx the spring Jacobian with the compressive clamp, blocks
    K_e = k [d d^T + max(0, 1 - L/l) (I - d d^T)] (positive semi-definite), plus the gas's
    rank-one term -(P/V) g g^T per object (g = dV/dx; zero while the volume clamp holds P fixed;
    the indefinite P d²V/dx² part is dropped, the full gas force stays in f_0), and df/dv the
    edge-dashpot blocks -c d d^T, air drag -gamma m I and the report's damping as drag. The
    system matrix is then symmetric positive definite and is solved matrix-free by
    Jacobi-preconditioned conjugate gradient (``jax.scipy.sparse.linalg.cg``) whose products are
    hand-written Jacobian-vector products on the one-ring tables (tests check them against
    ``jax.jvp`` of the force), to a relative residual ``cg_tol`` with at most ``cg_maxiter``
    iterations (static). Pinned vertices are filtered out of the solve (their dv is 0).

    Gradients: ``cg`` wraps the solve in ``jax.lax.custom_linear_solve``, so derivatives are
    implicit differentiation of the linear solve (a second CG solve with the same operator in
    reverse mode), exact for a converged solve; tests check them against central finite
    differences in float64.

    Order 1; state State(x, v). Stable at any h for the linearised system (tested at 10x the
    explicit limit on a stiff 642-vertex ball). Strongly dissipative: a mode of frequency omega
    loses amplitude by 1/sqrt(1 + omega² h²) per step, numerical damping of rate ~omega² h/2,
    which is confounded with any damping parameter being fitted (docs/model.md §9).
    """
    topo, terms, h = system.topo, system.terms, system.h
    ring = np.ascontiguousarray(topo.ring.T)
    mask = np.ascontiguousarray(topo.ring_mask.T)
    ring_rest = np.ascontiguousarray(topo.ring_rest.T)
    all_real = bool(mask.all())
    free = np.ones(topo.n_vertices)
    free[topo.fixed] = 0.0

    def gather(a):
        return a.at[ring].get(mode="promise_in_bounds")

    def step(params, state, k=None):
        x, v = state
        dtype = x.dtype
        m = model.vertex_mass(topo, params)
        f, volume = system.kernel(params, x, v)
        if terms.gravity:
            f = f + m * jnp.asarray(system.gravity, dtype)
        if terms.verlet_damping:
            f = f - (model.per_vertex(topo, damping_rate(params.damping, system.dt)) * m) * v
        jac = _jacobians(topo, terms, params, x, volume, system.temperature, gather, ring_rest, mask,
                         all_real, h, system.dt)
        fr = jnp.asarray(free, dtype)
        if system.drive is not None:      # driven vertices are filtered out of the solve as pins are
            if k is None:
                from jaxplush.stepping.constraints import missing_step_error
                raise missing_step_error()
            fr = fr * system.drive.free(k, topo.n_vertices, dtype)

        def system_matrix(u):
            u = fr * u
            au = m * u - h * jac.dfdv(u) - (h * h) * jac.dfdx(u)
            return fr * au + (1.0 - fr) * u

        diag = fr * jac.diag + (1.0 - fr)
        b = fr * (h * (f + h * jac.dfdx(v)))
        tol = CG_TOL[np.dtype(dtype)] if cg_tol is None else cg_tol
        guess = b / diag
        dv, _ = jax.scipy.sparse.linalg.cg(system_matrix, b, x0=guess, tol=tol, maxiter=cg_maxiter,
                                           M=lambda r: r / diag)
        v_new = v + dv
        x_new = x + h * v_new
        x_new, v_new = system.constrained(x, x_new, v_new, k)
        return State(x_new, v_new)

    return Scheme(_plain_init(system), step, _velocity_field)


class _Jacobians(NamedTuple):
    dfdx: Callable   # u (3, V) -> (df/dx) u, the clamped stiffness product (negative semi-definite)
    dfdv: Callable   # u (3, V) -> (df/dv) u (negative semi-definite)
    diag: object     # (3, V) diagonal of M - h df/dv - h² df/dx (the Jacobi preconditioner)


def _jacobians(topo, terms, params, x, volume, temperature, gather, ring_rest, mask, all_real, h, dt):
    """Jacobian-vector products of the force at x, on the one-ring tables (see implicit_euler)."""
    dtype = x.dtype
    m = model.vertex_mass(topo, params)
    rest = jnp.asarray(ring_rest, dtype)
    d = [gather(x[c]) - x[c] for c in range(3)]                             # 3 x (K, V)
    inv_l = T.inv_length(d, model.length_eps2(topo, dtype))
    dh = [dc * inv_l for dc in d]
    transverse, axial = T.spring_jacobian(model.ring_stiffness(topo, params.k_structural), rest, inv_l)
    if not all_real:
        transverse = jnp.where(mask, transverse, 0.0)
        axial = jnp.where(mask, axial, 0.0)
    dash = None
    if terms.dashpot:
        dash = model.per_vertex(topo, params.dashpot) * jnp.ones_like(inv_l)
        if not all_real:
            dash = jnp.where(mask, dash, 0.0)
    drag = jnp.zeros((), dtype)
    if terms.drag:
        drag = drag + model.per_vertex(topo, params.drag) * m
    if terms.verlet_damping:
        drag = drag + model.per_vertex(topo, damping_rate(params.damping, dt)) * m

    gas = None
    if terms.gas:
        nxt = [jnp.roll(dc, -1, axis=0) for dc in d]
        g = jnp.stack(T.volume_gradient([jnp.sum(a, axis=0) for a in T.fan(d, nxt)]))  # dV/dx (3, V)
        # -dP/dV = P/V while unclamped; the clamp holds P fixed below eps V0.
        gas = (g, -T.pressure_slopes(topo, params, volume, temperature)[1])

    def dfdx(u):
        du = [gather(u[c]) - u[c] for c in range(3)]
        s = axial * (dh[0] * du[0] + dh[1] * du[1] + dh[2] * du[2])
        out = jnp.stack([jnp.sum(transverse * du[c] + s * dh[c], axis=0) for c in range(3)])
        if gas is not None:
            g, coef = gas
            gu = model.per_object_sum(topo, jnp.sum(g * u, axis=0))
            out = out - model.per_vertex(topo, coef * gu) * g
        return out

    def dfdv(u):
        out = -drag * u
        if dash is not None:
            du = [gather(u[c]) - u[c] for c in range(3)]
            s = dash * (dh[0] * du[0] + dh[1] * du[1] + dh[2] * du[2])
            out = out + jnp.stack([jnp.sum(s * dh[c], axis=0) for c in range(3)])
        return out

    # Diagonal of M - h df/dv - h² df/dx: (df_i/dx_i)_cc = -sum_j (tr + ax d_c²), likewise dash.
    stiff = jnp.stack([jnp.sum(transverse + axial * dh[c] * dh[c], axis=0) for c in range(3)])
    damp = drag * jnp.ones_like(x)
    if dash is not None:
        damp = damp + jnp.stack([jnp.sum(dash * dh[c] * dh[c], axis=0) for c in range(3)])
    if gas is not None:
        g, coef = gas
        stiff = stiff + model.per_vertex(topo, coef) * g * g
    diag = m + h * damp + (h * h) * stiff
    return _Jacobians(dfdx, dfdv, diag)
