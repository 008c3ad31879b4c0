"""Code that gives the same answers on any backend: every matrix product on the simulation, energy,
loss and gradient paths asks for full float32 precision.

On NVIDIA GPUs, XLA's default precision for float32 matrix products is TF32 (10 mantissa bits); a
product left at the default gives millimetres of error in a point-cloud loss there and nothing
here. These tests read the traced programs (jaxprs), so they hold on this CPU and guard the GPU path.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.extend import core

import jaxplush
from jaxplush.fitting.objective import gradients, losses
from jaxplush.stepping import diagnostics
from conftest import icosphere_text

HIGHEST = jax.lax.Precision.HIGHEST


def _dot_precisions(jaxpr, out=None):
    """[(precision, where)] of every dot_general in ``jaxpr`` and the programs nested in it."""
    out = [] if out is None else out
    for e in jaxpr.eqns:
        if e.primitive.name == "dot_general":
            tb = e.source_info.traceback
            out.append((e.params.get("precision"), str(tb).splitlines()[-1] if tb else "?"))
        for v in e.params.values():
            for sub in (v if isinstance(v, (list, tuple)) else (v,)):
                if isinstance(sub, core.ClosedJaxpr):
                    _dot_precisions(sub.jaxpr, out)
                elif isinstance(sub, core.Jaxpr):
                    _dot_precisions(sub, out)
    return out


def _full_precision(precision):
    if precision is None:
        return False
    ps = precision if isinstance(precision, tuple) else (precision,)
    return all(p == HIGHEST for p in ps)


def _assert_full(fn, *args):
    found = _dot_precisions(jax.make_jaxpr(fn)(*args).jaxpr)
    loose = [(p, where) for p, where in found if not _full_precision(p)]
    assert not loose, f"matrix products at the backend's default precision: {loose}"
    return len(found)


def _scene():
    """Two gas balls with every per-vertex and edge term, contact, and a floor."""
    kw = dict(subdivisions=1, k=150.0, mass=0.05, nmol=1e-3, dashpot=0.01, drag=0.1, damping=500.0)
    text = icosphere_text(floor=-0.2, translate=(0, 0, 0), **kw)
    text += icosphere_text(header=False, name="top", translate=(0, 0.205, 0), offset=42, **kw)
    return jaxplush.parse_scene(text, "<two balls>")


def test_the_point_cloud_loss_and_energies_ask_for_full_precision():
    x = jnp.asarray(np.random.default_rng(0).normal(size=(30, 3)), jnp.float32)
    assert _assert_full(losses.chamfer, x, x[::-1]) >= 1
    assert _assert_full(losses.pairwise_sq_distances, x, x[:7]) >= 1
    sim = jaxplush.make_simulator(_scene(), 1e-4)
    p = sim.params()
    s = sim.init_fn(p)
    assert _assert_full(lambda q, st: diagnostics.energy_terms(sim, q, st)["total"], p, s) >= 1


@pytest.mark.parametrize("integrator", ["verlet", "rk4", "implicit_euler"])
def test_steps_rollouts_and_gradients_ask_for_full_precision(integrator):
    sim = jaxplush.make_simulator(_scene(), 1e-4, integrator=integrator)
    p = sim.params()
    s = sim.init_fn(p)
    _assert_full(sim.step_fn, p, s)
    _assert_full(lambda q: jaxplush.rollout(sim, q, sim.init_fn(q), 2, 5)[1], p)
    target = jnp.zeros((2, sim.topology.x0.shape[0], 3), sim.dtype)

    def loss(q):
        return gradients.rollout_loss(sim, q, sim.init_fn(q), (5, 10), lambda x, t: jnp.sum((x - t) ** 2), target)
    _assert_full(jax.value_and_grad(loss), p)


def test_the_check_sees_a_product_left_at_the_default():
    """The guard itself: a plain ``@`` is reported, the same product at HIGHEST is not."""
    a = jnp.ones((4, 3))
    with pytest.raises(AssertionError, match="default precision"):
        _assert_full(lambda m: m @ m.T, a)
    assert _assert_full(lambda m: jnp.matmul(m, m.T, precision=HIGHEST), a) == 1


def test_fused_reductions_of_broadcast_operands_compile_to_what_they_compute():
    """jaxlib 0.10.2's XLA:CPU YNNPACK fusions got this 80% wrong under jit (jaxplush._xla turns them
    off when it is imported); jit and eager must agree, and both match float64 numpy."""
    rng = np.random.default_rng(0)
    a = rng.normal(size=(512, 1, 3)).astype(np.float32)
    b = rng.normal(size=(1, 1280, 3)).astype(np.float32)

    def f(a, b):
        return jnp.sum(b * (a + b), -1) * jnp.sum(a * a, -1)
    ref = np.sum(b.astype(np.float64) * (a + b), -1) * np.sum(a.astype(np.float64) ** 2, -1)
    scale = np.abs(ref).max()
    for out in (f(a, b), jax.jit(f)(a, b)):
        assert np.max(np.abs(np.asarray(out, np.float64) - ref)) < 1e-5 * scale


def _python(code, env=None):
    import os
    import subprocess
    import sys
    e = dict(os.environ)
    e.pop("XLA_FLAGS", None)
    e.update(env or {})
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=e, timeout=120)


def test_importing_jaxplush_turns_the_fusions_off_unless_told_otherwise_or_too_late():
    from jaxplush import _xla
    code = "import os, jaxplush; print(os.environ.get('XLA_FLAGS'))"
    out = _python(code)
    assert out.returncode == 0, out.stderr
    assert _xla.FLAG in out.stdout
    mine = "--xla_cpu_experimental_ynn_fusion_type=reduce"           # the user's own setting wins
    out = _python(code, {"XLA_FLAGS": mine})
    assert out.stdout.strip() == mine, out.stderr
    late = _python("import jax.numpy as jnp; jnp.ones(2).sum(); import warnings; warnings.simplefilter('always'); "
                   "import jaxplush")
    assert late.returncode == 0 and "stay on" in late.stderr, late.stderr
