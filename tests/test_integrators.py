"""Integrators: convergence orders, free fall, Mesit's unsoundness, the Baraff-Witkin solve and its
gradients, substeps, per-integrator stability limits (docs/model.md §2-§4, §8)."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxplush
from jaxplush.stepping import integrators
from jaxplush.model import forces as model
from jaxplush.stepping import stability
from conftest import assert_gradient_matches_fd, icosphere_scene, icosphere_text

ALL = jaxplush.INTEGRATORS
#: Global error order of each scheme (docs/model.md §4); Mesit's update is explicit Euler with a
#: lag whose memory k h² n / (m + k h² n) vanishes as h -> 0, so it is first order too.
ORDER = dict(euler=1, symplectic_euler=1, rk4=4, verlet=2, mesit=1, implicit_euler=1)


def _direct_runner(scene, name, cg_tol=1e-12):
    """jit(h, n) -> positions after n steps of ``name`` with a *traced* step h: one compilation
    serves every step size (no floor or pins in these scenes, so constrain is the identity)."""
    topo = model.build_topology(scene)
    terms = model.Terms.for_scene(scene)
    assert not (terms.floor or terms.fixed)
    kernel = model.make_force_fn(topo, terms, scene.temperature)

    @jax.jit
    def run(params, x0, v0, h, n):
        system = integrators.System(topo, terms, kernel, np.asarray(scene.gravity)[:, None],
                                    lambda x_old, x, v: (x, v), h, scene.temperature)
        scheme = integrators.build(name, system, cg_tol=cg_tol)
        s = scheme.init(params, x0.T, v0.T)
        return jax.lax.fori_loop(0, n, lambda i, s: scheme.step(params, s), s).x.T

    return run


def _smooth_case():
    """Icosahedron with gas (uniform scaling is an exact mode, docs/model.md §8.5), released at its
    rest shape (it breathes), spinning and thrown: smooth, no floor, no damping."""
    scene = icosphere_scene(subdivisions=0, k=100.0, mass=0.05, nmol=5e-4)
    x0 = scene.vertices
    v0 = np.cross([0.0, 0.0, 4.0], x0) + np.array([0.2, 0.5, 0.0])
    return scene, x0, v0


# 1. Convergence orders ----------------------------------------------------------------------

@pytest.mark.parametrize("name", ALL)
def test_global_error_order(x64, name):
    """Self-convergence in float64: e(h) = max|x_h - x_{h/2}| at T = 0.02 s (6 rad of the fastest
    mode); the order log2(e(h)/e(h/2)) at the two finest pairs matches the scheme's order."""
    scene, x0, v0 = _smooth_case()
    run = _direct_runner(scene, name)
    params = jaxplush.make_simulator(scene, 1e-3).params()
    t_end = 0.02
    base = {4: t_end / 10, 2: t_end / 20}.get(ORDER[name], t_end / 40)
    xs = [np.asarray(run(params, jnp.asarray(x0), jnp.asarray(v0), base / n, 2 ** i * int(round(t_end / base))))
          for i, n in enumerate((1, 2, 4, 8, 16))]
    err = [np.abs(xs[i] - xs[i + 1]).max() for i in range(4)]
    orders = [np.log2(err[i] / err[i + 1]) for i in (1, 2)]
    assert err[-1] > 1e-11  # well above round-off: the orders are measured, not noise
    for p in orders:
        assert abs(p - ORDER[name]) < 0.2, (name, err, orders)


# 2. Free fall -------------------------------------------------------------------------------

@pytest.mark.parametrize("name, c", [("verlet", 0.0), ("rk4", 0.0), ("euler", -1.0), ("symplectic_euler", 1.0),
                                     ("implicit_euler", 1.0)])
