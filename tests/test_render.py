"""Tests for jaxplush.io.render on small synthetic trajectory files."""

from __future__ import annotations

import os

import h5py
import numpy as np
import pytest
import trimesh
from PIL import Image

from jaxplush.errors import JaxplushError, TrajectoryError
from jaxplush.io.render import render

N_FRAMES = 6
FLOOR = 0.0


def _synthetic_positions():
    """An icosphere (radius 0.1) falling onto the floor at y=0 and squashing, plus a small resting ball."""
    sphere = trimesh.creation.icosphere(subdivisions=1, radius=0.1)
    small = trimesh.creation.icosphere(subdivisions=1, radius=0.05)
    v0, f0 = np.asarray(sphere.vertices), np.asarray(sphere.faces)
    v1, f1 = np.asarray(small.vertices), np.asarray(small.faces)
    frames = []
    for k in range(N_FRAMES):
        s = k / (N_FRAMES - 1)
        squash = 1.0 - 0.3 * max(0.0, s - 0.6) / 0.4  # squash during the last frames
        scale = np.array([1 / np.sqrt(squash), squash, 1 / np.sqrt(squash)])
        centre_y = FLOOR + max(0.1 * squash, 0.4 * (1 - s) + 0.1)
        a = v0 * scale + [0.0, centre_y, 0.0]
        b = v1 + [0.25, FLOOR + 0.05, 0.1]
        frames.append(np.concatenate([a, b]))
    positions = np.stack(frames)
    faces = np.concatenate([f0, f1 + len(v0)])
    object_id = np.concatenate([np.zeros(len(v0), int), np.ones(len(v1), int)])
    return positions, faces, object_id


def write_trajectory(path, positions=None, faces=None, object_id=None, floor=FLOOR, **extra):
    """Write a trajectory file in the jaxplush schema; ``extra`` overrides/adds datasets."""
    p, fc, oid = _synthetic_positions()
    positions = p if positions is None else positions
    faces = fc if faces is None else faces
    object_id = oid if object_id is None else object_id
    with h5py.File(path, "w") as f:
        data = {
            "positions": positions,
            "times": np.arange(len(positions)) * 0.05,
            "faces": faces,
            "object_id": object_id,
        }
        data.update(extra)
        for name, value in data.items():
            if value is not None:
                f.create_dataset(name, data=value)
        f.create_dataset("object_names", data=["ball", "pebble"], dtype=h5py.string_dtype())
        f.attrs["dt"] = 0.001
        f.attrs["save_every"] = 50
        f.attrs["floor"] = floor
        f.attrs["gravity"] = [0.0, -9.81, 0.0]
    return path


@pytest.fixture
def traj(tmp_path):
    return write_trajectory(tmp_path / "traj.h5")


def _only(tmp_path, *names):
    """Assert that the directory holds exactly these files (no temp leftovers)."""
    assert sorted(os.listdir(tmp_path)) == sorted(names)


def test_gif_animation(traj, tmp_path):
    out = tmp_path / "anim.gif"
    result = render(traj, out, dpi=40)
    assert result == str(out)
    with Image.open(out) as im:
        assert im.format == "GIF"
        assert im.n_frames == N_FRAMES
    _only(tmp_path, "traj.h5", "anim.gif")


def test_gif_subsamples_keeping_first_and_last(traj, tmp_path):
    out = tmp_path / "short.gif"
    render(traj, out, max_frames=3, dpi=30)
    with Image.open(out) as im:
        assert im.n_frames == 3


def _gif_delays(path):
    with Image.open(path) as im:
        out = []
        for i in range(im.n_frames):
            im.seek(i)
            out.append(im.info["duration"])
        return out


def test_gif_plays_in_real_time_and_says_what_it_drew(traj, tmp_path):
    """Frames 50 ms apart in simulated time are shown 50 ms each; the report names the frames kept."""
    lines = []
    render(traj, tmp_path / "rt.gif", dpi=30, report=lines.append)
    assert _gif_delays(tmp_path / "rt.gif") == [50] * N_FRAMES
    assert lines == [f"drawing all {N_FRAMES} frames: 0.25 s of simulation played in 0.25 s (real time)"]


def test_gif_frame_cap_is_reported_and_keeps_real_time(tmp_path):
    """201 frames 10 ms apart: a GIF shows at most 50 frames per simulated second, so 101 are
    drawn, 20 ms each (real time), and the report says 101 of 201."""
    p, f, oid = _synthetic_positions()
    pos = np.repeat(p, [41, 40, 40, 40, 40, 0], axis=0)       # 201 frames
    path = write_trajectory(tmp_path / "long.h5", positions=pos, times=np.arange(201) * 0.01)
    lines = []
    render(path, tmp_path / "long.gif", dpi=20, report=lines.append)
    delays = _gif_delays(tmp_path / "long.gif")
    assert len(delays) == 101 and set(delays) == {20}
    assert "101 of 201 frames" in lines[0] and "(real time)" in lines[0]
    lines.clear()
    render(path, tmp_path / "capped.gif", dpi=20, max_frames=11, report=lines.append)
    assert _gif_delays(tmp_path / "capped.gif") == [200] * 11      # fewer frames, still real time
    assert "11 of 201 frames" in lines[0]
    lines.clear()
    render(path, tmp_path / "fixed.gif", dpi=20, max_frames=250, fps=25, report=lines.append)
    assert _gif_delays(tmp_path / "fixed.gif") == [40] * 201
    assert lines == ["drawing all 201 frames at 25 fps: 8.04 s of playback"]


