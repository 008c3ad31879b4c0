"""The term definitions of jaxplush.model.terms: the registry covers every switch, the gates of
the batched engine and the fused adjoint come from it, and each transpose written beside its
forward is that forward's derivative (float64, against jax's autodiff)."""

from __future__ import annotations

import dataclasses
import importlib

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxplush
from jaxplush.stepping import batched
from jaxplush.fitting.objective import gradients as G
from jaxplush.model import contact
from jaxplush.model import forces as model
from jaxplush.model import terms as T
from conftest import icosphere_text
from test_term_vjp import TOGGLES


def _names():
    return [f.name for f in dataclasses.fields(model.Terms)] + ["contact_friction"]


def test_every_switch_has_one_registry_entry():
    names = [s.name for s in T.REGISTRY]
    assert sorted(names) == sorted(_names())
    assert len(set(names)) == len(names)


@pytest.mark.parametrize("spec", T.REGISTRY, ids=lambda s: s.name)
def test_registry_points_at_code_that_exists(spec):
    parts = spec.forward.split(".")
    for cut in range(len(parts) - 1, 0, -1):
        try:
            obj = importlib.import_module(".".join(parts[:cut]))
        except ImportError:
            continue
        for attr in parts[cut:]:
            obj = getattr(obj, attr)
        assert callable(obj)
        return
    pytest.fail(f"{spec.forward} does not import")


def test_engines_take_their_gates_from_the_registry():
    assert G._ADJOINT_TERMS == T.supported("adjoint")
    assert batched.SUPPORTED_TERMS == T.supported("batched")
    # the one-step VJP check toggles exactly the terms the adjoint claims (spring is always on)
    # (driven vertices: a mask whose one-step VJP tests/test_driven.py checks against jax.vjp;
    # k_field, the spring's stiffness per edge: tests/test_kfield.py checks its gradient)
    assert T.supported("adjoint") == {"spring", "driven", "k_field", *TOGGLES}


def test_an_unsupported_term_is_refused_by_name():
    terms = model.Terms(gravity=True, floor=True, floor_friction=0.5)
    assert T.unsupported(terms, "adjoint") == ["floor_friction"]
    assert T.unsupported(terms, "batched") == []
    scene = jaxplush.parse_scene("floor_friction 0.5\n" + icosphere_text(0, floor=-0.2), "<friction>")
    sim = jaxplush.make_simulator(scene, 1e-4)
    assert not G.adjoint_supported(sim)
    with pytest.raises(ValueError, match="floor_friction"):
        G.rollout_loss(sim, sim.params(), sim.init_fn(sim.params()), (1,), lambda x, a: jnp.sum(x), jnp.zeros((1,)),
                       method="adjoint")
    # soft-soft contact (and its friction) is batched: the single-scene code under jax.vmap
    batched.check_terms(model.Terms(contact=contact.ContactConfig(((0, 1),), (), (0.01,), (), None, (8, 8), 0.5)))


def test_every_engine_sums_the_edge_terms_in_edge_weight(monkeypatch):
    """The edge terms are assembled once: the single-scene ring and segment kernels and the
    batched kernel all call terms.edge_weight, with every switched-on edge term's coefficient
    spread to their layout (a term added to EDGE_TERMS reaches every engine)."""
    calls = []
    real = T.edge_weight

    def spy(terms, coefficient, rest, d, inv_l, dv=None):
        calls.append({f: jnp.shape(coefficient(f)) for f in T.edge_fields(terms)})
        return real(terms, coefficient, rest, d, inv_l, dv)

    monkeypatch.setattr(T, "edge_weight", spy)
    scene = jaxplush.parse_scene(icosphere_text(0, dashpot=0.01, nmol=0.001), "<dashpot>")
    assert T.edge_fields(model.Terms.for_scene(scene)) == ("k_structural", "dashpot")
    for assembly in ("ring", "segment"):
        sim = jaxplush.make_simulator(scene, 1e-4, assembly=assembly)
        state = sim.init_fn(sim.params())
        calls.clear()
        jax.eval_shape(sim.force_fn, sim.params(), state.x, state.x)
        assert calls and all(set(c) == {"k_structural", "dashpot"} for c in calls), assembly
    bsim = batched.make_batched_simulator(scene, 1e-4, 2)
    p = bsim.params()
    state = bsim.init_fn(p)
    calls.clear()
    jax.eval_shape(bsim.force_fn, p, state.x, state.v)
    assert len(calls) == bsim.topology.ring.shape[1]         # one per ring slot
    assert all(set(c) == {"k_structural", "dashpot"} for c in calls)


# --------------------------------------------------------------------------- transposes

def _rand(key, shape, lo=-1.0, hi=1.0):
    return jax.random.uniform(key, shape, jnp.float64, lo, hi)


def _close(a, b, rtol=1e-12):
    a, b = np.asarray(a), np.asarray(b)
    assert np.linalg.norm(a - b) <= rtol * max(np.linalg.norm(b), 1e-300), (a, b)


def _edge_force(weight):
    """f(d, ...) = w(d, ...) d for one edge, as a (3,) vector."""
    def f(d, *args):
        return weight(d, *args) * d
    return f


