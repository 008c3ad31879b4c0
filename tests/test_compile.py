"""Compile once, run many (jaxplush.stepping.compiled): a second call with new values neither traces nor
compiles; a simulator rebuilt for the same scene shares the program; the cache is bounded and
frees what it drops; the command line keeps compiled programs across processes."""

from __future__ import annotations

import gc
import os
import subprocess
import sys
import weakref

import jax
import numpy as np
import pytest

import jaxplush
from jaxplush.stepping import compiled
from conftest import compiles
from jaxplush.fitting.targets.scenarios import drop_scene_text

DT = 2e-4


def _scene(name="<drop>", **kw):
    return jaxplush.parse_scene(drop_scene_text("ball", 1, **kw), name)


def test_the_compile_counter_sees_a_compile():
    """The check below is only as good as its counter: a fresh function is seen."""
    with compiles() as seen:
        jax.jit(lambda x: x * 3.0 + 1.0)(np.arange(3.0))
    assert any("Compiling" in s for s in seen)


def test_a_second_simulate_call_with_new_values_does_not_compile():
    scene = _scene(damping=2000.0)
    first = jaxplush.simulate(scene, 60, DT, save_every=20)
    p = scene.params
    new = p._replace(k_structural=p.k_structural * 1.5, nmol=p.nmol * 0.8)
    x0 = scene.vertices + np.array([0.0, 0.01, 0.0])
    with compiles() as seen:
        again = jaxplush.simulate(scene, 60, DT, save_every=20, params=new, x0=x0)
        # the same scene read again is the same program
        jaxplush.simulate(_scene("<read again>", damping=2000.0), 60, DT, save_every=20)
    assert seen == []
    moved = np.linalg.norm(again.positions[-1] - first.positions[-1]) / np.linalg.norm(first.positions[-1])
    assert moved > 1e-3                        # the new values were used, not a cached result


def test_what_decides_the_program_does_recompile():
    """A different dt, integrator or geometry is a different program (and runs correctly)."""
    scene = _scene(damping=2000.0)
    jaxplush.simulate(scene, 20, DT, save_every=20)
    for other in (dict(dt=DT / 2), dict(integrator="rk4")):
        with compiles() as seen:
            jaxplush.simulate(scene, 20, other.get("dt", DT), save_every=20, integrator=other.get("integrator", "verlet"))
        assert seen, other
    bigger = scene.replace(vertices=scene.vertices * 1.1)
    assert bigger.fingerprint != scene.fingerprint
    assert jaxplush.make_simulator(bigger, DT) != jaxplush.make_simulator(scene, DT)
    assert jaxplush.make_simulator(_scene("<other name>", damping=2000.0), DT) == jaxplush.make_simulator(scene, DT)


def test_the_cache_is_bounded_and_frees_what_it_drops(monkeypatch):
    monkeypatch.setattr(compiled, "SIZE", 2)
    compiled.clear()
    scenes = [_scene(damping=2000.0).replace(vertices=_scene().vertices * (1 + 0.01 * i)) for i in range(3)]
    sims = [jaxplush.make_simulator(s, DT) for s in scenes]
    first = weakref.ref(sims[0])
    for sim in sims:
        compiled.get(sim, "init", lambda sim=sim: jax.jit(sim.init_fn))(sim.params())
    assert compiled.size() == 2
    del sims
    gc.collect()
    assert first() is None                    # dropped from the cache and freed with its executable
    compiled.clear()


def _cli(args, env):
    return subprocess.run([sys.executable, "-m", "jaxplush", *args], env=env, capture_output=True, text=True,
                          timeout=300)


def test_the_command_line_keeps_compiled_programs_across_processes(tmp_path):
    scene = tmp_path / "ball.obj"
    scene.write_text(drop_scene_text("ball", 1, damping=2000.0))
    cache = tmp_path / "xla"
    env = dict(os.environ, JAXPLUSH_CACHE_DIR=str(cache))
    args = ["simulate", str(scene), "--steps", "40", "--dt", str(DT), "--quiet"]
    first = _cli(args + ["--out", str(tmp_path / "a.h5")], env)
    assert first.returncode == 0, first.stderr
    written = {f: os.stat(cache / f).st_mtime_ns for f in os.listdir(cache)}
    assert written                                         # the first process wrote its programs
    second = _cli(args + ["--out", str(tmp_path / "b.h5")], env)
    assert second.returncode == 0, second.stderr
    # ... and the second found them all: it wrote no entry, new or again (a miss would write one)
    assert {f: os.stat(cache / f).st_mtime_ns for f in os.listdir(cache)} == written
    off = tmp_path / "off"
    env_off = dict(os.environ, JAXPLUSH_CACHE_DIR="off", XDG_CACHE_HOME=str(off))
    assert _cli(args + ["--out", str(tmp_path / "c.h5")], env_off).returncode == 0
    assert not off.exists()                                # off means off


@pytest.mark.parametrize("value", ["off", "0"])
def test_the_persistent_cache_can_be_turned_off(value, monkeypatch):
    monkeypatch.setenv("JAXPLUSH_CACHE_DIR", value)
    assert compiled.enable_persistent_cache() is None


def test_batched_simulators_are_shared_per_program_and_cleared_with_the_rest():
    """``batched.shared_simulator``: one batched simulator per program in a process (the scene's
    geometry, dt, width, terms, substeps, chunk), whatever the scene's values; another geometry
    or width is another; ``compiled.clear()`` drops them. Nothing is compiled here."""
    from conftest import icosphere_scene
    from jaxplush.stepping import batched
    a = icosphere_scene(k=111.0)
    same_geometry = icosphere_scene(k=222.0, mass=0.2)
    moved = icosphere_scene(k=111.0, translate=(0.0, 0.01, 0.0))
    terms = batched.terms_for(a)
    first = batched.shared_simulator(a, 5e-4, 8, terms, 1, 4)
    assert batched.shared_simulator(same_geometry, 5e-4, 8, terms, 1, 4) is first
    assert batched.shared_simulator(moved, 5e-4, 8, terms, 1, 4) is not first
    assert batched.shared_simulator(a, 5e-4, 16, terms, 1, 4) is not first
    assert batched.shared_simulator(a, 5e-4, 8, terms, 2, 4) is not first
    compiled.clear()
    assert batched.shared_simulator(a, 5e-4, 8, terms, 1, 4) is not first
