"""The one judge of a fit: what its last candidate means.

* :mod:`~jaxplush.fitting.judge.outcome`: how a fit ended (:class:`~jaxplush.fitting.judge.outcome.Status`)
  from its residual, the noise or reproducibility floor, gradients and stopping reason;
* :mod:`~jaxplush.fitting.judge.identifiability`: which parameter directions the target
  determines;
* :mod:`~jaxplush.fitting.judge.intervals`: 95% intervals from twins (runs that differ by rounding,
  or noise redrawn);
* :mod:`~jaxplush.fitting.judge.result`: the :class:`~jaxplush.fitting.judge.result.FitResult`
  they make, with its frames, history and notes (FIT.h5: :mod:`jaxplush.fitting.io`).
"""
