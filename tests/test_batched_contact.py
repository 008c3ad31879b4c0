"""Soft-soft contact in the batched engine (jaxplush.stepping.batched): the single-scene contact under
``jax.vmap``, each point carrying its own candidate lists.

A batch of points of a two-ball collision must give, point for point, the frames of separate
``jaxplush.simulate`` runs (to float32 rounding, relative to the positions' size; to 1e-10 in
float64), and the balls must really touch. A point whose candidates overflow their capacity gets
the health code CONTACT_OVERFLOW for that object, as in a single-scene rollout, without touching
the other points; the default fit's Evaluator takes the batched path for such scenes, grows the
capacity on an overflow, and its losses are those of its one-point-at-a-time path.
"""

from __future__ import annotations

import dataclasses
import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxplush.errors import ContactCapacityWarning

import jaxplush
from jaxplush.stepping import batched
from jaxplush.model import contact
from jaxplush.stepping import diagnostics
from test_contact import two_balls

DT = 2e-4
SCENES = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "scenes")


def _thrown(gap=0.04, extra_scene=""):
    """Two 42-vertex balls 4 cm apart thrown at each other (2 m/s closing, off-centre), no gravity:
    they meet after about 100 steps."""
    scene, n = two_balls(sub=1, gap=gap, extra_scene=extra_scene)
    v0 = np.zeros((2 * n, 3))
    v0[:n, 0], v0[n:, 0] = 1.0, -1.0
    v0[n:, 1] = 0.3
    return scene, n, v0


POINTS = [dict(k_structural=[150.0, 200.0]),
          dict(k_structural=[300.0, 120.0], nmol=[2e-3, 1e-3]),
          dict(k_structural=[200.0, 400.0], total_weight=[0.08, 0.04])]


def _points(scene):
    return [scene.params._replace(**{k: np.asarray(v, np.float64) for k, v in p.items()}) for p in POINTS]


def _batched_frames(scene, points, v0, steps, every):
    bsim = batched.make_batched_simulator(scene, DT, len(points))
    assert bsim.coherent is not None                       # candidate lists carried per point
    pb = bsim.params(jaxplush.Params(*(np.stack(a, axis=1) for a in zip(*points))))
    final, frames, health = batched.rollout(bsim, pb, bsim.init_fn(pb, None, v0), steps // every, every,
                                            observe=batched.positions_observer)
    assert not health.failed.any()
    frames = np.asarray(frames)                            # (T, B, V, 3)
    np.testing.assert_array_equal(batched.positions(final), frames[-1])
    return bsim, frames


def _check_against_simulate(scene, n, v0, tol, steps=400, every=50):
    """Batched frames of the three POINTS against separate simulate runs; the balls touch."""
    points = _points(scene)
    bsim, frames = _batched_frames(scene, points, v0, steps, every)
    sim = jaxplush.make_simulator(scene, DT)
    assert sim.terms == bsim.terms and sim.terms.contact
    force = jax.jit(contact.make_contact_force(sim.topology, sim.terms.contact, DT))
    for b, p in enumerate(points):
        traj = jaxplush.simulate(scene, steps, DT, every, params=p, v0=v0, check_dt=False, sim=sim)
        ref = traj.positions[1:]
        err = np.linalg.norm(frames[:, b] - ref) / np.linalg.norm(ref)
        assert err < tol, (b, err)
        # they touch: the contact force at some saved frame is large (vs about none at the start)
        v = jnp.zeros((3, 2 * n), sim.dtype)
        f = [float(jnp.abs(force(sim.params(p), jnp.asarray(x.T, sim.dtype), v)).max())
             for x in traj.positions]
        assert max(f) > 1.0 and f[0] < 1e-3 * max(f), (b, f)
        # and bounce: ball a ends moving back (-x)
        assert ref[-1, :n, 0].mean() < ref[-2, :n, 0].mean()


@pytest.mark.heavy   # the default run covers batched contact by the sweep and evaluator tests
def test_batched_contact_matches_separate_simulate_runs_float32():
    scene, n, v0 = _thrown()
    # two differently vectorised programs: float32 rounding apart (a wrong force is off by far more)
    _check_against_simulate(scene, n, v0, 1e-4)


