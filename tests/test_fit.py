"""Fitting (fitting.fit, jaxplush.fitting.judge.identifiability, jaxplush.fitting.io): synthetic recovery, finite-difference
check of the fit's loss, identifiability flags, blow-up handling, Ctrl-C save and resume."""

from __future__ import annotations

import json
import os
import re
import signal
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxplush
from conftest import assert_gradient_matches_fd, icosphere_text
from jaxplush.fitting import fitter as F
from jaxplush.fitting.io import fitted_scene_text, load_fit
from jaxplush.fitting.targets import Target, make_target
from jaxplush.model import contact
from jaxplush.errors import JaxplushError

NAMES = ("k_structural", "damping", "nmol")


def _hanging(subdivisions=1, **kw):
    return jaxplush.parse_scene(F.recovery_scene_text(subdivisions, **kw), "<hanging>")


@pytest.fixture(scope="module")
def small():
    """42-vertex hanging ball: truth, a start off by x2 / x0.5, and a 200-step target."""
    truth = _hanging()
    p = truth.params
    start = _hanging(k_structural=2 * p.k_structural[0], damping=0.5 * p.damping[0], nmol=2 * p.nmol[0])
    target = make_target(truth, 200, 1e-3, 20)
    return truth, start, target


# --------------------------------------------------------------------------- recovery

@pytest.mark.heavy
def test_recovery_162_vertices():
    """k, damping and nmol from x2 / x0.5 / x2 starts, noise-free, within 1% (the fast version of the
    issue's 642-vertex acceptance run, which is test_recovery_acceptance)."""
    r = F.synthetic_recovery(2, steps=400, progress=False)
    assert r["vertices"] == 162
    assert r["max_error"] < 0.01, r["errors"]
    res = r["result"]
    assert res.converged and res.loss < 1e-4 * res.loss_start
    rep = res.identifiability
    assert rep.determined.all() and not rep.warnings and rep.condition < 1e6
    assert np.all(np.isfinite(res.history["loss"]))
    assert res.history["k_structural"].shape == (len(res.history["loss"]), 1)


@pytest.mark.slow
@pytest.mark.parametrize("noise,point_cloud,tol", [(0.0, False, 0.01), (1e-3, False, 0.05), (0.0, True, 0.05)],
                         ids=["noise-free", "noise-1mm", "point-cloud"])
def test_recovery_acceptance(noise, point_cloud, tol):
    """Issue 3 acceptance: 642 vertices, starts off by x2 and x0.5; within 1% noise-free, 5% with
    1 mm noise. The time limit (under 2 minutes) is measured by benchmarks/bench_fit.py, not asserted."""
    r = F.synthetic_recovery(3, noise=noise, point_cloud=point_cloud, progress=False)
    assert r["vertices"] == 642
    assert r["max_error"] < tol, r["errors"]


# --------------------------------------------------------------------------- the loss and its gradient

@pytest.mark.parametrize("kind", [pytest.param("positions", marks=pytest.mark.heavy), "points"])
def test_fit_loss_gradient_matches_finite_differences(x64, kind):
    truth = _hanging()
    p = truth.params
    start = _hanging(k_structural=1.3 * p.k_structural[0], damping=0.7 * p.damping[0], nmol=1.2 * p.nmol[0])
    target = make_target(truth, 90, 1e-3, 30, point_cloud=(kind == "points"), n_points=60)
    prob = F.build_problem(start, target, NAMES, noise_free=True)       # the fit's default method, "auto"
    assert prob.sim.dtype == jnp.float64
    theta = jnp.asarray(prob.theta0)
    vg = jax.jit(jax.value_and_grad(prob.loss_fn))     # one compiled function for values and gradient
    loss = lambda t: float(vg(t)[0])  # noqa: E731
    value, g = vg(theta)
    g = np.asarray(g)
    assert np.all(g != 0)
    assert_gradient_matches_fd(loss, np.asarray(theta), g, h=1e-4, rtol=1e-6)
    if kind == "positions":
        # the loss is what jaxplush.fitting.objective.losses says: the mean squared vertex distance over the frames / s²
        frames, _ = jax.jit(prob.frames)(theta)
        d = np.asarray(frames) - target.data
        assert float(value) == pytest.approx(np.mean(np.sum(d ** 2, -1)) / prob.loss.scale2, rel=1e-10)
        # autodiff through the rollout with and without checkpointing gives the same gradient
        for method in ("plain", "checkpoint"):
            other = F.build_problem(start, target, NAMES, noise_free=True, method=method)
            g_m = np.asarray(jax.jit(jax.grad(other.loss_fn))(theta))
            assert np.linalg.norm(g_m - g) <= 1e-9 * np.linalg.norm(g), method


# --------------------------------------------------------------------------- identifiability

def _free_ball():
    """Zero-gravity pressurised ball, strongly damped (D = 10): it inflates and settles."""
    text = icosphere_text(subdivisions=1, radius=0.1, k=50.0, mass=0.05, nmol=2e-4, damping=10.0,
                          gravity=(0.0, 0.0, 0.0))
    return jaxplush.parse_scene(text, "<free ball>")


@pytest.mark.heavy
def test_static_target_flags_damping_and_the_k_nmol_tradeoff():
    scene = _free_ball()
    frames = make_target(scene, 400, 1e-3, 10)
    static = frames.select([-1])                           # only the settled final shape (0.9^400 ~ e^-42)
    assert static.steps.tolist() == [400]
    rep = F.identifiability_at(F.build_problem(scene, static, NAMES, noise_free=True), np.log(
        [[50.0], [10.0], [2e-4]]))
    labels = dict(zip(rep.labels, rep.determined))
    assert not labels["damping[ball]"] and labels["k_structural[ball]"] and labels["nmol[ball]"]
    text = " ".join(rep.warnings)
    assert "damping[ball] is not determined by the target" in text
    assert "only the ratio k_structural[ball]/nmol[ball] is determined" in text
    assert rep.condition > 1e6 and not np.isfinite(rep.stderr[1])

    dynamic = frames.select(slice(0, 10))                 # the inflation transient, steps 10..100
    rep = F.identifiability_at(F.build_problem(scene, dynamic, NAMES, noise_free=True), np.log(
        [[50.0], [10.0], [2e-4]]))
    assert rep.determined.all() and rep.condition < 1e6 and not rep.warnings, rep.summary()
    # the least determined direction is mostly damping (its sensitivity is the smallest)
    assert rep.weakest.split(",")[0].endswith("log damping[ball]") and "weakest combination" in rep.summary()


