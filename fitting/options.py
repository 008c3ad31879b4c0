"""The options of :func:`fitting.fit`: one small frozen object instead of a long list of keywords.

    opts = FitOptions(iterations=60, noise_free=True,
                      search=SearchOptions(samples=32, starts=3),
                      checkpoint=CheckpointOptions(path="FIT.h5", every=5))
    fit(scene, target, options=opts)
    fit(scene, target, options=opts, iterations=80)      # a keyword overrides one option

Keywords given to ``fit`` beyond its own are :meth:`FitOptions.replace` changes: a field of
:class:`FitOptions`, or a field of one of its groups under a flat name (``bounds``,
``samples``, ``starts``, ``seed`` of :class:`SearchOptions`; ``checkpoint_path``,
``checkpoint_every``, ``resume`` of :class:`CheckpointOptions`). Anything else is an error
that names the keyword and lists the valid ones.

This module imports no jax: the command line builds its options before choosing the dtype.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import numbers

from jaxplush.errors import JaxplushError


@dataclasses.dataclass(frozen=True)
class SearchOptions:
    """The default fit's global stage (``optimizer="lm"`` only).

    Attributes:
      bounds: the search box {name: (lo, hi)} in parameter units (every fitted object), or
        "name=lo:hi,..." text; default each fitted parameter from start/4 to start*4. Refused
        with the other optimisers.
      samples: Sobol points of the global stage (default :data:`jaxplush.fitting.lmfit.GLOBAL_SAMPLES`, 64).
      starts: local Levenberg-Marquardt starts from its best candidates (default
        :data:`jaxplush.fitting.lmfit.STARTS`, 5).
      seed: the Sobol scrambling seed.
    """

    bounds: object = None
    samples: int | None = None
    starts: int | None = None
    seed: int = 0


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
      gtol, rtol, xtol, ftol, patience: when a gradient optimiser stops (max-norm of the
        gradient; relative loss change for ``patience`` accepted iterations; max-norm of the
        log-space step; the loss itself).
      method: gradient method of :func:`jaxplush.fitting.gradients.rollout_loss`.
      force: allow fitting ``total_weight`` jointly with k/dashpot/nmol.
      identifiability: compute the identifiability report at the optimum.
      check_dt: warn when dt exceeds the estimated stability limit at the start values
        (gradient optimisers; the default fit substeps such points instead).
      predictability: measure the predictability of the start values over the target before
        fitting (:func:`jaxplush.predictability`, two or three rollouts), reported in the result
        and FIT.h5; its reproducibility floor lets the outcome say ``at_floor``.
      search: :class:`SearchOptions` of the default fit's global stage.
      checkpoint: :class:`CheckpointOptions`.
    """

    iterations: int | None = None
    lr: float | None = None
    dt: float | None = None
    start: dict | None = None
    noise: float | None = None
    noise_free: bool = False
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
    search: SearchOptions = dataclasses.field(default_factory=SearchOptions)
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


#: Flat keyword -> (group, field) for the fields of FitOptions' groups.
SHORTCUTS = {"bounds": ("search", "bounds"), "samples": ("search", "samples"), "starts": ("search", "starts"),
             "seed": ("search", "seed"), "checkpoint_path": ("checkpoint", "path"),
             "checkpoint_every": ("checkpoint", "every"), "resume": ("checkpoint", "resume")}


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
    if opts.iterations is not None and (not _is_whole(opts.iterations) or int(opts.iterations) < 1):
        raise JaxplushError(f"iterations must be >= 1, got {opts.iterations}")
    s = opts.search
    for name, val in (("samples", s.samples), ("starts", s.starts)):
        if val is not None and (not _is_whole(val) or int(val) < (0 if name == "samples" else 1)):
            raise JaxplushError(f"{name} must be an integer >= {0 if name == 'samples' else 1}, got {val!r}")
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
    if opts.predictability not in (True, False):
        raise JaxplushError(f"predictability must be True or False, got {opts.predictability!r}")
    if not _is_whole(opts.patience) or opts.patience < 1:
        raise JaxplushError(f"patience must be an integer >= 1, got {opts.patience!r}")


def _is_whole(v):
    """A whole number (40 or 40.0; not True, not "40")."""
    return isinstance(v, numbers.Real) and not isinstance(v, bool) and math.isfinite(v) and int(v) == v