def test_free_fall_centre_of_mass(x64, name, c):
    """Internal forces sum to zero, so the centre of mass follows each scheme's discrete free
    fall: exact for Verlet (its initialisation) and RK4, x0 + v0 t + g t²/2 + c g h t / 2 for the
    Euler schemes (c = -1 explicit, +1 symplectic and implicit; docs/model.md §8.1)."""
    scene = icosphere_scene(subdivisions=1, k=200.0, nmol=1e-3, dashpot=0.01, gravity=(0.3, -9.81, 0.2))
    run = _direct_runner(scene, name)
    p = jaxplush.make_simulator(scene, 1e-3).params()
    rng = np.random.default_rng(0)
    x0 = scene.vertices * 1.03 + 0.002 * rng.standard_normal(scene.vertices.shape)
    v0 = np.array([0.5, 2.0, -1.0]) + 0.3 * rng.standard_normal(x0.shape)
    g = scene.gravity
    for h, steps in ((2e-4, 200), (1e-4, 300)):
        com = np.asarray(run(p, jnp.asarray(x0), jnp.asarray(v0), h, steps)).mean(axis=0)
        t = h * steps
        exact = x0.mean(0) + v0.mean(0) * t + 0.5 * g * t ** 2
        assert np.abs(com - exact - c * 0.5 * g * h * t).max() < 1e-10
        if c:  # the Euler offset is really there: the test tells the schemes apart
            assert np.abs(com - exact).max() > 1e-6


# 3. Mesit's update is unsound (docs/model.md §2) -----------------------------------------------

def test_mesit_first_step_accelerates_at_a_fraction_of_g(x64):
    """At rest (no spring force, no gas) a dropped body's first velocity change is
    h g m / (m + k h² n) (the lag), not h g: 0.29 g for m = 1/162, k = 100, n = 6, h = 5 ms."""
    scene = icosphere_scene(subdivisions=2, k=100.0, mass=1.0)
    h = 5e-3
    sim = jaxplush.make_simulator(scene, h, "mesit")
    p = sim.params()
    s1 = sim.step_fn(p, sim.init_fn(p))
    n = sim.topology.ring_mask.sum(axis=1)
    m = 1.0 / scene.n_vertices
    expect = h * 9.81 * m / (m + 100.0 * h * h * n)
    np.testing.assert_allclose(-np.asarray(s1.v)[:, 1], expect, rtol=1e-9)  # rest springs: ~1e-11 round-off
    assert 0.25 < (expect / (h * 9.81))[n == 6][0] < 0.33


@functools.lru_cache(maxsize=None)
def _ringing_setup():
    scene = icosphere_scene(subdivisions=2, k=100.0, mass=1.0, nmol=5e-4, gravity=(0, 0, 0))
    sim0 = jaxplush.make_simulator(scene, 1e-3)
    p0 = sim0.params()
    est = jaxplush.estimate_stable_dt(sim0, p0)
    return scene, est, np.asarray(stability.inflated(sim0, p0, scene.vertices))


def _ringing_energy(name, factor, steps):
    """(E - E_eq) at the end over its initial value, for a perturbed, undamped, weightless ball
    (float64), run at ``factor`` times the explicit limit."""
    scene, est, x_eq = _ringing_setup()
    sim = jaxplush.make_simulator(scene, factor * est.dt_max, name)
    p = sim.params()
    x0 = x_eq + 2e-3 * np.random.default_rng(0).standard_normal(x_eq.shape)
    topo = sim.topology

    def energy(state):
        v = sim.velocity_fn(p, state)
        x = state.x
        return float(model.potential_energy(topo, p, x, scene.temperature) + model.kinetic_energy(topo, p, v))

    e_eq = float(model.potential_energy(topo, p, jnp.asarray(x_eq), scene.temperature))
    state = sim.init_fn(p, x0, None)
    e0 = energy(state) - e_eq
    final, _, health = jaxplush.rollout(sim, p, state, 1, steps)
    return (energy(final) - e_eq) / e0 if not health.failed else np.inf


