"""The per-object global stage (jaxplush.fitting.stages.objects): residual blocks belong to the right
objects, scoring each object's parameters by its own residuals finds better candidates than the
full-dimensional Sobol design with as many runs, and the stage hands its candidates to
Levenberg-Marquardt through run_stages."""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np
import pytest
import trimesh

import jaxplush
from jaxplush.fitting import fitter as F
from jaxplush.fitting import stages
from jaxplush.fitting.stages import lmfit, objects
from jaxplush.fitting.targets import make_target
from jaxplush.types import GAS_CONSTANT

from conftest import icosphere_text

#: Two 42-vertex balls hanging from their top vertex 0.6 m apart (they never touch), each with
#: its own stiffness and gas; the fit starts with k x2 / nmol x0.5 on one and the opposite on the other.
TRUE_K = (60.0, 120.0)
FACTORS = ((2.0, 0.5), (0.5, 2.0))      # (k, nmol) start factors per ball
DT, STEPS, EVERY = 5e-4, 240, 12


def _nmol(k, inflation=1.05, sub=1):
    """Gas that inflates a free ball of stiffness k to ``inflation`` x its size (docs/model.md §8.5)."""
    m = trimesh.creation.icosphere(subdivisions=sub, radius=0.1)
    e = m.edges_unique
    sum_l2 = float(np.sum((m.vertices[e[:, 0]] - m.vertices[e[:, 1]]) ** 2))
    return k * inflation * (inflation - 1) * sum_l2 / (3 * GAS_CONSTANT * 293.15)


def _scene(ks, nmols):
    top = int(np.argmax(trimesh.creation.icosphere(subdivisions=1, radius=0.1).vertices[:, 1]))
    text = icosphere_text(name="a", k=ks[0], nmol=nmols[0], damping=1000.0, mass=0.1, translate=(-0.3, 1, 0),
                          fixed=(top,))
    text += icosphere_text(name="b", k=ks[1], nmol=nmols[1], damping=1000.0, mass=0.1, translate=(0.3, 1, 0),
                           fixed=(top,), offset=42, header=False)
    return jaxplush.parse_scene(text, "<two hanging balls>")


@pytest.fixture(scope="module")
def two_balls():
    """(problem, objective, true log values) of the two hanging balls, k and nmol of each fitted."""
    nmols = [_nmol(k) for k in TRUE_K]
    truth = _scene(TRUE_K, nmols)
    target = make_target(truth, STEPS, DT, EVERY)
    start = _scene([k * f[0] for k, f in zip(TRUE_K, FACTORS)], [n * f[1] for n, f in zip(nmols, FACTORS)])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        prob = F.build_problem(start, target, ("k_structural", "nmol"), noise_free=True)
    objective = stages.Objective(prob, lmfit.default_box(prob))
    return prob, objective, np.log(np.array([TRUE_K, nmols]))


def test_residual_blocks_belong_to_their_objects(two_balls):
    prob, objective, truth = two_balls
    owner = objects.residual_objects(prob)
    n_frames = prob.target.n_frames
    assert owner.shape == (objective.evaluator.residual.n,)
    # every residual is one of the two balls', 3 coordinates x 42 vertices x frames each
    assert np.array_equal(np.bincount(owner), [3 * 42 * n_frames] * 2)
    assert objects.suits(prob)
    # the physics: the balls do not touch, so moving ball a's parameters changes ball a's residuals
    # and leaves ball b's exactly as they were (and the other way round)
    moved_a, moved_b = truth.copy(), truth.copy()
    moved_a[:, 0] += 0.1
    moved_b[:, 1] -= 0.1
    ev = objective.evaluator(np.stack([truth, moved_a, moved_b]))
    assert ev.ok.all()
    change_a, change_b = np.abs(ev.residuals[1] - ev.residuals[0]), np.abs(ev.residuals[2] - ev.residuals[0])
    assert np.max(change_a[owner == 1]) == 0.0 and np.max(change_a[owner == 0]) > 1e-3
    assert np.max(change_b[owner == 0]) == 0.0 and np.max(change_b[owner == 1]) > 1e-3
    # block losses add up to the loss, and each ball's block is ~0 at the truth
    blocks = objects.block_losses(ev.residuals, owner, 2)
    np.testing.assert_allclose(blocks.sum(axis=1), ev.loss, rtol=1e-12)
    assert blocks[1, 1] == blocks[0, 1] and blocks[1, 0] > 1e3 * blocks[0, 0]


