"""Matplotlib renderer for jaxplush trajectory files.

Contract
--------
:func:`render` reads a trajectory HDF5 file and writes either a still image of
one frame (``.png``, ``.jpg``/``.jpeg``, ``.pdf``, ``.svg``) or an animation of
the whole trajectory (``.gif`` through Pillow, ``.mp4`` through ffmpeg when it is
installed). It returns the output path.

Input schema (only ``positions`` and ``faces`` are required):

* ``positions`` float ``[T, N, 3]``, metres, OBJ convention (world y is up);
* ``faces`` int ``[F, 3]``, 0-based global vertex indices;
* ``times`` float ``[T]`` in seconds (when absent: ``attrs["dt"] *
  attrs["save_every"] * frame`` if those attributes exist, else the frame index);
* ``object_id`` int ``[N]`` (default: every vertex belongs to object 0);
* ``object_names`` strings ``[O]`` (default: ``"object <i>"``);
* ``attrs["floor"]``: height of a horizontal, upward-facing floor plane; NaN or
  absent means "no floor". All other attributes are ignored.

Guarantees:

* The whole input is validated before any output file is created. Bad input
  raises :class:`jaxplush.errors.TrajectoryError`; bad arguments (unknown
  extension, ffmpeg missing for ``.mp4``, ...) raise
  :class:`jaxplush.errors.JaxplushError`. No raw h5py/KeyError escapes.
* Output is atomic: it is written to a temporary file in the destination
  directory and moved onto ``out`` with :func:`os.replace`; on failure the
  temporary file is removed, so a partial file is never left behind.
* The camera is fixed over the whole trajectory (limits from all frames) and the
  three axes share one scale. World ``(x, y, z)`` is drawn with world ``y`` as
  the plot's vertical axis, through a proper rotation (not a mirror): plot axes
  are ``(x, -z, y)`` and the middle axis is labelled with world-``z`` values.
  With the default ``azim=-60`` the camera looks at the scene from the front
  (+z) right.

This module does not import JAX and never touches pyplot's global state (it
builds :class:`matplotlib.figure.Figure` objects on an Agg canvas), so it is safe
to call from scripts, tests and servers without a display.
"""

from __future__ import annotations

import math
import os
import tempfile
from dataclasses import dataclass

import h5py
import numpy as np
from matplotlib import animation
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.colors import to_rgb
from matplotlib.figure import Figure
from matplotlib.patches import Patch
from matplotlib.ticker import FuncFormatter, MaxNLocator
from mpl_toolkits.mplot3d.art3d import Poly3DCollection

from jaxplush.errors import JaxplushError, TrajectoryError
from jaxplush.io.trajectory import open_hdf5

__all__ = ["render", "STILL_EXTENSIONS", "ANIMATION_EXTENSIONS"]

#: Output extensions accepted for a single frame (``frame=<int>``).
STILL_EXTENSIONS = (".png", ".jpg", ".jpeg", ".pdf", ".svg")
#: Output extensions accepted for an animation (``frame=None``).
ANIMATION_EXTENSIONS = (".gif", ".mp4")

# Seaborn "deep" palette: distinct, readable and not garish.
_PALETTE = (
    "#4C72B0", "#DD8452", "#55A868", "#C44E52", "#8172B3",
    "#937860", "#DA8BC3", "#8C8C8C", "#CCB974", "#64B5CD",
)
_FLOOR_RGBA = (0.55, 0.55, 0.55, 0.35)
_EDGE_RGBA = (0.0, 0.0, 0.0, 0.12)
_AMBIENT = 0.45  # shading: intensity = ambient + (1 - ambient) * max(n.l, 0)
_FIGSIZE = (6.4, 6.0)  # inches
_FALLBACK_FPS = 10.0  # frames per second when the file has no usable times
_MIN_GIF_DELAY = 0.02  # s: browsers show shorter GIF frame delays as 100 ms
_MAX_VIDEO_FPS = 60.0
_CHUNK_VALUES = 4_000_000  # floats read per chunk while scanning positions


@dataclass
class _Trajectory:
    """Validated trajectory data needed for drawing (frames already selected)."""

    n_frames: int  # T of the file
    frames: np.ndarray  # [K] selected frame indices, increasing
    positions: np.ndarray  # [K, N, 3] float64 positions of the selected frames
    times: np.ndarray  # [T] float64
    faces: np.ndarray  # [F, 3] int64
    face_object: np.ndarray  # [F] object index of each face
    names: list  # [O] object names
    lo: np.ndarray  # [3] world min over all frames
    hi: np.ndarray  # [3] world max over all frames
    floor: float  # NaN when there is no floor


