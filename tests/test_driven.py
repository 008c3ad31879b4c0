"""Driven vertices (scene keyword ``driven PATH I [I ...] [until T]``): parsing and its errors, the
path in every integrator, conservation, release, gradients (every method) against finite
differences, the writers, the batched engine (lanes against the single scene, each lane at its
own step), a sweep against a target's controls, multiple shooting and a fit."""

from __future__ import annotations

import os

import h5py
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxplush
from conftest import assert_gradient_matches_fd, icosphere_text
from jaxplush import SceneError
from jaxplush.stepping import batched
from jaxplush.fitting.objective import gradients as G
from jaxplush.stepping import constraints
from jaxplush.stepping.integrators import INTEGRATORS

DT = 1e-3


def _csv(path, times, positions):
    positions = np.asarray(positions, np.float64).reshape(len(times), -1)
    rows = ["t," + ",".join(f"c{i}" for i in range(positions.shape[1]))]
    rows += [",".join(repr(float(v)) for v in [t, *p]) for t, p in zip(times, positions)]
    path.write_text("\n".join(rows) + "\n")
    return path


def _ball_vertices(subdivisions=1, radius=0.1):
    import trimesh
    return np.asarray(trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius).vertices)


def _scene(tmp_path, times, offsets, vertices=(0,), until=None, subdivisions=1, name="s.obj", **kw):
    """An icosphere whose ``vertices`` follow their rest positions plus ``offsets`` (S, 3) (the
    same offset for each), from a CSV beside the scene file."""
    v = _ball_vertices(subdivisions)
    pos = np.stack([[v[i] + np.asarray(o, float) for i in vertices] for o in offsets])
    _csv(tmp_path / "path.csv", times, pos)
    line = "driven path.csv " + " ".join(str(i + 1) for i in vertices) + (f" until {until!r}" if until else "")
    (tmp_path / name).write_text(icosphere_text(subdivisions=subdivisions, extra=line, **kw))
    return jaxplush.load_scene(tmp_path / name)


def _path(scene, t):
    """(D, 3) positions of every driven vertex at time t (numpy reference)."""
    return np.concatenate([d.position(t) for d in scene.driven])


# --------------------------------------------------------------------------- parsing

def test_parse_csv_and_hdf5(tmp_path):
    s = _scene(tmp_path, [0.0, 0.1], [[0, 0, 0], [0, 0.1, 0]], vertices=(0, 5), until=0.05)
    (d,) = s.driven
    assert d.vertices == (0, 5) and d.until == 0.05 and d.source == "path.csv" and d.line > 0
    assert d.file == str(tmp_path / "path.csv") and d.positions.shape == (2, 2, 3)
    assert s.driven_vertices.tolist() == [0, 5]
    with h5py.File(tmp_path / "p.h5", "w") as f:
        f["times"] = d.times
        f["positions"] = d.positions
    text = (tmp_path / "s.obj").read_text().replace("driven path.csv", "driven p.h5")
    s2 = jaxplush.parse_scene(text, str(tmp_path / "s2.obj"))
    np.testing.assert_array_equal(s2.driven[0].positions, d.positions)
    assert s2.fingerprint == s.fingerprint
    assert jaxplush.make_simulator(s, DT).terms.driven
    assert not jaxplush.make_simulator(jaxplush.parse_scene(icosphere_text(), "<t>"), DT).terms.driven


