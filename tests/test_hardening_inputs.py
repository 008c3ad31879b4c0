"""Hardening of the newer inputs (issue 54): release times, noise, segment lengths and driven paths
whose values are out of range get one clean line naming the file (and line) or option, exit 2, and
nothing written; in-range values still run. The sweep's and the capture's options are in
tests/test_hardening_sweep.py and tests/test_hardening_capture.py."""

from __future__ import annotations

import dataclasses
import warnings

import h5py
import numpy as np
import pytest
import trimesh

import jaxplush
from jaxplush import cli
from jaxplush.errors import JaxplushError, SceneError, TrajectoryError
from jaxplush.fitting import cli as fit_cli
from jaxplush.fitting import fitter as F
from jaxplush.fitting.targets import Controls, load_target, make_target
from jaxplush.stepping import constraints
from conftest import icosphere_text

DT = 5e-4


def _ball_path(path, offset=(0.0, 0.0, 0.0)):
    """A CSV path for vertex 1 of the 42-vertex ball: its rest position plus ``offset``, 0-1 s."""
    v = (trimesh.creation.icosphere(subdivisions=1, radius=0.1).vertices[0] + np.asarray(offset, float)).tolist()
    path.write_text("t,c0,c1,c2\n" + "".join(f"{t!r},{v[0]!r},{v[1]!r},{v[2]!r}\n" for t in (0.0, 1.0)))


def _driven_scene(tmp_path, line, offset=(0.0, 0.0, 0.0)):
    _ball_path(tmp_path / "p.csv", offset)
    path = tmp_path / "s.obj"
    path.write_text(icosphere_text(extra=line))
    return path, icosphere_text(extra=line).splitlines().index(line) + 1


def _one_error_line(capsys, prog):
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"{prog}: error: ") and "Traceback" not in err, err
    return lines[0]


@pytest.mark.parametrize("command", ["simulate", "info"])
def test_a_release_time_no_run_reaches_is_refused_naming_the_line(tmp_path, capsys, command):
    """``driven ... until 1e300``: once an OverflowError converting the release step to int64."""
    scene, line = _driven_scene(tmp_path, "driven p.csv 1 until 1e300")
    out = tmp_path / "o.h5"
    argv = [command, str(scene), "--dt", str(DT)] + (["--steps", "10", "--out", str(out), "--quiet"]
                                                     if command == "simulate" else [])
    assert cli.main(argv) == 2
    msg = _one_error_line(capsys, "jaxplush " + command)
    assert f"s.obj:{line}: 'driven' release time 'until 1e+300' s is" in msg and "beyond any run" in msg
    assert not out.exists() and sorted(p.name for p in tmp_path.iterdir()) == ["p.csv", "s.obj"]


def test_a_late_release_time_within_the_step_counter_still_runs(tmp_path):
    """A release after the run's end drives the vertex throughout (no error); the limit is the
    step counter's range, for any substep length."""
    scene_path, _ = _driven_scene(tmp_path, "driven p.csv 1 until 1000")
    scene = jaxplush.load_scene(scene_path)
    drive = constraints.Drive(scene, DT)
    assert drive.release.tolist() == [int(np.floor(1000 / DT * (1 + 1e-12)))]
    traj = jaxplush.simulate(scene, steps=4, dt=DT)
    np.testing.assert_allclose(traj.positions[-1, 0], scene.vertices[0], atol=1e-6)
    with pytest.raises(SceneError, match="beyond any run"):
        constraints.Drive(scene, 1e-7)                    # 1e10 substeps: no run reaches them


def test_controls_until_no_run_reaches_is_refused_naming_the_target(tmp_path):
    """``controls/until`` = 1e300 (a finite number > 0, so the file loads): the fit refuses it
    naming the target file and the attribute, before anything is compiled."""
    scene = jaxplush.parse_scene(icosphere_text(), "<ball>")
    target = make_target(scene, 20, DT, 10)
    ctrl = Controls(vertices=np.array([3]), times=np.array([0.0, 0.01]),
                    positions=np.broadcast_to(scene.vertices[[3]], (2, 1, 3)).copy(), until=1e300)
    path = tmp_path / "t.h5"
    dataclasses.replace(target, controls=ctrl).save(path, scene)
    loaded = load_target(path, scene)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with pytest.raises(TrajectoryError, match=r"attribute 'controls/until' = 1e\+300 s is .* beyond any run") as e:
            F.build_problem(scene, loaded, ("k_structural",))
    assert e.value.path == str(path)


def test_a_driven_path_float32_cannot_resolve_is_refused_naming_the_path(tmp_path, capsys):
    """A path 9e29 m away used to pass the parser and blow up the run (exit 3, a time-step hint)."""
    scene, line = _driven_scene(tmp_path, "driven p.csv 1", offset=(9e29, 0.0, 0.0))
    out = tmp_path / "o.h5"
    assert cli.main(["simulate", str(scene), "--steps", "10", "--dt", str(DT), "--out", str(out), "--quiet"]) == 2
    msg = _one_error_line(capsys, "jaxplush simulate")
    assert f"s.obj:{line}: 'driven' path file 'p.csv': positions up to 9e+29 m" in msg and "float32" in msg
    assert not out.exists()


@pytest.fixture(scope="module")
def fit_files(tmp_path_factory):
    """A 42-vertex ball and a 2-frame target of it (its frame at t = 0 and one more)."""
    d = tmp_path_factory.mktemp("fit_inputs")
    scene = jaxplush.parse_scene(icosphere_text(damping=500.0), "<ball>")
    (d / "s.obj").write_text(icosphere_text(damping=500.0))
    make_target(scene, 10, DT, 10).save(d / "t.h5", scene)
    return d, scene


