"""The default fit's stages as pieces to recombine: one protocol, a few stages, a driver.

An :class:`Objective` is built from a problem (:func:`jaxplush.fitting.objective.problem.build_problem`) and
its search box: the residuals of the target at log values theta, batched and stable
(:class:`jaxplush.fitting.objective.evaluate.Evaluator`). A *stage* is any object with three methods:

* ``init(objective, theta, state) -> stage_state``: start at the log values ``theta`` (the
  problem's start values), or from ``state``, the previous stage's final state (None for the
  first stage): a local stage starts from the previous stage's searches (its ``states``);
* ``step(objective, stage_state) -> stage_state``: one step (a batch of evaluations), returning a
  new state and leaving the one it was given as it was (the driver's checkpoints and hooks hold
  states as they were);
* ``terminate(objective, stage_state) -> (bool, Stop)``: whether it is done, and why
  (:class:`jaxplush.fitting.judge.outcome.Stop`);
* optionally ``postprocess(objective, stage_state) -> Candidate``: the one point it hands on (a
  :class:`Candidate`: every stage here has one; a candidate may carry the searches it comes from,
  which a local stage starts from, and the Jacobian and residuals at its point). The next stage's
  ``init`` gets that candidate. A stage of one's own without it hands on its state itself, whose
  ``states`` (searches, as :class:`jaxplush.fitting.stages.search.LMState`) or ``theta`` the next stage
  starts from (:func:`start_points`).

``jaxplush.fitting.fit(scene, target, solver=[...])`` runs a user's list of stages and then the
one judge: the last stage's candidate is linearised (:class:`Linearise`) and judged as the default
fit's result is (outcome, intervals, identifiability, FIT.h5). :class:`Optax` makes an optax
transformation a stage like any other.

The stages of the default fit: :class:`GlobalStage` (a Sobol design over the box and the best
candidates), :class:`LocalLM` (Levenberg-Marquardt from them, with screening and rescues) and
:class:`Smoothing` (a noisy target's regression stage); :class:`Continuation` wraps stages to run
over horizons of growing length (the target's first frames, then more); :class:`Linearise`
takes the best point's residuals and Jacobian. :func:`run_stages` runs a list of stages in turn,
each from the last one's state, calling :class:`Hooks` around every step; its state
(:class:`RunState`: the stage running, its state, those finished) is plain data, which a
checkpoint holds (:mod:`jaxplush.fitting.io.treeio`) and ``run_stages`` resumes from.
:func:`jaxplush.fitting.stages.lmfit.run` is the default fit: ``run_stages`` of these stages, with
progress, the callback and checkpoints as hooks. Every tuning knob comes from the options
(:mod:`jaxplush.fitting.options`).

A stage of one's own needs no base class: ``init``, ``step`` and ``terminate`` are enough (the
docs/fitting.md's "Stages you can recombine" puts a user's Gauss-Newton solver after the global stage).
"""

from __future__ import annotations

import contextlib
import copy
import dataclasses
import math
import time
from typing import Protocol

import numpy as np

from jaxplush.fitting.stages import equation_error as _ee
from jaxplush.fitting.stages import search as _search
from jaxplush.fitting.objective import shooting as _shooting
from jaxplush.fitting.options import (DEFAULT_ITERATIONS, DEFAULT_SAMPLES, DEFAULT_STARTS, ContinuationOptions,
                                      LocalOptions, SmoothingOptions)
from jaxplush.fitting.judge.outcome import Stop


def own(state):
    """A copy of a stage's state that its ``step`` may change: stages leave the state they are
    given as it was (module docstring)."""
    return copy.deepcopy(state)


class Stage(Protocol):
    """The protocol every stage follows (module docstring)."""

    def init(self, objective, theta, state):
        ...

    def step(self, objective, state):
        ...

    def terminate(self, objective, state):
        ...


