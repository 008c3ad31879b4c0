"""A fit's result: :class:`FitResult`, made by :func:`_result` for every optimiser.

Also what a result is judged with: the reproducibility floor of the start values
(:func:`measure_predictability`), the outcome (:func:`_judge`, :mod:`jaxplush.fitting.judge.outcome`), the
target's motion (:func:`_motion`), and the identifiability report at a point
(:func:`identifiability_at`).
"""

from __future__ import annotations

import dataclasses
import warnings

import jax.numpy as jnp
import numpy as np

import jaxplush
from jaxplush.types import PARAM_NAMES, Params

from jaxplush.fitting.errors import FitWarning, IdentifiabilityWarning

from jaxplush.fitting.judge import identifiability as _ident
from jaxplush.fitting.objective import losses as _losses
from jaxplush.fitting.objective.losses import residual_samples
from jaxplush.fitting.judge.outcome import REPORTED, Status


@dataclasses.dataclass(frozen=True, eq=False)
class FitResult:
    """The outcome of :func:`fit`.

    Attributes:
      params: full :class:`jaxplush.types.Params` (numpy float64) with the fitted values.
      names: fitted parameter names; objects: fitted object names.
      values: dict name -> (O_f,) fitted values; start: dict name -> (O_f,) start values.
      loss: normalised loss at the fitted values (see :mod:`jaxplush.fitting.objective.losses`); loss_start.
      history: dict of arrays over accepted iterations: "iteration", "loss", "grad_norm",
        "time" (s), each fitted name (n, O_f); and "rejected" (iterations whose step was rejected).
      iterations: evaluations done; rejected: steps rejected (blow-ups).
      converged: the fit reached the data at an optimum (``status == "converged"``).
      reason: how it ended, in words (:attr:`outcome`'s message).
      identifiability: :class:`jaxplush.fitting.judge.identifiability.IdentifiabilityReport` (or None); its
        standard errors mean something only for a converged fit (:meth:`table` hides them otherwise).
      frames: (T, V, 3) simulated positions at the target frames with the fitted values.
      steps: (T,) their steps; dt.
      optimizer, lr, normalisation ("noise"/"motion"), scale2 (m²), noise.
      scene_text, scene_path, target_path, wall_time (s), warnings.
      predictability: :class:`jaxplush.Predictability` of the start values over the target,
        measured before fitting (None: not measured), or of the first fit's values where the fit
        was planned again from them (its ``warnings`` say so); the outcome's ``floor`` is the
        reproducibility floor it was judged against.
      intervals: :class:`jaxplush.fitting.judge.intervals.Intervals`, the fitted values' 95% intervals
        (the default fit: from twins of the fitted values where they apply, else from the
        residuals; ``intervals.method`` says which), or None (not measured). Shown by
        :meth:`table` for a fit that reached the data or the floor (:data:`jaxplush.fitting.judge.outcome.REPORTED`).
      combinations: :class:`jaxplush.fitting.judge.intervals.Combination` records of what the target
        determines where its parts are not (the report's ``damping`` fitted with ``drag``: their
        combined velocity decay rate), with their intervals; () when there are none.
      timing: :class:`jaxplush.compilestats.Timing` of the whole :func:`fit` call in this process
        (its report included; a resumed fit's earlier sessions not): ``wall_s``, ``compile_s``
        (XLA compiles and loads from the persistent cache), ``trace_s`` (tracing and lowering),
        ``programs`` (the programs it compiled or loaded), ``cache_hits`` (loaded); None when not
        measured. ``wall_time`` is the search's time (every session's), without the report.
    """

    params: Params
    names: tuple
    objects: tuple
    values: dict
    start: dict
    loss: float
    loss_start: float
    history: dict
    iterations: int
    rejected: int
    converged: bool
    reason: str
    identifiability: object
    frames: np.ndarray
    steps: np.ndarray
    dt: float
    optimizer: str
    lr: float | None
    normalisation: str
    scale2: float
    noise: float | None
    scene_text: str
    scene_path: str
    target_path: str
    wall_time: float
    warnings: tuple = ()
    loop: object = None     # the final LoopState / LMRun, whose .state a checkpoint holds (for a resumable file)
    problem: object = None  # the Problem that was solved
    settings: dict = dataclasses.field(default_factory=dict)
    outcome: object = None  # jaxplush.fitting.judge.outcome.Outcome
    search: dict = dataclasses.field(default_factory=dict)   # the default fit's samples and paths
    predictability: object = None  # jaxplush.Predictability of the start values
    timing: object = None  # jaxplush.compilestats.Timing: compile time apart from the rest
    intervals: object = None  # jaxplush.fitting.judge.intervals.Intervals: the values' 95% intervals
    combinations: tuple = ()  # jaxplush.fitting.judge.intervals.Combination: determined combinations of undetermined parts

    @property
    def status(self):
        """The :class:`jaxplush.fitting.judge.outcome.Status`: "converged", "poor_fit", "stalled", "iteration_limit",
        "at_bound", "at_floor" or "undetermined" (equal to those strings)."""
        if self.outcome is not None:
            return self.outcome.status
        return Status.CONVERGED if self.converged else Status.STALLED

    def table(self):
        """The fitted values as a text table: start, fitted value and, for a fit that reached the
        data or the floor (:data:`jaxplush.fitting.judge.outcome.REPORTED`), the approximate standard
        error and the 95% interval (for a fit that stopped short of them,
        :data:`jaxplush.fitting.judge.outcome.SHORT`, its search box in place of the interval); then the predictability and the outcome."""
        rep = self.identifiability
        se = {} if rep is None else dict(zip(rep.labels, rep.stderr))
        shown = self.status in REPORTED
        iv = self.intervals
        rows = [f"{'parameter':<14} {'object':<14} {'start':>12} {'fitted':>12} {'std. error':>11}"
                + ("  95% interval" if iv is not None else "")]
        for n in self.names:
            for j, o in enumerate(self.objects):
                label = f"{n}[{o}]"
                e = se.get(label, np.nan)
                if rep is None:
                    es = "-"
                elif not shown:
                    es = "n/a"
                else:
                    es = f"{100 * e:.2g}%" if np.isfinite(e) else "undetermined"
                row = f"{n:<14} {o:<14} {self.start[n][j]:>12.6g} {self.values[n][j]:>12.6g} {es:>11}"
                if iv is not None and label in iv.labels:
                    row += "  " + (iv.text(label) if shown or iv.method == "box" else "n/a")
                rows.append(row)
        rows.append(f"loss {self.loss_start:.4g} -> {self.loss:.4g} ({self.normalisation}-normalised) after "
                    f"{self.iterations} {'evaluations' if self.optimizer == 'lm' else 'iterations'} "
                    f"({self.rejected} rejected), {self.wall_time:.1f} s")
        if self.timing is not None:
            rows.append(f"time: {self.timing.text()}")
        if self.predictability is not None:
            rows.append(f"predictability: {self.predictability.text()}")
        for c in self.combinations:
            rows.append(f"determined: {c.text()}")
        rows.append(f"outcome: {self.reason}")
        if iv is not None and shown:
            rows.append(f"95% intervals: {iv.note}")
        elif iv is not None and iv.method == "box":
            rows.append(f"intervals: {iv.note}")
        if rep is not None and not shown:
            rows.append("standard errors: not meaningful, the fit reached neither the data nor the model's floor")
        return "\n".join(rows)

    def save(self, path):
        """Write FIT.h5 atomically (see :mod:`jaxplush.fitting.io`)."""
        from jaxplush.fitting import io as _io
        return _io.save_fit(self, path)

    def write_scene(self, path):
        """Write the scene with the fitted values (extended OBJ), ready to simulate."""
        from jaxplush.fitting import io as _io
        return _io.write_fitted_scene(self, path)


