"""Tests for the command line (jaxplush.cli): info, simulate (HDF5 schema), render, and the
error paths (clear message, exit code, no traceback, no partial output).

The CLI runs in-process through ``jaxplush.cli.main`` (fast: one JAX process), plus one real
``python -m jaxplush simulate`` subprocess for the exit code and a traceback-free stderr."""

from __future__ import annotations

import contextlib
import io
import math
import os
import re
import subprocess
import sys

import h5py
import numpy as np
import pytest
import trimesh
from PIL import Image

import jaxplush
from jaxplush import cli

STEPS = 200
SAVE_EVERY = 30


def ball_text(k=100.0, mass=0.05, nmol=0.0015, dashpot=0.02, height=0.3, floor=0.0):
    """A gas-filled 42-vertex icosphere (radius 0.1 m) above a floor."""
    m = trimesh.creation.icosphere(subdivisions=1, radius=0.1)
    lines = ["# small CLI test scene", f"floor {floor!r}", "o ball", f"k_structural {k!r}",
             f"total_weight {mass!r}", f"nmol {nmol!r}", f"dashpot {dashpot!r}", f"translate 0 {height!r} 0"]
    lines += [f"v {a!r} {b!r} {c!r}" for a, b, c in m.vertices.tolist()]
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in m.faces.tolist()]
    lines.append("END_OBJECT")
    return "\n".join(lines) + "\n"


