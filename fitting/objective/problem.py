"""A fit's problem, built and validated before anything is traced.

:func:`build_problem` checks a fit's inputs (the parameter names, :data:`ALIASES` accepted; the
objects; start values; the target against the scene; the gradient method) and returns a
:class:`Problem`: the scene with its start values, the target without its initial frame, the
simulator, the loss, and the log start values theta0 of the fitted parameters. Also the
parameters a scene switches on (:func:`default_params`), the search bounds of the default fit
(:func:`parse_bounds`) and the settings every fit records for a resume to check.
"""

from __future__ import annotations

import dataclasses
import math
import warnings

import jax.numpy as jnp
import numpy as np

import jaxplush
from jaxplush.model import contact
from jaxplush.model import forces as model
from jaxplush.errors import JaxplushError, TrajectoryError
from jaxplush.fitting.errors import ParameterWarning
from jaxplush.types import PARAM_NAMES, Params

from jaxplush.fitting.judge import identifiability as _ident
from jaxplush.fitting.objective import losses as _losses
from jaxplush.fitting.targets import Target, load_target, scene_with_controls


#: Accepted spellings of parameter names.
ALIASES = {"k": "k_structural", "stiffness": "k_structural", "mass": "total_weight", "weight": "total_weight"}


#: Parameters that scale with the mass under the exact symmetry of docs/model.md §9.1.
_MASS_CONFOUNDED = ("k_structural", "dashpot", "nmol")


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
    warnings.warn(msg, ParameterWarning, stacklevel=3)


@dataclasses.dataclass(frozen=True, eq=False)
class Problem:
    """Everything the loop needs, built and validated before any tracing.

    Attributes:
      scene, target, sim: what is fitted, to what, with which simulator.
      names: fitted parameter names (P_n,); objects: fitted object indices (O_f,).
      base: :class:`Params` (numpy float64) holding the start values (fitted) and fixed values.
      theta0: (P_n, O_f) float64 log start values.
      loss: :class:`jaxplush.fitting.objective.losses.Loss`.
      method: gradient method of :func:`jaxplush.fitting.objective.gradients.rollout_loss`.
      noise: the noise sigma of the normalisation (m), or None.
      predictability: :class:`jaxplush.Predictability` of the start values over the target
        (:func:`measure_predictability`), or None (not measured, or the start run blew up).
      shooting: :class:`jaxplush.fitting.objective.shooting.Shooting` of the default fit, or None (single shooting).
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
    shooting: object = None

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
        from jaxplush.fitting.objective.gradients import rollout_loss
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
        the same noise setting), for the default fit's continuation in time; on more of them where
        a part of the target (tracks, or a mixed target's scan or tracks) observes nothing in those
        (its loss would have no normalisation): up to the first frame where each observes something."""
        n_frames = max([int(n_frames)] + [int(np.argmax(p.observed.any(axis=1))) + 1 for p in self.target.parts])
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


#: Said before a fit of both the report's damping and air drag (they are one effect).
DAMPING_DRAG_NOTE = ("damping and drag are fitted together, but in this model both decay every vertex's velocity "
                     "uniformly (the report's damping D takes 1/D of it off per step, as a drag of rate 1/(D dt)), "
                     "so a target determines only their combined rate: the fit will report that rate with its "
                     "interval and end 'undetermined' for the split; fit one of them (--params) to measure it")


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
                  start=None, noise=None, noise_free=False, method="auto", force=False, track_weight=None):
    """Validate a fit's inputs and build its :class:`Problem` (see :func:`fit` for the arguments).

    ``params`` None fits :func:`default_params` (the note saying which is warned). A target with
    controls (:class:`jaxplush.fitting.targets.Controls`) drives its vertices in the fitted scene
    (:func:`jaxplush.fitting.targets.scene_with_controls`). ``track_weight``: a mixed target's
    weight of its tracks against its scan (default: the target's, 1)."""
    if params is None:
        params, note = default_params(scene, _default_param_objects(scene, objects))
        warnings.warn(note, ParameterWarning, stacklevel=3)
    names = canonical_names(params)
    check_mass_fit(names, force)
    objs = _fit_objects(scene, objects)
    base = _start_values(scene, start, objs)
    _check_start_values(scene, names, objs, base)
    if "damping" in names and "drag" in names:
        warnings.warn(DAMPING_DRAG_NOTE, ParameterWarning, stacklevel=3)
    target = _fit_target(scene, target, dt, track_weight)
    scene = scene_with_controls(scene, target)
    fit_scene = scene.replace(params=Params(**base))
    if noise is not None and not (np.isfinite(noise) and noise >= 0):
        raise JaxplushError(f"noise must be a number >= 0, got {noise!r}")
    if not noise_free:
        if noise is not None:
            check_noise(noise, scene, "noise")
        elif target.noise is not None:
            check_noise(target.noise, scene, "attribute 'noise'", path=target.path)
    sim = _fit_simulator(scene, fit_scene, target, method)
    loss = _losses.make_loss(target, sim.topology, sim.dtype, noise=noise, noise_free=noise_free,
                             check_volume=sim.terms.gas)
    theta0 = np.log(np.stack([base[n][list(objs)] for n in names]))
    sigma = None if noise_free else (target.noise if noise is None else float(noise))
    return Problem(scene=fit_scene, target=target, sim=sim, names=names, objects=objs,
                   base=Params(**base), theta0=theta0, loss=loss, method=method, noise=sigma)