@pytest.mark.heavy
def test_batched_contact_matches_separate_simulate_runs_float64(x64):
    scene, n, v0 = _thrown()
    _check_against_simulate(scene, n, v0, 1e-10)


@pytest.mark.parametrize("dt", [5e-4, 2e-4])
def test_carried_lists_of_a_fast_impact_equal_a_fresh_search_every_step(x64, dt):
    """Two 42-vertex balls 30 cm apart (beyond the broad phase's reach: the lists start empty)
    thrown at each other at 1.5 m/s each (0.75-1.5 mm closing a step) meet and bounce. The
    single-scene rollout and both points of a batch (the scene's k and a softer one), all carrying
    their candidate lists, give the frames of a fresh search every step (``jax.jit(sim.step_fn)``)
    to float64 rounding; a stale test that missed vertices coming near the other object would
    let the balls pass through each other.

    Ball b is offset by 1 mm/0.7 mm off the line of flight. Head-on, the setup is
    mirror-symmetric and the contact dents ball b's front, so a query vertex on the mirror plane
    lies at exactly the same distance from two mirror faces whose closest points are interior and
    whose normals differ: which face wins is decided by rounding, which differs between
    separately compiled programs (a per-step jit, a rollout's scan, the batched engine, with or
    without carried lists alike), and the runs part by about 1e-5 m within 15-30 steps."""
    scene, n = two_balls(sub=1, gap=0.3, k=100.0, nmol=1e-3, b_offset=(0.0, 1e-3, 7e-4))
    v0 = np.zeros((2 * n, 3))
    v0[:n, 0], v0[n:, 0] = 1.5, -1.5
    steps = int(round(0.135 / dt))
    sim = jaxplush.make_simulator(scene, dt)
    assert sim.internal.coherent is not None
    points = [scene.params, scene.params._replace(k_structural=0.6 * np.asarray(scene.params.k_structural))]
    step = jax.jit(sim.step_fn)
    fresh = []
    for p in map(sim.params, points):
        state = sim.init_fn(p, None, v0)
        frames = []
        for _ in range(steps):
            state = step(p, state)
            frames.append(np.asarray(state.x))
        fresh.append(np.asarray(frames))
    # they meet and bounce: ball a ends moving back (-x)
    assert fresh[0][-1, :n, 0].mean() < fresh[0][-2, :n, 0].mean()
    single = jaxplush.simulate(scene, steps, dt, 1, v0=v0, check_dt=False, sim=sim).positions[1:]
    bsim = batched.make_batched_simulator(scene, dt, len(points))
    assert bsim.coherent is not None
    pb = bsim.params(jaxplush.Params(*(np.stack(a, axis=1) for a in zip(*[np.asarray(x, np.float64) for x in points]))))
    _, frames, health = batched.rollout(bsim, pb, bsim.init_fn(pb, None, v0), steps, 1,
                                        observe=batched.positions_observer)
    assert not health.failed.any()
    frames = np.asarray(frames)
    for name, run, ref in (("simulate", single, fresh[0]), ("batched point 0", frames[:, 0], fresh[0]),
                           ("batched point 1", frames[:, 1], fresh[1])):
        err = np.linalg.norm(run - ref, axis=(1, 2)) / np.linalg.norm(ref, axis=(1, 2))
        assert err.max() < 1e-10, (name, int(np.argmax(err > 1e-10)) + 1, err.max())


@pytest.mark.heavy
def test_batched_contact_friction_and_self_collision_match_simulate():
    scene, n, v0 = _thrown(extra_scene="contact_friction 0.5\nself_collision on\n")
    assert scene.contact_friction == 0.5 and scene.self_collision
    _check_against_simulate(scene, n, v0, 1e-4)


def _overlapping_and_apart(n_points=3):
    """Two overlapping 42-vertex balls whose candidates overflow object a's capacity (4); the
    batch's point 1 starts with ball b 0.5 m away (no candidates), the others overlapping."""
    scene, n = two_balls(sub=1, gap=-0.005)
    base = jaxplush.make_simulator(scene, 1e-4)
    terms = dataclasses.replace(base.terms, contact=dataclasses.replace(base.terms.contact, capacity=(4, n)))
    x0 = np.repeat(scene.vertices[None], n_points, axis=0)
    x0[1, n:, 0] += 0.5
    return scene, n, terms, x0