@pytest.mark.parametrize("case, message", [
    ("missing", "'driven' path file 'nope.csv' .*: no such file"),
    ("bad_row", "line 3: expected 4 values"),
    ("not_numbers", "line 3: not a row of numbers"),
    ("decreasing", "times must be strictly increasing: sample 3"),
    ("nan", "positions of sample 2 are not finite"),
    ("other_object", "'driven' vertex 13 is not a vertex of object 'ball'"),
    ("fixed", "'driven' vertex 1 is also 'fixed'"),
    ("twice", "'driven' vertex 1 is driven twice"),
    ("until", "release time 'until -1' must be > 0"),
    ("no_vertex", "expects a path file and at least 1 vertex index"),
    ("h5_shape", "'positions' must have shape"),
])
def test_parse_errors(tmp_path, case, message):
    v = _ball_vertices(0)
    good = [[0.0] + v[0].tolist(), [0.1] + v[0].tolist()]
    rows = {"bad_row": ["t,x,y,z", "0,0,0,0", "0.1,0,0"], "not_numbers": ["t,x,y,z", "0,0,0,0", "0.1,a,0,0"],
            "decreasing": ["0,0,0,0", "0.2,0,0,0", "0.1,0,0,0"], "nan": ["0,0,0,0", "0.1,nan,0,0"]}
    (tmp_path / "p.csv").write_text("\n".join(rows.get(case, [",".join(map(repr, r)) for r in good])) + "\n")
    with h5py.File(tmp_path / "p.h5", "w") as f:
        f["times"] = [0.0, 0.1]
        f["positions"] = np.zeros((2, 3))
    line = {"missing": "driven nope.csv 1", "other_object": "driven p.csv 13", "fixed": "driven p.csv 1",
            "twice": "driven p.csv 1\ndriven p.csv 1", "until": "driven p.csv 1 until -1",
            "no_vertex": "driven p.csv", "h5_shape": "driven p.h5 1"}.get(case, "driven p.csv 1")
    text = icosphere_text(subdivisions=0, extra=line, fixed=(0,) if case == "fixed" else ())
    if case == "other_object":
        text += icosphere_text(subdivisions=0, name="b", translate=(1, 0, 0), offset=12, header=False)
    path = str(tmp_path / "s.obj")
    with pytest.raises(SceneError, match=message) as e:
        jaxplush.parse_scene(text, path)
    lines = text.splitlines()
    assert e.value.path == path and lines[e.value.line - 1].startswith("driven")


# --------------------------------------------------------------------------- the path in every integrator

@pytest.mark.parametrize("integrator, substeps", [(i, 1) for i in INTEGRATORS] + [("verlet", 3), ("rk4", 2)])
def test_driven_vertices_follow_the_path(tmp_path, integrator, substeps):
    """At every saved frame the driven vertices sit exactly at the path (linear between samples,
    held before the first and after the last), the others move; the state starts on the path."""
    times = [0.004, 0.011, 0.02]
    s = _scene(tmp_path, times, [[0, 0, 0], [0.02, 0.01, 0], [0.02, -0.01, 0.005]], vertices=(0, 7),
               gravity=(0.0, -9.81, 0.0), nmol=5e-4)
    sim = jaxplush.make_simulator(s, DT, integrator=integrator, substeps=substeps)
    p = sim.params()
    s0 = sim.init_fn(p)
    np.testing.assert_allclose(np.asarray(s0.x)[[0, 7]], _path(s, 0.0), atol=1e-7)
    _, frames, health = jaxplush.rollout(sim, p, s0, 10, 3)
    assert not health.failed
    frames = np.asarray(frames)
    for j in range(10):
        np.testing.assert_allclose(frames[j, [0, 7]], _path(s, (j + 1) * 3 * DT), rtol=0, atol=1e-6)
    assert np.abs(frames[-1, 1:7] - s.vertices[1:7]).max() > 1e-4           # the rest moves


