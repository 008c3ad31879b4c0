"""The fit's exceptions (no jax: the command line matches them by type without importing the fit).

:class:`FitError` is also :data:`jaxplush.fitting.FitError` and ``jaxplush.fitting.fitter.FitError``.
"""

from __future__ import annotations

from jaxplush.errors import JaxplushError, JaxplushWarning


class FitError(JaxplushError):
    """A fit that cannot proceed (the rollout blows up at the start or for every step tried)."""


class FitWarning(JaxplushWarning):
    """How a fit ended, when it did not converge (the outcome's text: ``FitResult.outcome``)."""


class ParameterWarning(JaxplushWarning):
    """A note on the fitted parameters themselves: which were chosen by default, or a combination
    the motion cannot split (the report's ``damping`` with ``drag``; mass with everything)."""


class IdentifiabilityWarning(JaxplushWarning):
    """The identifiability report finds parameters or combinations the target does not determine."""
