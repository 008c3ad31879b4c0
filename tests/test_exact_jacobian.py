"""Exact Jacobians for the default fit's Levenberg-Marquardt (issue 29 item 2):
``LocalOptions(jacobian="forward")`` / ``jaxplush-fit --jacobian forward``."""

from __future__ import annotations

import numpy as np
import pytest

import jaxplush
from jaxplush.errors import JaxplushError
from jaxplush.fitting import fitter as F
from jaxplush.fitting.stages import search
from jaxplush.fitting.objective.evaluate import Evaluator
from jaxplush.fitting.options import FitOptions, LocalOptions
from jaxplush.fitting.targets import make_target

NAMES = ("k_structural", "damping", "nmol")


def _hanging(**kw):
    return jaxplush.parse_scene(F.recovery_scene_text(1, **kw), "<hanging>")


def _problem(kind="positions", **kw):
    truth = _hanging()
    p = truth.params
    start = _hanging(k_structural=1.3 * p.k_structural[0], damping=0.7 * p.damping[0], nmol=1.2 * p.nmol[0])
    target = make_target(truth, 90, 1e-3, 30, point_cloud=(kind == "points"), n_points=60)
    return F.build_problem(start, target, NAMES, noise_free=True, **kw)


@pytest.mark.parametrize("kind", ["positions", "points"])
def test_forward_jacobian_is_the_limit_of_central_differences(x64, kind):
    """In float64 the forward-mode Jacobian of the residual vector agrees with central differences
    of the same residuals, and the differences converge to it as the step shrinks (second order)."""
    prob = _problem(kind)
    ev = Evaluator(prob, calibrate=False)
    theta = np.asarray(prob.theta0, np.float64)
    jac = ev.forward_jacobian(theta)
    assert jac is not None and jac.shape == (ev.residual.n, theta.size)
    assert np.all(np.linalg.norm(jac, axis=0) > 0)
    errs = []
    for h in (1e-2, 2.5e-3):
        cols = []
        for j in range(theta.size):
            e = np.zeros(theta.size)
            e[j] = h
            r = ev(np.stack([theta.ravel() + e, theta.ravel() - e]).reshape(2, *theta.shape)).residuals
            cols.append((r[0] - r[1]) / (2 * h))
        fd = np.stack(cols, axis=1)
        errs.append(np.linalg.norm(fd - jac, axis=0) / np.linalg.norm(jac, axis=0))
    errs = np.asarray(errs)
    assert np.all(errs[1] < 2e-3), errs
    # the central differences close on the exact Jacobian as h^2 (4x smaller step: about 16x smaller)
    big = errs[0] > 1e-7
    assert np.all(errs[1][big] < errs[0][big] / 6), errs


def test_a_search_takes_forward_jacobians_where_they_apply_and_differences_elsewhere():
    """``search._forward_jacobians`` sets the exact Jacobian (at step h_min, counted as P
    evaluations) of a state that needs no substeps, and hands a state that needs them back for
    differences, untouched."""
    prob = _problem()
    ev = Evaluator(prob, calibrate=False)
    o = LocalOptions(jacobian="forward")
    theta = np.asarray(prob.theta0, np.float64)
    plain = search.LMState(theta=theta, loss=np.nan, radius=0.2)
    sub = search.LMState(theta=theta, loss=np.nan, radius=0.2, substeps=2)
    assert ev.forward_jacobian(theta, substeps=2) is None
    rest = search._forward_jacobians(ev, [plain, sub], o)
    assert rest == [sub] and sub.jac is None and sub.evaluations == 0
    assert plain.jac.shape == (ev.residual.n, theta.size) and plain.jac_h == o.h_min
    assert plain.evaluations == theta.size
    assert np.array_equal(plain.jac, ev.forward_jacobian(theta))


def test_the_jacobian_option_is_checked():
    for bad in ("exact", 1, None):
        with pytest.raises(JaxplushError, match="jacobian must be one of difference, forward"):
            F.fit(None, None, options=FitOptions(local=LocalOptions(jacobian=bad)))
    with pytest.raises(JaxplushError, match="local options apply to the default fit"):
        F.fit(None, None, optimizer="adam", options=FitOptions(local=LocalOptions(jacobian="forward")))


def test_a_fit_on_exact_jacobians_recovers_the_truth_and_differences_once_per_point():
    """The default fit with forward-mode Jacobians recovers a noise-free hanging ball from x1.3 /
    x0.7 / x1.2, and a search takes one Jacobian per accepted point of a horizon (a rejected step,
    which shrinks the trust radius, keeps it)."""
    truth = _hanging()
    p = truth.params
    start = _hanging(k_structural=1.3 * p.k_structural[0], damping=0.7 * p.damping[0], nmol=1.2 * p.nmol[0])
    target = make_target(truth, 200, 1e-3, 20)
    calls = []
    orig = Evaluator.forward_jacobian

    def counted(self, theta, substeps=1):
        calls.append((id(self), np.asarray(theta).copy()))
        return orig(self, theta, substeps)
    try:
        Evaluator.forward_jacobian = counted
        res = F.fit(start, target, NAMES, noise_free=True, progress=False, identifiability=False,
                    options=FitOptions(local=LocalOptions(jacobian="forward")))
    finally:
        Evaluator.forward_jacobian = orig
    assert calls, "the forward-mode Jacobian was never asked for"
    for n in NAMES:
        assert float(res.values[n][0]) == pytest.approx(float(getattr(p, n)[0]), rel=1e-2), (n, res.values)
    # never twice in a row at the same point of the same horizon (its own evaluator)
    assert all(a[0] != b[0] or not np.array_equal(a[1], b[1]) for a, b in zip(calls, calls[1:]))
