"""The compiled step: only the needed terms, no recompilation, vmap, blow-up reports."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxplush

from jaxplush.types import Params
from conftest import compiles, icosphere_scene


def _hlo(scene):
    sim = jaxplush.make_simulator(scene, 1e-4)
    p = sim.params()
    # the public step is jitted itself: inside this jit its scopes read "floor/...", not "/floor/...";
    # every scope is written "/name/" here
    text = jax.jit(sim.step_fn).lower(p, sim.init_fn(p)).as_text(debug_info=True)
    return text.replace('loc("', 'loc("/'), sim


@pytest.mark.parametrize("term, kw", [
    ("floor", dict(floor=-1.0)),
    ("gas", dict(nmol=1e-3)),
    ("fixed", dict(fixed=(0,))),
    ("dashpot", dict(dashpot=0.01)),
    ("drag", dict(drag=1.0)),
    ("verlet_damping", dict(damping=100.0)),
])
def test_terms_are_compiled_only_when_the_scene_needs_them(term, kw):
    without, sim0 = _hlo(icosphere_scene(subdivisions=0))
    with_, sim1 = _hlo(icosphere_scene(subdivisions=0, **kw))
    assert term not in sim0.terms.names() and term in sim1.terms.names()
    assert f"/{term}/" not in without
    assert f"/{term}/" in with_
    assert "/spring/" in without


def test_gravity_free_scene_has_no_gravity_term():
    text, sim = _hlo(icosphere_scene(subdivisions=0, gravity=(0, 0, 0)))
    assert "gravity" not in sim.terms.names() and "/gravity/" not in text


@pytest.mark.parametrize("name, value", [("damping", 5.0), ("drag", 50.0), ("dashpot", 0.05)])
def test_simulate_params_switch_on_terms_the_scene_lacks(name, value):
    """simulate(..., params=p) with a damping, drag or dashpot the scene has at 0 compiles that term
    in (it used to be left out, silently simulating the undamped body); damping and drag slow the fall."""
    scene = icosphere_scene(subdivisions=1, k=200.0, mass=0.05, nmol=1e-3)
    p = scene.params._replace(**{name: np.full(1, value)})
    free = jaxplush.simulate(scene, 200, 2e-4, save_every=200)
    damped = jaxplush.simulate(scene, 200, 2e-4, save_every=200, params=p)
    assert damped.params[Params._fields.index(name)][0] == value
    assert np.abs(damped.positions[-1] - free.positions[-1]).max() > 1e-6
    if name != "dashpot":               # the dashpot resists stretching only, not the fall itself
        fall = lambda t: t.positions[0, :, 1].mean() - t.positions[-1, :, 1].mean()       # noqa: E731
        assert fall(damped) < 0.9 * fall(free)


def test_second_call_with_new_parameters_does_not_recompile():
    scene = icosphere_scene(subdivisions=1, nmol=1e-3, dashpot=0.01)
    sim = jaxplush.make_simulator(scene, 1e-4)
    p = sim.params()
    s = sim.init_fn(p)
    jaxplush.rollout(sim, p, s, 5, 4)
    p2 = p._replace(k_structural=p.k_structural * 2, nmol=p.nmol * 0.5, dashpot=p.dashpot + 1)
    s2 = sim.init_fn(p2)
    with compiles() as seen:
        _, frames, _ = jaxplush.rollout(sim, p2, s2, 5, 4)
        # a simulator rebuilt for the same scene and dt is the same program
        jaxplush.make_simulator(scene, 1e-4).rollout(p2, s2, 5, 4)
    assert seen == []
    assert frames.shape == (5, scene.n_vertices, 3)


def test_vmap_over_params_equals_python_loop():
    scene = icosphere_scene(subdivisions=1, nmol=1e-3, dashpot=0.01, floor=-0.2)
    sim = jaxplush.make_simulator(scene, 1e-4)
    p = sim.params()
    ks = jnp.array([50.0, 100.0, 300.0])
    batch = jax.tree_util.tree_map(lambda a: jnp.broadcast_to(a, (3,) + a.shape), p)._replace(k_structural=ks[:, None])

    def run(params):
        return jaxplush.rollout(sim, params, sim.init_fn(params), 4, 25)[1]

    batched = jax.vmap(run)(batch)
    for i, k in enumerate(ks):
        single = run(p._replace(k_structural=jnp.array([k])))
        np.testing.assert_allclose(batched[i], single, rtol=1e-5, atol=1e-7)


def test_blow_up_is_reported_with_step_object_and_cause():
    scene = icosphere_scene(subdivisions=2, k=500.0, mass=0.05, nmol=1e-3)
    sim = jaxplush.make_simulator(scene, 1e-4)
    dt = 3 * jaxplush.estimate_stable_dt(sim, sim.params()).dt_max
    with pytest.warns(UserWarning, match="exceeds the estimated explicit stability limit"):
        with pytest.raises(jaxplush.SimulationError) as e:
            jaxplush.simulate(scene, steps=3000, dt=dt, save_every=100)
    err = e.value
    assert err.object == 0 and err.object_name == "ball"
    assert 0 < err.step <= 3000
    assert "non-finite" in err.reason or "inside out" in err.reason
    # The reported step is where it happened: a separate rollout saved at every step (another
    # compiled program, so it may round differently and part from simulate's run by a step or
    # two on an instability that grows tenfold per step) is healthy a few steps before it and
    # fails within two steps of it (non-finite or inside out; frames[i] is after i + 1 steps).
    sim = jaxplush.make_simulator(scene, dt)
    p = sim.params()
    _, frames, _ = jaxplush.rollout(sim, p, sim.init_fn(p), err.step + 2, 1)
    frames = np.asarray(frames, np.float64)
    vol = lambda x: scene.volumes(x)[0]
    bad = lambda x: not np.isfinite(x).all() or vol(x) <= 0
    assert not any(bad(x) for x in frames[:max(err.step - 3, 0)])
    assert any(bad(x) for x in frames[max(err.step - 3, 0):err.step + 2])


def test_pinned_vertex_stays_put_and_plush_hangs():
    scene = icosphere_scene(subdivisions=1, k=200.0, mass=0.05, nmol=1e-3, dashpot=0.02, drag=2.0, fixed=(0,))
    traj = jaxplush.simulate(scene, steps=4000, dt=2e-4, save_every=400)
    np.testing.assert_array_equal(traj.positions[:, 0], np.broadcast_to(scene.vertices[0].astype(traj.positions.dtype), (len(traj.times), 3)))
    # It hangs below the pin: the centre of mass ends below the pinned vertex.
    assert traj.positions[-1].mean(0)[1] < scene.vertices[0, 1] - 0.05