def test_identifiability_wording():
    from jaxplush.fitting.judge.identifiability import analyse
    rng = np.random.default_rng(0)
    a = rng.normal(size=200)
    b = rng.normal(size=200)
    # raising p0 and p2 together leaves the features unchanged: only p0/p2 is determined
    jac = np.stack([a, b, -a + 1e-9 * b, 1e-9 * b], axis=1)    # ... and p3 not at all
    rep = analyse(jac, 1e-3 * rng.normal(size=200), ["p0", "p1", "p2", "p3"])
    assert list(rep.determined) == [True, True, True, False]
    assert any("only the ratio p0/p2 is determined" in w for w in rep.warnings), rep.warnings
    assert any("p3 is not determined" in w for w in rep.warnings)
    # raising p0 while lowering p2 leaves them unchanged: only the product
    rep = analyse(np.stack([a, b, a + 1e-9 * b], 1), 1e-3 * rng.normal(size=200), ["p0", "p1", "p2"])
    assert any("only the product p0*p2 is determined" in w for w in rep.warnings), rep.warnings
    good = analyse(np.stack([a, b], 1), 1e-3 * rng.normal(size=200), ["p0", "p1"])
    # standard errors: sigma^2 (J^T J)^-1
    cov = good.sigma ** 2 * np.linalg.inv(good.jtj)
    np.testing.assert_allclose(good.stderr, np.sqrt(np.diag(cov)), rtol=1e-10)
    assert not good.warnings


def test_the_reports_damping_and_drag_of_one_object_are_never_told_apart():
    """The model's damping and drag share one regressor: whatever a rounded Jacobian shows (here
    two well-separated columns, as seed 601 case 5's float32 fit on a floor did, converged 87% off
    in damping with a 0.06% standard error), the report calls each undetermined and says that
    their rate is what the target determines; another object's pair and other parameters stay."""
    from jaxplush.fitting.judge.identifiability import analyse, shared_regressors
    rng = np.random.default_rng(3)
    jac = rng.normal(size=(300, 5))                  # independent columns: every stderr finite
    labels = ["k_structural[a]", "damping[a]", "drag[a]", "damping[b]", "nmol[a]"]
    assert shared_regressors(labels) == [(1, 2)]
    rep = analyse(jac, 1e-4 * rng.normal(size=300), labels)
    assert rep.undetermined == ("damping[a]", "drag[a]")
    assert np.isinf(rep.stderr[1:3]).all() and np.isfinite(rep.stderr[[0, 3, 4]]).all()
    assert any("damping[a] and drag[a]" in w and "combined rate" in w for w in rep.warnings), rep.warnings
    assert analyse(jac[:, [0, 1, 4]], 1e-4 * rng.normal(size=300), ["k[a]", "damping[a]", "nmol[a]"]).undetermined == ()


def test_identifiability_sees_a_degenerate_pair_through_rounding_noise():
    """Two exactly collinear columns plus float32-like noise of known size: the condition number
    stays below the warning level (the noise breaks the degeneracy), the residual-based standard
    errors look tiny, and only the Jacobian's noise tells that the pair is not determined."""
    from jaxplush.fitting.judge.identifiability import COND_WARN, analyse, fd_noise
    rng = np.random.default_rng(1)
    n = 4000
    g, k = rng.normal(size=n), rng.normal(size=n)
    eps = 5e-3                                       # the noise of every column, RMS per residual
    # p0 and p1 act only through p0 + 3 p1 (as damping and drag act through their summed rate)
    jac = np.stack([g, 3.0 * g, k], 1) + eps * rng.normal(size=(n, 3))
    resid = 1e-7 * rng.normal(size=n)                # a noise-free fit: rounding-sized residuals
    blind = analyse(jac, resid, ["p0", "p1", "p2"])
    assert blind.condition < COND_WARN and np.all(np.isfinite(blind.stderr)) and max(blind.stderr) < 1e-3
    assert blind.undetermined == ()                  # the old verdict: everything determined
    # the same Jacobian with its noise known: the pair is unresolved, p2 still determined
    drift, h = eps * 2 * 1e-3, 1e-3                  # fd_noise(drift, h) == eps
    assert fd_noise(drift, h) == pytest.approx(eps)
    rep = analyse(jac, resid, ["p0", "p1", "p2"], jac_noise=fd_noise(drift, h))
    assert rep.undetermined == ("p0", "p1") and len(rep.unresolved) == 1
    assert not np.isfinite(rep.stderr[:2]).any() and np.isfinite(rep.stderr[2])
    assert any("p0, p1 are not determined individually" in w for w in rep.warnings), rep.warnings
    # a weak but real direction (a unit step along it moves the residuals by 10x the noise) stays resolved
    m = rng.normal(size=n)
    weak = np.stack([g, 3.0 * g + 10 * eps * np.sqrt(10) * m, k], 1) + eps * rng.normal(size=(n, 3))
    ok = analyse(weak, resid, ["p0", "p1", "p2"], jac_noise=eps)
    assert ok.unresolved == [] and ok.undetermined == (), ok.summary()


def test_damping_and_drag_fitted_together_end_undetermined():
    """The report's damping and air drag both decay every velocity uniformly, so a target
    determines only their combined rate: the default fit says so before it starts, reproduces
    the target, recovers that rate and the other parameters, and ends ``undetermined`` (not
    ``converged``) with the pair named, their standard errors infinite."""
    from jaxplush.fitting.judge.outcome import Status
    from jaxplush.fitting.objective.problem import DAMPING_DRAG_NOTE

    def scene(drag, **kw):
        return jaxplush.parse_scene(F.recovery_scene_text(1, **kw).replace("damping", f"drag {drag}\ndamping", 1),
                                    "<hanging+drag>")
    truth = scene(2.0, damping=1000.0)
    p = truth.params
    dt = 1e-3
    target = make_target(truth, 200, dt, 20)
    start = scene(2.0 * 1.7, damping=600.0, k_structural=1.3 * p.k_structural[0], nmol=0.8 * p.nmol[0])
    with pytest.warns(UserWarning, match=re.escape(DAMPING_DRAG_NOTE[:60])):
        res = F.fit(start, target, noise_free=True)
    assert set(res.names) == {"k_structural", "damping", "drag", "nmol"}
    assert res.status == Status.UNDETERMINED and not res.converged and res.outcome.reached, res.reason
    und = res.identifiability.undetermined
    assert "damping[ball]" in und and "drag[ball]" in und, res.identifiability.summary()
    assert "k_structural[ball]" not in und and "nmol[ball]" not in und
    # (Verlet's update takes 1/D of the half-step velocity off per step, and drag gamma dt of it)
    rate = lambda d, g: 1.0 / (d * dt) + g  # noqa: E731
    got, want = rate(res.values["damping"][0], res.values["drag"][0]), rate(p.damping[0], p.drag[0])
    assert got == pytest.approx(want, rel=1e-2)
    for n in ("k_structural", "nmol"):
        assert res.values[n][0] == pytest.approx(getattr(p, n)[0], rel=1e-2)
    # the determined combination is reported, with its value and its interval from twins; the
    # split is called undetermined
    (c,) = res.combinations
    assert c.label == "damping+drag rate[ball]" and c.parts == ("damping[ball]", "drag[ball]") and c.unit == "1/s"
    assert c.value == pytest.approx(got, rel=1e-12) and "split between damping and drag is undetermined" in c.note
    assert np.isfinite(c.sd) and c.lower < c.value < c.upper
    assert abs(np.log(want / c.value)) <= 4 * c.sd + 1e-12, (c, want)
    assert "determined: damping+drag rate[ball]" in res.table()
    assert np.isinf(res.intervals.sd[list(res.intervals.labels).index("drag[ball]")])
    # the search fitted the rate alone: the values split it as the start values did
    share = lambda d, g: g / rate(d, g)  # noqa: E731
    assert share(res.values["damping"][0], res.values["drag"][0]) == pytest.approx(share(600.0, 3.4), rel=1e-9)