def test_spring_vjp_is_the_transpose_of_the_spring_force(x64):
    keys = jax.random.split(jax.random.PRNGKey(0), 4)
    d, delta = _rand(keys[0], (3,)), _rand(keys[1], (3,))
    k, rest, eps2 = 300.0, 0.7, 1e-12

    def force(d):
        return T.spring_weight(k, rest, T.inv_length(d, eps2)) * d
    jt = jax.vjp(force, d)[1](delta)[0]                     # J^T delta
    w, coef, dens = T.spring_vjp(k, rest, T.inv_length(d, eps2), T.dot(d, delta))
    _close(w * delta + coef * T.dot(d, delta) * d, jt)
    # k density: an edge (i, j) pushes i by w d and j by -w d, so lam.f = -w t with
    # delta = lam_j - lam_i; its two ring entries (i, j) and (j, i) each carry -1/2 s t = d/dk / 2
    dk = jax.grad(lambda kk: jnp.dot(delta, T.spring_weight(kk, rest, T.inv_length(d, eps2)) * d))(k)
    _close(-2.0 * dens, dk)


def test_dashpot_vjp_is_the_transpose_of_the_dashpot_force(x64):
    keys = jax.random.split(jax.random.PRNGKey(1), 4)
    d, dv, delta = _rand(keys[0], (3,)), _rand(keys[1], (3,)), _rand(keys[2], (3,))
    c = 0.03

    def force(d, dv):
        return T.dashpot_weight(c, dv, d, T.inv_length(d, 0.0)) * d
    jx, ju = jax.vjp(force, d, dv)[1](delta)
    t = T.dot(d, delta)
    w, coef, ct, dens = T.dashpot_vjp(c, dv, d, T.inv_length(d, 0.0), t)
    _close(w * delta + coef * t * d + ct * dv, jx)
    _close(ct * d, ju)
    dc = jax.grad(lambda cc: jnp.dot(delta, T.dashpot_weight(cc, dv, d, T.inv_length(d, 0.0)) * d))(c)
    _close(-2.0 * dens, dc)


def test_spring_jacobian_is_the_spring_force_jacobian_when_stretched(x64):
    d = jnp.array([0.3, -0.5, 0.9])
    k, rest = 250.0, 0.6                                      # |d| > rest: stretched, nothing clamped
    jac = jax.jacfwd(lambda d: T.spring_weight(k, rest, T.inv_length(d, 0.0)) * d)(d)
    a, b = T.spring_jacobian(k, rest, T.inv_length(d, 0.0))
    dh = d / jnp.linalg.norm(d)
    _close(a * jnp.eye(3) + b * jnp.outer(dh, dh), jac)
    a, b = T.spring_jacobian(k, 2.0, T.inv_length(d, 0.0))   # compressed: transverse part clamped
    assert a == 0.0 and b == k


def test_fan_tangent_is_the_derivative_of_the_fan(x64):
    keys = jax.random.split(jax.random.PRNGKey(2), 4)
    d, dn, e, en = (_rand(k, (3,)) for k in keys)
    _, tangent = jax.jvp(lambda a, b: jnp.stack(T.fan(a, b)), (d, dn), (e, en))
    _close(jnp.stack(T.fan_tangent(d, dn, e, en)), tangent)


def test_pressure_slopes_are_the_derivatives_of_the_pressure(x64):
    scene = jaxplush.parse_scene(icosphere_text(0, nmol=0.001), "<ball>")
    sim = jaxplush.make_simulator(scene, 1e-4)
    topo, p = sim.topology, sim.params()
    v0 = float(topo.rest_volume[0])
    for volume in (0.9 * v0, 0.01 * v0):                      # above and below the clamp
        vol = jnp.asarray([volume])

        def pres(v, n):
            return T.pressure(topo, p._replace(nmol=n), v, scene.temperature)[0]
        got_p, dp, dpn = T.pressure_slopes(topo, p, vol, scene.temperature)
        _close(got_p, pres(vol, p.nmol))
        _close(dp, jax.grad(pres, 0)(vol, p.nmol))
        _close(dpn, jax.grad(pres, 1)(vol, p.nmol))


def test_drag_vjp_is_the_transpose_of_the_drag(x64):
    keys = jax.random.split(jax.random.PRNGKey(3), 3)
    v, a_bar = _rand(keys[0], (3, 5)), _rand(keys[1], (3, 5))
    gamma = _rand(keys[2], (5,), 0.1, 2.0)
    u_bar, dens = T.drag_vjp(gamma, v, a_bar)
    # the drag's acceleration is -gamma v (its force drag_force over the mass)
    _, vjp = jax.vjp(lambda g, vv: T.drag_force(g, 1.0, vv), gamma, v)
    g_bar, v_bar = vjp(a_bar)
    _close(u_bar, v_bar)
    _close(dens, g_bar)


def test_terms_are_layout_free(x64):
    """The same term on a (K, V) ring table and on (V, B) batch slots gives the same numbers."""
    keys = jax.random.split(jax.random.PRNGKey(4), 3)
    d = _rand(keys[0], (3, 4, 6))                             # (3, K, V)
    k = _rand(keys[1], (6,), 100.0, 500.0)
    rest = _rand(keys[2], (4, 6), 0.1, 1.0)
    ring = T.spring_weight(k, rest, T.inv_length(d, 1e-12))                       # (K, V)
    for slot in range(4):
        batch = T.spring_weight(k[:, None], rest[slot][:, None], T.inv_length(d[:, slot, :, None], 1e-12))
        _close(batch[:, 0], ring[slot], 1e-14)