def render(path, out, frame=None, fps=None, max_frames=200, elev=20.0, azim=-60.0, dpi=100, report=None) -> str:
    """Render a trajectory file to a still image or an animation.

    Args:
        path: Trajectory HDF5 file (see the module docstring for the schema).
        out: Output file. With ``frame`` given: ``.png``, ``.jpg``, ``.jpeg``,
            ``.pdf`` or ``.svg``; without: ``.gif`` (Pillow) or ``.mp4``
            (needs ffmpeg). Its directory must exist.
        frame: Index of the single frame to draw (negative counts from the end,
            as in Python), or None to animate the trajectory.
        fps: Playback frame rate. Default (None): real time, i.e. each drawn
            frame is shown for the simulated time until the next one (a GIF
            frame lasts at least 20 ms, so at most 50 frames per simulated
            second are drawn; an ``.mp4`` plays at the real-time rate of the
            drawn frames, at most 60 fps). With ``fps`` the drawn frames play at
            that fixed rate instead (slow or fast motion).
        max_frames: Most frames an animation holds (default 200). Longer
            trajectories are subsampled evenly, always keeping the first and
            the last frame; ``report`` says how many were drawn.
        elev: Camera elevation in degrees (above the floor plane).
        azim: Camera azimuth in degrees (matplotlib convention, about world y).
        dpi: Resolution in dots per inch (the figure is 6.4 x 6 inches).
        report: Optional callable taking one line of text: what is drawn (frames
            kept of the total, playback speed). The command line prints it.

    Returns:
        ``out`` as a string.

    Raises:
        TrajectoryError: The file is missing, not HDF5, lacks ``positions`` or
            ``faces``, has wrong shapes, out-of-range face indices, non-finite
            positions, or ``frame`` is out of range.
        JaxplushError: Bad arguments: unsupported output extension, ``.mp4``
            without ffmpeg, missing output directory, non-positive ``fps``,
            ``max_frames`` < 2, ...
    """
    out = os.fspath(out)
    ext = os.path.splitext(out)[1].lower()
    still = frame is not None
    _check_arguments(out, ext, still, frame, fps, max_frames, dpi)

    min_gap = _MIN_GIF_DELAY if ext == ".gif" else 1.0 / _MAX_VIDEO_FPS
    traj = _read_trajectory(path, frame, max_frames, None if (still or fps is not None) else min_gap)

    if still:
        _atomic_write(out, ext, lambda tmp: _render_still(traj, tmp, ext, elev, azim, dpi))
        return out
    durations = _durations(traj.times[traj.frames], fps, ext)
    if report is not None:
        report(_plan_text(traj, durations, fps))
    _atomic_write(out, ext, lambda tmp: _render_animation(traj, tmp, ext, durations, elev, azim, dpi))
    return out


# ----------------------------------------------------------------------------
# argument checks and output handling
# ----------------------------------------------------------------------------


def _check_arguments(out, ext, still, frame, fps, max_frames, dpi):
    """Validate everything about the call that does not need the input file."""
    if still:
        if isinstance(frame, bool) or not isinstance(frame, (int, np.integer)):
            raise JaxplushError(f"frame must be an integer or None, got {frame!r}")
        if ext not in STILL_EXTENSIONS:
            hint = " (.gif/.mp4 are for animations: leave frame=None)" if ext in ANIMATION_EXTENSIONS else ""
            raise JaxplushError(
                f"{out}: unsupported still-image extension {ext or '(none)'!r}; "
                f"use one of {', '.join(STILL_EXTENSIONS)}{hint}"
            )
    else:
        if ext not in ANIMATION_EXTENSIONS:
            hint = " (for a still image pass frame=<index>)" if ext in STILL_EXTENSIONS else ""
            raise JaxplushError(
                f"{out}: unsupported animation extension {ext or '(none)'!r}; "
                f"use one of {', '.join(ANIMATION_EXTENSIONS)}{hint}"
            )
        if ext == ".mp4" and not animation.writers.is_available("ffmpeg"):
            raise JaxplushError(
                f"{out}: ffmpeg was not found on PATH (it is needed to write .mp4); "
                "install ffmpeg or render a .gif instead"
            )
        if isinstance(max_frames, bool) or not isinstance(max_frames, (int, np.integer)) or max_frames < 2:
            raise JaxplushError(f"max_frames must be an integer >= 2, got {max_frames!r}")
        if fps is not None and not (isinstance(fps, (int, float, np.number)) and math.isfinite(fps) and fps > 0):
            raise JaxplushError(f"fps must be a positive number, got {fps!r}")
    if not (isinstance(dpi, (int, float, np.number)) and math.isfinite(dpi) and dpi > 0):
        raise JaxplushError(f"dpi must be a positive number, got {dpi!r}")
    out_dir = os.path.dirname(os.path.abspath(out))
    if not os.path.isdir(out_dir):
        raise JaxplushError(f"{out}: output directory {out_dir} does not exist")


