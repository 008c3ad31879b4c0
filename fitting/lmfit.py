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

Every tuning constant is a field of the :class:`jaxplush.fitting.options.FitOptions` that
:func:`run` takes (its ``search``, ``local``, ``continuation`` and ``smoothing`` groups).
"""

from __future__ import annotations

import dataclasses
import math
import time

import numpy as np

from jaxplush.progress import Progress

from jaxplush.fitting import search as _search
from jaxplush.fitting.evaluate import Evaluator
from jaxplush.fitting.options import ContinuationOptions, FitOptions
from jaxplush.fitting.outcome import Stop

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


def horizons(n_frames, continuation=None):
    """Frame counts of the stages (increasing, the last ``n_frames``) under ``continuation``
    (:class:`jaxplush.fitting.options.ContinuationOptions`, None: the defaults)."""
    c = continuation or ContinuationOptions()
    if n_frames < c.min_frames:
        return (int(n_frames),)
    out = sorted({max(2, int(math.ceil(f * n_frames))) for f in c.horizons})
    return tuple(out[:-1]) + (int(n_frames),) if out[-1] != n_frames else tuple(out)


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


def _order(states):
    return sorted(range(len(states)), key=lambda i: states[i].loss)


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
    evaluators = _Evaluators(prob, st.horizons)

    def tick():
        st.wall = wall0 + time.perf_counter() - t0
        st.evaluations = evals0 + evaluators.evaluations()

    n_stages = len(st.horizons)
    while st.phase in ("global", "local"):
        ev = evaluators(st.stage)
        label = f"stage {st.stage + 1}/{n_stages} ({st.horizons[st.stage]} of {st.horizons[-1]} frames)"
        if st.phase == "global":
            _global(prob, ev, box, st, opts, progress, label)
            tick()
            if save is not None:
                save(st)
        _local(prob, ev, box, st, opts, progress, tick, save, callback, label)
        st.paths.append([(list(s.history), s.reason) for s in st.states])
        if st.stage + 1 < n_stages and not any(s.stopped == Stop.CALLBACK for s in st.states):
            _next_stage(st, opts.local.keep, opts.continuation)
            tick()
            if save is not None:
                save(st)
        else:
            st.phase = "final"
    ev = evaluators.last()
    if st.phase == "final":
        _final(prob, ev, box, st, opts, progress)
        st.phase = "done"
        tick()
    return st, ev


class _Evaluators:
    """One :class:`jaxplush.fitting.evaluate.Evaluator` per stage (the problem truncated to its horizon),
    made on first use: each shares the first one's compiled rollout (frames in chunks of the
    first horizon), its calibration, and a contact capacity grown in an earlier stage."""

    def __init__(self, prob, horizons):
        self.prob, self.horizons, self.by_stage = prob, horizons, {}

    def __call__(self, stage):
        evaluators = self.by_stage
        if stage not in evaluators:
            sub = self.prob.truncated(self.horizons[stage])
            calibration = next((e.calibration() for e in evaluators.values()), None)
            if evaluators:              # a contact capacity grown in an earlier stage carries over
                sub = dataclasses.replace(sub, sim=evaluators[max(evaluators)].prob.sim)
            share = evaluators[min(evaluators)] if evaluators else None
            # frames in chunks of the first horizon: every stage runs the same compiled rollout
            evaluators[stage] = Evaluator(sub, calibration=calibration, share=share, chunk_frames=self.horizons[0])
        return evaluators[stage]

    def evaluations(self):
        return sum(e.evaluations for e in self.by_stage.values())

    def last(self):
        """The full problem's evaluator, holding the earlier stages' notes first."""
        last = len(self.horizons) - 1
        ev = self(last)
        ev.notes[:0] = [m for k, e in sorted(self.by_stage.items()) if k != last for m in e.notes]
        return ev


def _global(prob, ev, box, st, opts, progress, label):
    """The global stage (:func:`jaxplush.fitting.search.global_stage`) and the local searches it starts."""
    samples, local = opts.search.n_samples, opts.local
    th0 = np.asarray(prob.theta0, np.float64)
    with Progress(samples + 1, f"global search, {label}", enabled=progress, unit="points") as bar:
        st.global_result = _search.global_stage(ev, box, th0, samples, opts.search.seed, progress=bar.update)
        g = st.global_result
        bar.extra = f"best loss {np.min(np.where(g.ok, g.loss, np.inf)):.4g}"
        bar.finish(f"{int((~g.ok).sum())} failed" if (~g.ok).any() else "")
    width = float(np.max(box.hi - box.lo))
    chosen = st.global_result.best(opts.search.n_starts, local.start_distance * width)
    st.states = [_search.LMState(theta=st.global_result.thetas[i].copy(), loss=float(st.global_result.loss[i]),
                                 mu=local.mu0, radius=local.radius0) for i in chosen]
    st.phase = "local"


def _next_stage(st, keep, cont):
    """The stage's best points start the next, longer stage (``cont``: :class:`ContinuationOptions`)."""
    kept = []
    best_loss = st.states[_order(st.states)[0]].loss
    for i in _order(st.states)[:keep]:
        s = st.states[i]
        # searches that ended at the same point continue as one, and one that ended far
        # above the best (in another basin) stops here: a longer horizon does not rescue it
        if (math.isfinite(s.loss) and s.loss <= cont.carry_factor * best_loss
                and all(np.max(np.abs(s.theta - o.theta)) > cont.same_point for o in kept)):
            kept.append(s)
    # a longer horizon moves the optimum little: start with a small trust radius (and so
    # an accurate difference step), from the damping the previous stage ended with
    st.states = [_search.LMState(theta=s.theta.copy(), loss=math.inf, radius=cont.next_radius,
                                 mu=min(s.mu, 1.0)) for s in kept]
    st.stage += 1
    st.rounds = 0
    st.phase = "local"


