"""The gradient optimisers' fit: "adam", "lbfgs" or a user's optax transformation.

The optimiser is a stage (:class:`Gradient`, the protocol of :mod:`jaxplush.fitting.stages`) on
the log-parameters: each step evaluates the loss and its exact gradient through the rollout
(:func:`_make_step`) and steps (:func:`_iterate`); a step whose rollout blows up (non-finite loss or
gradient, an inverted object, damping < 1) is rejected and the step halved (:func:`_reject`); it
stops at its iteration limit or a tolerance (:func:`_check_convergence`). Its state is a
:class:`LoopState`, a new one per step, which checkpoints hold
(:func:`jaxplush.fitting.io.save_checkpoint`), so a resumed fit continues to the same answer.
:func:`drive` runs it with :func:`jaxplush.fitting.stages.run_stages` (the loop every fit family
shares: progress, callback, checkpoints and Ctrl-C as its hooks), for the gradient fit
(:class:`_GradientFit`) and the stiffness field's (:func:`jaxplush.fitting.stages.field.fit_field`);
:func:`_finish` makes the :class:`jaxplush.fitting.judge.result.FitResult` at the best accepted point.
"""

from __future__ import annotations

import dataclasses
import math
import time
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import optax

import jaxplush
from jaxplush.compilestats import compile_clock
from jaxplush.stepping import diagnostics
from jaxplush.errors import ContactCapacityWarning, JaxplushError, TimeStepWarning, VolumeClampWarning, warn
from jaxplush.progress import Progress

from jaxplush.fitting.judge import identifiability as _ident
from jaxplush.fitting.judge import intervals as _intervals
from jaxplush.fitting.objective import losses as _losses
from jaxplush.fitting.errors import FitError
from jaxplush.fitting.stages import Candidate, Hooks, RunState, run_stages, saving_on_interrupt
from jaxplush.fitting.judge.outcome import Stop, limited_by_rounding
from jaxplush.fitting.objective.problem import _common_settings
from jaxplush.fitting.judge.result import _history, _judge, _motion, _report, _result, measure_predictability


OPTIMIZERS = ("lm", "adam", "lbfgs")


#: Default learning rates (log space) per optimiser (L-BFGS: none, the line search sets the step).
DEFAULT_LR = {"adam": 0.05, "lbfgs": None, "lm": None}


MAX_REJECTIONS = 30


def make_optimizer(name, lr=None, iterations=100):
    """optax optimiser for the log-parameters: "adam" (cosine-decayed lr) or "lbfgs"."""
    if name not in OPTIMIZERS:
        raise JaxplushError(f"unknown optimizer {name!r}; expected {' or '.join(OPTIMIZERS)}")
    if name == "adam":
        lr = DEFAULT_LR["adam"] if lr is None else float(lr)
        if not (np.isfinite(lr) and lr > 0):
            raise JaxplushError(f"learning rate must be > 0, got {lr!r}")
        return optax.adam(optax.cosine_decay_schedule(lr, max(int(iterations), 1), alpha=0.01))
    if lr is not None and not (np.isfinite(lr) and lr > 0):
        raise JaxplushError(f"learning rate must be > 0, got {lr!r}")
    return optax.lbfgs(learning_rate=None if lr is None else float(lr))


def optimizer_kind(optimizer):
    """"lm", "adam" or "lbfgs" for those names, "optax" for an ``optax.GradientTransformation``."""
    if isinstance(optimizer, str) and optimizer in OPTIMIZERS:
        return optimizer
    if isinstance(optimizer, optax.GradientTransformation):
        return "optax"
    raise JaxplushError(f"unknown optimizer {optimizer!r}; expected one of {', '.join(OPTIMIZERS)} or an "
                        "optax.GradientTransformation")


