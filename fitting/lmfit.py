"""The default fit's driver: continuation in time, a global stage, local Levenberg-Marquardt.

:func:`run` takes a built :class:`jaxplush.fitting.fitter.Problem` and its search box and returns a
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

Progress is shown per stage; the run's state is checkpointed after the global stage and after
every local iteration (:func:`jaxplush.fitting.io.save_lm_checkpoint`), so ``resume`` continues an
interrupted fit to the same answer (every evaluation is deterministic).

The run is built from the stages of :mod:`jaxplush.fitting.stages` (:class:`~jaxplush.fitting.stages.GlobalStage`,
:class:`~jaxplush.fitting.stages.LocalLM` per horizon, :class:`~jaxplush.fitting.stages.Smoothing`);
this module adds the phases a checkpoint records, progress bars, the callback and the final
Jacobian and gradients. Every tuning constant is a field of the :class:`jaxplush.fitting.options.FitOptions` that
:func:`run` takes (its ``search``, ``local``, ``continuation`` and ``smoothing`` groups).
"""

from __future__ import annotations

import dataclasses
import math
import time

import numpy as np

from jaxplush.progress import Progress

from jaxplush.fitting import search as _search
from jaxplush.fitting import stages as _stages
from jaxplush.fitting.options import FitOptions
from jaxplush.fitting.outcome import Stop
from jaxplush.fitting.stages import horizons  # noqa: F401  (jaxplush.fitting.lmfit.horizons)

@dataclasses.dataclass
class LMRun:
    """The state and result of a default fit (everything its checkpoint holds, and more).

    Attributes:
      phase: "global", "local", "final" or "done".
      stage: index into ``horizons`` (frame counts) of the stage running.
      global_result: :class:`jaxplush.fitting.search.GlobalResult` (None before the global stage).
      states: list of :class:`jaxplush.fitting.search.LMState`, the local searches of this stage.
      rounds: local iterations done in this stage.
      best: the best state once done; jac (n, P) its Jacobian at step ``h_min``; residual (n,);
      grad, grad0: loss gradients (log space) at the best point and at the start values;
      paths: per finished stage, the (loss, theta) paths of its searches and why each ended;
      loss0: the loss of the start values on the whole target;
      wall: seconds spent; evaluations: points simulated;
      smoothed: the :class:`jaxplush.fitting.search.Smoothed` stage of a noisy target's fit (else None).
    """

    phase: str = "global"
    stage: int = 0
    horizons: tuple = ()
    global_result: object = None
    states: list = dataclasses.field(default_factory=list)
    rounds: int = 0
    best: object = None
    jac: np.ndarray | None = None
    residual: np.ndarray | None = None
    grad: np.ndarray | None = None
    grad0: np.ndarray | None = None
    paths: list = dataclasses.field(default_factory=list)
    loss0: float = math.nan
    wall: float = 0.0
    evaluations: int = 0
    smoothed: object = None


def default_box(prob, bounds=None, factor=4.0):
    """The search box in log space: each fitted parameter from start/factor to start*factor, or
    ``bounds`` {name: (lo, hi)} (absolute values, every fitted object); damping stays >= 1."""
    th0 = np.asarray(prob.theta0, np.float64)
    lo, hi = th0 - math.log(factor), th0 + math.log(factor)
    for i, n in enumerate(prob.names):
        if bounds and n in bounds:
            a, b = bounds[n]
            lo[i], hi[i] = math.log(a), math.log(b)
        if n == "damping":
            lo[i] = np.maximum(lo[i], 0.0)
    return _search.Box(lo, hi)


_order = _stages.order


def run(prob, box, options=None, *, progress=False, resume=None, save=None, callback=None):
    """Global stage, then Levenberg-Marquardt from the best ``starts`` candidates (successive
    halving to ``keep``), over horizons of growing length; then the Jacobian and gradients at
    the best point of the full problem (and, for a noisy target, the smoothing stage).

    Args:
      prob: :class:`jaxplush.fitting.fitter.Problem`; box: :class:`jaxplush.fitting.search.Box`.
      options: :class:`jaxplush.fitting.options.FitOptions` (None: the defaults): ``search``
        (Sobol points of the global stage, plus the start itself; local starts; the seed),
        ``iterations`` (Levenberg-Marquardt iterations per start and stage), ``local``,
        ``continuation`` and ``smoothing`` (the tuning knobs).
      progress: draw progress bars on stderr.
      resume: an :class:`LMRun` from a checkpoint to continue.
      save: ``save(run)`` called after the global stage and every local iteration.
      callback: ``callback(run)`` after every local iteration; returning True stops the search.

    Returns:
      (:class:`LMRun` (phase "done"), the :class:`jaxplush.fitting.evaluate.Evaluator` of the full problem).
    """
    opts = options or FitOptions()
    t0 = time.perf_counter()
    st = resume or LMRun(horizons=horizons(prob.target.n_frames, opts.continuation))
    wall0, evals0 = st.wall, st.evaluations
    objectives = _stages.Horizons(prob, box, st.horizons)

    def tick():
        st.wall = wall0 + time.perf_counter() - t0
        st.evaluations = evals0 + objectives.evaluations()

    n_stages = len(st.horizons)
    while st.phase in ("global", "local"):
        obj = objectives(st.stage)
        label = f"stage {st.stage + 1}/{n_stages} ({st.horizons[st.stage]} of {st.horizons[-1]} frames)"
        if st.phase == "global":
            _global(prob, obj, st, opts, progress, label)
            tick()
            if save is not None:
                save(st)
        _local(prob, obj, st, opts, progress, tick, save, callback, label)
        st.paths.append([(list(s.history), s.reason) for s in st.states])
        if st.stage + 1 < n_stages and not any(s.stopped == Stop.CALLBACK for s in st.states):
            _next_stage(st, opts.local.keep, opts.continuation)
            tick()
            if save is not None:
                save(st)
        else:
            st.phase = "final"
    ev = objectives.last()
    if st.phase == "final":
        _final(prob, ev, box, st, opts, progress)
        st.phase = "done"
        tick()
    return st, ev


