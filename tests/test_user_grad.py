"""The gradient of a user's own loss on ``jaxplush.rollout`` (issue 29): reverse mode takes the fused
adjoint (jaxplush.stepping.adjoint) by default, and it equals JAX's plain autodiff through the scan
(``gradient="autodiff"``) for every term the adjoint covers, under jit, vmap, jvp, jacfwd and
jacrev; where the adjoint does not apply it falls back to checkpointed autodiff and says so once;
its memory stays within the budget at 10,000 steps; a run that is not differentiated compiles to
the plain rollout's program."""

from __future__ import annotations

import collections
import re
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxplush
from jaxplush.stepping import adjoint, rollouts
from conftest import assert_gradient_matches_fd, icosphere_text

DT = 2e-4
N_FRAMES, EVERY = 6, 5


def _full():
    """Springs, gas, gravity, Verlet damping, dashpot and drag, 0.5 mm above a projection floor."""
    return jaxplush.parse_scene(icosphere_text(subdivisions=1, k=200.0, mass=0.05, nmol=5e-4, dashpot=0.02, drag=0.5,
                                               damping=300.0, floor=-0.1005), "<full>")


def _pinned_two():
    """Two objects without contact: one hangs from two pinned vertices, the other is free, with gas."""
    a = icosphere_text(subdivisions=1, k=150.0, mass=0.04, dashpot=0.01, fixed=(0, 3), name="hung", damping=200.0)
    b = icosphere_text(subdivisions=1, k=300.0, mass=0.08, nmol=8e-4, drag=0.3, name="free",
                       translate=(0.3, 0.0, 0.0), offset=42, header=False)
    return jaxplush.parse_scene("contact off\n" + a + b, "<two>")


def _contact(extra=""):
    """Two gas balls pressed together (soft-soft contact, candidate lists carried by the rollout)."""
    a = icosphere_text(subdivisions=1, k=150.0, mass=0.04, nmol=5e-4, name="a")
    b = icosphere_text(subdivisions=1, k=300.0, mass=0.08, nmol=8e-4, dashpot=0.01, name="b",
                       translate=(0.205, 0.0, 0.0), offset=42, header=False)
    return jaxplush.parse_scene(extra + a + b, "<contact>")


def _driven(tmp_path):
    """Vertices 1 and 4 driven along a path (CSV beside the scene) and released at t = 0.0043 s
    (during step 21), with gas, dashpot, drag and a floor."""
    import trimesh
    v = np.asarray(trimesh.creation.icosphere(subdivisions=1, radius=0.1).vertices)
    times, offsets = [0.0, 0.003, 0.006], [[0, 0, 0], [0.01, 0.02, 0], [0.0, 0.03, 0.01]]
    rows = ["t," + ",".join(f"c{i}" for i in range(6))]
    rows += [",".join(repr(float(a)) for a in [t, *(v[1] + o), *(v[4] + o)]) for t, o in zip(times, offsets)]
    (tmp_path / "path.csv").write_text("\n".join(rows) + "\n")
    text = icosphere_text(subdivisions=1, k=150.0, nmol=5e-4, dashpot=0.01, drag=0.3, floor=-0.1005,
                          extra="driven path.csv 2 5 until 0.0043")
    (tmp_path / "s.obj").write_text(text)
    return jaxplush.load_scene(tmp_path / "s.obj")


SCENES = {"full": _full, "pinned_two": _pinned_two, "contact": _contact}


def _v0(sim):
    """A downward initial velocity with some shear (the floor is hit within a few steps); balls in
    contact move towards each other."""
    x0 = np.asarray(sim.topology.x0)
    v = np.zeros_like(x0)
    v[:, 1] = -0.6 + 2.0 * x0[:, 0]
    v[:, 2] = 0.8 * x0[:, 1]
    if sim.terms.contact:
        v[:, 0] = np.where(np.asarray(sim.topology.vertex_object) == 0, 0.4, -0.4)
    return jnp.asarray(v)