@dataclasses.dataclass
class LoopState:
    """The complete state of the optimisation loop (what a checkpoint holds).

    ``theta`` is the next point to evaluate, with ``opt_state`` the optimiser state to use
    there; ``anchor`` the last accepted point it was reached from (None before the first).
    """

    theta: np.ndarray
    opt_state: object
    anchor: np.ndarray | None = None
    scale: float = 1.0
    iteration: int = 0           # evaluations done (accepted + rejected)
    rejected: int = 0
    rejected_in_row: int = 0
    stall: int = 0
    best_theta: np.ndarray | None = None
    best_loss: float = math.inf
    done: bool = False
    reason: str = ""             # why it stopped, in words for a person
    stopped: Stop = Stop.NONE    # ... and as a :class:`jaxplush.fitting.judge.outcome.Stop`
    h_iter: list = dataclasses.field(default_factory=list)
    h_loss: list = dataclasses.field(default_factory=list)
    h_theta: list = dataclasses.field(default_factory=list)
    h_gnorm: list = dataclasses.field(default_factory=list)
    h_time: list = dataclasses.field(default_factory=list)
    h_rejected: list = dataclasses.field(default_factory=list)
    wall: float = 0.0

    def snapshot(self):
        """A copy that later iterations do not change (lists copied; arrays are never mutated)."""
        return dataclasses.replace(self, **{f.name: list(getattr(self, f.name)) for f in dataclasses.fields(self)
                                            if f.name.startswith("h_")})


@dataclasses.dataclass(frozen=True)
class Gradient:
    """A gradient optimiser as a stage: an optax ``transformation`` on the log-parameters, each
    step one evaluation of the loss and its exact gradient through the rollout (the fused adjoint
    or checkpointed reverse mode, as the problem's ``method`` says). A step whose rollout blows up
    is rejected and the step halved (a line search's state restarted); a point whose soft-soft
    contact candidates overflow is evaluated again with a grown capacity, where the objective can
    grow it. It stops at ``iterations`` evaluations or a tolerance:

    * ``ftol``: the loss at or below it; ``gtol``: the gradient's max-norm at or below it;
    * ``rtol``: the relative loss change at or below it for ``patience`` accepted steps in a row;
    * ``xtol``: a step's max-norm (log space) at or below it.

    Its candidate is the best accepted point. The objective is anything with ``prob`` (a problem
    with ``loss_fn``, ``theta0``, ``sim``, ``valid`` and ``values``: the gradient fit's, a stiffness
    field's, or the default fit's :class:`jaxplush.fitting.stages.Objective`), and optionally
    ``grow_contact(theta) -> bool``, which rebuilds ``prob`` with room for contact.

    Attributes: transformation (an ``optax.GradientTransformation``), iterations, ftol, gtol,
    rtol, xtol, patience (defaults: :class:`jaxplush.fitting.FitOptions`'s).
    """

    transformation: object
    iterations: int = 100
    ftol: float = 0.0
    gtol: float = 1e-9
    rtol: float = 1e-7
    xtol: float = 1e-7
    patience: int = 5

    @classmethod
    def from_options(cls, transformation, opts, iterations):
        """The stage with the tolerances of :class:`jaxplush.fitting.FitOptions` ``opts``."""
        return cls(transformation, int(iterations), ftol=opts.ftol, gtol=opts.gtol, rtol=opts.rtol,
                   xtol=opts.xtol, patience=int(opts.patience))

    def init(self, objective, theta, state=None):
        """Start at the previous stage's candidate (or state) point, else at ``theta``."""
        prob = objective.prob
        point = getattr(state, "theta", None)
        th0 = jnp.asarray(np.asarray(theta if point is None else point).reshape(np.shape(prob.theta0)),
                          prob.sim.dtype)
        return LoopState(theta=np.asarray(th0), opt_state=jax.jit(self.transformation.init)(th0),
                         best_theta=np.asarray(th0))

    def step(self, objective, s):
        """One evaluation and update, on a copy of ``s``; ``s`` itself where the point is to be
        evaluated again because the contact capacity was grown."""
        prob = objective.prob
        fn, linesearch = stepper(objective, self.transformation)
        new = s.snapshot()
        grow = getattr(objective, "grow_contact", None)
        try:
            _iterate(prob, self.transformation, linesearch, fn, new, self)
        except FitError:
            if grow is None or not grow(s.theta):
                raise
            return s
        if new.h_rejected and new.h_rejected[-1] == s.iteration and grow is not None and grow(s.theta):
            return s
        return new

    def terminate(self, objective, s):
        if s.done:
            return True, s.stopped
        if s.iteration >= self.iterations:
            return True, Stop.ITERATIONS
        return False, Stop.NONE

    def postprocess(self, objective, s):
        best = s.best_theta if s.best_theta is not None else s.theta
        return Candidate(theta=np.asarray(best, np.float64), loss=float(s.best_loss),
                         reason=f"the best of {s.iteration} gradient steps ({s.reason or 'iteration limit'})",
                         stopped=s.stopped or Stop.ITERATIONS)

    def finished(self, s):
        """``s`` with the iteration limit said as its reason where nothing else stopped it."""
        if s.done:
            return s
        return dataclasses.replace(s.snapshot(), reason=f"reached the iteration limit ({self.iterations})",
                                   stopped=Stop.ITERATIONS)