def _atomic_write(out, ext, write):
    """Call ``write(tmp_path)`` and move the result onto ``out``; clean up on failure."""
    fd, tmp = tempfile.mkstemp(dir=os.path.dirname(os.path.abspath(out)), prefix=".render-", suffix=ext)
    os.close(fd)
    try:
        write(tmp)
        # mkstemp creates 0600 files; give the result ordinary permissions.
        mode = os.stat(out).st_mode & 0o777 if os.path.exists(out) else 0o644
        os.chmod(tmp, mode)
        os.replace(tmp, out)
    except BaseException:
        try:
            os.remove(tmp)
        except OSError:
            pass
        raise


def _select_frames(times, max_frames, min_gap=None):
    """Evenly spaced, increasing frame indices; first and last always kept.

    At most ``max_frames``; with ``min_gap`` (s) also no more than one frame per ``min_gap`` of
    simulated time (what a real-time GIF can show)."""
    n_frames = len(times)
    keep = min(n_frames, max_frames)
    if min_gap is not None and n_frames > 1:
        duration = float(times[-1] - times[0])
        if math.isfinite(duration) and duration > 0:
            keep = min(keep, max(2, int(duration / min_gap) + 1))
    if n_frames <= keep:
        return np.arange(n_frames)
    return np.unique(np.round(np.linspace(0, n_frames - 1, keep)).astype(np.int64))


def _durations(times, fps, ext):
    """Seconds each drawn frame is shown: real time (the simulated time to the next drawn frame;
    the last frame as long as the mean gap), or 1/fps each. GIF delays are whole hundredths of a
    second and at least 20 ms; a video needs one constant rate."""
    k = len(times)
    gaps = np.diff(np.asarray(times, np.float64))
    real = fps is None and k > 1 and np.all(np.isfinite(gaps)) and np.all(gaps > 0)
    if not real:
        rate = float(fps) if fps is not None else _FALLBACK_FPS
        return np.full(k, 1.0 / rate)
    if ext != ".gif":
        return np.full(k, float(np.mean(gaps)))        # constant rate, the same total duration
    return np.append(gaps, np.mean(gaps))


def _plan_text(traj, durations, fps):
    k, n = len(traj.frames), traj.n_frames
    which = f"all {n} frames" if k == n else f"{k} of {n} frames (evenly spaced, first and last kept)"
    times = traj.times[traj.frames]
    sim_time = float(times[-1] - times[0]) if k > 1 else 0.0
    play = float(np.sum(durations[:-1])) if k > 1 else float(durations[0])
    if fps is None and k > 1 and sim_time > 0:
        speed = "real time" if abs(play / sim_time - 1) < 0.05 else f"{sim_time / play:.2g}x real time"
        return f"drawing {which}: {sim_time:.3g} s of simulation played in {play:.3g} s ({speed})"
    return f"drawing {which} at {float(fps or _FALLBACK_FPS):g} fps: {float(np.sum(durations)):.3g} s of playback"


# ----------------------------------------------------------------------------
# reading and validation
# ----------------------------------------------------------------------------


def _read_trajectory(path, frame, max_frames, min_gap=None):
    """Open, validate and read what is needed to draw; raise TrajectoryError on bad input."""
    path = os.fspath(path)
    f = open_hdf5(path)
    try:
        with f:
            return _read_open_file(path, f, frame, max_frames, min_gap)
    except TrajectoryError:
        raise
    except (OSError, KeyError, ValueError, TypeError, IndexError, RuntimeError) as exc:
        # Corrupt datasets, odd dtypes and the like: never leak a raw traceback.
        raise TrajectoryError(path, f"could not read trajectory ({type(exc).__name__}: {exc})") from None