def test_interpolation_is_linear_and_velocity_is_the_paths(tmp_path):
    s = _scene(tmp_path, [0.0, 0.01], [[0, 0, 0], [0.01, 0.02, -0.03]], gravity=(0.0, 0.0, 0.0))
    sim = jaxplush.make_simulator(s, DT)
    p = sim.params()
    state = sim.init_fn(p)
    step = jax.jit(sim.step_fn)
    slope = np.array([1.0, 2.0, -3.0])
    np.testing.assert_allclose(np.asarray(state.v)[0], slope, rtol=1e-6)   # the path's velocity at 0
    for n in range(14):
        state = step(p, state, n)
        t = (n + 1) * DT
        want = s.vertices[0] + slope * min(t, 0.01)                      # linear, then held
        np.testing.assert_allclose(np.asarray(state.x)[0], want, atol=1e-7)
        np.testing.assert_allclose(np.asarray(state.v)[0], slope if t <= 0.01 + 1e-12 else 0 * slope, atol=1e-4)
    drive = constraints.Drive(s, DT)
    mid = np.asarray(drive.position(jnp.float32(0.0037), jnp.float32))[:, 0]
    np.testing.assert_allclose(mid, s.vertices[0] + slope * 0.0037, atol=1e-7)


def test_step_index_is_required_and_plain_scenes_ignore_it(tmp_path):
    s = _scene(tmp_path, [0.0], [[0, 0, 0]])
    sim = jaxplush.make_simulator(s, DT)
    p = sim.params()
    with pytest.raises(ValueError, match="pass the index of the step"):
        jax.jit(sim.step_fn)(p, sim.init_fn(p))
    plain = jaxplush.make_simulator(jaxplush.parse_scene(icosphere_text(fixed=(0,), floor=-0.2), "<t>"), DT)
    q = plain.params()
    s0 = plain.init_fn(q)
    def step_fn(q, s):
        return plain.step_fn(q, s)
    a = jax.jit(step_fn).lower(q, s0).as_text()

    def step_fn(q, s):                      # noqa: F811  (the same name: the same module text)
        return plain.step_fn(q, s, 7)
    b = jax.jit(step_fn).lower(q, s0).as_text()
    assert a == b and "driven" not in a


def test_release_after_until(tmp_path):
    """Before T the vertex is held on its path; after it, each step from a state is the free scene's
    step from that state (to rounding: two compiled programs may fuse and round differently, as on
    a GPU)."""
    until = 0.0105                                                          # released after step 10
    s = _scene(tmp_path, [0.0], [[0, 0.03, 0]], until=until, gravity=(0.0, -9.81, 0.0), nmol=5e-4)
    free = jaxplush.parse_scene(icosphere_text(gravity=(0.0, -9.81, 0.0), nmol=5e-4), "<free>")
    for integrator in ("verlet", "rk4", "implicit_euler"):
        sim = jaxplush.make_simulator(s, DT, integrator=integrator)
        ref = jaxplush.make_simulator(free, DT, integrator=integrator)
        p = sim.params()
        state = sim.init_fn(p)
        step, ref_step = jax.jit(sim.step_fn), jax.jit(ref.step_fn)
        for n in range(10):
            state = step(p, state, n)
            np.testing.assert_allclose(np.asarray(state.x)[0], _path(s, 0.0)[0], atol=1e-7)
        for n in range(10, 30):
            nxt, free_nxt = step(p, state, n), ref_step(p, state)
            for a, b in zip(nxt, free_nxt):
                a, b = np.asarray(a), np.asarray(b)
                assert np.max(np.abs(a - b)) <= 1e-6 * max(np.max(np.abs(b)), 1e-3), (integrator, n)
            state = nxt
        assert np.asarray(state.x)[0, 1] < _path(s, 0.0)[0, 1] - 1e-4, integrator   # it falls