def stepper(objective, transformation):
    """(the jitted update of :func:`_make_step`, whether the transformation holds a line search)
    for the objective's current problem, made once per problem and kept on the objective."""
    prob = objective.prob
    cache = objective.__dict__.setdefault("_gradient_steps", {})
    key = (id(prob), id(transformation))
    if key not in cache:
        shape = jax.eval_shape(transformation.init, jax.ShapeDtypeStruct(np.shape(prob.theta0), prob.sim.dtype))
        linesearch = uses_linesearch(shape)
        cache[key] = (prob, _make_step(prob, transformation, linesearch), linesearch)
    return cache[key][1:]


def drive(objective, stage, loop, *, bar=None, callback=None, save=None, every=None):
    """Run one :class:`Gradient` ``stage`` from ``loop`` (a fresh :class:`LoopState` or a
    checkpoint's) by :func:`jaxplush.fitting.stages.run_stages`, with its hooks: after each
    step the progress ``bar`` and the ``callback`` (a dict of iteration, loss, values and
    grad_norm; True stops the fit); ``save(state, status)`` every ``every`` evaluations and, with
    status "interrupted", on Ctrl-C (the state before the step that was interrupted). Returns the
    final state, its reason set (:meth:`Gradient.finished`)."""
    prob_values = lambda th: objective.prob.values(th)  # noqa: E731  (the problem may be rebuilt)
    t_loop = time.perf_counter() - loop.wall
    seen, saved = [loop.iteration], [loop.iteration]

    def after(run):
        s = run.state
        s.wall = time.perf_counter() - t_loop
        if s.iteration == seen[0]:
            return                          # the same point again, with a grown contact capacity
        seen[0] = s.iteration
        if s.h_iter and s.h_iter[-1] == s.iteration - 1:
            vals = prob_values(s.h_theta[-1])
            if bar is not None:
                bar.update(1, extra=_progress_text(s.h_loss[-1], vals))
            if callback is not None:       # every accepted iteration, the last one too
                stop = callback(dict(iteration=s.iteration - 1, loss=s.h_loss[-1], values=vals,
                                     grad_norm=s.h_gnorm[-1]))
                if stop is True and not s.done:
                    s.done, s.reason, s.stopped = True, "stopped by the callback", Stop.CALLBACK
        elif bar is not None:
            bar.update(1, extra="step rejected (rollout blew up); halving the step")

    def checkpoint(run):
        s = run.state
        if save is not None and every and s.iteration - saved[0] >= int(every) and not s.done:
            save(s, "running")
            saved[0] = s.iteration

    def interrupted(run):
        if save is not None and run.state is not None:
            run.state.wall = time.perf_counter() - t_loop
            save(run.state, "interrupted")

    run = RunState(index=0, state=loop, wall=loop.wall)
    (final,) = run_stages(objective, loop.theta, [stage], state=run,
                          hooks=Hooks(after=after, save=checkpoint, interrupted=interrupted))
    final.wall = time.perf_counter() - t_loop
    return stage.finished(final)


#: Depth from :class:`_GradientFit`'s methods to the caller of :func:`fit`, for warnings.
_LOOP_STACKLEVEL = {"warn_dt": 4, "grow_contact": 7}