def run_cli(*argv):
    """Run ``jaxplush.cli.main(argv)`` in-process; return (exit code, stdout, stderr)."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            rc = cli.main([str(a) for a in argv])
        except SystemExit as e:  # argparse usage errors
            rc = e.code
    return rc, out.getvalue(), err.getvalue()


def assert_clean_error(rc, stderr, code=cli.EXIT_USAGE, *phrases):
    assert rc == code, stderr
    assert "Traceback" not in stderr
    assert "error:" in stderr
    for p in phrases:
        assert p in stderr, (p, stderr)


@pytest.fixture(scope="module")
def work(tmp_path_factory):
    """A directory with the small scene, its `info` output and one simulated trajectory."""
    d = tmp_path_factory.mktemp("cli")
    scene = d / "ball.obj"
    scene.write_text(ball_text())
    rc, out, err = run_cli("info", scene, "--exact")
    assert rc == 0, err
    m = re.search(r"largest stable dt ([0-9.eE+-]+) s", out)
    assert m, out
    dt_max = float(m.group(1))
    dt = 0.5 * dt_max
    traj = d / "ball.h5"
    rc, sim_out, sim_err = run_cli("simulate", scene, "--steps", STEPS, "--dt", repr(dt),
                                   "--save-every", SAVE_EVERY, "--out", traj, "--quiet")
    assert rc == 0, sim_err
    return dict(dir=d, scene=scene, info=out, dt_max=dt_max, dt=dt, traj=traj, sim_out=sim_out, sim_err=sim_err)


def fresh_dir(tmp_path, text=None):
    """tmp_path holding only the small scene (or ``text``); returns the scene path."""
    scene = tmp_path / "scene.obj"
    scene.write_text(ball_text() if text is None else text)
    return scene


def listing(d):
    return sorted(os.listdir(d))


# ----------------------------------------------------------------------------------- info

def test_info_counts_and_stable_dt(work):
    out = work["info"]
    assert "1 object(s), 42 vertices, 120 springs, 80 faces" in out
    assert "object 0 'ball': 42 vertices, 120 edges, 80 faces, 0 fixed" in out
    assert "floor y = 0 m" in out and "temperature 293.15 K" in out
    assert "k_structural 100 N/m" in out and "nmol 0.0015" in out
    dt_max = work["dt_max"]
    assert math.isfinite(dt_max) and 0 < dt_max < 0.1
    # The closed-form bound is safe (below the power-iteration limit) and not far below it.
    b = float(re.search(r"every dt <= ([0-9.eE+-]+) s is stable", out).group(1))
    assert 0.5 * dt_max < b <= dt_max


def test_info_checks_a_given_dt(work):
    rc, out, _ = run_cli("info", work["scene"], "--dt", repr(work["dt"]), "--exact")
    assert rc == 0 and "is within the estimated limit" in out
    rc, out, _ = run_cli("info", work["scene"], "--dt", repr(3 * work["dt_max"]), "--exact")
    assert rc == 0 and "is ABOVE the estimated limit" in out
    rc, out, _ = run_cli("info", work["scene"], "--dt", repr(3 * work["dt_max"]))
    assert rc == 0 and "above the safe bound (use --exact to decide)" in out


def test_info_compiles_nothing_without_exact(work, monkeypatch):
    """Plain ``info`` prints the closed-form bound: no power iteration (which compiles) is run."""
    from jaxplush.stepping import stability

    def refuse(*a, **k):
        raise AssertionError("info ran the power iteration")
    monkeypatch.setattr(stability, "estimate", refuse)
    rc, out, err = run_cli("info", work["scene"], "--dt", repr(work["dt"]))
    assert rc == 0, err
    assert "is within the safe bound" in out and "--exact estimates it" in out


def test_info_bad_scene(tmp_path):
    scene = fresh_dir(tmp_path, ball_text().replace("nmol 0.0015", "nmol -1"))
    rc, out, err = run_cli("info", scene)
    assert_clean_error(rc, err, cli.EXIT_USAGE, f"{scene}:6:", "must be > 0")
    assert out == ""


# ------------------------------------------------------------------------------- simulate

def test_simulate_writes_schema(work):
    path, dt = work["traj"], work["dt"]
    assert listing(work["dir"]) == ["ball.h5", "ball.obj"]  # no temp files left behind
    assert "wrote" in work["sim_out"] and str(path) in work["sim_out"]
    n_frames = 1 + math.ceil(STEPS / SAVE_EVERY)
    scene = jaxplush.load_scene(work["scene"])
    with h5py.File(path, "r") as f:
        pos, times, faces = f["positions"][()], f["times"][()], f["faces"][()]
        assert pos.shape == (n_frames, 42, 3)
        assert times.shape == (n_frames,)
        assert faces.shape == (80, 3) and np.issubdtype(faces.dtype, np.integer)
        np.testing.assert_array_equal(faces, scene.faces)
        oid = f["object_id"][()]
        assert oid.shape == (42,) and (oid == 0).all()
        names = [n.decode() if isinstance(n, bytes) else str(n) for n in f["object_names"][()]]
        assert names == ["ball"]
        a = dict(f.attrs)
    assert np.isfinite(pos).all()
    np.testing.assert_allclose(pos[0], scene.vertices, atol=1e-6)
    assert times[0] == 0.0
    np.testing.assert_allclose(times[-1], STEPS * dt, rtol=1e-12)
    np.testing.assert_allclose(times[:-1], np.arange(n_frames - 1) * SAVE_EVERY * dt, rtol=1e-12)
    assert np.all(np.diff(times) > 0)
    np.testing.assert_allclose(a["dt"], dt, rtol=1e-12)
    assert a["integrator"] == "verlet"
    assert int(a["steps"]) == STEPS and int(a["save_every"]) == SAVE_EVERY
    for key, val in (("k_structural", 100.0), ("damping", 0.0), ("nmol", 0.0015), ("total_weight", 0.05),
                     ("dashpot", 0.02)):
        # the values the run used: float32-rounded without --x64
        np.testing.assert_allclose(np.atleast_1d(a[key]), [val], rtol=1e-6, err_msg=key)
    assert a["jaxplush_version"] == jaxplush.__version__
    assert a["scene"] == work["scene"].read_text()
    assert float(a["floor"]) == 0.0
    # The ball falls: its centre moves down, and it stays above the (penalty) floor within reason.
    assert pos[-1, :, 1].mean() < pos[0, :, 1].mean()
    assert pos[:, :, 1].min() > -0.05


def test_simulate_loads_back(work):
    t = jaxplush.load_trajectory(work["traj"])
    assert t["positions"].shape[0] == 1 + math.ceil(STEPS / SAVE_EVERY)
    assert t["object_names"] == ["ball"]


def test_simulate_subprocess(work, tmp_path):
    """One real process: exit code 0, no traceback, a progress bar allowed on stderr."""
    out = tmp_path / "sub.h5"
    env = dict(os.environ, JAX_PLATFORMS=os.environ.get("JAX_PLATFORMS", "cpu"))
    proc = subprocess.run([sys.executable, "-m", "jaxplush", "simulate", str(work["scene"]), "--steps", "40",
                           "--dt", repr(work["dt"]), "--out", str(out)],
                          capture_output=True, text=True, env=env, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert "Traceback" not in proc.stderr
    # stderr is a pipe, not a terminal: the progress bar writes its final line, not 40 redraws
    assert "\r" not in proc.stderr and proc.stderr.count("simulate [") == 1, proc.stderr
    assert "wrote" in proc.stdout
    with h5py.File(out, "r") as f:
        assert f["positions"].shape[1:] == (42, 3)
        assert int(f.attrs["steps"]) == 40
    assert listing(tmp_path) == ["sub.h5"]


@pytest.mark.parametrize("edit, line, phrase", [
    (lambda t: t.replace("k_structural 100.0", "k_structural -3"), 4, "must be >= 0"),
    (lambda t: t.replace("floor 0.0", "flooor 0.0"), 2, "unknown keyword"),
    (lambda t: t.replace("\nf 1 ", "\nf 1 1 "), None, "degenerate"),
    (lambda t: t.replace("floor 0.0", "floor 0.5"), 2, "below the floor"),
])
def test_simulate_bad_scene(tmp_path, edit, line, phrase):
    scene = fresh_dir(tmp_path, edit(ball_text()))
    before = listing(tmp_path)
    rc, out, err = run_cli("simulate", scene, "--steps", 10, "--dt", "1e-4", "--out", tmp_path / "o.h5", "--quiet")
    if line is None:
        line = next(i + 1 for i, ln in enumerate(scene.read_text().splitlines()) if ln.startswith("f 1 1 "))
    assert_clean_error(rc, err, cli.EXIT_USAGE, f"{scene}:{line}: ", phrase)
    assert listing(tmp_path) == before  # no output, no temp file
    assert out == ""


def test_simulate_missing_scene(tmp_path):
    rc, _, err = run_cli("simulate", tmp_path / "nope.obj", "--steps", 10, "--dt", "1e-4", "--out",
                         tmp_path / "o.h5", "--quiet")
    assert_clean_error(rc, err, cli.EXIT_USAGE, "nope.obj: no such file")
    assert listing(tmp_path) == []


def test_simulate_binary_scene(tmp_path):
    scene = tmp_path / "garbage.obj"
    scene.write_bytes(b"\x7fELF\x02\x01\x01\x00\x00\x00")
    rc, _, err = run_cli("simulate", scene, "--steps", 10, "--dt", "1e-4", "--out", tmp_path / "o.h5", "--quiet")
    assert_clean_error(rc, err, cli.EXIT_USAGE, f"{scene}:1: binary data")
    assert listing(tmp_path) == ["garbage.obj"]


@pytest.mark.parametrize("args, phrase", [
    (("--dt", "0", "--steps", "10"), "--dt must be a positive number"),
    (("--dt=-1e-4", "--steps", "10"), "--dt must be a positive number"),
    (("--dt", "-1", "--steps", "10"), "--dt must be a positive number"),
    (("--dt", "-5e-4", "--steps", "10"), "--dt must be a positive number"),   # exponent form, not an option
    (("--dt", "-.5", "--steps", "10"), "--dt must be a positive number"),
    (("--dt", "nan", "--steps", "10"), "--dt must be a positive number"),
    (("--dt", "inf", "--steps", "10"), "--dt must be a positive number"),
    (("--dt", "1e-4", "--steps", "0"), "--steps must be between 1 and"),
    (("--dt", "1e-4", "--steps", "-5"), "--steps must be between 1 and"),
    (("--dt", "1e-4", "--steps", "3000000000"), "--steps must be between 1 and 2,147,483,647"),
    (("--dt", "1e-4", "--steps", "2000000000", "--save-every", "1"), "would write 2,000,000,002 frames"),
    (("--dt", "1e-4", "--steps", "10", "--save-every", "0"), "--save-every must be >= 1"),
    (("--dt", "1e-4", "--steps", "10", "--integrator", "euler-ish"), "unknown integrator 'euler-ish'"),
])
def test_simulate_bad_arguments(tmp_path, args, phrase):
    scene = fresh_dir(tmp_path)
    rc, _, err = run_cli("simulate", scene, *args, "--out", tmp_path / "o.h5", "--quiet")
    assert_clean_error(rc, err, cli.EXIT_USAGE, phrase)
    assert listing(tmp_path) == ["scene.obj"]


@pytest.mark.parametrize("args", [("--dt", "abc", "--steps", "10"), ("--dt", "1e-4", "--steps", "1.5"),
                                  ("--dt", "1e-4")])
def test_simulate_unparseable_arguments(tmp_path, args):
    scene = fresh_dir(tmp_path)
    rc, _, err = run_cli("simulate", scene, *args, "--out", tmp_path / "o.h5", "--quiet")
    assert rc == 2 and "Traceback" not in err and "error:" in err
    assert listing(tmp_path) == ["scene.obj"]


def test_simulate_output_directory_missing(tmp_path):
    scene = fresh_dir(tmp_path)
    out = tmp_path / "no" / "such" / "dir" / "o.h5"
    rc, _, err = run_cli("simulate", scene, "--steps", 10, "--dt", "1e-4", "--out", out, "--quiet")
    assert_clean_error(rc, err, cli.EXIT_USAGE, "does not exist")
    assert listing(tmp_path) == ["scene.obj"]


def test_simulate_output_extension(tmp_path):
    scene = fresh_dir(tmp_path)
    rc, _, err = run_cli("simulate", scene, "--steps", 10, "--dt", "1e-4", "--out", tmp_path / "o.txt", "--quiet")
    assert_clean_error(rc, err, cli.EXIT_USAGE, "must end in .h5")
    assert listing(tmp_path) == ["scene.obj"]


def test_simulate_explodes(work, tmp_path):
    """dt 20x the stable limit: exit 3, message names the step and the object, nothing written."""
    scene = fresh_dir(tmp_path)
    out = tmp_path / "boom.h5"
    rc, stdout, err = run_cli("simulate", scene, "--steps", STEPS, "--dt", repr(20 * work["dt_max"]),
                              "--out", out, "--quiet")
    assert_clean_error(rc, err, cli.EXIT_FAILED, "object 0 ('ball')")
    m = re.search(r"simulation failed at step (\d+)", err)
    assert m, err
    assert 1 <= int(m.group(1)) <= STEPS
    assert "stable verlet step limit" in err  # the hint
    assert not out.exists()
    assert listing(tmp_path) == ["scene.obj"]
    assert "wrote" not in stdout


def test_simulate_overwrites_atomically(work, tmp_path):
    """An existing output survives a failed run untouched."""
    scene = fresh_dir(tmp_path)
    out = tmp_path / "keep.h5"
    out.write_bytes(b"old contents")
    rc, _, err = run_cli("simulate", scene, "--steps", STEPS, "--dt", repr(20 * work["dt_max"]),
                         "--out", out, "--quiet")
    assert rc == cli.EXIT_FAILED, err
    assert out.read_bytes() == b"old contents"
    assert listing(tmp_path) == ["keep.h5", "scene.obj"]


# --------------------------------------------------------------------------------- render

def test_render_last_frame(work, tmp_path):
    png = tmp_path / "last.png"
    rc, out, err = run_cli("render", work["traj"], "--out", png, "--frame", "-1")
    assert rc == 0, err
    assert "Traceback" not in err
    with Image.open(png) as im:
        assert im.format == "PNG" and im.size[0] > 100 and im.size[1] > 100
    assert listing(tmp_path) == ["last.png"]


def test_render_missing_trajectory(tmp_path):
    rc, _, err = run_cli("render", tmp_path / "missing.h5", "--out", tmp_path / "x.png", "--frame", "-1")
    assert_clean_error(rc, err, cli.EXIT_USAGE, "missing.h5")
    assert listing(tmp_path) == []


def test_render_not_hdf5(tmp_path):
    bad = tmp_path / "bad.h5"
    bad.write_text("not hdf5")
    rc, _, err = run_cli("render", bad, "--out", tmp_path / "x.png", "--frame", "0")
    assert_clean_error(rc, err, cli.EXIT_USAGE, "bad.h5")
    assert listing(tmp_path) == ["bad.h5"]


def test_render_frame_out_of_range(work, tmp_path):
    rc, _, err = run_cli("render", work["traj"], "--out", tmp_path / "x.png", "--frame", "999")
    assert_clean_error(rc, err, cli.EXIT_USAGE)
    assert listing(tmp_path) == []


# ------------------------------------------------------------------------------- progress, arguments

def test_attach_negative_values():
    from jaxplush.cliargs import attach_negative_values
    assert attach_negative_values(["--dt", "-5e-4", "--steps", "10"]) == ["--dt=-5e-4", "--steps", "10"]
    assert attach_negative_values(["--lr", "-1E+2", "-x"]) == ["--lr=-1E+2", "-x"]
    # not a number, or already joined, or a short option: left to argparse
    assert attach_negative_values(["--out", "-o.h5", "--dt=-1"]) == ["--out", "-o.h5", "--dt=-1"]
    assert attach_negative_values(["-n", "-5"]) == ["-n", "-5"]


def test_progress_final_line_says_where_and_why_it_stopped():
    """A fit that converges at iteration 11 of 200 must not leave the bar at 5.5% with an ETA."""
    from jaxplush.progress import Progress
    buf = io.StringIO()
    with Progress(200, "fit", stream=buf, unit="it", interactive=True) as bar:
        for _ in range(11):
            bar.update(1, extra="loss 0.1")
        bar.finish("converged")
    final = buf.getvalue().rsplit("\r", 1)[-1]
    assert "stopped at 11/200 it after" in final and ": converged" in final and "eta" not in final
    buf = io.StringIO()
    with Progress(40, "simulate", stream=buf, interactive=True) as bar:
        bar.update(40)
    final = buf.getvalue().rsplit("\r", 1)[-1]
    assert final.startswith("simulate [" + "#" * 30 + "] 40 steps in") and "eta" not in final


def test_progress_in_a_log_is_plain_lines_never_redraws(monkeypatch):
    """Where stderr is not a terminal (a CI log, ``2> fit.log``, a notebook), the bar writes plain
    lines, no carriage returns: a short stage leaves exactly its final line, and a long one at most
    one line per interval."""
    from jaxplush import progress
    buf = io.StringIO()                                   # not a terminal
    with progress.Progress(200, "fit", stream=buf, unit="it") as bar:
        for _ in range(200):
            bar.update(1, extra="loss 0.1")
    text = buf.getvalue()
    assert "\r" not in text and text.count("\n") == 1 and text.startswith("fit [" + "#" * 30 + "] 200 it in")
    # a fake clock: 100 updates 1 s apart with a 10 s interval -> 10 running lines and the final one
    clock = iter(float(t) for t in range(1000))
    monkeypatch.setattr(progress, "_clock", lambda: next(clock))
    buf = io.StringIO()
    with progress.Progress(100, "sweep", stream=buf, interval=10.0) as bar:
        for _ in range(100):
            bar.update(1)
    lines = buf.getvalue().splitlines()
    assert "\r" not in buf.getvalue() and 9 <= len(lines) <= 11, lines
    assert all(ln.startswith("sweep [") for ln in lines) and "steps in" in lines[-1]
    # a terminal still gets the in-place bar
    class Tty(io.StringIO):
        def isatty(self):
            return True
    tty = Tty()
    with progress.Progress(3, "simulate", stream=tty) as bar:
        bar.update(3)
    assert tty.getvalue().count("\r") >= 2


@pytest.mark.heavy
def test_a_run_that_would_take_hours_is_announced_before_it_starts(work, tmp_path):
    """--steps is checked against how long the run will take: a short compiled probe sets the rate,
    and a run of more than half an hour says so on stderr before it starts (here 2e9 steps; the
    process is stopped once it has said so, and wrote nothing)."""
    out = tmp_path / "long.h5"
    proc = subprocess.Popen([sys.executable, "-m", "jaxplush", "simulate", str(work["scene"]), "--steps", "2000000000",
                             "--dt", repr(work["dt"]), "--out", str(out), "--quiet"],
                            stderr=subprocess.PIPE, stdout=subprocess.DEVNULL, text=True)
    try:
        import select
        ready, _, _ = select.select([proc.stderr], [], [], 120)
        # the warning comes first, before any step of the run (without it: nothing until the end)
        line = proc.stderr.readline() if ready else "(nothing on stderr within 120 s)"
    finally:
        proc.kill()
        proc.wait(timeout=60)
    assert line.startswith("warning: --steps 2,000,000,000 will take about "), line
    assert re.search(r"about [0-9.]+ (h|days) at the measured [0-9,]+ steps/s", line), line
    assert not out.exists() and listing(tmp_path) == []


def test_an_ordinary_run_is_not_announced(work, capsys):
    import argparse
    args = argparse.Namespace(steps=cli.PROBE_ABOVE + 1, dt=work["dt"], integrator="verlet", substeps=1)
    cli._warn_if_long(jaxplush.load_scene(work["scene"]), args)
    assert capsys.readouterr().err == ""


# ------------------------------------------------------------------------------------------- capture

def test_capture_writes_a_point_cloud_target_of_what_the_camera_sees(work, tmp_path):
    from jaxplush.fitting.targets import load_target
    out = tmp_path / "scan.h5"
    rc, stdout, err = run_cli("capture", work["traj"], "--eye", "0,0.25,0.8", "--size", "40x30", "--fov", "40",
                              "--noise", "0.001", "--dropout", "0.2", "--seed", "3", "--out", out)
    assert rc == 0, err
    assert "points a frame" in stdout and str(out) in stdout
    scene = jaxplush.load_scene(work["scene"])
    target = load_target(out, scene)
    with h5py.File(work["traj"]) as f:
        times = f["times"][()]
    assert target.kind == "points" and target.noise == 0.001 and np.allclose(target.times, times)
    counts = target.observed.sum(axis=1)
    assert counts.min() > 50
    # every observed point lies within a few noise sigmas of the ball's frame it was taken of
    with h5py.File(work["traj"]) as f:
        pos = f["positions"][()]
    for j in (0, len(times) - 1):
        p = target.points[j, :counts[j]]
        centre = pos[j].mean(axis=0)
        r = np.linalg.norm(p - centre, axis=1)
        assert r.max() < np.linalg.norm(pos[j] - centre, axis=1).max() + 0.005
    # the truth's parameters travel with it, as a simulated target's do
    assert target.params["k_structural"][0] == pytest.approx(100.0)


@pytest.mark.parametrize("args, phrases", [
    (("--eye", "0,0.25"), ("--eye must be three finite numbers",)),
    (("--eye", "0,0.25,0.8", "--size", "40by30"), ("--size must be WIDTHxHEIGHT",)),
    (("--eye", "0,0.25,0.8", "--look-at", "0,0.25,2"), ("sees no object",)),
    (("--eye", "0,0.25,0.8", "--dropout", "1"), ("dropout must lie in [0, 1)",)),
    (("--eye", "0,0.25,0.8", "--fov", "0"), ("--fov must be in (0, 180) degrees",)),
])
def test_capture_refuses_bad_cameras_and_writes_nothing(work, tmp_path, args, phrases):
    out = tmp_path / "scan.h5"
    rc, _, err = run_cli("capture", work["traj"], *args, "--out", out)
    assert_clean_error(rc, err, cli.EXIT_USAGE, *phrases)
    assert listing(tmp_path) == []


def test_capture_of_a_missing_trajectory_is_a_clean_error(tmp_path):
    rc, _, err = run_cli("capture", tmp_path / "nope.h5", "--eye", "0,0,1", "--out", tmp_path / "scan.h5")
    assert_clean_error(rc, err, cli.EXIT_USAGE, "nope.h5")
    assert listing(tmp_path) == []