def test_momentum_changes_only_through_the_driven_vertex(x64, tmp_path):
    """No gravity, floor or damping; one vertex held still. Springs and gas exert equal and
    opposite forces, so the free vertices' momentum changes by exactly the impulse the driven
    vertex's neighbours feel from it: sum_free m u_N - sum_free m u_0 = -h sum_n F_d(x_n), F_d the
    internal force on the driven vertex (Verlet: u_{n+1} = u_n + h F(x_n)/m for free vertices)."""
    s = _scene(tmp_path, [0.0], [[0, 0, 0]], gravity=(0.0, 0.0, 0.0), nmol=8e-4)
    sim = jaxplush.make_simulator(s, DT)
    p = sim.params()
    rng = np.random.default_rng(0)
    state = sim.init_fn(p, v0=0.3 * rng.standard_normal((s.n_vertices, 3)))
    m = float(p.total_weight[0]) / s.n_vertices
    free = np.arange(s.n_vertices) != 0
    p0 = m * np.asarray(state.v)[free].sum(axis=0)
    impulse = np.zeros(3)
    step = jax.jit(sim.step_fn)
    for n in range(60):
        f, _ = sim.force_fn(p, state.x, state.v)
        impulse += DT * np.asarray(f)[0]
        state = step(p, state, n)
    p1 = m * np.asarray(state.v)[free].sum(axis=0)
    assert np.abs(impulse).max() > 1e-4                                     # the constraint does act
    np.testing.assert_allclose(p1 - p0, -impulse, rtol=0, atol=1e-12 * max(1.0, np.abs(impulse).max()))
    np.testing.assert_array_equal(np.asarray(state.x)[0], s.vertices[0])


# --------------------------------------------------------------------------- gradients

def _grad_scene(tmp_path, until=None):
    return _scene(tmp_path, [0.0, 0.02, 0.04], [[0, 0, 0], [0.01, 0.03, 0], [0.0, 0.05, 0.01]],
                  vertices=(0, 3), until=until, gravity=(0.0, -9.81, 0.0), nmol=5e-4, dashpot=0.01, drag=0.3,
                  k=150.0, floor=-0.1005)


@pytest.mark.parametrize("until", [None, 0.0215])
def test_step_vjp_matches_autodiff(x64, tmp_path, until):
    """The fused adjoint's one-step VJP (driven rows masked, before and after a release) equals
    jax.vjp of the step."""
    sim = jaxplush.make_simulator(_grad_scene(tmp_path, until), DT)
    assert G.adjoint_supported(sim)
    p = sim.params()
    rng = np.random.default_rng(1)
    x = jnp.asarray(sim.topology.x0.T) + 2e-3 * rng.standard_normal((3, sim.topology.n_vertices))
    u = jnp.asarray(0.3 * rng.standard_normal(x.shape))
    x_bar, u_bar = (jnp.asarray(rng.standard_normal(x.shape)) for _ in range(2))
    for k in (0, 20, 21, 30):
        out, vjp = jax.vjp(lambda p, s: sim.internal.step(p, s, k), p, jaxplush.State(x, u))
        p_ref, s_ref = vjp(jaxplush.State(x_bar, u_bar))
        xb, ub, pb = G._make_step_vjp(sim)(p, x, u, out.x, x_bar, u_bar, k)
        for got, ref in [(xb, s_ref.x), (ub, s_ref.v)] + list(zip(pb, p_ref)):
            assert float(jnp.linalg.norm(got - ref)) <= 1e-11 * float(jnp.linalg.norm(ref)) + 1e-300