@pytest.mark.heavy
def test_mesit_pumps_energy_where_symplectic_euler_is_bounded(x64):
    """The evidence for the docs: at a quarter of the explicit limit, 2000 steps of an undamped
    pressurised 162-vertex ball. Symplectic Euler keeps the ringing energy within a few percent;
    Mesit's lagged magnitude re-applied along the new force direction multiplies it (docs/model.md
    §2 measured x4.5e3 of the initial kinetic energy on the same sphere)."""
    assert abs(_ringing_energy("symplectic_euler", 0.25, 2000) - 1) < 0.1
    assert _ringing_energy("mesit", 0.25, 2000) > 10


# 4. Baraff-Witkin implicit Euler --------------------------------------------------------------

def _jacobians(sim, p, x):
    topo = sim.topology
    kernel = model.make_force_fn(topo, sim.terms, sim.scene.temperature)
    ring = np.ascontiguousarray(topo.ring.T)
    _, vol = kernel(p, x, jnp.zeros_like(x))
    jac = integrators._jacobians(topo, sim.terms, p, x, vol, sim.scene.temperature,
                                 lambda a: a.at[ring].get(), np.ascontiguousarray(topo.ring_rest.T),
                                 np.ascontiguousarray(topo.ring_mask.T), bool(topo.ring_mask.all()), 1e-4, 1e-4)
    return kernel, vol, jac


def test_implicit_jacobian_products_match_jvp(x64):
    """Stretched (no spring compressed): the hand-written df/dx u equals jax.jvp of the force
    minus the dropped P (d²V/dx²) u; df/dv u equals the jvp in v exactly (dashpot + drag)."""
    scene = icosphere_scene(subdivisions=1, k=200.0, nmol=1e-3, dashpot=0.05, drag=1.0)
    sim = jaxplush.make_simulator(scene, 1e-4, "implicit_euler")
    p = sim.params()
    rng = np.random.default_rng(0)
    x = jnp.asarray((1.3 * scene.vertices + 0.003 * rng.standard_normal(scene.vertices.shape)).T)
    u = jnp.asarray(rng.standard_normal(x.shape))

    @jax.jit
    def products(x, u):
        kernel, vol, jac = _jacobians(sim, p, x)
        zero = jnp.zeros_like(x)
        _, exact_x = jax.jvp(lambda y: kernel(p, y, zero)[0], (x,), (u,))
        grad_v = jax.grad(lambda y: model.face_volumes(sim.topology, y.T)[0])
        _, hess_u = jax.jvp(grad_v, (x,), (u,))
        pressure = model.pressure(sim.topology, p, vol, scene.temperature)
        _, exact_v = jax.jvp(lambda w: kernel(p, x, w)[0], (zero,), (u,))
        return exact_x - pressure * hess_u, jac.dfdx(u), exact_v, jac.dfdv(u)

    exact_x, ours_x, exact_v, ours_v = (np.asarray(a) for a in products(x, u))
    assert np.abs(exact_x - ours_x).max() < 1e-12 * np.abs(exact_x).max()
    assert np.abs(exact_v - ours_v).max() < 1e-12 * np.abs(exact_v).max()


def test_implicit_system_is_positive_definite_under_compression(x64):
    """Squashed to 60%: the exact spring Jacobian is indefinite (compressed springs), the clamped
    one is negative semi-definite, so M - h df/dv - h² df/dx is SPD for CG (docs/model.md §3)."""
    scene = icosphere_scene(subdivisions=1, k=200.0, gravity=(0, 0, 0))
    sim = jaxplush.make_simulator(scene, 1e-4, "implicit_euler")
    p = sim.params()
    x = jnp.asarray((0.6 * scene.vertices).T)
    n = x.size

    @jax.jit
    def matrices(x):
        kernel, _, jac = _jacobians(sim, p, x)
        basis = jnp.eye(n).reshape(n, 3, -1)
        exact = jax.vmap(lambda e: jax.jvp(lambda y: kernel(p, y, jnp.zeros_like(y))[0], (x,), (e,))[1])(basis)
        return jax.vmap(jac.dfdx)(basis).reshape(n, n), exact.reshape(n, n)

    ours, exact = (np.asarray(a) for a in matrices(x))
    np.testing.assert_allclose(ours, ours.T, atol=1e-9)
    assert np.linalg.eigvalsh(ours).max() < 1e-9              # -K: negative semi-definite
    assert np.linalg.eigvalsh(0.5 * (exact + exact.T)).max() > 1.0  # the raw Jacobian is not


