"""Predictability (jaxplush.predictability): two runs of a scene that differ only by rounding, their
drift, the predictable horizon and the reproducibility floor; the fit's ``at_floor`` outcome, its
record in FIT.h5 and the table, and ``jaxplush info --steps``.

The assertions are physical properties and orders of magnitude (a dashpot-damped ball in free fall
stays predictable, a bean tumbling on a floor with the report's damping does not), never one CPU's
rounding: XLA:CPU rounds differently on different instruction sets.
"""

from __future__ import annotations

import contextlib
import io
import math
import re
import warnings

import h5py
import numpy as np
import pytest

import jaxplush
from conftest import compiles, icosphere_scene
from jaxplush import cli
from jaxplush.fitting import fitter as F
from jaxplush.fitting import cli as fit_cli
from jaxplush.fitting.judge import outcome
from jaxplush.fitting.io import load_fit
from jaxplush.fitting.targets.scenarios import drop_scene_text
from jaxplush.fitting.targets import make_target
from jaxplush.stepping import predictability as P

pytestmark = pytest.mark.numeric      # rests on float rounding: CI runs it again on another instruction set

#: The sensitive case: a 162-vertex bean dropped tilted onto a floor, the report's damping, no
#: dashpot; 0.4 s, a frame every 4 ms.
BEAN = dict(steps=1000, dt=4e-4, save_every=10)


def _bean_text():
    return drop_scene_text("bean", 2, tilt_deg=30.0)


@pytest.fixture(scope="module")
def damped():
    """A 42-vertex ball with a strong edge dashpot falling in free space (no floor): 0.2 s."""
    return jaxplush.predictability(icosphere_scene(dashpot=0.5), 400, 5e-4, 10)


@pytest.fixture(scope="module")
def bean():
    scene = jaxplush.parse_scene(_bean_text(), "<bean>")
    return scene, jaxplush.predictability(scene, BEAN["steps"], BEAN["dt"], BEAN["save_every"])


def test_a_damped_ball_in_free_fall_is_predictable_for_the_whole_run(damped):
    r = damped
    assert r.predictable and r.horizon_frame is None and r.horizon_time == math.inf
    assert r.method == "both" and r.dtype == "float32" and r.threshold_kind == "motion"
    assert r.times.shape == r.drift_rms.shape == r.motion_rms.shape == r.steps.shape == (41,)
    assert r.steps[-1] == 400 and r.times[-1] == pytest.approx(0.2) and r.duration == pytest.approx(0.2)
    # it falls about g t² / 2 = 0.2 m; every twin stays within float32 rounding of it
    assert 0.02 < r.motion < 0.2 and r.threshold == pytest.approx(P.MOTION_FRACTION * r.motion)
    assert np.isfinite(r.drift_rms).all() and r.floor < 1e-4 * r.motion
    assert 0 < r.perturbation < 1e-6
    assert "for the whole run (0.2 s)" in r.text() and "reproducibility floor" in r.text()