@pytest.mark.parametrize("method", ["plain", "checkpoint", "adjoint"])
def test_gradient_matches_finite_differences(x64, tmp_path, method):
    """Every gradient method through a rollout with a moving driven pair (released part way) and a
    floor: against central differences at two step sizes (float64), in log-parameters."""
    sim = jaxplush.make_simulator(_grad_scene(tmp_path, until=0.0305), DT)
    p = sim.params()
    frames = (10, 25, 40)
    rng = np.random.default_rng(0)
    target = jnp.asarray(sim.topology.x0[None] + 1e-3 * rng.standard_normal((3, sim.topology.n_vertices, 3)))

    def loss(x, t):
        return jnp.sum((x - t) ** 2)

    def f(q):
        return G.rollout_loss(sim, q, sim.init_fn(q), frames, loss, target, method=method, segment=7)
    names = ("k_structural", "dashpot", "drag", "nmol")
    base = np.array([float(getattr(p, n)[0]) for n in names])

    def params_at(theta):
        vals = jnp.exp(theta)
        return p._replace(**{n: vals[i:i + 1] for i, n in enumerate(names)})
    fj = jax.jit(lambda th: f(params_at(th)))
    g = jax.jit(jax.grad(lambda th: f(params_at(th))))(jnp.asarray(np.log(base)))
    assert np.all(np.asarray(g) != 0)
    assert_gradient_matches_fd(lambda th: float(fj(jnp.asarray(th))), np.log(base), np.asarray(g), h=1e-4,
                               rtol=1e-6)
    # the methods agree (adjoint against plain autodiff)
    ref = jax.jit(jax.grad(lambda q: G.rollout_loss(sim, q, sim.init_fn(q), frames, loss, target,
                                                     method="plain")))(p)
    got = jax.jit(jax.grad(f))(p)
    for a, b in zip(got, ref):
        np.testing.assert_allclose(a, b, rtol=1e-9, atol=1e-12 * float(jnp.max(jnp.abs(b))) + 1e-300)


def test_rollout_loss_from_a_later_step(x64, tmp_path):
    """step0: a loss over a rollout that starts at step 15 equals the tail of one from step 0."""
    sim = jaxplush.make_simulator(_grad_scene(tmp_path), DT)
    p = sim.params()
    s0 = sim.init_fn(p)
    s15, _, _ = jaxplush.rollout(sim, p, s0, 1, 15)
    _, frames, _ = jaxplush.rollout(sim, p, s0, 3, 15)
    t = jnp.zeros((1, sim.topology.n_vertices, 3))

    def loss(x, t):
        return jnp.sum((x - t) ** 2)
    for method in ("plain", "adjoint"):
        v = G.rollout_loss(sim, p, s15, (30,), loss, t, method=method, step0=15)
        assert float(v) == pytest.approx(float(jnp.sum(frames[2] ** 2)), rel=1e-12)


# --------------------------------------------------------------------------- writers, batched, fit

def test_scene_writer_round_trip(tmp_path):
    from jaxplush.scene.write import format_scene
    s = _scene(tmp_path, [0.0, 0.1], [[0, 0, 0], [0, 0.1, 0]], vertices=(0, 5), until=0.05)
    o = s.objects[0]
    text = format_scene([dict(name="ball", vertices=s.vertices, faces=s.faces, fixed=[2],
                              driven=[dict(path=d.source, vertices=list(d.vertices), until=d.until)
                                      for d in o.driven])])
    assert "\ndriven path.csv 1 6 until 0.05\n" in text
    back = jaxplush.parse_scene(text, str(tmp_path / "back.obj"))
    assert back.driven[0].vertices == (0, 5) and back.driven[0].until == 0.05 and back.fixed.tolist() == [2]
    np.testing.assert_array_equal(back.driven[0].positions, s.driven[0].positions)
    with pytest.raises(ValueError, match="driven index"):
        format_scene([dict(name="b", vertices=s.vertices, faces=s.faces, driven=[dict(path="p", vertices=[999])])])


def _lanes(scene, ks):
    """Params of ``scene`` with one spring stiffness per lane (every object), as (O, B) arrays."""
    p = scene.params
    out = {f: np.stack([np.asarray(getattr(p, f), np.float64)] * len(ks), axis=1) for f in jaxplush.Params._fields}
    out["k_structural"] = np.tile(np.asarray(ks, np.float64), (len(scene.objects), 1))
    return jaxplush.Params(**out)