class Objective:
    """The residuals of a problem's target at log values theta, over a search box.

    Attributes:
      prob: :class:`jaxplush.fitting.objective.problem.Problem`; box: :class:`jaxplush.fitting.stages.search.Box`;
      evaluator: its :class:`jaxplush.fitting.objective.evaluate.Evaluator` (made on first use, or given).
    """

    def __init__(self, prob, box, evaluator=None):
        self.prob, self.box, self._evaluator = prob, box, evaluator
        self._horizons = None

    @property
    def evaluator(self):
        """The problem's evaluator: given, or the last horizon's of :meth:`horizons` (sharing its
        compiled rollout), or made on first use."""
        if self._evaluator is None:
            hs = self._horizons
            self._evaluator = hs(len(hs.horizons) - 1).evaluator if hs is not None else _shooting.evaluator(self.prob)
        return self._evaluator

    def horizons(self, frames, chunk_frames=None):
        """The :class:`Horizons` of this problem over the frame counts ``frames`` (made once; its
        rollouts in pieces of ``chunk_frames``, None: of the first horizon)."""
        frames = tuple(int(n) for n in frames)
        if self._horizons is None or self._horizons.horizons != frames:
            if self._horizons is not None or self._evaluator is not None:
                raise ValueError("an Objective holds the horizons of one continuation, made before its evaluator")
            self._horizons = Horizons(self.prob, self.box, frames, chunk_frames)
        return self._horizons

    def evaluations(self):
        """Points simulated by this objective's evaluators (its horizons' included)."""
        evs = {id(e): e for e in (self._horizons.by_stage.values() if self._horizons is not None else ())}
        if self._evaluator is not None:
            evs[id(self._evaluator)] = self._evaluator
        return sum(e.evaluations for e in evs.values())

    def floor(self):
        """The model's reproducibility floor over this objective's frames as a normalised loss
        (:func:`jaxplush.fitting.judge.result.rounding_drift`, measured at the start values; with multiple
        shooting, the shooting floor of its segments), for a noise-free position or tracks target
        (the drift per coordinate of a vertex, or of a point interpolated between vertices); None
        otherwise, or when it was not measured."""
        from jaxplush.fitting.judge.result import rounding_drift
        prob = self.prob
        if not prob.target.kind.material_points or (prob.noise is not None and prob.noise > 0):
            return None
        sh = prob.shooting
        # multiple shooting: the floor of its segments (what the outcome judges it by)
        drift = sh.floor if sh is not None and sh.on else rounding_drift(prob)
        if drift is None or not math.isfinite(drift):
            return None
        return drift * drift * prob.target.kind.components / prob.loss.scale2

    def residuals(self, theta):
        """(n,) residuals at one point (sum of squares: the loss), and whether it ran."""
        e = self.evaluator(np.asarray(theta, np.float64)[None])
        return e.residuals[0], bool(e.ok[0])

    def jacobian(self, theta, h):
        """(n, P) central-difference Jacobian at theta with step h (log space)."""
        return _search.jacobian(self.evaluator, self.box, theta, h)


def horizons(n_frames, continuation=None):
    """Frame counts of the stages in time (increasing, the last ``n_frames``) under ``continuation``
    (:class:`jaxplush.fitting.options.ContinuationOptions`, None: the defaults)."""
    c = continuation or ContinuationOptions()
    if n_frames < c.min_frames:
        return (int(n_frames),)
    out = sorted({max(2, int(math.ceil(f * n_frames))) for f in c.horizons})
    return tuple(out[:-1]) + (int(n_frames),) if out[-1] != n_frames else tuple(out)


class Horizons:
    """One :class:`Objective` per horizon (the problem truncated to its first frames), made on first
    use: each evaluator shares the first one's compiled rollout (frames in chunks of
    ``chunk_frames``, None: of the first horizon), its calibration, and a contact capacity grown
    at an earlier horizon."""

    def __init__(self, prob, box, horizons, chunk_frames=None):
        self.prob, self.box, self.horizons, self.by_stage = prob, box, horizons, {}
        self.chunk_frames = int(chunk_frames) if chunk_frames else int(horizons[0])

    def __call__(self, stage):
        """The :class:`Objective` of horizon ``stage`` (an index into ``horizons``)."""
        made = self.by_stage
        if stage not in made:
            sub = self.prob.truncated(self.horizons[stage])
            calibration = next((e.calibration() for e in made.values()), None)
            if made:              # a contact capacity grown at an earlier horizon carries over
                sub = dataclasses.replace(sub, sim=made[max(made)].prob.sim)
            share = made[min(made)] if made else None
            # frames in chunks of one length: every horizon runs the same compiled rollout
            made[stage] = _shooting.evaluator(sub, calibration=calibration, share=share, chunk_frames=self.chunk_frames)
        return Objective(made[stage].prob, self.box, made[stage])

    def notes(self):
        """The notes of every horizon's evaluator, the shortest horizon's first."""
        return [m for _, e in sorted(self.by_stage.items()) for m in e.notes]


def order(states):
    """Indices of ``states`` (:class:`jaxplush.fitting.stages.search.LMState`) by increasing loss."""
    return sorted(range(len(states)), key=lambda i: states[i].loss)