def _history(prob, thetas, **arrays):
    """A :attr:`FitResult.history`: ``arrays`` (iteration, loss, grad_norm, time, rejected) and each
    fitted parameter's values (n, O_f) at the log values ``thetas`` (n, P_n, O_f)."""
    hist = dict(arrays)
    th = np.asarray(thetas, np.float64).reshape(-1, len(prob.names), len(prob.objects))
    for i, n in enumerate(prob.names):
        hist[n] = np.exp(th[:, i])
    return hist


def _result(prob, theta, *, frames, history, outcome, report, warn_report, notes, settings, loop, wall, stacklevel,
            **fields):
    """The :class:`FitResult` of every fit (the default fit and the gradient optimisers) ending at
    log values ``theta``: the full parameters, the identifiability ``report`` (its warnings issued
    when ``warn_report``), the ``outcome`` (warned and noted unless converged), and ``fields``
    particular to the optimiser (loss, loss_start, iterations, rejected, reason, lr, search).
    ``stacklevel``: that of the caller's own warnings (its caller's caller is the user's code)."""
    notes = list(notes)
    if report is not None and warn_report:
        for w in report.warnings:
            warnings.warn(w, IdentifiabilityWarning, stacklevel=stacklevel + 1)
    if not outcome.converged:
        warnings.warn(outcome.text, FitWarning, stacklevel=stacklevel + 1)
        notes.append(outcome.text)
    vals = prob.values(theta)
    full = {n: np.array(getattr(prob.base, n), np.float64) for n in PARAM_NAMES}
    for n in prob.names:
        full[n][list(prob.objects)] = vals[n]
    return FitResult(
        params=Params(**full), names=prob.names, objects=tuple(prob.scene.object_names[o] for o in prob.objects),
        values=vals, start=prob.start, history=history, converged=outcome.converged, outcome=outcome,
        identifiability=report, frames=frames, steps=np.asarray(prob.loss.frame_steps, np.int64),
        dt=prob.target.dt, optimizer=settings["optimizer"], normalisation=prob.loss.normalisation,
        scale2=prob.loss.scale2, noise=prob.noise, scene_text=prob.scene.text, scene_path=prob.scene.path,
        target_path=prob.target.path, wall_time=float(wall), warnings=tuple(notes), loop=loop, problem=prob,
        settings=settings, predictability=prob.predictability, **fields)


