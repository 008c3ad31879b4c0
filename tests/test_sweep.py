"""Batched simulation (jaxplush.stepping.batched) and parameter sweeps (jaxplush.fitting.sweep, jaxplush-fit sweep).

The batched step must be the single-scene step, point for point: it is checked against separate
``jaxplush.simulate`` runs in float32 and float64, with every term compiled in, on two objects.
Blow-ups are located per point to the same exact step as ``simulate`` reports. Sweep losses are
checked against targets simulated at known parameters (the minimum is the truth) and against
direct numpy evaluations.
"""

from __future__ import annotations

import dataclasses
import os

import h5py
import jax.numpy as jnp
import numpy as np
import pytest

import jaxplush
from jaxplush.stepping import batched
from jaxplush.model import forces as model
from conftest import icosphere_scene, icosphere_text

from jaxplush.fitting import sweep as sweep_mod
from jaxplush.fitting.sweep import SweepError, load_sweep, sweep
from jaxplush.fitting.sweep.cli import main as sweep_main, parse_grid_spec

DT = 2e-4
TRUE_K, TRUE_NMOL = 300.0, 2e-3


def _two_object_scene(**kw):
    """Two icospheres with every term on: gas, floor, a pin, dashpot, drag, Verlet damping."""
    # (soft-soft contact off: batched contact is checked in tests/test_batched_contact.py)
    text = ("contact off\n"
            + icosphere_text(subdivisions=1, nmol=1e-3, dashpot=0.01, drag=0.5, damping=200.0, floor=-0.12,
                             fixed=(0,), **kw)
            + icosphere_text(subdivisions=1, nmol=2e-3, k=200.0, name="b2", translate=(0.3, 0, 0), offset=42,
                             header=False))
    return jaxplush.parse_scene(text, "<two>")


def _ball(**kw):
    kw = dict(dict(subdivisions=1, nmol=1e-3, k=200.0, floor=-0.12), **kw)
    return icosphere_scene(**kw)


def _point_params(scene, **values):
    """Params of (O,) numpy arrays with some entries replaced: values name -> (O,) list."""
    p = scene.params
    return p._replace(**{k: np.asarray(v, np.float64) for k, v in values.items()})


def _check_against_simulate(scene, points, steps, save_every, tol):
    bsim = batched.make_batched_simulator(scene, DT, len(points))
    pb = bsim.params(jaxplush.Params(*(np.stack(a, axis=1) for a in zip(*points))))
    state = bsim.init_fn(pb)
    final, frames, health = batched.rollout(bsim, pb, state, steps // save_every, save_every,
                                            observe=batched.positions_observer)
    assert not health.failed.any()
    frames = np.asarray(frames)                                        # (T, B, V, 3)
    sim = jaxplush.make_simulator(scene, DT)
    assert sim.terms == bsim.terms
    for b, p in enumerate(points):
        traj = jaxplush.simulate(scene, steps, DT, save_every, params=p, check_dt=False, sim=sim)
        ref = traj.positions[1:]
        moved = np.abs(ref - scene.vertices).max()
        assert moved > 1e-3                                              # the run does something
        err = np.abs(frames[:, b] - ref).max() / np.abs(ref).max()
        assert err < tol, (b, err)
        np.testing.assert_array_equal(batched.positions(final)[b], frames[-1, b])


POINTS = [dict(k_structural=[100.0, 200.0], nmol=[1e-3, 2e-3]),
          dict(k_structural=[400.0, 150.0], nmol=[2e-3, 1e-3], dashpot=[0.0, 0.02]),
          dict(k_structural=[250.0, 300.0], damping=[0.0, 50.0], drag=[2.0, 0.0], total_weight=[0.08, 0.05])]


def test_batched_matches_separate_simulate_runs_float32():
    scene = _two_object_scene()
    # two differently vectorised programs: float32 rounding apart (a wrong term is off by far more)
    _check_against_simulate(scene, [_point_params(scene, **v) for v in POINTS], 300, 100, 1e-4)


@pytest.mark.heavy
def test_batched_matches_separate_simulate_runs_float64(x64):
    scene = _two_object_scene()
    _check_against_simulate(scene, [_point_params(scene, **v) for v in POINTS], 300, 100, 1e-12)


def test_batched_floor_friction_and_restitution_match_simulate():
    scene = _ball(floor=-0.11, gravity=(2.0, -9.81, 0.0), extra="")
    scene = jaxplush.parse_scene("floor_friction 0.4\nfloor_restitution 0.5\n" + scene.text, "<friction>")
    assert scene.floor_friction == 0.4
    _check_against_simulate(scene, [_point_params(scene, k_structural=[k]) for k in (150.0, 300.0)], 400, 100, 1e-4)