# --------------------------------------------------------------------------- the global stage

@dataclasses.dataclass
class GlobalState:
    """A :class:`GlobalStage`'s state: the start, the design's result and the searches it starts."""

    theta: np.ndarray
    result: object = None
    states: list = dataclasses.field(default_factory=list)
    linear: np.ndarray | None = None


@dataclasses.dataclass(frozen=True)
class GlobalStage:
    """The start and ``samples`` Sobol points of the box (:func:`jaxplush.fitting.stages.search.global_stage`),
    in one step; its ``states`` are :class:`jaxplush.fitting.stages.search.LMState` s at the best
    ``starts`` of them, each ``local.start_distance`` of the box's width from those before.

    With ``linear`` (and a problem it suits, :func:`jaxplush.fitting.stages.equation_error.suits`), the
    design also holds the start that needs no start values: indirect inference on the
    equation-error estimate (:func:`jaxplush.fitting.stages.equation_error.design_point`; ``GlobalState.linear``).

    Attributes: samples, starts, seed, retries, linear (:class:`jaxplush.fitting.options.SearchOptions`);
    local: :class:`jaxplush.fitting.options.LocalOptions` (the spacing, and the searches' radius and mu);
    progress: ``progress(n)`` after the design ran (or None).
    """

    samples: int = DEFAULT_SAMPLES
    starts: int = DEFAULT_STARTS
    seed: int = 0
    local: LocalOptions = LocalOptions()
    progress: object = None
    retries: int | None = None
    linear: bool = False

    def init(self, objective, theta, state=None):
        return GlobalState(theta=np.asarray(theta, np.float64))

    def step(self, objective, s):
        s = own(s)
        box, o = objective.box, self.local
        if self.linear and s.linear is None:
            s.linear = _ee.design_point(objective)
        extra = () if s.linear is None or not np.all(np.isfinite(s.linear)) else (s.linear,)
        s.result = _search.global_stage(objective.evaluator, box, s.theta, self.samples, self.seed,
                                        progress=self.progress, retries=self.retries, extra=extra)
        s.states = design_starts(s.result, self.starts, box, o)
        return s

    def terminate(self, objective, s):
        return s.result is not None, Stop.NONE

    def postprocess(self, objective, s):
        return searches_candidate(s.states, objective.prob.theta0, "the global design's best point")


def design_starts(result, starts, box, local):
    """The local searches a global design starts (:class:`jaxplush.fitting.stages.search.LMState`):
    at its best ``starts`` points, each ``local.start_distance`` of the box's width from those
    before, with ``local``'s damping and trust radius."""
    chosen = result.best(starts, local.start_distance * float(np.max(box.hi - box.lo)))
    return [_search.LMState(theta=result.thetas[i].copy(), loss=float(result.loss[i]), mu=local.mu0,
                            radius=local.radius0) for i in chosen]


# --------------------------------------------------------------------------- local Levenberg-Marquardt

@dataclasses.dataclass
class LocalState:
    """A :class:`LocalLM`'s state: its searches and the rounds done."""

    states: list
    rounds: int = 0


@dataclasses.dataclass(frozen=True)
class LocalLM:
    """Levenberg-Marquardt searches, one round of all of them per step
    (:func:`jaxplush.fitting.stages.search.lm_round`), then rescues of stalled ones
    (:func:`jaxplush.fitting.stages.search.rescue`) and screening (all but the best ``keep`` set aside after
    ``screen_rounds`` when ``screen``; any far above the best, always).

    Attributes:
      max_iter: iterations per search; options: :class:`jaxplush.fitting.options.LocalOptions`;
      noise_stop: the Gauss-Newton stop in standard errors (None: ``options.noise_stop``);
      screen: screen down to ``options.keep`` searches (the first stage of the default fit).
    """

    max_iter: int = DEFAULT_ITERATIONS["lm"]
    options: LocalOptions = LocalOptions()
    noise_stop: float | None = None
    screen: bool = False

    def init(self, objective, theta, state=None):
        """From the previous stage's searches (``state.states``), or one search at its point or theta."""
        o = self.options
        given = state.searches if isinstance(state, Candidate) else getattr(state, "states", None)
        if given:                   # searches to continue (a global design's starts, a shorter horizon's)
            states = start_points(state, theta)
        else:
            states = [_search.LMState(theta=s.theta, loss=math.inf, mu=o.mu0, radius=o.radius0)
                      for s in start_points(state, theta)]
        start_residuals(objective.evaluator, states, o)
        return LocalState(states=states)

    def step(self, objective, s):
        s = own(s)
        o = self.options
        ev, box, states = objective.evaluator, objective.box, s.states
        start_residuals(ev, states, o)          # those a resumed checkpoint left out (recomputed, identically)
        floor = getattr(objective, "floor", None)
        _search.lm_round(ev, box, states, self.max_iter, o, noise_stop=self.noise_stop,
                         floor=floor() if floor is not None else None)
        s.rounds += 1
        # a search that stalls on a jump of the loss restarts from the lowest point of a scan
        _search.rescue(ev, box, states, o.max_rescues, o)
        screen(states, s.rounds, self.screen and len(states) > o.keep, o)
        return s

    def terminate(self, objective, s):
        if any(not st.done for st in s.states):
            return False, Stop.NONE
        return True, s.states[order(s.states)[0]].stopped

    def postprocess(self, objective, s):
        return searches_candidate(s.states, objective.prob.theta0, "the best search")


