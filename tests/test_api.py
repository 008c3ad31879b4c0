"""The public API: one entry module whose names do not shadow its modules, a simulator that
exposes init, step, params and rollout, no silently ignored parameters, and a user-written loss
that composes with jax.jit, jax.grad and jax.vmap."""

from __future__ import annotations

import importlib

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxplush
from conftest import icosphere_scene


def test_entry_module_names_do_not_shadow_modules():
    assert callable(jaxplush.simulate) and callable(jaxplush.contact_capacity_needed)
    sim_module = importlib.import_module("jaxplush.stepping.simulation")
    assert sim_module.simulate is jaxplush.simulate
    assert sim_module.contact_capacity_needed is jaxplush.contact_capacity_needed
    for name in jaxplush.__all__:
        assert hasattr(jaxplush, name), name


def test_simulator_public_surface_runs_a_rollout():
    scene = icosphere_scene(nmol=1e-3)
    sim = jaxplush.make_simulator(scene, 1e-4)
    p = sim.params()
    s = sim.init_fn(p)
    final, frames, health = sim.rollout(p, s, 3, 5)
    by_hand = s
    for _ in range(15):
        by_hand = sim.step_fn(p, by_hand)
    assert frames.shape == (3, scene.n_vertices, 3) and not health.failed
    err = float(jnp.linalg.norm(by_hand.x - final.x) / jnp.linalg.norm(final.x))
    assert err < 1e-5
    assert {"step", "to_internal", "to_public", "coherent"} <= set(sim.internal._fields)
    assert not hasattr(sim, "internal_step") and not hasattr(sim, "to_internal")


@pytest.mark.parametrize("field, value, term", [("drag", 5.0, "drag"), ("dashpot", 0.05, "dashpot"),
                                               ("damping", 500.0, "verlet_damping"), ("nmol", 1e-3, "gas")])
def test_a_value_for_a_term_that_is_not_compiled_in_is_an_error(field, value, term):
    scene = icosphere_scene()                              # no drag, dashpot, damping or gas
    sim = jaxplush.make_simulator(scene, 1e-4)
    p = sim.params()
    given = p._replace(**{field: jnp.full_like(getattr(p, field), value)})
    with pytest.raises(ValueError, match=f"{field} = .* would be ignored: this simulator has no {term} term"):
        sim.rollout(given, sim.init_fn(p), 2, 2)
    with pytest.raises(ValueError, match="would be ignored"):
        sim.params(given)
    if term != "gas":
        # simulate compiles the term in for the values it is given, so the value acts
        v0 = 10.0 * (scene.vertices - scene.vertices.mean(axis=0))          # swelling: every term damps it
        free = jaxplush.simulate(scene, 40, 1e-4, save_every=40, v0=v0)
        damped = jaxplush.simulate(scene, 40, 1e-4, save_every=40, params=given, v0=v0)
        assert np.linalg.norm(damped.positions[-1] - free.positions[-1]) > 1e-6


def test_a_term_compiled_in_on_request_gets_a_gradient():
    from jaxplush.model.forces import Terms
    scene = icosphere_scene()
    p0 = scene.params._replace(drag=np.array([2.0]))
    sim = jaxplush.make_simulator(scene, 1e-4, terms=Terms.for_scene(scene, p0))
    v0 = jnp.tile(jnp.array([0.0, 1.0, 0.0]), (scene.n_vertices, 1))

    def height(drag):
        p = sim.params(p0)._replace(drag=drag)
        return jnp.mean(sim.rollout(p, sim.init_fn(p, None, v0), 1, 20)[1][-1, :, 1])

    assert float(jax.grad(height)(jnp.array([2.0]))[0]) < 0      # more drag, less rise


def test_fitting_installs_as_a_jaxplush_subpackage(tmp_path):
    """fitting/ installs as jaxplush.fitting: outside the checkout, no top-level `fitting` exists
    (another distribution on the package index has that name), and the CLI entry point resolves."""
    import subprocess
    import sys
    code = ("import importlib.util, jaxplush.fitting, jaxplush.fitting.cli; "
            "assert importlib.util.find_spec('fitting') is None; "
            "from importlib.metadata import entry_points; "
            "(ep,) = [e for e in entry_points(group='console_scripts') if e.name == 'jaxplush-fit']; "
            "assert ep.value == 'jaxplush.fitting.cli:main' and ep.load() is jaxplush.fitting.cli.main")
    proc = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
