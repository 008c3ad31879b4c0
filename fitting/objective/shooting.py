"""Multiple shooting: fit a position target in segments that restart from the observed positions.

Where the motion amplifies rounding (weakly damped wrinkling, tumbling), one rollout over the whole
target ("single shooting") drifts from any target, the true parameters' own included, by more than
the parameters move it: the loss is a needle on a rough plateau. Multiple shooting cuts the target
into segments no longer than the predictable horizon (:func:`jaxplush.predictability`) and
restarts each from the observed state at its first frame (its *node*), so no rollout runs past
the horizon. All segments of all points run as one batch ("lanes") of the batched engine.

Model of a segment (frames on an even grid, H seconds apart; every vertex observed):

* segment 0 starts from the scene's own start; segment j > 0 from the observed positions of its
  node frame, with node velocities estimated by central differences of the neighbouring frames,
  ``(x[k+1] - x[k-1]) / 2H``, then refined at each evaluated point by ``refine`` Gauss-Newton
  steps of the velocity against the next frame (Jacobian of the position after one frame with
  respect to the start velocity taken as ``H`` I, the free flight's): the node velocities are
  inner unknowns solved for each parameter value (a variable projection), and a refinement
  that does not bring the next frame closer is not taken;
* each segment is simulated to the next node; its frames, the next node's included, are the
  residuals: the position gap at every node (where one segment ends and the next restarts) is a
  residual like any frame's;
* a final frame off the grid (a run that also saves its last step) is simulated by the last
  segment, which then ends on the last grid frame: the segments are laid out from the end, and
  the first one is the short one.

Where one rollout's floor is below half of what a converged fit may leave (the outcome's rule
allows at most 1.25 x the noise, or 1% of the motion), nothing is measured: one rollout can converge. Otherwise,
node states estimated from frames carry an error of their own (modes faster than the frame rate
are aliased): :func:`plan` measures it (the *shooting floor*: multiple shooting of a target
simulated at the start values, at those values). A lower floor is not enough: short segments see
little of what accumulates over the whole motion (the report's per-step damping above all). So
the plan also measures how well each way resolves the parameters: the standard error of each
log-parameter if the residuals carried the way's floor as noise (from a central-difference
Jacobian at the start values, :func:`resolution`), and takes multiple shooting only where its
worst resolved parameter is resolved better than single shooting's. The fitted rollout written to
FIT.h5 is the single-shooting one (what ``jaxplush simulate`` gives for the fitted values).

The node states' error also biases a fit in segments: the parameters absorb part of it. After
such a fit, :func:`debias` measures that bias on a twin target (one rollout at the fitted values,
whose truth is known) and takes it off the fitted values.

Point-cloud targets observe no vertex, so they have no node states: where the horizon is
shorter than the target, the fit uses the frames within the horizon (and says so).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from jaxplush.errors import JaxplushError
from jaxplush.fitting.objective import losses as _losses
from jaxplush.fitting.objective.evaluate import Evaluator, MAX_CAPACITY_GROWTHS, _batchable
from jaxplush.fitting.options import MIN_SEGMENT, ShootingOptions

#: The default options (:class:`jaxplush.fitting.options.ShootingOptions`): every tuning number of
#: this module is one of its fields; the names below are aliases of their defaults.
_DEFAULT = ShootingOptions()
#: Gauss-Newton refinements of the node velocities per evaluation.
REFINE = _DEFAULT.refine
#: Fewest frames a point-cloud fit keeps when it stops at the predictable horizon.
MIN_HORIZON_FRAMES = _DEFAULT.min_horizon_frames


@dataclasses.dataclass(frozen=True)
class Shooting:
    """How a fit shoots (:func:`plan`).

    Attributes:
      segment_frames: frames per segment (None: single shooting).
      floor: the shooting floor, m (RMS of multiple shooting of the start values' own rollout),
        or None (not measured).
      single_floor: single shooting's reproducibility floor, m (:func:`jaxplush.predictability`), or None.
      resolution, single_resolution: the largest standard error of a log-parameter with the
        floor as noise (:func:`resolution`), multiple and single shooting's (None: not measured).
      refine: node-velocity refinements per evaluation.
      reason: a line for a person saying what was chosen and why.
      bias: multiple shooting's own bias at the fitted values, in log-parameters (theta's shape),
        taken off the fitted values (:func:`debias`); None: not estimated (single shooting, or the
        estimate did not hold).
    """

    segment_frames: int | None
    floor: float | None = None
    single_floor: float | None = None
    refine: int = REFINE
    reason: str = ""
    resolution: float | None = None
    single_resolution: float | None = None
    bias: np.ndarray | None = None
    options: ShootingOptions = _DEFAULT

    @property
    def on(self):
        return self.segment_frames is not None


def frame_grid(target):
    """(gap, tail) when the target's frames lie on an even grid from step 0 (a frame at step 0
    allowed): ``gap`` steps between frames, and ``tail`` the steps from the last grid frame to a
    final frame off the grid (0: none; a run that saves its final step too, as ``jaxplush
    simulate`` does when the steps are not a multiple of the saving interval, ends with one,
    fewer than ``gap`` steps on); else None."""
    steps = np.asarray(target.steps, np.int64)
    steps = steps[steps > 0]
    if steps.size < 2:
        return None
    gap = int(steps[0])
    if np.array_equal(steps, gap * np.arange(1, steps.size + 1)):
        return gap, 0
    grid, last = steps[:-1], int(steps[-1])
    tail = last - gap * grid.size
    if grid.size >= 2 and np.array_equal(grid, gap * np.arange(1, grid.size + 1)) and 0 < tail < gap:
        return gap, tail
    return None


def even_gap(target):
    """The steps between frames of the target's grid (:func:`frame_grid`), or None."""
    g = frame_grid(target)
    return None if g is None else g[0]


