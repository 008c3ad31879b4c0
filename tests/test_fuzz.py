"""Property-based fuzzing (Hypothesis) of the scene parser, the target loader and the CLI's exit codes.

Contract: a mutated scene or target is either accepted, and then satisfies the documented
invariants, or rejected with a :class:`SceneError` / :class:`TrajectoryError` (a CLI: exit 2 or 3
with one message and no traceback), never anything else, and within a time bound. The default
run tries a bounded number of examples; ``pytest -m fuzz`` (with ``JAXPLUSH_FUZZ_EXAMPLES=N``,
default 2000) runs many more.
"""

from __future__ import annotations

import contextlib
import io
import os
import time

import h5py
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings, strategies as st

import jaxplush
from jaxplush import cli
from jaxplush.errors import SceneError, TrajectoryError
from conftest import icosphere_text

from jaxplush.fitting.targets import load_target, make_target

DEFAULT_EXAMPLES = 60
MANY = int(os.environ.get("JAXPLUSH_FUZZ_EXAMPLES", "2000"))
#: Seconds one parse (or load) may take: a mutated small scene never needs long.
TIME_BOUND = 5.0

BASE = (icosphere_text(subdivisions=0, k=80.0, nmol=1e-3, damping=50.0, floor=-1.0, fixed=(0,))
        + icosphere_text(subdivisions=0, name="b", offset=12, header=False, translate=(0.5, 0, 0)))
LINES = BASE.splitlines()
TOKENS = ["v", "f", "o", "g", "END_OBJECT", "fixed", "k_structural", "damping", "nmol", "total_weight", "scale",
          "translate", "floor", "gravity", "temperature", "contact", "floor_model", "smooth", "on", "off", "#",
          "1", "-1", "0", "12", "13", "1e30", "-1e308", "nan", "inf", "99999999999999999999999", "1/2/3", "0.5",
          "\t", "/", "\x00", "é", "-0"]

mutation = st.one_of(
    st.tuples(st.just("delete"), st.integers(0, len(LINES) - 1)),
    st.tuples(st.just("duplicate"), st.integers(0, len(LINES) - 1)),
    st.tuples(st.just("swap"), st.integers(0, len(LINES) - 1), st.integers(0, len(LINES) - 1)),
    st.tuples(st.just("token"), st.integers(0, len(LINES) - 1), st.integers(0, 4), st.sampled_from(TOKENS)),
    st.tuples(st.just("insert"), st.integers(0, len(LINES)), st.lists(st.sampled_from(TOKENS), max_size=5)),
    st.tuples(st.just("text"), st.integers(0, len(LINES) - 1), st.text(max_size=12)),
)


def _mutate(muts):
    lines = list(LINES)
    for m in muts:
        if not lines:
            break
        kind = m[0]
        i = min(m[1], len(lines) - 1)
        if kind == "delete":
            del lines[i]
        elif kind == "duplicate":
            lines.insert(i, lines[i])
        elif kind == "swap":
            j = min(m[2], len(lines) - 1)
            lines[i], lines[j] = lines[j], lines[i]
        elif kind == "token":
            toks = lines[i].split() or [""]
            toks[min(m[2], len(toks) - 1)] = m[3]
            lines[i] = " ".join(toks)
        elif kind == "insert":
            lines.insert(min(m[1], len(lines)), " ".join(m[2]))
        else:
            lines[i] = lines[i] + m[2]
    return "\n".join(lines) + "\n"


def _check_invariants(scene):
    """What an accepted scene promises (jaxplush.scene.parse): closed outward meshes with volume,
    finite coordinates, in-range indices and valid parameter values."""
    assert scene.n_objects >= 1 and np.isfinite(scene.vertices).all()
    assert scene.faces.min() >= 0 and scene.faces.max() < scene.n_vertices
    assert (scene.volumes() > 0).all()
    p = scene.params
    assert (p.total_weight > 0).all() and (p.k_structural >= 0).all() and (p.nmol >= 0).all()
    assert ((p.damping == 0) | (p.damping >= 1)).all()
    for o in scene.objects:
        a, b = o.vertex_slice
        assert all(a <= i < b for i in o.fixed)
    assert len(set(scene.object_names)) == scene.n_objects


def _parse(text):
    t = time.perf_counter()
    try:
        scene = jaxplush.parse_scene(text, "fuzz.obj")
    except SceneError as e:
        assert str(e).startswith("fuzz.obj")
        scene = None
    assert time.perf_counter() - t < TIME_BOUND
    if scene is not None:
        _check_invariants(scene)
    return scene


@settings(max_examples=DEFAULT_EXAMPLES, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(mutation, min_size=1, max_size=4))
def test_mutated_scenes_are_accepted_or_scene_errors(muts):
    with warnings_ignored():
        _parse(_mutate(muts))


@settings(max_examples=DEFAULT_EXAMPLES, deadline=None)
@given(st.binary(max_size=300))
def test_arbitrary_bytes_are_scene_errors(data):
    with warnings_ignored():
        try:
            jaxplush.parse_scene(data, "fuzz.obj")
        except SceneError:
            pass


