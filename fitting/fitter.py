"""Fit material parameters of a scene to a target.

``fit(scene, target, params=None, objects=None, *, optimizer="lm", options=None, callback=None,
progress=False, **overrides)``, its options a :class:`jaxplush.fitting.options.FitOptions` (keywords
override single fields: ``fit(scene, target, iterations=40)``):

* the fitted variables are theta = log(p) for the chosen parameters of the chosen objects
  (positivity for free); every other parameter stays at the scene's value. ``params=None``
  fits what the scene switches on (:func:`default_params`);
* the loss is :func:`jaxplush.fitting.losses.make_loss` over the target's frames (noise- or
  motion-normalised; positions or point-to-surface distances);
* the default optimiser, ``"lm"``, is global then local (:mod:`jaxplush.fitting.lmfit`,
  :mod:`jaxplush.fitting.search`): a Sobol design over a box around the start run through the batched
  simulator, then Levenberg-Marquardt with central-difference Jacobians from the best
  candidates, over horizons of growing length, every evaluated point stable (substeps where
  needed, :mod:`jaxplush.fitting.evaluate`);
* ``"adam"``, ``"lbfgs"`` and any optax transformation the caller passes descend the gradient
  through the rollout (:func:`jaxplush.fitting.gradients.rollout_loss`) in one loop: a step whose
  rollout blows up (non-finite loss or gradient, an inverted object, damping < 1) is rejected
  and the step halved; a start that blows up, or too many rejections in a row, raise
  :class:`FitError`; they stop at ``iterations`` or at ``gtol``/``rtol``/``xtol``/``ftol``;
* before fitting, the predictability of the start values over the target is measured
  (:func:`jaxplush.predictability`: two runs that differ only by rounding); its reproducibility
  floor is the residual no parameters can go below, which the outcome tells from a poor fit;
* every fit's outcome is judged by :mod:`jaxplush.fitting.outcome` ("converged" only at the noise level
  and an optimum), recorded in the result and FIT.h5 and warned about otherwise;
* checkpoints (``checkpoint_path``) hold the complete state, so ``resume=True`` continues an
  interrupted (Ctrl-C or killed) fit to the same answer; Ctrl-C saves before it exits;
* afterwards: the identifiability report (:mod:`jaxplush.fitting.identifiability`) and a health check of
  the fitted rollout.

The result is a :class:`FitResult`.
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
from jaxplush.stepping import diagnostics
from jaxplush.model import forces as model
from jaxplush.errors import JaxplushError
from jaxplush.progress import Progress
from jaxplush.types import PARAM_NAMES, Params

from jaxplush.fitting import identifiability as _ident
from jaxplush.fitting import losses as _losses
from jaxplush.fitting import options as _options
from jaxplush.fitting.errors import FitError  # noqa: F401  (jaxplush.fitting.fitter.FitError)
from jaxplush.fitting.outcome import Status, Stop
from jaxplush.fitting.options import CheckpointOptions, FitOptions, SearchOptions  # noqa: F401  (jaxplush.fitting.fitter.FitOptions)
from jaxplush.fitting.targets import Target, load_target

#: Accepted spellings of parameter names.
ALIASES = {"k": "k_structural", "stiffness": "k_structural", "mass": "total_weight", "weight": "total_weight"}
#: Parameters that scale with the mass under the exact symmetry of docs/model.md §9.1.
_MASS_CONFOUNDED = ("k_structural", "dashpot", "nmol")
OPTIMIZERS = ("lm", "adam", "lbfgs")
#: Default learning rates (log space) per optimiser (L-BFGS: none, the line search sets the step).
DEFAULT_LR = {"adam": 0.05, "lbfgs": None, "lm": None}
MAX_REJECTIONS = 30


def canonical_names(names):
    """Parameter names (strings or one comma-separated string) -> canonical tuple; validated."""
    if isinstance(names, str):
        names = [n for n in names.split(",") if n.strip()]   # "k,damping," and " k, nmol" as meant
    out = []
    for n in names:
        n = str(n).strip()
        c = ALIASES.get(n, n)
        if c not in PARAM_NAMES:
            raise JaxplushError(f"unknown parameter {n!r}; fittable: {', '.join(PARAM_NAMES)} (k = k_structural)")
        if c in out:
            raise JaxplushError(f"parameter {c!r} given twice")
        out.append(c)
    if not out:
        raise JaxplushError("no parameters to fit")
    return tuple(out)


def check_mass_fit(names, force=False):
    """docs/model.md §9.1: mass is set by the same symmetry as k, c and nRT. Warn; refuse jointly."""
    if "total_weight" not in names:
        return
    others = [n for n in names if n in _MASS_CONFOUNDED]
    msg = ("fitting total_weight: with gravity, scaling (k_structural, dashpot, nmol, total_weight) together "
           "leaves every trajectory unchanged (docs/model.md §9.1); mass must be measured, not fitted")
    if others and not force:
        raise JaxplushError(f"refusing to fit total_weight jointly with {', '.join(others)}: {msg}. "
                            "Fix the mass, or force it (force=True / --force)")
    warnings.warn(msg, stacklevel=3)


@dataclasses.dataclass(frozen=True, eq=False)
class Problem:
    """Everything the loop needs, built and validated before any tracing.

    Attributes:
      scene, target, sim: what is fitted, to what, with which simulator.
      names: fitted parameter names (P_n,); objects: fitted object indices (O_f,).
      base: :class:`Params` (numpy float64) holding the start values (fitted) and fixed values.
      theta0: (P_n, O_f) float64 log start values.
      loss: :class:`jaxplush.fitting.losses.Loss`.
      method: gradient method of :func:`jaxplush.fitting.gradients.rollout_loss`.
      noise: the noise sigma of the normalisation (m), or None.
      predictability: :class:`jaxplush.Predictability` of the start values over the target
        (:func:`measure_predictability`), or None (not measured, or the start run blew up).
    """

    scene: object
    target: Target
    sim: object
    names: tuple
    objects: tuple
    base: Params
    theta0: np.ndarray
    loss: _losses.Loss
    method: str
    noise: float | None
    predictability: object = None

    @property
    def labels(self):
        names = self.scene.object_names
        return tuple(f"{n}[{names[o]}]" for n in self.names for o in self.objects)

    def to_params(self, theta):
        """(P_n, O_f) log values -> full :class:`Params` (jnp, the simulator's dtype)."""
        dtype = self.sim.dtype
        vals = {n: jnp.asarray(np.asarray(getattr(self.base, n)), dtype) for n in PARAM_NAMES}
        idx = np.asarray(self.objects)
        for i, n in enumerate(self.names):
            vals[n] = vals[n].at[idx].set(jnp.exp(theta[i]).astype(dtype))
        return Params(**vals)

    def loss_fn(self, theta):
        """Normalised loss at log values theta (jax; differentiable)."""
        from jaxplush.fitting.gradients import rollout_loss
        p = self.to_params(theta)
        lo = self.loss
        return rollout_loss(self.sim, p, self.sim.init_fn(p), lo.frame_steps, lo.loss_fn, lo.aux,
                            method=self.method)

    @property
    def start(self):
        """dict name -> (O_f,) exact start values (float64)."""
        return {n: np.array(getattr(self.base, n), np.float64)[list(self.objects)] for n in self.names}

    def params_at(self, theta):
        """Full :class:`Params` of numpy float64 arrays at log values theta (nothing traced)."""
        vals = {n: np.array(getattr(self.base, n), np.float64) for n in PARAM_NAMES}
        for n, v in self.values(theta).items():
            vals[n][list(self.objects)] = v
        return Params(**vals)

    def values(self, theta):
        """dict name -> (O_f,) float64 values at theta."""
        th = np.asarray(theta, np.float64)
        return {n: np.exp(th[i]) for i, n in enumerate(self.names)}

    def valid(self, theta):
        """Whether theta is an admissible point (finite; the Verlet damping D >= 1)."""
        th = np.asarray(theta, np.float64)
        if not np.all(np.isfinite(th)):
            return False
        if "damping" in self.names and np.any(np.exp(th[self.names.index("damping")]) < 1.0):
            return False
        return True

    def truncated(self, n_frames):
        """This problem on the target's first ``n_frames`` frames only (its own loss normalisation;
        the same noise setting), for the default fit's continuation in time."""
        if n_frames >= self.target.n_frames:
            return self
        target = self.target.select(np.arange(int(n_frames)))
        loss = _losses.make_loss(target, self.sim.topology, self.sim.dtype, noise=self.noise,
                                 noise_free=self.noise is None or self.noise == 0, check_volume=self.sim.terms.gas)
        return dataclasses.replace(self, target=target, loss=loss)

    def frames(self, theta):
        """(T, V, 3) simulated positions at the target's steps and (T, O) health codes (jax)."""
        p = self.to_params(theta)
        return _ident.frames_at_steps(self.sim, p, self.sim.init_fn(p), self.loss.frame_steps)


def default_params(scene, objects=None):
    """The material parameters a scene switches on, to fit by default: ``k_structural``; the
    damping it uses (``damping``, ``dashpot`` and/or ``drag``, whichever is above 0 on a fitted
    object); ``nmol`` where every fitted object has gas. Returns (names, note)."""
    objs = range(scene.n_objects) if objects is None else objects
    names = ["k_structural"]
    p = scene.params
    for n in ("damping", "dashpot", "drag"):
        if any(float(getattr(p, n)[o]) > 0 for o in objs):
            names.append(n)
    gas = [scene.objects[o].has_gas for o in objs]
    if all(gas):
        names.append("nmol")
    note = f"fitting {', '.join(names)} (the material parameters the scene switches on"
    if any(gas) and not all(gas):
        note += "; nmol left out: not every fitted object has gas"
    return tuple(names), note + ")"


def build_problem(scene, target, params=None, objects=None, *, dt=None,
                  start=None, noise=None, noise_free=False, method="auto", force=False):
    """Validate a fit's inputs and build its :class:`Problem` (see :func:`fit` for the arguments).

    ``params`` None fits :func:`default_params` (the note saying which is warned)."""
    if params is None:
        params, note = default_params(scene, _default_param_objects(scene, objects))
        warnings.warn(note, stacklevel=3)
    names = canonical_names(params)
    check_mass_fit(names, force)
    objs = _fit_objects(scene, objects)
    base = _start_values(scene, start, objs)
    _check_start_values(scene, names, objs, base)
    fit_scene = scene.replace(params=Params(**base))
    target = _fit_target(scene, target, dt)
    if noise is not None and not (np.isfinite(noise) and noise >= 0):
        raise JaxplushError(f"noise must be a number >= 0, got {noise!r}")
    sim = _fit_simulator(scene, fit_scene, target, method)
    loss = _losses.make_loss(target, sim.topology, sim.dtype, noise=noise, noise_free=noise_free,
                             check_volume=sim.terms.gas)
    theta0 = np.log(np.stack([base[n][list(objs)] for n in names]))
    sigma = None if noise_free else (target.noise if noise is None else float(noise))
    return Problem(scene=fit_scene, target=target, sim=sim, names=names, objects=objs,
                   base=Params(**base), theta0=theta0, loss=loss, method=method, noise=sigma)


def _default_param_objects(scene, objects):
    """The objects among ``objects`` (names or indices; bad ones left to :func:`_fit_objects` to
    report) whose switched-on parameters are fitted by default; None: every object."""
    if objects is None:
        return None
    items = [x.strip() for x in objects.split(",")] if isinstance(objects, str) else objects
    objs = [scene.object_names.index(o) if isinstance(o, str) and o in scene.object_names else o
            for o in items
            if (isinstance(o, str) and o in scene.object_names) or
            (isinstance(o, (int, np.integer)) and 0 <= o < scene.n_objects)]
    return objs or None


def _fit_objects(scene, objects):
    """Validated fitted object indices (tuple) from names, indices or "a,b" text; None: all."""
    if objects is None:
        return tuple(range(scene.n_objects))
    if isinstance(objects, str):
        objects = [o.strip() for o in objects.split(",") if o.strip()]
    objs = []
    for o in objects:
        if isinstance(o, (int, np.integer)) and not isinstance(o, bool):
            if not 0 <= o < scene.n_objects:
                raise JaxplushError(f"object index {o} out of range: the scene has {scene.n_objects} object(s)")
            i = int(o)
        elif o in scene.object_names:
            i = scene.object_names.index(o)
        else:
            raise JaxplushError(f"unknown object {o!r}; the scene's objects: {', '.join(scene.object_names)}")
        if i in objs:
            raise JaxplushError(f"object {scene.object_names[i]!r} given twice")
        objs.append(i)
    if not objs:
        raise JaxplushError("no objects to fit")
    return tuple(objs)


def _start_values(scene, start, objs):
    """dict name -> (O,) float64 values of every parameter: the scene's, overridden by ``start``
    {name: scalar or (O,) or {object: value}} (a scalar or array applies to the fitted objects)."""
    base = {n: np.array(getattr(scene.params, n), np.float64) for n in PARAM_NAMES}
    for key, val in (start or {}).items():
        n = canonical_names([key])[0]
        if isinstance(val, dict):
            for o, v in val.items():
                if isinstance(o, str) and o in scene.object_names:
                    i = scene.object_names.index(o)
                elif isinstance(o, (int, np.integer)) and not isinstance(o, bool) and 0 <= o < scene.n_objects:
                    i = int(o)
                else:
                    raise JaxplushError(f"start value of {n} for unknown object {o!r}; the scene's objects: "
                                        f"{', '.join(scene.object_names)}")
                base[n][i] = float(v)
        else:
            v = np.broadcast_to(np.asarray(val, np.float64), (scene.n_objects,))
            base[n][list(objs)] = v[list(objs)]
    return base


def _check_start_values(scene, names, objs, base):
    """Every fitted start value positive (log space), damping >= 1, nmol only where there is gas."""
    for n in names:
        for o in objs:
            v = base[n][o]
            oname = scene.object_names[o]
            if n == "nmol" and not scene.objects[o].has_gas:
                raise JaxplushError(f"cannot fit nmol of object {oname!r}: it has no gas (no 'nmol' line in "
                                    f"{scene.path})")
            if not (np.isfinite(v) and v > 0):
                hint = " (0 means off; give a start value >= 1)" if n == "damping" else ""
                raise JaxplushError(f"cannot fit {n} of object {oname!r}: its start value is {v:g}{hint}; "
                                    "fitting works in log space and needs a positive start value")
            if n == "damping" and v < 1:
                raise JaxplushError(f"cannot fit damping of object {oname!r}: start value {v:g} < 1 "
                                    "(the per-step factor 1/D must be <= 1)")


def _fit_target(scene, target, dt):
    """The target (loaded from a path, or put on the ``dt`` grid) checked against the scene, without
    its initial frames (t = 0 does not depend on the parameters)."""
    if not isinstance(target, Target):
        target = load_target(target, scene, dt)
    elif dt is not None:
        target = target.on_grid(dt)
    if target.kind == "positions" and target.positions.shape[1] != scene.n_vertices:
        raise JaxplushError(f"{target.path}: target has {target.positions.shape[1]} vertices, the scene "
                            f"{scene.n_vertices}")
    keep = target.steps > 0
    if not keep.any():
        raise JaxplushError(f"{target.path}: the target holds only the initial frame (t = 0), which does not "
                            "depend on the parameters")
    return target.select(keep)


def _fit_simulator(scene, fit_scene, target, method):
    """The simulator of the fit (the terms ``fit_scene`` switches on), the gradient ``method`` checked."""
    from jaxplush.fitting.gradients import METHODS, adjoint_supported
    if method not in METHODS:
        raise JaxplushError(f"unknown gradient method {method!r}; expected one of {', '.join(METHODS)}")
    sim = jaxplush.make_simulator(fit_scene, target.dt, terms=model.Terms.for_scene(fit_scene))
    if method == "adjoint" and not adjoint_supported(sim):
        raise JaxplushError(f"gradient method 'adjoint' does not support this scene ({scene.path}: integrator "
                            f"{sim.integrator!r}, terms {', '.join(sim.terms.names())}); use auto or checkpoint")
    return sim


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



@dataclasses.dataclass(frozen=True, eq=False)
class FitResult:
    """The outcome of :func:`fit`.

    Attributes:
      params: full :class:`jaxplush.types.Params` (numpy float64) with the fitted values.
      names: fitted parameter names; objects: fitted object names.
      values: dict name -> (O_f,) fitted values; start: dict name -> (O_f,) start values.
      loss: normalised loss at the fitted values (see :mod:`jaxplush.fitting.losses`); loss_start.
      history: dict of arrays over accepted iterations: "iteration", "loss", "grad_norm",
        "time" (s), each fitted name (n, O_f); and "rejected" (iterations whose step was rejected).
      iterations: evaluations done; rejected: steps rejected (blow-ups).
      converged: the fit reached the data at an optimum (``status == "converged"``).
      reason: how it ended, in words (:attr:`outcome`'s message).
      identifiability: :class:`jaxplush.fitting.identifiability.IdentifiabilityReport` (or None); its
        standard errors mean something only for a converged fit (:meth:`table` hides them otherwise).
      frames: (T, V, 3) simulated positions at the target frames with the fitted values.
      steps: (T,) their steps; dt.
      optimizer, lr, normalisation ("noise"/"motion"), scale2 (m²), noise.
      scene_text, scene_path, target_path, wall_time (s), warnings.
      predictability: :class:`jaxplush.Predictability` of the start values over the target,
        measured before fitting (None: not measured); the outcome's ``floor`` is the
        reproducibility floor it was judged against.
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
    loop: object = None     # the final LoopState / the default fit's RunState (for saving a resumable file)
    problem: object = None  # the Problem that was solved
    settings: dict = dataclasses.field(default_factory=dict)
    outcome: object = None  # jaxplush.fitting.outcome.Outcome
    search: dict = dataclasses.field(default_factory=dict)   # the default fit's samples and paths
    predictability: object = None  # jaxplush.Predictability of the start values

    @property
    def status(self):
        """The :class:`jaxplush.fitting.outcome.Status`: "converged", "poor_fit", "stalled", "iteration_limit",
        "at_bound" or "at_floor" (equal to those strings)."""
        if self.outcome is not None:
            return self.outcome.status
        return Status.CONVERGED if self.converged else Status.STALLED

    def table(self):
        """The fitted values as a text table: start, fitted value and, for a converged fit only,
        the approximate standard error; then the predictability and the outcome."""
        rep = self.identifiability
        se = {} if rep is None else dict(zip(rep.labels, rep.stderr))
        rows = [f"{'parameter':<14} {'object':<14} {'start':>12} {'fitted':>12} {'std. error':>11}"]
        for n in self.names:
            for j, o in enumerate(self.objects):
                e = se.get(f"{n}[{o}]", np.nan)
                if rep is None:
                    es = "-"
                elif not self.converged:
                    es = "n/a"
                else:
                    es = f"{100 * e:.2g}%" if np.isfinite(e) else "undetermined"
                rows.append(f"{n:<14} {o:<14} {self.start[n][j]:>12.6g} {self.values[n][j]:>12.6g} {es:>11}")
        rows.append(f"loss {self.loss_start:.4g} -> {self.loss:.4g} ({self.normalisation}-normalised) after "
                    f"{self.iterations} {'evaluations' if self.optimizer == 'lm' else 'iterations'} "
                    f"({self.rejected} rejected), {self.wall_time:.1f} s")
        if self.predictability is not None:
            rows.append(f"predictability: {self.predictability.text()}")
        rows.append(f"outcome: {self.reason}")
        if rep is not None and not self.converged:
            rows.append("standard errors: not meaningful, the fit did not converge to the data")
        return "\n".join(rows)

    def save(self, path):
        """Write FIT.h5 atomically (see :mod:`jaxplush.fitting.io`)."""
        from jaxplush.fitting import io as _io
        return _io.save_fit(self, path)

    def write_scene(self, path):
        """Write the scene with the fitted values (extended OBJ), ready to simulate."""
        from jaxplush.fitting import io as _io
        return _io.write_fitted_scene(self, path)


def fit(scene, target, params=None, objects=None, *, optimizer="lm", options=None, callback=None, progress=False,
        report=None, **overrides):
    """Fit parameters of ``scene`` to ``target``.

    The default (``optimizer="lm"``) is global, then local (:mod:`jaxplush.fitting.search`): a Sobol
    design over a box around the start (each parameter from start/4 to start*4 in log space,
    or ``bounds``), run in compiled batches with every point stable (substeps where a point's
    explicit limit is below dt), then Levenberg-Marquardt with finite-difference Jacobians from
    the best candidates, keeping the best. The outcome is judged honestly
    (:mod:`jaxplush.fitting.outcome`): ``converged`` only when the residual is at the noise level (or
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
    opts = _options.resolve(options, overrides)
    kind = optimizer_kind(optimizer)
    _options.validate(opts, kind)
    prob, notes = _problem(scene, target, params, objects, opts)
    if kind == "lm":
        return _fit_lm(prob, opts, notes, t_start, progress=progress, callback=callback, report=report)
    return _GradientFit(prob, optimizer, opts, notes, progress=progress, callback=callback,
                        report=report).run(t_start)


def optimizer_kind(optimizer):
    """"lm", "adam" or "lbfgs" for those names, "optax" for an ``optax.GradientTransformation``."""
    if isinstance(optimizer, str) and optimizer in OPTIMIZERS:
        return optimizer
    if isinstance(optimizer, optax.GradientTransformation):
        return "optax"
    raise JaxplushError(f"unknown optimizer {optimizer!r}; expected one of {', '.join(OPTIMIZERS)} or an "
                        "optax.GradientTransformation")


def _iterations(opts, kind):
    """The iteration limit: ``opts.iterations``, or the default for the optimiser."""
    return opts.iteration_limit(kind)


def _problem(scene, target, params, objects, opts):
    """:func:`build_problem` with ``opts``; its warnings are re-issued (for the caller of
    :func:`fit`) and returned as the fit's notes."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        prob = build_problem(scene, target, params, objects, dt=opts.dt, start=opts.start, noise=opts.noise,
                             noise_free=opts.noise_free, method=opts.method, force=opts.force)
    notes = [str(w.message) for w in caught]
    for msg in notes:
        warnings.warn(msg, stacklevel=3)
    return prob, notes


def _common_settings(prob, opts, kind, iterations, lr):
    """The settings every fit records (and a resume must match; :mod:`jaxplush.fitting.io`)."""
    return dict(optimizer=kind, lr=lr, iterations=int(iterations), names=list(prob.names),
                objects=[prob.scene.object_names[o] for o in prob.objects], dt=prob.target.dt,
                noise_free=bool(opts.noise_free), noise=-1.0 if prob.noise is None else float(prob.noise),
                method=opts.method)


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
    stopped: Stop = Stop.NONE    # ... and as a :class:`jaxplush.fitting.outcome.Stop`
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


#: Depth from :class:`_GradientFit`'s methods to the caller of :func:`fit`, for warnings.
_LOOP_STACKLEVEL = {"warn_dt": 4, "grow_contact_capacity": 6}


class _GradientFit:
    """The gradient optimisers' loop ("adam", "lbfgs" or a user's optax transformation) on
    log-parameters: a step whose rollout blows up is rejected and the step halved (:func:`_iterate`);
    a contact-candidate overflow grows the capacity and evaluates the point again; checkpoints,
    Ctrl-C saves, callbacks and the progress bar; then :func:`_finish`."""

    def __init__(self, prob, optimizer, opts, notes, *, progress, callback, report=None):
        self.kind = optimizer_kind(optimizer)
        self.iterations = _iterations(opts, self.kind)
        self.opt = optimizer if self.kind == "optax" else make_optimizer(self.kind, opts.lr, self.iterations)
        self.prob, self.opts, self.notes = prob, opts, notes
        self.progress, self.callback, self.note = progress, callback, report
        shape = jax.eval_shape(self.opt.init, jax.ShapeDtypeStruct(np.shape(prob.theta0), prob.sim.dtype))
        self.linesearch = uses_linesearch(shape)
        self.settings = _common_settings(prob, opts, self.kind, self.iterations, opts.lr)
        self.settings.update(gtol=opts.gtol, rtol=opts.rtol, xtol=opts.xtol, ftol=opts.ftol,
                             patience=int(opts.patience), frame_steps=list(prob.loss.frame_steps),
                             target_kind=prob.target.kind)
        if self.kind == "optax":     # what a resume can check of a user's transformation: its state's structure
            self.settings["optax_state"] = str(jax.tree_util.tree_structure(shape))
        self.step_fn = _make_step(prob, self.opt, self.linesearch)
        self.bar = None
        self.consistent = None      # the last loop state that is not half-way through an iteration

    def run(self, t_start):
        """The whole fit: the loop (from a checkpoint with ``resume``), its result, FIT.h5."""
        loop = self.initial_loop()
        if self.opts.predictability:        # every input checked (a resumed checkpoint too)
            self.prob = measure_predictability(self.prob, self.note)
        self.warn_dt(loop)
        wall_before = loop.wall
        self.bar = Progress(self.iterations, "fit", enabled=self.progress, unit="it")
        self.bar.done = min(loop.iteration, self.iterations)
        t_loop = time.perf_counter() - loop.wall
        loop = self.loop(loop, t_loop)
        if not loop.done:
            loop.reason, loop.stopped = f"reached the iteration limit ({self.iterations})", Stop.ITERATIONS
        loop.wall = time.perf_counter() - t_loop
        try:
            result = _finish(self.prob, loop, self.settings, self.notes, self.opts.identifiability,
                             time.perf_counter() - t_start + wall_before)
        except KeyboardInterrupt:
            # Ctrl-C during the health check or the identifiability report (JVPs through the rollout,
            # not short): the loop has finished, so save it; --resume goes straight to this step
            self.save(loop, "interrupted")
            raise
        if self.opts.checkpoint.path is not None:
            from jaxplush.fitting import io as _io
            _io.save_fit(result, self.opts.checkpoint.path)
        return result

    def initial_loop(self):
        """The :class:`LoopState` to start from: the checkpoint's (resume), or the start values."""
        if self.opts.checkpoint.resume:
            from jaxplush.fitting import io as _io
            from jaxplush.fitting.treeio import conform

            def check(loop):      # this optimiser's state, with its dtypes and array kinds
                template = jax.jit(self.opt.init)(jnp.asarray(loop.theta))
                if not isinstance(loop, LoopState):
                    raise TypeError(f"the checkpoint holds a {type(loop).__name__}, not a gradient fit's LoopState")
                return dataclasses.replace(loop, opt_state=conform(loop.opt_state, template))
            return _io.load_checkpoint(self.opts.checkpoint.path, self.prob, self.settings, conform=check)
        th0 = jnp.asarray(self.prob.theta0, self.prob.sim.dtype)
        loop = LoopState(theta=np.asarray(th0), opt_state=jax.jit(self.opt.init)(th0))
        loop.best_theta = np.asarray(th0)
        return loop

    def warn_dt(self, loop):
        """Warn (and note) when dt exceeds the estimated stability limit at the loop's point."""
        prob = self.prob
        if not self.opts.check_dt:
            return
        est = jaxplush.estimate_stable_dt(prob.sim, prob.sim.params(prob.params_at(loop.theta)))
        if est is not None and prob.target.dt > est.dt_max:
            msg = (f"dt = {prob.target.dt:g} s exceeds the estimated stability limit {est.dt_max:.3g} s at the "
                   "start values; expect rejected steps")
            warnings.warn(msg, stacklevel=_LOOP_STACKLEVEL["warn_dt"])
            self.notes.append(msg)

    def loop(self, loop, t_loop):
        """Iterate to the limit or a stop; Ctrl-C saves the last consistent state and re-raises."""
        last_saved = loop.iteration
        self.consistent = loop
        every = self.opts.checkpoint.every
        try:
            with self.bar:
                while not loop.done and loop.iteration < self.iterations:
                    loop, again = self.attempt(loop)
                    if again:
                        continue
                    loop.wall = time.perf_counter() - t_loop
                    self.report(loop)
                    if every and loop.iteration - last_saved >= int(every) and not loop.done:
                        self.save(loop)
                        last_saved = loop.iteration
                self.bar.finish(loop.reason if loop.done else "iteration limit")
        except KeyboardInterrupt:
            # Ctrl-C may land anywhere, also inside an iteration: save the last consistent state
            self.consistent.wall = time.perf_counter() - t_loop
            self.save(self.consistent, "interrupted")
            raise
        return loop

    def attempt(self, loop):
        """One :func:`_iterate`. Returns (the loop state to go on from, whether the point is to be
        evaluated again because the contact capacity was grown)."""
        before = loop.snapshot()
        self.consistent = before
        try:
            _iterate(self.prob, self.opt, self.linesearch, self.step_fn, loop, self.opts)
        except FitError:
            if not self.grow_contact_capacity(before.theta):
                raise
            return before, True             # evaluate the same point again, with room for contact
        if loop.h_rejected and loop.h_rejected[-1] == before.iteration \
                and self.grow_contact_capacity(before.theta):
            return before, True
        self.consistent = loop
        return loop, False

    def report(self, loop):
        """The progress bar and the callback after an iteration (a True return stops the fit)."""
        if loop.h_iter and loop.h_iter[-1] == loop.iteration - 1:
            vals = self.prob.values(loop.h_theta[-1])
            self.bar.update(1, extra=_progress_text(loop.h_loss[-1], vals))
            if self.callback is not None:
                stop = self.callback(dict(iteration=loop.iteration - 1, loss=loop.h_loss[-1], values=vals,
                                          grad_norm=loop.h_gnorm[-1]))
                if stop is True and not loop.done:
                    loop.done, loop.reason, loop.stopped = True, "stopped by the callback", Stop.CALLBACK
        else:
            self.bar.update(1, extra="step rejected (rollout blew up); halving the step")

    def save(self, state, status="running"):
        if self.opts.checkpoint.path is not None:
            from jaxplush.fitting import io as _io
            _io.save_checkpoint(self.opts.checkpoint.path, self.prob, state, self.settings, status=status,
                                theta=state.best_theta, history=_loop_history(self.prob, state),
                                loss=float(state.best_loss), iterations=int(state.iteration),
                                rejected=int(state.rejected))

    def grow_contact_capacity(self, theta):
        """After a failed evaluation at theta: if soft-soft contact candidates overflowed there (its
        loss is NaN: :func:`jaxplush.fitting.gradients.rollout_loss`), rebuild the problem with a capacity
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
        sim = jaxplush.make_simulator(prob.scene, prob.target.dt, terms=contact.with_capacity(prob.sim.terms, need))
        self.prob = prob = dataclasses.replace(prob, sim=sim)
        self.step_fn = _make_step(prob, self.opt, self.linesearch)
        msg = (f"contact candidates overflowed (capacity {old}) at {_values_text(prob.values(theta))}; "
               f"refitting with contact_capacity {need} (set it in the scene to skip this)")
        warnings.warn(msg, stacklevel=_LOOP_STACKLEVEL["grow_contact_capacity"])
        self.notes.append(msg)
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
        warnings.warn(msg, stacklevel=4)
        notes.append(msg)
    report = _report(prob, frames, jac) if want_ident else None
    hist = _loop_history(prob, loop)
    out = _judge_loop(prob, loop)
    return _result(prob, best, frames=frames, history=hist, outcome=out, report=report, warn_report=True,
                   notes=notes, settings=settings, loop=loop, wall=wall, stacklevel=4,
                   loss=float(loop.best_loss if loop.h_loss else np.nan),
                   loss_start=float(loop.h_loss[0]) if loop.h_loss else float("nan"),
                   iterations=loop.iteration, rejected=loop.rejected,
                   reason=f"{out.text} (the optimiser stopped: {loop.reason})", lr=settings["lr"])


def _loop_history(prob, loop):
    """The :attr:`FitResult.history` of a gradient loop (:class:`LoopState`)."""
    return _history(prob, loop.h_theta, iteration=np.asarray(loop.h_iter, np.int64),
                    loss=np.asarray(loop.h_loss, np.float64), grad_norm=np.asarray(loop.h_gnorm, np.float64),
                    time=np.asarray(loop.h_time, np.float64), rejected=np.asarray(loop.h_rejected, np.int64))


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
            warnings.warn(w, stacklevel=stacklevel + 1)
    if not outcome.converged:
        warnings.warn(outcome.text, stacklevel=stacklevel + 1)
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
    rest = _losses.rest_distance(prob.target, prob.sim.topology.x0, prob.sim.topology.faces)
    return float(np.sqrt(rest / _losses.COMPONENTS[kind]))


#: Most frames the predictability measurement saves per target frame (a target on an irregular
#: grid is measured on an even grid of about as many frames instead).
_PREDICTABILITY_FRAMES = 4


def _predictability_grid(target):
    """(steps, save_every) of the predictability measurement over a target: its last step, and
    the largest step that divides every frame's step (or, where that saves too many frames, an
    even grid with about as many frames as the target)."""
    steps = int(target.steps[-1])
    every = int(np.gcd.reduce(np.asarray(target.steps, np.int64)))
    if steps // every > _PREDICTABILITY_FRAMES * target.n_frames + 100:
        every = max(1, steps // target.n_frames)
    return steps, every


def _predictability_at(prob, theta=None):
    """:func:`jaxplush.predictability` of the problem's scene over its target at log values theta
    (default: the start values); None when a run blows up."""
    steps, every = _predictability_grid(prob.target)
    params = None if theta is None else prob.params_at(theta)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")   # a volume clamp or grown capacity: the fit reports its own
            return jaxplush.predictability(prob.scene, steps, prob.target.dt, every, params=params, sim=prob.sim,
                                           noise=prob.noise, motion=_motion(prob))
    except jaxplush.SimulationError:
        return None


def measure_predictability(prob, report=None):
    """The problem with :attr:`Problem.predictability` measured at the start values; ``report``
    (if given) gets the line that describes it."""
    pred = _predictability_at(prob)
    if report is not None:
        report("predictability: " + (pred.text() if pred is not None else
                                     "not measured (the rollout at the start values blows up)"))
    return dataclasses.replace(prob, predictability=pred)


def _judge(prob, theta, **kw):
    """:func:`jaxplush.fitting.outcome.judge` of a fit ending at log values theta, with the
    reproducibility floor of :attr:`Problem.predictability`; for a fit that does not reach the
    data the floor is measured again at theta (the start's may be far from the result's)."""
    from jaxplush.fitting import outcome as _outcome
    pred = prob.predictability
    start = (None, None) if pred is None else (pred.floor, pred.horizon_time)
    out = _outcome.judge(**kw, floor=start[0], horizon=start[1])
    if out.reached or pred is None:
        return out
    pred = _predictability_at(prob, theta) or pred
    return _outcome.judge(**kw, floor=pred.floor, horizon=pred.horizon_time)


def _judge_loop(prob, loop):
    """The outcome of an Adam or L-BFGS loop: residual at the best point, exact gradients."""
    from jaxplush.fitting import outcome as _outcome
    if not loop.h_loss:
        return _outcome.judge(rms=np.inf, noise=prob.noise, motion=_motion(prob), grad=np.inf, grad0=1.0,
                              stopped=Stop.ITERATIONS)
    best = int(np.argmin(loop.h_loss))
    return _judge(prob, loop.h_theta[best], rms=_losses.rms_metres(loop.h_loss[best], prob.loss.scale2,
                                                                   prob.target.kind),
                  noise=prob.noise, motion=_motion(prob), grad=loop.h_gnorm[best], grad0=loop.h_gnorm[0],
                  stopped=loop.stopped)


def parse_bounds(bounds, names):
    """Validated bounds {canonical name: (lo, hi)} from {name: (lo, hi)} or "name=lo:hi,..." text."""
    if bounds is None:
        return None
    if isinstance(bounds, str):
        items = {}
        for part in (p.strip() for p in bounds.split(",")):
            if not part:
                continue
            name, eq, rng = part.partition("=")
            lo, colon, hi = rng.partition(":")
            if not eq or not colon:
                raise JaxplushError(f"bounds: expected NAME=LO:HI, got {part!r}")
            try:
                items[name.strip()] = (float(lo), float(hi))
            except ValueError:
                raise JaxplushError(f"bounds: {part!r}: LO and HI must be numbers") from None
        bounds = items
    out = {}
    for key, val in bounds.items():
        n = canonical_names([key])[0]
        if n not in names:
            raise JaxplushError(f"bounds given for {n}, which is not fitted (fitted: {', '.join(names)})")
        try:
            lo, hi = (float(v) for v in val)
        except (TypeError, ValueError):
            raise JaxplushError(f"bounds of {n} must be two numbers (lo, hi), got {val!r}") from None
        if not (0 < lo < hi < math.inf):
            raise JaxplushError(f"bounds of {n} must satisfy 0 < lo < hi, got {lo:g}:{hi:g}")
        if n == "damping" and lo < 1:
            raise JaxplushError(f"bounds of damping must be >= 1 (the per-step factor 1/D <= 1), got {lo:g}")
        out[n] = (lo, hi)
    return out


def _lm_box(prob, bounds):
    from jaxplush.fitting import lmfit
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
    settings = _common_settings(prob, opts, "lm", _iterations(opts, "lm"), None)
    settings.update(frame_steps=list(prob.loss.frame_steps), target_kind=prob.target.kind,
                    box_lo=box.lo.ravel().tolist(), box_hi=box.hi.ravel().tolist(),
                    samples=s.n_samples, starts=s.n_starts, seed=int(s.seed))
    settings.update({group: dataclasses.asdict(getattr(opts, group)) for group in _options.TUNING})
    return settings


def _fit_lm(prob, opts, notes, t_start, *, progress, callback, report=None):
    """The default fit (jaxplush.fitting.lmfit.run) with checkpoints, Ctrl-C saves and the honest outcome."""
    from jaxplush.fitting import io as _io, lmfit
    box = _lm_box(prob, opts.search.bounds)
    settings = _lm_settings(prob, opts, box)
    checkpoint_path, want_ident = opts.checkpoint.path, opts.identifiability
    prior = _io.load_checkpoint(checkpoint_path, prob, settings, conform=_driver_state) \
        if opts.checkpoint.resume else None
    if opts.predictability:                 # every input checked (a resumed checkpoint too)
        prob = measure_predictability(prob, report)
    last = [prior]

    def write(state, status):
        best = lmfit.best_search(state)
        extra = {} if best is None else dict(theta=best.theta, loss=float(best.loss))
        _io.save_checkpoint(checkpoint_path, prob, state, settings, status,
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
    try:
        run, ev = lmfit.run(prob, box, opts, progress=progress, resume=prior, save=save, callback=user_cb)
    except KeyboardInterrupt:
        if last[0] is not None and checkpoint_path is not None:
            write(last[0], "interrupted")
        raise
    try:
        wall = time.perf_counter() - t_start + (prior.wall if prior is not None else 0.0)
        result = _finish_lm(prob, box, run, ev, settings, notes, want_ident, wall)
    except KeyboardInterrupt:
        if checkpoint_path is not None:
            write(lmfit.light_copy(run.state), "interrupted")
        raise
    if checkpoint_path is not None:
        _io.save_fit(result, checkpoint_path)
    return result


def _driver_state(state):
    """A default fit's checkpointed state, checked to be its driver's."""
    from jaxplush.fitting.stages import RunState
    if not isinstance(state, RunState):
        raise TypeError(f"the checkpoint holds a {type(state).__name__}, not the default fit's RunState")
    return state


def _finish_lm(prob, box, run, ev, settings, notes, want_ident, wall):
    """The :class:`FitResult` of a default fit: frames, health, outcome, identifiability."""
    from jaxplush.fitting import lmfit
    from jaxplush.fitting.search import gauss_newton
    notes = list(notes) + list(ev.notes)
    prob = dataclasses.replace(prob, sim=ev.prob.sim)       # with a grown contact capacity, if any
    best = run.best
    e = ev(best.theta[None], keep_frames=True)
    frames = e.frames[0]
    if e.clamped[0]:
        msg = f"{diagnostics.MESSAGES[diagnostics.VOLUME_CLAMPED]} in the fitted rollout"
        warnings.warn(msg, stacklevel=3)
        notes.append(msg)
    if int(e.substeps[0]) > 1:
        msg = (f"the fitted values run stably only with {int(e.substeps[0])} substeps at dt = {prob.target.dt:g} s "
               "(their explicit limit is below dt); simulate them with --substeps")
        warnings.warn(msg, stacklevel=3)
        notes.append(msg)
    kind = prob.target.kind
    scale2 = prob.loss.scale2
    rms = _losses.rms_metres(best.loss, scale2, kind)
    motion = _motion(prob)
    labels = prob.labels
    edge = box.at_bound(best.theta).ravel()
    lo_edge = (best.theta <= box.lo + 1e-6).ravel()
    at_bound = tuple(f"{labels[i]} at its {'lower' if lo_edge[i] else 'upper'} bound "
                     f"{math.exp((box.lo if lo_edge[i] else box.hi).ravel()[i]):.4g}" for i in np.nonzero(edge)[0])
    gn_step, stderr = gauss_newton(run.jac, run.residual)
    out = _judge(prob, best.theta, rms=rms, noise=prob.noise, motion=motion, grad=run.grad, grad0=run.grad0,
                 stopped=best.stopped, at_bound=at_bound, gn_step=gn_step, stderr=stderr)
    report = None
    if want_ident:
        factor = math.sqrt(prob.target.n_frames * prob.target.data.shape[1] * scale2)
        report = _ident.analyse(run.jac * factor, np.nan_to_num(run.residual) * factor, labels, noise=prob.noise)
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
    # the identifiability warnings only for a converged fit (whose standard errors mean something)
    return _result(prob, best.theta, frames=frames, history=hist, outcome=out, report=report,
                   warn_report=out.converged, notes=notes, settings=settings, loop=lmfit.light_copy(run.state),
                   wall=wall, stacklevel=3,
                   loss=float(best.loss), loss_start=float(run.loss0), iterations=int(run.evaluations),
                   rejected=int((~g.ok).sum()), reason=out.text, lr=None, search=search)


def identifiability_at(prob, theta):
    """The :class:`jaxplush.fitting.identifiability.IdentifiabilityReport` of a problem at log values theta."""
    frames, _, jac = _ident.frames_and_jacobian(prob.frames, jnp.asarray(theta, prob.sim.dtype))
    return _report(prob, frames, jac)


def _report(prob, frames, jac):
    if prob.target.kind == "positions":
        residual = frames - prob.target.positions
    else:
        residual = np.concatenate([_nearest_residual(x, p) for x, p in zip(frames, prob.target.points)])
    return _ident.analyse(jac, residual, prob.labels, noise=prob.noise)


def _nearest_residual(x, p):
    """(V, 3) vector from each vertex to its nearest target point (numpy, chunked)."""
    out = np.empty_like(x)
    for a in range(0, len(x), 512):
        d2 = ((x[a:a + 512, None, :] - p[None, :, :]) ** 2).sum(-1)
        out[a:a + 512] = x[a:a + 512] - p[np.argmin(d2, axis=1)]
    return out


# --------------------------------------------------------------------------- synthetic recovery

#: The recovery scenario's true parameters (docs/model.md §9.4: dynamics determine k, damping and
#: nmol): a soft pressurised ball hanging from one pinned top vertex, released undeformed; it
#: inflates, sags and rings on its pin, damped by the Verlet damping.
RECOVERY_TRUTH = dict(k_structural=50.0, damping=1000.0, inflation=1.05, total_weight=0.1, radius=0.1)


def recovery_scene_text(subdivisions=2, k_structural=50.0, damping=1000.0, nmol=None, *, inflation=1.05,
                        total_weight=0.1, radius=0.1, height=1.0):
    """Scene text of the recovery scenario: an icosphere ball (radius 0.1 m) pinned at its top.

    ``nmol`` defaults to the gas that inflates the free ball to ``inflation`` x its size
    (docs/model.md §8.5: n = k s (s - 1) sum L² / (3 R T)).
    """
    import trimesh
    from jaxplush.scene.write import format_scene
    from jaxplush.types import GAS_CONSTANT
    mesh = trimesh.creation.icosphere(subdivisions=int(subdivisions), radius=radius)
    v = np.asarray(mesh.vertices, np.float64)
    f = np.asarray(mesh.faces, np.int64)
    if nmol is None:
        e = mesh.edges_unique
        sum_l2 = float(np.sum((v[e[:, 0]] - v[e[:, 1]]) ** 2))
        nmol = k_structural * inflation * (inflation - 1) * sum_l2 / (3 * GAS_CONSTANT * 293.15)
    obj = dict(name="ball", vertices=v, faces=f, k_structural=float(k_structural), damping=float(damping),
               nmol=float(nmol), total_weight=float(total_weight), translate=(0.0, float(height), 0.0),
               fixed=[int(np.argmax(v[:, 1]))])
    return format_scene([obj], gravity=(0.0, -9.81, 0.0), temperature=293.15,
                        header=f"fitting recovery scenario: level-{int(subdivisions)} icosphere ball pinned at its top")


def synthetic_recovery(subdivisions=3, noise=0.0, point_cloud=False, progress=True, *, factors=(2.0, 0.5, 2.0),
                       optimizer="lbfgs", iterations=60, steps=1600, save_every=20, dt=5e-4, seed=0, n_points=None,
                       checkpoint_path=None):
    """Recover k_structural, damping and nmol from a synthetic target (the issue's acceptance run).

    A target is simulated with known parameters (:data:`RECOVERY_TRUTH`), optionally with
    Gaussian noise of ``noise`` m per coordinate or as a point cloud sampled on the surface;
    the fit starts from the truth times ``factors`` (k x2, damping x0.5, nmol x2 by default).

    Returns:
      dict: true, start and fitted values, relative errors, wall time of the fit (s), loss,
      iterations, the identifiability summary, and the :class:`FitResult` ("result").
    """
    truth = recovery_scene_text(subdivisions)
    scene_true = jaxplush.parse_scene(truth, "<recovery truth>")
    t0 = time.perf_counter()
    target = _make_recovery_target(scene_true, steps, dt, save_every, noise, point_cloud, n_points, seed)
    t_target = time.perf_counter() - t0
    true_vals = {n: float(getattr(scene_true.params, n)[0]) for n in ("k_structural", "damping", "nmol")}
    start_vals = {n: v * f for (n, v), f in zip(true_vals.items(), factors)}
    scene = jaxplush.parse_scene(recovery_scene_text(subdivisions, start_vals["k_structural"], start_vals["damping"],
                                                     start_vals["nmol"]), "<recovery start>")
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = fit(scene, target, ("k_structural", "damping", "nmol"), optimizer=optimizer, iterations=iterations,
                  noise_free=not noise, progress=progress, checkpoint_path=checkpoint_path, check_dt=False)
    wall = time.perf_counter() - t0
    fitted = {n: float(res.values[n][0]) for n in true_vals}
    errors = {n: fitted[n] / true_vals[n] - 1.0 for n in true_vals}
    return dict(vertices=scene.n_vertices, noise=noise, point_cloud=point_cloud, true=true_vals, start=start_vals,
                fitted=fitted, errors=errors, max_error=max(abs(e) for e in errors.values()), wall_time=wall,
                target_time=t_target, loss=res.loss, iterations=res.iterations, rejected=res.rejected,
                converged=res.converged, reason=res.reason, frames=target.n_frames, steps=steps, dt=dt,
                identifiability=res.identifiability.summary() if res.identifiability else "", result=res)


def _make_recovery_target(scene, steps, dt, save_every, noise, point_cloud, n_points, seed):
    from jaxplush.fitting.targets import make_target
    return make_target(scene, steps, dt, save_every, noise=noise, point_cloud=point_cloud,
                       n_points=n_points or (2 * scene.n_vertices if point_cloud else None), seed=seed)