def _field(sim):
    """A random (E,) per-edge stiffness around each edge's object's k."""
    rng = np.random.default_rng(7)
    k = np.asarray(sim.params().k_structural)[np.asarray(sim.topology.edge_object)]
    return jnp.asarray(k * rng.uniform(0.5, 1.5, k.shape))


def _user_loss(sim, gradient, **kw):
    """A loss of the user's: weighted distances of every frame to a target, the final velocity's
    energy and height (so the final state's cotangent is exercised too)."""
    x0 = np.asarray(sim.topology.x0)
    target = jnp.asarray(x0 + 1e-3 * np.random.default_rng(0).standard_normal(x0.shape))
    w = jnp.arange(1.0, N_FRAMES + 1.0)[:, None, None]

    def f(p, s):
        final, frames, _ = jaxplush.rollout(sim, p, s, N_FRAMES, EVERY, gradient=gradient, **kw)
        return jnp.sum(w * (frames - target) ** 2) + 1e-3 * jnp.sum(final.v ** 2) + 1e-2 * jnp.sum(final.x[:, 1])
    return f


def _assert_close(got, ref, rtol=1e-9):
    """Leaf by leaf, in norm (a component near zero gets no say over a rounding-level difference)."""
    for a, b in zip(jax.tree_util.tree_leaves(got), jax.tree_util.tree_leaves(ref), strict=True):
        a, b = np.asarray(a), np.asarray(b)
        assert a.shape == b.shape
        assert np.linalg.norm(a - b) <= rtol * np.linalg.norm(b) + 1e-300, (a, b)


def _grads(sim, p, s, gradient, **kw):
    return jax.jit(jax.value_and_grad(_user_loss(sim, gradient, **kw), argnums=(0, 1)))(p, s)


@pytest.mark.parametrize("name, field, budget", [
    ("full", False, None),
    ("full", False, 4096),                    # over budget: checkpoints and recomputed segments
    ("pinned_two", False, None),
    ("contact", True, None),                  # soft-soft contact and a per-edge stiffness field
])
def test_gradient_matches_plain_autodiff(x64, name, field, budget):
    sim = jaxplush.make_simulator(SCENES[name](), DT)
    assert adjoint.adjoint_supported(sim)
    p = sim.params()
    if field:
        p = p._replace(k_structural=_field(sim))
    s = sim.init_fn(p, None, _v0(sim))
    if budget is not None:
        assert not adjoint._plan(sim, N_FRAMES * EVERY, None, budget, 8).store
    v, g = _grads(sim, p, s, "auto", memory_budget=budget)
    v_ref, g_ref = _grads(sim, p, s, "autodiff")
    assert float(v) == pytest.approx(float(v_ref), rel=1e-12)
    assert np.abs(np.asarray(g_ref[0].k_structural)).max() > 0
    if field:
        assert g[0].k_structural.shape == (sim.topology.n_edges,)
    _assert_close(g, g_ref)
    if name == "full":     # the floor is really hit (its projection is part of the gradient)
        frames = jaxplush.rollout(sim, p, s, N_FRAMES, EVERY)[1]
        assert float(jnp.min(frames[:, :, 1])) == pytest.approx(sim.scene.floor, abs=1e-12)
    if name == "contact":  # the balls do press on each other
        from jaxplush.model import contact
        force = contact.make_contact_force(sim.topology, sim.terms.contact)
        x = jaxplush.rollout(sim, p, s, N_FRAMES, EVERY)[1][-1]
        assert float(jnp.max(jnp.abs(force(p, x.T)))) > 0


