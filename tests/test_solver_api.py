"""The fit as stages a researcher composes, with public imports only: the global stage alone, an
optax transformation or one's own stage after it, each ending in the one judge (a FitResult and
a FIT.h5), checkpoints and Ctrl-C handled by the loop, and bad solvers refused before anything runs."""

from __future__ import annotations

import os
import signal

import numpy as np
import optax
import pytest

from jaxplush import fitting
from jaxplush.errors import JaxplushError
from jaxplush.fitting.io import load_fit
from jaxplush.fitting.judge.outcome import STATUSES, Status

NAMES = ("k_structural", "nmol")


@pytest.fixture(scope="module")
def case(hanging_case):
    """42-vertex hanging ball, noise-free target, a start k x1.4 and nmol x0.8 (conftest)."""
    return hanging_case


KW = dict(noise_free=True, predictability=False)


class GaussNewton:
    """A user's own stage: Gauss-Newton steps from the previous stage's best point."""

    def __init__(self, steps=4):
        self.steps = steps

    def init(self, objective, theta, state):
        return {"theta": min(state.states, key=lambda s: s.loss).theta if state else theta, "k": 0}

    def step(self, objective, s):
        r, _ = objective.residuals(s["theta"])
        dx = np.linalg.lstsq(objective.jacobian(s["theta"], 1e-3), r, rcond=None)[0]
        return {"theta": objective.box.clip(s["theta"] - dx.reshape(np.shape(s["theta"]))), "k": s["k"] + 1}

    def terminate(self, objective, s):
        return s["k"] >= self.steps, None

    def postprocess(self, objective, s):
        return fitting.Candidate(theta=s["theta"], reason=f"{s['k']} Gauss-Newton steps")


def _err(res, truth):
    return max(abs(float(res.values[n][0] / getattr(truth.params, n)[0]) - 1) for n in NAMES)


def test_the_global_stage_alone_is_judged_and_saved(case, tmp_path):
    truth, start, target = case
    res = fitting.fit(start, target, NAMES, solver=[fitting.GlobalStage(samples=8, starts=2)], **KW)
    assert isinstance(res, fitting.FitResult) and res.status in STATUSES
    # a design's best point: judged as any fit (its stopping rule is the stages' budget)
    assert res.status in (Status.CONVERGED, Status.ITERATION_LIMIT, Status.POOR_FIT)
    assert res.search["global_thetas"].shape[0] == 9                         # the start and 8 Sobol points
    assert res.loss == pytest.approx(float(np.min(res.search["global_loss"])), rel=1e-6)
    res.save(tmp_path / "FIT.h5")
    saved = load_fit(tmp_path / "FIT.h5")
    assert saved["attrs"]["status"] == res.status
    assert saved["fitted"]["positions"].shape == target.positions.shape     # what jaxplush view shows


def test_an_optax_stage_and_a_users_own_stage_after_the_global_stage(case):
    truth, start, target = case
    glob = fitting.GlobalStage(samples=8, starts=2)
    alone = fitting.fit(start, target, NAMES, solver=[glob], **KW)
    adam = fitting.fit(start, target, NAMES, solver=[glob, fitting.Optax(optax.adam(0.01), steps=6)], **KW)
    assert adam.loss <= alone.loss                   # it keeps the best point it evaluated
    assert adam.intervals is not None and adam.identifiability is not None
    # the gradient optimisers' own stage (exact gradients through the rollout) composes as well
    grad = fitting.fit(start, target, NAMES, solver=[glob, fitting.Gradient(optax.adam(0.02), iterations=6)], **KW)
    assert grad.loss <= alone.loss and grad.intervals is not None
    gn = fitting.fit(start, target, NAMES, solver=[glob, GaussNewton()], **KW)
    assert gn.status == Status.CONVERGED and _err(gn, truth) < 1e-3, (gn.status, _err(gn, truth))
    assert gn.loss < 1e-3 * alone.loss
    # the same stages as the default fit's local search give a converged fit too
    lm = fitting.fit(start, target, NAMES, solver=[glob, fitting.LocalLM(max_iter=20)], **KW)
    assert lm.status == Status.CONVERGED and _err(lm, truth) < 1e-3


