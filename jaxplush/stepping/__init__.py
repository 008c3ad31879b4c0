"""Time stepping: from parameters and a state to a trajectory.

- :mod:`jaxplush.stepping.integrators`: the time integrators; :mod:`jaxplush.stepping.constraints`:
  the floor projection and pins.
- :mod:`jaxplush.stepping.step`: ``make_simulator`` (init, step, status, params).
- :mod:`jaxplush.stepping.rollouts`: ``rollout`` (scanned frames, carried health).
- :mod:`jaxplush.stepping.diagnostics`: health codes and energies;
  :mod:`jaxplush.stepping.stability`: the stable-dt bound and the dt check.
- :mod:`jaxplush.stepping.simulation`: ``simulate``, the driver; :mod:`jaxplush.stepping.compiled`:
  the per-program cache of compiled functions and the persistent compilation cache.
- :mod:`jaxplush.stepping.predictability`: ``predictability``, how far two runs that differ only by
  rounding drift apart (the predictable horizon and the reproducibility floor).
"""