class _GradientFit:
    """The gradient fit: its problem, the optimiser as a :class:`Gradient` stage, run by
    :func:`drive` (progress, callback, checkpoints, Ctrl-C), then :func:`_finish`. It is the
    stage's objective: ``prob``, and ``grow_contact`` after a contact-candidate overflow."""

    def __init__(self, prob, optimizer, opts, notes, *, progress, callback, report=None):
        self.kind = optimizer_kind(optimizer)
        self.iterations = opts.iteration_limit(self.kind)
        self.opt = optimizer if self.kind == "optax" else make_optimizer(self.kind, opts.lr, self.iterations)
        self.stage = Gradient.from_options(self.opt, opts, self.iterations)
        self.prob, self.opts, self.notes = prob, opts, notes
        self.progress, self.callback, self.note = progress, callback, report
        shape = jax.eval_shape(self.opt.init, jax.ShapeDtypeStruct(np.shape(prob.theta0), prob.sim.dtype))
        self.settings = _common_settings(prob, opts, self.kind, self.iterations, opts.lr)
        self.settings.update(gtol=opts.gtol, rtol=opts.rtol, xtol=opts.xtol, ftol=opts.ftol,
                             patience=int(opts.patience), frame_steps=list(prob.loss.frame_steps),
                             target_kind=prob.target.kind)
        if self.kind == "optax":     # what a resume can check of a user's transformation: its state's structure
            self.settings["optax_state"] = str(jax.tree_util.tree_structure(shape))
        self.bar = None

    def run(self, t_start, clock=None):
        """The whole fit: the loop (from a checkpoint with ``resume``), its result, FIT.h5.
        ``clock``: a :class:`jaxplush.compilestats.CompileClock` started with the fit, whose
        :class:`~jaxplush.compilestats.Timing` the result gets (None: one started here)."""
        clock = compile_clock() if clock is None else clock
        loop = self.initial_loop()
        if self.opts.predictability:        # every input checked (a resumed checkpoint too)
            self.prob = measure_predictability(self.prob, self.note)
        self.warn_dt(loop)
        wall_before = loop.wall
        self.bar = Progress(self.iterations, "fit", enabled=self.progress, unit="it", compiles=True)
        self.bar.done = min(loop.iteration, self.iterations)
        with self.bar:
            loop = drive(self, self.stage, loop, bar=self.bar, callback=self.callback, save=self.save,
                         every=self.opts.checkpoint.every)
            self.bar.finish(loop.reason if loop.done else "iteration limit")
        # Ctrl-C during the health check or the identifiability report (JVPs through the rollout,
        # not short): the loop has finished, so save it; --resume goes straight to this step
        with saving_on_interrupt(lambda: self.save(loop, "interrupted")):
            result = _finish(self.prob, loop, self.settings, self.notes, self.opts.identifiability,
                             time.perf_counter() - t_start + wall_before)
        result = dataclasses.replace(result, timing=clock.stop())
        if self.opts.checkpoint.path is not None:
            from jaxplush.fitting import io as _io
            _io.save_fit(result, self.opts.checkpoint.path)
        return result

    def initial_loop(self):
        """The :class:`LoopState` to start from: the checkpoint's (resume), or the stage's start."""
        if self.opts.checkpoint.resume:
            from jaxplush.fitting import io as _io
            from jaxplush.fitting.io.treeio import conform

            def check(loop):      # this optimiser's state, with its dtypes and array kinds
                template = jax.jit(self.opt.init)(jnp.asarray(loop.theta))
                if not isinstance(loop, LoopState):
                    raise TypeError(f"the checkpoint holds a {type(loop).__name__}, not a gradient fit's LoopState")
                return dataclasses.replace(loop, opt_state=conform(loop.opt_state, template))
            return _io.load_checkpoint(self.opts.checkpoint.path, self.prob, self.settings, conform=check)
        return self.stage.init(self, self.prob.theta0)

    def warn_dt(self, loop):
        """Warn (and note) when dt exceeds the estimated stability limit at the loop's point."""
        prob = self.prob
        if not self.opts.check_dt:
            return
        est = jaxplush.estimate_stable_dt(prob.sim, prob.sim.params(prob.params_at(loop.theta)))
        if est is not None and prob.target.dt > est.dt_max:
            msg = (f"dt = {prob.target.dt:g} s exceeds the estimated stability limit {est.dt_max:.3g} s at the "
                   "start values; expect rejected steps")
            warnings.warn(msg, TimeStepWarning, stacklevel=_LOOP_STACKLEVEL["warn_dt"])
            self.notes.append(msg)

    def save(self, state, status="running"):
        if self.opts.checkpoint.path is not None:
            from jaxplush.fitting import io as _io
            _io.save_checkpoint(self.opts.checkpoint.path, self.prob, state, self.settings, status=status,
                                theta=state.best_theta, history=_loop_history(self.prob, state),
                                loss=float(state.best_loss), iterations=int(state.iteration),
                                rejected=int(state.rejected))

    def grow_contact(self, theta):
        """The stage's hook after a failed evaluation at theta: if soft-soft contact candidates overflowed there (its
        loss is NaN: :func:`jaxplush.fitting.objective.gradients.rollout_loss`), rebuild the problem with a capacity
        that fits (warning) and return True."""
        prob = self.prob
        if prob.sim.terms.contact is None:
            return False
        from jaxplush.model import contact
        from jaxplush.stepping.simulation import contact_capacity_needed
        # the loss's own check (a fresh search at every step) decides whether it was an overflow
        _, codes = prob.frames(theta)
        if not (np.asarray(codes) == diagnostics.CONTACT_OVERFLOW).any():
            return False
        old = max(prob.sim.terms.contact.capacity)
        need = contact_capacity_needed(prob.scene, int(prob.loss.frame_steps[-1]), prob.target.dt,
                                       params=prob.params_at(theta), sim=prob.sim)
        if need is None:
            # simulate's carried candidate lists (rebuilt at other steps) did not overflow where
            # the fresh search of every step did: grow past the current capacity all the same
            need = contact.grown_capacity(old + 1)
        terms = contact.with_capacity(prob.sim.terms, need, contact.object_sizes(prob.scene))
        sim = jaxplush.make_simulator(prob.scene, prob.target.dt, terms=terms)
        self.prob = prob = dataclasses.replace(prob, sim=sim)
        msg = (f"contact candidates overflowed (capacity {old}) at {_values_text(prob.values(theta))}; "
               f"refitting with contact_capacity {need} (set it in the scene to skip this)")
        self.notes.append(warn(msg, ContactCapacityWarning, stacklevel=_LOOP_STACKLEVEL["grow_contact"]))
        self.bar.update(0, extra=f"contact capacity raised to {need}; recompiling")
        return True