def test_a_search_moves_damping_and_drag_only_along_their_combined_rate():
    """Where an object's damping D and drag are both fitted, a search's step keeps drag's share
    of the rate r = drag + 1/(D dt) (in log space the pair moves along (-1, +1)); its starts go
    onto the start values' share, the rate kept; a step clipped by the box on one of the two is
    cut on the other as well; and a problem without the pair has no ties."""
    from jaxplush.fitting.stages.search import Box, Ties, _steps
    dt = 1e-3
    ties = Ties(shape=(3, 2), damping=(2, 3), drag=(4, 5), share=np.array([0.25, 0.5]), dt=dt)
    rate = lambda th: np.exp(th[2]) + np.exp(-th[1]) / dt  # noqa: E731
    share = lambda th: np.exp(th[2]) / rate(th)  # noqa: E731
    theta = np.log(np.array([[300.0, 200.0], [800.0, 50.0], [2.0, 7.0]]))
    on = ties.project(theta)
    np.testing.assert_allclose(rate(on), rate(theta), rtol=1e-12)
    np.testing.assert_allclose(share(on), [0.25, 0.5], rtol=1e-12)
    np.testing.assert_array_equal(on[0], theta[0])
    assert np.array_equal(ties.project(on), on)               # on the line: left exactly as it is
    # LM steps on a random Jacobian keep every share, and move the rate
    rng = np.random.default_rng(0)
    jac, r = rng.normal(size=(40, 6)), rng.normal(size=40)
    box = Box(lo=on - 3.0, hi=on + 3.0)
    for trial, step, pred, mu in _steps(jac, r, (1e-3, 1e-1), 0.5, box, on, ties):
        np.testing.assert_allclose(share(trial), [0.25, 0.5], rtol=1e-9)
        assert pred > 0 and 0 < np.max(np.abs(step)) <= 0.5 + 1e-12
    assert any(abs(rate(t)[0] / rate(on)[0] - 1) > 1e-3 for t, *_ in _steps(jac, r, (1e-3,), 0.5, box, on, ties))
    # a clip on drag cuts the damping's change too
    tight = Box(lo=on - 3.0, hi=on + 3.0)
    tight.hi[2, 0] = on[2, 0] + 0.01
    for trial, *_ in _steps(jac, r, (1e-3,), 0.5, tight, on, ties):
        np.testing.assert_allclose(share(trial), [0.25, 0.5], rtol=1e-9)
        assert trial[2, 0] <= tight.hi[2, 0] + 1e-15 and trial[1, 0] >= on[1, 0] - 0.01 - 1e-12

    class Ev:
        def __init__(self, names):
            self.prob = type("P", (), dict(names=names, theta0=np.zeros((len(names), 1))))()
    assert Ties.of(Ev(("k_structural", "damping", "nmol"))) is None
    assert Ties.of(Ev(("k_structural", "drag"))) is None


# --------------------------------------------------------------------------- blow-ups

@pytest.mark.heavy
def test_blown_up_step_is_rejected_and_the_step_halved():
    truth = _hanging()
    target = make_target(truth, 200, 3e-3, 20)
    start = _hanging(k_structural=25.0, nmol=truth.params.nmol[0])
    # a log-step of 2.5 takes k from 25 to ~300 N/m: unstable at dt = 3 ms, the rollout blows up
    res = F.fit(start, target, ("k_structural",), optimizer="adam", lr=2.5, iterations=25, noise_free=True,
                check_dt=False)
    assert res.rejected >= 1 and len(res.history["rejected"]) == res.rejected
    assert np.all(np.isfinite(res.history["loss"])) and np.all(np.isfinite(res.history["k_structural"]))
    assert res.loss < res.loss_start and np.isfinite(res.values["k_structural"]).all()
    # a start that blows up cannot proceed with Adam or L-BFGS: FitError (the CLI's exit 3), after
    # the dt warning (the default fit substeps it instead: tests/test_fit_robust.py)
    with pytest.warns(UserWarning, match="exceeds the estimated stability limit"):
        with pytest.raises(F.FitError, match="blows up .* at the start values"):
            F.fit(_hanging(k_structural=3000.0), target, ("k_structural",), optimizer="adam", iterations=3)


def _pressed_pair(k_a, capacity=None):
    """Two 12-vertex balls overlapping by 1 cm (soft-soft contact pushes them apart), no gravity."""
    a = icosphere_text(subdivisions=0, k=k_a, mass=0.04, nmol=5e-4, gravity=(0.0, 0.0, 0.0), name="a")
    b = icosphere_text(subdivisions=0, k=300.0, mass=0.08, nmol=8e-4, name="b", translate=(0.19, 0.0, 0.0),
                       offset=12, header=False)
    # a contact setting that --out-scene must carry over (not friction: the fused adjoint has none)
    head = "contact_thickness 0.05\n" + ("" if capacity is None else f"contact_capacity {capacity}\n")
    return jaxplush.parse_scene(head + a + b, "<pressed pair>")