@pytest.mark.fuzz
@settings(max_examples=MANY, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(mutation, min_size=1, max_size=8))
def test_many_mutated_scenes(muts):
    with warnings_ignored():
        _parse(_mutate(muts))


def warnings_ignored():
    import warnings
    cm = warnings.catch_warnings()
    cm.__enter__()
    warnings.simplefilter("ignore")

    class _Exit(contextlib.AbstractContextManager):
        def __exit__(self, *exc):
            cm.__exit__(*exc)
            return False
    return _Exit()


# --------------------------------------------------------------------------- targets

@pytest.fixture(scope="module")
def target_bytes(tmp_path_factory):
    scene = jaxplush.parse_scene(icosphere_text(subdivisions=1, nmol=1e-3), "<ball>")
    path = tmp_path_factory.mktemp("fuzz") / "t.h5"
    make_target(scene, 30, 1e-3, 10).save(path, scene)
    return scene, path.read_bytes()


def _load(scene, path):
    t = time.perf_counter()
    try:
        tgt = load_target(path, scene)
    except TrajectoryError as e:
        assert str(path) in str(e)
        tgt = None
    assert time.perf_counter() - t < TIME_BOUND
    if tgt is not None:
        assert np.isfinite(tgt.data).all() and (np.diff(tgt.steps) > 0).all() and tgt.dt > 0
        assert tgt.data.shape[0] == len(tgt.steps) and tgt.data.shape[2] == 3


@settings(max_examples=DEFAULT_EXAMPLES, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.lists(st.tuples(st.integers(0, 10 ** 6), st.integers(1, 255)), min_size=1, max_size=4))
def test_corrupted_targets_are_loaded_or_trajectory_errors(target_bytes, tmp_path, flips):
    scene, raw = target_bytes
    bad = bytearray(raw)
    for off, x in flips:
        bad[off % len(bad)] ^= x
    path = tmp_path / "bad.h5"
    path.write_bytes(bytes(bad))
    _load(scene, path)


@pytest.mark.fuzz
@settings(max_examples=MANY, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.lists(st.tuples(st.integers(0, 10 ** 6), st.integers(1, 255)), min_size=1, max_size=8))
def test_many_corrupted_targets(target_bytes, tmp_path, flips):
    test_corrupted_targets_are_loaded_or_trajectory_errors.hypothesis.inner_test(target_bytes, tmp_path, flips)


arrays = st.one_of(
    st.just(None),
    st.sampled_from([np.zeros((2, 42, 3)), np.ones((1, 42, 3), bool), np.full((2, 42, 3), np.nan),
                     np.zeros((2, 41, 3)), np.zeros((0, 42, 3)), np.zeros((2, 42)), np.full((2, 42, 3), 1e30),
                     np.array(["a", "b"]), np.zeros((2, 42, 3), np.int8)]))
times = st.one_of(st.just(None), st.sampled_from([np.array([0.01, 0.02]), np.array([0.02, 0.01]),
                                                   np.array([0.01]), np.array([np.inf, 0.0]),
                                                   np.array([0.0105, 0.02]), np.array([1e30, 2e30])]))


@settings(max_examples=DEFAULT_EXAMPLES, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(arrays, times, st.sampled_from([None, 1e-3, -1.0, 0.0, np.nan, "x"]),
       st.sampled_from([None, 0.001, -1.0, np.inf]))
def test_generated_targets_are_loaded_or_trajectory_errors(target_bytes, tmp_path, pos, t, dt, noise):
    scene, _ = target_bytes
    path = tmp_path / "gen.h5"
    with h5py.File(path, "w") as f:
        if pos is not None:
            # h5py has no numpy-unicode type: store strings as HDF5 strings (what a user's file would hold)
            f["positions"] = pos.astype(object) if pos.dtype.kind == "U" else pos
        if t is not None:
            f["times"] = t
        if dt is not None:
            f.attrs["dt"] = dt
        if noise is not None:
            f.attrs["noise"] = noise
    _load(scene, path)


# --------------------------------------------------------------------------- the CLI's exit codes

@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.lists(mutation, min_size=1, max_size=3))
def test_cli_exit_codes_on_mutated_scenes(tmp_path, muts):
    path = tmp_path / "s.obj"
    path.write_text(_mutate(muts), encoding="utf-8", errors="surrogatepass")
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        rc = cli.main(["info", str(path)])
    assert rc in (0, 2), err.getvalue()
    assert "Traceback" not in err.getvalue()
    if rc == 2:
        assert err.getvalue().startswith("jaxplush info: error: ") and err.getvalue().count("\n") == 1


@pytest.mark.fuzz
@settings(max_examples=max(MANY // 10, 25), deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.lists(mutation, min_size=1, max_size=8))
def test_many_cli_exit_codes(tmp_path, muts):
    test_cli_exit_codes_on_mutated_scenes.hypothesis.inner_test(tmp_path, muts)