def test_driven_vertices_and_a_chained_rollout(x64, tmp_path):
    """Driven vertices (read by step index, released during step 21): the gradient of a loss over
    two chained rollouts (the second continues the first's state, health and step count) equals
    autodiff's, and that of the same loss over one rollout of both's frames."""
    sim = jaxplush.make_simulator(_driven(tmp_path), DT)
    assert sim.terms.driven and adjoint.adjoint_supported(sim)
    p = sim.params()
    s = sim.init_fn(p, None, _v0(sim))
    target = jnp.asarray(sim.topology.x0) + 0.01

    def chained(gradient):
        def f(p, s):
            mid, a, h = jaxplush.rollout(sim, p, s, 3, EVERY, gradient=gradient)
            end, b, _ = jaxplush.rollout(sim, p, mid, 3, EVERY, health=h, step0=3 * EVERY, gradient=gradient)
            return jnp.sum((jnp.concatenate([a, b]) - target) ** 2) + jnp.sum(end.v ** 2)
        return jax.jit(jax.value_and_grad(f, argnums=(0, 1)))

    def single(p, s):
        end, frames, _ = jaxplush.rollout(sim, p, s, 6, EVERY)
        return jnp.sum((frames - target) ** 2) + jnp.sum(end.v ** 2)
    v, g = chained("auto")(p, s)
    v_ref, g_ref = chained("autodiff")(p, s)
    v1, g1 = jax.jit(jax.value_and_grad(single, argnums=(0, 1)))(p, s)
    assert float(v) == pytest.approx(float(v_ref), rel=1e-12) and float(v1) == pytest.approx(float(v), rel=1e-12)
    _assert_close(g, g_ref)
    _assert_close(g1, g)


def test_gradient_matches_finite_differences(x64):
    """The default gradient along a random direction of (log parameters, initial state) against
    central differences at two step sizes."""
    sim = jaxplush.make_simulator(_full(), DT)
    p = sim.params()
    s = sim.init_fn(p, None, _v0(sim))
    f = _user_loss(sim, "auto")
    on = [i for i, a in enumerate(p) if float(a[0]) != 0]
    rng = np.random.default_rng(3)
    d_log = rng.standard_normal(len(on))
    dx, dv = (jnp.asarray(rng.standard_normal(s.x.shape)) for _ in range(2))

    def along(t):
        q = list(p)
        for j, i in enumerate(on):
            q[i] = p[i] * jnp.exp(t * d_log[j])
        return f(type(p)(*q), jaxplush.State(s.x + 1e-3 * t * dx, s.v + 1e-3 * t * dv))
    g = jax.jit(jax.grad(f, argnums=(0, 1)))(p, s)
    an = (sum(float(g[0][i][0] * p[i][0]) * d_log[j] for j, i in enumerate(on))
          + 1e-3 * float(jnp.sum(g[1].x * dx) + jnp.sum(g[1].v * dv)))
    fj = jax.jit(along)
    assert_gradient_matches_fd(lambda t: float(fj(t[0])), np.zeros(1), [an], h=1e-4, rtol=1e-6)


def _small():
    """12 vertices with every per-vertex term and a floor: cheap compiles for the transformations."""
    return jaxplush.make_simulator(jaxplush.parse_scene(icosphere_text(
        subdivisions=0, k=200.0, mass=0.05, nmol=5e-4, dashpot=0.02, drag=0.5, damping=300.0, floor=-0.1005),
        "<small>"), DT)


def _heights(sim, gradient):
    """Each frame's mean height and the final velocity of vertex 0: a vector output, for Jacobians."""
    def f(k, v0):
        p = sim.params()._replace(k_structural=k)
        final, frames, _ = jaxplush.rollout(sim, p, sim.init_fn(p, None, v0), N_FRAMES, EVERY, gradient=gradient)
        return jnp.concatenate([jnp.mean(frames[:, :, 1], axis=1), final.v[0]])
    return f