@pytest.mark.heavy   # CI's second tier (the single-scene overflow code is checked in the default run)
def test_an_overflowing_point_reports_contact_overflow_and_leaves_the_others():
    scene, n, terms, x0 = _overlapping_and_apart()
    bsim = batched.make_batched_simulator(scene, 1e-4, 3, terms=terms)
    pb = bsim.params()
    state = bsim.init_fn(pb, x0)
    final, frames, health = batched.rollout(bsim, pb, state, 3, 5, observe=batched.positions_observer)
    assert np.isfinite(np.asarray(frames)).all()
    over, ok = diagnostics.CONTACT_OVERFLOW, diagnostics.OK
    np.testing.assert_array_equal(np.asarray(health.code), [[over, ok, over], [ok, ok, ok]])
    np.testing.assert_array_equal(np.asarray(health.bad_step), [[5, -1, 5], [-1, -1, -1]])   # the first saved frame
    np.testing.assert_array_equal(health.failed, [True, False, True])
    # as a single-scene rollout of the same point reports it, and the located step is the first
    sim = jaxplush.make_simulator(scene, 1e-4, terms=terms)
    p = sim.params()
    _, _, h1 = jaxplush.rollout(sim, p, sim.init_fn(p, x0[0]), 3, 5)
    np.testing.assert_array_equal(np.asarray(h1.code), np.asarray(health.code)[:, 0])
    step, code = batched.locate_failures(bsim, pb, health)
    np.testing.assert_array_equal(step, [[1, -1, 1], [-1, -1, -1]])
    np.testing.assert_array_equal(code[0], [over, ok, over])
    # status_fn reports a state whose fresh search overflows, per point
    np.testing.assert_array_equal(np.asarray(jax.jit(bsim.status_fn)(pb, state.x)), [[over, ok, over], [ok, ok, ok]])


def _pressed_problem(capacity=None, sub=1):
    """A fit of both balls' k to a target of two overlapping balls pushing apart (no gravity)."""
    from jaxplush.fitting import fitter as F
    from jaxplush.fitting.targets import make_target
    head = "" if capacity is None else f"contact_capacity {capacity}\n"
    scene, n = two_balls(sub=sub, gap=-0.006, extra_scene=head)
    truth, _ = two_balls(sub=sub, gap=-0.006)
    target = make_target(truth, 200, DT, 25)
    return F.build_problem(scene, target, ("k_structural",), objects=["a", "b"])


def test_evaluator_runs_contact_scenes_batched_with_the_single_paths_losses():
    from jaxplush.fitting.objective.evaluate import Evaluator
    prob = _pressed_problem()
    thetas = np.asarray(prob.theta0)[None] + np.array([0.3, -0.3, 0.5])[:, None, None] * np.array([[[1.0, -0.5]]])
    ev = Evaluator(prob, calibrate=False)
    assert ev.batched
    single = Evaluator(prob, calibrate=False)
    single.batched = False
    e_b, e_s = ev(thetas, keep_frames=True), single(thetas, keep_frames=True)
    assert e_b.ok.all() and e_s.ok.all()
    # carried candidate lists against a search every step, in two programs: float32 rounding apart
    for fb, fs in zip(e_b.frames, e_s.frames):
        assert np.linalg.norm(fb - fs) <= 1e-4 * np.linalg.norm(fs)
    assert np.all(e_b.loss > 0)
    np.testing.assert_allclose(e_b.loss, e_s.loss, rtol=1e-3)


@pytest.mark.heavy
def test_evaluator_grows_the_capacity_of_overflowing_batched_points():
    from jaxplush.fitting.objective.evaluate import Evaluator
    prob = _pressed_problem(capacity=4)
    ev = Evaluator(prob, calibrate=False)
    # the fit's headroom: twice the scene's capacity (still too few here)
    assert ev.batched and max(prob.sim.terms.contact.capacity) == 8
    thetas = np.asarray(prob.theta0)[None] + np.array([0.0, 0.3])[:, None, None]
    with pytest.warns(UserWarning, match=r"contact candidates overflowed \(capacity 8\).*contact_capacity"):
        e = ev(thetas, keep_frames=True)
    assert e.ok.all() and np.isfinite(e.loss).all() and len(ev.notes) == 1
    assert max(ev.prob.sim.terms.contact.capacity) > 8
    # the grown run is the run of a scene with that capacity from the start
    big = _pressed_problem(capacity=max(ev.prob.sim.terms.contact.capacity))
    ref = Evaluator(big, calibrate=False)(thetas, keep_frames=True)
    assert np.linalg.norm(e.frames - ref.frames) <= 1e-4 * np.linalg.norm(ref.frames)


