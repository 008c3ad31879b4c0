"""Input/output and pictures.

- :mod:`jaxplush.io.trajectory`: trajectory HDF5 files (docs/formats.md §3), written atomically.
- :mod:`jaxplush.io.render`: plots and animations of trajectories (matplotlib).
- :mod:`jaxplush.io.capture`: synthetic depth-camera captures of a trajectory (partial, noisy point clouds).
- :mod:`jaxplush.io.view`: the interactive 3-D viewer (viser, the optional extra ``viewer``); the
  function :func:`view` is ``jaxplush.io.view`` (the module itself: ``sys.modules["jaxplush.io.view"]``).
"""

from jaxplush.io.view import view  # noqa: E402,F401  (binds the function over the submodule's name)