def test_a_fit_of_ones_own_stages_resumes_from_its_checkpoint(case, tmp_path, ctrl_c):
    truth, start, target = case
    solver = [fitting.GlobalStage(samples=8, starts=2), fitting.LocalLM(max_iter=6)]
    ref = fitting.fit(start, target, NAMES, solver=solver, **KW)
    out = tmp_path / "FIT.h5"
    seen = []

    def interrupt(info):
        seen.append(info["iteration"])
        if len(seen) == 2:
            os.kill(os.getpid(), signal.SIGINT)       # a real Ctrl-C, inside the local stage

    with pytest.raises(KeyboardInterrupt):
        fitting.fit(start, target, NAMES, solver=solver, checkpoint_path=out, callback=interrupt, **KW)
    assert load_fit(out)["attrs"]["status"] == "interrupted"
    res = fitting.fit(start, target, NAMES, solver=solver, checkpoint_path=out, resume=True, **KW)
    for n in NAMES:
        np.testing.assert_array_equal(res.values[n], ref.values[n])
    assert res.status == ref.status
    # another list of stages does not resume this checkpoint
    with pytest.raises(JaxplushError, match="different fit"):
        fitting.fit(start, target, NAMES, solver=[fitting.GlobalStage(samples=8, starts=2), GaussNewton()],
                    checkpoint_path=out, resume=True, **KW)


def test_a_solver_that_is_not_a_list_of_stages_is_refused_before_anything_runs(case):
    _, start, target = case
    for bad, msg in (([object()], r"solver\[0\] \(object\) is not a stage: it has no init, step, terminate"),
                     ([], "solver is empty"), ("GlobalStage", "solver must be a sequence of stages"),
                     (fitting.GlobalStage(), "solver must be a sequence of stages")):
        with pytest.raises(JaxplushError, match=msg):
            fitting.fit(start, target, NAMES, solver=bad, **KW)
    with pytest.raises(JaxplushError, match="does not go with optimizer 'adam'"):
        fitting.fit(start, target, NAMES, optimizer="adam", solver=[fitting.GlobalStage()], **KW)


class _Interrupt:
    """A stage whose first start is a Ctrl-C (once per test: ``fired``)."""

    def __init__(self):
        self.fired = False

    def init(self, objective, theta, state):
        if not self.fired:
            self.fired = True
            raise KeyboardInterrupt
        return state

    def step(self, objective, s):
        return s

    def terminate(self, objective, s):
        return True, None


@pytest.mark.parametrize("make", [lambda: fitting.Optax(optax.adam(0.01), steps=4),
                                  lambda: fitting.Gradient(optax.adam(0.02), iterations=6)],
                         ids=["optax", "gradient"])
def test_an_optax_stage_is_checkpointed_and_resumed(case, tmp_path, make):
    """The optax stage's state, or the gradient optimisers' (the transformation's state included),
    goes into the checkpoint and comes back: a fit interrupted after it resumes to the
    uninterrupted fit's values."""
    truth, start, target = case
    glob, adam = fitting.GlobalStage(samples=8, starts=2), make()
    ref = fitting.fit(start, target, NAMES, solver=[glob, adam], **KW)
    out, stop = tmp_path / "FIT.h5", _Interrupt()
    with pytest.raises(KeyboardInterrupt):
        fitting.fit(start, target, NAMES, solver=[glob, adam, stop], checkpoint_path=out, **KW)
    res = fitting.fit(start, target, NAMES, solver=[glob, adam, stop], checkpoint_path=out, resume=True, **KW)
    for n in NAMES:
        np.testing.assert_array_equal(res.values[n], ref.values[n])
