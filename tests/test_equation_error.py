"""The start from the model's linearity (issue 53 item 1): the equation-error estimate of the linear
force balance, and indirect inference on it.

Given positions and velocities every force is linear in its parameter, so from frames close enough
together (finite-difference accelerations exact to second order) a least-squares fit of the force
balance recovers k, the dashpot, nmol and the velocity-decay rate with no start values and no
rollout. Frames far apart alias the fast modes and bias it; indirect inference (the same estimator
on simulated frames, iterated) takes the bias off. The report's damping and air drag share one
regressor: only their combined rate is determined."""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np
import pytest

import jaxplush
from jaxplush import fitting
from jaxplush.fitting.stages import equation_error as EE
from jaxplush.fitting.objective import problem as P
from conftest import icosphere_text

DT = 5e-4
NAMES = ("k_structural", "dashpot", "nmol", "drag")


def _hung(**kw):
    """A 42-vertex gas ball hanging from one pinned vertex: it drops, stretches and bounces (its
    springs damped at about a fifth of critical, as a plush's)."""
    args = dict(subdivisions=1, k=100.0, mass=0.05, nmol=3e-4, dashpot=0.1, drag=1.0, fixed=(0,))
    args.update(kw)
    return jaxplush.parse_scene(icosphere_text(**args), "<hung>")


def _problem(truth, every, names=NAMES, factor=3.0, steps=400, force=False):
    """A fit's problem: a noise-free positions target of ``truth`` saved every ``every`` steps,
    from a start ``factor`` x every fitted value (the estimate uses no start value)."""
    target = fitting.make_target(truth, steps=steps, dt=DT, save_every=every)
    p = truth.params
    start = truth.replace(params=p._replace(**{n: getattr(p, n) * factor for n in names}))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return P.build_problem(start, target, names, noise_free=True, force=force)


def _errors(truth, values, names=NAMES):
    return {n: float(np.max(np.abs(np.asarray(values[n]) / np.asarray(getattr(truth.params, n)) - 1))) for n in names}


@pytest.fixture(scope="module")
def hung():
    return _hung()


def test_the_force_balance_recovers_every_linear_parameter_from_close_frames(hung):
    """Every step saved: the balance is the model's own (second differences are Verlet's update,
    and the forces see its half-step velocity), so the least-squares fit gives k, c, nmol and the
    drag to rounding. Every 4th step saved: finite differences, within a few percent."""
    errs = {}
    for every in (1, 4):
        est = EE.equation_error(_problem(hung, every))
        errs[every] = _errors(hung, est.values)
        assert not est.clamped and est.rows[0] > 0
    assert max(errs[1].values()) < 1e-4, errs
    assert 1e-3 < max(errs[4].values()) < 0.05, errs
    # the report's damping D too: Verlet's per-step decay 1/D enters as the rate 1/(D dt)
    truth = _hung(drag=None, damping=300.0)
    names = ("k_structural", "dashpot", "nmol", "damping")
    est = EE.equation_error(_problem(truth, 1, names=names))
    assert max(_errors(truth, est.values, names).values()) < 1e-4


def test_pinned_and_floor_vertices_are_left_out():
    """The pinned vertex never enters the fit; a ball dropped on a floor loses the vertices near it
    while they touch, and its estimate from close frames still holds."""
    prob = _problem(_hung(), 1)
    xs, _ = EE.frames_with_start(prob)
    ok = EE._masks(prob, xs)
    assert not ok[:, 0].any() and ok[:, 1:].all()
    ball = jaxplush.parse_scene(icosphere_text(subdivisions=1, k=100.0, mass=0.05, nmol=3e-4, dashpot=0.02,
                                               floor=0.0, translate=(0, 0.12, 0)), "<drop>")
    prob = _problem(ball, 1, names=("k_structural", "dashpot", "nmol"))
    xs, _ = EE.frames_with_start(prob)
    ok = EE._masks(prob, xs)
    assert 0 < ok.sum() < ok.size                       # some vertex-frames out (near the floor), most in
    low = xs[1:-1, :, 1] < prob.scene.floor + 1e-3
    assert low.any() and not (ok & low).any()
    est = EE.equation_error(prob)
    assert max(_errors(ball, est.values, prob.names).values()) < 0.02