def _global(prob, obj, st, opts, progress, label):
    """The global stage (:class:`jaxplush.fitting.stages.GlobalStage`) and the local searches it starts."""
    samples = opts.search.n_samples
    with Progress(samples + 1, f"global search, {label}", enabled=progress, unit="points") as bar:
        stage = _stages.GlobalStage(samples=samples, starts=opts.search.n_starts, seed=opts.search.seed,
                                    local=opts.local, progress=bar.update)
        g = stage.step(obj, stage.init(obj, prob.theta0))
        st.global_result = g.result
        bar.extra = f"best loss {np.min(np.where(g.result.ok, g.result.loss, np.inf)):.4g}"
        bar.finish(f"{int((~g.result.ok).sum())} failed" if (~g.result.ok).any() else "")
    st.states = g.states
    st.phase = "local"


def _next_stage(st, keep, cont):
    """The stage's best points start the next, longer stage (:func:`jaxplush.fitting.stages.carry`)."""
    st.states = _stages.carry(st.states, keep, cont)
    st.stage += 1
    st.rounds = 0
    st.phase = "local"


def _local(prob, obj, st, opts, progress, tick, save, callback, label):
    """The local searches of the running stage (:class:`jaxplush.fitting.stages.LocalLM` on ``st``,
    which holds its searches and rounds), each round followed by the progress bar, the callback
    and a checkpoint."""
    states = st.states
    noisy = prob.noise is not None and prob.noise > 0
    stage = _stages.local_for(_stages.LocalLM(max_iter=opts.iteration_limit("lm"), options=opts.local),
                              st.stage, len(st.horizons), noisy, opts.continuation)
    _stages.start_residuals(obj.evaluator, states, opts.local)
    with Progress(stage.max_iter, f"local search, {label}", enabled=progress, unit="it") as bar:
        bar.done = min(st.rounds, stage.max_iter)
        while not stage.terminate(obj, st)[0]:
            stage.step(obj, st)
            b = states[_order(states)[0]]
            vals = prob.values(b.theta)
            bar.update(1, extra=f"loss {b.loss:.4g} " + " ".join(
                ("k" if n == "k_structural" else n) + " " + ",".join(f"{x:.4g}" for x in np.atleast_1d(v))
                for n, v in vals.items()))
            tick()
            stop = callback(st) if callback is not None else None
            if stop is True:
                for s in states:
                    if not s.done:
                        s.done, s.stopped, s.reason = True, Stop.CALLBACK, "stopped by the callback"
            if save is not None and any(not s.done for s in states):
                save(st)
        bar.finish(states[_order(states)[0]].reason)


def _final(prob, ev, box, st, opts, progress=False):
    """Jacobian at the best point (at step ``h_min``) and the gradients at it and at the start; for a noisy
    target, the smoothing stage (:func:`jaxplush.fitting.search.smooth`) moves the best point to the
    optimum of a regression model, whose slope and intercept then stand for the Jacobian and the
    residuals."""
    states = st.states
    st.best = states[_order(states)[0]]
    b = st.best
    th0 = np.asarray(prob.theta0, np.float64)
    centre = ev(np.asarray([b.theta, th0]))
    st.residual = centre.residuals[0]
    st.loss0 = float(centre.loss[1])
    n_sub = max(int(centre.substeps[0]), b.substeps)
    local = opts.local
    st.jac = _search.jacobian(ev, box, b.theta, local.h_min, n_sub, local)
    if prob.noise is not None and prob.noise > 0 and b.stopped != Stop.CALLBACK:
        with Progress(opts.smoothing.iterations, "smoothing (regression designs)", enabled=progress,
                      unit="designs") as bar:
            stage = _stages.Smoothing(options=opts.smoothing, local=local, progress=bar.update)
            sm = stage.step(_stages.Objective(ev.prob, box, ev),
                            _stages.SmoothState(theta=b.theta, jac=st.jac, residual=st.residual)).result
            bar.finish("skipped: singular Jacobian" if sm is None else
                       ("the step is within the standard errors" if sm.converged else f"stopped after {len(sm.path)} designs"))
        e = ev(np.asarray(sm.theta)[None]) if sm is not None else None
        if e is not None and e.ok[0]:
            # the result moves to the model's optimum; the model's slope and intercept (at the last
            # design's centre) stand for the Jacobian and residuals the outcome is judged by
            st.smoothed = sm
            b.theta, b.loss, b.residual, b.substeps = sm.theta.copy(), float(e.loss[0]), e.residuals[0], int(e.substeps[0])
            history = list(sm.path) + [(b.loss, b.theta.copy())]
            b.history.extend(history)
            st.jac, st.residual = sm.jac, sm.residual
            worst = float(np.max(np.abs(sm.step) / sm.stderr))
            reason = (f"smoothed over {len(sm.path)} regression design(s): the Gauss-Newton step of the last is "
                      f"{worst:.2g} of the standard errors")
            b.reason = f"{b.reason}; {reason}" if b.reason else reason
            if st.paths:
                st.paths[-1].append((history, reason))
    st.grad = 2.0 * st.jac.T @ np.nan_to_num(st.residual)
    if centre.ok[1]:
        jac0 = _search.jacobian(ev, box, th0, local.h_max, int(centre.substeps[1]), local)
        st.grad0 = 2.0 * jac0.T @ centre.residuals[1]
    else:
        st.grad0 = np.full(th0.size, np.inf)