def _dataset(path, f, name, required):
    if name not in f:
        if required:
            raise TrajectoryError(path, f"missing dataset {name!r}")
        return None
    ds = f[name]
    if not isinstance(ds, h5py.Dataset):
        raise TrajectoryError(path, f"{name!r} is a group, expected a dataset")
    return ds


def _read_open_file(path, f, frame, max_frames, min_gap):
    pos_ds = _dataset(path, f, "positions", required=True)
    faces_ds = _dataset(path, f, "faces", required=True)
    n_frames, n_verts = _positions_shape(path, pos_ds)
    faces = _read_faces(path, faces_ds, n_verts)

    if frame is not None and not -n_frames <= int(frame) < n_frames:
        raise TrajectoryError(path, f"frame {int(frame)} out of range: the trajectory has {n_frames} frames")

    times = _read_times(path, f, n_frames)

    # --- frame selection --------------------------------------------------------
    if frame is not None:
        frames = np.array([int(frame) % n_frames])
    else:
        frames = _select_frames(times, max_frames, min_gap)

    object_id, names = _read_objects(path, f, n_verts)
    positions, lo, hi = _scan_positions(path, pos_ds, frames, times)

    return _Trajectory(
        n_frames=n_frames,
        frames=frames,
        positions=positions,
        times=times,
        faces=faces,
        face_object=object_id[faces[:, 0]],
        names=names,
        lo=lo,
        hi=hi,
        floor=_float_attr(f, "floor"),
    )


def _positions_shape(path, pos_ds):
    """(n_frames, n_verts) of the positions dataset, after checking its shape and dtype (its
    values are scanned by :func:`_scan_positions`)."""
    if pos_ds.ndim != 3 or pos_ds.shape[2] != 3:
        raise TrajectoryError(path, f"positions must have shape [T, N, 3], got {list(pos_ds.shape)}")
    n_frames, n_verts = int(pos_ds.shape[0]), int(pos_ds.shape[1])
    if n_frames == 0 or n_verts == 0:
        raise TrajectoryError(path, f"positions is empty (shape {list(pos_ds.shape)})")
    if pos_ds.dtype.kind not in "fiu":
        raise TrajectoryError(path, f"positions must be numeric, got dtype {pos_ds.dtype}")
    return n_frames, n_verts


def _read_faces(path, faces_ds, n_verts):
    """The (F, 3) int64 faces, checked against the vertex count."""
    if faces_ds.ndim != 2 or faces_ds.shape[1] != 3:
        raise TrajectoryError(path, f"faces must have shape [F, 3], got {list(faces_ds.shape)}")
    if faces_ds.shape[0] == 0:
        raise TrajectoryError(path, "faces is empty: nothing to draw")
    faces = _as_index_array(path, "faces", faces_ds[()])
    if faces.min() < 0 or faces.max() >= n_verts:
        raise TrajectoryError(
            path, f"face vertex indices must lie in [0, {n_verts - 1}], found [{faces.min()}, {faces.max()}]"
        )
    return faces


def _read_times(path, f, n_frames):
    """(T,) float64 frame times: the ``times`` dataset, else from the ``dt`` and ``save_every``
    attributes, else the frame index."""
    times_ds = _dataset(path, f, "times", required=False)
    if times_ds is not None:
        times = np.asarray(times_ds[()], dtype=np.float64).reshape(-1) if times_ds.ndim <= 1 else None
        if times is None or times.shape != (n_frames,):
            raise TrajectoryError(path, f"times must have shape [{n_frames}], got {list(times_ds.shape)}")
        if not np.all(np.isfinite(times)):
            raise TrajectoryError(path, "times contains non-finite values")
    else:
        dt = _float_attr(f, "dt")
        every = _float_attr(f, "save_every")
        step = dt * (every if math.isfinite(every) else 1.0)
        times = np.arange(n_frames, dtype=np.float64) * (step if math.isfinite(step) and step > 0 else 1.0)
    return times


