"""The fit's exceptions (no jax: the command line matches them by type without importing the fit).

:class:`FitError` is also :data:`jaxplush.fitting.FitError` and ``jaxplush.fitting.fitter.FitError``.
"""

from __future__ import annotations

from jaxplush.errors import JaxplushError


class FitError(JaxplushError):
    """A fit that cannot proceed (the rollout blows up at the start or for every step tried)."""