def test_sweep_of_a_contact_scene_matches_simulate():
    from jaxplush.fitting.sweep import sweep
    # (a sweep starts every point at rest: two overlapping balls pushing apart)
    scene, n = two_balls(sub=1, gap=-0.006)
    res = sweep(scene, {"k": [150.0, 300.0]}, steps=200, dt=DT, progress=False)
    assert not res.fail_code.any()
    for i, k in enumerate((150.0, 300.0)):
        p = scene.params._replace(k_structural=np.array([k, k]))
        traj = jaxplush.simulate(scene, 200, DT, 200, params=p, check_dt=False)
        ref = traj.positions[-1]
        assert np.linalg.norm(res.final_positions[i] - ref) <= 1e-4 * np.linalg.norm(ref)
        assert np.abs(ref - scene.vertices).max() > 1e-3                 # contact pushed them apart


@pytest.mark.heavy
def test_a_gradient_fit_grows_the_capacity_and_evaluates_the_point_again():
    # the gradient fit's stage (jaxplush.fitting.stages.gradfit.Gradient) asks its objective to grow
    # the capacity after an overflow, and evaluates the same point again: no step is lost to it
    from jaxplush.fitting import fitter as F
    from jaxplush.fitting.targets import make_target
    scene, _ = two_balls(sub=1, gap=-0.006, extra_scene="contact_capacity 4\n")
    truth, _ = two_balls(sub=1, gap=-0.006)
    target = make_target(truth, 200, DT, 25)
    with pytest.warns(UserWarning, match=r"contact candidates overflowed \(capacity 8\).*contact_capacity") as rec:
        res = F.fit(scene, target, ("k_structural",), objects=["a", "b"], optimizer="adam", iterations=3,
                    predictability=False, identifiability=False)
    grown = [w for w in rec if "overflowed" in str(w.message)]
    assert grown and all(w.filename == __file__ for w in grown)       # pointed at the caller
    assert any(w.category is ContactCapacityWarning for w in res.warnings if hasattr(w, "category"))
    assert max(res.problem.sim.terms.contact.capacity) > 8
    assert res.iterations == 3 and res.rejected == 0 and np.isfinite(res.loss)


def _pieces(bsim, pb, v0, pieces, pad_to, separation):
    """Frames, final state, health and closest separation of a rollout run in ``pieces`` [(frames,
    steps per frame), ...], each piece its own program (``pad_to`` None) or all of them one
    program of ``pad_to`` frames with their lengths and spacings as data."""
    state = bsim.init_fn(pb, None, v0)
    health, done, frames, closest = batched.initial_health(bsim, state), 0, [], np.inf
    for n, every in pieces:
        state, obs, health, *sep = batched.rollout(bsim, pb, state, n, every, health=health, step0=done,
                                                   observe=batched.positions_observer, separation=separation,
                                                   pad_to=pad_to)
        assert np.shape(obs)[0] == (pad_to or n)
        frames.append(np.asarray(obs)[:n])
        closest = np.minimum(closest, np.asarray(sep[0])) if separation else closest
        done += n * every
    return np.concatenate(frames), state, health, closest


