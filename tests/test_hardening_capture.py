"""Bad input to ``jaxplush capture`` and ``jaxplush view --target`` (rows found by fuzzing): each is
refused with exit 2 and one stderr line that names the option, no traceback, no numpy
RuntimeWarning, and nothing written. One small trajectory (a 42-vertex ball, a few steps) serves
the whole module; every refusal happens before the ray casting, so nothing here compiles but
that trajectory's rollout."""

from __future__ import annotations

import contextlib
import io
import os
import sys
import warnings

import h5py
import numpy as np
import pytest

import jaxplush
from conftest import icosphere_text
from jaxplush import cli

EYE = "0,0.3,1"                     # 0.7 m in front of the ball (centre 0,0.3,0, radius 0.1 m)
VIEW = sys.modules["jaxplush.io.view"]


@pytest.fixture(scope="module")
def traj(tmp_path_factory):
    """(trajectory file, its scene text): the ball dropped for 20 steps, 3 frames."""
    d = tmp_path_factory.mktemp("hardening_capture")
    text = icosphere_text(1, 0.1, translate=(0, 0.3, 0), floor=0.0)
    scene = jaxplush.parse_scene(text, str(d / "ball.obj"))
    path = d / "ball.h5"
    jaxplush.simulate(scene, 20, 5e-4, 10, progress=False).save(path)
    return path, text


def run(*argv):
    """``cli.main(argv)`` in-process: (exit code, stdout, stderr, the warnings it raised)."""
    out, err = io.StringIO(), io.StringIO()
    with warnings.catch_warnings(record=True) as caught, contextlib.redirect_stdout(out), \
            contextlib.redirect_stderr(err):
        warnings.simplefilter("always")
        try:
            rc = cli.main([str(a) for a in argv])
        except SystemExit as e:         # argparse
            rc = e.code
    return rc, out.getvalue(), err.getvalue(), caught


def assert_refused(result, prefix, option, *phrases):
    """Exit 2, one stderr line 'PREFIX: error: OPTION...' holding the phrases, no traceback or RuntimeWarning."""
    rc, _, err, caught = result
    assert rc == 2, err
    assert err.endswith("\n") and err.count("\n") == 1, err
    assert err.startswith(f"{prefix}: error: {option}"), err
    assert "Traceback" not in err and "RuntimeWarning" not in err
    assert not [w for w in caught if issubclass(w.category, RuntimeWarning)], [str(w.message) for w in caught]
    for p in phrases:
        assert p in err, (p, err)


def nothing_written(d):
    return os.listdir(d) == []


# ---------------------------------------------------------------------------------- row 1: --noise


def test_capture_refuses_noise_beyond_the_scene_extent(traj, tmp_path):
    out = tmp_path / "scan.h5"
    r = run("capture", traj[0], "--eye", EYE, "--noise", "1e308", "--out", out)
    assert_refused(r, "jaxplush capture", "--noise must be at most the scene's extent", "got 1e+308",
                   "the diagonal of the box holding every vertex of every frame")
    assert nothing_written(tmp_path)


def test_capture_never_writes_non_finite_points(traj, tmp_path, monkeypatch):
    """The check of the result before writing: a capture with an inf coordinate is refused."""
    from jaxplush.io import capture

    def overflowing(frames, faces, camera, **kw):
        pts = np.full((len(frames), 4, 3), np.nan)
        pts[:, :2] = 0.1
        pts[1, 1, 2] = np.inf
        return capture.Capture(points=pts, counts=np.full(len(frames), 2), camera=camera, noise=kw["noise"],
                               dropout=kw["dropout"])
    monkeypatch.setattr(capture, "depth_capture", overflowing)
    out = tmp_path / "scan.h5"
    r = run("capture", traj[0], "--eye", EYE, "--noise", "0.01", "--out", out)
    assert_refused(r, "jaxplush capture", "--noise 0.01", "non-finite coordinates (first in frame 1)",
                   "nothing written")
    assert nothing_written(tmp_path)


def test_track_capture_refuses_noise_that_overflows_without_a_runtime_warning():
    from jaxplush.io.capture import NonFiniteCapture, track_capture
    m = jaxplush.parse_scene(icosphere_text(1, 0.1), "<ball>")
    x = np.stack([m.vertices, m.vertices])
    with warnings.catch_warnings():
        warnings.simplefilter("error")                   # a RuntimeWarning would fail here
        with pytest.raises(NonFiniteCapture, match="non-finite position"):
            track_capture(x, m.faces, 5, noise=1e308, seed=1)


def test_the_cli_limits_are_the_capture_modules():
    from jaxplush.io import capture
    assert (cli.MAX_NOISE_EXTENTS, cli.CAMERA_RANGE) == (capture.MAX_NOISE_EXTENTS, capture.CAMERA_RANGE)


# -------------------------------------------------------------------- row 2: the camera's options