def test_indirect_inference_takes_off_the_bias_of_frames_far_apart(hung):
    """Frames every 10 steps (5 ms: the fastest modes, near 700 rad/s, turn 3.5 rad between frames,
    past the sampling's limit of pi): the estimate alone is off by a percent or more; indirect
    inference from it recovers every value within 0.1% in a few rollouts, from no start value."""
    prob = _problem(hung, 10)
    raw = EE.equation_error(prob)
    assert max(_errors(hung, raw.values).values()) > 0.01
    ii = EE.indirect_inference(prob, iterations=10)
    assert ii.converged, ii.history
    assert max(_errors(hung, ii.values).values()) < 1e-3, _errors(hung, ii.values)
    assert ii.rollouts <= 10 + len(NAMES) and not ii.undetermined


def test_damping_and_drag_are_one_rate():
    """The report's damping and air drag fitted together: their combined rate is determined (and
    found), their split is not (said so; the start's split is kept)."""
    truth = _hung(drag=0.5, damping=800.0)
    prob = _problem(truth, 5, names=("k_structural", "drag", "damping"), factor=1.5)
    ii = EE.indirect_inference(prob, iterations=10)
    assert ii.undetermined == ("damping", "drag")
    rate = lambda drag, d: float(drag) + float(EE.damping_rate(d, DT))      # noqa: E731
    got = rate(ii.values["drag"][0], ii.values["damping"][0])
    want = rate(truth.params.drag[0], truth.params.damping[0])
    assert got == pytest.approx(want, rel=5e-3)
    assert ii.values["k_structural"][0] == pytest.approx(truth.params.k_structural[0], rel=5e-3)
    # the start's split: drag / rate as at the start values
    start = prob.start
    share = start["drag"][0] / rate(start["drag"][0], start["damping"][0])
    assert ii.values["drag"][0] / got == pytest.approx(share, rel=1e-6)


def test_refuses_what_it_cannot_estimate(hung):
    prob = _problem(hung, 5)
    with pytest.raises(ValueError, match="positions target"):
        EE.equation_error(dataclasses.replace(prob, target=dataclasses.replace(
            prob.target, positions=None, points=prob.target.positions)))
    assert EE.suits(prob)
    mass = _problem(hung, 5, names=("k_structural", "total_weight"), force=True)
    assert not EE.suits(mass)
    with pytest.raises(ValueError, match="not total_weight"):
        EE.equation_error(mass)


def test_the_default_fits_design_holds_the_linear_start(hung):
    """The default fit's global stage evaluates the linear start beside its Sobol points (the design's
    second point), and from a start 3x off that point is the design's best."""
    from jaxplush.fitting import options, stages
    from jaxplush.fitting.stages import lmfit
    prob = _problem(hung, 10, factor=3.0)
    box = lmfit.default_box(prob)
    obj = stages.Objective(prob, box)
    st = stages.GlobalStage(samples=8, starts=2, linear=True)
    s = st.step(obj, st.init(obj, prob.theta0))
    assert np.all(np.isfinite(s.linear))
    assert np.allclose(s.result.thetas[1], box.clip(s.linear))
    assert int(np.argmin(s.result.loss)) == 1
    assert max(_errors(hung, prob.values(s.linear)).values()) < 1e-3
    off = stages.GlobalStage(samples=8, starts=2)
    assert len(off.step(obj, off.init(obj, prob.theta0)).result.thetas) == 9
    assert lmfit.default_stages(prob, options.FitOptions())[0].first[0].linear