def _progress_text(loss, vals):
    return f"loss {loss:.4g} " + _values_text(vals)


def _values_text(vals):
    return " ".join(("k" if n == "k_structural" else n) + " " + ",".join(f"{x:.4g}" for x in np.atleast_1d(v))
                    for n, v in vals.items())


_LINESEARCH_STATES = (optax.ScaleByZoomLinesearchState, optax.ScaleByBacktrackingLinesearchState)


def _linesearch_states(state):
    """The line-search states (optax's zoom and backtracking line searches) inside an optimiser state."""
    nodes = jax.tree_util.tree_leaves(state, is_leaf=lambda s: isinstance(s, _LINESEARCH_STATES))
    return [s for s in nodes if isinstance(s, _LINESEARCH_STATES)]


def uses_linesearch(state):
    """Whether an optax state (or its ``jax.eval_shape``) holds a line search, as L-BFGS's does:
    such an optimiser chooses its own step, which the loop then never rescales."""
    return bool(_linesearch_states(state))


def _make_step(prob, opt, linesearch):
    """The jitted update: (theta, opt_state) -> (loss, grad, updates, new_opt_state) at theta.

    A line search that stores the loss and gradient at its accepted point (L-BFGS's zoom line
    search) has them read back from its state (``optax.value_and_grad_from_state``) rather than
    recomputed. A ``GradientTransformationExtraArgs`` gets ``value``, ``grad`` and ``value_fn``
    with the update (transformations that need none ignore them)."""
    loss_fn = prob.loss_fn
    extra = isinstance(opt, optax.GradientTransformationExtraArgs)
    from_state = linesearch and all(s.grad is not None for s in _linesearch_states(
        jax.eval_shape(opt.init, jax.ShapeDtypeStruct(np.shape(prob.theta0), prob.sim.dtype))))
    vg = optax.value_and_grad_from_state(loss_fn) if from_state else jax.value_and_grad(loss_fn)

    def step(theta, state):
        loss, g = vg(theta, state=state) if from_state else vg(theta)
        if extra:
            updates, new_state = opt.update(g, state, theta, value=loss, grad=g, value_fn=loss_fn)
        else:
            updates, new_state = opt.update(g, state, theta)
        return loss, g, updates, new_state
    return jax.jit(step)


