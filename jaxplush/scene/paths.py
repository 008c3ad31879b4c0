"""Path files of driven vertices (the scene keyword ``driven``; docs/formats.md §2.7).

A path gives the world positions of D vertices at S sample times:

* CSV (any name but ``.h5``/``.hdf5``): one row per sample, ``t,x1,y1,z1,x2,y2,z2,...`` (one x, y, z
  triple per listed vertex, in the order the ``driven`` line lists them); a first line that is
  not all numbers is a header; blank lines and ``#`` comments are ignored.
* HDF5 (``.h5``/``.hdf5``, or any file that starts with the HDF5 signature): datasets ``times``
  [S] and ``positions`` [S, D, 3].

:func:`read_path` reads and checks one (times finite and strictly increasing, S >= 1, positions
finite and of the listed vertices' count) and raises :class:`PathFileError` with the problem;
the scene parser adds its own file and line.
"""

from __future__ import annotations

import os

import numpy as np

#: Largest path file read (bytes).
MAX_PATH_BYTES = 2 ** 30
_HDF5_SIGNATURE = b"\x89HDF\r\n\x1a\n"


class PathFileError(ValueError):
    """A path file that is missing, unreadable or malformed (the message says which)."""


def read_path(file, n_vertices):
    """(times (S,) float64, positions (S, n_vertices, 3) float64) of a path file, checked.

    Raises:
      PathFileError: the file is missing or unreadable, or its contents break a rule.
    """
    file = os.fspath(file)
    if not os.path.exists(file):
        raise PathFileError("no such file")
    if not os.path.isfile(file):
        raise PathFileError("not a regular file")
    if os.path.getsize(file) > MAX_PATH_BYTES:
        raise PathFileError(f"too large (at most {MAX_PATH_BYTES // 2 ** 20} MiB)")
    try:
        with open(file, "rb") as fh:
            head = fh.read(8)
    except OSError as e:
        raise PathFileError(f"cannot read: {e.strerror}") from None
    if file.lower().endswith((".h5", ".hdf5")) or head == _HDF5_SIGNATURE:
        times, positions = _read_hdf5(file)
    else:
        times, positions = _read_csv(file, n_vertices)
    _check(times, positions, n_vertices)
    return times, positions


def _read_hdf5(file):
    import h5py
    try:
        with h5py.File(file, "r") as f:
            for key in ("times", "positions"):
                if key not in f or not isinstance(f[key], h5py.Dataset):
                    raise PathFileError(f"HDF5 path file needs a dataset {key!r}")
            times = np.asarray(f["times"][()], np.float64)
            positions = np.asarray(f["positions"][()], np.float64)
    except PathFileError:
        raise
    except (OSError, ValueError, TypeError) as e:
        raise PathFileError(f"cannot read as HDF5: {e}") from None
    if times.ndim != 1:
        raise PathFileError(f"'times' must have shape [S], got {list(times.shape)}")
    if positions.ndim != 3 or positions.shape[2] != 3 or positions.shape[0] != len(times):
        raise PathFileError(f"'positions' must have shape [S, D, 3] with S = {len(times)} samples, "
                            f"got {list(positions.shape)}")
    return times, positions


def _read_csv(file, n_vertices):
    try:
        with open(file, encoding="utf-8-sig") as fh:
            text = fh.read()
    except UnicodeDecodeError:
        raise PathFileError("not a UTF-8 text CSV file") from None
    except OSError as e:
        raise PathFileError(f"cannot read: {e.strerror}") from None
    rows, first = [], True
    width = 1 + 3 * n_vertices
    for lineno, raw in enumerate(text.splitlines(), 1):
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        cells = [c.strip() for c in line.split(",")]
        try:
            vals = [float(c) for c in cells]
        except ValueError:
            if first:
                first = False        # a header line
                continue
            raise PathFileError(f"line {lineno}: not a row of numbers: {raw.strip()!r}") from None
        first = False
        if len(vals) != width:
            raise PathFileError(f"line {lineno}: expected {width} values (t and x, y, z for each of the "
                                f"{n_vertices} listed vertices), got {len(vals)}")
        rows.append(vals)
    if not rows:
        raise PathFileError("no samples (at least one row t,x,y,z,... is needed)")
    a = np.asarray(rows, np.float64)
    return a[:, 0].copy(), a[:, 1:].reshape(len(a), n_vertices, 3)


def _check(times, positions, n_vertices):
    if len(times) < 1:
        raise PathFileError("no samples (S must be at least 1)")
    if positions.shape[1] != n_vertices:
        raise PathFileError(f"positions for {positions.shape[1]} vertices, but the line lists {n_vertices}")
    if not np.isfinite(times).all():
        raise PathFileError(f"time of sample {int(np.argmin(np.isfinite(times))) + 1} is not finite")
    if len(times) > 1 and not (np.diff(times) > 0).all():
        i = int(np.argmin(np.diff(times) > 0))
        raise PathFileError(f"times must be strictly increasing: sample {i + 2} (t = {times[i + 1]!r}) "
                            f"does not come after sample {i + 1} (t = {times[i]!r})")
    if not np.isfinite(positions).all():
        s = int(np.argmax(~np.isfinite(positions).all(axis=(1, 2))))
        raise PathFileError(f"positions of sample {s + 1} are not finite")
    if np.abs(positions).max() >= 1e30:
        raise PathFileError("positions too large (|value| must be < 1e30 m)")