def _read_objects(path, f, n_verts):
    """(object_id (N,) int64, names: one per object, defaults filled in)."""
    oid_ds = _dataset(path, f, "object_id", required=False)
    if oid_ds is not None:
        if oid_ds.shape != (n_verts,):
            raise TrajectoryError(path, f"object_id must have shape [{n_verts}], got {list(oid_ds.shape)}")
        object_id = _as_index_array(path, "object_id", oid_ds[()])
        if object_id.min() < 0:
            raise TrajectoryError(path, "object_id contains negative values")
    else:
        object_id = np.zeros(n_verts, dtype=np.int64)
    names = _read_names(f)
    n_objects = max(int(object_id.max()) + 1, len(names))
    names = names + [f"object {i}" for i in range(len(names), n_objects)]
    return object_id, names


def _scan_positions(path, pos_ds, frames, times):
    """Scan all positions once, in chunks: check finiteness, and return (the selected frames'
    positions (k, N, 3) float64, lo (3,), hi (3,) bounds over all frames)."""
    n_frames, n_verts = int(pos_ds.shape[0]), int(pos_ds.shape[1])
    chunk = max(1, _CHUNK_VALUES // (3 * n_verts))
    lo = np.full(3, np.inf)
    hi = np.full(3, -np.inf)
    picked = []
    for start in range(0, n_frames, chunk):
        block = np.asarray(pos_ds[start : start + chunk], dtype=np.float64)
        finite = np.isfinite(block).all(axis=(1, 2))
        if not finite.all():
            bad = start + int(np.argmin(finite))
            raise TrajectoryError(
                path,
                f"positions contain non-finite values (first at frame {bad} of {n_frames}, "
                f"t = {times[bad]:.6g} s); the simulation probably blew up",
            )
        lo = np.minimum(lo, block.min(axis=(0, 1)))
        hi = np.maximum(hi, block.max(axis=(0, 1)))
        sel = frames[(frames >= start) & (frames < start + len(block))]
        if len(sel):
            picked.append(block[sel - start])
    return np.concatenate(picked, axis=0), lo, hi


def _as_index_array(path, name, values):
    """Integer copy of ``values``; floats are accepted only when integral."""
    arr = np.asarray(values)
    if arr.dtype.kind in "iu":
        return arr.astype(np.int64)
    if arr.dtype.kind == "f" and np.all(np.isfinite(arr)) and np.all(arr == np.round(arr)):
        return arr.astype(np.int64)
    raise TrajectoryError(path, f"{name} must hold integers, got dtype {arr.dtype}")


def _float_attr(f, name):
    """A scalar float attribute, or NaN when absent or not a number."""
    try:
        value = np.asarray(f.attrs.get(name, np.nan), dtype=np.float64)
        return float(value.reshape(-1)[0]) if value.size == 1 else math.nan
    except (TypeError, ValueError, OSError):
        return math.nan


def _read_names(f):
    """Object names as a list of str ([] when absent or unreadable)."""
    if "object_names" not in f or not isinstance(f["object_names"], h5py.Dataset):
        return []
    try:
        raw = np.asarray(f["object_names"][()]).reshape(-1)
    except (OSError, TypeError, ValueError):
        return []
    return [v.decode("utf-8", "replace") if isinstance(v, bytes) else str(v) for v in raw.tolist()]


# ----------------------------------------------------------------------------
# drawing
# ----------------------------------------------------------------------------


def _to_plot(xyz):
    """World (x, y, z) with y up -> plot (x, -z, y): a rotation, so nothing is mirrored."""
    return np.stack([xyz[..., 0], -xyz[..., 2], xyz[..., 1]], axis=-1)


class _Scene:
    """A figure with fixed axes, optional floor and one mesh collection to update per frame."""

    def __init__(self, traj, elev, azim, dpi):
        self.traj = traj
        self.fig = Figure(figsize=_FIGSIZE, dpi=dpi)
        FigureCanvasAgg(self.fig)
        self.fig.subplots_adjust(left=0.0, right=1.0, bottom=0.0, top=0.95)
        ax = self.fig.add_subplot(projection="3d")
        self.ax = ax

        lo, hi = traj.lo.copy(), traj.hi.copy()
        centre = 0.5 * (lo + hi)
        extent = float(max(np.max(hi - lo), 1e-6))
        has_floor = math.isfinite(traj.floor)
        if has_floor:
            # Floor square centred under the objects, a bit larger than their footprint.
            half = 0.5 * max(hi[0] - lo[0], hi[2] - lo[2]) + 0.25 * extent
            lo[[0, 2]] = centre[[0, 2]] - half
            hi[[0, 2]] = centre[[0, 2]] + half
            lo[1] = min(lo[1], traj.floor)
            hi[1] = max(hi[1], traj.floor)
        pad = 0.03 * float(max(np.max(hi - lo), 1e-6))
        lo, hi = lo - pad, hi + pad
        # Every axis spans at least 30% of the longest one (limits grow, the
        # scale stays equal), so flat or long scenes keep a readable box.
        tiny = 0.3 * float(np.max(hi - lo))
        grow = np.maximum(tiny - (hi - lo), 0.0) / 2
        lo, hi = lo - grow, hi + grow

        plo, phi = _to_plot(lo), _to_plot(hi)  # note: -z swaps the second axis' ends
        ax.set_xlim(plo[0], phi[0])
        ax.set_ylim(phi[1], plo[1])
        ax.set_zlim(plo[2], phi[2])
        # zoom < 1 leaves room for tick and axis labels whatever the box proportions.
        ax.set_box_aspect((hi[0] - lo[0], hi[2] - lo[2], hi[1] - lo[1]), zoom=0.88)
        ax.yaxis.set_major_formatter(FuncFormatter(lambda v, _pos: f"{-v + 0.0:g}"))
        ax.set_xlabel("x (m)")
        ax.set_ylabel("z (m)")
        ax.set_zlabel("y (m, up)")
        ax.view_init(elev=elev, azim=azim)
        for axis in (ax.xaxis, ax.yaxis, ax.zaxis):
            axis.set_pane_color((0.97, 0.97, 0.97, 1.0))
        ax.tick_params(labelsize=7)
        for axis in (ax.xaxis, ax.yaxis, ax.zaxis):
            axis.set_major_locator(MaxNLocator(nbins=5))
        # Draw order is set by hand: floor first (seen from above), then the
        # meshes, whose faces are depth-sorted together in one collection.
        ax.computed_zorder = False

        if has_floor:
            y = traj.floor
            square = np.array(
                [[[lo[0], y, lo[2]], [hi[0], y, lo[2]], [hi[0], y, hi[2]], [lo[0], y, hi[2]]]]
            )
            floor = Poly3DCollection(
                _to_plot(square), facecolors=[_FLOOR_RGBA], edgecolors=[(0.4, 0.4, 0.4, 0.5)], linewidths=0.8
            )
            floor.set_zorder(1 if elev >= 0 else 3)
            ax.add_collection3d(floor)

        self.base_rgb = np.array([to_rgb(_PALETTE[i % len(_PALETTE)]) for i in range(len(traj.names))])
        self.face_rgb = self.base_rgb[traj.face_object]
        self.mesh = Poly3DCollection(
            np.zeros((len(traj.faces), 3, 3)), edgecolors=[_EDGE_RGBA], linewidths=0.3
        )
        self.mesh.set_zorder(2)
        ax.add_collection3d(self.mesh)

        if len(traj.names) > 1:
            used = np.unique(traj.face_object)
            handles = [Patch(facecolor=self.base_rgb[i], label=traj.names[i]) for i in used]
            ax.legend(handles=handles, loc="upper right", fontsize=8, frameon=False)

        # World-space view and light directions for shading.
        e, a = math.radians(elev), math.radians(azim)
        view_plot = np.array([math.cos(e) * math.cos(a), math.cos(e) * math.sin(a), math.sin(e)])
        self.view = np.array([view_plot[0], view_plot[2], -view_plot[1]])  # plot -> world
        side = np.cross(np.array([0.0, 1.0, 0.0]), self.view)
        light = self.view + np.array([0.0, 1.2, 0.0]) + 0.4 * side
        self.light = light / np.linalg.norm(light)
        self.title = self.fig.suptitle("", fontsize=11)

    def show(self, k):
        """Put the k-th selected frame on the figure."""
        traj = self.traj
        tri = traj.positions[k][traj.faces]  # [F, 3, 3] world
        normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-30)
        # Two-sided lighting: flip each normal towards the camera, so the visible
        # side is lit correctly whatever the winding and for open meshes too.
        normal *= np.where(normal @ self.view < 0, -1.0, 1.0)[:, None]
        shade = _AMBIENT + (1 - _AMBIENT) * np.clip(normal @ self.light, 0.0, 1.0)
        colours = np.clip(self.face_rgb * shade[:, None], 0.0, 1.0)
        self.mesh.set_verts(_to_plot(tri))
        self.mesh.set_facecolor(colours)
        i = int(traj.frames[k])
        self.title.set_text(f"t = {traj.times[i]:.3f} s    frame {i} / {traj.n_frames - 1}")