def _iterate(prob, opt, linesearch, step_fn, loop, opts):
    """One evaluation at loop.theta: accept and step, or reject and halve the step."""
    dtype = prob.sim.dtype
    t0 = time.perf_counter()
    theta = jnp.asarray(loop.theta, dtype)
    ok = prob.valid(loop.theta)
    if ok:
        loss, g, updates, new_state = step_fn(theta, loop.opt_state)
        loss = float(loss)
        g = np.asarray(g)
        ok = math.isfinite(loss) and bool(np.all(np.isfinite(g)))
    it = loop.iteration
    loop.iteration += 1
    if not ok:
        _reject(prob, opt, linesearch, loop, it)
        return
    loop.rejected_in_row = 0
    gnorm = float(np.max(np.abs(g)))
    prev = loop.h_loss[-1] if loop.h_loss else None
    loop.h_iter.append(it)
    loop.h_loss.append(loss)
    loop.h_theta.append(np.asarray(loop.theta, np.float64))
    loop.h_gnorm.append(gnorm)
    loop.h_time.append(loop.wall + time.perf_counter() - t0)
    if loss < loop.best_loss:
        loop.best_loss, loop.best_theta = loss, np.asarray(loop.theta)
    # a line search (L-BFGS's) already chose the step (and stored the loss there): never rescale it
    step = np.asarray(updates) if linesearch else loop.scale * np.asarray(updates)
    _check_convergence(loop, loss, prev, gnorm, step, opts)
    if loop.done:
        return
    loop.anchor = np.asarray(loop.theta)
    loop.theta = (np.asarray(loop.theta, dtype) + step.astype(dtype)).astype(dtype)
    loop.opt_state = new_state


def _reject(prob, opt, linesearch, loop, it):
    """A blown-up evaluation (iteration ``it``): halve the step back toward the last accepted point,
    or raise :class:`FitError` at the start or after too many rejections in a row."""
    loop.rejected += 1
    loop.rejected_in_row += 1
    loop.h_rejected.append(it)
    if loop.anchor is None:
        raise FitError("the rollout blows up (non-finite loss or gradient, or an object turned inside out) "
                       "at the start values; start closer to a stable setting or use a smaller dt")
    if loop.rejected_in_row > MAX_REJECTIONS:
        raise FitError(f"{loop.rejected_in_row} steps in a row blew up the rollout; the last good values were "
                       + _progress_text(loop.best_loss, prob.values(loop.anchor)))
    loop.scale *= 0.5
    loop.theta = loop.anchor + 0.5 * (loop.theta - loop.anchor)
    if linesearch:  # its memory holds the rejected pair: start it afresh there
        loop.opt_state = jax.jit(opt.init)(jnp.asarray(loop.theta, prob.sim.dtype))


def _check_convergence(loop, loss, prev, gnorm, step, opts):
    """Set ``loop.done``, its reason and its :class:`Stop` when an accepted point meets a criterion of ``opts``."""
    rtol, patience = opts.rtol, int(opts.patience)
    if prev is not None and abs(prev - loss) <= rtol * max(abs(loss), 1e-300):
        loop.stall += 1
    else:
        loop.stall = 0
    if loss <= opts.ftol:
        loop.done, loop.stopped, loop.reason = True, Stop.LOSS, f"converged: loss {loss:.3g} <= ftol {opts.ftol:g}"
    elif gnorm <= opts.gtol:
        loop.done, loop.stopped = True, Stop.GRADIENT
        loop.reason = f"converged: gradient max-norm {gnorm:.3g} <= gtol {opts.gtol:g}"
    elif loop.stall >= patience:
        loop.done, loop.stopped = True, Stop.LOSS
        loop.reason = f"converged: relative loss change <= rtol {rtol:g} for {patience} iterations"
    elif float(np.max(np.abs(step))) <= opts.xtol:
        loop.done, loop.stopped = True, Stop.STEP
        loop.reason = f"converged: step {float(np.max(np.abs(step))):.3g} <= xtol {opts.xtol:g} (log space)"