@pytest.mark.heavy
def test_blow_up_is_located_per_point_at_simulates_step():
    scene = _ball()
    ks = [200.0, 1e5, 300.0]                       # the middle point is far beyond the stable dt
    bsim = batched.make_batched_simulator(scene, DT, 3)
    pb = bsim.params(scene.params._replace(k_structural=np.array([ks])))
    _, _, health = batched.rollout(bsim, pb, bsim.init_fn(pb), 10, 50)
    np.testing.assert_array_equal(health.failed, [False, True, False])
    step, code = batched.locate_failures(bsim, pb, health)
    with pytest.raises(jaxplush.SimulationError) as e:
        jaxplush.simulate(scene, 500, DT, 50, params=_point_params(scene, k_structural=[1e5]), check_dt=False)
    # the same blow-up, located to the step: the batched and the single-scene kernels sum in different
    # orders, so on an instability that grows by orders of magnitude per step they may part by a step or two
    assert abs(int(step[0, 1]) - e.value.step) <= 3 and 0 < step[0, 1] < 50
    assert jaxplush.stepping.diagnostics.MESSAGES[int(code[0, 1])] == e.value.reason
    assert step[0, 0] == step[0, 2] == -1
    # the last healthy state of the failed point is finite and earlier than the failure
    good = batched.positions(health.good_state)
    assert np.all(np.isfinite(good)) and int(health.good_step[1]) < step[0, 1]


def test_unsupported_terms_and_integrators_raise_before_tracing():
    two = jaxplush.parse_scene(icosphere_text(subdivisions=0) + icosphere_text(
        subdivisions=0, name="b", translate=(0.5, 0, 0), offset=12, header=False), "<contact>")
    # soft-soft contact is batched (tests/test_batched_contact.py): built, with per-point candidate lists
    assert batched.terms_for(two).contact and batched.make_batched_simulator(two, DT, 2).coherent is not None

    @dataclasses.dataclass(frozen=True)
    class FutureTerms(model.Terms):
        magnetism: bool = False

    scene = _ball(subdivisions=0)
    batched.make_batched_simulator(scene, DT, 2, terms=FutureTerms(**dataclasses.asdict(batched.terms_for(scene))))
    with pytest.raises(NotImplementedError, match="magnetism"):
        batched.make_batched_simulator(scene, DT, 2, terms=FutureTerms(magnetism=True))
    with pytest.raises(NotImplementedError, match="verlet"):
        batched.make_batched_simulator(scene, DT, 2, integrator="rk4")


def test_grid_is_a_cartesian_product_and_points_are_zipped():
    two = _two_object_scene()
    grid = {"k": [100.0, 200.0], "nmol@b2": [1e-3, 2e-3, 3e-3]}
    axes = sweep_mod._axes(two, grid, "grid")
    vals = sweep_mod._point_values(axes, "grid")
    assert [a.label for a in axes] == ["k_structural", "nmol@b2"]
    np.testing.assert_array_equal(vals[:, 0], np.repeat([100.0, 200.0], 3))      # last axis fastest
    np.testing.assert_array_equal(vals[:, 1], np.tile([1e-3, 2e-3, 3e-3], 2))
    p = sweep_mod._point_params(two, axes, vals)
    np.testing.assert_array_equal(p.k_structural, np.repeat(vals[:, :1], 2, axis=1))   # all objects
    np.testing.assert_array_equal(p.nmol[:, 0], 1e-3)                                  # object 0 untouched
    np.testing.assert_array_equal(p.nmol[:, 1], vals[:, 1])
    pts = sweep_mod._axes(two, sweep_mod._normalise_points([{"k@0": 1.0, "drag": 2.0}, {"k@0": 3.0, "drag": 4.0}]),
                          "points")
    np.testing.assert_array_equal(sweep_mod._point_values(pts, "points"), [[1.0, 2.0], [3.0, 4.0]])


@pytest.mark.parametrize("spec, match", [
    (dict(grid={"stiffness": [1.0]}), "unknown parameter"),
    (dict(grid={"k@nobody": [1.0]}), "no object 'nobody'"),
    (dict(grid={"k": [-1.0]}), "must be >= 0"),
    (dict(grid={"damping": [0.5]}), "must be 0"),
    (dict(grid={"k": [np.nan]}), "finite"),
    (dict(grid={"k": []}), "non-empty"),
    (dict(grid={"k": [1.0], "k_structural@b2": [2.0]}), "both set k_structural"),
    (dict(grid={"k": [1.0]}, points={"k": [1.0]}), "exactly one"),
    (dict(points={"k": [1.0, 2.0], "drag": [1.0]}), "same number"),
    (dict(grid={"k": [100.0, 200.0, 100.0]}), "distinct"),
    (dict(grid={"k@": [1.0]}), "no object after '@'"),
    (dict(grid={"k": ["stiff"]}), "must be numbers"),
    (dict(points=[{"k": 1.0, "drag": 2.0}, {"k": 3.0}]), "same parameters"),
])
def test_bad_sweep_specs_are_clear_errors(spec, match):
    with pytest.raises(SweepError, match=match):
        sweep(_two_object_scene(), steps=10, dt=DT, progress=False, **spec)