def _pushed_into_a_ball(tmp_path):
    """Two 42-vertex balls 2 cm apart, no gravity: ball a's leftmost vertex is driven 6 cm to the
    right over 40 ms, so that a is pushed into b (soft-soft contact beside a driven vertex)."""
    r, gap, n = 0.1, 0.02, len(_ball_vertices(1))
    shift = np.array([r + gap / 2, 0.0, 0.0])
    i = int(np.argmin(_ball_vertices(1)[:, 0]))
    start = _ball_vertices(1)[i] - shift
    _csv(tmp_path / "push.csv", [0.0, 0.04], [start, start + [0.06, 0.0, 0.0]])
    text = icosphere_text(k=200.0, nmol=1e-3, gravity=(0.0, 0.0, 0.0), translate=tuple(-shift), name="a",
                          extra=f"driven push.csv {i + 1}")
    # ball b offset by (0, 1, 0.7) mm: a mirror-symmetric impact has exact ties between two faces,
    # where the contact force jumps and rounding picks the face (docs/contact.md)
    text += icosphere_text(k=200.0, nmol=1e-3, name="b", offset=n, header=False,
                           translate=tuple(shift + [0.0, 1e-3, 7e-4]))
    (tmp_path / "pushed.obj").write_text(text)
    return jaxplush.load_scene(tmp_path / "pushed.obj")


def _held(tmp_path, prefix=""):
    """Vertices 0 and 7 of a ball led along a path while it falls onto a floor 4 mm below it."""
    s = _scene(tmp_path, [0.004, 0.011, 0.02], [[0, 0, 0], [0.02, 0.01, 0], [0.02, -0.01, 0.005]],
               vertices=(0, 7), nmol=5e-4, dashpot=0.02, floor=-0.104)
    if not prefix:
        return s
    (tmp_path / "f.obj").write_text(prefix + (tmp_path / "s.obj").read_text())
    return jaxplush.load_scene(tmp_path / "f.obj")


BATCHED_CASES = {
    "held": _held,
    "friction": lambda tmp_path: _held(tmp_path, "floor_friction 0.5\nfloor_restitution 0.3\n"),
    "released": lambda tmp_path: _scene(tmp_path, [0.0, 0.01], [[0, 0, 0], [0, 0.03, 0]], until=0.0105,
                                        nmol=5e-4, damping=40.0),
    "contact": _pushed_into_a_ball,
}


@pytest.mark.parametrize("case, substeps", [("held", 1), ("held", 3), ("friction", 1), ("released", 1), ("contact", 2)])
def test_batched_lanes_follow_the_single_scene(tmp_path, case, substeps):
    """The batched engine drives the same vertices on the same path: each lane (its own k) gives the
    frames of ``jaxplush.simulate`` at that k, to float32 rounding relative to the positions' size,
    with the driven vertices on the path while they are held (and free after a release)."""
    scene = BATCHED_CASES[case](tmp_path)
    ks = [60.0, 100.0, 160.0]
    bsim = batched.make_batched_simulator(scene, DT, len(ks), substeps=substeps)
    assert bsim.terms.driven and (bsim.coherent is not None) == (case == "contact")
    pb = bsim.params(_lanes(scene, ks))
    steps, every = 40, 4
    _, frames, health = batched.rollout(bsim, pb, bsim.init_fn(pb), steps // every, every,
                                        observe=batched.positions_observer)
    assert not np.asarray(health.failed).any()
    frames = np.asarray(frames, np.float64)                                   # (T, B, V, 3)
    idx = list(scene.driven_vertices)
    for b, k in enumerate(ks):
        p = scene.params._replace(k_structural=np.full(len(scene.objects), k))
        ref = jaxplush.simulate(scene, steps, DT, every, params=p, substeps=substeps).positions[1:]
        err = np.linalg.norm(frames[:, b] - ref) / np.linalg.norm(ref)
        assert err < 2e-6, (b, err)
        for j in range(len(ref)):
            t = (j + 1) * every * DT
            if case != "released" or t <= 0.0105:
                np.testing.assert_allclose(frames[j, b, idx], _path(scene, t), rtol=0, atol=1e-6)
    assert np.abs(frames[:, 0] - frames[:, 2]).max() > 1e-4                 # the lanes' k matter
    if case == "released":                                                   # released, it falls back
        assert frames[-1, 0, idx[0], 1] < _path(scene, 1.0)[0, 1] - 1e-3
    if case == "contact":                                                    # b was pushed
        assert frames[-1, 0, 42:, 0].mean() > scene.vertices[42:, 0].mean() + 1e-3