def test_implicit_euler_is_stable_and_dissipative_at_ten_times_the_limit(x64):
    """10x the explicit limit on a ringing pressurised ball: no blow-up and the ringing energy
    decays (backward Euler's numerical damping ~omega² h/2), while Verlet blows up there."""
    assert _ringing_energy("implicit_euler", 10.0, 200) < 0.1
    assert _ringing_energy("verlet", 10.0, 200) == np.inf


# 5. Gradients ---------------------------------------------------------------------------------

@pytest.mark.parametrize("name", [pytest.param("implicit_euler", marks=pytest.mark.heavy), "mesit"])
def test_gradients_match_central_differences(x64, name):
    """d loss / d log(k, nmol, dashpot, drag) through 30 steps against central finite differences,
    float64. implicit_euler (at 3x the explicit limit) differentiates the CG solve implicitly
    (custom_linear_solve: a second CG solve in reverse mode); the explicit schemes are plain
    autodiff (Mesit's safe normalisation checked here; Verlet's in tests/test_physics.py)."""
    scene = icosphere_scene(subdivisions=1, k=100.0, nmol=1e-3, dashpot=0.05, drag=0.5)
    sim0 = jaxplush.make_simulator(scene, 1e-4)
    hc = jaxplush.estimate_stable_dt(sim0, sim0.params()).dt_max
    sim = jaxplush.make_simulator(scene, (3.0 if name == "implicit_euler" else 0.2) * hc, name)
    p0 = sim.params()
    rng = np.random.default_rng(1)
    x0 = scene.vertices * 1.02 + 0.002 * rng.standard_normal(scene.vertices.shape)
    target = scene.vertices + 0.01 * rng.standard_normal(scene.vertices.shape)

    @jax.jit
    def loss(theta):
        k, n, c, g = jnp.exp(theta)
        p = p0._replace(k_structural=p0.k_structural * 0 + k, nmol=p0.nmol * 0 + n,
                        dashpot=p0.dashpot * 0 + c, drag=p0.drag * 0 + g)
        s = sim.internal.to_internal(sim.init_fn(p, x0, None))
        s = jax.lax.scan(lambda s, _: (sim.internal.step(p, s), None), s, None, length=30)[0]
        return jnp.mean((s.x.T - target) ** 2)

    theta = jnp.log(jnp.array([100.0, 1e-3, 0.05, 0.5]))
    g = np.asarray(jax.grad(loss)(theta))
    res = assert_gradient_matches_fd(lambda t: float(loss(jnp.asarray(t))), np.asarray(theta), g, h=1e-4,
                                     rtol=1e-4)   # the CG tolerance (1e-10) limits the differences
    assert np.all(np.abs(res.fd) > 1e-12)   # every parameter matters (FD noise ~1e-15)


# 6. Substeps and per-integrator stability limits -------------------------------------------------

@pytest.mark.parametrize("name", ["verlet", "implicit_euler"])
def test_substeps_equal_smaller_steps(x64, name):
    """``substeps=4`` at dt is the same computation as four steps of dt/4 (floor, pins included)."""
    scene = icosphere_scene(subdivisions=1, k=200.0, nmol=1e-3, dashpot=0.01, floor=-0.12, fixed=(3,))
    dt = 8e-4
    a = jaxplush.make_simulator(scene, dt, name, substeps=4)
    b = jaxplush.make_simulator(scene, dt / 4, name)
    assert a.h == b.dt and a.substeps == 4
    p = a.params()
    fa = jaxplush.rollout(a, p, a.init_fn(p), 5, 10)[1]
    fb = jaxplush.rollout(b, p, b.init_fn(p), 5, 40)[1]
    assert np.asarray(fa)[:, :, 1].min() < -0.1   # it reached the floor
    np.testing.assert_allclose(fa, fb, rtol=0, atol=1e-10)