def _render_still(traj, tmp, ext, elev, azim, dpi):
    scene = _Scene(traj, elev, azim, dpi)
    scene.show(0)
    fmt = "jpeg" if ext in (".jpg", ".jpeg") else ext[1:]
    scene.fig.savefig(tmp, format=fmt, dpi=dpi)


def _render_animation(traj, tmp, ext, durations, elev, azim, dpi):
    scene = _Scene(traj, elev, azim, dpi)
    if ext == ".gif":
        _write_gif(scene, tmp, durations)
        return
    # libx264 needs even frame sizes; the scale filter rounds them down.
    writer = animation.FFMpegWriter(
        fps=1.0 / float(durations[0]), codec="h264", extra_args=["-vf", "scale=trunc(iw/2)*2:trunc(ih/2)*2"]
    )
    with writer.saving(scene.fig, tmp, dpi):
        for k in range(len(traj.frames)):
            scene.show(k)
            writer.grab_frame()


def _write_gif(scene, tmp, durations):
    """Draw the axes, floor and legend once, then only the mesh and the title per frame
    (blitting), and quantise each frame with Pillow's fast octree, which is much cheaper than a
    full redraw with Pillow's default quantiser."""
    from PIL import Image

    fig, canvas = scene.fig, scene.fig.canvas
    scene.mesh.set_visible(False)
    scene.title.set_visible(False)
    canvas.draw()
    background = canvas.copy_from_bbox(fig.bbox)
    scene.mesh.set_visible(True)
    scene.title.set_visible(True)
    images = []
    for k in range(len(scene.traj.frames)):
        scene.show(k)
        canvas.restore_region(background)
        scene.mesh.do_3d_projection()
        scene.ax.draw_artist(scene.mesh)
        fig.draw_artist(scene.title)
        rgb = np.asarray(canvas.buffer_rgba())[..., :3]
        images.append(Image.fromarray(np.ascontiguousarray(rgb)).quantize(256, method=Image.Quantize.FASTOCTREE))
    # GIF delays are whole hundredths of a second (at least 2): round the running total, so that
    # the whole animation keeps its duration when the frame gaps are not multiples of 10 ms
    ends = np.round(100 * np.cumsum(durations)).astype(np.int64)
    ms = [10 * int(max(2, c)) for c in np.diff(np.concatenate([[0], ends]))]
    images[0].save(tmp, format="GIF", save_all=True, append_images=images[1:], duration=ms, loop=0,
                   disposal=1)