def test_batched_lanes_at_their_own_steps(tmp_path):
    """Each lane reads its own step index: lanes started from a single-scene run's states at steps 0,
    6 and 12 continue that run (its states 6 steps later), and ``init_fn(..., step0=n)`` puts the
    driven vertices where the path has them at step n, moving at the path's velocity."""
    scene = BATCHED_CASES["released"](tmp_path)
    sim = jaxplush.make_simulator(scene, DT)
    p = sim.params()
    states = [sim.init_fn(p)]
    for m in range(3):
        states.append(jaxplush.rollout(sim, p, states[-1], 1, 6, step0=6 * m)[0])
    bsim = batched.make_batched_simulator(scene, DT, 3)
    pb = bsim.params()
    start = bsim.to_internal(jaxplush.State(*(np.stack([np.asarray(getattr(s, f)) for s in states[:3]])
                                              for f in ("x", "v"))))
    final, _, _ = batched.rollout(bsim, pb, start, 1, 6, step0=np.array([0, 6, 12]))
    got = batched.positions(final)
    for b in range(3):
        want = np.asarray(states[b + 1].x)
        assert np.linalg.norm(got[b] - want) <= 1e-6 * np.linalg.norm(want), b
    # a start at later steps: the driven vertex on the path (released after step 10: left alone)
    x0 = np.stack([scene.vertices] * 3)
    s0 = bsim.to_public(bsim.init_fn(pb, x0, np.zeros_like(x0), step0=np.array([0, 5, 12])))
    i = scene.driven_vertices[0]
    np.testing.assert_allclose(np.asarray(s0.x)[:2, i], [_path(scene, 0.0)[0], _path(scene, 5 * DT)[0]], atol=1e-7)
    np.testing.assert_allclose(np.asarray(s0.x)[2, i], scene.vertices[i], atol=1e-7)
    np.testing.assert_allclose(np.asarray(s0.v)[1, i], [0.0, 3.0, 0.0], rtol=1e-4)      # 3 cm in 10 ms


def test_the_batched_engine_takes_driven_scenes(tmp_path):
    from jaxplush.fitting.objective.evaluate import _batchable
    s = _scene(tmp_path, [0.0], [[0, 0, 0]])
    terms = jaxplush.make_simulator(s, DT).terms
    batched.check_terms(terms)
    assert _batchable(terms)
    bsim = batched.make_batched_simulator(s, DT, batch=2)
    pb = bsim.params()
    with pytest.raises(ValueError, match="pass the index of the step"):
        bsim.step_fn(pb, bsim.init_fn(pb))


def _squeezed(tmp_path, k):
    """A small gas-filled ball squeezed between two driven caps (in, hold, out), no gravity."""
    v = _ball_vertices(1)
    right, left = np.flatnonzero(v[:, 0] > 0.07), np.flatnonzero(v[:, 0] < -0.07)
    times = [0.0, 0.03, 0.045, 0.075]
    depth = np.array([0.0, 0.02, 0.02, 0.0])
    lines = []
    for side, patch, name in ((1.0, right, "r.csv"), (-1.0, left, "l.csv")):
        _csv(tmp_path / name, times, [v[patch] - side * d * np.array([1.0, 0, 0]) for d in depth])
        lines.append(f"driven {name} " + " ".join(str(i + 1) for i in patch))
    path = tmp_path / f"sq_{k:g}.obj"
    path.write_text(icosphere_text(subdivisions=1, k=k, mass=0.05, nmol=5e-4, dashpot=0.01,
                                   gravity=(0.0, 0.0, 0.0), extra="\n".join(lines)))
    return jaxplush.load_scene(path)