def test_dt_warning_per_integrator_and_substep():
    """The limit each integrator is held to (docs/model.md §4): Verlet/symplectic 2/omega, RK4
    2 sqrt(2)/omega, Euler-type none without damping, implicit Euler none; per substep."""
    est = stability.StabilityEstimate(dt_max=2e-3, omega_max=1e3, gamma_max=0.0, dt_gershgorin=1e-3)
    assert "exceeds" in stability.dt_warning(est, "verlet", 2.2e-3)
    assert "exceeds" in stability.dt_warning(est, "symplectic_euler", 2.2e-3)
    assert stability.dt_warning(est, "verlet", 1.8e-3) is None
    assert stability.dt_warning(est, "verlet", 4.4e-3, substeps=3) is None
    assert stability.dt_warning(est, "rk4", 2.7e-3) is None and "exceeds" in stability.dt_warning(est, "rk4", 2.9e-3)
    assert "no stable step" in stability.dt_warning(est, "euler", 1e-5)
    assert "no stable step" in stability.dt_warning(est, "mesit", 1e-5)
    assert stability.dt_warning(est, "implicit_euler", 1.0) is None
    damped = est._replace(gamma_max=100.0)                        # Euler: h < gamma / omega²
    assert abs(stability.integrator_limit(damped, "euler") - 1e-4) < 1e-9


def test_simulate_warns_with_the_integrators_limit(x64):
    scene = icosphere_scene(subdivisions=1, k=200.0, nmol=1e-3)
    sim = jaxplush.make_simulator(scene, 1e-4)
    hc = jaxplush.estimate_stable_dt(sim, sim.params()).dt_max
    with pytest.warns(UserWarning, match="exceeds the estimated explicit stability limit .* of verlet"):
        traj = jaxplush.simulate(scene, steps=2, dt=2.4 * hc, integrator="verlet", substeps=2)
    assert traj.substeps == 2 and traj.integrator == "verlet"


def _exact_rates(sim, params, x):
    """(omega_max², gamma_max) of the linearised force at x from dense Jacobians (float64)."""
    topo = sim.topology
    m = np.asarray(jaxplush.model.forces.vertex_mass(topo, params))
    free = np.ones(topo.n_vertices, bool)
    free[topo.fixed] = False
    s = np.repeat(free / np.sqrt(m), 3)
    n = 3 * topo.n_vertices
    zero = jnp.zeros((topo.n_vertices, 3))
    # jitted: one compile instead of thousands of small dispatches
    k = -np.asarray(jax.jit(jax.jacfwd(lambda y: sim.force_fn(params, y.reshape(-1, 3), zero)[0].ravel()))(
        jnp.asarray(x).ravel())).reshape(n, n)
    c = -np.asarray(jax.jit(jax.jacfwd(lambda w: sim.force_fn(params, jnp.asarray(x), w.reshape(-1, 3))[0].ravel()))(
        jnp.zeros(n))).reshape(n, n)
    sym = lambda a: 0.5 * (a + a.T)  # noqa: E731
    return (np.linalg.eigvalsh(sym(s[:, None] * k * s[None]))[-1],
            np.linalg.eigvalsh(sym(s[:, None] * c * s[None]))[-1])


@pytest.mark.parametrize("case", [pytest.param("gas_dashpot", marks=pytest.mark.heavy), "pinned_drag", "stretched",
                                  pytest.param("two_objects", marks=pytest.mark.heavy)])