@pytest.mark.heavy
def test_contact_capacity_overflow_is_grown_not_rejected():
    """A fit through soft-soft contact whose candidate lists are too short is rebuilt with a larger
    capacity (a warning names it) and goes on; the overflow is not taken for a blow-up."""
    from jaxplush.stepping.simulation import contact_capacity_needed
    dt = 2e-4
    truth = _pressed_pair(150.0)
    target = make_target(truth, 100, dt, 25)
    small = _pressed_pair(300.0, capacity=2)
    assert contact_capacity_needed(_hanging(), 10, 1e-3) is None          # no soft-soft contact
    # (a fit starts with twice the scene's capacity: 4, still too few)
    with pytest.warns(UserWarning, match=r"contact candidates overflowed \(capacity 4\).*contact_capacity"):
        res = F.fit(small, target, ("k_structural",), objects=["a"], optimizer="adam", iterations=4, noise_free=True,
                    check_dt=False, identifiability=False)
    assert res.rejected == 0 and np.all(np.isfinite(res.history["loss"]))
    assert res.loss < res.loss_start
    need = max(res.problem.sim.terms.contact.capacity)
    assert need > 4 and any(f"contact_capacity {need}" in w for w in res.warnings)
    # the grown capacity holds over the whole fitted run
    final = jaxplush.simulate(small, 100, dt, params=res.params, sim=res.problem.sim)
    assert not any("contact" in w for w in final.warnings)
    assert contact.capacity_report(res.problem.sim, final.positions[-1]) is None
    # --out-scene: the fitted values, the scene's contact settings and the capacity the fit ran with
    out = jaxplush.parse_scene(fitted_scene_text(res), "<fitted>")
    assert out.contact_capacity == need and out.contact_thickness == 0.05 and out.contact
    assert out.params.k_structural[0] == pytest.approx(res.values["k_structural"][0])


@pytest.mark.heavy
def test_evaluator_grows_the_contact_capacity_on_an_overflow_code():
    """The default fit's evaluator (batched, with contact) reads the health code
    CONTACT_OVERFLOW of its rollout, raises the capacity (a warning names it) and runs the point
    again; the frames it returns are those of the grown capacity."""
    from jaxplush.fitting.objective.evaluate import Evaluator
    from jaxplush.fitting.judge.identifiability import frames_at_steps
    dt = 2e-4
    target = make_target(_pressed_pair(150.0), 100, dt, 25)
    small = _pressed_pair(300.0, capacity=2)
    prob = F.build_problem(small, target, ("k_structural",), objects=["a"])
    p = prob.sim.params(prob.params_at(prob.theta0))
    frames, codes = jax.jit(lambda q: frames_at_steps(prob.sim, q, prob.sim.init_fn(q), prob.loss.frame_steps))(p)
    assert np.isfinite(np.asarray(frames)).all()
    assert (np.asarray(codes) == jaxplush.stepping.diagnostics.CONTACT_OVERFLOW).all()     # from the first frame on
    ev = Evaluator(prob)
    assert ev.batched                      # the batched path grows it (tests/test_batched_contact.py)
    assert max(prob.sim.terms.contact.capacity) == 4          # the fit's headroom: twice the scene's
    with pytest.warns(UserWarning, match=r"contact candidates overflowed \(capacity 4\).*contact_capacity"):
        e = ev(np.asarray(prob.theta0)[None], keep_frames=True)
    assert e.ok.all() and np.isfinite(e.loss).all() and len(ev.notes) == 1
    sim = ev.prob.sim
    assert max(sim.terms.contact.capacity) > 4
    ref, codes = jax.jit(lambda q: frames_at_steps(sim, q, sim.init_fn(q), prob.loss.frame_steps))(p)
    assert (np.asarray(codes) == jaxplush.stepping.diagnostics.OK).all()
    ref = np.asarray(ref, np.float64)
    assert np.linalg.norm(e.frames[0] - ref) <= 1e-4 * np.linalg.norm(ref)


# --------------------------------------------------------------------------- inputs

def test_parameter_and_object_selection():
    two = icosphere_text(name="a", translate=(-1, 0, 0), nmol=1e-4) + icosphere_text(
        name="b", translate=(1, 0, 0), nmol=1e-4, k=80.0, offset=42, header=False)
    scene = jaxplush.parse_scene(two, "<two>")
    target = Target(positions=scene.vertices[None] + 0.01, points=None, steps=np.array([10]), times=np.array([0.01]),
                    dt=1e-3, path="<memory>")     # nothing is simulated here
    prob = F.build_problem(scene, target, "k,nmol", objects="b", noise_free=True)
    assert prob.names == ("k_structural", "nmol") and prob.objects == (1,)
    p = prob.to_params(jnp.log(jnp.asarray([[200.0], [3e-4]])))
    np.testing.assert_allclose(np.asarray(p.k_structural), [100.0, 200.0], rtol=1e-6)
    np.testing.assert_allclose(np.asarray(p.nmol), [1e-4, 3e-4], rtol=1e-6)
    assert prob.labels == ("k_structural[b]", "nmol[b]")
    with pytest.raises(JaxplushError, match="unknown object 'c'"):
        F.build_problem(scene, target, "k", objects="c")
    with pytest.raises(JaxplushError, match="unknown parameter 'stiff'"):
        F.build_problem(scene, target, "stiff")
    with pytest.raises(JaxplushError, match="damping of object 'a': its start value is 0"):
        F.build_problem(scene, target, "damping")
    with pytest.raises(JaxplushError, match="refusing to fit total_weight jointly with k_structural"):
        F.build_problem(scene, target, "k,total_weight")
    with pytest.warns(UserWarning, match="mass must be measured, not fitted"):
        F.build_problem(scene, target, "total_weight,damping", start={"damping": 100.0})
    # start values from the caller; dashpot is compiled in when fitted
    prob = F.build_problem(scene, target, "dashpot", start={"dashpot": {"a": 0.1, "b": 0.2}})
    assert prob.sim.terms.dashpot and np.allclose(np.exp(prob.theta0), [[0.1, 0.2]])


# --------------------------------------------------------------------------- Ctrl-C, checkpoint, resume