# ----------------------------------------------------------------------------
# a stiffness field on the mesh
# ----------------------------------------------------------------------------

#: The views of :func:`render_field`: (elevation, azimuth) in degrees, from the front (+z, as
#: :func:`render`'s plot axes put it) and from the back.
FIELD_VIEWS = ((20.0, -90.0), (20.0, 90.0))


def face_log_stiffness(faces, edges, k_edge):
    """(F,) each face's mean log10 stiffness over its three edges (``edges`` (E, 2) in the order of
    :func:`jaxplush.model.mesh.unique_edges`, ``k_edge`` (E,) N/m, > 0)."""
    from jaxplush.model.mesh import edge_index
    faces = np.asarray(faces, np.int64)
    fe = np.stack([edge_index(edges, faces[:, a], faces[:, b]) for a, b in ((0, 1), (1, 2), (2, 0))], axis=1)
    if (fe < 0).any():
        raise JaxplushError("render_field: a face's edge is not among the edges given")
    return np.log10(np.asarray(k_edge, np.float64))[fe].mean(axis=1)


def render_field(vertices, faces, edges, fields, out, views=FIELD_VIEWS, dpi=100, title=None) -> str:
    """Draw stiffness fields on a mesh, side by side, as a still image (PNG, PDF, SVG, JPEG).

    Each face is coloured by the mean log10 stiffness of its three edges, on one logarithmic colour
    scale shared by every field (a colour bar in N/m), and shaded by its orientation to a light;
    each field is drawn from every view in ``views`` (front and back by default: a closed surface
    hides half of itself), one column per field, one row per view.

    Args:
      vertices: (V, 3) positions, m (world y up; drawn as :func:`render` draws).
      faces: (F, 3) int; edges: (E, 2) sorted unique edges (``Scene.edges``).
      fields: sequence of (label, (E,) stiffness) pairs, e.g. [("fitted", k_fit), ("true", k_true)].
      out: the image path; written atomically.
      views: (elevation, azimuth) pairs in degrees; dpi; title: above the figure.

    Returns:
      ``out``.
    """
    ext = os.path.splitext(os.fspath(out))[1].lower()
    if ext not in STILL_EXTENSIONS:
        raise JaxplushError(f"render_field: unknown image extension {ext!r}; expected one of "
                            f"{', '.join(STILL_EXTENSIONS)}")
    x = np.asarray(vertices, np.float64)
    faces = np.asarray(faces, np.int64)
    fields = [(str(label), np.asarray(k, np.float64)) for label, k in fields]
    if not fields:
        raise JaxplushError("render_field: no field to draw")
    for label, k in fields:
        if k.shape != (len(edges),) or not np.all(np.isfinite(k) & (k > 0)):
            raise JaxplushError(f"render_field: field {label!r} must hold {len(edges)} finite values > 0, got "
                                f"shape {k.shape}")
    values = [face_log_stiffness(faces, edges, k) for _, k in fields]
    lo = min(float(v.min()) for v in values)
    hi = max(float(v.max()) for v in values)
    if hi - lo < 1e-6:
        lo, hi = lo - 0.05, hi + 0.05
    from matplotlib import colormaps
    from matplotlib.cm import ScalarMappable
    from matplotlib.colors import LogNorm, Normalize
    cmap = colormaps["viridis"]
    norm = Normalize(lo, hi)
    tri = x[faces]
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-30)
    centre = 0.5 * (x.min(axis=0) + x.max(axis=0))
    half = 0.5 * float(np.max(x.max(axis=0) - x.min(axis=0))) * 1.05
    cols, rows = len(fields), len(views)
    fig = Figure(figsize=(3.2 * cols + 0.9, 3.1 * rows + 0.4), dpi=dpi)
    FigureCanvasAgg(fig)
    for r, (elev, azim) in enumerate(views):
        e, a = math.radians(elev), math.radians(azim)
        vp = np.array([math.cos(e) * math.cos(a), math.cos(e) * math.sin(a), math.sin(e)])
        view = np.array([vp[0], vp[2], -vp[1]])                          # plot -> world
        light = view + np.array([0.0, 1.2, 0.0]) + 0.4 * np.cross(np.array([0.0, 1.0, 0.0]), view)
        light /= np.linalg.norm(light)
        shade = _AMBIENT + (1 - _AMBIENT) * np.clip(normal @ light, 0.0, 1.0)
        for c, ((label, _), val) in enumerate(zip(fields, values)):
            ax = fig.add_subplot(rows, cols, r * cols + c + 1, projection="3d")
            rgb = np.asarray(cmap(norm(val)))[:, :3] * shade[:, None]
            mesh = Poly3DCollection(_to_plot(tri), facecolors=np.clip(rgb, 0, 1), edgecolors=[_EDGE_RGBA],
                                    linewidths=0.2)
            ax.add_collection3d(mesh)
            pc = _to_plot(centre)
            ax.set_xlim(pc[0] - half, pc[0] + half)
            ax.set_ylim(pc[1] - half, pc[1] + half)
            ax.set_zlim(pc[2] - half, pc[2] + half)
            ax.set_box_aspect((1, 1, 1))
            ax.view_init(elev=elev, azim=azim)
            ax.set_axis_off()
            ax.set_title(f"{label} ({'front' if r == 0 else 'back' if r == 1 else f'view {r + 1}'})", fontsize=9)
    fig.subplots_adjust(left=0.0, right=0.80, bottom=0.02, top=0.92 if title else 0.96, wspace=0.0, hspace=0.08)
    cax = fig.add_axes([0.82, 0.15, 0.025, 0.7])
    bar = fig.colorbar(ScalarMappable(norm=LogNorm(10 ** lo, 10 ** hi), cmap=cmap), cax=cax)
    bar.set_label("k (N/m), mean log over each face's edges", fontsize=7)
    bar.ax.tick_params(labelsize=7)
    if title:
        fig.suptitle(title, fontsize=10)

    def write(tmp):
        fig.savefig(tmp, format="jpeg" if ext in (".jpg", ".jpeg") else ext[1:], dpi=dpi)
    _atomic_write(out, ext, write)
    return os.fspath(out)
