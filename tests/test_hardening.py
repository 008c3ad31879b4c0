"""Hardening found by fuzzing: every bad input gets a clean error, and no absurd scene gives a silent
wrong answer (huge indices, devices and FIFOs as scenes, damaged HDF5 headers, absurd parameter
values, coordinates float32 cannot resolve, targets in the wrong units, dangling symlinks, stale
temporary files)."""

from __future__ import annotations

import os
import shutil
import time
import warnings

import h5py
import numpy as np
import pytest

import jaxplush
from jaxplush import cli
from jaxplush.stepping import stability
from jaxplush.errors import JaxplushError, SceneError, TrajectoryError
from jaxplush.io.trajectory import atomic_path, check_output_path
from conftest import icosphere_text

from jaxplush.fitting.targets import load_target, make_target


def test_a_huge_face_index_is_a_scene_error():
    with pytest.raises(SceneError, match=r"<s>:1: 'f': vertex index 99999999999999999999999 out of range"):
        jaxplush.parse_scene("f 2 99999999999999999999999 4\n", "<s>")
    with pytest.raises(SceneError, match="out of range"):
        jaxplush.parse_scene(icosphere_text(subdivisions=0).replace("END_OBJECT", f"fixed {2 ** 63}\nEND_OBJECT"), "<s>")


@pytest.mark.skipif(not os.path.exists("/dev/zero"), reason="no /dev/zero here")
def test_devices_and_fifos_are_not_read_as_scenes(tmp_path):
    for dev in ("/dev/zero", "/dev/urandom"):
        t = time.perf_counter()
        with pytest.raises(SceneError, match="not a regular file"):
            jaxplush.load_scene(dev)
        assert time.perf_counter() - t < 1.0
    fifo = tmp_path / "pipe.obj"
    os.mkfifo(fifo)
    with pytest.raises(SceneError, match="not a regular file"):
        jaxplush.load_scene(fifo)                 # opening a FIFO for reading would block forever


@pytest.fixture(scope="module")
def target_file(tmp_path_factory):
    d = tmp_path_factory.mktemp("targets")
    scene = jaxplush.parse_scene(icosphere_text(subdivisions=1, nmol=1e-3), "<ball>")
    path = d / "t.h5"
    make_target(scene, 40, 1e-3, 10).save(path, scene)
    return scene, path


def test_damaged_hdf5_headers_are_clean_errors(target_file, tmp_path):
    """Every single-byte corruption of the file's first 2 KiB either still loads or raises a
    TrajectoryError naming the file; h5py's RuntimeError ("addr overflow") included."""
    scene, path = target_file
    raw = path.read_bytes()
    rng = np.random.default_rng(0)
    for i, off in enumerate(sorted(set(rng.integers(0, min(2048, len(raw)), 150).tolist()))):
        bad = bytearray(raw)
        bad[off] ^= int(rng.integers(1, 256))
        p = tmp_path / f"bad{i}.h5"
        p.write_bytes(bytes(bad))
        try:
            load_target(p, scene)
        except TrajectoryError as e:
            assert str(p) in str(e)


def test_targets_in_the_wrong_units_or_of_booleans_are_refused(target_file, tmp_path):
    scene, path = target_file
    scaled = tmp_path / "scaled.h5"
    shutil.copy(path, scaled)
    with h5py.File(scaled, "a") as f:
        f["positions"][...] = f["positions"][()] * 1e30
    with pytest.raises(TrajectoryError, match="times the scene's size .*wrong units"):
        load_target(scaled, scene)
    boolean = tmp_path / "bool.h5"
    shutil.copy(path, boolean)
    with h5py.File(boolean, "a") as f:
        data = f["positions"][()] > 0
        del f["positions"]
        f["positions"] = data
    with pytest.raises(TrajectoryError, match="'positions' must be numeric, got dtype bool"):
        load_target(boolean, scene)


@pytest.mark.parametrize("edit", ["k_structural 1e30", "nmol 1e30", "total_weight 1e-30", "damping 1"])
def test_stability_limits_of_absurd_values_are_finite_and_warn(edit):
    """The bound and the estimate stay finite (no inf/nan, no numpy warnings), so the dt check
    still warns before the run; damping 1 (velocities zeroed every step) has a finite limit."""
    key = edit.split()[0]
    text = icosphere_text(subdivisions=1, nmol=1e-3)
    lines = [ln for ln in text.splitlines() if not ln.startswith(key)]
    i = next(j for j, ln in enumerate(lines) if ln.startswith("o "))
    scene = jaxplush.parse_scene("\n".join(lines[:i + 1] + [edit] + lines[i + 1:]) + "\n", "<absurd>")
    sim = jaxplush.make_simulator(scene, 1e-3)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        b = stability.bound(sim, sim.params())
        e = stability.estimate(sim, sim.params())
    for est in (b, e):
        assert np.isfinite(est.dt_max) and est.dt_max > 0 and np.isfinite(est.omega_max)
    if key != "damping":
        assert "exceeds the estimated explicit stability limit" in stability.check_dt(sim, sim.params())
    else:
        assert 0 < e.dt_max < np.inf


@pytest.mark.parametrize("offset", ["1e10", "1e7"])
def test_coordinates_float32_cannot_resolve_are_refused(tmp_path, offset, capsys):
    text = icosphere_text(subdivisions=1, translate=(offset, 0, 0))
    scene = jaxplush.parse_scene(text, "far.obj")
    with pytest.raises(JaxplushError, match="float32 resolves only .* translate the scene near the origin, or run "
                                            "in float64"):
        jaxplush.make_simulator(scene, 1e-4)
    path = tmp_path / "far.obj"
    path.write_text(text)
    rc = cli.main(["simulate", str(path), "--steps", "10", "--dt", "1e-4", "--out", str(tmp_path / "o.h5"), "--quiet"])
    assert rc == 2 and "float32 resolves only" in capsys.readouterr().err
    assert sorted(os.listdir(tmp_path)) == ["far.obj"]


def test_a_dangling_symlink_output_is_refused(tmp_path):
    link = tmp_path / "out.h5"
    os.symlink(tmp_path / "missing" / "x.h5", link)
    with pytest.raises(JaxplushError, match="is a symbolic link to .* which does not exist"):
        check_output_path(link, (".h5",))


def test_a_killed_writers_temporary_file_is_removed_by_the_next_write(tmp_path):
    out = tmp_path / "FIT.h5"
    stale = tmp_path / ".tmp-FIT.h5-abc123.h5"           # what a SIGKILL during a write leaves
    stale.write_bytes(b"partial")
    old = time.time() - 60
    os.utime(stale, (old, old))
    other = tmp_path / ".tmp-other.h5-xyz.h5"               # another output's: left alone
    other.write_bytes(b"x")
    os.utime(other, (old, old))
    with atomic_path(out, ".h5") as tmp:
        with open(tmp, "w") as fh:
            fh.write("done")
    assert out.read_text() == "done" and not stale.exists() and other.exists()