def test_closed_form_bound_is_safe(x64, case):
    """stability.bound (numpy, nothing compiled) bounds omega_max and gamma_max from above, checked
    against the exact eigenvalues of dense Jacobians, at rest and inflated; so its dt is safe. It is
    also not far below the power-iteration estimate (at least 0.6 of it)."""
    if case == "gas_dashpot":
        scene = icosphere_scene(subdivisions=1, k=200.0, nmol=3e-3, dashpot=0.05)
    elif case == "pinned_drag":
        scene = icosphere_scene(subdivisions=1, k=80.0, nmol=1e-3, drag=2.0, fixed=(0,))
    elif case == "stretched":              # strongly inflated: springs pre-tensioned 30% past rest
        scene = icosphere_scene(subdivisions=1, k=20.0, nmol=5e-4, damping=300.0)   # s* = 1.3
    else:
        text = icosphere_text(subdivisions=1, k=150.0, nmol=1e-3, name="a") + icosphere_text(
            subdivisions=1, k=300.0, mass=0.02, nmol=5e-4, name="b", offset=42, header=False, translate=(0.25, 0, 0))
        scene = jaxplush.parse_scene(text, "<two>")
    sim = jaxplush.make_simulator(scene, 1e-4)
    p = sim.params()
    b = stability.bound(sim, p)
    for x in (scene.vertices, np.asarray(stability.inflated(sim, p, scene.vertices))):
        w2, gam = _exact_rates(sim, p, x)
        assert b.omega_max ** 2 >= w2 * (1 - 1e-9) and b.gamma_max >= gam * (1 - 1e-9) - 1e-12
    est = stability.estimate(sim, p)
    assert 0.6 * est.dt_max <= b.dt_max <= est.dt_max * (1 + 1e-9)


@pytest.mark.parametrize("factor, stable", [(0.9, True), (1.1, False)])
def test_rk4_limit_is_right(x64, factor, stable):
    """RK4 runs at 0.9x its estimated limit 2 sqrt(2)/omega_max and fails at 1.1x, on the inflated
    ball (docs/model.md §4 and §8.9; Verlet's own limit: tests/test_physics.py)."""
    name = "rk4"
    scene = icosphere_scene(subdivisions=2, k=100.0, mass=1.0, nmol=5e-4, gravity=(0, 0, 0))
    sim = jaxplush.make_simulator(scene, 1e-3)
    est = jaxplush.estimate_stable_dt(sim, sim.params())
    limit = stability.integrator_limit(est, name)
    assert abs(limit * est.omega_max - 2 * np.sqrt(2)) < 1e-6
    x_eq = np.asarray(stability.inflated(sim, sim.params(), scene.vertices))
    sim = jaxplush.make_simulator(scene, factor * limit, name)
    p = sim.params()
    state = sim.init_fn(p, x_eq + 1e-4 * np.random.default_rng(0).standard_normal(x_eq.shape), None)
    final, _, health = jaxplush.rollout(sim, p, state, 20, 100)
    amp = np.abs(np.asarray(final.x) - x_eq).max()
    if stable:
        assert not health.failed and amp < 0.05
    else:
        assert health.failed or amp > 1.0


def test_report_damping_keeps_its_meaning_per_dt_under_substeps(x64):
    """D is per time step dt: a free-falling drop with only the report's damping reaches the same
    velocity after 1 s with 1 or 4 substeps (terminal velocity g dt / f per dt either way), and the
    per-substep factor compounds to 1 - 1/D over one dt."""
    assert float(integrators.damping_keep(jnp.asarray(50.0), 4) ** 4) == pytest.approx(1 - 1 / 50, rel=1e-12)
    assert float(integrators.damping_keep(jnp.asarray(50.0), 1)) == 1 - 1 / 50
    scene = icosphere_scene(subdivisions=1, k=100.0, damping=50.0)
    speeds = []
    for n in (1, 4):
        sim = jaxplush.make_simulator(scene, 1e-3, substeps=n)
        p = sim.params()
        final, _, _ = jaxplush.rollout(sim, p, sim.init_fn(p), 1, 1000)
        speeds.append(float(jnp.mean(sim.velocity_fn(p, final)[:, 1])))
    gamma = -np.log(1 - 1 / 50) / 1e-3                  # the drag rate of D per dt
    assert speeds[1] == pytest.approx(-9.81 / gamma, rel=2e-2)
    assert speeds[0] == pytest.approx(speeds[1], rel=2e-2)