def start_residuals(ev, states, local):
    """The residuals of the states that lack them (a fresh start, or a resumed one: deterministic,
    so the same values), in one evaluation."""
    need = [s for s in states if s.residual is None and not s.done]
    if not need:
        return
    fresh = _search.start_states(ev, np.asarray([s.theta for s in need]), options=local)
    for s, f in zip(need, fresh):
        s.residual, s.substeps, s.loss, s.separation = f.residual, f.substeps, f.loss, f.separation
        if not np.array_equal(f.theta, s.theta):     # put on its tied pairs' lines (search.Ties)
            s.theta, s.jac, s.updates = f.theta.copy(), None, 0
        if f.done:
            s.done, s.stopped, s.reason = f.done, f.stopped, f.reason
        if not s.history:
            s.history.append((f.loss, s.theta.copy()))


def screen(states, rounds, screening, local):
    """Set searches aside after ``rounds`` rounds: with ``screening``, all but the best ``keep`` after
    ``screen_rounds``; then (or without screening) any whose loss exceeds ``drop_factor`` x the best's."""
    if screening and rounds == local.screen_rounds:
        for i in order(states)[local.keep:]:
            if not states[i].done:
                states[i].done, states[i].stopped = True, Stop.SCREENED
                states[i].reason = f"set aside after {local.screen_rounds} iterations (loss {states[i].loss:.4g})"
    if rounds >= local.screen_rounds or not screening:
        best = min(s.loss for s in states)
        for s in states:
            if not s.done and s.loss > local.drop_factor * best:
                s.done, s.stopped = True, Stop.SCREENED
                s.reason = f"set aside: its loss {s.loss:.4g} is {s.loss / best:.3g}x the best search's"


# --------------------------------------------------------------------------- the best point, linearised

@dataclasses.dataclass
class LinearState:
    """A :class:`Linearise` stage's state: the best search (``best``, a
    :class:`jaxplush.fitting.stages.search.LMState`), the residuals and Jacobian at its point, and the
    residuals (``start_residual``; ``start_ok``: it ran; ``start_substeps``; ``start_separation``:
    how close its objects came) and loss ``loss0`` of the start values; ``ran``: stepped."""

    best: object
    residual: np.ndarray | None = None
    jac: np.ndarray | None = None
    start_residual: np.ndarray | None = None
    start_ok: bool = False
    start_substeps: int = 1
    loss0: float = math.nan
    ran: bool = False
    start_separation: float = math.nan


@dataclasses.dataclass(frozen=True)
class Linearise:
    """The best search of the previous stage, linearised in one step: its residuals and those of the
    start values (one batch), and the Jacobian at its point with step ``local.h_min`` (as many
    substeps as either it or the search needed). What the smoothing stage starts from and the
    outcome is judged by.

    Attributes: local (:class:`jaxplush.fitting.options.LocalOptions`).
    """

    local: LocalOptions = LocalOptions()

    def init(self, objective, theta, state=None):
        states = start_points(state, theta)
        return LinearState(best=states[order(states)[0]], start_residual=None)

    def step(self, objective, s):
        s = own(s)
        ev, b = objective.evaluator, s.best
        centre = ev(np.asarray([b.theta, np.asarray(objective.prob.theta0, np.float64)]))
        if not np.isfinite(b.loss):          # a candidate handed on unevaluated
            b.loss, b.substeps = float(centre.loss[0]), int(centre.substeps[0])
        if not b.history:
            b.history.append((float(b.loss), np.asarray(b.theta, np.float64).copy()))
        s.residual, s.loss0 = centre.residuals[0], float(centre.loss[1])
        s.start_residual, s.start_ok, s.start_substeps = centre.residuals[1], bool(centre.ok[1]), int(centre.substeps[1])
        s.start_separation = _search._separation(centre, 1)
        n_sub = max(int(centre.substeps[0]), b.substeps)
        s.jac = _search.jacobian(ev, objective.box, b.theta, self.local.h_min, n_sub, self.local,
                                 separation=_search._separation(centre, 0))
        s.ran = True
        return s

    def terminate(self, objective, s):
        return s.ran, Stop.NONE

    def postprocess(self, objective, s):
        b = s.best
        return Candidate(theta=np.asarray(b.theta, np.float64), loss=float(b.loss), reason=b.reason, searches=(b,),
                         jac=s.jac, residual=s.residual, stopped=b.stopped)


