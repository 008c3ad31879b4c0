"""Fit material parameters of a scene to a target.

``fit(scene, target, params=None, objects=None, *, optimizer="lm", options=None, callback=None,
progress=False, **overrides)``, its options a :class:`jaxplush.fitting.options.FitOptions` (keywords
override single fields: ``fit(scene, target, iterations=40)``):

* the fitted variables are theta = log(p) for the chosen parameters of the chosen objects
  (positivity for free); every other parameter stays at the scene's value. ``params=None``
  fits what the scene switches on (:func:`default_params`);
* the loss is :func:`jaxplush.fitting.objective.losses.make_loss` over the target's frames (noise- or
  motion-normalised; positions or point-to-surface distances);
* the default optimiser, ``"lm"``, is global then local (:mod:`jaxplush.fitting.stages.lmfit`,
  :mod:`jaxplush.fitting.stages.search`): a Sobol design over a box around the start run through the batched
  simulator, then Levenberg-Marquardt with central-difference Jacobians from the best
  candidates, over horizons of growing length, every evaluated point stable (substeps where
  needed, :mod:`jaxplush.fitting.objective.evaluate`);
* ``"adam"``, ``"lbfgs"`` and any optax transformation the caller passes descend the gradient
  through the rollout (:func:`jaxplush.fitting.objective.gradients.rollout_loss`) in one loop: a step whose
  rollout blows up (non-finite loss or gradient, an inverted object, damping < 1) is rejected
  and the step halved; a start that blows up, or too many rejections in a row, raise
  :class:`FitError`; they stop at ``iterations`` or at ``gtol``/``rtol``/``xtol``/``ftol``;
* before fitting, the predictability of the start values over the target is measured
  (:func:`jaxplush.predictability`: two runs that differ only by rounding); its reproducibility
  floor is the residual no parameters can go below, which the outcome tells from a poor fit;
* every fit's outcome is judged by :mod:`jaxplush.fitting.judge.outcome` ("converged" only at the noise level
  and an optimum), recorded in the result and FIT.h5 and warned about otherwise;
* checkpoints (``checkpoint_path``) hold the complete state, so ``resume=True`` continues an
  interrupted (Ctrl-C or killed) fit to the same answer; Ctrl-C saves before it exits;
* afterwards: the identifiability report (:mod:`jaxplush.fitting.judge.identifiability`) and a health check of
  the fitted rollout.

The result is a :class:`FitResult`.

This module holds :func:`fit` and the default fit's wrapper (checkpoints, Ctrl-C saves, the
result); the pieces live beside it and are importable from here as well: the problem
(:mod:`jaxplush.fitting.objective.problem`), the gradient optimisers' loop (:mod:`jaxplush.fitting.stages.gradfit`),
the result and its judgement (:mod:`jaxplush.fitting.judge.result`), synthetic recovery
(:mod:`jaxplush.fitting.targets.recovery`); the default fit's stages and driver are
:mod:`jaxplush.fitting.stages` and :mod:`jaxplush.fitting.stages.lmfit`.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import sys
import time
import warnings

import numpy as np

from jaxplush.compilestats import compile_clock
from jaxplush.fitting.judge import intervals as _intervals
from jaxplush.stepping import diagnostics
from jaxplush.errors import JaxplushError, TimeStepWarning, VolumeClampWarning
from jaxplush.types import PARAM_NAMES  # noqa: F401  (jaxplush.fitting.fitter.PARAM_NAMES)

from jaxplush.fitting.judge import identifiability as _ident
from jaxplush.fitting.stages import objects as _objects
from jaxplush.fitting.objective import losses as _losses
from jaxplush.fitting import options as _options
from jaxplush.fitting.stages import saving_on_interrupt
from jaxplush.fitting.errors import FitError, FitWarning  # noqa: F401  (jaxplush.fitting.fitter.FitError)
# the pieces of a fit, importable from here as before
from jaxplush.fitting.stages.gradfit import (DEFAULT_LR, MAX_REJECTIONS, OPTIMIZERS, LoopState,  # noqa: F401
                                      _GradientFit, make_optimizer, optimizer_kind, uses_linesearch)
from jaxplush.fitting.options import CheckpointOptions, FitOptions, SearchOptions  # noqa: F401
from jaxplush.fitting.objective.problem import (ALIASES, Problem, _common_settings, build_problem,  # noqa: F401
                                      canonical_names, check_mass_fit, default_params, parse_bounds)
from jaxplush.fitting.targets.recovery import RECOVERY_TRUTH, recovery_scene_text, synthetic_recovery  # noqa: F401
from jaxplush.fitting.judge.result import (FitResult, _history, _judge, _motion, _predictability_at, _result,  # noqa: F401
                                     identifiability_at, measure_predictability, residual_samples,
                                     rounding_drift)
from jaxplush.fitting.objective import shooting as _shooting
from jaxplush.fitting.judge.outcome import REPORTED as _REPORTED, Status, limited_by_rounding as _limited
from jaxplush.fitting.objective.shooting import plan_shooting


def fit(scene, target, params=None, objects=None, *, optimizer="lm", options=None, callback=None, progress=False,
        report=None, solver=None, **overrides):
    """Fit parameters of ``scene`` to ``target``.

    The default (``optimizer="lm"``) is global, then local (:mod:`jaxplush.fitting.stages.search`): a Sobol
    design over a box around the start (each parameter from start/4 to start*4 in log space,
    or ``bounds``), run in compiled batches with every point stable (substeps where a point's
    explicit limit is below dt), then Levenberg-Marquardt with finite-difference Jacobians from
    the best candidates, keeping the best. The outcome is judged honestly
    (:mod:`jaxplush.fitting.judge.outcome`): ``converged`` only when the residual is at the noise level (or
    small against the target's motion) and the gradient is small against the start's.

    Args:
      scene: :class:`jaxplush.scene.parse.Scene`; its values of the fitted parameters are the start.
      target: :class:`jaxplush.fitting.targets.Target` or a path (loaded with :func:`load_target`).
      params: names to fit (``k`` = ``k_structural``; also ``dashpot``, ``drag``; ``total_weight``
        only alone, with a warning, unless ``force``); default :func:`default_params`, the
        material parameters the scene switches on (with a warning naming them).
      objects: object names or indices to fit (default all); the others keep their values.
      optimizer: "lm" (default: global stage and Levenberg-Marquardt), "adam", "lbfgs", or any
        ``optax.GradientTransformation`` (e.g. ``optax.adam(0.02)`` or an ``optax.chain``). The
        gradient optimisers descend the gradient of the loss with respect to the log-parameters
        in one loop (module docstring). An optax transformation that is an
        ``optax.GradientTransformationExtraArgs`` (as ``optax.chain`` and most of optax's are)
        gets ``value``, ``grad`` and ``value_fn`` (the loss at the log-parameters) with every
        ``update``, as its line searches and ``polyak_sgd`` need. One whose state holds a line
        search (``optax.lbfgs``, ``scale_by_zoom_linesearch``, ``scale_by_backtracking_linesearch``)
        is run as "lbfgs" is: its step is never rescaled, and a rejected step restarts its state.
      options: :class:`fitting.FitOptions` (default ``FitOptions()``): iterations, lr, dt, start
        values, noise, tolerances, gradient method, identifiability, the default fit's
        :class:`fitting.SearchOptions` (bounds, samples, starts, seed), its tuning knobs
        (:class:`fitting.LocalOptions`, :class:`fitting.ContinuationOptions`,
        :class:`fitting.SmoothingOptions`) and :class:`fitting.CheckpointOptions` (path, every,
        resume); see :mod:`jaxplush.fitting.options`.
      callback: called after every accepted iteration with a dict (iteration, loss, values,
        grad_norm); returning True stops the fit.
      progress: draw a progress bar (loss and parameters) on stderr.
      report: called with a line of text for a person before the fit starts (the
        predictability of the start values; the command line prints it to stderr).
      solver: a sequence of stages to run instead of the default fit's (``optimizer="lm"``
        only): each an object with ``init``, ``step``, ``terminate`` and optionally
        ``postprocess`` (:mod:`jaxplush.fitting.stages`; e.g. :class:`fitting.GlobalStage`,
        :class:`fitting.LocalLM`, :class:`fitting.Optax`, or one's own). They run on the whole
        target (no continuation in time, no multiple shooting's re-plan); the last stage's
        candidate is linearised and judged as the default fit's result is, with checkpoints,
        Ctrl-C saves, intervals and FIT.h5.
      **overrides: changes to ``options`` by field name, e.g. ``iterations=40``,
        ``noise_free=True``; the group fields by their flat names ``bounds``, ``samples``,
        ``starts``, ``seed``, ``checkpoint_path``, ``checkpoint_every``, ``resume``, and the
        tuning knobs (``keep``, ``local_xtol``, ``horizons``, ``smooth_points``, ...;
        :data:`jaxplush.fitting.options.SHORTCUTS`) (:meth:`fitting.FitOptions.replace`). An unknown name raises :class:`JaxplushError`.

    Returns:
      :class:`FitResult`.

    Raises:
      JaxplushError / TrajectoryError: bad input (before anything is traced).
      FitError: the fit cannot proceed (the rollout blows up at the start or for every step).
      KeyboardInterrupt: after saving the checkpoint (when a checkpoint path is given).

    Soft-soft contact: an evaluation whose contact candidates overflow the capacity is not a
    blow-up; the fit raises the capacity to what the run needs, warns, and evaluates that point
    again (see ``contact_capacity`` in the scene format).
    """
    t_start = time.perf_counter()
    clock = compile_clock()                 # the whole fit's XLA compiles, apart from the rest
    opts = _options.resolve(options, overrides)
    kind = optimizer_kind(optimizer)
    _options.validate(opts, kind)
    solver = _check_solver(solver, kind)
    prob, notes = _problem(scene, target, params, objects, opts)
    if kind == "lm":
        def rebuild():          # the same problem in the dtype of the moment (the float64 polish)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                return _problem(scene, target, params, objects, opts)[0]
        result = _fit_lm(prob, opts, notes, t_start, progress=progress, callback=callback, report=report,
                         clock=clock, solver=solver, rebuild=rebuild)
    else:
        result = _GradientFit(prob, optimizer, opts, notes, progress=progress, callback=callback,
                              report=report).run(t_start, clock)
    if progress:
        say_timing(result.timing)
    return result


def _check_solver(solver, kind):
    """``solver`` as a tuple of stages (None: the default fit's), checked before anything is built."""
    if solver is None:
        return None
    if kind != "lm":
        raise JaxplushError(f"solver (a sequence of stages) replaces the default fit's stages; it does not go with "
                            f"optimizer {kind!r} (for an optax transformation as a stage, use fitting.Optax)")
    if isinstance(solver, (str, bytes)) or not hasattr(solver, "__iter__"):
        raise JaxplushError(f"solver must be a sequence of stages, got {type(solver).__name__}")
    stages = tuple(solver)
    if not stages:
        raise JaxplushError("solver is empty: give at least one stage (or leave it out for the default fit)")
    for i, st in enumerate(stages):
        missing = [m for m in ("init", "step", "terminate") if not callable(getattr(st, m, None))]
        if missing:
            raise JaxplushError(f"solver[{i}] ({type(st).__name__}) is not a stage: it has no {', '.join(missing)} "
                                "method (a stage has init, step and terminate; jaxplush.fitting.stages)")
    return stages


def say_timing(timing, label="fit"):
    """The line on stderr that tells a fit's compile time apart from the rest
    (:class:`jaxplush.compilestats.Timing`), after its progress bars."""
    if timing is not None:
        print(f"{label}: {timing.text()}", file=sys.stderr, flush=True)


def _problem(scene, target, params, objects, opts):
    """:func:`build_problem` with ``opts``; its warnings are re-issued (for the caller of
    :func:`fit`) and returned as the fit's notes."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        prob = build_problem(scene, target, params, objects, dt=opts.dt, start=opts.start, noise=opts.noise,
                             noise_free=opts.noise_free, method=opts.method, force=opts.force,
                             track_weight=opts.track_weight)
    notes = [str(w.message) for w in caught]
    for w in caught:
        warnings.warn(str(w.message), w.category, stacklevel=3)
    return prob, notes


def _lm_box(prob, bounds):
    from jaxplush.fitting.stages import lmfit
    box = lmfit.default_box(prob, parse_bounds(bounds, prob.names))
    th0 = np.asarray(prob.theta0, np.float64)
    if not box.contains(th0):
        i = np.argwhere((th0 < box.lo - 1e-12) | (th0 > box.hi + 1e-12))[0]
        raise JaxplushError(f"the start value of {prob.labels[i[0] * len(prob.objects) + i[1]]} "
                            f"({math.exp(th0[tuple(i)]):g}) lies outside its bounds "
                            f"{math.exp(box.lo[tuple(i)]):g}:{math.exp(box.hi[tuple(i)]):g}")
    return box


def _lm_settings(prob, opts, box):
    """The default fit's settings (:func:`_common_settings`, its box, global design and tuning knobs)."""
    s = opts.search
    settings = _common_settings(prob, opts, "lm", opts.iteration_limit("lm"), None)
    settings.update(frame_steps=list(prob.loss.frame_steps), target_kind=prob.target.kind,
                    box_lo=box.lo.ravel().tolist(), box_hi=box.hi.ravel().tolist(),
                    samples=s.n_samples, starts=s.n_starts, seed=int(s.seed), shooting=str(opts.shooting),
                    global_stage="per_object" if _objects.suits(prob) else "sobol")
    settings.update({group: dataclasses.asdict(getattr(opts, group)) for group in _options.TUNING})
    return settings


def _fit_lm(prob, opts, notes, t_start, *, progress, callback, report=None, clock=None, solver=None, rebuild=None):
    """The default fit (jaxplush.fitting.stages.lmfit.run) with checkpoints, Ctrl-C saves and the honest outcome.
    ``clock``: a :class:`jaxplush.compilestats.CompileClock` started with the fit, whose
    :class:`~jaxplush.compilestats.Timing` the result gets (None: one started here)."""
    from jaxplush.fitting import io as _io
    from jaxplush.fitting.stages import lmfit
    clock = compile_clock() if clock is None else clock
    _shooting.check_segments(opts.shooting, prob.target)
    box = _lm_box(prob, opts.search.bounds)
    settings = _lm_settings(prob, opts, box)
    if solver is not None:           # a resume must run the same stages
        settings["solver"] = [f"{type(s).__module__}:{type(s).__qualname__}" for s in solver]
    checkpoint_path, want_ident = opts.checkpoint.path, opts.identifiability
    prior = _io.load_checkpoint(checkpoint_path, prob, settings, conform=_driver_state) \
        if opts.checkpoint.resume else None
    # the measurements before the search run on the program it compiles next (pieces of its first horizon)
    chunk = _first_horizon(prob, opts)
    if opts.predictability:                 # every input checked (a resumed checkpoint too)
        prob = measure_predictability(prob, report, batched=True, chunk_frames=chunk)
    full = prob
    prob = planned = plan_shooting(prob, opts.shooting, report, opts.multiple_shooting, chunk)
    last = [prior]

    def write(state, status):
        best = lmfit.best_search(state)
        extra = {} if best is None else dict(theta=best.theta, loss=float(best.loss))
        _io.save_checkpoint(checkpoint_path, planned, state, settings, status,
                            iterations=int(state.evaluations), **extra)

    def save(run):
        last[0] = lmfit.light_copy(run)
        if checkpoint_path is not None:
            write(last[0], "running")

    user_cb = None
    if callback is not None:
        def user_cb(local):
            b = min(local.states, key=lambda st: st.loss)
            return callback(dict(iteration=local.rounds, loss=b.loss, values=prob.values(b.theta), grad_norm=np.nan))
    saved = [False]

    def interrupted(run):            # Ctrl-C in the stages (their loop's hook): the last finished step
        saved[0] = True
        if checkpoint_path is not None and (run.state is not None or run.finished):
            write(lmfit.light_copy(run), "interrupted")

    def save_last():                 # Ctrl-C outside the stages' loop: their last saved step
        if not saved[0] and last[0] is not None and checkpoint_path is not None:
            write(last[0], "interrupted")

    common = dict(progress=progress, save=save, interrupted=interrupted, callback=user_cb, chunk_frames=chunk)
    with saving_on_interrupt(save_last):
        if solver is None and _may_replan(full, prob, opts):
            # the plan cut the target short: the fitted values may predict further, and then the
            # fit goes on over more of it; the smoothing stage waits for that answer (on seed 901's
            # case 1 it took 23 s, then ran again over the whole target)
            state, obj = lmfit.run(prob, box, opts, resume=prior, smooth=False, finish=False, **common)
            replanned = _replan(full, prob, lmfit.linearised(state).best.theta, opts, report)
            run, ev = lmfit.run(prob, box, opts, resume=state, smooth=replanned is None, objective=obj, **common)
        else:
            run, ev = lmfit.run(prob, box, opts, resume=prior, stages=solver, **common)
            replanned = None

        def again(first, cut, note):
            # fit again, locally (the global stage has done its work), from the first fit's values
            local_only = dataclasses.replace(opts, search=dataclasses.replace(opts.search, samples=0, starts=1))
            run, ev = lmfit.run(cut, box, local_only, progress=progress, callback=user_cb, start=first.best.theta,
                                chunk_frames=chunk)
            run.evaluations += first.evaluations
            run.global_result, run.paths = first.global_result, list(first.paths) + list(run.paths)
            return cut, run, ev, list(notes) + [note]

        if replanned is not None:
            # the start's horizon cut the fit short; the fitted values predict further: fit again
            # over what they predict
            prob, run, ev, notes = again(run, *replanned)
        within = _within_horizon(prob, run, ev, opts, report) if solver is None else None
        if within is not None:
            # the fit lies near the reproducibility floor over the whole target, but not over the
            # frames its values predict: fit those again
            replanned = replanned or within
            prob, run, ev, notes = again(run, *within)

    def save_finished():
        if checkpoint_path is not None:
            # (the checkpoint holds the first fit's state: a resumed fit plans again from it)
            write(last[0] if replanned is not None else lmfit.light_copy(run.state), "interrupted")

    polish = opts.polish == "float64" and rebuild is not None and np.dtype(prob.sim.dtype) != np.float64
    # how far the positions are predictable at the fitted values (the start's measurement can be
    # far from them: the bean dropped from k x2, dashpot x0.5, nmol x2 is predictable for 0.06 s
    # of 0.6 s at its start, for the whole run at its fitted values)
    pred = (_predictability_at(prob, run.best.theta, batched=True, chunk_frames=_first_horizon(prob, opts))
            if polish else None) or prob.predictability
    if polish and pred is not None and not pred.predictable:
        # beyond the predictable horizon a float64 fit fits the target's own rounding drift, no
        # better than float32 (seed 601's cases 14 and 40: nmol 0.36% -> 2.7%, drag 4.1% -> 6.6%)
        polish = False
        line = (f"not polished in float64: at the fitted values {pred.text()}; beyond that horizon a float64 fit "
                "does no better than float32")
        notes = list(notes) + [line]
        if report is not None:
            report(line)
    prob32, ev32 = prob, ev
    with saving_on_interrupt(save_finished), _x64(polish):
        if polish:
            prob, run, ev, line = _polish(rebuild(), prob, box, opts, run, progress=progress, callback=user_cb)
            notes = list(notes) + [line]
            settings = dict(settings, polish="float64")
            if report is not None:
                report(line)
        wall = time.perf_counter() - t_start + (prior.wall if prior is not None else 0.0)
        result = _finish_lm(prob, box, run, ev, settings, notes, want_ident, wall, report)
    if polish:
        with saving_on_interrupt(save_finished):
            result = _float32_twins(result, run, prob32, ev32)
    result = dataclasses.replace(result, timing=clock.stop())
    if checkpoint_path is not None:
        _io.save_fit(result, checkpoint_path)
    return result


def _x64(on):
    """``jax.enable_x64(True)`` where ``on`` (the float64 polish and its judge run inside it), else nothing."""
    if not on:
        return contextlib.nullcontext()
    import jax
    return jax.enable_x64(True)


def _polish(prob64, prob, box, opts, first, *, progress, callback):
    """The float64 polish (``FitOptions.polish``; only where the positions are predictable over the
    whole target, at the fit's latest measurement), inside ``jax.enable_x64``: the default fit's
    local stages again from the float32 fit's best point (no global design: it is the only start;
    Levenberg-Marquardt over horizons of growing length, then the linearisation; no smoothing
    stage, the float64 loss is not rough), on ``prob64``, the problem rebuilt in float64 with the
    float32 fit's predictability and shooting plan. The horizons matter: on seed 601's case 0
    (three pinned objects, a cloud) Levenberg-Marquardt on the whole target alone stalled in
    float64 too, where the same stages over growing horizons reached the truth. Returns (the
    float64 problem, its run, whose global design, paths and evaluations include the float32
    fit's, its evaluator, a line for a person)."""
    from jaxplush.fitting.stages import lmfit
    prob64 = dataclasses.replace(prob64, predictability=prob.predictability, shooting=prob.shooting)
    local_only = dataclasses.replace(opts, search=dataclasses.replace(opts.search, samples=0, starts=1))
    run, ev = lmfit.run(prob64, box, local_only, progress=progress, callback=callback, start=first.best.theta,
                        smooth=False)
    run.evaluations += first.evaluations
    run.global_result, run.paths = first.global_result, list(first.paths) + list(run.paths)
    line = (f"polished in float64 from the float32 fit's best point (loss {first.best.loss:.4g} in float32, "
            f"{run.best.loss:.4g} in float64)")
    return prob64, run, ev, line


def _float32_twins(result, run, prob, ev):
    """A polished ``result`` with its intervals (and the combinations they give) from twins run on
    the float32 fit's evaluator ``ev`` at the polished values, with the float64 Jacobian and
    residuals of the polish (``run``). A target is known to its own precision: float64 twins of a
    target simulated or stored in float32 leave out that target's rounding (the hanging ball
    polished to k 9.6e-7 off, against a float64 spread of 2.2e-7; its float32 twins: 1.2e-6)."""
    iv = result.intervals
    if iv is None or iv.method != "twins" or run.jac is None:
        return result
    theta = np.asarray(iv.theta, np.float64).reshape(np.shape(prob.theta0))
    ivals = _intervals.twins(prob, ev, theta, run.jac, result.identifiability, residual=run.residual)
    if ivals.method != "twins":
        return result
    ivals = dataclasses.replace(ivals, note=ivals.note + " (the values polished in float64; the twins in float32, "
                                "the target's own precision)")
    combos = _intervals.combinations(prob, theta, ivals, substeps=int(ev.substeps_for(theta[None])[0]))
    out = _limited(result.outcome, ivals)
    if out.status != result.outcome.status or out.message != result.outcome.message:
        warnings.warn(out.text, FitWarning, stacklevel=3)
        result = dataclasses.replace(result, outcome=out, converged=out.converged, reason=out.text,
                                     warnings=tuple(result.warnings) + (out.text,))
    return dataclasses.replace(result, intervals=ivals, combinations=combos)


def _replan(full, prob, theta, opts, report=None):
    """The problem planned again from the predictability at the fitted values theta, when the plan
    made at the start values cut the fit short (a point-cloud target cut at the start's horizon,
    or multiple shooting) and the fitted values predict more of the target (more frames, or longer
    segments): (the problem, a note saying so); else None. A start far from the truth (near its
    stability limit, say) can be much less predictable than the result."""
    if not _may_replan(full, prob, opts):
        return None
    pred = _predictability_at(full, theta, batched=True, chunk_frames=_first_horizon(full, opts))
    if pred is None:
        return None
    sh, again = _shooting.plan(dataclasses.replace(full, predictability=pred), "auto", opts.multiple_shooting,
                               _first_horizon(full, opts))
    new = dataclasses.replace(again, shooting=sh)
    if _shooting.span(new) <= _shooting.span(prob):
        return None
    note = (f"fitted again from the first fit's values, which predict further than the start values: "
            f"{pred.text()}; shooting: {sh.reason}")
    if report is not None:
        report(note)
    return new, note


def _within_horizon(prob, run, ev, opts, report=None):
    """The problem cut at the predictable horizon measured at the fitted values, when a fit over
    single-shooting frames did not reach the data, lies within
    :data:`jaxplush.fitting.judge.outcome.FLOOR_FACTOR` of its reproducibility floor there (the
    residual above the noise), and its frames before that horizon sit above what rounding
    explains there: (the problem, a note saying so); else None.

    Past the horizon two runs that differ only by rounding drift apart by as much as the data
    allow, so the residual there says nothing about the values, yet it dominates the loss: a fit
    over all of it can stop where the whole target's residual is at its floor while the frames
    before the horizon, where the model is deterministic, are far from theirs. On the recovery
    bench's fits that ended at the floor, those frames sat 2-33x above their rounding drift
    (a fit at the truth: 0-0.9x), and fitting them alone, from the fit's values, took k and
    nmol from 0.05-0.4% off to within 0.001% (benchmarks/RESULTS.md, 2026-12-02).

    The horizon is the first frame whose rounding drift exceeds the data's demand (the noise, or
    a hundredth of the motion; :func:`jaxplush.predictability`), kept at ``min_horizon_frames``
    frames at least (:class:`jaxplush.fitting.options.ShootingOptions`). The frames before it are
    "above their drift" when their residual RMS above the noise (taken off in quadrature) exceeds
    :data:`jaxplush.fitting.judge.outcome.FLOOR_REACHED` x the drift's RMS over them."""
    from jaxplush.fitting.judge import outcome as _outcome
    if not opts.predictability or (prob.shooting is not None and prob.shooting.on):
        return None
    best = run.best
    if best is None or not np.isfinite(best.loss):
        return None
    t = prob.target
    kind = t.kind
    noise = float(prob.noise or 0.0)
    rms = _losses.rms_metres(best.loss, prob.loss.scale2, kind)
    start_floor = None if prob.predictability is None else prob.predictability.floor
    demand = (_outcome.reach_limit(noise, residual_samples(prob), start_floor) if noise
              else _outcome.MOTION_FRACTION * _motion(prob))
    if rms <= demand:
        return None
    pred = _predictability_at(prob, best.theta, batched=True, chunk_frames=_first_horizon(prob, opts))
    if pred is None or pred.predictable:
        return None
    if not math.sqrt(max(rms * rms - noise * noise, 0.0)) <= _outcome.FLOOR_FACTOR * pred.floor:
        # far above its floor the fit has not reached what rounding allows anywhere: its values
        # say little about its horizon, and the frames before it can leave them undetermined
        # (seed 1501's case 19, 2.2x its floor, refitted over 8 of 51 frames: a ball 5x off with
        # a spread of 0.03%)
        return None
    times = np.asarray(t.times, np.float64)
    keep = int(np.searchsorted(times, pred.horizon_time, side="right"))
    keep = max(keep, int(opts.multiple_shooting.min_horizon_frames))
    if keep >= t.n_frames:
        return None
    e = ev(np.asarray(best.theta)[None])
    r = np.asarray(e.residuals[0], np.float64)
    per = int(ev.residual.per_frame)
    if not np.isfinite(e.loss[0]) or r.size != t.n_frames * per:
        return None
    frames = r.reshape(t.n_frames, per)
    whole, early = np.nanmean(r ** 2), np.nanmean(frames[:keep] ** 2)
    if not (whole > 0 and np.isfinite(early)):
        return None
    pre = rms * math.sqrt(early / whole)                     # the frames before the horizon, m
    drift = np.interp(times[:keep], np.asarray(pred.times, np.float64), np.asarray(pred.drift_rms, np.float64))
    drift = float(np.sqrt(np.mean(drift ** 2)))
    above = math.sqrt(max(pre * pre - noise * noise, 0.0))
    if not above > _outcome.FLOOR_REACHED * drift:
        return None
    cut = prob.truncated(keep)
    cut = dataclasses.replace(cut, predictability=_predictability_at(cut, best.theta, batched=True,
                                                                     chunk_frames=_first_horizon(prob, opts)))
    note = (f"fitted again over the first {keep} of {t.n_frames} frames, from the first fit's values, at which "
            f"{pred.text()}: over the whole target its residual was {rms * 1e3:.3g} mm, over those frames "
            f"{above * 1e3:.3g} mm"
            + (" above the noise" if noise else "")
            + f", {above / drift if drift > 0 else math.inf:.3g}x their rounding drift ({drift * 1e3:.3g} mm): beyond "
            "them no values do better than rounding allows")
    if report is not None:
        report(note)
    return cut, note


def _may_replan(full, prob, opts):
    """Whether the plan made at the start values cut the fit short (:func:`_replan` may fit again)."""
    return (opts.predictability and opts.shooting == "auto" and full.predictability is not None
            and _shooting.restricted(full, prob))


def _first_horizon(prob, opts):
    """Frames of the default fit's first horizon over ``prob``'s target: the piece length its
    batched rollouts run in (:class:`jaxplush.fitting.stages.Horizons`)."""
    from jaxplush.fitting.stages import horizons
    return horizons(prob.target.n_frames, opts.continuation)[0]


def _driver_state(state):
    """A default fit's checkpointed state, checked to be its driver's."""
    from jaxplush.fitting.stages import RunState
    if not isinstance(state, RunState):
        raise TypeError(f"the checkpoint holds a {type(state).__name__}, not the default fit's RunState")
    return state


def _resolve_again(prob, box, run, ev, local, report, drift, factor, notes):
    """The identifiability report from a second Jacobian at the optimum, at the larger step
    ``local.resolve_h`` (:class:`LocalOptions`), when the search's own Jacobian (at step
    ``run.jac_step``) left combinations unresolved.

    A combination is unresolved when a unit step along it moves the frames by at most
    RESOLVE_FACTOR times the Jacobian's rounding noise, drift / (2 h). At the search's last
    step (h_min, 1e-3) that noise is large: the test calls undetermined whatever the target
    determines no better than about 2h/3 (a standard error of drift / effect), and exact fits
    (every parameter within 0.01%) were called undetermined. A step 10x larger carries a tenth
    of that noise and still truncates at about h²: what it cannot resolve is not determined to
    about a percent.

    Where the motion is sensitive (a drift of half a millimetre), even that step can leave
    combinations within its rounding noise that a larger one resolves: it is measured once more,
    at the step where the weakest of them, at the effect this Jacobian measured, would carry
    twice RESOLVE_FACTOR x its noise (at most ``h_max``). Seed 19 case 8 of the recovery
    benchmark (two pinned 642-vertex objects, the report's damping; drift 0.52 mm), every
    parameter within 0.2% of the truth: all six combinations unresolved at steps 0.001 and 0.01
    (sensitivities 0.02-0.04 m per e-fold, mostly noise), two resolved at 0.05 (sensitivities
    0.008-0.017 m per e-fold against a noise of 0.0052 m)."""
    from jaxplush.fitting.stages.search import fd_step, jacobian
    if drift is None:
        return report
    best, h_prev, radius = run.best, float(run.jac_step), float(local.resolve_h)
    jac_prev = np.asarray(run.jac, np.float64) * factor
    for _ in range(2):
        h = fd_step(4.0 * radius, local)       # the step jacobian() takes: within [h_min, h_max]
        if not h > h_prev:
            break
        jac = jacobian(ev, box, best.theta, h, int(best.substeps or 1), local,
                       separation=getattr(best, "separation", math.nan))
        if jac is None or not np.all(np.isfinite(jac)) or not np.any(jac):
            break
        jac = jac * factor
        off = _disagreement(jac_prev, jac, report.unresolved, prob.labels,
                            _ident.fd_noise(drift, h_prev), _ident.fd_noise(drift, h))
        if off is not None:
            notes.append(f"identifiability: the Jacobian at step {h:g} (log space) differs from the one at "
                         f"step {h_prev:g} along an unresolved combination by {off[0]:.2g} m RMS per unit step, "
                         f"more than {_ident.RESOLVE_FACTOR:g}x their rounding noise ({off[1]:.2g} m): the slope "
                         "along it depends on the step, so the larger step does not resolve it "
                         f"({len(report.unresolved)} combination(s) stay unresolved)")
            break
        again = _ident.analyse(jac, np.nan_to_num(run.residual) * factor, prob.labels, noise=prob.noise,
                               jac_noise=_ident.fd_noise(drift, h))
        notes.append(f"identifiability: the Jacobian at step {h_prev:g} left {len(report.unresolved)} "
                     f"parameter combination(s) within its rounding noise; measured again at step {h:g} (log space): "
                     + (f"{len(again.unresolved)} remain unresolved" if again.unresolved else "all resolved"))
        report, h_prev, jac_prev = again, h, jac
        weakest = min((e for e, _ in again.unresolved), default=0.0)
        if weakest <= 0.0:
            break
        radius = 2.0 * _ident.RESOLVE_FACTOR * float(drift) / (2.0 * weakest)
    return report


def _disagreement(jac_a, jac_b, unresolved, labels, noise_a, noise_b):
    """(difference, noise) where two Jacobians (n, P) of the same residuals, at two difference
    steps with rounding noise ``noise_a`` and ``noise_b`` (RMS m per unit step in log space),
    differ along one of the ``unresolved`` combinations of the first
    (:attr:`IdentifiabilityReport.unresolved`) by more than RESOLVE_FACTOR x hypot(noise_a,
    noise_b), RMS m per unit step; else None.

    A larger step resolves a combination that a smaller one left within its noise only where the
    motion is linear along it on the scale of both steps: the two measure the same slope, one
    with less noise. Where they measure different slopes, the larger step's is a secant over a
    rough or curved loss, not the local sensitivity. Seed 23 case 2 of the recovery benchmark (a
    160-vertex torus on a floor, damping and drag, only their combined rate determined): at step
    0.001 the combination was rightly unresolved; at 0.01 the damping column was 0.0101 m per
    e-fold against 0.0058 implied by the degeneracy, and the fit was called converged with
    damping 4x the truth."""
    noise = math.hypot(float(noise_a), float(noise_b))
    n = max(jac_a.shape[0], 1)
    index = {label: i for i, label in enumerate(labels)}
    for _, comp in unresolved:
        d = np.zeros(jac_a.shape[1])
        for label, c in comp.items():
            d[index[label]] = c
        diff = float(np.linalg.norm((jac_b - jac_a) @ d)) / math.sqrt(n)
        if diff > _ident.RESOLVE_FACTOR * noise:
            return diff, noise
    return None


def _finish_lm(prob, box, run, ev, settings, notes, want_ident, wall, say=None):
    """The :class:`FitResult` of a default fit: frames, health, outcome, identifiability. A fit in
    segments returns its values with multiple shooting's own bias taken off (:func:`jaxplush.fitting.
    shooting.debias`; ``say`` gets the line that says so); its loss and outcome are the fit's own."""
    from jaxplush.fitting.stages import lmfit
    from jaxplush.fitting.stages.search import Ties, gauss_newton
    notes = list(notes) + list(ev.notes)
    prob = dataclasses.replace(prob, sim=ev.prob.sim)       # with a grown contact capacity, if any
    best = run.best
    kind = prob.target.kind
    scale2 = prob.loss.scale2
    rms = _losses.rms_metres(best.loss, scale2, kind)
    motion = _motion(prob)
    labels = prob.labels
    edge = box.at_bound(best.theta).ravel()
    lo_edge = (best.theta <= box.lo + 1e-6).ravel()
    at_bound = tuple(f"{labels[i]} at its {'lower' if lo_edge[i] else 'upper'} bound "
                     f"{math.exp((box.lo if lo_edge[i] else box.hi).ravel()[i]):.4g}" for i in np.nonzero(edge)[0])
    # the Gauss-Newton step and standard errors, along the combined rate where the report's damping
    # and drag are both fitted (search.Ties: the search fits that rate; each of the two gets its
    # standard error)
    ties = Ties.of(ev, np.shape(best.theta))
    gn_step, stderr = gauss_newton(run.jac if ties is None else run.jac @ ties.basis, run.residual)
    if ties is not None and gn_step is not None:
        gn_step, stderr = ties.basis @ gn_step, ties.spread(stderr)
    # the identifiability report (its undetermined parameters set the status), with the rounding
    # noise of a finite-difference Jacobian from the measured reproducibility drift
    # (a mixed target's: its scan's, the tracks' residuals weighing against them as in the loss)
    factor = (1.0 / float(np.ravel(ev.residual.norm)[0]) if kind.compound
              else math.sqrt(int(prob.target.observed.sum()) * scale2))
    # (the drift was measured at the start values, which can be far less predictable than the
    # fitted ones: a torus from x0.5 drifts 0.086 mm, 0.0003 mm at the truth. A run at the fitted
    # values reproduces the target's to the residual RMS, so two runs near them differ by rounding
    # no more than that: the smaller of the two is the yardstick)
    drift = rounding_drift(prob)
    if drift is not None:
        drift = min(drift, rms)
    noise_j = None if run.jac_step is None or drift is None else _ident.fd_noise(drift, run.jac_step)
    report = _ident.analyse(run.jac * factor, np.nan_to_num(run.residual) * factor, labels, noise=prob.noise,
                            jac_noise=noise_j)
    if want_ident and report.unresolved:
        report = _resolve_again(prob, box, run, ev, _options.LocalOptions(**settings["local"]), report, drift,
                                factor, notes)
    out = _judge(prob, best.theta, batched=True, chunk_frames=run.horizons[0] if run.horizons else None,
                 rms=rms, noise=prob.noise, motion=motion, grad=run.grad, grad0=run.grad0,
                 stopped=best.stopped, at_bound=at_bound, gn_step=gn_step, stderr=stderr,
                 undetermined=report.undetermined if want_ident else ())
    theta = best.theta
    if prob.shooting is not None and prob.shooting.on and np.isfinite(best.loss):
        # multiple shooting's own bias, measured on a twin target and taken off (shooting.debias),
        # where the fit stopped at an optimum of its own (converged, or a poor fit: the method's
        # floor can be what keeps it from converging). Not at the reproducibility floor, where
        # rounding drift, not the method, sets the values' error and a linear estimate of the
        # bias does not hold (a torus dropped with the report's damping, in segments of 5 frames:
        # the estimate moved nmol from +2.3% to +3.7%), nor where the fit did not finish
        if out.status in (Status.CONVERGED, Status.POOR_FIT):
            theta, bias, line = _shooting.debias(prob, best.theta, ev)
        else:
            bias, line = None, (f"its own bias is not estimated: the fit ended {out.status.replace('_', ' ')}, where "
                                "the values' error is not the method's alone")
        inside = np.clip(theta, box.lo, box.hi)
        if not np.array_equal(inside, theta):
            theta, line = inside, line + " (held within the search box)"
        notes.append(f"shooting: {line}")
        if say is not None:
            say(f"shooting: {line}")
        if bias is not None:
            prob = dataclasses.replace(prob, shooting=dataclasses.replace(prob.shooting, bias=bias))
    e = ev(theta[None], keep_frames=True)
    frames = e.frames[0]
    if e.clamped[0]:
        msg = f"{diagnostics.MESSAGES[diagnostics.VOLUME_CLAMPED]} in the fitted rollout"
        warnings.warn(msg, VolumeClampWarning, stacklevel=3)
        notes.append(msg)
    if int(e.substeps[0]) > 1:
        msg = (f"the fitted values run stably only with {int(e.substeps[0])} substeps at dt = {prob.target.dt:g} s "
               "(their explicit limit is below dt); simulate them with --substeps")
        warnings.warn(msg, TimeStepWarning, stacklevel=3)
        notes.append(msg)
    ivals = None
    if want_ident:
        if out.status in _intervals.SHORT:
            # a fit that stopped short of the data: its neighbourhood does not say where the truth
            # lies (the twins' spread of a fit stuck 28% off was 0.015%); its interval is the box
            ivals = _intervals.box(report.labels, theta, box, out.status)
        else:
            # the values' 95% intervals from twins of the fitted values (jaxplush.fitting.judge.intervals),
            # at the reproducibility floor too: over all frames, where the identifiability report
            # leaves a parameter undetermined if the rounding noise of its Jacobian column swamps it
            # (twins over the predictable horizon alone missed: a capsule at its floor 0.052% off in
            # k against a spread of 0.0049%, benchmarks/RESULTS.md)
            ivals = _intervals.twins(prob, ev, theta, run.jac, report, residual=run.residual)
            # where values far from the fitted ones fit as well as rounding twins do (a chaotic
            # motion), the floor sets the precision, not the noise (intervals.scan)
            out = _limited(out, ivals)
    else:
        report = None
    # what the target determines where the parts are not: the report's damping with drag
    combos = _intervals.combinations(prob, theta, ivals, substeps=int(e.substeps[0]))
    path = best.history
    hist = _history(prob, [t for _, t in path], iteration=np.arange(len(path), dtype=np.int64),
                    loss=np.asarray([l for l, _ in path], np.float64), grad_norm=np.full(len(path), np.nan),
                    time=np.full(len(path), np.nan), rejected=np.zeros(0, np.int64))
    g = run.global_result
    paths = [(stage, hist, reason) for stage, stage_paths in enumerate(run.paths) for hist, reason in stage_paths]
    search = dict(global_thetas=g.thetas, global_loss=g.loss, global_ok=g.ok, global_substeps=g.substeps,
                  local_paths=[np.asarray([t for _, t in h]) for _, h, _ in paths],
                  local_losses=[np.asarray([l for l, _ in h]) for _, h, _ in paths],
                  local_reasons=[r for _, _, r in paths], local_stages=[s for s, _, _ in paths],
                  horizons=run.horizons, box_lo=box.lo, box_hi=box.hi, grad=run.grad, grad0=run.grad0)
    # the identifiability warnings only for a fit that reached the data at an optimum (converged or
    # undetermined: there the standard errors mean something)
    return _result(prob, theta, frames=frames, history=hist, outcome=out, report=report,
                   warn_report=out.status in _REPORTED, notes=notes, settings=settings,
                   loop=dataclasses.replace(run, state=lmfit.light_copy(run.state)),
                   wall=wall, stacklevel=3,
                   loss=float(best.loss), loss_start=float(run.loss0), iterations=int(run.evaluations),
                   rejected=int((~g.ok).sum()), reason=out.text, lr=None, search=search, intervals=ivals,
                   combinations=combos)