def _finish(prob, loop, settings, notes, want_ident, wall):
    """Health check, identifiability and the :class:`FitResult` at the best accepted point."""
    best = loop.best_theta if loop.h_loss else np.asarray(prob.theta0)
    th = jnp.asarray(best, prob.sim.dtype)
    if want_ident:
        frames, codes, jac = _ident.frames_and_jacobian(prob.frames, th)
    else:
        frames, codes = jax.jit(prob.frames)(th)
        frames, codes = np.asarray(frames, np.float64), np.asarray(codes)
    notes = list(notes)
    bad = diagnostics.first_failure(codes)
    if bad is not None:
        t, o, c = bad
        raise FitError(f"the fitted rollout fails at step {prob.loss.frame_steps[t]}, object "
                       f"{prob.scene.object_names[o]!r}: {diagnostics.MESSAGES[c]}")
    if (codes == diagnostics.VOLUME_CLAMPED).any():
        t, o = (int(a[0]) for a in np.nonzero(codes == diagnostics.VOLUME_CLAMPED))
        msg = (f"object {prob.scene.object_names[o]!r}: {diagnostics.MESSAGES[diagnostics.VOLUME_CLAMPED]} "
               f"at step {prob.loss.frame_steps[t]} of the fitted rollout")
        warnings.warn(msg, VolumeClampWarning, stacklevel=4)
        notes.append(msg)
    report = _report(prob, frames, jac) if want_ident else None
    hist = _loop_history(prob, loop)
    out = _judge_loop(prob, loop)
    ivals, substeps = (None, 1) if report is None else _twin_intervals(prob, best, report)
    out = limited_by_rounding(out, ivals)
    combos = _intervals.combinations(prob, best, ivals, substeps=substeps)
    return _result(prob, best, frames=frames, history=hist, outcome=out, report=report, warn_report=True,
                   notes=notes, settings=settings, loop=loop, wall=wall, stacklevel=4,
                   loss=float(loop.best_loss if loop.h_loss else np.nan),
                   loss_start=float(loop.h_loss[0]) if loop.h_loss else float("nan"),
                   iterations=loop.iteration, rejected=loop.rejected,
                   reason=f"{out.text} (the optimiser stopped: {loop.reason})", lr=settings["lr"], intervals=ivals,
                   combinations=combos)


def _twin_intervals(prob, theta, report):
    """(:class:`jaxplush.fitting.judge.intervals.Intervals`, substeps) at a gradient fit's best point
    ``theta``, as the default fit's judge makes them: from twins of the fitted values on the
    batched engine (:func:`jaxplush.fitting.judge.intervals.twins`), each propagated by a central
    difference Jacobian there (the default search box, centred on theta, holds its stencil). Where twins do
    not apply, from the exact Jacobian's ``report`` (the residuals treated as independent noise),
    with the reason in the note."""
    from jaxplush.fitting.objective import shooting as _shooting
    from jaxplush.fitting.options import LocalOptions
    from jaxplush.fitting.stages import lmfit
    from jaxplush.fitting.stages import search as _search
    theta = np.asarray(theta, np.float64)
    ev = _shooting.evaluator(prob)
    if _intervals.applies(prob, ev) is not None:
        return _intervals.twins(prob, ev, theta, None, report), 1
    centre = ev(theta[None])
    if not centre.ok[0]:
        return _intervals.from_report(report, theta, note="from the residuals at the optimum, treated as "
                                      "independent noise: the batched engine's run of the fitted values failed"), 1
    n_sub = int(centre.substeps[0])
    local = LocalOptions()
    jac = _search.jacobian(ev, lmfit.default_box(prob, centre=theta), theta, local.h_min, n_sub, local,
                           separation=_search._separation(centre, 0))
    return _intervals.twins(prob, ev, theta, jac, report, residual=centre.residuals[0]), n_sub


def _loop_history(prob, loop):
    """The :attr:`FitResult.history` of a gradient loop (:class:`LoopState`)."""
    return _history(prob, loop.h_theta, iteration=np.asarray(loop.h_iter, np.int64),
                    loss=np.asarray(loop.h_loss, np.float64), grad_norm=np.asarray(loop.h_gnorm, np.float64),
                    time=np.asarray(loop.h_time, np.float64), rejected=np.asarray(loop.h_rejected, np.int64))


def _judge_loop(prob, loop):
    """The outcome of an Adam or L-BFGS loop: residual at the best point, exact gradients."""
    from jaxplush.fitting.judge import outcome as _outcome
    if not loop.h_loss:
        return _outcome.judge(rms=np.inf, noise=prob.noise, motion=_motion(prob), grad=np.inf, grad0=1.0,
                              stopped=Stop.ITERATIONS)
    best = int(np.argmin(loop.h_loss))
    return _judge(prob, loop.h_theta[best], rms=_losses.rms_metres(loop.h_loss[best], prob.loss.scale2,
                                                                   prob.target.kind),
                  noise=prob.noise, motion=_motion(prob), grad=loop.h_gnorm[best], grad0=loop.h_gnorm[0],
                  stopped=loop.stopped)