#: A measurement noise sigma must lie within these multiples of the scene's size (the diagonal of
#: its rest bounding box): below, no measurement is that exact and sigma² underflows; above, the
#: target carries no information about the shape (and sigma² overflows).
NOISE_RANGE = (1e-9, 1e3)


def check_noise(sigma, scene, what="noise", path=None):
    """Refuse a noise sigma (m) > 0 outside :data:`NOISE_RANGE` times the scene's size: a
    :class:`jaxplush.errors.JaxplushError` naming ``what`` (the option or attribute; with ``path``
    a :class:`jaxplush.errors.TrajectoryError` of that file). 0 (noise-free) passes."""
    sigma = float(sigma)
    if sigma == 0:
        return
    size = float(np.linalg.norm(np.ptp(np.asarray(scene.vertices, np.float64), axis=0)))
    lo, hi = NOISE_RANGE[0] * size, NOISE_RANGE[1] * size
    if lo <= sigma <= hi:
        return
    why = (f"below {NOISE_RANGE[0]:g} of the scene's size ({size:.3g} m): no measurement is that exact; for an "
           "exact target use noise-free (--noise-free)" if sigma < lo else
           f"more than {NOISE_RANGE[1]:g} times the scene's size ({size:.3g} m): such a target says nothing "
           "about the shape")
    msg = f"{what} {sigma:g} m is {why}"
    raise TrajectoryError(path, msg) if path is not None else JaxplushError(msg)


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


def _fit_target(scene, target, dt, track_weight=None):
    """The target (loaded from a path, or put on the ``dt`` grid; a mixed target with its
    ``track_weight`` when given) checked against the scene, without its initial frames (t = 0 does
    not depend on the parameters)."""
    if not isinstance(target, Target):
        target = load_target(target, scene, dt)
    elif dt is not None:
        target = target.on_grid(dt)
    if track_weight is not None:
        if not target.kind.compound:
            raise JaxplushError(f"{target.path}: a track weight weighs a mixed target's tracks against its scan; "
                                f"this target is {target.kind} alone")
        w = track_weight
        if isinstance(w, bool) or not isinstance(w, (int, float, np.floating, np.integer)) or not (
                np.isfinite(w) and w > 0):
            raise JaxplushError(f"the track weight must be a finite number > 0, got {track_weight!r}")
        target = dataclasses.replace(target, track_weight=float(w))
    if target.kind.every_vertex and target.positions.shape[1] != scene.n_vertices:
        raise JaxplushError(f"{target.path}: target has {target.positions.shape[1]} vertices, the scene "
                            f"{scene.n_vertices}")
    if target.tracks is not None:
        _check_tracks(scene, target)
    keep = target.steps > 0
    if not keep.any():
        raise JaxplushError(f"{target.path}: the target holds only the initial frame (t = 0), which does not "
                            "depend on the parameters")
    for part in target.parts:
        if not part.observed[keep].any():
            what = f"'{part.kind}' observe" if target.kind.compound else "the target observes"
            raise JaxplushError(f"{target.path}: {what} nothing after the initial frame (t = 0)")
    return target.select(keep)


def _check_tracks(scene, target):
    """A tracks target's correspondence ((M, 3) vertices and weights) fits the scene (numpy)."""
    m = target.tracks.shape[1]
    tv, tw = target.track_vertices, target.track_weights
    if tv is None or tw is None or np.shape(tv) != (m, 3) or np.shape(tw) != (m, 3):
        raise JaxplushError(f"{target.path}: a tracks target needs track_vertices and track_weights of shape "
                            f"[{m}, 3], got {np.shape(tv) if tv is not None else None} and "
                            f"{np.shape(tw) if tw is not None else None}")
    tv = np.asarray(tv)
    if tv.min() < 0 or tv.max() >= scene.n_vertices:
        raise JaxplushError(f"{target.path}: track_vertices index vertices outside the scene's "
                            f"0..{scene.n_vertices - 1}")


def _fit_simulator(scene, fit_scene, target, method):
    """The simulator of the fit (the terms ``fit_scene`` switches on), the gradient ``method`` checked."""
    from jaxplush.fitting.objective.gradients import METHODS, adjoint_supported
    if method not in METHODS:
        raise JaxplushError(f"unknown gradient method {method!r}; expected one of {', '.join(METHODS)}")
    # soft-soft contact with headroom: the fit's parameters squash objects into each other far more
    # than the scene's own values (each growth on overflow costs a rerun and compiles)
    terms = contact.with_headroom(model.Terms.for_scene(fit_scene), contact.object_sizes(fit_scene))
    sim = jaxplush.make_simulator(fit_scene, target.dt, terms=terms)
    if method == "adjoint" and not adjoint_supported(sim):
        raise JaxplushError(f"gradient method 'adjoint' does not support this scene ({scene.path}: integrator "
                            f"{sim.integrator!r}, terms {', '.join(sim.terms.names())}); use auto or checkpoint")
    return sim


def _common_settings(prob, opts, kind, iterations, lr):
    """The settings every fit records (and a resume must match; :mod:`jaxplush.fitting.io`)."""
    return dict(optimizer=kind, lr=lr, iterations=int(iterations), names=list(prob.names),
                objects=[prob.scene.object_names[o] for o in prob.objects], dt=prob.target.dt,
                noise_free=bool(opts.noise_free), noise=-1.0 if prob.noise is None else float(prob.noise),
                method=opts.method)


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