# --------------------------------------------------------------------------- smoothing

@dataclasses.dataclass
class SmoothState:
    """A :class:`Smoothing` stage's state: its start, Jacobian and residuals there, and its result
    (:class:`jaxplush.fitting.stages.search.Smoothed`, or None: singular Jacobian, or skipped); ``ran``:
    stepped (or skipped: a search the callback stopped is not smoothed)."""

    theta: np.ndarray
    jac: np.ndarray | None
    residual: np.ndarray | None
    result: object = None
    ran: bool = False


@dataclasses.dataclass(frozen=True)
class Smoothing:
    """The smoothing stage of a noisy target (:func:`jaxplush.fitting.stages.search.smooth`), in one step,
    from the previous stage's best point: a :class:`Linearise` state's (its Jacobian and residuals),
    or the best search's (its Jacobian taken at ``local.h_min``), or theta.

    Attributes: options (:class:`jaxplush.fitting.options.SmoothingOptions`), local
    (:class:`jaxplush.fitting.options.LocalOptions`), seed, progress (``progress(1, extra=...)``).
    """

    options: SmoothingOptions = SmoothingOptions()
    local: LocalOptions = LocalOptions()
    seed: int = 0
    progress: object = None

    def init(self, objective, theta, state=None):
        if getattr(state, "jac", None) is not None:          # a linearised candidate (Linearise's)
            skip = state.stopped == Stop.CALLBACK
            return SmoothState(theta=np.asarray(state.theta, np.float64), jac=state.jac, residual=state.residual,
                               ran=skip)
        states = start_points(state, theta)
        theta = states[order(states)[0]].theta
        residual, _ = objective.residuals(theta)
        jac = _search.jacobian(objective.evaluator, objective.box, theta, self.local.h_min, options=self.local)
        return SmoothState(theta=theta, jac=jac, residual=residual)

    def step(self, objective, s):
        s = own(s)
        s.result = _search.smooth(objective.evaluator, objective.box, s.theta, s.jac, s.residual, seed=self.seed,
                                  progress=self.progress, options=self.options)
        s.ran = True
        return s

    def terminate(self, objective, s):
        return s.ran, Stop.NONE


# --------------------------------------------------------------------------- continuation in time

def local_for(local, index, n_horizons, noisy, continuation):
    """The :class:`LocalLM` of horizon ``index`` of ``n_horizons`` in the default fit: ``local``
    screening on the first horizon; before the last (and on the last of a ``noisy`` target, which
    the smoothing stage resolves) at most ``continuation.iterations`` iterations and the
    continuation's Gauss-Newton stop."""
    out = dataclasses.replace(local, screen=index == 0)
    if index + 1 < n_horizons or noisy:
        out = dataclasses.replace(out, max_iter=min(local.max_iter, continuation.iterations),
                                  noise_stop=continuation.noise_stop)
    return out


def carry(states, keep, continuation):
    """The searches that start the next horizon: of the best ``keep``, those within
    ``carry_factor`` of the best loss, one per point (``same_point``), with the trust radius
    ``next_radius`` (a longer horizon moves the optimum little) and their damping (at most 1)."""
    kept = []
    best_loss = states[order(states)[0]].loss
    for i in order(states)[:keep]:
        s = states[i]
        # searches that ended at the same point continue as one, and one that ended far
        # above the best (in another basin) stops here: a longer horizon does not rescue it
        if (math.isfinite(s.loss) and s.loss <= continuation.carry_factor * best_loss
                and all(np.max(np.abs(s.theta - o.theta)) > continuation.same_point for o in kept)):
            kept.append(s)
    return [_search.LMState(theta=s.theta.copy(), loss=math.inf, radius=continuation.next_radius,
                            mu=min(s.mu, 1.0)) for s in kept]


