"""fitting: recover material parameters (k_structural, damping, nmol, ...) of a jaxplush scene from
a target deformation, by gradients through the rollout; batched parameter sweeps.

Quick use::

    scene = jaxplush.load_scene("scene.obj")
    target = fitting.load_target("target.h5", scene)          # validated before anything is traced
    result = fitting.fit(scene, target, params=("k_structural", "damping", "nmol"))
    result.values, result.loss, result.identifiability.summary()
    result.save("FIT.h5")

Command line: ``jaxplush-fit SCENE.obj TARGET.h5 --params k,damping,nmol --out FIT.h5``.

``fitting`` depends on ``jaxplush``, never the reverse. Names are imported lazily, so that
``import fitting.targets`` (or the CLI's input checks) does not pull in every module.
"""

from __future__ import annotations

import importlib

_EXPORTS = {
    "Target": "fitting.targets",
    "load_target": "fitting.targets",
    "make_target": "fitting.targets",
    "fit": "fitting.fit",
    "FitResult": "fitting.fit",
    "FitError": "fitting.fit",
    "synthetic_recovery": "fitting.fit",
    "identifiability": "fitting.identifiability",
    "load_fit": "fitting.io",
    "SweepResult": "fitting.sweep",
    "load_sweep": "fitting.sweep",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name):
    if name in _EXPORTS:
        module = importlib.import_module(_EXPORTS[name])
        return module if module.__name__.endswith(name) else getattr(module, name)
    raise AttributeError(f"module 'fitting' has no attribute {name!r}")