def test_composes_with_jvp_jacfwd_jacrev_vmap_and_vjp(x64):
    sim = _small()
    k = sim.params().k_structural
    v0 = _v0(sim)
    f, ref = _heights(sim, "auto"), _heights(sim, "autodiff")
    # forward mode
    dv = jnp.asarray(np.random.default_rng(1).standard_normal(v0.shape))
    _assert_close(jax.jit(lambda a, b: jax.jvp(f, (a, b), (jnp.ones_like(a), dv)))(k, v0),
                  jax.jit(lambda a, b: jax.jvp(ref, (a, b), (jnp.ones_like(a), dv)))(k, v0))
    # reverse against forward mode, and against autodiff
    jr = jax.jit(jax.jacrev(f, argnums=(0, 1)))(k, v0)
    _assert_close(jr, jax.jit(jax.jacfwd(f, argnums=(0, 1)))(k, v0))
    _assert_close(jr, jax.jit(jax.jacrev(ref, argnums=(0, 1)))(k, v0))
    # vjp of the final state's and frames' cotangents, eager (outside jit)
    ct = jnp.asarray(np.random.default_rng(2).standard_normal(N_FRAMES + 3))
    _assert_close(jax.vjp(f, k, v0)[1](ct), jax.vjp(ref, k, v0)[1](ct))
    # a batch of gradients: several starts, several stiffnesses, at once
    starts = jnp.stack([v0, 0.5 * v0, -v0])
    ks = jnp.stack([k, 1.5 * k, 0.7 * k])

    def scalar(k, v0):
        return jnp.sum(f(k, v0) ** 2)
    batched = jax.jit(jax.vmap(jax.grad(scalar, argnums=(0, 1))))(ks, starts)
    grad_ref = jax.jit(jax.grad(lambda a, b: jnp.sum(ref(a, b) ** 2), argnums=(0, 1)))     # one compile
    one_by_one = [grad_ref(a, b) for a, b in zip(ks, starts)]
    _assert_close(batched, jax.tree_util.tree_map(lambda *a: jnp.stack(a), *one_by_one))
    # vmap of the loss, then its gradient
    _assert_close(jax.jit(jax.grad(lambda ks: jnp.sum(jax.vmap(scalar)(ks, starts))))(ks),
                  jnp.stack([g[0] for g in one_by_one]))


def test_health_carries_no_derivative_and_integers_pass(x64):
    """A loss may read the health record: its integer fields are data and its good_state carries
    a zero derivative (documented), in both modes."""
    sim = _small()
    p = sim.params()
    s = sim.init_fn(p, None, _v0(sim))

    def f(k):
        _, frames, h = jaxplush.rollout(sim, p._replace(k_structural=k), s, N_FRAMES, EVERY)
        return jnp.sum(frames[-1] ** 2) * (h.bad_step[0] < 0) + jnp.sum(h.good_state.x)
    g = jax.jit(jax.grad(f))(p.k_structural)
    assert np.isfinite(np.asarray(g)).all() and float(jnp.abs(g[0])) > 0
    t = jax.jvp(f, (p.k_structural,), (jnp.ones_like(p.k_structural),))[1]
    assert float(t) == pytest.approx(float(g[0]), rel=1e-9)


def test_fallback_warns_once_and_matches_autodiff(x64):
    """Contact friction is outside the fused adjoint: the default gradient is checkpointed
    autodiff, says so once (per process and reason), and equals plain autodiff."""
    sim = jaxplush.make_simulator(_contact("contact_friction 0.4\n"), DT)
    assert "contact_friction" in sim.terms.names() and not adjoint.adjoint_supported(sim)
    p = sim.params()
    s = sim.init_fn(p, None, _v0(sim))
    rollouts._WARNED.clear()
    with pytest.warns(UserWarning, match="does not cover contact_friction.*checkpointed autodiff"):
        v, g = _grads(sim, p, s, "auto")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        # (the warning is said while tracing: lowering shows it without compiling again)
        jax.jit(jax.value_and_grad(_user_loss(sim, "auto"), argnums=(0, 1))).lower(
            p._replace(k_structural=p.k_structural * 1.1), s)                       # no second warning
        jax.jit(jax.grad(_user_loss(sim, "checkpoint"))).lower(p, s)                # asked for: none
    v_ref, g_ref = _grads(sim, p, s, "autodiff")
    assert float(v) == pytest.approx(float(v_ref), rel=1e-12)
    _assert_close(g, g_ref)
    with pytest.raises(ValueError, match="does not cover contact_friction"):
        jaxplush.rollout(sim, p, s, 2, 2, gradient="adjoint")


