"""Fitting targets (jaxplush.fitting.targets): any simulate output loads as a target; every mismatch with the
scene is a clear TrajectoryError naming the file, raised before anything is traced."""

from __future__ import annotations

import h5py
import jax
import numpy as np
import pytest

import jaxplush
from conftest import icosphere_scene, icosphere_text
from jaxplush.fitting.objective.losses import chamfer as _chamfer, squared_distance as _squared_distance
from jaxplush.fitting.targets import Target, load_target, make_target, sample_surface
from jaxplush.errors import TrajectoryError

DT = 1e-3


@pytest.fixture(scope="module")
def scene():
    return icosphere_scene(subdivisions=1, nmol=1e-4, k=50.0, mass=0.05)


@pytest.fixture(scope="module")
def sim_file(tmp_path_factory, scene):
    """A 'jaxplush simulate' output (the target schema), 40 steps saved every 10."""
    path = tmp_path_factory.mktemp("targets") / "sim.h5"
    jaxplush.simulate(scene, 40, DT, 10, check_dt=False).save(path)
    return path


def _copy_with(src, dst, edit):
    """Copy an HDF5 file, then apply ``edit(h5py.File)`` to the copy."""
    with h5py.File(src, "r") as a, h5py.File(dst, "w") as b:
        for k in a:
            a.copy(k, b)
        for k, v in a.attrs.items():
            b.attrs[k] = v
        edit(b)
    return dst


def test_simulate_output_is_a_target(sim_file, scene):
    t = load_target(sim_file, scene)
    traj = jaxplush.load_trajectory(sim_file)
    assert t.kind == "positions" and t.points is None
    np.testing.assert_array_equal(t.positions, traj["positions"])
    np.testing.assert_array_equal(t.steps, [0, 10, 20, 30, 40])
    assert t.dt == DT and t.path == str(sim_file)
    assert set(t.params) >= {"k_structural", "nmol"} and t.params["k_structural"][0] == 50.0


def test_subset_of_frames_and_explicit_dt(sim_file, scene, tmp_path):
    def last_only(f):
        pos, times = f["positions"][-1:], f["times"][-1:]
        del f["positions"], f["times"]
        f["positions"], f["times"] = pos, times
    path = _copy_with(sim_file, tmp_path / "last.h5", last_only)
    t = load_target(path, scene)
    assert t.n_frames == 1 and t.steps.tolist() == [40]
    # a finer dt that divides every frame time is fine: the steps follow it
    t2 = load_target(path, scene, dt=DT / 4)
    assert t2.steps.tolist() == [160] and t2.dt == DT / 4
    assert t.on_grid(DT / 2).steps.tolist() == [80]


def test_point_cloud_target(tmp_path, scene):
    t = make_target(scene, 20, DT, 10, point_cloud=True, n_points=100, noise=1e-4, seed=1)
    assert t.kind == "points" and t.points.shape == (2, 100, 3) and t.noise == 1e-4
    t.save(tmp_path / "pc.h5")
    back = load_target(tmp_path / "pc.h5", scene)
    np.testing.assert_array_equal(back.points, t.points)
    assert back.noise == 1e-4 and back.steps.tolist() == [10, 20]


def test_point_cloud_needs_no_vertex_match(tmp_path):
    other = icosphere_scene(subdivisions=2)   # 162 vertices; the cloud has 37 points
    t = Target(positions=None, points=np.random.default_rng(0).normal(size=(1, 37, 3)), steps=np.array([5]),
               times=np.array([5 * DT]), dt=DT, path="<memory>")
    t.save(tmp_path / "cloud.h5")
    assert load_target(tmp_path / "cloud.h5", other).points.shape == (1, 37, 3)


def test_sample_surface_lies_on_the_mesh():
    s = icosphere_scene(subdivisions=2, radius=0.1)
    p = sample_surface(s.vertices, s.faces, 2000, np.random.default_rng(0))
    r = np.linalg.norm(p, axis=1)
    # points on the flat faces of a level-2 icosphere of radius 0.1 lie between its inradius and 0.1
    assert r.max() <= 0.1 + 1e-12 and r.min() > 0.095