def test_a_bean_tumbling_with_the_reports_damping_is_not(bean, damped):
    """The horizon lies inside the run, the floor is orders above the damped ball's (relative to the
    motion), and the drift grows: two runs that differ by rounding tumble apart after the bounce."""
    _, r = bean
    assert not r.predictable and 0 < r.horizon_time < 0.75 * r.duration
    k = r.horizon_frame
    assert r.drift_rms[k] > r.threshold and (r.drift_rms[1:k] <= r.threshold).all()
    assert r.floor > 1e-3 * r.motion and r.floor / r.motion > 100 * damped.floor / damped.motion
    n = len(r.drift_rms)
    assert r.drift_rms[1:n // 2].mean() < r.drift_rms[n // 2:].mean()
    # the floor is the RMS of the drift over the frames after the start
    assert r.floor == pytest.approx(np.sqrt(np.mean(r.drift_rms[1:] ** 2)))
    assert f"for the first {r.horizon_time:.4g} s of 0.4 s" in r.text()


def test_both_twins_take_the_larger_drift_and_a_noise_sets_the_threshold(bean):
    scene, both = bean
    alone = jaxplush.predictability(scene, BEAN["steps"], BEAN["dt"], BEAN["save_every"], method="perturbed",
                                    noise=2e-3)
    assert alone.method == "perturbed" and (alone.drift_rms <= both.drift_rms).all()
    assert alone.threshold == 2e-3 and alone.threshold_kind == "noise"
    # a drift that never reaches 2 mm keeps the whole run predictable at that noise
    assert alone.predictable == bool((alone.drift_rms[1:] <= 2e-3).all())


def test_the_twins_share_one_compiled_program():
    """The unperturbed and the perturbed run are one program; the float64 twin is one more."""
    scene = icosphere_scene(dashpot=0.3, k=123.0)          # a program no other test builds
    with compiles() as seen:
        jaxplush.predictability(scene, 40, 5e-4, 10, method="perturbed")
    assert len([x for x in seen if x.startswith("Finished tracing _core")]) == 1, seen
    with compiles() as seen:
        jaxplush.predictability(scene, 40, 5e-4, 10, method="both")
    traced = [x for x in seen if x.startswith("Compiling jit(_core)")]
    assert len([x for x in seen if x.startswith("Finished tracing _core")]) == 1, seen
    assert all("float64" in x for x in traced), traced


@pytest.mark.parametrize("kw, message", [
    (dict(steps=0), "steps must be"), (dict(dt=-1e-3), "dt must be"), (dict(save_every=0), "save_every must be"),
    (dict(method="twice"), "unknown method"), (dict(noise=-1.0), "noise must be"),
    (dict(integrator="leapfrog"), "unknown integrator"), (dict(substeps=0), "substeps must be"),
])
def test_bad_arguments_are_refused_before_anything_runs(kw, message):
    args = dict(steps=10, dt=5e-4, save_every=5)
    args.update(kw)
    with pytest.raises(ValueError, match=message):
        jaxplush.predictability(icosphere_scene(), args.pop("steps"), args.pop("dt"), **args)


def test_a_run_that_blows_up_says_which_run():
    """A 162-vertex ball at k 100 with a strong dashpot is unstable at dt = 5e-4 s."""
    with pytest.raises(jaxplush.SimulationError, match="unperturbed run of the predictability measurement"):
        jaxplush.predictability(icosphere_scene(subdivisions=2, dashpot=0.5), 100, 5e-4, 10)


# --------------------------------------------------------------------------- the outcome

_OPTIMAL = dict(grad=np.array([1e-4]), grad0=np.array([1.0]), stopped="step")


def test_judge_tells_the_reproducibility_floor_from_a_poor_fit():
    motion = 0.1                                    # noise-free: reached means rms <= 1 mm
    at = outcome.judge(rms=2.2e-3, noise=None, motion=motion, floor=2e-3, horizon=0.15, **_OPTIMAL)
    assert at.status == "at_floor" and not at.converged and at.floor == 2e-3 and at.horizon == 0.15
    for words in ("reproducibility floor", "2.2 mm against the floor 2 mm", "not predictable beyond 0.15 s",
                  "Not converged", "done what the data allow", "shorter target", "multiple shooting", "dashpot"):
        assert words in at.text, words
    # jaxplush-fit exits 0 for converged and undetermined fits (they reached the data) and for fits
    # at the floor (no values do better), reporting their intervals; 4 for the rest
    assert at.status in outcome.DONE and at.status in outcome.REPORTED
    assert set(outcome.DONE) == set(outcome.REPORTED) == {"converged", "undetermined", "at_floor"}
    assert outcome.judge(rms=3e-2, noise=None, motion=motion, floor=2e-3, **_OPTIMAL).status == "poor_fit"
    assert outcome.judge(rms=5e-4, noise=None, motion=motion, floor=2e-3, **_OPTIMAL).status == "converged"
    # a floor far below what the data ask for is no obstacle: the fit is poor
    assert outcome.judge(rms=3e-3, noise=None, motion=motion, floor=1e-6, **_OPTIMAL).status == "poor_fit"
    # without a measurement, as before
    plain = outcome.judge(rms=3e-3, noise=None, motion=motion, **_OPTIMAL)
    assert plain.status == "poor_fit" and math.isnan(plain.floor) and math.isnan(plain.horizon)


def test_a_fit_above_its_floor_has_not_reached_it():
    """A fit at the exact values sits at about 1x its floor; one 1.4-2x above it has not reached
    the floor (a fit whose residual above the noise was 1.56x a cloud's floor was 21.6% off in
    drag): it keeps the status it would have without a floor, exits 4, and its message names the
    floor and the ratio."""
    motion, floor = 0.1, 2e-3
    edge = outcome.FLOOR_REACHED * floor
    assert outcome.judge(rms=edge * 0.99, noise=None, motion=motion, floor=floor, **_OPTIMAL).status == "at_floor"
    above = outcome.judge(rms=edge * 1.01, noise=None, motion=motion, floor=floor, **_OPTIMAL)
    assert above.status == "poor_fit" and above.status not in outcome.DONE
    assert "floor is not reached" in above.message and "1.41x the floor" in above.message and "1.4x" in above.message
    stuck = outcome.judge(rms=3e-3, noise=None, motion=motion, floor=floor, grad=np.array([1e-4]),
                          grad0=np.array([1.0]), stopped="iterations")
    assert stuck.status == "iteration_limit" and "1.5x" in stuck.message
    # beyond FLOOR_FACTOR the floor is not named at all
    far = outcome.judge(rms=5e-3, noise=None, motion=motion, floor=floor, **_OPTIMAL)
    assert far.status == "poor_fit" and "floor" not in far.message


def test_judge_at_floor_with_noise_and_its_precedence():
    noise = 1e-3                                    # reached means rms <= 1.25 mm
    # the noise taken off in quadrature: 2.5 mm leaves sqrt(6.25 - 1) = 2.29 mm, 1.15x the floor
    noisy = outcome.judge(rms=2.5e-3, noise=noise, motion=0.1, floor=2e-3, **_OPTIMAL)
    assert noisy.status == "at_floor" and "noise 1 mm" in noisy.message
    # 3.2 mm leaves 3.04 mm, 1.52x: not at the floor, although within 1.4x of sqrt(noise² + floor²)
    high = outcome.judge(rms=3.2e-3, noise=noise, motion=0.1, floor=2e-3, **_OPTIMAL)
    assert high.status == "poor_fit" and "the residual above the noise is 1.52x the floor" in high.message
    assert outcome.judge(rms=6e-3, noise=noise, motion=0.1, floor=2e-3, **_OPTIMAL).status == "poor_fit"
    assert outcome.judge(rms=1.5e-3, noise=noise, motion=0.1, floor=1e-4, **_OPTIMAL).status == "poor_fit"
    # at_bound first; at_floor before the iteration limit and a stall (more iterations cannot go below it)
    assert outcome.judge(rms=2.2e-3, noise=None, motion=0.1, floor=2e-3, at_bound=("k[ball] at its upper bound",),
                         **_OPTIMAL).status == "at_bound"
    for stopped, grad in (("iterations", [1e-4]), ("step", [0.5])):
        out = outcome.judge(rms=2.2e-3, noise=None, motion=0.1, floor=2e-3, grad=np.array(grad), grad0=np.array([1.0]),
                            stopped=stopped)
        assert out.status == "at_floor", stopped
    assert "at_floor" in outcome.STATUSES and "at_floor" in outcome.NOT_CONVERGED
    assert outcome.FLOOR_FACTOR == 2.0 and outcome.FLOOR_REACHED == 1.4



def test_a_fit_that_reached_the_data_within_its_floor_is_optimal():
    """A fit that reached the data, with a gradient still 6% of the start's, is first-order
    optimal when its residual (above the noise) lies within 1.4x the reproducibility floor: what
    is left is rounding drift, which sets the gradient too. Above that, or without a floor, it
    stalled."""
    stuck = dict(grad=np.array([0.065]), grad0=np.array([1.0]), stopped="stalled")
    noise, floor = 2e-3, 1.07e-3
    # 2.3 mm against a 2 mm noise (reached: <= 2.5 mm) leaves 1.14 mm above it, 1.06x the floor
    out = outcome.judge(rms=2.3e-3, noise=noise, motion=0.1, floor=floor, **stuck)
    assert out.status == "converged" and out.optimal and out.reached
    assert "1.14 mm, is within 1.4x the model's reproducibility floor 1.07 mm" in out.message
    # 2.45 mm leaves 1.41 mm, 1.32x: still within; a floor half as large: not
    assert outcome.judge(rms=2.45e-3, noise=noise, motion=0.1, floor=floor, **stuck).status == "converged"
    assert outcome.judge(rms=2.45e-3, noise=noise, motion=0.1, floor=floor / 2, **stuck).status == "stalled"
    assert outcome.judge(rms=2.3e-3, noise=noise, motion=0.1, **stuck).status == "stalled"
    # noise-free: the residual itself against the floor (reached: <= 1% of the 0.1 m motion)
    assert outcome.judge(rms=5e-4, noise=None, motion=0.1, floor=4e-4, **stuck).status == "converged"
    assert outcome.judge(rms=5e-4, noise=None, motion=0.1, floor=3e-4, **stuck).status == "stalled"
    # a fit that did not reach the data is judged against the floor as before
    assert outcome.judge(rms=3e-3, noise=noise, motion=0.1, floor=floor, **stuck).status != "converged"


# --------------------------------------------------------------------------- the fit

@pytest.fixture(scope="module")
def bean_target():
    truth = jaxplush.parse_scene(_bean_text(), "<bean truth>")
    return truth, make_target(truth, BEAN["steps"], BEAN["dt"], BEAN["save_every"])


def test_a_fit_records_the_predictability_in_the_table_and_fit_h5(bean_target, tmp_path):
    """A short Adam fit (2 iterations): the line before the fit, the table, FIT.h5's group."""
    truth, target = bean_target
    lines = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = F.fit(truth, target, ("k_structural",), optimizer="adam", iterations=2, noise_free=True,
                    identifiability=False, report=lines.append)
    pred = res.predictability
    assert lines == [f"predictability: {pred.text()}"]
    assert not pred.predictable and pred.floor > 1e-3 * pred.motion
    # its threshold is 0.1% of the fit's own measure of the motion
    assert pred.threshold == pytest.approx(P.MOTION_FRACTION * res.outcome.reference)
    assert f"predictability: {pred.text()}" in res.table()
    out = res.save(tmp_path / "FIT.h5")
    with h5py.File(out) as f:
        g = f["predictability"]
        np.testing.assert_array_equal(g["drift_rms"][()], pred.drift_rms)
        np.testing.assert_array_equal(g["times"][()], pred.times)
        assert g.attrs["horizon_time"] == pred.horizon_time and g.attrs["floor_rms"] == pred.floor
        assert g.attrs["threshold"] == pred.threshold and g.attrs["method"] == "both"
        assert np.isfinite(f.attrs["outcome_floor"]) and f.attrs["outcome_floor"] > 0
    assert load_fit(out)["predictability_attrs"]["floor_rms"] == pred.floor
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        off = F.fit(truth, target, ("k_structural",), optimizer="adam", iterations=1, noise_free=True,
                    identifiability=False, predictability=False)
    assert off.predictability is None and "predictability" not in off.table()
    assert "predictability" not in load_fit(off.save(tmp_path / "OFF.h5"))


def test_the_default_fit_of_a_tumbling_bean_ends_at_the_floor_or_fits_its_predictable_frames(bean_target):
    """From k x1.2 the default fit finds k, but over the whole target its residual cannot go below
    the drift of two runs that differ by rounding. Where the frames before the horizon measured at
    its values sit above their own rounding drift, it fits those again (fitter._within_horizon):
    there the model is deterministic, and k comes out far closer. Else it ends at_floor (never
    poor_fit), or reaches the data where a CPU's rounding leaves less drift."""
    truth, target = bean_target
    p = truth.params
    start = truth.replace(params=p._replace(k_structural=p.k_structural * 1.2))
    lines = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = F.fit(start, target, ("k_structural",), noise_free=True, identifiability=False, report=lines.append)
    assert res.values["k_structural"][0] == pytest.approx(p.k_structural[0], rel=0.02)
    assert "predictability:" in res.table()
    o = res.outcome
    assert res.status in ("at_floor", "converged"), res.reason
    again = [x for x in lines if x.startswith("fitted again over the first ")]
    if again:
        # cut at the horizon of its first values, which sat above their drift there
        keep, total = (int(w) for w in again[0].split()[5:8:2])
        assert 4 <= keep < total == target.n_frames
        assert res.frames.shape[0] == keep and again[0] in res.warnings
        m = re.search(r"over those frames ([0-9.e+-]+) mm, ([0-9.e+-]+)x their rounding drift", again[0])
        assert m and float(m[2]) > outcome.FLOOR_REACHED
        # the (noise-free) bean reproduces its predictable frames: k within 0.1%, not 2%
        assert res.values["k_structural"][0] == pytest.approx(p.k_structural[0], rel=1e-3)
    if res.status == "at_floor":
        # the residual lies at the floor (it sat near 1.7 mm, 0.9x the floor, 1.19x under SSE4.2,
        # above 1% of the motion, before the fit of the predictable frames); the floor is one
        # sample of the drift, so which status comes is the CPU's business
        assert o.rms <= outcome.FLOOR_REACHED * o.floor and o.rms > outcome.MOTION_FRACTION * o.reference
        assert not res.converged and "reproducibility floor" in res.reason


def test_jaxplush_fit_prints_the_predictability_before_fitting(bean_target, tmp_path, capsys):
    truth, target = bean_target
    scene, target_path, out = tmp_path / "bean.obj", tmp_path / "target.h5", tmp_path / "FIT.h5"
    scene.write_text(truth.text)
    target.save(target_path, truth)
    rc = fit_cli.main([str(scene), str(target_path), "--params", "k", "--optimizer", "adam", "--iterations", "1",
                       "--noise-free", "--out", str(out)])
    text = capsys.readouterr()
    assert rc in (0, fit_cli.EXIT_NOT_CONVERGED), text.err
    line = next(x for x in text.err.splitlines() if x.startswith("predictability: "))
    assert text.err.index(line) < text.err.index("fit [")            # before the fit's progress
    assert line in text.out.splitlines()                             # and in the table
    with h5py.File(out) as f:
        assert "predictability" in f and f["predictability"].attrs["text"] == line[len("predictability: "):]


# --------------------------------------------------------------------------- jaxplush info

def _info(*argv):
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        rc = cli.main(["info", *map(str, argv)])
    return rc, out.getvalue(), err.getvalue()


def test_info_shows_the_predictable_horizon_only_when_asked(tmp_path):
    scene = tmp_path / "bean.obj"
    scene.write_text(_bean_text())
    rc, out, err = _info(scene, "--dt", BEAN["dt"], "--steps", BEAN["steps"], "--save-every", BEAN["save_every"])
    assert rc == 0, err
    line = next(x for x in out.splitlines() if "predictable horizon:" in x)
    assert "drift of two runs that differ by rounding exceeds 0.1% of the motion" in line
    assert "reproducibility floor" in line and f"over {BEAN['steps']} steps" in line
    rc, out, _ = _info(scene, "--dt", BEAN["dt"])
    assert rc == 0 and "predictable" not in out and "reproducibility" not in out
    rc, _, err = _info(scene, "--steps", 100)
    assert rc == cli.EXIT_USAGE and "--steps needs --dt" in err


def test_the_fits_measurement_runs_its_float32_twins_on_the_batched_simulator():
    """Issue 52 (few programs per fit): the default fit measures the predictability with its two
    float32 runs as lanes of the batched simulator its search compiles anyway (no float32
    single-scene rollout of its own). The measurement agrees with the one made by ``simulate``:
    the same motion to float32 rounding, both predictable, both floors at rounding level. A
    42-vertex ball with a dashpot falling onto a floor, 0.1 s."""
    from jaxplush.fitting.judge import result as R
    scene = icosphere_scene(dashpot=0.4, k=157.0, floor=-0.15)
    # the target from the ball 1 mm higher: another program, so this one's is not compiled yet
    target = make_target(icosphere_scene(dashpot=0.4, k=157.0, floor=-0.15, translate=(0, 1e-3, 0)), 200, 5e-4, 10)
    prob = F.build_problem(scene, target, ("k_structural",), noise_free=True)
    with compiles() as seen:
        lanes = R._predictability_at(prob, batched=True)
    # no single-scene program of the working dtype ((42, 3) float32 states): the float64 twin's alone
    single_f32 = [x for x in seen if x.startswith(("Compiling jit(_core)", "Compiling jit(init_fn)"))
                  and "float32[42,3]" in x]
    assert not single_f32, single_f32
    assert any("float64[42,3]" in x for x in seen if x.startswith("Compiling jit(_core)")), seen
    single = R._predictability_at(prob, batched=False)
    assert lanes is not None and single is not None
    np.testing.assert_allclose(lanes.times, single.times)
    np.testing.assert_array_equal(lanes.steps, single.steps)
    assert lanes.motion == pytest.approx(single.motion, rel=1e-4)
    np.testing.assert_allclose(lanes.motion_rms, single.motion_rms, atol=1e-4 * lanes.motion)
    assert lanes.predictable and single.predictable
    assert lanes.floor < 1e-4 * lanes.motion and single.floor < 1e-4 * single.motion


def test_a_last_frame_off_the_grid_is_measured_on_the_batched_simulator_too():
    """A target whose last frame lies off its frames' grid (205 steps saved every 10, and the
    last) is measured on an even grid that ends on its last step, so its float32 twins still run as
    lanes of the batched simulator (before, they ran on single-scene programs of their own: two
    per run, the last frame's one). A long run saved on a coarse irregular grid gets an even grid
    whose step divides its last step (4720 steps in 51 frames: every 80, not 92)."""
    from types import SimpleNamespace
    from jaxplush.fitting.judge import result as R
    scene = icosphere_scene(dashpot=0.4, k=161.0, floor=-0.15)
    target = make_target(icosphere_scene(dashpot=0.4, k=161.0, floor=-0.15, translate=(0, 2e-3, 0)), 205, 5e-4, 10)
    assert target.steps[-1] == 205 and target.steps[-2] == 200
    assert R._predictability_grid(target) == (205, 5)
    prob = F.build_problem(scene, target, ("k_structural",), noise_free=True)
    with compiles() as seen:
        pred = R._predictability_at(prob, batched=True, chunk_frames=8)
    single_f32 = [x for x in seen if x.startswith(("Compiling jit(_core)", "Compiling jit(init_fn)"))
                  and "float32[42,3]" in x]
    assert not single_f32, single_f32
    assert pred is not None and pred.steps[-1] == 205 and pred.predictable
    assert pred.floor < 1e-4 * pred.motion
    coarse = SimpleNamespace(steps=np.r_[np.arange(1, 51) * 94, 4720], n_frames=51)
    assert R._predictability_grid(coarse) == (4720, 80)
    prime = SimpleNamespace(steps=np.r_[np.arange(1, 51) * 94, 4721], n_frames=51)
    assert R._predictability_grid(prime) == (4721, 92)      # no divisor near: the grid of old