def _without_driven(scene):
    import dataclasses
    return scene.replace(objects=tuple(dataclasses.replace(o, driven=()) for o in scene.objects))


def test_a_sweep_against_a_target_with_controls(tmp_path):
    """A sweep drives the vertices a target's controls name, in every point, as a fit does: the
    scene without its ``driven`` lines against a squeeze's target has its loss minimum (0, to
    rounding) at the true k, and the same losses as the scene with the lines."""
    from jaxplush.fitting.sweep import sweep
    from jaxplush.fitting.targets import make_target
    truth = _squeezed(tmp_path, 120.0)
    target = make_target(truth, 90, DT, 10, controls=True)
    grid = {"k": [80.0, 120.0, 180.0]}
    res = sweep(_without_driven(truth), grid, steps=90, dt=DT, target=target, progress=False, batch=3)
    assert res.best()["k_structural"] == 120.0
    assert res.loss[1] < 1e-6 * res.loss[0] and res.loss[1] < 1e-6 * res.loss[2]
    same = sweep(truth, grid, steps=90, dt=DT, target=make_target(truth, 90, DT, 10), progress=False, batch=3)
    np.testing.assert_allclose(res.loss, same.loss, rtol=1e-5, atol=1e-6 * res.loss[0])


def test_multiple_shooting_of_a_driven_scene(tmp_path):
    """Multiple shooting runs a driven scene's segments as lanes of the batched engine, each at its
    node's step (the squeeze goes in, holds and comes out over the target): along k its loss has
    its minimum at the truth, where the segments land on the target."""
    import warnings
    from jaxplush.fitting import fitter as F
    from jaxplush.fitting.objective import shooting as S
    from jaxplush.fitting.targets import make_target
    truth = _squeezed(tmp_path, 120.0)
    target = make_target(truth, 90, DT, 5)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        prob = F.build_problem(truth, target, ["k_structural"], noise_free=True)
    assert S.why_not(prob) is None
    ev = S.ShootingEvaluator(prob, 6)
    assert len(ev.nodes) == 3
    loss = ev(prob.theta0[None] + np.log([0.8, 1.0, 1.25])[:, None, None]).loss
    assert loss[1] < 0.2 * min(loss[0], loss[2]), loss
    # at the truth only the node velocities (estimated from the frames) are off: the residual is a
    # few % of the motion (segments that read the path from t = 0 instead of their node's step: 60%)
    motion = np.sqrt(np.mean((target.positions - truth.vertices) ** 2))
    from jaxplush.fitting.objective import losses
    assert losses.rms_metres(loss[1], prob.loss.scale2, "positions") < 0.1 * motion


def test_fit_of_a_squeezed_plush_and_fitted_scene(tmp_path):
    from jaxplush.fitting import fitter as F
    from jaxplush.fitting.io import write_fitted_scene
    from jaxplush.fitting.targets import make_target
    truth = _squeezed(tmp_path, 120.0)
    target = make_target(truth, 90, DT, 10)
    start = _squeezed(tmp_path, 180.0)
    res = F.fit(start, target, ("k_structural",), noise_free=True)
    assert res.values["k_structural"][0] == pytest.approx(120.0, rel=1e-2), res.reason
    out = tmp_path / "sub" / "fitted.obj"
    out.parent.mkdir()
    write_fitted_scene(res, out)
    text = out.read_text()
    assert "\ndriven ../r.csv " in text and "\ndriven ../l.csv " in text
    back = jaxplush.load_scene(out)
    assert [d.file for d in back.driven] == [d.file for d in truth.driven]
    assert [d.vertices for d in back.driven] == [d.vertices for d in truth.driven]
    assert back.params.k_structural[0] == pytest.approx(120.0, rel=1e-2)
    assert os.path.isabs(back.driven[0].file)
