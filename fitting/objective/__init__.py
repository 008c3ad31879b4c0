"""What a fit minimises: the target's residuals at parameter values.

* :mod:`~jaxplush.fitting.objective.problem`: a fit's problem, the scene, target, fitted
  parameters (in log space) and the rollout that maps them to frames;
* :mod:`~jaxplush.fitting.objective.losses`: the loss and residuals of a target (its kind's,
  :mod:`jaxplush.fitting.targets.kinds`), normalised by the noise or the target's motion;
* :mod:`~jaxplush.fitting.objective.evaluate`: residuals of many parameter points at once on the
  batched engine, each stable (substeps, retries, contact capacity);
* :mod:`~jaxplush.fitting.objective.shooting`: the same in segments restarted from observed
  states (multiple shooting);
* :mod:`~jaxplush.fitting.objective.gradients`: gradients of a loss through long rollouts (the
  gradient optimisers' and a user's own).
"""