def test_coloured_jacobian_equals_the_full_stencil_and_costs_a_fraction(two_balls):
    """Objects that never come within reach of contact move only with their own parameters, so
    one stencil that moves a parameter of every object at once gives every object's column (2 P_n
    runs instead of 2 P_n O_f). It must equal the full stencil's Jacobian; a stencil that is not
    clear of contact is run again in full, and after COLOUR_MISSES such misses no longer tried."""
    from jaxplush.fitting.stages import search
    from jaxplush.fitting.objective.evaluate import Evaluator
    prob, objective, truth = two_balls
    box = objective.box
    theta = truth + np.array([[0.05, -0.03], [0.02, 0.04]])
    ev = Evaluator(prob, share=objective.evaluator, calibration=objective.evaluator.calibration())
    assert ev.owners() is not None and ev.clear(ev(theta[None]).residuals)[0]
    before = ev.evaluations
    coloured = search.jacobian(ev, box, theta, 1e-3)
    assert ev.evaluations - before == 2 * theta.shape[0]                # 4 runs, not 8
    full_ev = Evaluator(prob, share=objective.evaluator, calibration=objective.evaluator.calibration())
    full_ev.colour_misses = search.COLOUR_MISSES                        # colouring off
    before = full_ev.evaluations
    full = search.jacobian(full_ev, box, theta, 1e-3)
    assert full_ev.evaluations - before == 2 * theta.size
    # each column: exact zeros on the other ball's rows in both, the same values on its own
    owner = ev.owners()
    for j in range(theta.size):
        o = j % theta.shape[1]
        assert np.max(np.abs(full[owner != o, j])) == 0.0 and np.max(np.abs(coloured[owner != o, j])) == 0.0
        np.testing.assert_allclose(coloured[:, j], full[:, j], rtol=0, atol=1e-6 * np.linalg.norm(full[:, j]))
    # a centre whose own run came within reach of contact (its separation, as a search state or
    # the shooting plan knows it) goes straight to the full stencil: no coloured attempt, no miss
    before = ev.evaluations
    near = search.jacobian(ev, box, theta, 1e-3, separation=0.0)
    assert not ev.clear_by_separation([0.0])[0] and ev.clear_by_separation([100.0])[0]
    assert ev.evaluations - before == 2 * theta.size and ev.colour_misses == 0
    np.testing.assert_allclose(near, full, rtol=0, atol=1e-6 * np.linalg.norm(full))
    # a stencil that comes near contact is run again in full (the same Jacobian), and counted
    ev.clear = lambda r, separation=None: np.zeros(len(r), bool)
    before = ev.evaluations
    again = search.jacobian(ev, box, theta, 1e-3)
    assert ev.evaluations - before == 2 * theta.shape[0] + 2 * theta.size and ev.colour_misses == 1
    np.testing.assert_allclose(again, full, rtol=0, atol=1e-6 * np.linalg.norm(full))
    search.jacobian(ev, box, theta, 1e-3)
    before = ev.evaluations
    search.jacobian(ev, box, theta, 1e-3)                               # two misses: full stencils only
    assert ev.colour_misses == search.COLOUR_MISSES and ev.evaluations - before == 2 * theta.size