def _local(prob, ev, box, st, opts, progress, tick, save, callback, label):
    """The local searches of the running stage, a Levenberg-Marquardt round of all of them at a
    time (:func:`jaxplush.fitting.search.lm_round`), each round followed by rescues, screening, the
    progress bar, the callback and a checkpoint."""
    states, local, cont = st.states, opts.local, opts.continuation
    _start_residuals(ev, states, local)
    screen = st.stage == 0 and len(states) > local.keep
    max_iter, noise_stop = opts.iteration_limit("lm"), local.noise_stop
    if st.stage + 1 < len(st.horizons) or (prob.noise is not None and prob.noise > 0):
        # only the last stage of a noise-free fit resolves the optimum itself: with a noisy
        # target, the smoothing stage (jaxplush.fitting.search.smooth) does, at the scale of the noise
        max_iter = min(max_iter, cont.iterations)
        noise_stop = cont.noise_stop
    with Progress(max_iter, f"local search, {label}", enabled=progress, unit="it") as bar:
        bar.done = min(st.rounds, max_iter)
        while any(not s.done for s in states):
            _search.lm_round(ev, box, states, max_iter, local, noise_stop=noise_stop)
            st.rounds += 1
            # a search that stalls on a jump of the loss restarts from the lowest point of a scan
            _search.rescue(ev, box, states, local.max_rescues, local)
            _screen(states, st.rounds, screen, local)
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


def _start_residuals(ev, states, local):
    """The residuals of the states that lack them (a fresh start, or a resumed one: deterministic,
    so the same values), in one evaluation."""
    need = [s for s in states if s.residual is None and not s.done]
    if not need:
        return
    fresh = _search.start_states(ev, np.asarray([s.theta for s in need]), options=local)
    for s, f in zip(need, fresh):
        s.residual, s.substeps, s.loss = f.residual, f.substeps, f.loss
        if f.done:
            s.done, s.stopped, s.reason = f.done, f.stopped, f.reason
        if not s.history:
            s.history.append((f.loss, s.theta.copy()))


def _screen(states, rounds, screen, local):
    """Set searches aside after ``rounds`` rounds: with ``screen``, all but the best ``keep`` after
    ``screen_rounds``; then (or without screening) any whose loss exceeds ``drop_factor`` x the best's."""
    if screen and rounds == local.screen_rounds:
        for i in _order(states)[local.keep:]:
            if not states[i].done:
                states[i].done, states[i].stopped = True, Stop.SCREENED
                states[i].reason = f"set aside after {local.screen_rounds} iterations (loss {states[i].loss:.4g})"
    if rounds >= local.screen_rounds or not screen:
        best = min(s.loss for s in states)
        for s in states:
            if not s.done and s.loss > local.drop_factor * best:
                s.done, s.stopped = True, Stop.SCREENED
                s.reason = f"set aside: its loss {s.loss:.4g} is {s.loss / best:.3g}x the best search's"


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
            sm = _search.smooth(ev, box, b.theta, st.jac, st.residual, progress=bar.update, options=opts.smoothing)
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
