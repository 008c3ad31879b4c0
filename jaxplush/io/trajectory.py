"""HDF5 trajectories: one schema for ``simulate`` output and fitting targets.

Datasets: ``positions`` float [T, V, 3] (m), ``times`` float [T] (s), ``faces`` int32 [F, 3]
(0-based, global), ``object_id`` int32 [V], ``object_names`` (UTF-8 strings [O]).
Attributes: ``dt``, ``integrator``, ``steps``, ``save_every``, ``substeps``, ``floor`` (NaN: none),
``gravity`` [3], ``temperature``, one (O,) array per parameter (``k_structural``, ``damping``,
``dashpot``, ``drag``, ``nmol``, ``total_weight``), ``jaxplush_version``, ``scene`` (the full
scene text), ``scene_path`` and ``wall_time``. A run with a per-edge stiffness field also has the
dataset ``k_structural_field`` [E] (its ``k_structural`` attribute: each object's mean). Files are
written atomically (temp file, then rename).

Format: docs/formats.md §3 (dtypes, attributes, what readers require); atomic writes: §1.
"""

from __future__ import annotations

import contextlib
import glob
import os
import tempfile
import time

import h5py
import numpy as np

from jaxplush.errors import JaxplushError, TrajectoryError
from jaxplush.types import PARAM_NAMES


@contextlib.contextmanager
def atomic_path(path, suffix=None):
    """Yield a temporary path beside ``path``; rename it onto ``path`` only on success."""
    path = os.fspath(path)
    d = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(d):
        raise JaxplushError(f"{path}: output directory {d} does not exist")
    suffix = suffix or os.path.splitext(path)[1]
    prefix = f".tmp-{os.path.basename(path)}-"
    started = time.time()
    fd, tmp = tempfile.mkstemp(dir=d, prefix=prefix, suffix=suffix)
    os.close(fd)
    try:
        yield tmp
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)  # mkstemp makes 0600; give the file ordinary permissions
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.remove(tmp)
        raise
    # a writer of this file killed outright (SIGKILL) left its temporary file: it is stale now
    for old in glob.glob(os.path.join(glob.escape(d), glob.escape(prefix) + "*" + glob.escape(suffix))):
        with contextlib.suppress(OSError):
            if os.path.getmtime(old) < started:
                os.remove(old)


def check_output_path(path, exts, what="output"):
    """Before any work: ``path`` must end in one of ``exts``, lie in an existing directory and not
    be a directory itself; else a :class:`JaxplushError` naming the path and the problem."""
    path = os.fspath(path)
    if os.path.splitext(path)[1].lower() not in exts:
        raise JaxplushError(f"{path}: {what} must end in {' or '.join(exts)}")
    d = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(d):
        raise JaxplushError(f"{path}: output directory {d} does not exist")
    if os.path.isdir(path):
        raise JaxplushError(f"{path}: is a directory")
    if os.path.islink(path) and not os.path.exists(path):
        raise JaxplushError(f"{path}: is a symbolic link to {os.readlink(path)}, which does not exist; "
                            "the output would replace the link with a file: remove it or name another output")


def open_hdf5(path):
    """Open an existing HDF5 file read-only; a :class:`TrajectoryError` names the file when it is
    missing, a directory, or not HDF5. Use as ``with open_hdf5(path) as f: ...``."""
    path = os.fspath(path)
    if not os.path.exists(path):
        raise TrajectoryError(path, "no such file")
    if os.path.isdir(path):
        raise TrajectoryError(path, "is a directory, not an HDF5 file")
    try:
        return h5py.File(path, "r")
    except (OSError, RuntimeError):          # RuntimeError: a damaged header (h5py "addr overflow")
        raise TrajectoryError(path, "not an HDF5 file (or a damaged one)") from None


def save_trajectory(traj, path):
    """Write a :class:`jaxplush.stepping.simulation.Trajectory` to ``path`` atomically."""
    from jaxplush import __version__
    with atomic_path(path, ".h5") as tmp:
        with h5py.File(tmp, "w") as f:
            f.create_dataset("positions", data=np.asarray(traj.positions), compression="gzip", compression_opts=1)
            f.create_dataset("times", data=np.asarray(traj.times))
            f.create_dataset("faces", data=np.asarray(traj.faces, np.int32))
            f.create_dataset("object_id", data=np.asarray(traj.object_id, np.int32))
            f.create_dataset("object_names", data=np.asarray(traj.object_names, dtype=object),
                             dtype=h5py.string_dtype("utf-8"))
            a = f.attrs
            a["dt"] = float(traj.dt)
            a["integrator"] = traj.integrator
            a["steps"] = int(traj.steps)
            a["save_every"] = int(traj.save_every)
            a["substeps"] = int(traj.substeps)
            a["floor"] = np.nan if traj.floor is None else float(traj.floor)
            a["gravity"] = np.asarray(traj.gravity, np.float64)
            a["temperature"] = float(traj.temperature)
            for name in PARAM_NAMES:
                value = np.asarray(getattr(traj.params, name), np.float64)
                if name == "k_structural" and value.ndim == 1 and value.shape[0] != len(traj.object_names):
                    # a per-edge stiffness field: a dataset (an attribute holds at most 64 KiB), and
                    # the attribute each object's mean
                    f.create_dataset("k_structural_field", data=value)
                    value = _object_means(traj, value)
                a[name] = value
            a["jaxplush_version"] = __version__
            a["scene"] = traj.scene_text
            a["scene_path"] = traj.scene_path
            a["wall_time"] = float(traj.wall_time)
    return os.fspath(path)


def _object_means(traj, field):
    """(O,) each object's mean of an (E,) per-edge field (edges: the sorted unique edges of the faces)."""
    from jaxplush.model.mesh import unique_edges
    eo = np.asarray(traj.object_id)[unique_edges(np.asarray(traj.faces))[:, 0]]
    n_o = len(traj.object_names)
    return np.bincount(eo, weights=field, minlength=n_o) / np.maximum(np.bincount(eo, minlength=n_o), 1)


def load_trajectory(path):
    """Read a trajectory file into a dict of numpy arrays and attributes (validated shapes)."""
    path = os.fspath(path)
    with open_hdf5(path) as f:
        for key in ("positions", "faces"):
            if key not in f:
                raise TrajectoryError(path, f"missing dataset '{key}'")
        out = {k: f[k][()] for k in f.keys() if isinstance(f[k], h5py.Dataset)}
        out["attrs"] = {k: f.attrs[k] for k in f.attrs}
    pos = out["positions"]
    if pos.ndim != 3 or pos.shape[2] != 3:
        raise TrajectoryError(path, f"'positions' must have shape [T, N, 3], got {list(pos.shape)}")
    if "object_names" in out:
        out["object_names"] = [n.decode() if isinstance(n, bytes) else str(n) for n in out["object_names"]]
    return out