def test_ctrl_c_saves_and_resume_reaches_the_same_answer(small, tmp_path, ctrl_c):
    _, start, target = small
    kw = dict(optimizer="adam", iterations=12, noise_free=True, identifiability=False, check_dt=False)
    ref = F.fit(start, target, NAMES, **kw)

    out = tmp_path / "FIT.h5"

    def interrupt(info):
        if info["iteration"] == 5:
            os.kill(os.getpid(), signal.SIGINT)   # a real Ctrl-C, delivered between iterations

    with pytest.raises(KeyboardInterrupt):
        F.fit(start, target, NAMES, checkpoint_path=out, checkpoint_every=100, callback=interrupt, **kw)
    saved = load_fit(out)
    assert saved["attrs"]["status"] == "interrupted" and saved["attrs"]["iterations"] == 6
    assert len(saved["history"]["loss"]) == 6

    res = F.fit(start, target, NAMES, checkpoint_path=out, resume=True, **kw)
    assert res.iterations == ref.iterations == 12
    np.testing.assert_array_equal(res.history["loss"], ref.history["loss"])
    for n in NAMES:
        np.testing.assert_array_equal(res.values[n], ref.values[n])
    done = load_fit(out)
    assert done["attrs"]["status"] == res.status                # the outcome (12 Adam steps: the limit)
    np.testing.assert_array_equal(done["params"]["k_structural"], ref.params.k_structural)
    # resuming another fit from this file is refused
    with pytest.raises(JaxplushError, match="checkpoint is of a different fit \\(names"):
        F.fit(start, target, ("k_structural",), optimizer="adam", iterations=2, noise_free=True, checkpoint_path=out,
              resume=True)
    with pytest.raises(JaxplushError, match="no checkpoint to resume"):
        F.fit(start, target, NAMES, checkpoint_path=tmp_path / "none.h5", resume=True)


def test_resume_refuses_a_different_setting(small, tmp_path):
    """A checkpoint resumes only the same fit: float64 vs float32, Adam with another iteration count
    (its learning-rate schedule spans them), other start or fixed values are all refused before
    anything is traced."""
    _, start, target = small
    out = tmp_path / "FIT.h5"
    kw = dict(noise_free=True, identifiability=False, check_dt=False, checkpoint_path=out)
    res = F.fit(start, target, NAMES, optimizer="adam", iterations=2, **kw)
    assert "undetermined" not in res.table()      # no report computed: no standard errors, not "undetermined"
    # the whole fit's compile time apart from the rest, in the result and in FIT.h5
    timing = load_fit(out)["timing_attrs"]
    assert set(timing) == {"wall_s", "compile_s", "trace_s", "programs", "cache_hits"}
    assert 0.0 <= timing["compile_s"] <= timing["wall_s"] and timing["programs"] >= 0
    assert 0 <= timing["cache_hits"] <= timing["programs"]
    assert timing["wall_s"] == res.timing.wall_s and timing["programs"] == res.timing.programs
    assert f"time: {res.timing.text()}" in res.table()
    with pytest.raises(JaxplushError, match="different fit \\(iterations: checkpoint 2, now 5; Adam"):
        F.fit(start, target, NAMES, optimizer="adam", iterations=5, resume=True, **kw)
    with pytest.raises(JaxplushError, match="different fit \\(params_hash"):
        F.fit(start, target, NAMES, optimizer="adam", iterations=2, resume=True, start={"k": 60.0}, **kw)
    with pytest.raises(JaxplushError, match="different fit \\(gtol"):
        F.fit(start, target, NAMES, optimizer="adam", iterations=2, resume=True, gtol=1e-3, **kw)
    with jax.enable_x64(True):
        with pytest.raises(JaxplushError, match="different fit \\(dtype: checkpoint 'float32', now 'float64'"):
            F.fit(start, target, NAMES, optimizer="adam", iterations=2, resume=True, **kw)
    assert load_fit(out)["attrs"]["status"] == "iteration_limit"     # 2 Adam steps: honestly not converged
    import h5py
    with h5py.File(out, "a") as f:       # a damaged checkpoint (or one of another version)
        del f["checkpoint"].attrs["stall"]
    with pytest.raises(JaxplushError, match="cannot read the checkpoint"):
        F.fit(start, target, NAMES, optimizer="adam", iterations=2, resume=True, **kw)


def test_ctrl_c_during_the_report_saves_the_finished_loop(small, tmp_path, monkeypatch):
    """Ctrl-C after the last iteration (health check, identifiability report) saves the finished
    loop; --resume then only redoes the report."""
    _, start, target = small
    out = tmp_path / "FIT.h5"
    kw = dict(optimizer="adam", iterations=3, noise_free=True, check_dt=False, checkpoint_path=out,
              checkpoint_every=100)

    def interrupted(*a, **k):
        raise KeyboardInterrupt
    monkeypatch.setattr(F._ident, "frames_and_jacobian", interrupted)
    with pytest.raises(KeyboardInterrupt):
        F.fit(start, target, NAMES, **kw)
    saved = load_fit(out)
    assert saved["attrs"]["status"] == "interrupted" and saved["attrs"]["iterations"] == 3
    assert len(saved["history"]["loss"]) == 3
    monkeypatch.undo()
    calls = []
    res = F.fit(start, target, NAMES, resume=True, callback=calls.append, **kw)
    assert calls == [] and res.iterations == 3 and res.identifiability is not None
    np.testing.assert_array_equal(res.history["loss"], saved["history"]["loss"])


def test_parameter_list_and_method_are_checked_before_tracing():
    assert F.canonical_names("k,damping,") == ("k_structural", "damping")
    assert F.canonical_names(" k , nmol") == ("k_structural", "nmol")
    with pytest.raises(JaxplushError, match="no parameters to fit"):
        F.canonical_names(",")
    scene = jaxplush.parse_scene(icosphere_text(floor=-1.0, nmol=1e-4).replace(
        "floor -1.0", "floor -1.0\nfloor_friction 0.5"), "<rough floor>")
    target = Target(positions=scene.vertices[None] + 0.01, points=None, steps=np.array([10]), times=np.array([0.01]),
                    dt=1e-3, path="<memory>")
    with pytest.raises(JaxplushError, match="unknown gradient method 'fast'"):
        F.build_problem(scene, target, "k", method="fast")
    with pytest.raises(JaxplushError, match="gradient method 'adjoint' does not support this scene"):
        F.build_problem(scene, target, "k", method="adjoint")
    assert F.build_problem(scene, target, "k", method="checkpoint").method == "checkpoint"
    with pytest.raises(JaxplushError, match="start value of k_structural for unknown object 'bear'"):
        F.build_problem(scene, target, "k", start={"k": {"bear": 50.0}})
    with pytest.raises(JaxplushError, match="unknown object 3"):
        F.build_problem(scene, target, "k", start={"k": {3: 50.0}})


# --------------------------------------------------------------------------- options and optimisers