def test_gif_delays_keep_the_total_when_gaps_are_not_whole_hundredths(tmp_path):
    p, f, oid = _synthetic_positions()
    path = write_trajectory(tmp_path / "odd.h5", times=np.arange(N_FRAMES) * 0.025)
    render(path, tmp_path / "odd.gif", dpi=20)
    delays = _gif_delays(tmp_path / "odd.gif")
    assert set(delays) <= {20, 30} and abs(sum(delays[:-1]) - 125) <= 5    # 5 gaps of 25 ms, rounded as a whole


def test_png_still_last_frame(traj, tmp_path):
    out = tmp_path / "still.png"
    assert render(traj, out, frame=-1) == str(out)
    with Image.open(out) as im:
        assert im.format == "PNG"
        assert im.size == (640, 600)
    _only(tmp_path, "traj.h5", "still.png")


def test_still_without_floor_or_optional_data(tmp_path):
    positions, faces, _ = _synthetic_positions()
    path = tmp_path / "bare.h5"
    with h5py.File(path, "w") as f:  # only the required datasets
        f["positions"] = positions
        f["faces"] = faces
    out = tmp_path / "bare.svg"
    render(path, out, frame=2)
    assert out.read_text().lstrip().startswith("<?xml")


@pytest.mark.parametrize("name", ["out.txt", "out", "out.gif"])
def test_bad_extension(traj, tmp_path, name):
    # .gif with frame= is also refused: stills need an image extension.
    frame = 0 if name == "out.gif" else None
    with pytest.raises(JaxplushError, match="extension"):
        render(traj, tmp_path / name, frame=frame)
    _only(tmp_path, "traj.h5")


def test_png_without_frame_is_refused(traj, tmp_path):
    with pytest.raises(JaxplushError, match="frame="):
        render(traj, tmp_path / "x.png")
    _only(tmp_path, "traj.h5")


def test_nan_positions(tmp_path):
    positions, _, _ = _synthetic_positions()
    positions[3, 5, 1] = np.nan
    path = write_trajectory(tmp_path / "nan.h5", positions=positions)
    for out, frame in [("a.gif", None), ("b.png", 0)]:
        with pytest.raises(TrajectoryError, match="non-finite.*frame 3"):
            render(path, tmp_path / out, frame=frame)
    _only(tmp_path, "nan.h5")


@pytest.mark.parametrize("frame", [N_FRAMES, -N_FRAMES - 1])
def test_frame_out_of_range(traj, tmp_path, frame):
    with pytest.raises(TrajectoryError, match="out of range"):
        render(traj, tmp_path / "x.png", frame=frame)
    _only(tmp_path, "traj.h5")


def test_missing_file(tmp_path):
    with pytest.raises(TrajectoryError, match="no such file"):
        render(tmp_path / "nope.h5", tmp_path / "x.gif")
    _only(tmp_path)


def test_not_hdf5(tmp_path):
    path = tmp_path / "fake.h5"
    path.write_text("hello")
    with pytest.raises(TrajectoryError, match="HDF5"):
        render(path, tmp_path / "x.gif")
    _only(tmp_path, "fake.h5")


@pytest.mark.parametrize(
    "kwargs, message",
    [
        ({"positions": None}, "missing dataset 'positions'"),
        ({"faces": None}, "missing dataset 'faces'"),
        ({"positions": np.zeros((6, 10, 2))}, r"positions must have shape \[T, N, 3\]"),
        ({"faces": np.zeros((4, 4), int)}, r"faces must have shape \[F, 3\]"),
        ({"faces": np.array([[0, 1, 9999]])}, "face vertex indices"),
        ({"faces": np.array([[0.5, 1, 2]])}, "faces must hold integers"),
        ({"object_id": np.zeros(3, int)}, "object_id must have shape"),
        ({"times": np.zeros(2)}, "times must have shape"),
    ],
)
def test_malformed_files(tmp_path, kwargs, message):
    path = tmp_path / "bad.h5"
    with h5py.File(path, "w") as f:
        p, fc, oid = _synthetic_positions()
        data = {"positions": p, "faces": fc, "object_id": oid, "times": np.arange(len(p)) * 0.05}
        data.update(kwargs)
        for name, value in data.items():
            if value is not None:
                f[name] = value
    with pytest.raises(TrajectoryError, match=message):
        render(path, tmp_path / "x.gif")
    _only(tmp_path, "bad.h5")


def test_failed_write_leaves_nothing(traj, tmp_path, monkeypatch):
    import jaxplush.io.render as mod

    def boom(*args, **kwargs):
        raise RuntimeError("disk on fire")

    monkeypatch.setattr(mod, "_render_still", boom)
    out = tmp_path / "x.png"
    out.write_bytes(b"old")
    with pytest.raises(RuntimeError):
        render(traj, out, frame=0)
    assert out.read_bytes() == b"old"  # previous output untouched
    _only(tmp_path, "traj.h5", "x.png")


def test_mp4_without_ffmpeg(traj, tmp_path, monkeypatch):
    from matplotlib import animation

    monkeypatch.setattr(animation.writers, "is_available", lambda name: False)
    with pytest.raises(JaxplushError, match="ffmpeg was not found.*gif"):
        render(traj, tmp_path / "x.mp4")
    _only(tmp_path, "traj.h5")