@pytest.mark.parametrize("args, option, phrases", [
    (("--seed", "-1"), "--seed must be a non-negative integer", ("got -1",)),
    (("--fov", "0"), "--fov must be in (0, 180) degrees", ("got 0",)),
    (("--fov", "180"), "--fov must be in (0, 180) degrees", ("got 180",)),
    (("--look-at", "0,0,1e300"), "--look-at 0,0,1e300 is too far", ("1e+300 m from its centre",)),
    (("--look-at", "1.5e308,-1.5e308,1.5e308"), "--look-at 1.5e308,-1.5e308,1.5e308 is too far", ("overflows",)),
    (("--eye", "0,0,-1e300"), "--eye 0,0,-1e300 is too far", ("more than 10000 times its extent",)),
    (("--look-at", "0,0.3,0", "--up", "0,0,1"), "--up 0,0,1 must not be parallel to the viewing direction",
     ("from --eye 0,0.3,1 to --look-at 0,0.3,0",)),
    (("--eye", "0,2,0"), "--up 0,1,0 must not be parallel to the viewing direction",
     ("from --eye 0,2,0 to the default look-at point", "(the first frame's centre)")),
    (("--up", "0,0,0"), "--up must be a non-zero direction", ()),
    (("--look-at", EYE), f"--eye {EYE} is at the look-at point", ("no viewing direction",)),
    (("--dropout", "1"), "--dropout must lie in [0, 1)", ()),
], ids=["seed", "fov-0", "fov-180", "look-at-far", "look-at-overflow", "eye-far", "up-parallel-look-at",
        "up-parallel-default-look-at", "up-zero", "eye-at-look-at", "dropout"])
def test_capture_refuses_a_bad_camera_option_naming_it(traj, tmp_path, args, option, phrases):
    args = ("--eye", EYE) * ("--eye" not in args) + args
    out = tmp_path / "scan.h5"
    r = run("capture", traj[0], *args, "--out", out)
    assert_refused(r, "jaxplush capture", option, *phrases)
    assert nothing_written(tmp_path)


# ------------------------------------------------------------------- row 3: view --target of another scene


def _fit_file(d, traj):
    """A FIT.h5 of the module's trajectory as jaxplush-fit lays it out (scene text, fitted rollout,
    target path), its target recorded as the trajectory itself."""
    path, text = traj
    with h5py.File(path) as f:
        pos, times = f["positions"][()], f["times"][()]
    fit = d / "FIT.h5"
    with h5py.File(fit, "w") as f:
        f.attrs["status"], f.attrs["scene"], f.attrs["scene_path"] = "converged", text, "ball.obj"
        f.attrs["target_path"] = str(path)
        f["fitted/positions"], f["fitted/steps"], f["fitted/times"] = pos, np.arange(len(pos)) * 10, times
    return fit, pos, times


def _target(path, kind, data, times, **fields):
    with h5py.File(path, "w") as f:
        f[kind], f["times"] = data, times
        for name, value in fields.items():
            if name == "scene":
                f.attrs["scene"] = value
            elif name == "object_names":
                f.create_dataset(name, data=np.asarray(value, dtype=object), dtype=h5py.string_dtype("utf-8"))
            else:
                f[name] = value
    return path


@pytest.mark.parametrize("case", ["vertex count", "object names", "stored scene"])
def test_view_refuses_a_target_of_another_scene(traj, tmp_path, monkeypatch, case):
    monkeypatch.setattr(VIEW, "require_viser", lambda: None)      # the target is checked before viser is used
    inputs = tmp_path / "in"
    inputs.mkdir()
    fit, pos, times = _fit_file(inputs, traj)
    other = inputs / "other.h5"
    if case == "vertex count":                  # positions of a 162-vertex ball
        _target(other, "positions", np.zeros((len(times), 162, 3)), times)
        phrases = ("its 'positions' hold 162 vertices but FIT.h5 has 42",)
    elif case == "object names":                # a scan that records another scene's objects
        _target(other, "points", pos[:, ::2], times, object_names=["cube"])
        phrases = ("its objects ['cube'] differ from FIT.h5's ['ball']",)
    else:                                       # a scan of the same ball dropped from 0.6 m
        moved = icosphere_text(1, 0.1, translate=(0, 0.6, 0), floor=0.0)
        _target(other, "points", pos[:, ::2] + [0, 0.3, 0], times, scene=moved, object_names=["ball"])
        phrases = ("places object 'ball' elsewhere than FIT.h5's", "0.3 m apart")
    out = tmp_path / "view.html"
    r = run("view", fit, "--target", other, "--html", out)
    assert_refused(r, "jaxplush view", f"--target {other}: ", "belongs to another scene", *phrases)
    assert os.listdir(tmp_path) == ["in"] and sorted(os.listdir(inputs)) == ["FIT.h5", "other.h5"]


@pytest.mark.skipif(not __import__("importlib").util.find_spec("viser"), reason="viser not installed")
def test_view_still_shows_a_target_that_belongs(traj, tmp_path):
    """The trajectory itself, and a scan of it recording the same scene with other parameters."""
    fit, pos, times = _fit_file(tmp_path, traj)
    stiffer = icosphere_text(1, 0.1, k=300.0, translate=(0, 0.3, 0), floor=0.0)
    scan = _target(tmp_path / "scan.h5", "points", pos[:, ::2], times, scene=stiffer, object_names=["ball"])
    for target in (traj[0], scan):
        out = tmp_path / "view.html"
        rc, stdout, err, _ = run("view", fit, "--target", target, "--html", out)
        assert rc == 0, err
        assert f"target {target}: {len(times)} frames" in stdout and out.exists()
        os.remove(out)


@pytest.mark.skipif(not __import__("importlib").util.find_spec("viser"), reason="viser not installed")
def test_view_leaves_out_a_recorded_fit_target_of_another_scene_with_a_note(traj, tmp_path):
    fit, pos, times = _fit_file(tmp_path, traj)
    other = _target(tmp_path / "other.h5", "points", pos[:, ::2], times, object_names=["cube"])
    with h5py.File(fit, "a") as f:
        f.attrs["target_path"] = str(other)
    rc, stdout, err, _ = run("view", fit, "--html", tmp_path / "view.html")
    assert rc == 0 and err == "", err
    assert f"the fit's target {other} does not belong to {fit}" in stdout and "--target names the right one" in stdout
