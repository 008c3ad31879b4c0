"""Driven vertices given by the target (its group ``controls``: a gripper's measured path) instead
of a ``driven`` line of the scene: they round-trip through HDF5, become the scene's driven paths
(the same rollout as the keyword's), a fit with them equals the same fit with the keyword,
malformed or conflicting controls are refused naming the file and the dataset, the fitted scene
keeps them, ``jaxplush capture --controls`` writes them, and a sweep refuses them."""

from __future__ import annotations

import dataclasses
import warnings

import h5py
import numpy as np
import pytest

import jaxplush
from jaxplush.errors import JaxplushError, TrajectoryError
from jaxplush.fitting import fitter as F
from jaxplush.fitting.judge.identifiability import frames_at_steps
from jaxplush.fitting.targets import Controls, controls_of_scene, load_target, make_target, scene_with_controls
from test_driven import _squeezed

DT, STEPS, EVERY = 1e-3, 90, 10


def _bare(scene, name="bare.obj"):
    """The scene without its ``driven`` lines (parsed beside it)."""
    import os
    text = "\n".join(line for line in scene.text.splitlines() if not line.startswith("driven"))
    return jaxplush.parse_scene(text, os.path.join(os.path.dirname(scene.path), name))


def _frames(scene, steps):
    sim = jaxplush.make_simulator(scene, DT)
    p = sim.params()
    fr, _ = frames_at_steps(sim, p, sim.init_fn(p), steps)
    return np.asarray(fr, np.float64)


def test_controls_round_trip_and_drive_the_scene_as_the_keyword_does(tmp_path):
    truth = _squeezed(tmp_path, 120.0)
    ctrl = controls_of_scene(truth)
    assert ctrl.vertices.tolist() == truth.driven_vertices.tolist() and ctrl.until is None
    np.testing.assert_array_equal(ctrl.positions, np.concatenate([d.positions for d in truth.driven], axis=1))
    np.testing.assert_array_equal(ctrl.times, truth.driven[0].times)
    target = make_target(truth, STEPS, DT, EVERY, controls=True)
    bare = _bare(truth)
    assert not bare.driven
    path = tmp_path / "t.h5"
    target.save(path, bare)
    back = load_target(path, bare)
    for name in ("vertices", "times", "positions"):
        np.testing.assert_array_equal(getattr(back.controls, name), getattr(ctrl, name))
    driven = scene_with_controls(bare, back)
    assert driven.driven_vertices.tolist() == truth.driven_vertices.tolist()
    assert [d.source for d in driven.driven] == ["<target controls>"] and driven.driven[0].file == str(path)
    steps = [int(s) for s in target.steps]
    np.testing.assert_array_equal(_frames(driven, steps), _frames(truth, steps))
    assert not np.allclose(_frames(bare, steps), _frames(truth, steps))           # the controls do drive it
    # a release time: the same release as the keyword's
    released = dataclasses.replace(back, controls=dataclasses.replace(back.controls, until=0.05))
    kw = jaxplush.parse_scene("\n".join(line + (" until 0.05" if line.startswith("driven") else "")
                                        for line in truth.text.splitlines()), truth.path)
    np.testing.assert_array_equal(_frames(scene_with_controls(bare, released), steps), _frames(kw, steps))
    released.save(tmp_path / "u.h5", bare)
    assert load_target(tmp_path / "u.h5", bare).controls.until == 0.05