def test_pieces_of_any_length_and_spacing_run_one_padded_program_with_the_same_results():
    """A run cut into pieces of different lengths and frame spacings (a fit's horizons in chunks,
    a last frame closer to the one before) runs one compiled program with ``pad_to``: frames,
    state, health and contact separations are those of one program per piece (to rounding; the
    frames past a short piece run no step), through a soft-soft impact."""
    scene, n, v0 = _thrown()
    bsim = batched.make_batched_simulator(scene, DT, 3, chunk=3)
    pb = bsim.params(jaxplush.Params(*(np.stack(a, axis=1) for a in zip(*_points(scene)))))
    pieces = [(4, 30), (4, 30), (3, 30), (1, 17)]            # 347 steps: the balls meet after ~100
    ref = _pieces(bsim, pb, v0, pieces, None, True)
    n0 = batched._core_jit._cache_size()
    got = _pieces(bsim, pb, v0, pieces, 4, True)
    assert batched._core_jit._cache_size() <= n0 + 1          # one program for the four pieces
    # the same operations (bit for bit on this machine; another CPU may round two programs apart)
    scale = np.abs(ref[0]).max()
    np.testing.assert_allclose(got[0], ref[0], rtol=0, atol=1e-6 * scale)
    np.testing.assert_allclose(batched.positions(got[1]), batched.positions(ref[1]), rtol=0, atol=1e-6 * scale)
    for a, b in zip(jax.tree_util.tree_leaves(got[2]), jax.tree_util.tree_leaves(ref[2])):
        a, b = np.asarray(a), np.asarray(b)
        if np.issubdtype(a.dtype, np.integer):
            np.testing.assert_array_equal(a, b)               # codes and steps
        else:
            np.testing.assert_allclose(a, b, rtol=0, atol=1e-6 * scale)
    np.testing.assert_allclose(got[3], ref[3], rtol=0, atol=1e-6 * scale)
    reach = 2 * np.max(bsim.terms.contact.thickness)
    assert np.asarray(ref[2].good_step).tolist() == [347] * 3 and (ref[3] < reach).all()   # ran through, met


def test_a_padded_piece_of_a_driven_scene_reads_the_path_step_by_step():
    """With driven vertices, a padded program reads the path's rows step by step (its spacing is
    data): the same frames as the program that reads them frame by frame."""
    scene = jaxplush.load_scene(os.path.join(SCENES, "lifted.obj"))
    bsim = batched.make_batched_simulator(scene, 4e-4, 2, chunk=2)
    assert bsim.drive is not None
    pb = bsim.params(jaxplush.Params(*(np.stack([np.asarray(a, np.float64)] * 2, axis=-1) for a in scene.params)))
    pieces = [(3, 25), (2, 25), (1, 10)]
    ref, got = _pieces(bsim, pb, None, pieces, None, False), _pieces(bsim, pb, None, pieces, 3, False)
    np.testing.assert_allclose(got[0], ref[0], rtol=0, atol=1e-6 * np.abs(ref[0]).max())
    assert np.abs(ref[0][-1] - ref[0][0]).max() > 1e-3                     # the path moved it


def test_a_target_whose_last_frame_is_closer_runs_one_rollout_program_in_one_piece_or_in_chunks():
    """A target whose last frame is closer to the one before (190 steps saved every 25: runs of
    7 frames 25 steps apart and 1 frame 15 after) runs on one compiled rollout per evaluator,
    whole or in chunks of 3 frames, and both give the losses and frames of the target's steps."""
    from jaxplush.fitting import fitter as F
    from jaxplush.fitting.objective.evaluate import Evaluator
    from jaxplush.fitting.targets import make_target
    scene, _ = two_balls(sub=1, gap=-0.006)
    prob = F.build_problem(scene, make_target(scene, 190, DT, 25), ("k_structural",), objects=["a", "b"])
    assert len(set(np.diff(np.concatenate([[0], prob.loss.frame_steps])))) == 2
    thetas = np.asarray(prob.theta0)[None] + np.array([0.0, 0.3, -0.3])[:, None, None]
    n0 = batched._core_jit._cache_size()
    whole = Evaluator(prob, calibrate=False)(thetas, keep_frames=True)
    assert batched._core_jit._cache_size() <= n0 + 1
    n1 = batched._core_jit._cache_size()
    pieces = Evaluator(prob, calibrate=False, chunk_frames=3)(thetas, keep_frames=True)
    assert batched._core_jit._cache_size() <= n1 + 1
    assert whole.ok.all() and pieces.ok.all() and np.ptp(whole.loss) > 0
    scale = np.abs(whole.frames).max()
    assert np.abs(pieces.frames - whole.frames).max() <= 1e-6 * scale
    np.testing.assert_allclose(pieces.loss, whole.loss, rtol=1e-4)
    # the frames are the target's: the last, 15 steps after the one before, is where the truth is
    truth = Evaluator(prob, calibrate=False)(np.asarray(prob.theta0)[None], keep_frames=True).frames[0]
    np.testing.assert_allclose(truth[-1], np.asarray(prob.target.positions)[-1], atol=1e-5 * scale)


