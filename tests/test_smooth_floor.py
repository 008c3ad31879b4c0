"""The smooth floor (``floor_model smooth``): scene keywords, the force as minus the gradient of its
energy, energy conservation, the batched simulator, a loss that is smooth where the projection's
is not, and a fit that keeps the scene's floor model."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxplush
from jaxplush.stepping import batched
from jaxplush.model import forces as model
from jaxplush.stepping import stability
from jaxplush.scene.write import format_scene
from conftest import assert_gradient_matches_fd, icosphere_text


def _smooth(text):
    return text.replace("floor 0.0\n", "floor 0.0\nfloor_model smooth\n", 1)


def _ball(sub=1, **kw):
    kw.setdefault("floor", 0.0)
    kw.setdefault("translate", (0, 0.15, 0))
    return _smooth(icosphere_text(subdivisions=sub, k=200.0, nmol=1e-3, **kw))


def test_keywords_parse_and_round_trip():
    scene = jaxplush.parse_scene(_ball(), "<s>")
    assert scene.floor_model == "smooth" and scene.floor_stiffness is None
    terms = model.Terms.for_scene(scene)
    assert terms.floor_smooth is not None and not terms.floor          # no projection compiled
    assert "floor_smooth" in terms.names() and "floor" not in terms.names()
    fixed = jaxplush.parse_scene(_ball().replace("floor_model smooth\n", "floor_model smooth\nfloor_stiffness 321\n"),
                                 "<s>")
    assert fixed.floor_stiffness == 321.0 and model.Terms.for_scene(fixed).floor_smooth.stiffness == 321.0
    o = scene.objects[0]
    text = format_scene([dict(name=o.name, vertices=scene.vertices, faces=scene.faces, k_structural=200.0,
                              nmol=1e-3, total_weight=0.05)], floor=0.0, floor_model="smooth", floor_stiffness=50.0)
    back = jaxplush.parse_scene(text, "<back>")
    assert back.floor_model == "smooth" and back.floor_stiffness == 50.0


@pytest.mark.parametrize("edit, message", [
    (lambda t: t.replace("floor_model smooth", "floor_model bouncy"), "'floor_model' expects 'projection' or 'smooth'"),
    (lambda t: t.replace("floor 0.0\n", ""), "'floor_model' needs a 'floor'"),
    (lambda t: t.replace("floor_model smooth", "floor_model projection\nfloor_stiffness 10"),
     "'floor_stiffness' needs 'floor_model smooth'"),
    (lambda t: t.replace("floor_model smooth", "floor_model smooth\nfloor_friction 0.5"),
     "'floor_friction' acts in the floor projection"),
    (lambda t: t.replace("floor_model smooth", "floor_model smooth\nfloor_stiffness -3"), "must be > 0"),
])
def test_bad_keywords_name_file_and_line(edit, message):
    with pytest.raises(jaxplush.SceneError, match=message) as e:
        jaxplush.parse_scene(edit(_ball()), "floor.obj")
    assert str(e.value).startswith("floor.obj:")


def test_force_is_minus_the_gradient_of_its_energy(x64):
    scene = jaxplush.parse_scene(_ball(), "<s>")
    topo = model.build_topology(scene)
    cfg = model.Terms.for_scene(scene).floor_smooth
    p = jaxplush.make_simulator(scene, 1e-4).params()
    y = jnp.linspace(-0.01, 0.05, topo.n_vertices)            # below, at and well above the floor
    f = model.smooth_floor_force(topo, cfg, p, y)
    g = jax.grad(lambda yy: model.smooth_floor_energy(topo, cfg, p, yy))(y)
    np.testing.assert_allclose(np.asarray(f), -np.asarray(g), rtol=1e-12, atol=1e-12 * float(jnp.max(jnp.abs(f))))
    assert float(f[0]) > 0 and abs(float(f[-1])) < 1e-6 * float(f[0])   # pushes up below, nothing well above


def _bounce_energy_error(scene, dt, duration=0.4):
    from jaxplush.stepping import diagnostics
    sim = jaxplush.make_simulator(scene, dt)
    p = sim.params()
    state = sim.init_fn(p)
    e0 = diagnostics.energies(sim, p, state)
    errs, lowest = [], np.inf
    n = int(round(0.02 / dt))
    for _ in range(int(round(duration / 0.02))):
        state, frames, health = jaxplush.rollout(sim, p, state, n, 1)
        assert not health.failed
        lowest = min(lowest, float(np.min(frames[:, :, 1])))
        errs.append(diagnostics.energies(sim, p, state)["total"] - e0["total"])
    return np.max(np.abs(errs)), lowest, e0


def test_undamped_bounce_conserves_energy_and_a_damped_ball_rests(x64):
    """No damping: through impacts on the smooth floor the total energy (with the floor's) stays
    bounded, within 5% of the drop's, and halving dt cuts the error about fourfold (second order,
    no drift). A damped ball comes to rest a little below the floor, less deep than its whole weight
    would press one vertex (M g / k_f)."""
    scene = jaxplush.parse_scene(_ball(sub=2), "<s>")
    sim0 = jaxplush.make_simulator(scene, 1e-4)
    dt = 0.4 * stability.estimate(sim0, sim0.params()).dt_max
    err, lowest, e0 = _bounce_energy_error(scene, dt)
    err2, _, _ = _bounce_energy_error(scene, dt / 2)
    assert lowest < 0.0                                            # it went into the floor and back
    assert err < 0.05 * e0["gravity"] and 2.5 < err / err2 < 6.0
    damped = jaxplush.parse_scene(_ball(sub=2, dashpot=0.05, drag=5.0), "<d>")
    traj = jaxplush.simulate(damped, steps=int(1.5 / dt), dt=dt, save_every=int(0.5 / dt))
    k_f = 0.1 * 2 * 6 * 200.0
    assert -0.05 * 9.81 / k_f < traj.positions[-1][:, 1].min() < 0.0     # less than all the weight on one vertex


def test_batched_matches_the_single_scene_step(x64):
    scene = jaxplush.parse_scene(_ball(), "<s>")
    traj = jaxplush.simulate(scene, 600, 2e-4, 100)
    bsim = batched.make_batched_simulator(scene, 2e-4, 2)
    p = bsim.params()
    _, obs, health = batched.rollout(bsim, p, jax.jit(bsim.init_fn)(p), 6, 100, observe=batched.positions_observer)
    assert not health.failed.any() and traj.positions[:, :, 1].min() < 0
    np.testing.assert_allclose(np.asarray(obs)[:, 0], traj.positions[1:], atol=1e-10)


@pytest.mark.heavy
def test_loss_through_the_smooth_floor_is_smooth(x64):
    """A dashpot-damped ball dropped onto the smooth floor, its loss against a target along log k:
    central differences at steps 1e-4 and 1e-5 agree with each other and with the gradient (through
    the projection they scatter by up to 5% at 1e-3: benchmarks/RESULTS.md, "Roughness")."""
    text = _smooth(icosphere_text(subdivisions=2, k=300.0, nmol=1e-3, dashpot=0.05, floor=0.0, translate=(0, 0.12, 0)))
    scene = jaxplush.parse_scene(text, "<smooth>")
    sim = jaxplush.make_simulator(scene, 2e-4)
    p0 = sim.params()
    target = jnp.asarray(jaxplush.rollout(sim, p0, sim.init_fn(p0), 1, 1500)[1][0]) + 0.003

    @jax.jit
    def loss(logk):
        p = p0._replace(k_structural=jnp.exp(logk))
        return jnp.mean((jaxplush.rollout(sim, p, sim.init_fn(p), 1, 1500)[1][0] - target) ** 2)

    x = np.log(np.asarray(p0.k_structural)) + 0.3               # away from the minimum
    assert float(jnp.min(jaxplush.rollout(sim, p0, sim.init_fn(p0), 1, 1500)[1][0][:, 1])) < 0.02
    g = np.asarray(jax.grad(loss)(jnp.asarray(x)))
    assert_gradient_matches_fd(lambda t: float(loss(jnp.asarray(t))), x, g, h=1e-4, rtol=1e-5)
