"""Input/output and pictures.

- :mod:`jaxplush.io.trajectory`: trajectory HDF5 files (docs/formats.md §3), written atomically.
- :mod:`jaxplush.io.render`: plots and animations of trajectories (matplotlib).
- :mod:`jaxplush.io.capture`: synthetic depth-camera captures of a trajectory (partial, noisy point clouds).
"""
