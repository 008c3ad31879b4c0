"""Every tuning knob of the default fit in one place: a named, documented field of its stage's
options, each default written once, and the fields are what the code reads (a changed field
changes what the search does)."""

from __future__ import annotations

import dataclasses
import math
from types import SimpleNamespace

import numpy as np
import pytest

from jaxplush.errors import JaxplushError
from jaxplush.fitting import options as O, stages
from jaxplush.fitting.stages import objects, search
from jaxplush.fitting.objective import shooting


@pytest.mark.parametrize("cls", list(O.TUNING.values()) + [O.SearchOptions, O.CheckpointOptions])
def test_every_option_field_is_documented_in_its_class(cls):
    doc = cls.__doc__
    attrs = doc[doc.index("Attributes:"):]
    for f in dataclasses.fields(cls):
        # a field is named at the start of an entry, alone or in a list ("h_min, h_max:")
        assert f"\n      {f.name}:" in attrs or f"\n      {f.name}," in attrs or f", {f.name}:" in attrs, (
            f"{cls.__name__}.{f.name} is not documented")


def test_defaults_are_written_once():
    assert stages.GlobalStage().samples == O.DEFAULT_SAMPLES == O.SearchOptions().n_samples
    assert stages.GlobalStage().starts == O.DEFAULT_STARTS == O.SearchOptions().n_starts
    assert objects.PerObjectGlobal().samples == O.DEFAULT_SAMPLES and objects.PerObjectGlobal().starts == O.DEFAULT_STARTS
    assert stages.LocalLM().max_iter == O.DEFAULT_ITERATIONS["lm"] == O.FitOptions().iteration_limit("lm")
    import inspect
    assert inspect.signature(search.global_stage).parameters["n"].default == O.DEFAULT_SAMPLES
    assert inspect.signature(search.lm_round).parameters["max_iter"].default == O.DEFAULT_ITERATIONS["lm"]
    d = O.ShootingOptions()
    assert (shooting.REFINE, shooting.MIN_HORIZON_FRAMES, shooting.RESOLUTION_STEP, shooting.MAX_BIAS) == (
        d.refine, d.min_horizon_frames, d.resolution_step, d.max_bias)
    assert search.COLOUR_MISSES == O.LocalOptions().colour_misses


def test_flat_names_reach_every_new_knob_and_bad_values_are_refused():
    opts = O.FitOptions().replace(shooting_refine=0, max_bias=0.1, min_segment=3, mu_fail=4.0, trial_mu=(0.5, 2.0),
                                  colour_misses=0, h_fraction=0.5)
    assert opts.multiple_shooting == O.ShootingOptions(refine=0, max_bias=0.1, min_segment=3)
    assert (opts.local.mu_fail, opts.local.trial_mu, opts.local.colour_misses) == (4.0, (0.5, 2.0), 0)
    O.validate(opts, "lm")
    for bad, msg in ((dict(min_segment=1), "min_segment must be a whole number >= 2"),
                     (dict(ratio_good=0.2), "ratio_poor"), (dict(mu_good=1.5), "mu_good"),
                     (dict(radius_fail=2.0), "radius_fail"), (dict(radius_grow=0.5), "radius_grow"),
                     (dict(trial_mu=(10.0, 1.0)), "trial_mu must be increasing"),
                     (dict(max_bias=-1.0), "max_bias must be a number > 0")):
        with pytest.raises(JaxplushError, match=msg):
            O.validate(O.FitOptions().replace(**bad), "lm")
    with pytest.raises(JaxplushError, match="multiple_shooting options apply to the default fit"):
        O.validate(O.FitOptions().replace(max_bias=0.1), "adam")


def _trial(theta, step, pred, mu):
    return (theta + step, step, pred, mu)


def _ev(losses, ok=True):
    n = len(losses)
    return SimpleNamespace(ok=np.full(n, ok), loss=np.asarray(losses, np.float64),
                           residuals=np.zeros((n, 3)), substeps=np.ones(n, int), separation=None)