def _motion(prob):
    """The target's RMS motion from the rest shape, m (the measure of the residual RMS)."""
    kind, scale2 = prob.target.kind, prob.loss.scale2
    if prob.loss.normalisation == "motion":
        return _losses.rms_metres(1.0, scale2, kind)
    rest = _losses.rest_distance(prob.target, prob.sim.topology)
    return float(np.sqrt(rest / _losses.components(kind)))


#: Most frames the predictability measurement saves per target frame (a target on an irregular
#: grid is measured on an even grid of about as many frames instead).
_PREDICTABILITY_FRAMES = 4


def _predictability_grid(target):
    """(steps, save_every) of the predictability measurement over a target: its last step, and
    the largest step that divides every frame's step (or, where that saves too many frames, an
    even grid with about as many frames as the target, on a step that divides the last one where
    one lies within a factor of two: a shorter last frame would be a program of its own)."""
    steps = int(target.steps[-1])
    every = int(np.gcd.reduce(np.asarray(target.steps, np.int64)))
    if steps // every > _PREDICTABILITY_FRAMES * target.n_frames + 100:
        near = max(1, steps // target.n_frames)
        whole = [d for d in range(near, max(1, near // 2) - 1, -1) if steps % d == 0]
        every = whole[0] if whole else near
    return steps, every


def _predictability_at(prob, theta=None, batched=False, chunk_frames=None):
    """:func:`jaxplush.predictability` of the problem's scene over its target at log values theta
    (default: the start values); None when a run blows up. With ``batched`` (for the default
    fit, whose search compiles the batched simulator anyway) its two float32 runs are lanes of that
    simulator's rollout, in pieces of ``chunk_frames`` frames as the search runs them
    (:func:`_batched_lanes`; None: each run of frames in one piece)."""
    steps, every = _predictability_grid(prob.target)
    params = None if theta is None else prob.params_at(theta)
    lanes = _batched_lanes(prob, steps, every, chunk_frames) if batched else None
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")   # a volume clamp or grown capacity: the fit reports its own
            return jaxplush.predictability(prob.scene, steps, prob.target.dt, every, params=params, sim=prob.sim,
                                           noise=prob.noise, motion=_motion(prob), lanes=lanes)
    except jaxplush.SimulationError:
        return None


def _batched_lanes(prob, steps, every, chunk_frames=None):
    """``lanes`` for :func:`jaxplush.predictability`: its runs as lanes of the batched simulator
    that the fit's evaluators share (:class:`jaxplush.fitting.objective.evaluate.Evaluator`, the full
    batch width, the frames in pieces of ``chunk_frames``, with their length and spacing as data),
    so that the measurement compiles no float32 program of its own; None where the evaluator
    would not run the target batched, or the grid does not end on its last step."""
    from jaxplush.fitting.objective.evaluate import Evaluator
    ev = Evaluator(prob, calibrate=False, chunk_frames=chunk_frames)
    if not ev.batched or steps % every:
        return None
    runs = [(int(every), int(steps // every))]

    def lanes(params, starts):
        one = Params(*(np.asarray(a, np.float64) for a in (prob.scene.params if params is None else params)))
        fr, ok, _, over, _ = ev._run_lanes([one] * len(starts), 1, runs, x0=starts, v0=np.zeros_like(starts),
                                           separation=True, width=ev.batch)
        return fr if ok.all() and not over.any() else None
    return lanes


def measure_predictability(prob, report=None, batched=False, chunk_frames=None):
    """The problem with :attr:`Problem.predictability` measured at the start values; ``report``
    (if given) gets the line that describes it. ``batched``, ``chunk_frames``: as
    :func:`_predictability_at` (the gradient fits, which compile no batched simulator, leave it off)."""
    pred = _predictability_at(prob, batched=batched, chunk_frames=chunk_frames)
    if report is not None:
        report("predictability: " + (pred.text() if pred is not None else
                                     "not measured (the rollout at the start values blows up)"))
    return dataclasses.replace(prob, predictability=pred)


def _judge(prob, theta, batched=False, chunk_frames=None, **kw):
    """:func:`jaxplush.fitting.judge.outcome.judge` of a fit ending at log values theta, with the
    reproducibility floor of :attr:`Problem.predictability`; for a fit that does not reach the
    data, or reaches it but is first-order optimal only because its residual lies within the
    floor, the floor is measured again at theta (the start's may be far from the result's;
    ``batched``, ``chunk_frames``: as :func:`_predictability_at`)."""
    from jaxplush.fitting.judge import outcome as _outcome
    kw.setdefault("samples", residual_samples(prob))
    pred = prob.predictability
    start = (None, None) if pred is None else (pred.floor, pred.horizon_time)
    if prob.shooting is not None and prob.shooting.on:
        # segments no longer than the horizon: the floor is the node states' (the shooting floor)
        return _outcome.judge(**kw, floor=prob.shooting.floor, horizon=None)
    out = _outcome.judge(**kw, floor=start[0], horizon=start[1])
    if pred is None or (out.reached and _outcome.judge(**kw).optimal):
        return out
    # not reached, or reached but optimal only within a floor: the floor at theta decides
    pred = _predictability_at(prob, theta, batched=batched, chunk_frames=chunk_frames) or pred
    return _outcome.judge(**kw, floor=pred.floor, horizon=pred.horizon_time)


def rounding_drift(prob):
    """The float32 rollout's own rounding drift over the fitted frames (RMS m), from the
    predictability measured at the start values: over the whole target, or with multiple
    shooting over one segment's length; None when not measured. A truncated problem
    (:meth:`Problem.truncated`) counts only the frames up to its last."""
    pred = prob.predictability
    if pred is None:
        return None
    use = (pred.times > 0) & (np.asarray(pred.steps) <= int(prob.target.steps[-1]))
    sh = prob.shooting
    if sh is not None and sh.on and prob.target.n_frames > 1:
        span = float(np.median(np.diff(np.asarray(prob.target.times, np.float64)))) * sh.segment_frames
        use &= pred.times <= pred.times[0] + span * (1 + 1e-9)
    d = np.asarray(pred.drift_rms, np.float64)[use]
    return float(np.sqrt(np.mean(d * d))) if d.size else None


def identifiability_at(prob, theta):
    """The :class:`jaxplush.fitting.judge.identifiability.IdentifiabilityReport` of a problem at log values theta."""
    frames, _, jac = _ident.frames_and_jacobian(prob.frames, jnp.asarray(theta, prob.sim.dtype))
    return _report(prob, frames, jac)


def _report(prob, frames, jac):
    residual, jac = prob.target.kind.linearised(prob.target, prob.sim.topology, prob.loss, frames, jac)
    return _ident.analyse(jac, residual, prob.labels, noise=prob.noise)