def why_not(prob):
    """Why multiple shooting cannot run on this problem (a phrase), or None when it can."""
    kind = prob.target.kind
    if not kind.every_vertex:
        seen = "not every vertex is observed" if kind.sees_vertices else "no vertex is observed"
        return f"the target is {kind.noun} ({seen}, so there are no node states)"
    if even_gap(prob.target) is None:
        return "the target's frames are not on an even grid"
    if prob.sim.integrator != "verlet":
        return f"the {prob.sim.integrator} integrator has no batched engine"
    if not _batchable(prob.sim.terms):
        return "this scene's terms have no batched engine"
    return None


class ShootingEvaluator(Evaluator):
    """An :class:`jaxplush.fitting.objective.evaluate.Evaluator` whose points run as segments of
    ``segment_frames`` frames (module docstring); the residuals have the layout of the single
    shooting's (every target frame, each simulated by its segment).

    Args:
      prob: :class:`jaxplush.fitting.fitter.Problem` with a position target on an even grid
        (:func:`frame_grid`).
      segment_frames: frames per segment (>= :data:`MIN_SEGMENT`).
      refine: node-velocity refinements per evaluation (0: central differences alone).
      **kw: as :class:`Evaluator`.
    """

    def forward_jacobian(self, theta, substeps=1):
        """None: forward-mode Jacobians do not cover the segments' restarts (the fit takes
        differences)."""
        return None

    def __init__(self, prob, segment_frames, refine=REFINE, **kw):
        super().__init__(prob, **kw)
        reason = why_not(prob)
        if reason is not None:
            raise JaxplushError(f"multiple shooting cannot run: {reason}")
        self.segment_frames = max(MIN_SEGMENT, int(segment_frames))
        self.refine = int(refine)
        t = prob.target
        self.gap, self.tail = frame_grid(t)
        keep = np.asarray(t.steps) > 0
        x0 = np.asarray(prob.sim.topology.x0, np.float64)
        frames = np.asarray(t.positions, np.float64)[keep]
        if self.tail:
            frames = frames[:-1]
        # observed positions at steps 0, gap, 2 gap, ...: the scene's start, then the target's frames
        # on the grid (an off-grid final frame is not a node)
        self.observed = np.concatenate([x0[None], frames])
        self.n_steps_frames = T = len(self.observed) - 1
        if self.tail:
            # every lane saves one frame more, ``tail`` steps after its last: the segments are
            # aligned to end at the last grid frame, so that the last segment's extra frame is the
            # off-grid final frame (the first segment is the short one)
            self.segment_frames = min(self.segment_frames, T)
            self.nodes = np.r_[0, np.arange(T, 0, -self.segment_frames)[::-1][:-1]].astype(np.int64)
        else:
            self.nodes = np.arange(0, T, self.segment_frames)
        self._runs = [(self.gap, self.segment_frames)] + ([(self.tail, 1)] if self.tail else [])
        self.h_frame = self.gap * t.dt
        obs = self.observed
        v = np.zeros((len(self.nodes),) + x0.shape)
        k = self.nodes[1:]
        v[1:] = (obs[k + 1] - obs[k - 1]) / (2.0 * self.h_frame)
        self.v_estimate = v
        # the target's frame at step 0 (if any) is the start itself, in every segmentation
        self._frame_rows = np.flatnonzero(keep)

    def _frames(self, thetas, n):
        self.evaluations += len(thetas)
        return self._segments(thetas, n)

    def _lanes(self, thetas):
        """Per lane (point, segment): values, start positions, velocities, start step."""
        n_seg = len(self.nodes)
        values = [self.prob.params_at(th) for th in thetas for _ in range(n_seg)]
        x0 = np.tile(self.observed[self.nodes], (len(thetas), 1, 1, 1)).reshape((-1,) + self.observed.shape[1:])
        v0 = np.tile(self.v_estimate, (len(thetas), 1, 1, 1)).reshape(x0.shape)
        step0 = np.tile(self.nodes * self.gap, len(thetas))
        return values, x0, v0, step0

    def _refine(self, values, x0, v0, step0, n):
        """Node velocities (lanes of segments after the first) refined against the next frame."""
        n_seg = len(self.nodes)
        rows = np.flatnonzero(np.arange(len(values)) % n_seg != 0)
        if not rows.size or self.refine <= 0:
            return v0
        nxt = self.observed[(step0[rows] // self.gap) + 1]
        vals = [values[i] for i in rows]
        v = v0[rows].copy()
        fr, ok, _, _ = self._run_lanes(vals, n, [(self.gap, 1)], x0[rows], v, step0[rows])
        gap = np.sqrt(np.mean((fr[:, 0] - nxt) ** 2, axis=(1, 2)))
        for _ in range(self.refine):
            trial = v + np.where(ok[:, None, None], nxt - fr[:, 0], 0.0) / self.h_frame
            fr2, ok2, _, _ = self._run_lanes(vals, n, [(self.gap, 1)], x0[rows], trial, step0[rows])
            gap2 = np.sqrt(np.mean((fr2[:, 0] - nxt) ** 2, axis=(1, 2)))
            better = ok2 & (gap2 < gap)
            v[better], fr[better], gap[better] = trial[better], fr2[better], gap2[better]
        out = v0.copy()
        out[rows] = v
        return out

    def _segments(self, thetas, n):
        """(frames (N, T, V, 3), ok, clamped, separation, inverted) of :meth:`Evaluator._frames`,
        run as segments (a point's separation: the least of its segments'; inverted: -1, every
        failure retried with more substeps)."""
        n_pts, n_seg, seg = len(thetas), len(self.nodes), self.segment_frames
        values, x0, v0, step0 = self._lanes(thetas)
        v0 = self._refine(values, x0, v0, step0, n)
        fr, good, clamp, over, sep = self._run_lanes(values, n, self._runs, x0, v0, step0, separation=True)
        for _ in range(MAX_CAPACITY_GROWTHS):
            lanes = np.flatnonzero(over)
            if not lanes.size or not self._grow_contact(thetas[lanes[0] // n_seg]):
                break
            pts = np.unique(lanes // n_seg)
            redo = (pts[:, None] * n_seg + np.arange(n_seg)).ravel()
            fr[redo], good[redo], clamp[redo], over[redo], sep[redo] = self._run_lanes(
                [values[i] for i in redo], n, self._runs, x0[redo], v0[redo], step0[redo], separation=True)
        if over.any():
            self.notes.append("contact candidates still overflowed in some segments after growing the capacity")
        T = self.n_steps_frames
        out = np.empty((n_pts, T + (1 if self.tail else 0)) + self.observed.shape[1:])
        fr = fr.reshape((n_pts, n_seg) + fr.shape[1:])
        ends = np.r_[self.nodes[1:], T]
        for j, k in enumerate(self.nodes):
            m = min(seg, ends[j] - k)
            out[:, k:k + m] = fr[:, j, :m]
        if self.tail:
            out[:, T] = fr[:, -1, seg]          # the last segment ends at T (__init__)
        full = np.empty((n_pts, self.prob.target.n_frames) + out.shape[2:])
        full[:, self._frame_rows] = out
        full[:, np.setdiff1d(np.arange(self.prob.target.n_frames), self._frame_rows)] = self.observed[0]
        return (full, good.reshape(n_pts, n_seg).all(axis=1), clamp.reshape(n_pts, n_seg).any(axis=1),
                sep.reshape(n_pts, n_seg).min(axis=1), np.full(n_pts, -1, np.int64))

    def __call__(self, thetas, substeps=None, keep_frames=False, retries=None):
        """As :meth:`Evaluator.__call__`; the frames kept (``keep_frames``) are the single-shooting
        rollout's (the fitted motion), the residuals multiple shooting's."""
        e = super().__call__(thetas, substeps=substeps, retries=retries)
        if not keep_frames:
            return e
        whole = Evaluator(self.prob, calibration=self.calibration(), share=self)(thetas, substeps=e.substeps,
                                                                               keep_frames=True)
        return e._replace(frames=whole.frames)


def evaluator(prob, **kw):
    """The evaluator of a problem: :class:`ShootingEvaluator` where its :attr:`shooting` is on,
    else :class:`jaxplush.fitting.objective.evaluate.Evaluator`."""
    sh = getattr(prob, "shooting", None)
    if sh is not None and sh.on:
        return ShootingEvaluator(prob, sh.segment_frames, sh.refine, **kw)
    return Evaluator(prob, **kw)


def _floor(prob, segment_frames, refine, chunk_frames=None):
    """(the shooting floor (module docstring) of ``segment_frames`` frames at the start values, m,
    or None when the start's own rollout does not run; how close the objects came in that rollout,
    :attr:`jaxplush.fitting.objective.evaluate.Evaluation.separation`, NaN where not measured).
    ``chunk_frames``: as :class:`jaxplush.fitting.objective.evaluate.Evaluator`'s."""
    ev = Evaluator(prob, chunk_frames=chunk_frames)
    e = ev(prob.theta0[None], keep_frames=True)
    sep = math.nan if e.separation is None else float(e.separation[0])
    if not e.ok[0]:
        return None, sep
    own = dataclasses.replace(prob.target, positions=e.frames[0], noise=None)
    twin = dataclasses.replace(prob, target=own)
    ms = ShootingEvaluator(twin, segment_frames, refine, calibration=ev.calibration(), share=ev)
    d = ms(prob.theta0[None], substeps=e.substeps, keep_frames=False)
    if not d.ok[0]:
        return None, sep
    # the residuals are normalised by the target's scale: back to metres per coordinate
    return _losses.rms_metres(float(d.loss[0]), prob.loss.scale2, prob.target.kind), sep


#: Central-difference step (log space) of :func:`resolution`'s Jacobian (``ShootingOptions.resolution_step``).
RESOLUTION_STEP = _DEFAULT.resolution_step


def resolution(ev, theta, floor, separation=math.nan, step=RESOLUTION_STEP):
    """The largest standard error of a log-parameter at theta if every residual of ``ev`` carried
    noise of RMS ``floor`` (m): sqrt of the largest diagonal entry of s² (JᵀJ)⁻¹, J the
    central-difference Jacobian (``step``, log space; ``separation``: how close the objects came
    in the run at theta, as :func:`jaxplush.fitting.stages.search.jacobian` takes it); inf where J is
    singular, None where the stencil does not run."""
    from jaxplush.fitting.stages import search as _search
    theta = np.asarray(theta, np.float64)
    box = _search.Box(theta - 1.0, theta + 1.0)
    jac = _search.jacobian(ev, box, theta, step, separation=separation)
    if not np.isfinite(jac).all() or not np.any(jac):
        return None
    prob = ev.prob
    # the floor as a normalised loss, spread evenly over the residual entries
    s2 = floor ** 2 * prob.target.kind.components / prob.loss.scale2 / jac.shape[0]
    try:
        cov = s2 * np.linalg.inv(jac.T @ jac)
    except np.linalg.LinAlgError:
        return math.inf
    d = np.diag(cov)
    return float(np.sqrt(d.max())) if np.all(d > 0) else math.inf


#: Largest bias (log space) :func:`debias` takes off (``ShootingOptions.max_bias``).
MAX_BIAS = _DEFAULT.max_bias


def debias(prob, theta, ev=None, step=None):
    """Multiple shooting's own bias at the fitted values ``theta``, estimated and taken off.

    Node velocities estimated from the frames carry an error (modes faster than the frame rate
    are aliased, and a refinement against the next frame does not remove it), and the fitted
    parameters absorb part of it: a noise-free target fitted in segments converges a few percent
    off (``scenes/ball_drop.obj`` in segments of 8 frames: k +3%). That error is a property of
    the method at these values, so it is measured on a *twin*: the target simulated in one rollout
    at ``theta``, whose truth is known. One Gauss-Newton step of multiple shooting on the twin
    from ``theta`` (central-difference Jacobian, ``step`` in log space) is where a fit of the twin
    would go: ``theta + b``. The fit of the real target is then taken to sit ``b`` off its own truth
    (a parametric bootstrap's bias correction), and ``theta - b`` is returned.

    The step is taken off only where the linear model holds on the twin: the twin's loss at
    ``theta + b`` is below its loss at ``theta``, and every entry of ``b`` is within
    ``max_bias`` of the plan's options (``step`` None: their ``resolution_step``).

    Returns:
      (corrected theta, b or None, a line for a person). ``b`` None: nothing taken off, and the
      line says why.
    """
    from jaxplush.fitting.stages import search as _search
    sh = prob.shooting
    theta = np.asarray(theta, np.float64)
    if sh is None or not sh.on:
        return theta, None, "single shooting: nothing to correct"
    step = sh.options.resolution_step if step is None else step
    max_bias = sh.options.max_bias
    base = Evaluator(prob, calibration=None if ev is None else ev.calibration(), share=ev)
    e = base(theta[None], keep_frames=True)
    if not e.ok[0]:
        return theta, None, "the fitted values' rollout did not run"
    own = dataclasses.replace(prob.target, positions=e.frames[0], noise=None)
    twin = dataclasses.replace(prob, target=own)
    ms = ShootingEvaluator(twin, sh.segment_frames, sh.refine, calibration=base.calibration(), share=base)
    at = ms(theta[None], substeps=e.substeps)
    box = _search.Box(theta - 1.0, theta + 1.0)
    jac = _search.jacobian(ms, box, theta, step, substeps=int(e.substeps[0]))
    r = at.residuals[0]
    if not (at.ok[0] and np.isfinite(jac).all() and np.isfinite(r).all() and np.any(jac)):
        return theta, None, "the twin's Jacobian did not run"
    b = -np.linalg.lstsq(jac, r, rcond=None)[0].reshape(theta.shape)
    if not np.all(np.abs(b) <= max_bias):
        return theta, None, (f"the estimate ({_percent(prob, b)}) exceeds {math.expm1(max_bias):.0%}: "
                             "not taken off")
    moved = ms((theta + b)[None], substeps=e.substeps)
    if not (moved.ok[0] and moved.loss[0] < at.loss[0]):
        return theta, None, f"the estimate ({_percent(prob, b)}) does not lower the twin's loss: not taken off"
    return theta - b, b, (f"values corrected for multiple shooting's own bias, estimated on a twin target "
                          f"simulated at the fitted values: {_percent(prob, b)} taken off")


def _percent(prob, b):
    """``b`` (log space) as relative changes per label, e.g. "k_structural[ball] +3.1%"."""
    return ", ".join(f"{label} {math.expm1(v):+.2%}" for label, v in zip(prob.labels, np.ravel(b)))


def segment_frames_for(prob, min_segment=MIN_SEGMENT):
    """Frames per segment from the measured horizon (at least ``min_segment``), or None when
    the positions stay predictable over the whole target (or it was not measured)."""
    pred = prob.predictability
    if pred is None or not math.isfinite(pred.horizon_time):
        return None
    gap = even_gap(prob.target)
    if gap is None:
        return None
    h = gap * prob.target.dt
    return max(MIN_SEGMENT, int(min_segment), int(pred.horizon_time / h))


def check_segments(setting, target, what="shooting (--shooting)"):
    """Refuse frames per segment (an int ``setting``; "auto" and "off" pass) longer than the
    fitted target's frames: a :class:`jaxplush.errors.JaxplushError` naming ``what``."""
    if setting in ("auto", "off", None):
        return
    n, t = int(setting), int(target.n_frames)
    if n < MIN_SEGMENT:
        raise JaxplushError(f"{what} {n}: a segment needs at least {MIN_SEGMENT} frames")
    if n > t:
        frames = f"{t} frame" + ("s" if t != 1 else "")
        fix = f"give at most {t}, auto or off" if t >= MIN_SEGMENT else "give auto or off"
        raise JaxplushError(f"{what} {n}: segments of {n} frames are longer than the target, which has {frames} "
                            f"after its start; {fix}")


def plan(prob, setting="auto", options=None, chunk_frames=None):
    """How to shoot a problem (after its predictability was measured).

    Args:
      prob: :class:`jaxplush.fitting.fitter.Problem`.
      setting: "off" (single shooting), "auto" (multiple shooting where the horizon is shorter
        than the target and the shooting floor is below single shooting's), or frames per segment.
      options: :class:`jaxplush.fitting.options.ShootingOptions` (None: the defaults).
      chunk_frames: the frames of the batched rollouts that measure the choice (as
        :class:`jaxplush.fitting.objective.evaluate.Evaluator`'s; the fit's first horizon, so
        that they run on the program its search compiles).

    Returns:
      (:class:`Shooting`, the problem to fit: a point-cloud target cut at the horizon under "auto").

    Raises:
      JaxplushError: frames per segment were asked for and multiple shooting cannot run.
    """
    o = _DEFAULT if options is None else options
    refine = o.refine
    pred = prob.predictability
    single = None if pred is None else float(pred.floor)
    if setting == "off":
        return Shooting(None, single_floor=single, reason="single shooting (--shooting off)"), prob
    if setting != "auto":
        reason = why_not(prob)
        if reason is not None:
            raise JaxplushError(f"--shooting {setting}: multiple shooting cannot run: {reason}")
        seg = max(MIN_SEGMENT, int(setting))
        floor, _ = _floor(prob, seg, refine, chunk_frames)
        return Shooting(seg, floor, single, refine, f"multiple shooting in segments of {seg} frames (asked for)"
                        + ("" if floor is None else f"; shooting floor {floor * 1e3:.3g} mm"), options=o), prob
    if pred is None or not math.isfinite(pred.horizon_time):
        why = "not measured" if pred is None else "the positions stay predictable over the whole target"
        return Shooting(None, single_floor=single, reason=f"single shooting ({why})"), prob
    reason = why_not(prob)
    if reason is not None and not prob.target.kind.every_vertex:
        return _points_within_horizon(prob, single, o.min_horizon_frames)
    if reason is not None:
        return Shooting(None, single_floor=single, reason=f"single shooting ({reason})"), prob
    seg = segment_frames_for(prob, o.min_segment)
    if seg >= prob.target.n_frames:
        return Shooting(None, single_floor=single, reason="single shooting (the horizon spans the target)"), prob
    need = _reach(prob)
    if single is not None and single <= need / 2:
        return Shooting(None, single_floor=single, reason=(
            f"single shooting (its floor, {single * 1e3:.3g} mm, is below half of what a converged fit "
            f"needs, {need * 1e3:.3g} mm)")), prob
    floor, sep = _floor(prob, seg, refine, chunk_frames)
    if floor is None or single is None or floor >= single:
        why = ("the shooting floor could not be measured" if floor is None or single is None else
               f"node states estimated from the frames ({floor * 1e3:.3g} mm) are no better than "
               f"single shooting's floor ({single * 1e3:.3g} mm)")
        return Shooting(None, floor, single, refine, f"single shooting ({why})", options=o), prob
    ms = ShootingEvaluator(prob, seg, refine, chunk_frames=chunk_frames)
    res_ms = resolution(ms, prob.theta0, floor, sep, o.resolution_step)
    res_single = resolution(Evaluator(prob, calibration=ms.calibration(), share=ms), prob.theta0, single, sep,
                            o.resolution_step)
    floors = f"shooting floor {floor * 1e3:.3g} mm against single shooting's {single * 1e3:.3g} mm"
    if res_ms is None or res_single is None or not res_ms < res_single:
        why = ("the parameters' resolution could not be measured" if res_ms is None or res_single is None else
               f"{floors}, but segments of {seg} frames resolve the parameters less well: a log-parameter "
               f"to {res_ms:.2g} against {res_single:.2g}")
        return Shooting(None, floor, single, refine, f"single shooting ({why})", res_ms, res_single,
                        options=o), prob
    return Shooting(seg, floor, single, refine,
                    f"multiple shooting in segments of {seg} frames (the horizon is {pred.horizon_time:.3g} s; "
                    f"{floors}; a log-parameter resolved to {res_ms:.2g} against {res_single:.2g})",
                    res_ms, res_single, options=o), prob


def span(prob):
    """How much of the target a planned problem fits at a stretch: (frames fitted, frames per
    segment; a single-shooting problem's segment is all of them). Larger tuples fit more."""
    n = int(prob.target.n_frames)
    sh = prob.shooting
    return n, (int(sh.segment_frames) if sh is not None and sh.on else n)


def restricted(full, prob):
    """Whether the planned problem fits less than the full one at a stretch (a point-cloud target
    cut at the horizon, or multiple shooting)."""
    return span(prob) < (int(full.target.n_frames),) * 2


def plan_shooting(prob, setting, report=None, options=None, chunk_frames=None):
    """The problem with :attr:`~jaxplush.fitting.objective.problem.Problem.shooting` planned (:func:`plan`,
    with ``options`` and ``chunk_frames``); ``report`` (if given) gets the line that says what was chosen."""
    sh, prob = plan(prob, setting, options, chunk_frames)
    if report is not None:
        report("shooting: " + sh.reason)
    return dataclasses.replace(prob, shooting=sh)


def _reach(prob):
    """The residual RMS (m) a converged fit must reach (:func:`jaxplush.fitting.judge.outcome.judge`):
    ``NOISE_FACTOR`` x the noise, or ``MOTION_FRACTION`` x the target's motion."""
    from jaxplush.fitting.judge import outcome
    from jaxplush.fitting.judge.result import _motion
    if prob.noise:
        return outcome.NOISE_FACTOR * float(prob.noise)
    return outcome.MOTION_FRACTION * _motion(prob)


def _points_within_horizon(prob, single, min_frames=MIN_HORIZON_FRAMES):
    """A point-cloud or tracks target cut at the predictable horizon (at least ``min_frames`` frames)."""
    t, pred = prob.target, prob.predictability
    keep = int(np.searchsorted(np.asarray(t.times, np.float64), pred.horizon_time, side="right"))
    seen = max(int(np.argmax(part.observed.any(axis=1))) + 1 for part in t.parts)     # each part observes
    keep = max(min(int(min_frames), t.n_frames), keep, seen)
    if keep >= t.n_frames:
        return Shooting(None, single_floor=single, reason="single shooting (the horizon spans the target)"), prob
    reason = (f"single shooting within the predictable horizon: the first {keep} of {t.n_frames} frames "
              f"(up to {float(t.times[keep - 1]):.3g} s; a "
              f"{t.kind.adjective} "
              "target has no node states to shoot from)")
    return Shooting(None, single_floor=single, reason=reason), prob.truncated(keep)