def test_fit_options_and_keywords_are_checked_before_anything_is_built():
    """Keywords are FitOptions fields (or its groups' flat names); an unknown one is an error naming
    it and the valid ones, raised before the scene or target is looked at (None here)."""
    import optax
    from jaxplush.fitting import CheckpointOptions, FitOptions, SearchOptions
    opts = FitOptions().replace(iterations=7, samples=16, checkpoint_path="FIT.h5", resume=True)
    assert opts == FitOptions(iterations=7, search=SearchOptions(samples=16),
                              checkpoint=CheckpointOptions(path="FIT.h5", resume=True))
    assert FitOptions(lr=0.1).replace(lr=0.2).lr == 0.2 and FitOptions().search.samples is None
    with pytest.raises(JaxplushError, match=r"unknown option 'iteration' \(did you mean 'iterations'\?\); "
                                            r"valid options: iterations, lr, .*checkpoint_path"):
        F.fit(None, None, iteration=3)
    with pytest.raises(JaxplushError, match="unknown option 'colour'"):
        F.fit(None, None, options=FitOptions(), colour="red")
    assert FitOptions().replace(global_retries=None).search.retries is None
    assert FitOptions().replace(local_floor_step=None).local.floor_step is None
    bad = [(dict(iterations=0), "iterations must be >= 1"), (dict(samples=-1), "samples must be an integer >= 0"),
           (dict(global_retries=-1), "global_retries must be None or an integer >= 0"),
           (dict(local_floor_step=-1e-3), "local_floor_step must be a number > 0 or None"),
           (dict(starts=0), "starts must be an integer >= 1"), (dict(resume=True), "resume needs a checkpoint_path"),
           (dict(checkpoint_every=0), "checkpoint_every must be >= 1"), (dict(patience=0), "patience must be"),
           (dict(gtol=-1.0), "gtol must be a number >= 0"),
           (dict(optimizer="adam", lr=-0.1), "learning rate must be > 0"),
           (dict(optimizer="adam", bounds={"k": (1, 2)}), "bounds apply to the default fit"),
           (dict(optimizer=optax.adam(0.1), lr=0.1), "an optax transformation carries its own learning rate"),
           (dict(optimizer="sgd"), "unknown optimizer 'sgd'; expected one of lm, adam, lbfgs or an optax"),
           (dict(options={"iterations": 3}), "options must be a fitting.FitOptions"),
           (dict(search=dict(samples=3)), "search must be a fitting.SearchOptions")]
    for kw, msg in bad:
        with pytest.raises(JaxplushError, match=re.escape(msg)):
            F.fit(None, None, **kw)


def test_the_default_fits_tuning_knobs_are_options_that_a_resume_checks(small, tmp_path):
    """The default fit's tuning constants are fields of FitOptions' groups (LocalOptions,
    ContinuationOptions, SmoothingOptions) with flat keywords, checked before anything is built,
    refused with a gradient optimiser; a knob changes the search, and a checkpoint records the
    knobs: a resume with another is refused, and one that predates them resumes with the defaults."""
    import h5py
    from jaxplush.fitting import ContinuationOptions, FitOptions, LocalOptions, SmoothingOptions
    opts = FitOptions().replace(keep=1, local_xtol=1e-5, horizons=(0.5, 1.0), smooth_points=15)
    assert opts.local == LocalOptions(keep=1, xtol=1e-5) and opts.continuation == ContinuationOptions(
        horizons=(0.5, 1.0)) and opts.smoothing == SmoothingOptions(points=15)
    for kw, msg in [(dict(keep=0), "keep must be a whole number >= 1"), (dict(h_min=-1.0), "h_min must be a number > 0"),
                    (dict(secant_updates=-1), "secant_updates must be a whole number >= 0"),
                    (dict(secant_updates=1.5), "secant_updates must be a whole number >= 0"),
                    (dict(horizons=(0.5, 0.25)), "horizons must be increasing"),
                    (dict(optimizer="adam", smooth_points=15), "smoothing options apply to the default fit"),
                    (dict(local=dict(keep=1)), "local must be a fitting.LocalOptions")]:
        with pytest.raises(JaxplushError, match=re.escape(msg)):
            F.fit(None, None, **kw)
    _, start, target = small
    out = tmp_path / "FIT.h5"
    kw = dict(noise_free=True, identifiability=False, predictability=False, samples=4, starts=1, iterations=2)
    ref = F.fit(start, target, NAMES, checkpoint_path=out, **kw)
    assert list(ref.search["horizons"]) == [3, 5, 10]
    timing = load_fit(out)["timing_attrs"]          # the default fit's compile time apart from the rest
    assert 0.0 <= timing["compile_s"] <= timing["wall_s"] and timing["programs"] >= 0
    assert timing["compile_s"] + timing["trace_s"] <= timing["wall_s"] and timing["programs"] == ref.timing.programs
    assert list(F.fit(start, target, NAMES, horizons=(0.5, 1.0), **kw).search["horizons"]) == [5, 10]
    with pytest.raises(JaxplushError, match="different fit \\(continuation: checkpoint"):
        F.fit(start, target, NAMES, checkpoint_path=out, resume=True, horizons=(0.5, 1.0), **kw)
    with h5py.File(out, "a") as f:       # a checkpoint written before the knobs were recorded
        g = f["checkpoint"]
        g.attrs["settings"] = json.dumps({k: v for k, v in json.loads(g.attrs["settings"]).items()
                                          if k not in ("local", "continuation", "smoothing")})
    res = F.fit(start, target, NAMES, checkpoint_path=out, resume=True, **kw)
    for n in NAMES:
        np.testing.assert_array_equal(res.values[n], ref.values[n])