def test_points_may_list_their_parameters_in_any_order():
    two = _two_object_scene()
    pts = sweep_mod._normalise_points([{"k@0": 1.0, "drag": 2.0}, {"drag": 4.0, "k@0": 3.0}])
    np.testing.assert_array_equal(sweep_mod._point_values(sweep_mod._axes(two, pts, "points"), "points"),
                                  [[1.0, 2.0], [3.0, 4.0]])


def test_nmol_cannot_be_swept_on_an_object_without_gas():
    with pytest.raises(SweepError, match="no gas"):
        sweep(_ball(nmol=None), {"nmol": [1e-3]}, steps=10, dt=DT, progress=False)


@pytest.mark.heavy
def test_rollout_in_concurrent_chunks_matches_one_call():
    # batch 7 in chunks of 3 (the last one padded), run concurrently from a thread pool: the
    # same frames, final state and health (with a blow-up in one chunk) as one 7-point call
    scene = _ball()
    ks = np.array([[150.0, 200.0, 1e5, 250.0, 300.0, 350.0, 400.0]])
    out = []
    for chunk in (7, 3):
        bsim = batched.make_batched_simulator(scene, DT, 7, chunk=chunk)
        assert bsim.chunk == chunk
        pb = bsim.params(scene.params._replace(k_structural=ks))
        n0 = batched._core_jit._cache_size()
        final, frames, health = batched.rollout(bsim, pb, bsim.init_fn(pb), 4, 50,
                                                observe=batched.positions_observer)
        assert batched._core_jit._cache_size() == n0 + 1             # every chunk one compilation
        out.append((batched.positions(final), np.asarray(frames), health,
                    batched.locate_failures(bsim, pb, health)))
    (x1, f1, h1, l1), (x3, f3, h3, l3) = out
    assert f3.shape == f1.shape == (4, 7, scene.n_vertices, 3)
    np.testing.assert_array_equal(h3.failed, [False, False, True, False, False, False, False])
    np.testing.assert_array_equal(h3.failed, h1.failed)
    for a, b in zip(h1[:3] + (h1.good_step,), h3[:3] + (h3.good_step,)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    # the blow-up located to the step: healthy points exactly (-1); a failed one to within a few
    # steps (the chunks are separate programs; an instability amplifies their rounding)
    l1s, l3s = np.asarray(l1[0]), np.asarray(l3[0])
    np.testing.assert_array_equal(l1s == -1, l3s == -1)
    assert np.abs(l1s - l3s).max() <= 3
    ok = ~h1.failed
    np.testing.assert_allclose(x3[ok], x1[ok], rtol=0, atol=1e-6)
    np.testing.assert_allclose(f3[:, ok], f1[:, ok], rtol=0, atol=1e-6)
    np.testing.assert_allclose(batched.positions(h3.good_state), batched.positions(h1.good_state), rtol=0, atol=1e-6)


def test_fewer_lanes_than_the_batch_run_as_its_chunks_with_no_new_compile():
    # a simulator built for 8 points in chunks of 2 runs 3 of them (its first lanes): the same
    # compiled core (2 chunks, the last padded), the same frames and health as those lanes of the
    # whole batch
    scene = _ball()
    ks = np.array([[150.0, 200.0, 250.0, 300.0, 350.0, 400.0, 450.0, 500.0]])
    bsim = batched.make_batched_simulator(scene, DT, 8, chunk=2)
    pb = bsim.params(scene.params._replace(k_structural=ks))
    state = bsim.init_fn(pb)
    full_x, full_f, full_h = batched.rollout(bsim, pb, state, 3, 20, observe=batched.positions_observer)
    n0 = batched._core_jit._cache_size()
    p3, s3 = batched.take_lanes((pb, state), 3)
    assert batched.lanes(s3) == 3
    x3, f3, h3 = batched.rollout(bsim, p3, s3, 3, 20, observe=batched.positions_observer)
    assert batched._core_jit._cache_size() == n0                   # no new compilation
    assert np.asarray(f3).shape == (3, 3, scene.n_vertices, 3)
    np.testing.assert_array_equal(np.asarray(f3), np.asarray(full_f)[:, :3])
    np.testing.assert_array_equal(batched.positions(x3), batched.positions(full_x)[:3])
    np.testing.assert_array_equal(np.asarray(h3.code), np.asarray(full_h.code)[:, :3])


def test_default_chunk_splits_large_batches(monkeypatch):
    monkeypatch.setattr(batched.jax, "default_backend", lambda: "cpu")    # the CPU's chunking
    for b in (1, 7, 16, 17, 33, 64, 100):
        c = batched.default_chunk(b)
        n = -(-b // c)                                                  # chunks
        assert 1 <= c <= batched.MAX_CHUNK and n * c - b < c          # padding: less than one chunk
    assert batched.default_chunk(5) == 5
    assert batched.make_batched_simulator(_ball(subdivisions=0), DT, 64).chunk == batched.MAX_CHUNK


def test_batching_is_chosen_by_backend(monkeypatch):
    # the chunks, thread pool and XLA:CPU options are CPU tuning: on another backend a batch runs
    # in one call with default options, and a sweep's default batch is wider; a CPU keeps its
    # tuning (whichever backend runs this test)
    from jaxplush.fitting.objective import evaluate
    scene = _ball(subdivisions=0)
    monkeypatch.setattr(batched.jax, "default_backend", lambda: "cpu")
    assert batched.on_cpu() and sweep_mod.default_batch() == 64
    assert batched.default_chunk(1024) == batched.MAX_CHUNK
    monkeypatch.setattr(batched.jax, "default_backend", lambda: "gpu")
    assert not batched.on_cpu()
    assert batched.default_chunk(1024) == 1024 and batched.default_chunk(5) == 5
    assert sweep_mod.default_batch() == sweep_mod.DEFAULT_ACCELERATOR_BATCH
    assert batched.make_batched_simulator(scene, DT, 64).chunk == 64
    assert sweep_mod._outer_batch(3000, 1024) == 1000               # 3 equal batches, one call each
    seen, jit = [], batched.jax.jit
    monkeypatch.setattr(batched.jax, "jit", lambda f, **kw: seen.append(kw) or jit(f, **kw))
    lazy = batched._LazyJit(lambda a: a * 2, ())
    assert float(lazy(np.float32(3))) == 6.0
    assert seen and not any("compiler_options" in kw for kw in seen)
    monkeypatch.setattr(batched.jax, "default_backend", lambda: "cpu")
    seen.clear()
    assert float(batched._LazyJit(lambda a: a * 2, ())(np.float32(3))) == 6.0
    assert any(kw.get("compiler_options") == batched.ROLLOUT_COMPILER_OPTIONS for kw in seen)
    monkeypatch.setattr(batched.jax, "default_backend", lambda: "gpu")
    ev = evaluate.Evaluator.__new__(evaluate.Evaluator)
    assert ev._chunk_of(32) == 32 and ev._chunk_of(7) == 7
    # several GPUs: the batch split evenly over them (rollout shards the chunks, one per device)
    monkeypatch.setattr(batched, "local_devices", lambda: ("gpu0", "gpu1", "gpu2", "gpu3"))
    assert batched.default_chunk(1024) == 256 and batched.default_chunk(10) == 3 and ev._chunk_of(32) == 8


def test_folded_position_update_changes_no_result(monkeypatch):
    # the rollout carries positions folded to rows of >= _FOLD_WIDTH floats (a reshape, for the
    # vectoriser): the fold divides the vertex count, and a rollout with every term on (floor
    # contact, a pin, two objects) gives the frames and health of the unfolded one
    assert batched._fold_factor(642, 16) == 3 and batched._fold_factor(642, 48) == 1
    assert batched._fold_factor(84, 5) == 12 and batched._fold_factor(67, 16) == 1    # 67: prime
    scene = _two_object_scene()
    assert batched._fold_factor(scene.n_vertices, 3) > 1
    out = []
    for width in (batched._FOLD_WIDTH, 0):                              # 0: no folding
        monkeypatch.setattr(batched, "_FOLD_WIDTH", width)
        bsim = batched.make_batched_simulator(scene, DT, 3)
        points = [_point_params(scene, **v) for v in POINTS]
        pb = bsim.params(jaxplush.Params(*(np.stack(a, axis=1) for a in zip(*points))))
        final, frames, health = batched.rollout(bsim, pb, bsim.init_fn(pb), 5, 60,
                                                observe=batched.positions_observer)
        out.append((batched.positions(final), np.asarray(frames), health))
    (x1, f1, h1), (x0, f0, h0) = out
    assert not h1.failed.any() and not h0.failed.any()
    assert (f1[..., 1] <= -0.12 + 1e-6).any()                          # on the floor at some point
    np.testing.assert_allclose(f1, f0, rtol=0, atol=1e-6)
    np.testing.assert_allclose(x1, x0, rtol=0, atol=1e-6)
    np.testing.assert_array_equal(np.asarray(h1.code), np.asarray(h0.code))


def test_chunks_compile_once_and_match_one_batch():
    scene = _ball()
    grid = {"k": [150.0, 200.0, 250.0, 300.0, 350.0]}
    n0 = batched._core_jit._cache_size()
    small = sweep(scene, grid, steps=200, dt=DT, batch=2, progress=False)   # 3 chunks, last one padded
    assert batched._core_jit._cache_size() == n0 + 1
    whole = sweep(scene, grid, steps=200, dt=DT, batch=5, progress=False)
    np.testing.assert_allclose(small.final_positions, whole.final_positions, rtol=0, atol=1e-5)
    assert small.final_positions.shape == (5, scene.n_vertices, 3)
    # each point is the separate simulation with that k
    traj = jaxplush.simulate(scene, 200, DT, 200, params=_point_params(scene, k_structural=[350.0]), check_dt=False)
    np.testing.assert_allclose(small.final_positions[4], traj.positions[-1], rtol=0, atol=1e-5)
    np.testing.assert_allclose(small.volume[4], traj.volumes[-1], rtol=1e-4)


@pytest.fixture(scope="module")
def truth_target():
    from jaxplush.fitting.targets import make_target
    scene = _ball()
    return scene, make_target(scene, 400, DT, 100, frames=[0, 2, 4],
                              params=_point_params(scene, k_structural=[TRUE_K], nmol=[TRUE_NMOL]))


def test_loss_landscape_has_its_minimum_at_the_true_parameters(truth_target):
    scene, target = truth_target
    assert list(target.steps) == [0, 200, 400]                  # a step-0 frame is part of the loss
    res = sweep(scene, {"k": [200.0, TRUE_K, 450.0], "nmol": [1e-3, TRUE_NMOL, 3e-3]}, steps=400, dt=DT,
                target=target, progress=False, batch=4)
    best = res.best()
    assert (best["k_structural"], best["nmol"]) == (TRUE_K, TRUE_NMOL)
    assert best["loss"] < 1e-10 < np.sort(res.loss)[1]
    # one off-truth point against a direct evaluation
    i = 2                                                        # k = 200, nmol = 3e-3
    traj = jaxplush.simulate(scene, 400, DT, 200, params=_point_params(scene, k_structural=[200.0], nmol=[3e-3]),
                             check_dt=False)
    direct = np.mean([np.mean(np.sum((x - y) ** 2, axis=1)) for x, y in zip(traj.positions, target.positions)])
    np.testing.assert_allclose(res.loss[i], direct, rtol=1e-4)


def test_a_point_cloud_padded_with_nan_rows_gives_the_same_losses(truth_target):
    """Frames of different sizes (a depth camera's captures) are padded with NaN rows: padding
    changes no loss, a frame's absent points are left out of it, and a frame left with no points,
    or a partly NaN row, is refused."""
    from jaxplush.fitting.sweep import SweepError
    from jaxplush.fitting.targets import Target
    scene, target = truth_target
    rng = np.random.default_rng(1)
    cloud = np.stack([y[rng.permutation(len(y))] for y in target.positions[1:]])
    padded = np.concatenate([cloud, np.full((len(cloud), 11, 3), np.nan)], axis=1)
    fewer = padded.copy()
    n = cloud.shape[1]
    fewer[0, n - 9:n] = np.nan                                       # frame 0: 9 points fewer
    kw = dict(steps=target.steps[1:], times=target.times[1:], dt=DT, path="<memory>")
    grid = {"nmol": [1e-3, TRUE_NMOL, 3e-3], "k": [TRUE_K]}

    def run(points):
        return sweep(scene, grid, steps=400, dt=DT, progress=False, target=Target(positions=None, points=points, **kw))
    plain, pad, short = run(cloud), run(padded), run(fewer)
    # equal up to float32 rounding
    np.testing.assert_allclose(pad.loss, plain.loss, rtol=1e-5, atol=1e-6 * plain.loss.max())
    traj = jaxplush.simulate(scene, 400, DT, 200, params=_point_params(scene, nmol=[3e-3], k_structural=[TRUE_K]),
                             check_dt=False)
    # the fit's loss (every observed point weighs alike) times its normaliser
    from jaxplush.fitting.objective import losses
    loss = losses.make_loss(Target(positions=None, points=fewer, **kw), jaxplush.make_simulator(scene, DT).topology,
                            jnp.float64)
    d = sum(float(loss.loss_fn(jnp.asarray(x, jnp.float64), jnp.asarray(y, jnp.float64)))
            for x, y in zip(traj.positions[1:], fewer)) * loss.scale2
    np.testing.assert_allclose(short.loss[2], d, rtol=3e-4)
    assert abs(short.loss[2] / plain.loss[2] - 1) > 1e-3             # frame 0's 9 points are gone
    bad = padded.copy()
    bad[1, 0, 2] = np.nan
    with pytest.raises(SweepError, match="absent points are rows of NaN"):
        run(bad)
    bad = padded.copy()
    bad[1] = np.nan
    with pytest.raises(SweepError, match="frame 1 .* holds no points"):
        run(bad)


def test_point_cloud_target_uses_the_fits_distance_to_the_surface(truth_target):
    """A sweep's loss against a scan is the fit's (each point's squared distance to the simulated
    surface), times the fit's normaliser: the same numbers, so the sweep's best point is the fit's."""
    from jaxplush.fitting.objective import losses
    from jaxplush.fitting.targets import Target
    scene, target = truth_target
    # a correspondence-free cloud: the true vertices, shuffled, one frame padded with NaN rows
    rng = np.random.default_rng(0)
    cloud = np.stack([y[rng.permutation(len(y))] for y in target.positions[1:]])
    cloud[0, -5:] = np.nan
    target = Target(positions=None, points=cloud, steps=target.steps[1:], times=target.times[1:], dt=DT,
                    path="<memory>")
    grid = {"nmol": [1e-3, TRUE_NMOL, 3e-3], "k": [TRUE_K]}
    res = sweep(scene, grid, steps=400, dt=DT, target=target, progress=False)
    assert res.target_kind == "points" and res.best()["nmol"] == TRUE_NMOL
    # 0 at the truth up to float32 rounding
    assert res.best()["loss"] < 1e-3 * np.sort(res.loss)[1]
    sim = jaxplush.make_simulator(scene, DT)
    loss = losses.make_loss(target, sim.topology, jnp.float64)
    for i, n in enumerate(grid["nmol"]):
        traj = jaxplush.simulate(scene, 400, DT, 200, params=_point_params(scene, nmol=[n], k_structural=[TRUE_K]),
                                 check_dt=False)
        fit_loss = sum(float(loss.loss_fn(jnp.asarray(x, jnp.float64), jnp.asarray(y, jnp.float64)))
                       for x, y in zip(traj.positions[1:], cloud))
        assert (fit_loss > 0) == (n != TRUE_NMOL)
        np.testing.assert_allclose(res.loss[i], fit_loss * loss.scale2, rtol=3e-4, atol=1e-3 * np.sort(res.loss)[1])


def test_failed_points_are_reported_not_nan(truth_target):
    scene, target = truth_target
    with pytest.warns(UserWarning, match="1 of 3 sweep point"):
        res = sweep(scene, {"k": [200.0, 1e5, TRUE_K]}, steps=400, dt=DT, target=target, progress=False)
    np.testing.assert_array_equal(res.failed, [False, True, False])
    assert np.isnan(res.loss[1]) and np.all(np.isfinite(res.loss[[0, 2]]))
    assert np.all(np.isfinite(res.final_positions)) and res.final_step[1] < res.fail_step[1, 0] <= 400
    assert res.fail_code[1, 0] >= jaxplush.stepping.diagnostics.ERROR and res.fail_step[0, 0] == -1
    assert "1 point(s) failed" in res.table() and "step" in res.table()


def test_save_schema_frames_and_plots(tmp_path, truth_target):
    scene, target = truth_target
    res = sweep(scene, {"k": [200.0, TRUE_K], "nmol": [1e-3, TRUE_NMOL]}, steps=400, dt=DT, target=target,
                save_every=200, progress=False)
    assert res.frames.shape == (3, 4, scene.n_vertices, 3) and list(res.frame_steps) == [0, 200, 400]
    np.testing.assert_array_equal(res.frames[-1], res.final_positions)
    path = tmp_path / "sweep.h5"
    res.save(path)
    assert sorted(os.listdir(tmp_path)) == ["sweep.h5"]           # atomic: no temporary left behind
    d = load_sweep(path)
    assert d["attrs"]["scene"] == scene.text and list(d["attrs"]["labels"]) == ["k_structural", "nmol"]
    assert d["values"].shape == (4, 2) and d["params/k_structural"].shape == (4, 1)
    np.testing.assert_array_equal(d["loss"], res.loss)
    np.testing.assert_array_equal(d["axes/nmol"], [1e-3, TRUE_NMOL])
    for key in ("final_positions", "final_step", "summary/volume", "summary/centroid_height",
                "summary/max_displacement", "failure/code", "failure/step", "frames", "faces"):
        assert key in d
    assert res.plot(tmp_path / "map.png") == os.fspath(tmp_path / "map.png")
    one = sweep(scene, {"k": [200.0, TRUE_K]}, steps=400, dt=DT, progress=False)
    one.plot(tmp_path / "curve.png")                              # no target: the final volume
    assert (tmp_path / "map.png").stat().st_size > 1000 and (tmp_path / "curve.png").stat().st_size > 1000
    with pytest.raises(ValueError, match="no target"):
        one.quantity("loss")


def test_parse_grid_spec():
    np.testing.assert_allclose(parse_grid_spec("k=100:1000:4")[1], [100, 400, 700, 1000])
    np.testing.assert_allclose(parse_grid_spec("nmol=0.001:0.1:3", log=True)[1], [1e-3, 1e-2, 1e-1])
    assert parse_grid_spec("k@ball=1,2.5")[0] == "k@ball"
    np.testing.assert_array_equal(parse_grid_spec("k@ball=1,2.5")[1], [1.0, 2.5])
    for bad in ("k", "k=", "k=1:2", "k=1:2:0", "k=a:2:3", "k=1,x", "k=1:2:3.5"):
        with pytest.raises(ValueError):
            parse_grid_spec(bad)
    with pytest.raises(ValueError, match="--log"):
        parse_grid_spec("k=0:1:3", log=True)


def test_cli_writes_sweep_and_rejects_bad_input(tmp_path, truth_target, capsys):
    scene, target = truth_target
    obj = tmp_path / "ball.obj"
    obj.write_text(scene.text)
    tgt = tmp_path / "target.h5"
    target.save(tgt, scene)
    out, png = tmp_path / "out.h5", tmp_path / "out.png"
    rc = sweep_main([str(obj), "--grid", f"k={TRUE_K},450", "--grid", f"nmol={TRUE_NMOL}", "--target", str(tgt),
                     "--steps", "400", "--out", str(out), "--plot", str(png), "--quiet"])
    text = capsys.readouterr().out
    assert rc == 0 and out.exists() and png.exists()
    assert f"minimum: k_structural = {TRUE_K:g}" in text
    bad = tmp_path / "bad.h5"
    wrong = tmp_path / "wrong.h5"                                  # a target of another mesh
    with h5py.File(wrong, "w") as f:
        f["positions"] = np.zeros((1, 12, 3))
        f["times"] = [0.08]
        f.attrs["dt"] = DT
    for argv, msg in [
        ([str(obj), "--grid", "k=1:2:x", "--steps", "10", "--dt", "1e-4"], "integer"),
        ([str(obj), "--grid", "spring=1", "--steps", "10", "--dt", "1e-4"], "unknown parameter"),
        ([str(tmp_path / "none.obj"), "--grid", "k=1", "--steps", "10", "--dt", "1e-4"], "no such file"),
        ([str(obj), "--grid", "k=1", "--steps", "10"], "--dt is required"),
        ([str(obj), "--grid", "k=1", "--steps", "400", "--target", str(wrong)], "wrong.h5"),
        ([str(obj), "--grid", "k=1", "--steps", "10", "--target", str(tgt)], "--steps is 10"),
    ]:
        rc = sweep_main(argv + ["--out", str(bad), "--quiet"])
        err = capsys.readouterr().err
        assert rc == 2 and msg in err and "Traceback" not in err, (argv, err)
        assert not bad.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ball.obj", "out.h5", "out.png", "target.h5",
                                                           "wrong.h5"]


def test_failed_points_frames_hold_no_nan():
    # a point that blows up at step ~11: its saved frames after its last healthy step repeat its
    # final (last healthy) positions instead of the blown-up NaN state; the others are untouched
    scene = _ball()
    with pytest.warns(UserWarning, match="1 of 2 sweep point"):
        res = sweep(scene, {"k": [200.0, 1e5]}, steps=100, dt=DT, save_every=20, progress=False)
    assert list(res.failed) == [False, True] and list(res.frame_steps) == [0, 20, 40, 60, 80, 100]
    assert np.all(np.isfinite(res.frames))
    np.testing.assert_array_equal(res.frames[-1], res.final_positions)
    after = res.frame_steps > res.final_step[1]
    assert after.sum() >= 4
    np.testing.assert_array_equal(res.frames[after, 1],
                                  np.broadcast_to(res.final_positions[1], res.frames[after, 1].shape))
    traj = jaxplush.simulate(scene, 100, DT, 20, params=_point_params(scene, k_structural=[200.0]), check_dt=False)
    np.testing.assert_allclose(res.frames[:, 0], traj.positions, rtol=0, atol=1e-5)


def test_heat_map_sorts_axes_given_in_any_order():
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    scene = _ball(subdivisions=0)
    res = sweep(scene, {"k": [300.0, 100.0, 200.0], "total_weight": [0.08, 0.04]}, steps=20, dt=DT, progress=False)
    fig, ax = plt.subplots()
    try:
        res.plot(ax, quantity="centroid_height")
        mesh = ax.collections[0]
        z = np.asarray(mesh.get_array()).reshape(2, 3)                    # rows: total_weight, cols: k
    finally:
        plt.close(fig)
    edges = mesh.get_coordinates()                                        # (3, 4, 2) cell corners
    assert np.all(np.diff(edges[0, :, 0]) > 0) and np.all(np.diff(edges[:, 0, 1]) > 0)
    q = res.quantity("centroid_height")
    for i, w in enumerate([0.04, 0.08]):
        for j, k in enumerate([100.0, 200.0, 300.0]):
            p = int(np.nonzero((res.values[:, 0] == k) & (res.values[:, 1] == w))[0][0])
            assert z[i, j] == pytest.approx(q[p], rel=1e-6)


@pytest.mark.heavy
def test_large_sweeps_pad_less_than_one_chunk_per_batch(monkeypatch):
    # 49 points with batch 48 ran as two batches of 48 (47 copies of the last point); now two
    # equal batches of 32 (two 16-point chunks each), the same results as one 49-point batch
    assert sweep_mod._outer_batch(65, 64) == 48 and sweep_mod._outer_batch(49, 48) == 32
    assert sweep_mod._outer_batch(64, 64) == 64 and sweep_mod._outer_batch(17, 64) == 17
    for n, b in ((65, 64), (100, 64), (130, 64), (49, 48), (20, 16), (1000, 64)):
        ob = sweep_mod._outer_batch(n, b)
        n_outer = -(-n // b)
        assert ob <= b and -(-n // ob) == n_outer                       # no more batches than before
        assert n_outer * ob - n < n_outer * batched.default_chunk(ob)  # less than a chunk of padding each
    scene = _ball(subdivisions=0)
    built = []
    make = batched.make_batched_simulator
    monkeypatch.setattr(batched, "make_batched_simulator", lambda *a, **kw: built.append(a[2]) or make(*a, **kw))
    grid = {"k": np.linspace(100.0, 400.0, 7), "total_weight": np.linspace(0.04, 0.1, 7)}
    split = sweep(scene, grid, steps=30, dt=DT, batch=48, progress=False)
    whole = sweep(scene, grid, steps=30, dt=DT, batch=64, progress=False)
    assert built == [32, 49]
    np.testing.assert_allclose(split.final_positions, whole.final_positions, rtol=0, atol=1e-6)
    p = _point_params(scene, k_structural=[400.0], total_weight=[0.1])
    traj = jaxplush.simulate(scene, 30, DT, 30, params=p, check_dt=False)
    np.testing.assert_allclose(split.final_positions[48], traj.positions[-1], rtol=0, atol=1e-6)


def test_cli_rejects_unplottable_grids_and_empty_ranges(tmp_path, capsys):
    obj = tmp_path / "ball.obj"
    obj.write_text(icosphere_text(subdivisions=0, nmol=1e-3))
    out = tmp_path / "out.h5"
    common = ["--steps", "10", "--dt", "1e-4", "--out", str(out), "--quiet"]
    cases = [
        ([str(obj), "--grid", "k=1,2", "--grid", "nmol=1e-3,2e-3", "--grid", "drag=0,1",
          "--plot", str(tmp_path / "p.png")], "one or two swept parameters"),
        ([str(obj), "--grid", "k=100:200:1"], "one value cannot run from 100 to 200"),
        ([str(obj), "--grid", "k=100:100:3"], "all be 100"),
        ([str(obj), "--grid", "k=100,200,100"], "distinct"),
    ]
    for argv, msg in cases:
        rc = sweep_main(argv + common)
        err = capsys.readouterr().err
        assert rc == 2 and msg in err and "Traceback" not in err, (argv, err)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ball.obj"]


def test_target_frames_must_be_strictly_increasing(truth_target):
    # two frames at one step would share one slot of the per-frame loss table (one frame's loss
    # lost, yet counted in the mean): refused before anything runs
    from jaxplush.fitting.targets import Target
    scene, target = truth_target
    dup = Target(positions=target.positions[[1, 1, 2]], points=None, steps=target.steps[[1, 1, 2]],
                 times=target.times[[1, 1, 2]], dt=DT, path="<memory>")
    with pytest.raises(SweepError, match="strictly increasing"):
        sweep(scene, {"k": [200.0]}, steps=400, dt=DT, target=dup, progress=False)
