"""The fused adjoint's hand-written one-step VJP against jax.vjp of ``sim.internal.step``, float64,
over every combination of the force terms it supports (issue 16 item 1).

Spring is always compiled in; each of the other eight terms of ``G._ADJOINT_TERMS`` is switched on
or off by the scene text, giving 2**8 = 256 combinations. Each is checked on two 12-vertex
icosahedra (cheap to compile) at a perturbed, moving state with random cotangents. The default run
checks a pairwise covering subset (all-off, all-on, and every on/off pair of every two toggles
occurs in some combination: :func:`covering_array`); the full enumeration of all 256 is in the CI
tier (``-m heavy``; the combinations with contact in tests/test_term_vjp_contact.py). Each case first asserts that the simulator compiled exactly the intended
terms (``sim.terms.names()``), then that each switched-on term acts (its parameter's cotangent is
non-zero, the floor projects, the pin holds, the contact force is non-zero).
"""

from __future__ import annotations

import itertools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxplush
from jaxplush.fitting.objective import gradients as G
from jaxplush.model import contact
from conftest import icosphere_text

DT = 2e-4
#: the toggles, in bit order (spring is always on)
TOGGLES = ("dashpot", "drag", "gas", "gravity", "floor", "fixed", "verlet_damping", "contact")
#: the Params field whose cotangent a toggle makes non-zero (None: the term has no parameter)
PARAM_OF = {"dashpot": "dashpot", "drag": "drag", "gas": "nmol", "verlet_damping": "damping"}
N_VERTS = 12                      # a subdivision-0 icosphere (icosahedron)
FLOOR = -0.086                    # just below the icosahedron's lowest vertex (y = -0.08507)
RTOL = 1e-10
#: both VJPs are compiled in one program, with LLVM's optimisations off: the comparison is of the
#: two derivations, and compiling is most of this test's cost (contact: ~7 s -> ~4.5 s per program)
COMPILER_OPTIONS = {"xla_backend_optimization_level": 0}


def _combo(bits):
    """The set of toggles a bit mask switches on."""
    return frozenset(t for i, t in enumerate(TOGGLES) if bits >> i & 1)


def _name(on):
    return "+".join(t for t in TOGGLES if t in on) or "spring_only"


ALL = [_combo(b) for b in range(2 ** len(TOGGLES))]


def _pairs(bits, n):
    """The (i, j, value_i, value_j) pairs of toggle values a combination (bit mask) contains."""
    return {(i, j, bits >> i & 1, bits >> j & 1) for i, j in itertools.combinations(range(n), 2)}


def covering_array(n=len(TOGGLES), slow=TOGGLES.index("contact")):
    """A deterministic pairwise covering array of n on/off toggles, as bit masks: every value pair
    of every two toggles occurs in some row. Rows: all off, all on, only toggle ``slow`` on (contact,
    whose compile costs several times the others'; these two rows already give every other toggle
    both values next to it on), then greedily the row with ``slow`` off covering the most pairs
    not yet covered (the lowest bit mask on ties), until none is left."""
    rows = [0, 2 ** n - 1, 1 << slow]
    todo = {(i, j, a, b) for i, j in itertools.combinations(range(n), 2) for a in (0, 1) for b in (0, 1)}
    for r in rows:
        todo -= _pairs(r, n)
    candidates = [c for c in range(2 ** n) if not c >> slow & 1]
    while todo:
        best = max(candidates, key=lambda c: (len(_pairs(c, n) & todo), -c))
        rows.append(best)
        todo -= _pairs(best, n)
    return rows


DEFAULT = [_combo(b) for b in covering_array()]


def test_covering_array_covers_every_pair():
    rows = covering_array()
    assert len(set(rows)) == len(rows) <= 10
    assert 0 in rows and 2 ** len(TOGGLES) - 1 in rows
    assert set(DEFAULT) == {_combo(r) for r in rows} and set(DEFAULT) <= set(ALL)
    for i, j in itertools.combinations(range(len(TOGGLES)), 2):
        seen = {(r >> i & 1, r >> j & 1) for r in rows}
        assert seen == {(0, 0), (0, 1), (1, 0), (1, 1)}, (TOGGLES[i], TOGGLES[j], seen)
    assert len(ALL) == 256 and len(set(ALL)) == 256


