"""The default fit's float64 polish (``FitOptions.polish``, ``jaxplush-fit --polish float64``): one
more local search from the float32 fit's best point on the problem rebuilt in float64, judged in
float64; refused where it does not apply."""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np
import pytest

from jaxplush import fitting
from jaxplush.errors import JaxplushError
from jaxplush.fitting.io import load_fit

NAMES = ("k_structural", "nmol")


@pytest.fixture(scope="module")
def case(hanging_case):
    """42-vertex hanging ball, noise-free target, a start k x1.4 and nmol x0.8 (conftest)."""
    return hanging_case


def test_the_float64_polish_starts_from_the_float32_fit_and_is_judged_in_float64(case, tmp_path):
    truth, start, target = case
    kw = dict(noise_free=True, predictability=False, samples=8, starts=2)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        plain = fitting.fit(start, target, NAMES, **kw)
        res = fitting.fit(start, target, NAMES, polish="float64", checkpoint_path=tmp_path / "FIT.h5", **kw)
    assert np.dtype(plain.problem.sim.dtype) == np.float32
    assert np.dtype(res.problem.sim.dtype) == np.float64          # the judged problem is the float64 one
    assert any("polished in float64" in str(w) for w in res.warnings)
    assert res.intervals.method == "twins" and "twins in float32" in res.intervals.note
    assert res.status == "converged"
    for n in NAMES:                                                # a float64 fit's accuracy, or better
        err = abs(float(res.values[n][0] / getattr(truth.params, n)[0]) - 1)
        assert err <= max(1e-4, abs(float(plain.values[n][0] / getattr(truth.params, n)[0]) - 1)), (n, err)
        # its spreads are the float32 twins' (the target's precision): the truth within 4 of them
        assert res.intervals.contains(f"{n}[{truth.object_names[0]}]", float(getattr(truth.params, n)[0]), width=4)
    # the float64 search went on from the float32 fit's best point: its evaluations add to them
    assert res.search["global_thetas"].shape == plain.search["global_thetas"].shape
    saved = load_fit(tmp_path / "FIT.h5")
    assert '"polish": "float64"' in saved["attrs"]["settings"]
    assert saved["attrs"]["status"] == "converged"


def test_a_polish_that_does_not_apply_is_refused_before_anything_runs(case):
    _, start, target = case
    with pytest.raises(JaxplushError, match="polish must be one of 'off', 'float64'"):
        fitting.fit(start, target, NAMES, polish="float128")
    with pytest.raises(JaxplushError, match="polish is part of the default fit"):
        fitting.fit(start, target, NAMES, optimizer="adam", polish="float64")


def test_no_polish_beyond_the_predictable_horizon(case, monkeypatch):
    # beyond the horizon a float64 fit fits the target's own rounding drift (benchmarks/RESULTS.md:
    # seed 601's cases 14 and 40 came out worse polished): the fit measures the horizon at its
    # fitted values, says so and stays in float32
    from jaxplush.fitting import fitter as F
    _, start, target = case
    real, at = F._predictability_at, []

    def short(prob, theta=None, *a, **kw):    # the measurement, its horizon cut to the first frame
        at.append(theta)
        p = real(prob, theta, *a, **kw)
        return dataclasses.replace(p, horizon_frame=1, horizon_time=float(p.times[1]))
    monkeypatch.setattr(F, "_predictability_at", short)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = fitting.fit(start, target, NAMES, polish="float64", noise_free=True, samples=8, starts=2)
    assert np.dtype(res.problem.sim.dtype) == np.float32
    assert at and np.allclose(at[-1], np.log(np.stack([res.values[n] for n in NAMES])), rtol=0, atol=1e-12)
    assert any(str(w).startswith("not polished in float64: at the fitted values positions predictable")
               for w in res.warnings)
    assert not any("polished in float64 from" in str(w) for w in res.warnings)