def test_coloured_jacobian_of_a_point_cloud_reads_each_point_off_its_own_object(two_balls):
    """A point cloud has no vertex correspondence, but each point's residual is measured from one
    vertex (its nearest), so it moves with that vertex's object alone: a coloured stencil gives
    every object's column from the points each run measures from that object, and must equal the
    full stencil. A stencil in which a point changes object is run again in full."""
    from jaxplush.fitting.stages import search
    from jaxplush.fitting.objective.evaluate import Evaluator
    prob0, _, truth = two_balls
    target = make_target(_scene(TRUE_K, [_nmol(k) for k in TRUE_K]), STEPS, DT, EVERY, point_cloud=True, n_points=60,
                         noise=0.002, seed=3)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        prob = F.build_problem(prob0.scene, target, ("k_structural", "nmol"))
    box = lmfit.default_box(prob)
    theta = truth + np.array([[0.05, -0.03], [0.02, 0.04]])
    ev = Evaluator(prob)
    assert ev.owners() is None and ev.colourable()
    e = ev(theta[None], keep_frames=True)
    owner = ev.point_owners(e.frames)[0]
    # the points measured from ball a are those on ball a's side (x < 0), every one of them owned
    x = np.asarray(target.data, np.float64)[..., 0].ravel()
    assert np.array_equal(owner, np.where(x < 0, 0, 1))
    before = ev.evaluations
    coloured = search.jacobian(ev, box, theta, 1e-3)
    assert ev.evaluations - before == 2 * theta.shape[0]                # 4 runs, not 8
    full_ev = Evaluator(prob, share=ev, calibration=ev.calibration())
    full_ev.colour_misses = search.COLOUR_MISSES                        # colouring off
    full = search.jacobian(full_ev, box, theta, 1e-3)
    for j in range(theta.size):
        o = j % theta.shape[1]
        assert np.max(np.abs(full[owner != o, j])) == 0.0 and np.max(np.abs(coloured[owner != o, j])) == 0.0
        assert np.linalg.norm(full[:, j]) > 0
        np.testing.assert_allclose(coloured[:, j], full[:, j], rtol=0, atol=1e-6 * np.linalg.norm(full[:, j]))
    # a point that changes object in one run of the stencil: the full stencil, counted as a miss
    real = ev.point_owners

    def switched(frames):
        out = real(frames)
        out[1, 0] = 1 - out[1, 0]
        return out
    ev.point_owners = switched
    before = ev.evaluations
    again = search.jacobian(ev, box, theta, 1e-3)
    assert ev.evaluations - before == 2 * theta.shape[0] + 2 * theta.size and ev.colour_misses == 1
    np.testing.assert_allclose(again, full, rtol=0, atol=1e-6 * np.linalg.norm(full))


def test_clear_of_contact_sees_objects_within_reach(two_balls):
    prob, _, _ = two_balls
    frames = np.asarray(prob.target.data, np.float64)                  # the balls hang 0.6 m apart
    assert objects.clear_of_contact(prob, frames)
    topo = prob.sim.topology
    vobj = np.asarray(topo.vertex_object)
    reach = 2 * prob.sim.terms.contact.thickness[0]                     # 2 delta, whatever the edges
    gap = frames[:, vobj == 1, 0].min() - frames[:, vobj == 0, 0].max()   # along x, between their boxes
    near = frames.copy()
    near[:, vobj == 1, 0] -= gap - 0.5 * reach                          # b within reach of a
    assert not objects.clear_of_contact(prob, near)
    near = frames.copy()                                                # 1.2 reach apart: inside the safety
    near[:, vobj == 1, 0] -= gap - 1.2 * reach
    assert not objects.clear_of_contact(prob, near)
    far = frames.copy()
    far[:, vobj == 1, 0] -= gap - 4.0 * reach
    both = objects.clear_of_contact(prob, np.stack([far, near]))
    assert both.tolist() == [True, False]