def test_the_default_fits_stages_recombine_and_reach_its_searches_result(small):
    """The stages (jaxplush.fitting.stages) recombined as the default fit's search (a global stage,
    then Levenberg-Marquardt over horizons of growing length) reach lmfit.run's best point bit for
    bit; a global stage alone gives its candidates, and a local stage after it goes on from them."""
    import warnings
    from jaxplush.fitting import FitOptions, stages
    from jaxplush.fitting.stages import lmfit
    _, start, target = small
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        prob = F.build_problem(start, target, NAMES, noise_free=True)
    box = lmfit.default_box(prob)
    run, _ = lmfit.run(prob, box, FitOptions().replace(samples=4, starts=2, iterations=3))
    objective = stages.Objective(prob, box)
    cont = stages.Continuation(local=stages.LocalLM(max_iter=3),
                               first=(stages.GlobalStage(samples=4, starts=2, linear=True),))
    (c,) = stages.run_stages(objective, prob.theta0, [cont])
    best = c.states[stages.order(c.states)[0]]
    np.testing.assert_array_equal(best.theta, run.best.theta)
    assert best.loss == run.best.loss and len(c.paths) == len(run.paths) == 3
    assert cont.terminate(objective, c) == (True, best.stopped)
    glob, local = stages.run_stages(objective, prob.theta0, [stages.GlobalStage(samples=4, starts=2),
                                                             stages.LocalLM(max_iter=2)])
    assert len(glob.states) == 2 and glob.result.loss.shape == (5,)
    assert all(s.iteration <= 2 and s.done for s in local.states)
    assert min(s.loss for s in local.states) <= min(s.loss for s in glob.states)
    # every stage's step returns a new state and leaves the one it was given as it was (what the
    # loop's checkpoints and callbacks hold); a stage hands on a candidate with its searches
    import copy
    import pickle
    g = stages.GlobalStage(samples=4, starts=2)
    s0 = g.init(objective, prob.theta0, None)
    snap = copy.deepcopy(s0)
    s1 = g.step(objective, s0)
    assert s1 is not s0 and pickle.dumps(s0) == pickle.dumps(snap) and s0.result is None
    cand = g.postprocess(objective, s1)
    assert isinstance(cand, stages.Candidate) and len(cand.searches) == 2
    assert cand.loss == min(x.loss for x in s1.states)
    lm = stages.LocalLM(max_iter=2)
    l0 = lm.init(objective, prob.theta0, cand)
    snap = copy.deepcopy(l0)
    l1 = lm.step(objective, l0)
    assert l1 is not l0 and pickle.dumps(l0) == pickle.dumps(snap) and (l0.rounds, l1.rounds) == (0, 1)
    assert all(a is not b for a, b in zip(l0.states, l1.states)) and cand.searches[0].iteration == 0


@pytest.mark.heavy
def test_user_optax_optimizer_and_options_object(small, tmp_path):
    """A user's optax transformation runs through the fit's loop: the options object and the same
    keywords give the identical fit, the loss falls from the start, the checkpoint records the
    transformation's state structure (a different one is refused on resume); optax.lbfgs() passed
    in runs exactly as optimizer="lbfgs" (its line search chooses the step)."""
    import optax
    from jaxplush.fitting import FitOptions
    _, start, target = small
    names = ("k_structural",)
    opts = FitOptions(iterations=6, noise_free=True, identifiability=False, check_dt=False)
    out = tmp_path / "FIT.h5"
    a = F.fit(start, target, names, optimizer=optax.adam(0.05), options=opts, checkpoint_path=out)
    b = F.fit(start, target, names, optimizer=optax.adam(0.05), iterations=6, noise_free=True,
              identifiability=False, check_dt=False)
    np.testing.assert_array_equal(a.history["loss"], b.history["loss"])
    assert a.optimizer == "optax" and a.iterations == 6 and a.loss < a.loss_start
    assert "ScaleByAdamState" in a.settings["optax_state"] and load_fit(out)["attrs"]["optimizer"] == "optax"
    with pytest.raises(JaxplushError, match="different fit \\(optax_state"):
        F.fit(start, target, names, optimizer=optax.sgd(0.05), options=opts, checkpoint_path=out, resume=True)
    with pytest.raises(JaxplushError, match="different fit \\(optimizer: checkpoint 'optax', now 'adam'"):
        F.fit(start, target, names, optimizer="adam", options=opts, checkpoint_path=out, resume=True)
    named = F.fit(start, target, names, optimizer="lbfgs", options=opts.replace(iterations=3))
    user = F.fit(start, target, names, optimizer=optax.lbfgs(), options=opts.replace(iterations=3))
    np.testing.assert_array_equal(named.history["loss"], user.history["loss"])
    assert user.loss < user.loss_start


def test_a_start_far_less_predictable_than_the_result_leaves_a_determined_fit_converged(monkeypatch):
    """The Jacobian's rounding noise is estimated from the drift measured at the start values. A
    start can drift far more than the fitted values do (a torus from x0.5: 0.086 mm against 0.0003
    mm at the truth), which once called every parameter of an exact fit rounding. A run at the
    fitted values reproduces the target to the residual the fit reached, so that bounds the
    yardstick: a noise-free fit of k and nmol that reaches the target stays converged."""
    import dataclasses
    from jaxplush.fitting.judge.outcome import Status
    truth = _hanging()
    p = truth.params
    target = make_target(truth, 200, 1e-3, 20)
    start = truth.replace(params=p._replace(k_structural=p.k_structural * 1.3, nmol=p.nmol * 0.8))
    measure = F.measure_predictability

    def drifting_start(prob, report=None, **kw):
        prob = measure(prob, **kw)
        pred = prob.predictability
        return dataclasses.replace(prob, predictability=dataclasses.replace(pred, drift_rms=pred.drift_rms * 1e4))

    monkeypatch.setattr(F, "measure_predictability", drifting_start)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = F.fit(start, target, ("k_structural", "nmol"), noise_free=True, samples=8)
    assert res.outcome.reached
    assert res.status == Status.CONVERGED, res.reason
    assert not res.identifiability.undetermined
    for n in ("k_structural", "nmol"):
        assert res.values[n][0] == pytest.approx(getattr(p, n)[0], rel=1e-3)


class _RoundingModel:
    """A stand-in evaluator: residuals r(theta) = A theta plus a pseudo-random 'rounding' term of
    RMS ``drift`` / sqrt 2 that changes completely with any change of theta (as a float32
    rollout's does): two runs lie ``drift`` apart (RMS), and a central-difference Jacobian column
    at step h carries noise drift / (2 h). With ``cubic`` (a vector of residuals), the residuals
    also move by ``cubic`` (theta_0 - theta_2)^3: no slope at theta = 0 along that combination,
    but a secant that grows with the step."""

    def __init__(self, a, drift, cubic=None):
        from types import SimpleNamespace
        self.a, self.drift = np.asarray(a, np.float64), float(drift)
        self.cubic = np.zeros(self.a.shape[0]) if cubic is None else np.asarray(cubic, np.float64)
        self.residual = SimpleNamespace(n=self.a.shape[0])

    def substeps_for(self, points):
        return np.ones(len(points), np.int64)

    def __call__(self, points, substeps=None):
        from jaxplush.fitting.objective.evaluate import Evaluation
        pts = np.asarray(points, np.float64).reshape(len(points), -1)
        res = []
        for t in pts:
            seed = np.frombuffer(np.round(t, 12).tobytes(), np.uint32)
            rng = np.random.default_rng(seed)
            res.append(self.a @ t + self.cubic * (t[0] - t[2]) ** 3
                       + self.drift / np.sqrt(2) * rng.standard_normal(self.a.shape[0]))
        res = np.asarray(res)
        n = len(pts)
        return Evaluation(res, (res ** 2).sum(1), np.ones(n, bool), np.ones(n, np.int64), np.zeros(n, bool))