def test_a_fit_with_controls_equals_the_fit_with_the_keyword(tmp_path):
    from jaxplush.fitting.io import write_fitted_scene
    truth = _squeezed(tmp_path, 120.0)
    target = make_target(truth, STEPS, DT, EVERY)
    start = _squeezed(tmp_path, 180.0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        by_keyword = F.fit(start, target, ("k_structural",), noise_free=True)
        by_controls = F.fit(_bare(start), dataclasses.replace(target, controls=controls_of_scene(truth)),
                            ("k_structural",), noise_free=True)
    k = by_keyword.values["k_structural"][0]
    assert k == pytest.approx(120.0, rel=1e-2), by_keyword.reason
    assert by_controls.values["k_structural"][0] == pytest.approx(k, rel=1e-6)
    assert by_controls.loss == pytest.approx(by_keyword.loss, rel=1e-4, abs=1e-12)
    assert by_controls.status == by_keyword.status
    # the fitted scene keeps the drive: a path file beside it, and the same rollout
    out = tmp_path / "sub" / "fitted.obj"
    out.parent.mkdir()
    write_fitted_scene(by_controls, out)
    assert (tmp_path / "sub" / "fitted.controls-0.h5").exists()
    assert "\ndriven fitted.controls-0.h5 " in out.read_text()
    back = jaxplush.load_scene(out)
    assert back.driven_vertices.tolist() == truth.driven_vertices.tolist()
    steps = [int(s) for s in target.steps]
    ref = jaxplush.load_scene(write_fitted_scene(by_keyword, tmp_path / "sub" / "kw.obj"))
    np.testing.assert_array_equal(_frames(back, steps), _frames(ref, steps))


def _write(path, target, scene, **controls):
    """``target`` saved with its controls' datasets replaced (None: left out) or ``until``."""
    target.save(path, scene)
    with h5py.File(path, "a") as f:
        g = f["controls"]
        for name, val in controls.items():
            if name == "until":
                g.attrs["until"] = val
                continue
            del g[name]
            if val is not None:
                g[name] = val
    return path


@pytest.mark.parametrize("change, message", [
    (dict(vertices=np.zeros((2, 2), int)), r"'controls/vertices' must have shape \[D\]"),
    (dict(vertices=[3, 42]), r"'controls/vertices' has 42 at entry 1: not an index of the scene's 42 vertices "
                             r"\(0\.\.41, 0-based as 'track_vertex'\)"),
    (dict(vertices=[3, -1]), r"'controls/vertices' has -1 at entry 1"),
    (dict(vertices=[3, 1.5]), r"'controls/vertices' has 1.5 at entry 1"),
    (dict(vertices=[3, 3]), r"'controls/vertices' lists vertex 3 twice \(entries 0 and 1\)"),
    (dict(times=[0.0, 0.02, 0.01, 0.03]), r"'controls/times' must be strictly increasing; sample 2"),
    (dict(times=[0.0, np.nan, 0.02, 0.03]), r"'controls/times' has a non-finite value at sample 1"),
    (dict(times=None), r"missing dataset 'controls/times'"),
    (dict(positions=np.zeros((4, 3, 3))), r"'controls/positions' must have shape \[S, D, 3\] = \[4, 2, 3\]"),
    (dict(positions=np.where(np.arange(4)[:, None, None] == 2, np.nan, np.zeros((4, 2, 3)))),
     r"'controls/positions' has non-finite values \(first at sample 2, driven vertex 0\)"),
    (dict(positions=np.full((4, 2, 3), 1e5)), r"'controls/positions' reaches .* wrong units"),
    (dict(until=-1.0), r"attribute 'controls/until' \(the release time\) must be a finite number > 0"),
    (dict(until="soon"), r"attribute 'controls/until' must be a number"),
])
def test_malformed_controls_are_refused_naming_file_and_dataset(tmp_path, change, message):
    from conftest import icosphere_scene
    scene = icosphere_scene(subdivisions=1)
    target = make_target(scene, 20, DT, 10)
    ctrl = Controls(vertices=np.array([3, 5]), times=np.array([0.0, 0.01, 0.02, 0.03]),
                    positions=np.broadcast_to(scene.vertices[[3, 5]], (4, 2, 3)).copy())
    path = _write(tmp_path / "bad.h5", dataclasses.replace(target, controls=ctrl), scene, **change)
    with pytest.raises(TrajectoryError, match=message) as e:
        load_target(path, scene)
    assert e.value.path == str(path)


def test_controls_that_conflict_with_the_scene_are_refused(tmp_path):
    from conftest import icosphere_scene
    truth = _squeezed(tmp_path, 120.0)
    target = make_target(truth, 20, DT, 10, controls=True)
    path = tmp_path / "t.h5"
    target.save(path, truth)
    line = truth.driven[0].line
    v = truth.driven_vertices[0]
    with pytest.raises(TrajectoryError, match=rf"'controls/vertices' entry 0 drives vertex {v}, which the scene "
                                              rf".* already drives \('driven' on line {line}\)") as e:
        load_target(path, truth)
    assert e.value.path == str(path)
    with pytest.raises(TrajectoryError, match="already drives"):         # a target built in memory: at the fit
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            F.build_problem(truth, target, ("k_structural",))
    pinned = icosphere_scene(subdivisions=1, fixed=(3,))
    free = make_target(pinned, 20, DT, 10)
    ctrl = Controls(vertices=np.array([3]), times=np.array([0.0]), positions=pinned.vertices[[3]][None])
    dataclasses.replace(free, controls=ctrl).save(tmp_path / "p.h5", pinned)
    with pytest.raises(TrajectoryError, match="entry 0 drives vertex 3, which the scene .* pins"):
        load_target(tmp_path / "p.h5", pinned)
    with pytest.raises(ValueError, match="drives no vertices"):
        make_target(pinned, 20, DT, 10, controls=True)


def test_capture_writes_the_controls_and_a_sweep_drives_them(tmp_path):
    from jaxplush.fitting.sweep import sweep
    from test_cli import run_cli
    truth = _squeezed(tmp_path, 120.0)
    traj = tmp_path / "sq.h5"
    rc, _, err = run_cli("simulate", truth.path, "--steps", 40, "--dt", DT, "--save-every", 10, "--out", traj,
                         "--quiet")
    assert rc == 0, err
    out = tmp_path / "scan.h5"
    rc, stdout, err = run_cli("capture", traj, "--eye", "0,0,0.8", "--size", "32x24", "--controls", "--out", out)
    assert rc == 0, err
    assert f"the paths of {len(truth.driven_vertices)} driven vertices as 'controls'" in stdout
    bare = _bare(truth)
    t = load_target(out, bare)
    assert t.kind == "points" and t.controls.vertices.tolist() == truth.driven_vertices.tolist()
    with pytest.raises(TrajectoryError, match="already drives"):
        load_target(out, truth)
    plain = tmp_path / "plain.h5"
    rc, _, err = run_cli("simulate", _write_scene(tmp_path, bare), "--steps", 20, "--dt", DT, "--out", plain,
                         "--quiet")
    assert rc == 0, err
    rc, _, err = run_cli("capture", plain, "--eye", "0,0,0.8", "--controls", "--out", tmp_path / "no.h5")
    assert rc != 0 and "--controls: the scene of" in err and "drives no vertices" in err
    # a sweep drives the controlled vertices in every point: the same losses as the scene that
    # drives them itself against the capture without its controls
    grid = {"k": [100.0, 120.0, 150.0]}
    got = sweep(bare, grid, steps=40, dt=DT, target=t, progress=False, batch=3)
    want = sweep(truth, grid, steps=40, dt=DT, target=dataclasses.replace(t, controls=None), progress=False, batch=3)
    assert np.isfinite(got.loss).all() and np.ptp(got.loss) > 0
    np.testing.assert_allclose(got.loss, want.loss, rtol=1e-5)


def _write_scene(tmp_path, scene):
    path = tmp_path / "bare.obj"
    path.write_text(scene.text)
    return path


def test_a_target_without_controls_leaves_the_scene_alone(tmp_path):
    from conftest import icosphere_scene
    scene = icosphere_scene(subdivisions=1)
    target = make_target(scene, 20, DT, 10)
    assert scene_with_controls(scene, target) is scene
    with pytest.raises(JaxplushError):
        scene_with_controls(scene, dataclasses.replace(target, controls=Controls(
            vertices=np.array([99]), times=np.array([0.0]), positions=np.zeros((1, 1, 3)))))