def test_bad_arguments():
    sim = _small()
    p = sim.params()
    s = sim.init_fn(p)
    with pytest.raises(ValueError, match="unknown gradient 'fast'"):
        jaxplush.rollout(sim, p, s, 2, 2, gradient="fast")
    with pytest.raises(ValueError, match="checkpoint=True"):
        jaxplush.rollout(sim, p, s, 2, 2, checkpoint=True, gradient="adjoint")

    def f(k, gradient="auto"):
        return jnp.sum(jaxplush.rollout(sim, p._replace(k_structural=k), s, 2, 2, gradient=gradient)[1] ** 2)
    with pytest.raises(NotImplementedError, match="second derivative.*gradient='autodiff'"):
        jax.hessian(f)(p.k_structural)
    assert np.isfinite(np.asarray(jax.hessian(lambda k: f(k, "autodiff"))(p.k_structural))).all()


def _temp(sim, steps, n_frames=10, **kw):
    """XLA's temporaries (bytes) of the jitted gradient of a loss on the rollout's frames, float32."""
    p = sim.params()
    s = sim.init_fn(p)

    def f(q):
        final, frames, _ = jaxplush.rollout(sim, q, s, n_frames, steps // n_frames, **kw)
        return jnp.sum(frames[:, :, 1]) + jnp.sum(final.v)
    return jax.jit(jax.grad(f)).lower(p).compile().memory_analysis().temp_size_in_bytes


def test_memory_stays_within_the_budget_at_10000_steps():
    """Compiled temporaries of the gradient (static analysis, nothing run): within the budget the
    adjoint keeps every step's positions and velocities and little more; over it, checkpoints and
    one recomputed segment, about sqrt(steps) states each, so 10x the steps costs about 3x, not
    10x; plain autodiff keeps every step's residuals."""
    sim = jaxplush.make_simulator(jaxplush.parse_scene(icosphere_text(
        subdivisions=1, k=200.0, nmol=5e-4, dashpot=0.02, floor=-0.2), "<mem>"), 1e-4)
    state = 2 * 3 * sim.topology.n_vertices * 4                    # float32 (x, u) of one step
    stored = _temp(sim, 10_000)
    assert 10_000 * state <= stored < 1.2 * 10_000 * state < adjoint.DEFAULT_MEMORY_BUDGET
    budget = 100 * state
    small, large = _temp(sim, 1000, memory_budget=budget), _temp(sim, 10_000, memory_budget=budget)
    assert large < 0.05 * 10_000 * state and large < 4.5 * small
    assert large > 1.5 * small                                      # (the analysis does see the states)
    plain = _temp(sim, 10_000, gradient="autodiff")
    assert plain > 2 * 10_000 * state > 20 * large


def _opcodes(fn, *args):
    """The multiset of a compiled program's HLO instructions (opcode and shape), parameters left out."""
    text = jax.jit(fn).lower(*args).compile().as_text()
    ops = re.findall(r"^\s*(?:ROOT )?%\S+ = (\S+) (\w[\w-]*)\(", text, flags=re.M)
    return collections.Counter(o for o in ops if o[1] != "parameter")


def test_a_run_that_is_not_differentiated_compiles_to_the_plain_rollout():
    sim = _small()
    p = sim.params()
    s = sim.init_fn(p)

    def plain(p, s):
        return rollouts._core_jit(sim, p, s, rollouts.initial_health(sim, s), jnp.asarray(0, jnp.int32),
                                  n_frames=4, save_every=7, checkpoint=False)
    got = _opcodes(lambda p, s: jaxplush.rollout(sim, p, s, 4, 7), p, s)
    assert got == _opcodes(plain, p, s) and sum(got.values()) > 50