def test_objects_clear_of_contact_move_with_their_own_parameters_alone(two_balls):
    """The physics behind the clearance test: two balls hanging 4 contact thicknesses apart, closer
    than the contact's thickness plus an edge length of their coarse meshes, each move with their
    own parameters only (ball a's frames do not change when ball b's stiffness does)."""
    from jaxplush.fitting.objective.evaluate import Evaluator
    prob0, _, truth = two_balls
    sc = prob0.scene
    delta = prob0.sim.terms.contact.thickness[0]
    edge = float(np.max(prob0.sim.topology.rest_length))
    vobj = np.asarray(prob0.sim.topology.vertex_object)
    x0 = np.asarray(prob0.sim.topology.x0, np.float64)
    gap0 = x0[vobj == 1, 0].min() - x0[vobj == 0, 0].max()
    gap = 4.0 * delta                                                   # clear by thickness,
    assert gap < 1.5 * (2.0 * delta + edge)                             # not by thickness + an edge
    ks, nmols = (tuple(float(v) for v in row) for row in np.exp(truth))
    text_a = icosphere_text(name="a", k=ks[0], nmol=nmols[0], damping=1000.0, mass=0.1,
                            translate=(-0.3, 1, 0), fixed=(int(np.argmax(x0[vobj == 0, 1])),))
    text_b = icosphere_text(name="b", k=ks[1], nmol=nmols[1], damping=1000.0, mass=0.1,
                            translate=(0.3 - (gap0 - gap), 1, 0), fixed=(int(np.argmax(x0[vobj == 1, 1])),),
                            offset=42, header=False)
    scene = jaxplush.parse_scene(text_a + text_b, "<two close balls>")
    target = make_target(scene, STEPS, DT, EVERY)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        prob = F.build_problem(scene, target, ("k_structural", "nmol"), noise_free=True)
    frames = np.asarray(target.data, np.float64)
    assert objects.clear_of_contact(prob, frames)
    moved = truth.copy()
    moved[0, 1] += 0.3                                                  # ball b 35% stiffer
    ev = Evaluator(prob)
    e = ev(np.stack([truth, moved]), keep_frames=True)
    assert e.ok.all()
    change = np.abs(e.frames[1] - e.frames[0]).max(axis=(0, 2))        # per vertex
    assert change[vobj == 1].max() > 1e-4 and change[vobj == 0].max() <= 1e-6 * change[vobj == 1].max()
    # the batched runs measure how close the boxes came at every step, in units of the reach: as
    # a run saving every step shows it
    every = jaxplush.simulate(scene, STEPS, DT, 1, check_dt=False).positions.astype(np.float64)
    lo_a, hi_a = every[:, vobj == 0].min(axis=1), every[:, vobj == 0].max(axis=1)
    lo_b, hi_b = every[:, vobj == 1].min(axis=1), every[:, vobj == 1].max(axis=1)
    closest = np.max(np.maximum(lo_b - hi_a, lo_a - hi_b), axis=1).min() / (2 * delta)
    assert 1.5 < closest < 2.5
    assert abs(e.separation[0] - closest) <= 1e-4 * closest
    assert objects.clear_by_separation(e.separation).all() and ev.clear(e.residuals, e.separation).all()
    # closer than the contact's thickness allows: not clear
    near = frames.copy()
    near[:, vobj == 1, 0] -= gap - 0.5 * delta
    assert not objects.clear_of_contact(prob, near)


def test_point_cloud_points_go_to_the_nearest_object(two_balls):
    prob, objective, truth = two_balls
    frames = objective.evaluator(truth[None], keep_frames=True).frames[0]
    # points on each ball's surface (its vertices, pushed out 1 mm) in every frame
    n = 42
    pts = np.concatenate([frames[:, :n], frames[:, n:]], axis=1) * 1.001
    p2 = dataclasses.replace(prob, target=dataclasses.replace(prob.target, positions=None, points=pts))
    assert p2.target.kind == "points"
    owner = objects.residual_objects(p2, frames)
    assert owner.shape == (prob.target.n_frames * 2 * n,)
    per_frame = owner.reshape(prob.target.n_frames, 2 * n)
    assert (per_frame[:, :n] == 0).all() and (per_frame[:, n:] == 1).all()
    assert not objects.suits(p2)


def test_compose_takes_each_objects_best_block():
    thetas = np.zeros((4, 2, 2))
    thetas[:, :, 0] = np.arange(4)[:, None]          # object 0's block of point i: (i, i)
    thetas[:, :, 1] = 10 + np.arange(4)[:, None]     # object 1's: (10 + i, 10 + i)
    blocks = np.array([[3.0, 0.1], [0.2, 5.0], [1.0, 4.0], [np.inf, 0.5]])
    out = objects.compose(thetas, blocks, 2)
    assert len(out) == 4                              # 2 x 2 combinations
    np.testing.assert_array_equal(out[0], [[1, 10], [1, 10]])    # object 0 from point 1, object 1 from point 0
    assert {(int(c[0, 0]), int(c[0, 1])) for c in out} == {(1, 10), (1, 13), (2, 10), (2, 13)}