def _damped_pair_on_a_floor():
    """Two 42-vertex balls dropped side by side onto a floor with friction, thrown at each other,
    with contact friction and the report's damping on one: every term whose step reads the
    substep length h or the substep count."""
    from conftest import icosphere_text
    n = 42
    text = "floor_friction 0.3\ncontact_friction 0.5\n"
    text += icosphere_text(1, floor=-0.12, translate=(-0.11, 0, 0), name="a", k=200.0, damping=300.0, nmol=1e-3)
    text += icosphere_text(1, translate=(0.11, 0.02, 0), name="b", k=250.0, nmol=1e-3, offset=n, header=False)
    v0 = np.zeros((2 * n, 3))
    v0[:n, 0], v0[n:, 0] = 1.5, -1.5
    return jaxplush.parse_scene(text, "<damped pair>"), n, v0


def test_the_substep_count_as_data_runs_every_count_on_one_program_with_the_fixed_counts_frames():
    """Issue 52 (few programs per fit): a batched simulator built with ``substeps=None`` takes the
    count per call. 1, 2 and 4 substeps run on one compiled rollout and one compiled init, and
    each gives the frames of the simulator built for that count, to rounding, through a floor
    landing with friction, a soft-soft impact with contact friction and the report's damping."""
    from conftest import compiles
    scene, n, v0 = _damped_pair_on_a_floor()
    terms = batched.terms_for(scene)
    assert terms.contact and terms.contact.friction > 0 and terms.floor_friction and terms.verlet_damping
    dyn = batched.make_batched_simulator(scene, DT, 3, substeps=None, chunk=3)
    assert dyn.substeps is None and dyn.at_substeps is not None
    pb = dyn.params(jaxplush.Params(*(np.stack(a, axis=1) for a in zip(*_points(scene)))))
    x0 = np.asarray(dyn.topology.x0)
    got = {}
    with compiles() as seen:
        for k in (1, 2, 4):
            state = dyn.init_fn(pb, None, v0, substeps=k)
            _, frames, health, sep = batched.rollout(dyn, pb, state, 6, 60, observe=batched.positions_observer,
                                                     separation=True, substeps=k)
            assert not np.asarray(health.failed).any()
            got[k] = np.asarray(frames), np.asarray(sep)
    programs = [x for x in seen if x.startswith("Compiling ")]
    assert sum(x.startswith("Compiling jit(_core)") for x in programs) == 1, programs
    assert sum(x.startswith("Compiling jit(init") for x in programs) <= 1, programs
    reach = 2 * np.max(dyn.terms.contact.thickness)
    for k in (1, 2, 4):
        fixed = batched.make_batched_simulator(scene, DT, 3, substeps=k, chunk=3)
        _, ref, _, sep = batched.rollout(fixed, pb, fixed.init_fn(pb, None, v0), 6, 60,
                                         observe=batched.positions_observer, separation=True, pad_to=6)
        ref, sep = np.asarray(ref), np.asarray(sep)
        motion = np.linalg.norm(ref - x0)
        assert np.linalg.norm(got[k][0] - ref) <= 1e-5 * motion, (k, np.linalg.norm(got[k][0] - ref) / motion)
        assert (sep < reach).all() and np.all(np.abs(got[k][1] - sep) <= 1e-5 * reach)      # they met
        assert ref[-1, :, :n, 1].min() < -0.11                                                # a landed
    # the counts differ by the time discretisation only: each halving moves the frames less
    d12, d24 = (np.linalg.norm(got[a][0] - got[b][0]) for a, b in ((1, 2), (2, 4)))
    assert 0 < d24 < d12