@pytest.mark.parametrize("weak, resolved, measured", [(0.02, True, 1), (0.004, True, 2), (0.0, False, 2)])
def test_a_combination_the_search_step_cannot_resolve_is_measured_again_at_a_larger_step(weak, resolved, measured):
    """The search's last Jacobian (step h_min = 1e-3) carries rounding noise drift / (2 h):
    a combination whose effect is within 3x that noise is unresolved there. The report then
    takes a second Jacobian at ``resolve_h`` (1e-2), where the noise is 10x smaller: a weak but
    real combination (here a unit step along it moves the residuals by 2% of the strong
    ones', 7.5x the noise at 1e-2 and 0.75x at 1e-3) is resolved and its parameters determined.
    One five times weaker (1.5x the noise at 1e-2) is measured once more, at the step its
    measured effect asks for (within h_max), and resolved there; an exactly degenerate pair (two
    equal columns) stays unresolved at any step."""
    from types import SimpleNamespace
    from jaxplush.fitting import options as O
    from jaxplush.fitting.judge import identifiability as I
    from jaxplush.fitting.stages import search as S
    rng = np.random.default_rng(3)
    n = 4000
    q, _ = np.linalg.qr(rng.standard_normal((n, 3)))
    a = q * np.sqrt(n) * np.array([1.0, 0.5, 1.0])              # orthogonal columns, RMS 1 and 0.5 per unit step
    a[:, 2] = a[:, 0] + weak * np.sqrt(n) * q[:, 2]             # column 2 = column 0 + a weak own part
    # the weak direction (p0 - p2) / sqrt 2 of the real case moves the residuals by 0.02 / sqrt 2
    # RMS per unit step: with this rounding it is 7.5x the Jacobian noise drift / (2 h) at step
    # 1e-2 (resolved: > 3x) and 0.75x at 1e-3 (not)
    drift = (0.02 / np.sqrt(2)) * 2 * 1e-2 / 7.5
    model = _RoundingModel(a, drift)
    box = S.Box(lo=np.full((3, 1), -5.0), hi=np.full((3, 1), 5.0))
    theta = np.zeros((3, 1))
    local = O.LocalOptions()
    jac = S.jacobian(model, box, theta, local.h_min, 1, local)
    residual = model(theta[None]).residuals[0]
    labels = ("p0", "p1", "p2")
    first = I.analyse(jac, residual, labels, jac_noise=I.fd_noise(drift, local.h_min))
    assert first.unresolved and {"p0", "p2"} <= set(first.undetermined)      # at 1e-3 both cases are lost
    run = SimpleNamespace(best=SimpleNamespace(theta=theta, substeps=1), jac_step=local.h_min, residual=residual,
                          jac=jac)
    prob = SimpleNamespace(labels=labels, noise=None)
    notes = []
    again = F._resolve_again(prob, box, run, model, local, first, drift, 1.0, notes)
    assert notes and f"measured again at step {local.resolve_h:g}" in notes[0]
    assert len(notes) == measured, notes
    if measured > 1:
        h = float(notes[1].split("measured again at step ")[1].split(" ")[0])
        assert local.resolve_h < h <= local.h_max, notes
    if resolved:
        assert not again.unresolved and not again.undetermined, again.summary()
        assert np.all(np.isfinite(again.stderr))
    else:
        assert again.unresolved and {"p0", "p2"} <= set(again.undetermined), again.summary()
        assert "p1" not in again.undetermined


def test_a_larger_step_that_measures_another_slope_does_not_resolve_a_combination():
    """Two equal columns (p0 and p2 determined only together) and residuals cubic along p0 - p2:
    no slope there, so the combination is unresolved, but a central difference at step h sees a
    secant of h². At 1e-3 that secant is 0.6x the Jacobian's noise (unresolved); at 1e-2, 100x
    larger, it would pass as 60x the smaller noise there and the pair would be called determined.
    The two Jacobians differ along the combination by far more than their noise: the report keeps
    it unresolved and says why. Without the cubic term the same pair stays unresolved by the
    ladder (the parametrised test above): here only the check keeps it."""
    from types import SimpleNamespace
    from jaxplush.fitting import options as O
    from jaxplush.fitting.judge import identifiability as I
    from jaxplush.fitting.stages import search as S
    rng = np.random.default_rng(3)
    n = 4000
    q, _ = np.linalg.qr(rng.standard_normal((n, 3)))
    a = q * np.sqrt(n) * np.array([1.0, 0.5, 1.0])
    a[:, 2] = a[:, 0]
    local = O.LocalOptions()
    drift = 1e-4
    noise_b = I.fd_noise(drift, local.resolve_h)
    # along d = (1, 0, -1)/sqrt 2 a step-h Jacobian sees sqrt 2 c h² u: 60x noise_b at resolve_h
    c = 60.0 * noise_b / (np.sqrt(2) * local.resolve_h ** 2)
    cubic = c * q[:, 2] * np.sqrt(n)                            # RMS c
    model = _RoundingModel(a, drift, cubic)
    box = S.Box(lo=np.full((3, 1), -5.0), hi=np.full((3, 1), 5.0))
    theta = np.zeros((3, 1))
    jac = S.jacobian(model, box, theta, local.h_min, 1, local)
    residual = model(theta[None]).residuals[0]
    labels = ("p0", "p1", "p2")
    first = I.analyse(jac, residual, labels, jac_noise=I.fd_noise(drift, local.h_min))
    assert first.unresolved and {"p0", "p2"} <= set(first.undetermined)
    # the larger step alone would call the pair determined
    wide = S.jacobian(model, box, theta, local.resolve_h, 1, local)
    assert not I.analyse(wide, residual, labels, jac_noise=noise_b).unresolved
    run = SimpleNamespace(best=SimpleNamespace(theta=theta, substeps=1), jac_step=local.h_min, residual=residual,
                          jac=jac)
    notes = []
    again = F._resolve_again(SimpleNamespace(labels=labels, noise=None), box, run, model, local, first, drift, 1.0,
                             notes)
    assert again.unresolved and {"p0", "p2"} <= set(again.undetermined), again.summary()
    assert "p1" not in again.undetermined
    assert len(notes) == 1 and "differs from the one at step" in notes[0], notes
