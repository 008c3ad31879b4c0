"""The default fit's driver: continuation in time, a global stage, local Levenberg-Marquardt.

:func:`run` takes a built :class:`jaxplush.fitting.objective.problem.Problem` and its search box and returns a
:class:`LMRun`: the global samples, every local search, the best point, its residuals and
finite-difference Jacobian, and the gradients the outcome is judged by.

Continuation in time. A lightly damped body oscillates, and the phase of a mode of frequency
omega after time t moves by about omega t / 2 per e-fold of k: over a long target the loss
along log k has a minimum every few percent to few tens of percent, each a local optimum of
its own (a torus ringing for 0.6 s has one every 0.25 in log k). Over the first quarter of the
target it has one, wide minimum. So the fit runs in stages over the target's first
``horizons`` of its frames (:class:`jaxplush.fitting.options.ContinuationOptions`: a quarter, a
half, all): the global stage and the screening of
local starts on the shortest, then each stage's best points start the next, longer one, whose
minimum lies close by (for an exact model, at the same parameters).

The run is a list of the stages of :mod:`jaxplush.fitting.stages` (:func:`default_stages`: a
:class:`~jaxplush.fitting.stages.Continuation` of a :class:`~jaxplush.fitting.stages.GlobalStage` and
:class:`~jaxplush.fitting.stages.LocalLM` per horizon, :class:`~jaxplush.fitting.stages.Linearise`, and
for a noisy target :class:`~jaxplush.fitting.stages.Smoothing`) run by
:func:`jaxplush.fitting.stages.run_stages`, with hooks around its steps: progress per stage and
horizon, the callback after every local iteration, and a checkpoint of the driver's state
(:class:`~jaxplush.fitting.stages.RunState`, :func:`light_copy`) after every step, so ``resume``
continues an interrupted fit to the same answer (every evaluation is deterministic). This module
then reads the result off the final states (the smoothed optimum, the gradients). Every tuning
constant is a field of the :class:`jaxplush.fitting.options.FitOptions` that :func:`run` takes
(its ``search``, ``local``, ``continuation`` and ``smoothing`` groups).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from jaxplush.progress import Progress

from jaxplush.fitting.stages import objects as _objects
from jaxplush.fitting.stages import search as _search
from jaxplush.fitting import stages as _stages
from jaxplush.fitting.options import FitOptions
from jaxplush.fitting.judge.outcome import Stop
from jaxplush.fitting.stages import horizons  # noqa: F401  (jaxplush.fitting.stages.lmfit.horizons)

@dataclasses.dataclass
class LMRun:
    """The result of a default fit, read off the driver's final state.

    Attributes:
      best: the best search (:class:`jaxplush.fitting.stages.search.LMState`; for a noisy target at the
      smoothed optimum); jac (n, P) its Jacobian (at step ``h_min``, or the smoothing's slope);
      residual (n,); grad, grad0: loss gradients (log space) at the best point and at the start values;
      global_result: :class:`jaxplush.fitting.stages.search.GlobalResult`;
      paths: per finished horizon, the (loss, theta) paths of its searches and why each ended;
      horizons: the frame counts of the horizons; loss0: the loss of the start values on the whole target;
      wall: seconds spent; evaluations: points simulated;
      smoothed: the :class:`jaxplush.fitting.stages.search.Smoothed` stage of a noisy target's fit (else None);
      state: the driver's final :class:`jaxplush.fitting.stages.RunState` (as a checkpoint holds it);
      jac_step: the central-difference step (log space) of ``jac``, None for the smoothing's slope.
    """

    best: object
    jac: np.ndarray
    residual: np.ndarray
    grad: np.ndarray
    grad0: np.ndarray
    global_result: object
    paths: list
    horizons: tuple
    loss0: float
    wall: float = 0.0
    evaluations: int = 0
    smoothed: object = None
    state: object = None
    jac_step: float | None = None


def default_box(prob, bounds=None, factor=4.0, centre=None):
    """The search box in log space: each fitted parameter from start/factor to start*factor (or
    about the log values ``centre``), or ``bounds`` {name: (lo, hi)} (absolute values, every
    fitted object); damping stays >= 1."""
    th0 = np.asarray(prob.theta0 if centre is None else centre, np.float64)
    lo, hi = th0 - math.log(factor), th0 + math.log(factor)
    for i, n in enumerate(prob.names):
        if bounds and n in bounds:
            a, b = bounds[n]
            lo[i], hi[i] = math.log(a), math.log(b)
        if n == "damping":
            lo[i] = np.maximum(lo[i], 0.0)
    return _search.Box(lo, hi)


_order = _stages.order


def _noisy(prob):
    return prob.noise is not None and prob.noise > 0


def default_stages(prob, opts, progress=None, smooth=True):
    """The default fit's stages under ``opts`` (:class:`jaxplush.fitting.options.FitOptions`):
    the global stage and local Levenberg-Marquardt over horizons of growing length, the best point
    linearised, and for a noisy target the smoothing stage (unless ``smooth`` is False: a float64
    polish, whose loss is not rough). ``progress(n, extra=...)``: what the global and smoothing
    stages report their progress to."""
    local = opts.local
    # several fitted objects, positions observed: each object's parameters scored by its own residuals
    kind = _objects.PerObjectGlobal if _objects.suits(prob) else _stages.GlobalStage
    first = kind(samples=opts.search.n_samples, starts=opts.search.n_starts, seed=opts.search.seed,
                 local=local, progress=progress, retries=opts.search.retries, linear=opts.search.linear)
    out = [_stages.Continuation(local=_stages.LocalLM(max_iter=opts.iteration_limit("lm"), options=local),
                                first=(first,), options=opts.continuation, noisy=_noisy(prob)),
           _stages.Linearise(local=local)]
    if smooth and _noisy(prob):
        out.append(_stages.Smoothing(options=opts.smoothing, local=local, progress=progress))
    return out


def run(prob, box, options=None, *, progress=False, resume=None, save=None, interrupted=None, callback=None,
        start=None, stages=None, smooth=True, chunk_frames=None, finish=True, objective=None):
    """Global stage, then Levenberg-Marquardt from the best ``starts`` candidates (successive
    halving to ``keep``), over horizons of growing length; then the Jacobian and gradients at
    the best point of the full problem (and, for a noisy target, the smoothing stage):
    :func:`jaxplush.fitting.stages.run_stages` of :func:`default_stages`.

    Args:
      prob: :class:`jaxplush.fitting.objective.problem.Problem`; box: :class:`jaxplush.fitting.stages.search.Box`.
      options: :class:`jaxplush.fitting.options.FitOptions` (None: the defaults): ``search``
        (Sobol points of the global stage, plus the start itself; local starts; the seed),
        ``iterations`` (Levenberg-Marquardt iterations per start and stage), ``local``,
        ``continuation`` and ``smoothing`` (the tuning knobs).
      progress: draw progress bars on stderr.
      resume: a :class:`jaxplush.fitting.stages.RunState` from a checkpoint to continue.
      save: ``save(run)`` after every step, with the driver's :class:`~jaxplush.fitting.stages.RunState`.
      interrupted: ``interrupted(run)`` on Ctrl-C, with the driver's state after its last finished
        step (:class:`~jaxplush.fitting.stages.Hooks`), before the ``KeyboardInterrupt`` goes on.
      callback: ``callback(local)`` after every local iteration with the local stage's state (its
        ``states`` and ``rounds``); returning True stops the search.
      start: where the global stage starts (log values; None: ``prob.theta0``, which stays the
        start the fit's gradient ratio and start loss refer to).
      stages: a user's stages to run instead of :func:`default_stages` (``fit(solver=...)``): they
        run on the whole target, and the last one's candidate is linearised (:class:`Linearise`)
        for the judge.
      smooth: the default stages end with the smoothing stage for a noisy target (False: they do
        not; :func:`default_stages`).
      chunk_frames: the piece length of the horizons' rollouts (None: the first horizon's), for
        a fit that runs on programs compiled for a longer target's horizons.
      finish: False: return (the driver's :class:`~jaxplush.fitting.stages.RunState`, the
        :class:`~jaxplush.fitting.stages.Objective`) without the result, for a fit that goes on
        from that state (``resume``) on that objective (``objective``: its evaluators, compiled
        and calibrated).

    Returns:
      (:class:`LMRun`, the :class:`jaxplush.fitting.objective.evaluate.Evaluator` of the full problem, its notes
      those of every horizon).
    """
    opts = options or FitOptions()
    show = _Show(prob, opts, progress, callback)
    user = stages is not None
    if user:
        stages = list(stages) + [_stages.Linearise(local=opts.local)]
    else:
        stages = default_stages(prob, opts, show.feed, smooth=smooth)
    show.stages = stages
    objective = _stages.Objective(prob, box) if objective is None else objective
    hs = None if user else objective.horizons(horizons(prob.target.n_frames, opts.continuation), chunk_frames)
    state = resume if resume is not None else _stages.RunState()
    try:
        _stages.run_stages(objective, prob.theta0 if start is None else np.asarray(start, np.float64), stages,
                           state=state,
                           hooks=_stages.Hooks(before=show.before, after=show.after, save=save,
                                               interrupted=interrupted))
    finally:
        show.close()
    if not finish:
        return state, objective
    n0 = objective.evaluations()
    out = _result(objective, state, opts)
    out.evaluations = state.evaluations + objective.evaluations() - n0
    ev = objective.evaluator
    if hs is not None:
        ev.notes[:] = hs.notes()
    return out, ev


def _start_gradient(objective, lin, local):
    """The loss gradient (log space) at the start values, from the :class:`Linearise` state ``lin``
    (inf where the start did not run)."""
    th0 = np.asarray(objective.prob.theta0, np.float64)
    if not lin.start_ok:
        return np.full(th0.size, np.inf)
    jac0 = _search.jacobian(objective.evaluator, objective.box, th0, local.h_max, lin.start_substeps, local,
                            separation=lin.start_separation)
    return 2.0 * jac0.T @ lin.start_residual


def _result(objective, state, opts):
    """The :class:`LMRun` of the driver's final ``state`` (left as it is), found by what its stages
    are, not where they stand: the best point and its Jacobian from the :class:`Linearise` stage
    (every run ends in one, or in the smoothing stage after it); for a noisy target the smoothing
    stage's optimum, whose regression slope and intercept (at the last design's centre) stand for
    the Jacobian and residuals; the global design of the first stage that ran one (else an empty
    one); the horizons and paths of a continuation, or each stage's searches' paths; then the
    gradients at the best point and at the start values. A point handed on without a stopping
    rule of its own (a design's best, a candidate) ended with the stages' budget: an iteration limit."""
    ev, local, prob = objective.evaluator, opts.local, objective.prob
    finished = state.finished
    lin = linearised(state)
    sm = next((s.result for s in finished if isinstance(s, _stages.SmoothState)), None)
    cont = next((s for s in finished if isinstance(s, _stages.ContinuationState)), None)
    best = dataclasses.replace(lin.best, history=list(lin.best.history))
    if best.stopped == Stop.NONE:
        best.stopped = Stop.ITERATIONS
        best.reason = best.reason or "the last stage ended"
    designs = [x for s in finished for x in ([s] + list(getattr(s, "first", [])))]
    g = next((s.result for s in designs if isinstance(getattr(s, "result", None), _search.GlobalResult)), None)
    if g is None:
        shape = (0,) + np.shape(prob.theta0)
        g = _search.GlobalResult(thetas=np.zeros(shape), loss=np.zeros(0), ok=np.zeros(0, bool),
                                 substeps=np.zeros(0, np.int64))
    if cont is not None:
        paths, hz = [list(p) for p in cont.paths], cont.horizons
    else:
        paths = [[(list(x.history), x.reason) for x in s.states if isinstance(x, _search.LMState) and x.history]
                 for s in finished if s is not lin and getattr(s, "states", None)]
        paths, hz = [p for p in paths if p], (int(prob.target.n_frames),)
    jac, residual, smoothed = lin.jac, lin.residual, None
    e = ev(np.asarray(sm.theta)[None]) if sm is not None else None
    if e is not None and e.ok[0]:
        smoothed = sm
        best.theta, best.loss, best.residual = sm.theta.copy(), float(e.loss[0]), e.residuals[0]
        best.substeps = int(e.substeps[0])
        history = list(sm.path) + [(best.loss, best.theta.copy())]
        best.history.extend(history)
        jac, residual = sm.jac, sm.residual
        worst = float(np.max(np.abs(sm.step) / sm.stderr))
        reason = (f"smoothed over {len(sm.path)} regression design(s): the Gauss-Newton step of the last is "
                  f"{worst:.2g} of the standard errors")
        best.reason = f"{best.reason}; {reason}" if best.reason else reason
        if paths:
            paths[-1].append((history, reason))
    grad0 = _start_gradient(objective, lin, local)
    return LMRun(best=best, jac=jac, residual=residual, grad=2.0 * jac.T @ np.nan_to_num(residual), grad0=grad0,
                 global_result=g, paths=paths, horizons=hz, loss0=lin.loss0, wall=state.wall, smoothed=smoothed,
                 state=state, jac_step=None if smoothed is not None else float(local.h_min))


def linearised(run):
    """The best point of a driver state whose stages have run up to their :class:`Linearise` stage
    (:class:`~jaxplush.fitting.stages.LinearState`: its ``best``, Jacobian and residuals)."""
    return next(s for s in run.finished[::-1] if isinstance(s, _stages.LinearState))


def best_search(run):
    """The best search (:class:`jaxplush.fitting.stages.search.LMState`) of a driver state so far, or None."""
    for st in [run.state] + run.finished[::-1]:
        states = getattr(st, "states", None)
        if states:
            return states[_order(states)[0]]
    return None


def light_copy(run):
    """The driver's state as a checkpoint holds it: without the searches' residuals and differenced
    Jacobians (which a resumed fit recomputes, identically) and a continuation's ``stepped``. A
    secant-updated Jacobian (``updates`` > 0) cannot be recomputed and is kept. Stages return new
    states and leave old ones as they were, so this shares their arrays: only the containers the
    driver itself fills (its lists) are new."""
    def strip(x):
        if isinstance(x, _search.LMState):
            return dataclasses.replace(x, residual=None, jac=x.jac if x.updates else None)
        if isinstance(x, _stages.ContinuationState):
            x = dataclasses.replace(x, stepped=None)
        if dataclasses.is_dataclass(x) and not isinstance(x, type):
            return dataclasses.replace(x, **{f.name: strip(getattr(x, f.name))
                                             for f in dataclasses.fields(x) if f.init})
        if type(x) in (list, tuple):
            return type(x)(strip(v) for v in x)
        return x
    return strip(run)


class _Show:
    """The default fit's progress bars (one per stage and horizon) and the user's callback, as the
    driver's ``before`` and ``after`` hooks."""

    def __init__(self, prob, opts, enabled, callback):
        self.prob, self.opts, self.enabled, self.callback = prob, opts, enabled, callback
        self.stages, self.bar, self.key, self.inner, self.active = None, None, None, None, False

    def feed(self, n=1, **kw):
        """Progress inside a step (the global design's batches, the smoothing's designs)."""
        if self.bar is not None:
            self.bar.update(n, **kw)

    def before(self, run):
        s = run.state
        if isinstance(s, _stages.ContinuationState):
            key, inner = (run.index, s.index, s.position), s.inner
        else:
            key, inner = (run.index,), s
        self.inner = inner
        self.active = not (isinstance(inner, _stages.LocalState) and all(x.done for x in inner.states))
        if key != self.key:
            self.close()
            self.key = key
            self.bar = self._open(run, s, inner)

    def _open(self, run, s, inner):
        opts, on = self.opts, self.enabled
        stage = self.stages[run.index]
        if isinstance(s, _stages.ContinuationState):
            hs = s.horizons
            label = f", stage {s.index + 1}/{len(hs)} ({hs[s.index]} of {hs[-1]} frames)"
            first = stage.first[0] if s.index == 0 and s.position < len(stage.first) else None
            inner_stage = stage.stage(s)
        else:            # a stage of a user's solver, run on its own
            label, first, inner_stage = f" (stage {run.index + 1})", stage, stage
        if isinstance(inner, _stages.GlobalState):
            bar = Progress(getattr(first, "samples", opts.search.n_samples) + 1, f"global search{label}", enabled=on,
                           unit="points", compiles=True)
        elif isinstance(inner, _objects.PerObjectState):
            total = first.evaluations(len(self.prob.objects))
            bar = Progress(total, f"global search per object{label}", enabled=on, unit="points", compiles=True)
        elif isinstance(inner, _stages.LocalState):
            total = inner_stage.max_iter
            bar = Progress(total, f"local search{label}", enabled=on, unit="it", compiles=True)
            bar.done = min(inner.rounds, total)
        elif isinstance(s, _stages.SmoothState):
            bar = Progress(opts.smoothing.iterations, "smoothing (regression designs)", enabled=on, unit="designs",
                           compiles=True)
        else:
            return None
        return bar.__enter__()

    def after(self, run):
        s = run.state               # the state the step returned (stages leave the old one as it was)
        inner = (s.stepped if s.stepped is not None else s.inner) if isinstance(s, _stages.ContinuationState) else s
        bar = self.bar
        if bar is None or not self.active:
            return
        if isinstance(inner, _objects.PerObjectState):
            g = inner.result
            if g is not None:
                bar.extra = f"best loss {np.min(np.where(g.ok, g.loss, np.inf)):.4g}"
            if inner.states:
                bar.finish(f"{inner.rounds} rounds" + (f", {int((~g.ok).sum())} failed" if (~g.ok).any() else ""))
                self.close()
        elif isinstance(inner, _stages.GlobalState):
            g = inner.result
            bar.extra = f"best loss {np.min(np.where(g.ok, g.loss, np.inf)):.4g}"
            bar.finish(f"{int((~g.ok).sum())} failed" if (~g.ok).any() else "")
            self.close()
        elif isinstance(inner, _stages.LocalState):
            states = inner.states
            b = states[_order(states)[0]]
            bar.update(1, extra=f"loss {b.loss:.4g} " + " ".join(
                ("k" if n == "k_structural" else n) + " " + ",".join(f"{x:.4g}" for x in np.atleast_1d(v))
                for n, v in self.prob.values(b.theta).items()))
            if self.callback is not None and self.callback(inner) is True:
                for x in states:
                    if not x.done:
                        x.done, x.stopped, x.reason = True, Stop.CALLBACK, "stopped by the callback"
            if all(x.done for x in states):
                bar.finish(states[_order(states)[0]].reason)
                self.close()
        elif isinstance(inner, _stages.SmoothState):
            sm = inner.result
            bar.finish("skipped: singular Jacobian" if sm is None else
                       ("the step is within the standard errors" if sm.converged else
                        f"stopped after {len(sm.path)} designs"))
            self.close()

    def close(self):
        if self.bar is not None:
            self.bar.__exit__(None, None, None)
        self.bar = None