def test_the_substep_count_as_data_is_refused_where_it_cannot_hold():
    """A driven scene's paths are tabulated per substep length: it needs a fixed count. A simulator
    with a fixed count refuses another one, and one with the count as data requires it."""
    driven = jaxplush.load_scene(os.path.join(SCENES, "lifted.obj"))
    with pytest.raises(ValueError, match="driven vertices needs a fixed substep count"):
        batched.make_batched_simulator(driven, 4e-4, 2, substeps=None)
    scene, n, v0 = _thrown()
    fixed = batched.make_batched_simulator(scene, DT, 2, substeps=2)
    pb = fixed.params()
    with pytest.raises(ValueError, match="runs 2 substeps per step"):
        batched.rollout(fixed, pb, fixed.init_fn(pb), 1, 5, substeps=1)
    dyn = batched.make_batched_simulator(scene, DT, 2, substeps=None)      # the count is not guessed
    with pytest.raises(ValueError, match="takes its substep count per call"):
        batched.rollout(dyn, pb, dyn.init_fn(pb, substeps=2), 1, 5)


def test_the_evaluators_points_at_more_substeps_run_the_same_program():
    """The fit's evaluator runs the points the stability limit sends to more substeps on the
    program the others run: one compiled rollout and init for two counts, each point's losses
    those of the count it ran at."""
    from conftest import compiles
    from jaxplush.fitting.objective.evaluate import Evaluator
    prob = _pressed_problem()
    thetas = np.asarray(prob.theta0)[None] + np.array([0.0, 0.2])[:, None, None]
    ev = Evaluator(prob, calibrate=False)
    with compiles() as seen:
        e = ev(thetas, substeps=np.array([1, 2]), keep_frames=True)
        e2 = ev(thetas, substeps=np.array([2, 1]), keep_frames=True)
    assert e.ok.all() and e.substeps.tolist() == [1, 2] and e2.substeps.tolist() == [2, 1]
    # one simulator (a static argument of the compiled rollout: one per program) for both counts;
    # compiled here at most once (another test of this bucket may have compiled it already)
    assert len({id(bsim) for bsim, _ in ev._bsims.values()}) == 1
    programs = [x for x in seen if x.startswith("Compiling jit(_core)")]
    assert len(programs) <= 1, programs
    # a point's frames at 1 and at 2 substeps differ by the time discretisation, which is small
    scale = np.linalg.norm(e.frames[0] - prob.scene.vertices)
    for i in range(2):
        assert 0 < np.linalg.norm(e.frames[i] - e2.frames[i]) <= 1e-2 * scale


@pytest.mark.parametrize("vertices, dashpot, wide, narrow_calls", [
    (324, False, 4, False),        # small contact scenes: chunks of 4, one simulator for every call
    (964, False, 16, True),        # from CONTACT_WIDE_MESH up: chunks of 16, few points on a narrow one
    (1282, True, 16, True),
])
def test_contact_scenes_from_the_wide_mesh_size_run_chunks_of_16_and_few_points_narrow(
        monkeypatch, vertices, dashpot, wide, narrow_calls):
    """The evaluator's chunk rule with soft-soft contact (Evaluator._chunk): a contact scene of
    CONTACT_WIDE_MESH to LARGE_MESH vertices runs its full calls in chunks of 16 points (its
    contact term costs about half as much per point-step as in chunks of 4), and a call of a few
    points on a narrow simulator of chunks of 4, at one substep or more; a smaller contact scene
    keeps chunks of 4 and its one simulator for every call. No simulation runs here."""
    import types
    from jaxplush.fitting.objective import evaluate
    monkeypatch.setattr(batched.jax, "default_backend", lambda: "cpu")
    ev = evaluate.Evaluator.__new__(evaluate.Evaluator)
    ev.prob = types.SimpleNamespace(scene=types.SimpleNamespace(n_vertices=vertices),
                                    sim=types.SimpleNamespace(terms=types.SimpleNamespace(dashpot=dashpot)))
    ev._contact, ev.batch = True, evaluate.DEFAULT_BATCH
    assert (vertices >= evaluate.CONTACT_WIDE_MESH) == (wide == 16)
    assert ev._chunk_of(ev.batch) == wide
    narrow = ev.batch // 4
    assert ev._width(3) == (narrow if narrow_calls else ev.batch)
    assert ev._width(ev.batch) == ev.batch and ev._width(narrow + 1) == ev.batch
    assert ev._width(ev.batch, n=2) == (narrow if narrow_calls else ev.batch)
    if narrow_calls:
        assert ev._chunk_of(narrow) == 4
    ev._contact = False               # without contact: 8 with a dashpot, 16 without (unchanged)
    assert ev._chunk_of(ev.batch) == (8 if dashpot else 16)
