"""jaxplush.fitting: recover material parameters (k_structural, damping, nmol, ...) of a jaxplush scene from
a target deformation (by default a global search, then Levenberg-Marquardt with finite-difference
Jacobians on batched rollouts; Adam or L-BFGS on gradients through the rollout as options);
batched parameter sweeps. File formats: docs/formats.md §4-§6.

Quick use (run from the repository root; the test suite executes this example): a target
simulated from the bundled hanging ball, and a fit of its spring stiffness from a start 50% off.

>>> import jaxplush
>>> from jaxplush import fitting
>>> truth = jaxplush.load_scene("scenes/hanging.obj")
>>> target = fitting.make_target(truth, steps=400, dt=5e-4, save_every=20)
>>> start = truth.replace(params=truth.params._replace(k_structural=truth.params.k_structural * 1.5))
>>> result = fitting.fit(start, target, params=("k_structural",))     # global, then Levenberg-Marquardt
>>> ratio = float(result.values["k_structural"][0] / truth.params.k_structural[0])
>>> result.status, abs(ratio - 1) < 1e-3                          # within 0.1% of the truth
('converged', True)

Options: ``fitting.fit(scene, target, options=fitting.FitOptions(...))``, or single fields as
keywords (``iterations=40``); ``optimizer`` is "lm" (default), "adam", "lbfgs" or any optax
transformation (:mod:`jaxplush.fitting.options`, :func:`jaxplush.fitting.fitter.fit`).

Command line: ``jaxplush-fit SCENE.obj TARGET.h5 --out FIT.h5`` (exit 4 when the fit did not converge).

``fitting`` depends on ``jaxplush``, never the reverse. Names are imported lazily, so that
``import jaxplush.fitting.targets`` (or the CLI's input checks) does not pull in every module.
"""

from __future__ import annotations

import importlib

_EXPORTS = {
    "Target": "jaxplush.fitting.targets",
    "TargetKind": "jaxplush.fitting.targets.kinds",
    "Kind": "jaxplush.fitting.targets.kinds",
    "Status": "jaxplush.fitting.judge.outcome",
    "Controls": "jaxplush.fitting.targets",
    "scene_with_controls": "jaxplush.fitting.targets",
    "load_target": "jaxplush.fitting.targets",
    "make_target": "jaxplush.fitting.targets",
    "fit": "jaxplush.fitting.fitter",
    "FitOptions": "jaxplush.fitting.options",
    "SearchOptions": "jaxplush.fitting.options",
    "LocalOptions": "jaxplush.fitting.options",
    "ContinuationOptions": "jaxplush.fitting.options",
    "SmoothingOptions": "jaxplush.fitting.options",
    "CheckpointOptions": "jaxplush.fitting.options",
    "FitResult": "jaxplush.fitting.judge.result",
    "FitError": "jaxplush.fitting.errors",
    "GlobalStage": "jaxplush.fitting.stages",
    "LocalLM": "jaxplush.fitting.stages",
    "Smoothing": "jaxplush.fitting.stages",
    "Optax": "jaxplush.fitting.stages",
    "Gradient": "jaxplush.fitting.stages.gradfit",
    "Candidate": "jaxplush.fitting.stages",
    "LMState": "jaxplush.fitting.stages.search",
    "FitWarning": "jaxplush.fitting.errors",
    "ParameterWarning": "jaxplush.fitting.errors",
    "IdentifiabilityWarning": "jaxplush.fitting.errors",
    "Intervals": "jaxplush.fitting.judge.intervals",
    "synthetic_recovery": "jaxplush.fitting.targets.recovery",
    "identifiability": "jaxplush.fitting.judge.identifiability",
    "load_fit": "jaxplush.fitting.io",
    "SweepResult": "jaxplush.fitting.sweep",
    "fit_field": "jaxplush.fitting.stages.field",
    "FieldResult": "jaxplush.fitting.stages.field",
    "load_sweep": "jaxplush.fitting.sweep",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name):
    if name in _EXPORTS:
        module = importlib.import_module(_EXPORTS[name])
        return module if module.__name__.endswith(name) else getattr(module, name)
    raise AttributeError(f"module 'fitting' has no attribute {name!r}")