@pytest.mark.parametrize("noise, why", [("1e-300", "below 1e-09 of the scene's size"),
                                        ("1e200", "more than 1000 times the scene's size")])
def test_a_noise_option_out_of_scale_is_refused(fit_files, tmp_path, capsys, noise, why):
    """--noise 1e-300 was a ZeroDivisionError (sigma² underflows); 1e200 wrote NaN to FIT.h5."""
    d, _ = fit_files
    out = tmp_path / "FIT.h5"
    assert fit_cli.main([str(d / "s.obj"), str(d / "t.h5"), "--noise", noise, "--out", str(out), "--quiet"]) == 2
    msg = _one_error_line(capsys, "jaxplush-fit")
    assert msg.startswith(f"jaxplush-fit: error: --noise {float(noise):g} m is {why}") and not out.exists()


def test_a_target_noise_attribute_out_of_scale_is_refused_naming_the_file(fit_files, tmp_path, capsys):
    d, scene = fit_files
    bad = tmp_path / "noisy.h5"
    bad.write_bytes((d / "t.h5").read_bytes())
    with h5py.File(bad, "a") as f:
        f.attrs["noise"] = 1e-300
    out = tmp_path / "FIT.h5"
    assert fit_cli.main([str(d / "s.obj"), str(bad), "--out", str(out), "--quiet"]) == 2
    msg = _one_error_line(capsys, "jaxplush-fit")
    assert f"{bad}: attribute 'noise' 1e-300 m is below" in msg and not out.exists()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with pytest.raises(JaxplushError, match=r"^noise 1e\+200 m is more than 1000 times"):
            F.build_problem(scene, load_target(d / "t.h5", scene), ("k_structural",), noise=1e200)
        # in range, and noise-free over a bad attribute: accepted
        F.build_problem(scene, load_target(d / "t.h5", scene), ("k_structural",), noise=1e-3)
        F.build_problem(scene, load_target(bad, scene), ("k_structural",), noise_free=True)


@pytest.mark.parametrize("frames", ["1000000000", "2"])
def test_segments_longer_than_the_target_are_refused(fit_files, tmp_path, capsys, frames):
    """--shooting 10^9 on a 2-frame target once aborted XLA (SIGABRT); the target has one frame
    after its start, so no segment length fits."""
    d, _ = fit_files
    out = tmp_path / "FIT.h5"
    rc = fit_cli.main([str(d / "s.obj"), str(d / "t.h5"), "--noise-free", "--shooting", frames, "--out", str(out),
                       "--quiet"])
    assert rc == 2
    msg = _one_error_line(capsys, "jaxplush-fit")
    assert f"(--shooting) {frames}: segments of {frames} frames are longer than the target, which has 1 frame" in msg
    assert not out.exists()


def test_a_driven_path_whose_speed_overflows_is_refused(tmp_path):
    """Found by the fuzzing of this issue: samples 5e-324 s apart gave an infinite start velocity
    (a numpy RuntimeWarning, then a run that blows up)."""
    v = trimesh.creation.icosphere(subdivisions=1, radius=0.1).vertices[0].tolist()
    (tmp_path / "p.csv").write_text(f"t,c0,c1,c2\n0.0,{v[0]!r},{v[1]!r},{v[2]!r}\n5e-324,{v[0] + 0.01!r},{v[1]!r},"
                                    f"{v[2]!r}\n")
    (tmp_path / "s.obj").write_text(icosphere_text(extra="driven p.csv 1"))
    scene = jaxplush.load_scene(tmp_path / "s.obj")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(SceneError, match=r"s.obj:\d+: 'driven' path file 'p.csv': the speed between samples 0 "
                                             r"and 1 .* overflows"):
            jaxplush.make_simulator(scene, DT)


def test_view_of_a_damaged_file_is_a_clean_error(tmp_path, capsys):
    """Found by the fuzzing of this issue: a trajectory whose HDF5 is damaged past its header made
    ``jaxplush view`` raise h5py's RuntimeError ("bad local heap signature") with a traceback."""
    pytest.importorskip("viser")
    scene = jaxplush.parse_scene(icosphere_text(), "<ball>")
    good = tmp_path / "t.h5"
    jaxplush.simulate(scene, 4, DT, 2, progress=False).save(good)
    raw = bytearray(good.read_bytes())
    raw[600:700] = b"\xff" * 100
    bad = tmp_path / "damaged.h5"
    bad.write_bytes(bytes(raw))
    out = tmp_path / "v.html"
    assert cli.main(["view", str(bad), "--html", str(out)]) == 2
    msg = _one_error_line(capsys, "jaxplush view")
    assert f"{bad}: not a readable trajectory or FIT.h5 (damaged HDF5" in msg and not out.exists()


@pytest.mark.parametrize("command", ["fit", "sweep"])
def test_a_release_time_no_run_reaches_is_refused_by_the_fit_and_the_sweep(fit_files, tmp_path, capsys, command):
    d, _ = fit_files
    scene, line = _driven_scene(tmp_path, "driven p.csv 1 until 1e300")
    out = tmp_path / "o.h5"
    argv = ([str(scene), str(d / "t.h5"), "--noise-free"] if command == "fit" else
            ["sweep", str(scene), "--grid", "k_structural=50:150:3", "--steps", "10", "--dt", str(DT)])
    assert fit_cli.main(argv + ["--out", str(out), "--quiet"]) == 2
    msg = _one_error_line(capsys, "jaxplush-fit" + (" sweep" if command == "sweep" else ""))
    assert f"s.obj:{line}: 'driven' release time 'until 1e+300' s is" in msg
    assert sorted(p.name for p in tmp_path.iterdir()) == ["p.csv", "s.obj"]