def test_a_search_adapts_its_damping_and_radius_by_its_options():
    theta = np.zeros((1, 1))
    o = O.LocalOptions(mu_good=0.2, mu_poor=3.0, mu_fail=7.0, radius_fail=0.5, radius_grow=1.5, radius0=1.0)
    step = np.full((1, 1), 0.1)
    # better than predicted (rho = 1 > ratio_good): mu x mu_good, radius grows by radius_grow
    st = search.LMState(theta=theta, loss=1.0, mu=1.0, radius=0.2)
    search._take_step(st, _ev([0.5]), np.array([0]), [_trial(theta, step, 0.5, 1.0)], o)
    assert math.isclose(st.mu, 0.2) and math.isclose(st.radius, 0.3)
    # worse than predicted (rho = 0.1 < ratio_poor): mu x mu_poor, radius half the step
    st = search.LMState(theta=theta, loss=1.0, mu=1.0, radius=0.2)
    search._take_step(st, _ev([0.95]), np.array([0]), [_trial(theta, step, 0.5, 1.0)], o)
    assert math.isclose(st.mu, 3.0) and math.isclose(st.radius, 0.05)
    # no trial lowers the loss: mu x mu_fail, radius radius_fail x the step
    st = search.LMState(theta=theta, loss=1.0, mu=1.0, radius=0.2)
    search._take_step(st, _ev([1.5]), np.array([0]), [_trial(theta, step, 0.5, 1.0)], o)
    assert math.isclose(st.mu, 7.0) and math.isclose(st.radius, 0.05) and not st.done
    # the defaults as the search was tuned with
    st = search.LMState(theta=theta, loss=1.0, mu=1.0, radius=0.2)
    search._take_step(st, _ev([1.5]), np.array([0]), [_trial(theta, step, 0.5, 1.0)])
    assert math.isclose(st.mu, 10.0) and math.isclose(st.radius, 0.025)


def test_the_difference_step_and_the_trial_dampings_follow_the_options():
    assert search.fd_step(0.1) == 0.025
    assert search.fd_step(0.1, O.LocalOptions(h_fraction=0.5)) == 0.05
    assert search.fd_step(10.0, O.LocalOptions(h_fraction=0.5)) == O.LocalOptions().h_max

    class Ev:
        prob = None

        def __init__(self):
            self.asked = []

        def __call__(self, thetas):
            self.asked.append(np.asarray(thetas))
            n = len(thetas)
            return SimpleNamespace(ok=np.ones(n, bool), loss=np.full(n, 2.0), residuals=np.zeros((n, 2)),
                                   substeps=np.ones(n, int), separation=None)

    jac = np.array([[1.0], [0.5]])
    for trial_mu in ((0.1, 1.0, 10.0), (0.5, 2.0)):
        ev = Ev()
        st = search.LMState(theta=np.zeros((1, 1)), loss=1.0, mu=1.0, radius=0.08, jac=jac, jac_h=0.02,
                            residual=np.array([1.0, 1.0]))
        o = O.LocalOptions(trial_mu=trial_mu, pred_tol=0.0, noise_stop=0.0, radius0=1.0)
        search.lm_round(ev, search.Box(np.full((1, 1), -5.0), np.full((1, 1), 5.0)), [st], options=o)
        assert len(ev.asked) == 1 and len(ev.asked[0]) == len(trial_mu)       # one trial per damping
        assert st.mu == pytest.approx(max(trial_mu[0], 1.0) * o.mu_fail)        # none lowered the loss


def test_a_plan_on_a_single_shooting_target_keeps_its_options():
    prob = SimpleNamespace(predictability=None, target=None)
    sh, _ = shooting.plan(prob, "off", O.ShootingOptions(max_bias=0.05))
    assert not sh.on
    sh, _ = shooting.plan(prob, "auto")
    assert not sh.on and sh.options == O.ShootingOptions()