def _scene(on):
    """Two icosahedra, b overlapping a's +x side, the terms in ``on`` switched on by keywords."""
    kw = dict(subdivisions=0, dashpot=0.02 if "dashpot" in on else None, drag=0.5 if "drag" in on else None,
              damping=300.0 if "verlet_damping" in on else None)
    head = "" if "contact" in on else "contact off\n"
    a = icosphere_text(k=150.0, mass=0.04, nmol=5e-4 if "gas" in on else None, name="a",
                       gravity=(0.0, -9.81, 0.0) if "gravity" in on else (0.0, 0.0, 0.0),
                       floor=FLOOR if "floor" in on else None, fixed=(0,) if "fixed" in on else (), **kw)
    b = icosphere_text(k=300.0, mass=0.08, nmol=8e-4 if "gas" in on else None, name="b",
                       translate=(0.19, 0.004, 0.003), offset=N_VERTS, header=False, **kw)
    return jaxplush.parse_scene(head + a + b, "<" + _name(on) + ">")


def _check(on):
    sim = jaxplush.make_simulator(_scene(on), DT)
    assert set(sim.terms.names()) == {"spring"} | on          # exactly the intended combination
    assert G.adjoint_supported(sim)
    p = sim.params()
    rng = np.random.default_rng(sum(1 << i for i, t in enumerate(TOGGLES) if t in on))
    n = sim.topology.n_vertices
    x = jnp.asarray(sim.topology.x0.T) + 2e-3 * rng.standard_normal((3, n))
    low = np.flatnonzero(sim.topology.x0[:, 1] < -0.08)       # each object's two lowest vertices
    x = x.at[1].add(-4e-3).at[1, low].set(FLOOR - 1e-3)       # these (and maybe more) below the floor
    u = jnp.asarray(0.3 * rng.standard_normal(x.shape)).at[1].add(-1.0).at[0, :N_VERTS].add(0.2)
    u = u.at[1, low].set(-1.0)                                # and moving down: projected
    x_bar, u_bar = (jnp.asarray(rng.standard_normal(x.shape)) for _ in range(2))
    contact_force = contact.make_contact_force(sim.topology, sim.terms.contact) if sim.terms.contact else None

    def both(p, x, u):
        out, vjp = jax.vjp(sim.internal.step, p, jaxplush.State(x, u))
        f_c = jnp.max(jnp.abs(contact_force(p, x))) if contact_force else jnp.zeros(())
        return out, vjp(jaxplush.State(x_bar, u_bar)), G._make_step_vjp(sim)(p, x, u, out.x, x_bar, u_bar), f_c

    both = jax.jit(both).lower(p, x, u).compile(compiler_options=COMPILER_OPTIONS)
    out, (p_ref, s_ref), (xb, ub, pb), f_contact = both(p, x, u)
    pairs = [("x_bar", xb, s_ref.x), ("u_bar", ub, s_ref.v)] + [
        (f"params_bar.{f}", a, b) for f, a, b in zip(p._fields, pb, p_ref)]
    errors = {}
    for what, got, ref in pairs:
        got, ref = np.asarray(got), np.asarray(ref)
        assert got.shape == ref.shape and np.all(np.isfinite(got)), what
        scale = float(np.max(np.abs(ref)))
        errors[what] = float(np.max(np.abs(got - ref))) / scale if scale else float(np.max(np.abs(got)))
    bad = {k: v for k, v in errors.items() if not v <= RTOL}
    assert not bad, f"{_name(on)}: hand VJP vs jax.vjp, max |error| / max |ref|: {bad}"

    # every switched term really acts, and its cotangents are non-trivial
    for term, field in PARAM_OF.items():
        ref = np.asarray(getattr(p_ref, field))
        if term in on:
            assert np.all(ref != 0), (term, ref)
        else:
            assert np.all(ref == 0) and np.all(np.asarray(getattr(pb, field)) == 0), (term, ref)
    if "floor" in on:
        assert bool(jnp.any(out.x[1] == FLOOR)) and bool(jnp.any(x[1] < FLOOR))   # projection exercised
    else:
        assert bool(jnp.any(out.x[1] < FLOOR))
    if "fixed" in on:
        np.testing.assert_array_equal(out.x[:, 0], sim.topology.x0[0])
    if "contact" in on:
        assert float(f_contact) > 0                             # the objects do touch
    for what, _, ref in pairs[:2]:
        assert np.any(np.asarray(ref) != 0), what


@pytest.mark.parametrize("on", DEFAULT, ids=_name)
def test_step_vjp_term_combination(x64, on):
    """Pairwise covering subset of the term combinations (default run)."""
    _check(on)


@pytest.mark.heavy
@pytest.mark.parametrize("on", [c for c in ALL if "contact" not in c], ids=_name)
def test_step_vjp_every_term_combination_without_contact(x64, on):
    """The 128 combinations without soft-soft contact (CI tier; the 128 with contact, which cost
    several times more to compile, are in tests/test_term_vjp_contact.py, so that CI's two
    workers, one file each, share the enumeration)."""
    _check(on)