@dataclasses.dataclass
class ContinuationState:
    """A :class:`Continuation`'s state (plain data, as a checkpoint holds it): the horizons (frame
    counts), the horizon running (``index``), on the first horizon which of the ``first`` stages runs
    (``position``; past them, the local stage), the running stage's state (``inner``), the final
    states of the ``first`` stages, and the finished horizons' searches (``paths``: per horizon, the
    (loss, theta) path of each search and why it ended); ``stepped``: the state the running stage's
    last step returned, before the move to the next stage or horizon (what a progress bar or a
    callback reads; a checkpoint leaves it out)."""

    horizons: tuple
    index: int = 0
    position: int = 0
    inner: object = None
    first: list = dataclasses.field(default_factory=list)
    paths: list = dataclasses.field(default_factory=list)
    done: bool = False
    stepped: object = None

    @property
    def states(self):
        return getattr(self.inner, "states", [])


@dataclasses.dataclass(frozen=True)
class Continuation:
    """Stages over horizons of growing length (:func:`horizons`): ``first`` (e.g. a
    :class:`GlobalStage`) and then ``local`` on the target's first frames; on each longer horizon,
    ``local`` (:func:`local_for`) from the searches :func:`carry` keeps. Its ``states`` are the
    running stage's; one step is one step of the running stage. The horizons' objectives are the
    objective's (:meth:`Objective.horizons`).

    Attributes: local (:class:`LocalLM`), first (stages before it on the first horizon),
    options (:class:`jaxplush.fitting.options.ContinuationOptions`), noisy (a noisy target: the
    last horizon's searches stop as the earlier ones' do, for :class:`Smoothing` to resolve).
    """

    local: LocalLM = LocalLM()
    first: tuple = ()
    options: ContinuationOptions = ContinuationOptions()
    noisy: bool = False

    def init(self, objective, theta, state=None):
        s = ContinuationState(horizons=horizons(objective.prob.target.n_frames, self.options))
        s.inner = self.stage(s).init(self.objective(objective, s), theta, state)
        return s

    def stage(self, s):
        """The stage running in state ``s``."""
        if s.index == 0 and s.position < len(self.first):
            return self.first[s.position]
        return local_for(self.local, s.index, len(s.horizons), self.noisy, self.options)

    @staticmethod
    def objective(objective, s):
        """The :class:`Objective` of the horizon running in state ``s``."""
        return objective.horizons(s.horizons)(s.index)

    def step(self, objective, s):
        s = dataclasses.replace(s, first=list(s.first), paths=list(s.paths), stepped=None)
        obj, stage = self.objective(objective, s), self.stage(s)
        if not stage.terminate(obj, s.inner)[0]:      # (a hook may have stopped its searches)
            s.inner = s.stepped = stage.step(obj, s.inner)
            if not stage.terminate(obj, s.inner)[0]:
                return s
        theta0 = objective.prob.theta0
        if s.index == 0 and s.position < len(self.first):
            s.first.append(s.inner)
            s.position += 1
            s.inner = self.stage(s).init(obj, theta0, _handed(stage, obj, s.inner))
            return s
        s.paths.append([(list(x.history), x.reason) for x in s.states])
        if s.index + 1 < len(s.horizons) and not any(x.stopped == Stop.CALLBACK for x in s.states):
            carried = carry(s.states, self.local.options.keep, self.options)
            s.index += 1
            s.inner = self.stage(s).init(self.objective(objective, s), theta0,
                                         searches_candidate(carried, theta0, "carried to a longer horizon"))
        else:
            s.done = True
        return s

    def terminate(self, objective, s):
        if not s.done:
            return False, Stop.NONE
        return True, s.states[order(s.states)[0]].stopped if s.states else Stop.NONE

    def postprocess(self, objective, s):
        return searches_candidate(s.states, objective.prob.theta0, "the best search of the last horizon")


# --------------------------------------------------------------------------- the driver

# --------------------------------------------------------------------------- candidates