def test_per_object_candidates_beat_the_full_design_with_as_many_runs(two_balls):
    prob, objective, truth = two_balls
    stage = objects.PerObjectGlobal(samples=32, per_object=3, rounds=2, starts=3)
    (po,) = stages.run_stages(objective, prob.theta0, [stage])
    n_runs = len(po.result.thetas)
    assert n_runs == stage.evaluations(2) == 1 + 2 * (32 + 9)
    (gl,) = stages.run_stages(objective, prob.theta0, [stages.GlobalStage(samples=n_runs - 1, starts=3)])
    assert len(gl.result.thetas) == n_runs

    def error(s):
        return float(np.max(np.abs(s.theta - truth)))

    best_po, best_gl = po.states[0], gl.states[0]
    # lower loss, and closer to the truth in every parameter's worst case, by a wide margin
    assert best_po.loss < 0.5 * best_gl.loss, (best_po.loss, best_gl.loss)
    assert error(best_po) < 0.6 * error(best_gl), (error(best_po), error(best_gl))


def test_per_object_stage_without_samples_starts_from_its_start_alone(two_balls):
    """A fit that continues from a point (``samples=0``, as the default fit's replanning runs its
    stages again over a longer horizon) evaluates the start alone and hands it on, as the
    full-dimensional GlobalStage does (it used to zoom into an empty design and fail)."""
    prob, objective, _ = two_balls
    theta = prob.theta0 + 0.1
    stage = objects.PerObjectGlobal(samples=0, rounds=3, starts=5)
    (po,) = stages.run_stages(objective, theta, [stage])
    assert len(po.result.thetas) == stage.evaluations(2) == 1
    assert len(po.states) == 1
    np.testing.assert_array_equal(po.states[0].theta, theta)
    (gl,) = stages.run_stages(objective, theta, [stages.GlobalStage(samples=0, starts=5)])
    assert po.states[0].loss == gl.states[0].loss


def test_per_object_stage_then_local_lm_recovers_the_truth(two_balls):
    prob, objective, truth = two_balls
    out = stages.run_stages(objective, prob.theta0,
                            [objects.PerObjectGlobal(samples=32, per_object=3, rounds=2, starts=3),
                             stages.LocalLM(max_iter=40)])
    best = out[-1].states[stages.order(out[-1].states)[0]]
    rel = np.exp(best.theta - truth) - 1.0
    assert np.max(np.abs(rel)) < 0.01, rel


@pytest.mark.heavy        # two whole fits (46 s cold): CI's heavy tier
def test_the_default_fit_of_two_objects_uses_it_and_resumes(two_balls, tmp_path):
    """``fitting.fit`` picks the per-object stage for two fitted objects observed as positions,
    records it in its settings and recovers both balls; its checkpoint (which holds that stage's
    state) resumes to the same answer."""
    prob, _, truth = two_balls
    path = tmp_path / "FIT.h5"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = F.fit(prob.scene, prob.target, ("k_structural", "nmol"), noise_free=True, identifiability=False,
                    checkpoint_path=path)
        again = F.fit(prob.scene, prob.target, ("k_structural", "nmol"), noise_free=True, identifiability=False,
                      checkpoint_path=path, resume=True)
    assert res.settings["global_stage"] == "per_object"
    fitted = np.log(np.array([res.values["k_structural"], res.values["nmol"]]))
    assert np.max(np.abs(fitted - truth)) < 0.01
    for n in ("k_structural", "nmol"):
        np.testing.assert_array_equal(again.values[n], res.values[n])
    # one object alone keeps the full-dimensional design
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        one = F.build_problem(prob.scene, prob.target, ("k_structural",), objects=["a"], noise_free=True)
    assert not objects.suits(one)


def test_first_inversion_names_the_inverted_objects_step_in_a_lane_with_a_healthy_object():
    """An inversion in one object of a lane whose other objects stay healthy is reported at its
    step, whatever the integer type the health carries (int32 from the engine): the int64
    sentinel for the healthy object must not wrap to -1 or overflow."""
    from jaxplush.fitting.objective.evaluate import first_inversion
    from jaxplush.stepping import diagnostics as D
    bad = np.array([[7, -1, 12, 5], [-1, -1, 9, -1]], np.int32)           # (O=2, B=4)
    code = np.array([[D.INVERTED, 0, D.INVERTED, D.INVERTED], [0, 0, D.INVERTED, 0]], np.int32)
    seen = bad >= 0
    np.testing.assert_array_equal(first_inversion(seen, code, bad), [7, -1, 9, 5])
    other = code.copy()
    other[1, 2] = D.INVERTED + 1                                            # another failure too
    np.testing.assert_array_equal(first_inversion(seen, other, bad), [7, -1, -1, 5])
