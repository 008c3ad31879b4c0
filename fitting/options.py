"""The options of :func:`fitting.fit`: one small frozen object instead of a long list of keywords.

    opts = FitOptions(iterations=60, noise_free=True,
                      search=SearchOptions(samples=32, starts=3),
                      checkpoint=CheckpointOptions(path="FIT.h5", every=5))
    fit(scene, target, options=opts)
    fit(scene, target, options=opts, iterations=80)      # a keyword overrides one option

Keywords given to ``fit`` beyond its own are :meth:`FitOptions.replace` changes: a field of
:class:`FitOptions`, or a field of one of its groups under a flat name (``bounds``,
``samples``, ``starts``, ``seed`` of :class:`SearchOptions`; ``checkpoint_path``,
``checkpoint_every``, ``resume`` of :class:`CheckpointOptions`; the default fit's tuning knobs
of :class:`LocalOptions`, :class:`ContinuationOptions` and :class:`SmoothingOptions` by their
field names, or the names :data:`SHORTCUTS` lists where a field's name alone would be
ambiguous, e.g. ``local_xtol``, ``continuation_iterations``, ``smooth_points``). Anything else
is an error that names the keyword and lists the valid ones.

The tuning knobs have the defaults the default fit was tuned with (benchmarks/RESULTS.md);
changing one changes the fit's result, so a checkpoint records them and a resume with others
is refused.

This module imports no jax: the command line builds its options before choosing the dtype.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import numbers

from jaxplush.errors import JaxplushError


#: The default fit's global design and local starts when :class:`SearchOptions` leaves them None.
DEFAULT_SAMPLES = 64
DEFAULT_STARTS = 5
#: Iteration limits when ``FitOptions.iterations`` is None: Levenberg-Marquardt iterations per
#: search and stage (the default fit), and iterations of the gradient optimisers.
DEFAULT_ITERATIONS = {"lm": 40, "gradient": 200}


@dataclasses.dataclass(frozen=True)
class SearchOptions:
    """The default fit's global stage (``optimizer="lm"`` only).

    Attributes:
      bounds: the search box {name: (lo, hi)} in parameter units (every fitted object), or
        "name=lo:hi,..." text; default each fitted parameter from start/4 to start*4. Refused
        with the other optimisers.
      samples: Sobol points of the global stage (default :data:`DEFAULT_SAMPLES`, 64).
      starts: local Levenberg-Marquardt starts from its best candidates (default
        :data:`DEFAULT_STARTS`, 5).
      seed: the Sobol scrambling seed.
      retries: a design point that blows up at the substeps its stability limit predicts is run
        again with twice as many at most this many times (``global_retries``; None: up to
        :data:`jaxplush.fitting.objective.evaluate.MAX_SUBSTEPS`, as a local search's points are). The
        design does not need every point, and each further substep count is one more compiled
        simulator (5-20 s with soft-soft contact) for a point or two at the box's wild corners.
      linear: add the start that needs no start values to the design (``linear_start``): indirect
        inference on the equation-error estimate of the model's linear force balance
        (:mod:`jaxplush.fitting.stages.equation_error`), where the target is vertex positions and every
        fitted parameter enters the forces linearly (k, dashpot, nmol, drag, damping); a dozen
        rollouts or so. The design keeps whichever point fits best.
    """

    bounds: object = None
    samples: int | None = None
    starts: int | None = None
    seed: int = 0
    retries: int | None = dataclasses.field(default=1, metadata={"flat": "global_retries"})
    linear: bool = dataclasses.field(default=True, metadata={"flat": "linear_start"})

    @property
    def n_samples(self):
        """``samples``, or :data:`DEFAULT_SAMPLES`."""
        return int(DEFAULT_SAMPLES if self.samples is None else self.samples)

    @property
    def n_starts(self):
        """``starts``, or :data:`DEFAULT_STARTS`."""
        return int(DEFAULT_STARTS if self.starts is None else self.starts)


@dataclasses.dataclass(frozen=True)
class LocalOptions:
    """The default fit's local Levenberg-Marquardt searches (:func:`jaxplush.fitting.stages.search.lm_round`),
    their screening and their rescue (``optimizer="lm"`` only). Everything is in log space.

    Attributes:
      keep: searches kept after screening (of ``starts``).
      screen_rounds: iterations of the first stage after which all but the best ``keep`` are set aside.
      drop_factor: a search whose loss exceeds this many times the best one's is set aside.
      start_distance: the global stage's candidates that start searches lie at least this
        fraction of the box's widest side apart (max-norm).
      max_rescues: restarts from an axis scan (:func:`jaxplush.fitting.stages.search.rescue`) per search and stage.
      scan_points: points of an axis scan, in all (at least 4 per parameter).
      rescue_gain: a scan point must lower the loss by this fraction to restart a search there.
      h_min, h_max: smallest and largest central-difference step of the Jacobian (the step is
        the trust radius x ``h_fraction``, clipped to them).
      h_fraction: the central-difference step as a fraction of the trust radius.
      colour_misses: coloured Jacobian stencils (every object's parameter moved at once) that
        came near contact, and were run again in full, after which a fit stops trying them.
      radius0, mu0: trust radius and Levenberg-Marquardt damping of a fresh search (a step that
        does better than predicted doubles a smaller radius, up to ``radius0``).
      xtol: a search stops when an accepted step is at most this (max-norm), and stalls when the
        trust radius falls below it without one (flat name ``local_xtol``).
      ftol: ... or when the relative loss change of an accepted step is at most this (``local_ftol``).
      pred_tol: ... or when the Gauss-Newton model promises less than this fraction of the loss
        (at a noisy target's optimum the loss sits at the noise level), judged at step ``h_min``.
      noise_stop: ... or when the Gauss-Newton step is at most this fraction of every parameter's
        standard error (residual variance x (JᵀJ)⁻¹): further steps move the result by less than its noise;
      noise_stop_h: ... judged only with a difference step at most this small (a local Jacobian).
      resolve_h: the step of a second Jacobian at the optimum, taken when the search's own (at
        its last step, often ``h_min``) leaves a parameter combination within its rounding
        noise: the report then rests on this one (rounding weighs h / resolve_h as much), and
        only combinations that a step of this size cannot tell from rounding are undetermined.
      floor_step: a search on a noise-free position target stops once its residual RMS is at most
        the model's reproducibility floor over the fitted frames (two runs that differ only by
        rounding differ by as much) and its Gauss-Newton step is at most this (max-norm): no
        further step can be told from rounding (None: never; flat name ``local_floor_step``).
      jacobian: how a search's Jacobian is taken: "difference" (the default: central differences
        at a step that follows the trust radius, 2 P rollouts on the batched engine) or
        "forward" (exact, by forward-mode JVPs: one rollout with P tangents, at each new point
        only). Forward mode serves where the residuals are smooth; multiple shooting, points that
        need substeps and runs that blow up take differences instead. Measured in
        benchmarks/RESULTS.md ("Exact Jacobians").
      secant_updates: iterations a search may take on a Jacobian updated from its own steps (a
        Broyden secant update, r(x + s) - r(x) = J s, after each accepted step) before it is
        differenced again (2 P rollouts); a stop judged on the Jacobian, or a step that fails, on
        an updated Jacobian differences it first. 0 (the default): every iteration differences.
      trial_mu: the Levenberg-Marquardt dampings tried at each iteration (one batch), as factors
        of the search's damping mu; the best of them is the step.
      ratio_good, ratio_poor: the step's actual over predicted loss decrease above which mu is
        multiplied by ``mu_good`` (and the radius may grow by ``radius_grow``), below which by
        ``mu_poor`` (and the radius shrinks to half the step); in between mu is kept.
      mu_good, mu_poor: those factors.
      mu_fail, radius_fail: after an iteration where no trial lowers the loss, mu is multiplied
        by ``mu_fail`` and the trust radius becomes ``radius_fail`` x the failed step.
      radius_grow: a step that did better than predicted grows the radius by this factor (up to
        ``radius0``).
    """

    keep: int = 2
    screen_rounds: int = 3
    drop_factor: float = 30.0
    start_distance: float = 0.1
    max_rescues: int = 2
    scan_points: int = 30
    rescue_gain: float = 1e-3
    h_min: float = 1e-3
    h_max: float = 0.05
    radius0: float = 0.5
    mu0: float = 1e-3
    xtol: float = dataclasses.field(default=1e-4, metadata={"flat": "local_xtol"})
    ftol: float = dataclasses.field(default=1e-7, metadata={"flat": "local_ftol"})
    pred_tol: float = 1e-4
    noise_stop: float = 0.1
    noise_stop_h: float = 0.02
    resolve_h: float = 0.01
    floor_step: float | None = dataclasses.field(default=1e-3, metadata={"flat": "local_floor_step"})
    secant_updates: int = 0
    jacobian: str = "difference"
    h_fraction: float = 0.25
    colour_misses: int = 2
    trial_mu: tuple = (0.1, 1.0, 10.0)
    ratio_good: float = 0.75
    ratio_poor: float = 0.25
    mu_good: float = 1 / 3
    mu_poor: float = 2.0
    mu_fail: float = 10.0
    radius_fail: float = 0.25
    radius_grow: float = 2.0


@dataclasses.dataclass(frozen=True)
class ContinuationOptions:
    """The default fit's continuation in time (:mod:`jaxplush.fitting.stages.lmfit`): stages over the
    target's first frames, each starting from the previous stage's best points (``optimizer="lm"`` only).

    Attributes:
      horizons: the stages' horizons as fractions of the target's frames, increasing (the last
        is always all of them).
      min_frames: targets with fewer frames are fitted in one stage (``min_frames_for_stages``).
      iterations: iterations per search in a stage before the last (and, for a noisy target, in
        the last, which the smoothing stage resolves): those stages only carry the searches on
        toward the full target's optimum (``continuation_iterations``).
      noise_stop: ... and there a search stops once its Gauss-Newton step is within this many
        standard errors: a shorter horizon's optimum lies about that far from the full target's
        anyway (``continuation_noise_stop``).
      carry_factor: a search whose loss ended above this many times the best one's does not go
        on to the next stage.
      same_point: searches that ended within this distance (max-norm, log space) continue as one.
      next_radius: the trust radius (log space) with which a later stage starts.
    """

    horizons: tuple = (0.25, 0.5, 1.0)
    min_frames: int = dataclasses.field(default=8, metadata={"flat": "min_frames_for_stages"})
    iterations: int = dataclasses.field(default=8, metadata={"flat": "continuation_iterations"})
    noise_stop: float = dataclasses.field(default=1.0, metadata={"flat": "continuation_noise_stop"})
    carry_factor: float = 3.0
    same_point: float = 0.02
    next_radius: float = 0.05


@dataclasses.dataclass(frozen=True)
class SmoothingOptions:
    """The default fit's smoothing stage for a noisy target (:func:`jaxplush.fitting.stages.search.smooth`):
    Gauss-Newton on a regression model of the residuals over Sobol designs (``optimizer="lm"`` only).

    Attributes:
      points: design points per iteration (plus the centre: one batch) (``smooth_points``).
      width: the design's half-width, in standard errors (``smooth_width``).
      iterations: designs at most (``smooth_iterations``).
      stop: it stops once the smoothed Gauss-Newton step is within this many standard errors (``smooth_stop``).
      sigma: (lo, hi) bounds on a standard error used to size the design, log space (``smooth_sigma``).
      grow: while the model's step reaches past the design, the next design (and the step it may
        take) is twice as wide, up to this factor; it is back to 1 once a step stays inside, or
        when the regression's smoothed loss at the new centre is above the last one's (``smooth_grow``).
    """

    points: int = dataclasses.field(default=31, metadata={"flat": "smooth_points"})
    width: float = dataclasses.field(default=6.0, metadata={"flat": "smooth_width"})
    iterations: int = dataclasses.field(default=10, metadata={"flat": "smooth_iterations"})
    stop: float = dataclasses.field(default=1.0, metadata={"flat": "smooth_stop"})
    sigma: tuple = dataclasses.field(default=(1e-4, 0.05), metadata={"flat": "smooth_sigma"})
    grow: float = dataclasses.field(default=8.0, metadata={"flat": "smooth_grow"})


#: The fewest frames a segment of multiple shooting can have: its node's next frame refines the
#: node's velocity, the rest fit.
MIN_SEGMENT = 2


@dataclasses.dataclass(frozen=True)
class ShootingOptions:
    """The default fit's multiple shooting (:mod:`jaxplush.fitting.objective.shooting`; ``optimizer="lm"``
    only). Whether it shoots at all is ``FitOptions.shooting``.

    Attributes:
      refine: Gauss-Newton refinements of the node velocities against their next frame, per
        evaluation (``shooting_refine``; 0: central differences of the frames alone).
      min_segment: the fewest frames per segment the plan chooses (at least :data:`MIN_SEGMENT`).
      min_horizon_frames: the fewest frames a point-cloud or tracks fit keeps when it is cut at
        the predictable horizon.
      resolution_step: the central-difference step (log space) of the Jacobians that compare
        how well one rollout and segments resolve the parameters, and of the bias estimate on a
        twin target: wide enough to see past the rough plateau of a sensitive motion's loss.
      max_bias: the largest bias (log space, any parameter) taken off the fitted values; beyond
        it the linear estimate is not trusted.
    """

    refine: int = dataclasses.field(default=1, metadata={"flat": "shooting_refine"})
    min_segment: int = MIN_SEGMENT
    min_horizon_frames: int = 4
    resolution_step: float = 0.02
    max_bias: float = 0.2


@dataclasses.dataclass(frozen=True)
class CheckpointOptions:
    """Checkpoints: FIT.h5 written atomically every ``every`` iterations, on Ctrl-C and at the end.

    Attributes:
      path: the FIT.h5 to checkpoint into (None: no checkpoints).
      every: iterations between checkpoints (Adam, L-BFGS, optax; the default fit saves after
        every local iteration).
      resume: continue the interrupted fit saved in ``path`` (it must be the same fit).
    """

    path: object = None
    every: int = 10
    resume: bool = False


@dataclasses.dataclass(frozen=True)
class FitOptions:
    """Options of :func:`fitting.fit` (every one has a default).

    Attributes:
      iterations: maximum iterations (None: 40 Levenberg-Marquardt iterations per start for the
        default fit, 200 for the gradient optimisers, each an evaluation of loss and gradient).
      lr: learning rate in log space for ``"adam"`` (default 0.05) or ``"lbfgs"`` (default: its
        line search); an optax transformation carries its own.
      dt: time step (default: the target's).
      start: start values {name: value, (O,) array or {object: value}} overriding the scene's.
      noise: measurement noise sigma per coordinate (m) for the normalisation and the report
        (default: the target's ``noise`` attribute, if any).
      noise_free: the target is exact (normalise by its motion; ignore any noise value).
      track_weight: a mixed target's (a scan with tracked points) weight w of its tracks against
        its scan, L = (L_points + w L_tracks) / (1 + w) (default None: the target's, 1; docs/fitting.md).
      gtol, rtol, xtol, ftol, patience: when a gradient optimiser stops (max-norm of the
        gradient; relative loss change for ``patience`` accepted iterations; max-norm of the
        log-space step; the loss itself).
      method: gradient method of :func:`jaxplush.fitting.objective.gradients.rollout_loss`.
      force: allow fitting ``total_weight`` jointly with k/dashpot/nmol.
      identifiability: compute the identifiability report at the optimum.
      check_dt: warn when dt exceeds the estimated stability limit at the start values
        (gradient optimisers; the default fit substeps such points instead).
      predictability: measure the predictability of the start values over the target before
        fitting (:func:`jaxplush.predictability`, two or three rollouts), reported in the result
        and FIT.h5; its reproducibility floor lets the outcome say ``at_floor``.
      shooting: how the default fit runs a position target (:mod:`jaxplush.fitting.objective.shooting`):
        "auto" (multiple shooting where the measured horizon is shorter than the target and
        shooting measures better than one rollout), "off" (one rollout over the target), or the
        frames per segment (an int >= 2).
      polish: "off" (default) or "float64": after the default fit, its local stages again from
        its best point on the problem rebuilt in float64 (no global design, no smoothing), whose
        result is judged (outcome, identifiability, the intervals' Jacobian) in float64, its
        twins run in float32 (:func:`jaxplush.fitting.fitter._polish`). Where
        the motion amplifies rounding, the float32 loss is rough at the scale of the drift and a
        fit can stop short of the optimum within it (benchmarks/RESULTS.md, 2026-11-30: 6.8% and
        1.5% off in float32, 1.06% and 0.23% after float64). It costs a float64 compile and
        about 1.4-2x the float32 search's time per iteration. Nothing to do in a float64 fit.
      search: :class:`SearchOptions` of the default fit's global stage.
      local: :class:`LocalOptions` of its local searches; continuation: :class:`ContinuationOptions`
        of its stages in time; smoothing: :class:`SmoothingOptions` of its smoothing stage;
        multiple_shooting: :class:`ShootingOptions` of its segments.
      checkpoint: :class:`CheckpointOptions`.
    """

    iterations: int | None = None
    lr: float | None = None
    dt: float | None = None
    start: dict | None = None
    noise: float | None = None
    noise_free: bool = False
    track_weight: float | None = None
    gtol: float = 1e-9
    rtol: float = 1e-7
    xtol: float = 1e-7
    ftol: float = 0.0
    patience: int = 5
    method: str = "auto"
    force: bool = False
    identifiability: bool = True
    check_dt: bool = True
    predictability: bool = True
    shooting: object = "auto"
    polish: str = "off"
    search: SearchOptions = dataclasses.field(default_factory=SearchOptions)
    local: LocalOptions = dataclasses.field(default_factory=LocalOptions)
    continuation: ContinuationOptions = dataclasses.field(default_factory=ContinuationOptions)
    smoothing: SmoothingOptions = dataclasses.field(default_factory=SmoothingOptions)
    multiple_shooting: ShootingOptions = dataclasses.field(default_factory=ShootingOptions)
    checkpoint: CheckpointOptions = dataclasses.field(default_factory=CheckpointOptions)

    def replace(self, **changes):
        """A copy with ``changes``: fields of this class, or of its groups by their flat names
        (:data:`SHORTCUTS`); an unknown name raises :class:`JaxplushError` listing the valid ones."""
        own = {f.name for f in dataclasses.fields(self)}
        for key in changes:
            if key not in own and key not in SHORTCUTS:
                raise JaxplushError(_unknown_message(key))
        out = dataclasses.replace(self, **{k: v for k, v in changes.items() if k in own})
        groups = {}
        for key, val in changes.items():
            if key in SHORTCUTS:
                group, name = SHORTCUTS[key]
                groups.setdefault(group, {})[name] = val
        for group, kw in groups.items():
            out = dataclasses.replace(out, **{group: dataclasses.replace(getattr(out, group), **kw)})
        return out

    def iteration_limit(self, kind):
        """``iterations``, or the default of optimiser ``kind`` ("lm", else a gradient
        optimiser; :data:`DEFAULT_ITERATIONS`)."""
        if self.iterations is not None:
            return int(self.iterations)
        return DEFAULT_ITERATIONS["lm" if kind == "lm" else "gradient"]


#: The groups of the default fit's tuning knobs: FitOptions field -> class.
TUNING = {"local": LocalOptions, "continuation": ContinuationOptions, "smoothing": SmoothingOptions,
          "multiple_shooting": ShootingOptions}


def _tuning_shortcuts():
    """Flat keyword -> (group, field) of every tuning knob (its field name, or its ``flat`` name)."""
    return {f.metadata.get("flat", f.name): (group, f.name)
            for group, cls in TUNING.items() for f in dataclasses.fields(cls)}


#: Flat keyword -> (group, field) for the fields of FitOptions' groups.
SHORTCUTS = {"bounds": ("search", "bounds"), "samples": ("search", "samples"), "starts": ("search", "starts"),
             "seed": ("search", "seed"), "global_retries": ("search", "retries"), "linear_start": ("search", "linear"),
             "checkpoint_path": ("checkpoint", "path"),
             "checkpoint_every": ("checkpoint", "every"), "resume": ("checkpoint", "resume"),
             **_tuning_shortcuts()}


def option_names():
    """Every keyword :meth:`FitOptions.replace` (and so ``fit``) accepts."""
    return tuple(f.name for f in dataclasses.fields(FitOptions)) + tuple(SHORTCUTS)


def _unknown_message(key):
    near = difflib.get_close_matches(key, option_names(), n=1)
    hint = f" (did you mean {near[0]!r}?)" if near else ""
    return (f"fit: unknown option {key!r}{hint}; valid options: {', '.join(option_names())} "
            "(or options=FitOptions(...))")


def resolve(options, overrides):
    """The :class:`FitOptions` of a call: ``options`` (None: the defaults) with ``overrides``."""
    if options is None:
        options = FitOptions()
    elif not isinstance(options, FitOptions):
        raise JaxplushError(f"options must be a fitting.FitOptions, got {type(options).__name__}")
    return options.replace(**overrides) if overrides else options


def validate(opts, optimizer):
    """Check ``opts`` for ``optimizer`` ("lm", "adam", "lbfgs" or "optax") before anything is
    built or traced; raises :class:`JaxplushError` with the first problem."""
    if not isinstance(opts.search, SearchOptions):
        raise JaxplushError(f"search must be a fitting.SearchOptions, got {type(opts.search).__name__}")
    if not isinstance(opts.checkpoint, CheckpointOptions):
        raise JaxplushError(f"checkpoint must be a fitting.CheckpointOptions, got {type(opts.checkpoint).__name__}")
    _validate_tuning(opts, optimizer)
    if opts.iterations is not None and (not _is_whole(opts.iterations) or int(opts.iterations) < 1):
        raise JaxplushError(f"iterations must be >= 1, got {opts.iterations}")
    s = opts.search
    for name, val in (("samples", s.samples), ("starts", s.starts)):
        if val is not None and (not _is_whole(val) or int(val) < (0 if name == "samples" else 1)):
            raise JaxplushError(f"{name} must be an integer >= {0 if name == 'samples' else 1}, got {val!r}")
    if s.retries is not None and (not _is_whole(s.retries) or int(s.retries) < 0):
        raise JaxplushError(f"global_retries must be None or an integer >= 0, got {s.retries!r}")
    if not isinstance(s.linear, bool):
        raise JaxplushError(f"linear_start must be True or False, got {s.linear!r}")
    c = opts.checkpoint
    if c.every is not None and (not _is_whole(c.every) or int(c.every) < 1):
        raise JaxplushError(f"checkpoint_every must be >= 1, got {c.every}")
    if c.resume and c.path is None:
        raise JaxplushError("resume needs a checkpoint_path (the FIT.h5 of the interrupted fit)")
    if optimizer != "lm" and s.bounds is not None:
        raise JaxplushError(f"bounds apply to the default fit (optimizer 'lm'), not to {optimizer}")
    if opts.lr is not None:
        if optimizer == "optax":
            raise JaxplushError("lr applies to optimizer 'adam' or 'lbfgs'; an optax transformation carries "
                                "its own learning rate")
        if optimizer != "lm" and not (isinstance(opts.lr, numbers.Real) and math.isfinite(opts.lr) and opts.lr > 0):
            raise JaxplushError(f"learning rate must be > 0, got {opts.lr!r}")
    for name in ("gtol", "rtol", "xtol", "ftol"):
        val = getattr(opts, name)
        if not (isinstance(val, numbers.Real) and val >= 0):
            raise JaxplushError(f"{name} must be a number >= 0, got {val!r}")
    if opts.track_weight is not None and not _is_positive(opts.track_weight):
        raise JaxplushError(f"track_weight must be a number > 0, got {opts.track_weight!r}")
    if opts.predictability not in (True, False):
        raise JaxplushError(f"predictability must be True or False, got {opts.predictability!r}")
    if opts.shooting not in ("auto", "off") and not (_is_whole(opts.shooting) and int(opts.shooting) >= 2):
        raise JaxplushError(f"shooting must be 'auto', 'off' or frames per segment (an integer >= 2), "
                            f"got {opts.shooting!r}")
    if opts.polish not in POLISHES:
        raise JaxplushError(f"polish must be one of {', '.join(map(repr, POLISHES))}, got {opts.polish!r}")
    if optimizer != "lm" and opts.polish != "off":
        raise JaxplushError(f"polish is part of the default fit (optimizer 'lm'), not of {optimizer}")
    if optimizer != "lm" and opts.shooting not in ("auto", "off"):
        raise JaxplushError(f"multiple shooting is part of the default fit (optimizer 'lm'), not of {optimizer}")
    if not _is_whole(opts.patience) or opts.patience < 1:
        raise JaxplushError(f"patience must be an integer >= 1, got {opts.patience!r}")


#: What the default fit may polish its result in (:attr:`FitOptions.polish`).
POLISHES = ("off", "float64")

#: How a search may take its Jacobian (:attr:`LocalOptions.jacobian`).
JACOBIANS = ("difference", "forward")


def _validate_tuning(opts, optimizer):
    """The tuning groups: of their classes, every number valid, and left alone unless ``optimizer`` is "lm"."""
    for group, cls in TUNING.items():
        val = getattr(opts, group)
        if not isinstance(val, cls):
            raise JaxplushError(f"{group} must be a fitting.{cls.__name__}, got {type(val).__name__}")
        if optimizer != "lm" and val != cls():
            raise JaxplushError(f"{group} options apply to the default fit (optimizer 'lm'), not to {optimizer}")
        for f in dataclasses.fields(cls):
            name, v = f.metadata.get("flat", f.name), getattr(val, f.name)
            if isinstance(f.default, str):
                if v not in JACOBIANS:
                    raise JaxplushError(f"{name} must be one of {', '.join(JACOBIANS)}, got {v!r}")
            elif isinstance(f.default, tuple):
                ok = (isinstance(v, (tuple, list)) and len(v) > 0 and all(_is_positive(x) for x in v)
                      and all(a < b for a, b in zip(v, v[1:])))
                if ok and group == "continuation":
                    ok = v[-1] <= 1.0
                if not ok or (group == "smoothing" and len(v) != 2):
                    raise JaxplushError(f"{name} must be increasing positive numbers, got {v!r}")
            elif isinstance(f.default, int):
                low = {"max_rescues": 0, "secant_updates": 0, "colour_misses": 0, "shooting_refine": 0,
                       "min_segment": MIN_SEGMENT}.get(name, 1)
                if not _is_whole(v) or v < low:
                    raise JaxplushError(f"{name} must be a whole number >= {low}, got {v!r}")
            elif v is None and _optional(f):
                continue
            elif not (_is_positive(v) or (v == 0 and name in ("local_xtol", "local_ftol", "pred_tol", "noise_stop",
                                                             "continuation_noise_stop", "rescue_gain"))):
                raise JaxplushError(f"{name} must be a number > 0{' or None' if _optional(f) else ''}, got {v!r}")
    lo = opts.local
    for what, ok in ((f"ratio_poor ({lo.ratio_poor!r}) < ratio_good ({lo.ratio_good!r}) < 1",
                      lo.ratio_poor < lo.ratio_good < 1),
                     (f"mu_good ({lo.mu_good!r}) < 1", lo.mu_good < 1), (f"mu_poor ({lo.mu_poor!r}) >= 1", lo.mu_poor >= 1),
                     (f"mu_fail ({lo.mu_fail!r}) > 1", lo.mu_fail > 1),
                     (f"radius_fail ({lo.radius_fail!r}) < 1", lo.radius_fail < 1),
                     (f"radius_grow ({lo.radius_grow!r}) > 1", lo.radius_grow > 1),
                     (f"h_fraction ({lo.h_fraction!r}) <= 1", lo.h_fraction <= 1)):
        if not ok:
            raise JaxplushError(f"local options: need {what}")


def _optional(field):
    """Whether a tuning field may be None (its annotation says ``| None``)."""
    return "None" in str(field.type)


def _is_positive(v):
    """A finite number > 0 (not a bool)."""
    return isinstance(v, numbers.Real) and not isinstance(v, bool) and math.isfinite(v) and v > 0


def _is_whole(v):
    """A whole number (40 or 40.0; not True, not "40")."""
    return isinstance(v, numbers.Real) and not isinstance(v, bool) and math.isfinite(v) and int(v) == v
