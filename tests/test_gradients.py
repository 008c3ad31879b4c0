"""Gradients through rollouts (jaxplush.fitting.objective.gradients): every method gives the same value and gradient,
and that gradient matches central finite differences (float64)."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxplush
from jaxplush.model import contact
from conftest import assert_gradient_matches_fd, icosphere_scene, icosphere_text
from jaxplush.fitting.objective import gradients as G

DT = 2e-4
FRAMES = (0, 5, 17, 30)
#: methods compared against each other; "adjoint" joins when the simulator supports it.
METHODS = ("plain", "checkpoint", "adjoint")


def _full_scene():
    """Springs + gas + gravity + Verlet damping + dashpot + drag, resting 0.5 mm above a floor."""
    return icosphere_scene(subdivisions=1, k=200.0, mass=0.05, nmol=5e-4, dashpot=0.02, drag=0.5,
                           damping=300.0, floor=-0.1005)


def _pinned_two_objects():
    """Two objects (no contact), the first hanging from two pinned vertices, the second free with gas."""
    a = icosphere_text(subdivisions=1, k=150.0, mass=0.04, dashpot=0.01, fixed=(0, 3), name="hung",
                       damping=200.0)
    b = icosphere_text(subdivisions=1, k=300.0, mass=0.08, nmol=8e-4, drag=0.3, name="free",
                       translate=(0.3, 0.0, 0.0), offset=42, header=False)
    return jaxplush.parse_scene("contact off\n" + a + b, "<two>")


SCENES = {"full": _full_scene, "pinned_two": _pinned_two_objects}


def test_recomputed_segments_restart_with_their_velocity(x64):
    """A scene whose backward pass needs no velocity (springs, gas, gravity: no damping term): the
    adjoint that recomputes segments from checkpoints still equals plain autodiff (each segment
    restarts from its checkpoint's velocity as well as its positions)."""
    sim = jaxplush.make_simulator(icosphere_scene(subdivisions=1, k=200.0, mass=0.05, nmol=5e-4), DT)
    p = sim.params()
    x0 = np.asarray(sim.topology.x0)
    aux = (jnp.asarray(x0[None] + 1e-3 * np.random.default_rng(6).standard_normal((len(FRAMES),) + x0.shape)),
           jnp.ones((len(FRAMES), sim.topology.n_vertices)))

    def f(q, method, seg=None):
        return G.rollout_loss(sim, q, sim.init_fn(q, v0=_v0(sim)), FRAMES, _sq_loss, aux, method=method, segment=seg)
    ref = np.asarray(jnp.stack(list(jax.jit(jax.grad(functools.partial(f, method="plain")))(p))))
    got = np.asarray(jnp.stack(list(jax.jit(jax.grad(functools.partial(f, method="adjoint", seg=7)))(p))))
    np.testing.assert_allclose(got, ref, rtol=1e-10, atol=1e-10 * np.abs(ref).max())


def _v0(sim):
    """A downward initial velocity with some shear, so the floor is hit within a few steps."""
    x0 = np.asarray(sim.topology.x0)
    v = np.zeros_like(x0)
    v[:, 1] = -0.6 + 2.0 * x0[:, 0]
    v[:, 2] = 0.8 * x0[:, 1]
    return v


def _targets(sim):
    x0 = np.asarray(sim.topology.x0)
    rng = np.random.default_rng(0)
    return jnp.asarray(x0[None] + 1e-3 * rng.standard_normal((len(FRAMES),) + x0.shape))


def _sq_loss(x, aux):
    t, w = aux
    return jnp.sum(w * jnp.sum((x - t) ** 2, axis=-1))


def _setup(name):
    sim = jaxplush.make_simulator(SCENES[name](), DT)
    p = sim.params()
    w = jnp.linspace(0.5, 1.5, len(FRAMES))[:, None] * jnp.ones((1, sim.topology.n_vertices))
    aux = (_targets(sim), w)
    return sim, p, aux


def _loss(sim, aux, method, segment=None):
    v0 = _v0(sim)

    def f(p):
        return G.rollout_loss(sim, p, sim.init_fn(p, v0=v0), FRAMES, _sq_loss, aux, method=method,
                              segment=segment)
    return f


def _methods(sim):
    return [m for m in METHODS if m != "adjoint" or G.adjoint_supported(sim)]


@functools.lru_cache(maxsize=None)
def _results(name):
    with jax.enable_x64(True):
        sim, p, aux = _setup(name)
        out = {}
        for m in _methods(sim):
            if m == "checkpoint" and name != "full":
                continue                          # autodiff either way; compiled once is enough
            for seg in {"plain": (None,), "checkpoint": (7,), "adjoint": (None, 7)}[m]:
                v, g = jax.jit(jax.value_and_grad(_loss(sim, aux, m, seg)))(p)
                out[(m, seg)] = (float(v), np.asarray(jnp.stack(list(g))))
        return out


@pytest.mark.parametrize("name", ["full", pytest.param("pinned_two", marks=pytest.mark.heavy)])
def test_methods_agree(x64, name):
    res = _results(name)
    v_ref, g_ref = res[("plain", None)]
    assert np.isfinite(g_ref).all() and np.abs(g_ref).max() > 0
    for key, (v, g) in res.items():
        assert v == pytest.approx(v_ref, rel=1e-12), key
        # in norm: a component near zero gets no say over a rounding-level difference
        assert np.linalg.norm(np.asarray(g) - g_ref) <= 1e-10 * np.linalg.norm(g_ref), key


@pytest.mark.parametrize("name", ["full", pytest.param("pinned_two", marks=pytest.mark.heavy)])
def test_gradient_matches_finite_differences(x64, name):
    """Central differences along each parameter (relative step), float64."""
    sim, p, aux = _setup(name)
    f = jax.jit(_loss(sim, aux, "auto"))
    _, g = _results(name)[("plain", None)]
    g = g.reshape(len(p), -1)
    # in log space over the non-zero parameters, so that every component has the same units
    base = np.asarray(jnp.stack(list(p)))
    on = base != 0

    def f_log(theta):
        vals = np.array(base)
        vals[on] = np.exp(theta)
        return float(f(type(p)(*(jnp.asarray(v) for v in vals))))
    assert_gradient_matches_fd(f_log, np.log(base[on]), g[on] * base[on], h=1e-4, rtol=1e-6)


def test_value_matches_forward_rollout(x64):
    """The loss equals the same sum computed from an ordinary jaxplush.rollout."""
    sim, p, aux = _setup("full")
    v0 = _v0(sim)
    state = sim.init_fn(p, v0=v0)
    _, frames, health = jaxplush.rollout(sim, p, state, FRAMES[-1], 1)
    assert not health.failed
    xs = jnp.concatenate([state.x[None], frames])[jnp.asarray(FRAMES)]
    expect = sum(float(_sq_loss(xs[j], (aux[0][j], aux[1][j]))) for j in range(len(FRAMES)))
    assert float(_loss(sim, aux, "auto")(p)) == pytest.approx(expect, rel=1e-12)
    # the floor is really hit in this scene (so its projection is exercised by the gradient tests)
    assert float(jnp.min(frames[:, :, 1])) == pytest.approx(sim.scene.floor, abs=1e-12)


def test_gradient_wrt_initial_state(x64):
    """Cotangents flow into state0 (positions and velocity) and match finite differences."""
    sim, p, aux = _setup("full")
    s0 = sim.init_fn(p, v0=_v0(sim))
    rng = np.random.default_rng(1)
    dx, dv = (jnp.asarray(rng.standard_normal(s0.x.shape)) for _ in range(2))

    def f(s):
        return G.rollout_loss(sim, p, s, FRAMES, _sq_loss, aux, method="adjoint", segment=7)
    g = jax.jit(jax.grad(f))(s0)
    fj = jax.jit(f)
    an = jnp.sum(g.x * dx) + jnp.sum(g.v * dv)
    # the directional derivative along (dx, dv), against differences at two steps
    assert_gradient_matches_fd(lambda t: float(fj(jaxplush.State(s0.x + t[0] * dx, s0.v + t[0] * dv))),
                               np.zeros(1), [float(an)], h=1e-6, rtol=1e-6)


def test_chain_rule_through_log_parameters_and_jit(x64):
    """Usable inside jit and value_and_grad through a user's log-parameter map."""
    sim, p, aux = _setup("full")
    v0 = _v0(sim)

    def f(logk):
        q = p._replace(k_structural=jnp.exp(logk))
        return G.rollout_loss(sim, q, sim.init_fn(q, v0=v0), FRAMES, _sq_loss, aux)

    logk = jnp.log(p.k_structural)
    v, g = jax.jit(jax.value_and_grad(f))(logk)
    _, gp = _results("full")[("plain", None)]
    np.testing.assert_allclose(np.asarray(g), gp[0] * np.asarray(p.k_structural), rtol=1e-10)


def test_bad_arguments():
    sim = jaxplush.make_simulator(icosphere_scene(subdivisions=0), DT)
    p = sim.params()
    s = sim.init_fn(p)
    t = jnp.zeros((2, sim.topology.n_vertices, 3))
    lf = lambda x, a: jnp.sum((x - a) ** 2)  # noqa: E731
    with pytest.raises(ValueError, match="strictly increasing"):
        G.rollout_loss(sim, p, s, (0, 0), lf, t)
    with pytest.raises(ValueError, match=">= 0"):
        G.rollout_loss(sim, p, s, (-1, 3), lf, t)
    with pytest.raises(ValueError, match="leading axis"):
        G.rollout_loss(sim, p, s, (1, 2, 3), lf, t)
    with pytest.raises(ValueError, match="unknown method"):
        G.rollout_loss(sim, p, s, (1, 2), lf, t, method="magic")
    with pytest.raises(ValueError, match="segment"):
        G.rollout_loss(sim, p, s, (1, 2), lf, t, method="checkpoint", segment=0)
    with pytest.raises(ValueError, match="empty"):
        G.rollout_loss(sim, p, s, (), lf, t[:0])


@pytest.mark.heavy
def test_memory_is_bounded():
    """Compiled temporaries of the gradient: plain autodiff keeps residuals of every step; the
    checkpointed and the recomputing adjoint grow with segments; the storing adjoint keeps the
    positions of every step and nothing more."""
    sim = jaxplush.make_simulator(icosphere_scene(subdivisions=0, floor=-0.2), 1e-4)
    p = sim.params()
    n = sim.topology.n_vertices
    steps = 5000
    aux = jnp.zeros((1, n, 3))

    def temp(method, **kw):
        def f(q):
            return G.rollout_loss(sim, q, sim.init_fn(q), (steps,), lambda x, t: jnp.sum((x - t) ** 2), aux,
                                  method=method, **kw)
        return G.compiled_memory(jax.grad(f), p)["temp"]

    positions = steps * 3 * n * 4                 # float32 positions of every step
    plain = temp("plain")
    assert plain > 2 * positions                  # residuals of every step
    assert temp("checkpoint", segment=50) < 0.1 * plain
    assert temp("adjoint", segment=50) < 0.1 * positions
    assert positions <= temp("adjoint") < 1.2 * positions
    assert temp("adjoint", memory_budget=positions // 2) < 0.1 * positions   # over budget: recompute


def _chamfer(x, aux, scale):
    pts, w = aux
    d2 = jnp.sum((x[:, None, :] - pts[None, :, :]) ** 2, axis=-1)           # (V, M)
    return scale * w * (jnp.mean(jnp.min(d2, axis=1)) + jnp.mean(jnp.min(d2, axis=0)))


@pytest.mark.heavy
def test_cotangents_of_loss_data(x64):
    """A point-cloud (Chamfer) loss whose aux and a closed-over constant are differentiated too:
    the adjoint returns the same cotangents as autodiff for params, aux and the constant."""
    sim, p, _ = _setup("full")
    rng = np.random.default_rng(3)
    pts = jnp.asarray(0.1 * rng.standard_normal((len(FRAMES), 30, 3)))
    w = jnp.linspace(1.0, 2.0, len(FRAMES))
    v0 = _v0(sim)

    def f(p, aux, scale, method):
        return G.rollout_loss(sim, p, sim.init_fn(p, v0=v0), FRAMES, lambda x, a: _chamfer(x, a, scale), aux,
                              method=method, segment=7)

    grads = {m: jax.jit(jax.grad(functools.partial(f, method=m), argnums=(0, 1, 2)))(p, (pts, w), 1.5)
             for m in ("plain", "adjoint")}
    flat = {m: jax.tree_util.tree_leaves(g) for m, g in grads.items()}
    for a, b in zip(flat["adjoint"], flat["plain"]):
        np.testing.assert_allclose(a, b, rtol=1e-10, atol=1e-10 * float(jnp.max(jnp.abs(b))))
    assert float(jnp.max(jnp.abs(grads["adjoint"][1][0]))) > 0     # the points do get a gradient


@pytest.mark.parametrize("name", list(SCENES))
def test_step_vjp_matches_autodiff(x64, name):
    """The fused adjoint's one-step VJP equals jax.vjp of sim.internal.step (all terms, pins,
    floor contacts, several objects) at a perturbed, moving state."""
    sim, p, _ = _setup(name)
    rng = np.random.default_rng(2)
    x = jnp.asarray(sim.topology.x0.T) + 2e-3 * rng.standard_normal((3, sim.topology.n_vertices))
    x = x.at[1].add(-4e-3)                                   # some vertices land below the floor
    u = jnp.asarray(0.3 * rng.standard_normal(x.shape)).at[1].add(-1.0)
    x_bar, u_bar = (jnp.asarray(rng.standard_normal(x.shape)) for _ in range(2))

    @jax.jit
    def both(p, x, u):
        out, vjp = jax.vjp(sim.internal.step, p, jaxplush.State(x, u))
        return out, vjp(jaxplush.State(x_bar, u_bar)), G._make_step_vjp(sim)(p, x, u, out.x, x_bar, u_bar)

    out, (p_ref, s_ref), (xb, ub, pb) = both(p, x, u)
    for got, ref in [(xb, s_ref.x), (ub, s_ref.v)] + list(zip(pb, p_ref)):
        # in norm (a parameter's cotangent sums many terms; its components can cancel)
        assert float(jnp.linalg.norm(got - ref)) <= 1e-11 * float(jnp.linalg.norm(ref))
    if sim.terms.floor:
        assert bool(jnp.any(out.x[1] == sim.scene.floor))     # the projection is exercised


@pytest.mark.heavy
def test_generic_fallback_for_other_integrators(x64):
    """Integrators without a fused adjoint ("auto" -> checkpoint) give autodiff's gradient."""
    sim = jaxplush.make_simulator(_full_scene(), DT, integrator="symplectic_euler")
    assert not G.adjoint_supported(sim)
    p = sim.params()
    aux = (_targets(sim), jnp.ones((len(FRAMES), sim.topology.n_vertices)))
    res = [jax.jit(jax.value_and_grad(_loss(sim, aux, m, 7)))(p) for m in ("auto", "plain")]
    assert float(res[0][0]) == pytest.approx(float(res[1][0]), rel=1e-12)
    for a, b in zip(res[0][1], res[1][1]):
        np.testing.assert_allclose(a, b, rtol=1e-10)
    with pytest.raises(ValueError, match="not supported"):
        _loss(sim, aux, "adjoint")(p)


@pytest.mark.heavy
def test_step_vjp_with_contact(x64):
    """Soft-soft contact (on by default between objects) is part of the fused adjoint: two balls
    pressed together, one step's VJP against autodiff."""
    a = icosphere_text(subdivisions=0, k=150.0, mass=0.04, nmol=5e-4, name="a")
    b = icosphere_text(subdivisions=0, k=300.0, mass=0.08, nmol=8e-4, name="b", translate=(0.19, 0.0, 0.0),
                       offset=12, header=False)
    sim = jaxplush.make_simulator(jaxplush.parse_scene(a + b, "<contact>"), DT)
    assert sim.terms.contact and G.adjoint_supported(sim)
    p = sim.params()
    x = jnp.asarray(sim.topology.x0.T)
    u = jnp.zeros_like(x).at[0, :12].set(0.2)                 # a pushes into b
    rng = np.random.default_rng(4)
    x_bar, u_bar = (jnp.asarray(rng.standard_normal(x.shape)) for _ in range(2))
    contact_force = contact.make_contact_force(sim.topology, sim.terms.contact)

    @jax.jit
    def both(p, x, u):
        out, vjp = jax.vjp(sim.internal.step, p, jaxplush.State(x, u))
        return (vjp(jaxplush.State(x_bar, u_bar)), G._make_step_vjp(sim)(p, x, u, out.x, x_bar, u_bar),
                jnp.max(jnp.abs(contact_force(p, x))))

    (p_ref, s_ref), (xb, ub, pb), f_contact = both(p, x, u)
    assert float(f_contact) > 0                               # the balls do touch
    for got, ref in [(xb, s_ref.x), (ub, s_ref.v)] + list(zip(pb, p_ref)):
        np.testing.assert_allclose(got, ref, rtol=1e-11, atol=1e-11 * float(jnp.max(jnp.abs(ref))))


def test_vmap_over_params_and_integer_aux():
    """jax.vmap of the adjoint's gradient over a batch of parameters equals one-by-one autodiff;
    integer leaves of aux are data (no cotangent)."""
    sim = jaxplush.make_simulator(icosphere_scene(subdivisions=0, nmol=5e-4, floor=-0.2, damping=300.0), 1e-4)
    p = sim.params()
    aux = (jnp.zeros((2, sim.topology.n_vertices, 3)), jnp.arange(2))

    def f(q, method):
        return G.rollout_loss(sim, q, sim.init_fn(q), (10, 20), lambda x, a: jnp.sum((x - a[0]) ** 2) * (1 + a[1]),
                              aux, method=method)

    ks = jnp.asarray([80.0, 100.0, 120.0], p.k_structural.dtype)
    batch = jax.tree_util.tree_map(lambda a: jnp.broadcast_to(a, (3,) + a.shape), p)._replace(k_structural=ks[:, None])
    got = jax.jit(jax.vmap(jax.grad(functools.partial(f, method="adjoint"))))(batch).k_structural[:, 0]
    grad_plain = jax.jit(jax.grad(functools.partial(f, method="plain")))
    ref = [grad_plain(p._replace(k_structural=k[None])).k_structural[0] for k in ks]
    np.testing.assert_allclose(got, ref, rtol=1e-4)


@pytest.mark.heavy
def test_adjoint_frames_on_segment_boundaries(x64):
    """Frames at step 0, on every step (1, 2, 3), on checkpoint boundaries (4, 8, 14, 21) and in a
    short last segment (23), under segments of 7, 4 and 1 step and with every state stored: the
    adjoint equals plain autodiff. (One frame set, so one compile per segment length.)"""
    frames = (0, 1, 2, 3, 4, 8, 9, 14, 21, 23)
    sim, p, _ = _setup("full")
    v0 = _v0(sim)
    x0 = np.asarray(sim.topology.x0)
    rng = np.random.default_rng(5)
    aux = (jnp.asarray(x0[None] + 1e-3 * rng.standard_normal((len(frames),) + x0.shape)),
           jnp.linspace(0.5, 1.5, len(frames))[:, None] * jnp.ones((1, sim.topology.n_vertices)))

    def f(q, method, seg):
        return G.rollout_loss(sim, q, sim.init_fn(q, v0=v0), frames, _sq_loss, aux, method=method, segment=seg)

    ref_v, ref_g = jax.jit(jax.value_and_grad(functools.partial(f, method="plain", seg=None)))(p)
    ref_g = np.asarray(jnp.stack(list(ref_g)))
    assert np.abs(ref_g).max() > 0
    for seg in (7, 4, 1, None):
        v, g = jax.jit(jax.value_and_grad(functools.partial(f, method="adjoint", seg=seg)))(p)
        assert float(v) == pytest.approx(float(ref_v), rel=1e-12)
        np.testing.assert_allclose(np.asarray(jnp.stack(list(g))), ref_g, rtol=1e-10,
                                   atol=1e-10 * np.abs(ref_g).max(), err_msg=str(seg))