@dataclasses.dataclass(frozen=True, eq=False)
class Candidate:
    """The point a stage hands on (its ``postprocess``): log values ``theta`` (the problem's
    shape), their ``loss`` if known (inf: not evaluated; the next stage evaluates it) and a
    ``reason`` for a person. Its ``states`` make it a start for any stage that starts from
    searches (:class:`LocalLM`, :class:`Linearise`, :class:`Smoothing`).

    A stage may say more: ``searches``, the searches (:class:`jaxplush.fitting.stages.search.LMState`)
    it comes from, best first, which a local stage continues all of (a global design's best
    starts, say); ``jac`` (n, P) and ``residual`` (n,) at theta, when it linearised there
    (:class:`Linearise`), which the smoothing stage starts from; ``stopped``: why the search at
    theta stopped (:class:`jaxplush.fitting.judge.outcome.Stop`)."""

    theta: np.ndarray
    loss: float = math.inf
    reason: str = ""
    searches: tuple = ()
    jac: np.ndarray | None = None
    residual: np.ndarray | None = None
    stopped: Stop = Stop.NONE

    @property
    def states(self):
        """Searches to start from (copies): its ``searches``, or one at theta."""
        if self.searches:
            return [dataclasses.replace(s, theta=np.asarray(s.theta, np.float64).copy(), history=list(s.history))
                    for s in self.searches]
        return [_search.LMState(theta=np.asarray(self.theta, np.float64).copy(), loss=float(self.loss),
                                reason=self.reason, stopped=self.stopped)]


def searches_candidate(states, theta, reason):
    """The :class:`Candidate` of a stage that ends in searches ``states``: the best one's point,
    with every search (in their order) for the next stage to continue; at ``theta`` (log values)
    when there is none."""
    if not states:
        return Candidate(theta=np.asarray(theta, np.float64), reason=reason)
    b = states[order(states)[0]]
    return Candidate(theta=np.asarray(b.theta, np.float64), loss=float(b.loss), reason=b.reason or reason,
                     searches=tuple(states), stopped=b.stopped)


def _handed(stage, objective, state):
    """What a finished ``stage`` hands the next one: its ``postprocess`` candidate, or its state."""
    post = getattr(stage, "postprocess", None)
    return post(objective, state) if post is not None else state


def start_points(state, theta):
    """The searches (:class:`jaxplush.fitting.stages.search.LMState`) a stage starts from, given the
    previous stage's handed-on ``state``: its ``states``, or one search at its ``theta``, or (no
    previous stage) one at ``theta``. Each is a copy the new stage may change."""
    states = getattr(state, "states", None)
    if states:
        return [dataclasses.replace(s, theta=np.asarray(s.theta, np.float64).copy(), history=list(s.history))
                for s in states]
    point = getattr(state, "theta", None)
    point = np.asarray(theta if point is None else point, np.float64).copy()
    return [_search.LMState(theta=point, loss=math.inf)]


# --------------------------------------------------------------------------- an optax transformation

@dataclasses.dataclass
class OptaxState:
    """An :class:`Optax` stage's state: the point, the transformation's state, the updates done,
    and the best point seen (``best_theta``, ``best_loss``); ``done`` and ``reason``."""

    theta: np.ndarray
    opt_state: object
    iteration: int = 0
    best_theta: np.ndarray | None = None
    best_loss: float = math.inf
    history: list = dataclasses.field(default_factory=list)
    done: bool = False
    reason: str = ""


@dataclasses.dataclass(frozen=True)
class Optax:
    """An optax ``GradientTransformation`` as a stage: ``steps`` updates of the log-parameters
    from the previous stage's best point, each with the loss gradient 2 Jᵀr from a
    central-difference Jacobian (step ``h``, log space) on the objective's batched engine (one
    batch of 2 P + 1 rollouts); each new point is held in the search box. A point that does not
    run is stepped back from (the update halved, its state kept). Its candidate is the best point
    it evaluated.

    Attributes: transformation (e.g. ``optax.adam(0.05)``), steps, h.
    """

    transformation: object
    steps: int = 20
    h: float = 1e-3

    def init(self, objective, theta, state=None):
        import jax.numpy as jnp
        best = min(start_points(state, theta), key=lambda s: s.loss)
        theta = np.asarray(best.theta, np.float64)
        return OptaxState(theta=theta, opt_state=self.transformation.init(jnp.asarray(theta.ravel())))

    def step(self, objective, s):
        import jax.numpy as jnp
        s = own(s)
        e = objective.evaluator(np.asarray(s.theta)[None])
        loss = float(e.loss[0]) if e.ok[0] else math.inf
        if loss < s.best_loss:
            s.best_theta, s.best_loss = s.theta.copy(), loss
        s.history.append((loss, s.theta.copy()))
        if not np.isfinite(loss):
            # the point does not run: back halfway to the best one, the transformation's state kept
            s.theta = 0.5 * (s.theta + s.best_theta) if s.best_theta is not None else s.theta
            s.iteration += 1
            s.done, s.reason = s.iteration >= self.steps, f"{self.steps} optax updates"
            return s
        jac = _search.jacobian(objective.evaluator, objective.box, s.theta, self.h, int(e.substeps[0]),
                               separation=_search._separation(e, 0))
        grad = 2.0 * jac.T @ np.nan_to_num(e.residuals[0])
        updates, s.opt_state = self.transformation.update(jnp.asarray(grad), s.opt_state,
                                                           jnp.asarray(s.theta.ravel()))
        box = objective.box
        s.theta = np.clip(s.theta + np.asarray(updates, np.float64).reshape(s.theta.shape), box.lo, box.hi)
        s.iteration += 1
        s.done, s.reason = s.iteration >= self.steps, f"{self.steps} optax updates"
        return s

    def terminate(self, objective, s):
        return s.done, Stop.ITERATIONS if s.done else Stop.NONE

    def postprocess(self, objective, s):
        theta = s.best_theta if s.best_theta is not None else s.theta
        return Candidate(theta=np.asarray(theta, np.float64), loss=s.best_loss,
                         reason=f"the best of {s.iteration} optax updates (loss {s.best_loss:.4g})")


