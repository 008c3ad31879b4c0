"""Topology as data: scenes of one size bucket lower to one program (issue 52 item 2).

The compiled programs take a scene's topology and the values derived from its geometry as
arguments (jaxplush._xla.hoist_constants, jaxplush.model.layout.scene_value), so two scenes that
differ in shape, size, placement and parameters, but not in their bucket's sizes
(jaxplush.stepping.compiled.bucket), lower to the same program text: the second scene's fit loads
every program from the persistent cache. A scene of another bucket lowers to another program, so
the comparison can fail.
"""

from __future__ import annotations

import jax
import numpy as np
import pytest

import jaxplush
from jaxplush.fitting.targets import scenarios
from jaxplush.stepping import batched, compiled

try:                                   # jax versions that can hoist constants into arguments
    from jax._src.interpreters import mlir as _mlir
    _CAN_HOIST = hasattr(_mlir.LoweringParameters(), "hoist_constants_as_args")
except Exception:                      # pragma: no cover - jax internals moved
    _CAN_HOIST = False
pytestmark = pytest.mark.skipif(not _CAN_HOIST, reason="this jax cannot hoist constants into program arguments")


def _text(shapes, scale, k, weight, shift, floor=True):
    out = ["gravity 0.0 -9.81 0.0"] + (["floor 0.0"] if floor else [])
    base = 0
    for i, shape in enumerate(shapes):
        v, f = scenarios.shape_mesh(shape, 1)
        v = np.asarray(v, np.float64) * scale
        out += [f"o {shape}{i}", f"k_structural {k * (1 + 0.3 * i)!r}", f"total_weight {weight!r}",
                "nmol 0.0004", "damping 400.0",
                f"translate {shift + 0.05 * i!r} {0.15 + 0.25 * i!r} {0.01 * i!r}"]
        out += [f"v {float(a)!r} {float(b)!r} {float(c)!r}" for a, b, c in v]
        out += [f"f {a + 1 + base} {b + 1 + base} {c + 1 + base}" for a, b, c in np.asarray(f)]
        out.append("END_OBJECT")
        base += len(v)
    return "\n".join(out) + "\n"


def _scene(shapes, *args):
    return jaxplush.parse_scene(_text(shapes, *args), f"<{'+'.join(shapes)}>")


@pytest.fixture(scope="module")
def scenes():
    a = _scene(("ball", "bean"), 1.0, 300.0, 0.1, 0.0)
    b = _scene(("cushion", "capsule"), 1.3, 520.0, 0.17, 0.04)      # another shape, size, place, k, mass
    c = _scene(("ball", "torus"), 1.0, 300.0, 0.1, 0.0)              # a torus of 40 vertices: another bucket
    return a, b, c


def _single_text(scene):
    sim = jaxplush.make_simulator(scene, 2e-4)
    p, s = sim.params(), sim.init_fn(sim.params())
    return jax.jit(lambda p, s: jaxplush.rollout(sim, p, s, 2, 3)[1]).lower(p, s).as_text()


def _batched_text(scene):
    bsim = batched.make_batched_simulator(scene, 2e-4, 2, chunk=2)
    p = bsim.params()
    s = bsim.init_fn(p)
    step0 = np.zeros(2, np.int32)
    health = batched.initial_health(bsim, s, step0)
    return batched._core_jit.lower(bsim, p, s, health, step0, None, n_frames=2, save_every=3,
                                   observe=None, separation=False).as_text()


def test_hoisting_is_on_in_the_tests():
    # conftest imports jaxplush before jax, as a user's script should
    assert jaxplush._xla._hoisting()


def test_scenes_of_one_bucket_lower_to_one_single_scene_program(scenes):
    a, b, c = scenes
    assert a.fingerprint != b.fingerprint
    assert compiled.bucket(a) == compiled.bucket(b)
    assert compiled.bucket(a) != compiled.bucket(c)
    ta, tb, tc = _single_text(a), _single_text(b), _single_text(c)
    assert "jax.const" in ta                  # the topology entered as arguments
    assert ta == tb
    assert ta != tc


def test_scenes_of_one_bucket_lower_to_one_batched_program(scenes):
    a, b, _ = scenes
    ta, tb = _batched_text(a), _batched_text(b)
    assert "jax.const" in ta
    assert ta == tb


def test_info_names_the_bucket(scenes, capsys, tmp_path):
    from jaxplush import cli
    path = tmp_path / "a.obj"
    path.write_text(_text(("ball", "bean"), 1.0, 300.0, 0.1, 0.0))
    assert cli.main(["info", str(path)]) == 0
    out = capsys.readouterr().out
    line = next(ln for ln in out.splitlines() if "program bucket" in ln)
    assert "2 x (42 vertices, 120 edges, 80 faces)" in line
    assert "ring width 6" in line and "contact capacity" in line