def test_losses_vanish_on_the_target_and_chamfer_is_symmetric():
    squared_distance, chamfer = jax.jit(_squared_distance), jax.jit(_chamfer)
    rng = np.random.default_rng(0)
    x = rng.normal(size=(30, 3))
    assert float(squared_distance(x, x)) == 0.0
    assert float(chamfer(x, x[::-1])) == pytest.approx(0.0, abs=1e-5)     # float32 |x|²+|y|²-2x·y floor
    y = rng.normal(size=(50, 3))
    assert float(chamfer(x, y)) == pytest.approx(float(chamfer(y, x)), rel=1e-5)
    d = ((x[:, None] - y[None]) ** 2).sum(-1)
    assert float(chamfer(x, y)) == pytest.approx(d.min(1).mean() + d.min(0).mean(), rel=1e-4)


def _bad_cases():
    def drop(name):
        return lambda f: f.__delitem__(name)

    def replace(name, fn):
        def edit(f):
            data = fn(f[name][()])
            del f[name]
            f[name] = data
        return edit

    def nan_at(f):
        p = f["positions"][()]
        p[2, 7, 1] = np.nan
        del f["positions"]
        f["positions"] = p

    def attr(name, value):
        def edit(f):
            if value is None:
                del f.attrs[name]
            else:
                f.attrs[name] = value
        return edit

    return {
        "no positions": (drop("positions"), "missing dataset 'positions'"),
        "no times": (drop("times"), "missing dataset 'times'"),
        "vertex count": (replace("positions", lambda p: p[:, :-1]), "41 vertices but the scene"),
        "shape": (replace("positions", lambda p: p[..., :2]), "must have shape [T, V, 3]"),
        "times length": (replace("times", lambda t: t[:-1]), "'times' must have shape [5]"),
        "off grid": (replace("times", lambda t: t + 0.3 * DT), "not on the dt = 0.001 s grid"),
        "not increasing": (replace("times", lambda t: t[::-1]), "strictly increasing"),
        "non-finite": (nan_at, "non-finite values (first at frame 2, vertex 7)"),
        "object count": (replace("object_names", lambda n: np.array([b"a", b"b"], dtype=object)),
                         "2 object(s)"),
        "object ids": (replace("object_id", lambda o: o + 1), "describes 2 object(s)"),
        "faces": (replace("faces", lambda f: f[:, [0, 0, 1]]), "'faces' differ from the scene"),
        "no dt": (attr("dt", None), "no 'dt' attribute"),
        "bad dt": (attr("dt", -1.0), "must be a positive number"),
        "group": (lambda f: (f.__delitem__("times"), f.create_group("times")), "'times' is a group"),
        "object names": (replace("object_names", lambda n: np.array([b"bear"], dtype=object)),
                         "'object_names' ['bear'] differ from the scene"),
        "object ids not integers": (replace("object_id", lambda o: o + 0.5), "'object_id' must hold integers"),
        "noise not a number": (attr("noise", "1 mm"), "attribute 'noise' must be a number"),
        "noise array": (attr("noise", np.array([1e-3, 2e-3])), "attribute 'noise' must be a number"),
        "absurd times": (replace("times", lambda t: t * 1e30), "too many steps to simulate"),
    }


BAD = _bad_cases()


@pytest.mark.parametrize("case", sorted(BAD))
def test_each_mismatch_is_a_clear_error(sim_file, scene, tmp_path, case):
    edit, message = BAD[case]
    path = _copy_with(sim_file, tmp_path / "bad.h5", edit)
    with pytest.raises(TrajectoryError) as e:
        load_target(path, scene)
    assert str(path) in str(e.value) and message in str(e.value)


def test_unreadable_files(tmp_path, scene):
    with pytest.raises(TrajectoryError, match="no such file"):
        load_target(tmp_path / "missing.h5", scene)
    text = tmp_path / "text.h5"
    text.write_text("not hdf5\n")
    with pytest.raises(TrajectoryError, match="not an HDF5 file"):
        load_target(text, scene)
    with pytest.raises(TrajectoryError, match="is a directory"):
        load_target(tmp_path, scene)


def test_a_different_scene_is_rejected(sim_file):
    bigger = jaxplush.parse_scene(icosphere_text(subdivisions=2), "<bigger>")
    with pytest.raises(TrajectoryError, match="42 vertices but the scene <bigger> has 162"):
        load_target(sim_file, bigger)