@dataclasses.dataclass
class RunState:
    """:func:`run_stages`' state (what the default fit checkpoints): the stage running (``index``
    into the list of stages) and its state (None: not started), the final states of the stages
    before it, and the seconds and evaluations (:meth:`Objective.evaluations`) spent so far."""

    index: int = 0
    state: object = None
    finished: list = dataclasses.field(default_factory=list)
    wall: float = 0.0
    evaluations: int = 0


@dataclasses.dataclass(frozen=True)
class Hooks:
    """What :func:`run_stages` calls around each step (each optional): ``before(run)`` before it
    (e.g. to open a progress bar), ``after(run)`` after it (progress; a callback, which may stop the
    running stage's searches), then ``save(run)`` (a checkpoint); on Ctrl-C, ``interrupted(run)``
    (a checkpoint of the last finished step: ``run.state`` is never half-way through one), before
    the ``KeyboardInterrupt`` goes on. ``run`` is the :class:`RunState`."""

    before: object = None
    after: object = None
    save: object = None
    interrupted: object = None


@contextlib.contextmanager
def saving_on_interrupt(save):
    """Run the block; on Ctrl-C (``KeyboardInterrupt``, which the command line also raises on
    SIGTERM) call ``save()`` and re-raise. ``save`` is looked up when the interrupt comes, so it
    sees the last consistent state; it decides itself whether there is anywhere to save to. Every
    fit family (the default fit, the gradient optimisers, the stiffness field) saves this way."""
    try:
        yield
    except KeyboardInterrupt:
        save()
        raise


def handed_on(stages, objective, run):
    """What the last finished stage of ``run`` hands the next one: its ``postprocess`` candidate
    where it has one, else its final state (None before the first stage)."""
    if not run.finished:
        return None
    return _handed(stages[len(run.finished) - 1], objective, run.finished[-1])


def run_stages(objective, theta, stages, *, hooks=None, state=None):
    """Run ``stages`` in turn, each from the previous one's final state (the first from theta), and
    return the list of their final states.

    Args:
      objective: an :class:`Objective` (or any object the stages take).
      theta: the start (log values); every stage's ``init`` gets it.
      stages: stages (the protocol of the module docstring).
      hooks: :class:`Hooks` called around every step (None: none).
      state: a :class:`RunState` to continue (a checkpoint's) or to fill (None: a fresh one); it
        holds the run's progress as it goes.
    """
    run = state if state is not None else RunState()
    hooks = hooks or Hooks()
    count = getattr(objective, "evaluations", None)
    t0, wall0, evals0 = time.perf_counter(), run.wall, run.evaluations
    n0 = count() if count is not None else 0
    with saving_on_interrupt(lambda: hooks.interrupted(run) if hooks.interrupted is not None else None):
        while run.index < len(stages):
            stage = stages[run.index]
            if run.state is None:
                run.state = stage.init(objective, theta, handed_on(stages, objective, run))
            while not stage.terminate(objective, run.state)[0]:
                if hooks.before is not None:
                    hooks.before(run)
                run.state = stage.step(objective, run.state)
                run.wall = wall0 + time.perf_counter() - t0
                if count is not None:
                    run.evaluations = evals0 + count() - n0
                if hooks.after is not None:
                    hooks.after(run)
                if hooks.save is not None:
                    hooks.save(run)
            run.finished.append(run.state)
            run.index, run.state = run.index + 1, None
    return list(run.finished)
