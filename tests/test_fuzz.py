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


# --------------------------------------------------------------------------- the newer inputs
# driven paths and their release times, controls, tracks and ragged clouds, the noise attribute and
# option, and --shooting: each with extreme finite values as well as malformed ones. An accepted
# input must then build its simulator and loss (nothing is compiled); a refused one is a
# JaxplushError naming the file (or the option). The sweep's, capture's and viewer's options are
# fuzzed in their own sections below.

EXTREME = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True, width=64),
    st.sampled_from([0.0, -0.0, 5e-324, 1e-300, 1e-30, 1e-9, 1e-3, 0.5, 1e9, 1e30, 9e29, 1e300,
                     1.7976931348623157e308, -1e300, -1.0]))
TOKEN = st.one_of(EXTREME.map(repr), st.sampled_from(["x", "", "1e", "0x10", "nan", "inf", "-inf", "-", "1/2", "1e999"]))
FEW = 15
FUZZ_DT = 5e-4


def _small_fit_scene():
    return jaxplush.parse_scene(icosphere_text(subdivisions=0, damping=500.0), "fuzz.obj")


def _build(scene, target, **kw):
    """build_problem: a Problem, or None after a JaxplushError (never another exception)."""
    import warnings
    from jaxplush.errors import JaxplushError
    from jaxplush.fitting import fitter as F
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            prob = F.build_problem(scene, target, ("k_structural",), **kw)
    except JaxplushError:
        return None
    assert np.isfinite(prob.loss.scale2) and prob.loss.scale2 > 0
    return prob


def _driven_case(tmp_path, until, offsets, times):
    v0 = trimesh_vertex0()
    rows = ["t,c0,c1,c2"] + [f"{t},{v0[0] + o!r},{v0[1]!r},{v0[2]!r}" for t, o in zip(times, offsets)]
    (tmp_path / "p.csv").write_text("\n".join(rows) + "\n")
    line = "driven p.csv 1" + ("" if until is None else f" until {until}")
    path = tmp_path / "d.obj"
    path.write_text(icosphere_text(subdivisions=0, extra=line))
    from jaxplush.errors import JaxplushError
    try:
        scene = jaxplush.load_scene(path)
        jaxplush.make_simulator(scene, FUZZ_DT)
    except JaxplushError as e:
        assert str(e).startswith(str(path)), str(e)


def trimesh_vertex0():
    import trimesh
    return trimesh.creation.icosphere(subdivisions=0, radius=0.1).vertices[0].tolist()


driven_args = (st.one_of(st.none(), TOKEN), st.lists(EXTREME, min_size=1, max_size=3),
               st.sampled_from([["0.0", "1.0", "2.0"], ["0.0", "0.0", "1.0"], ["1e300", "1e301", "1e302"],
                                ["-1e30", "0.0", "1e30"], ["nan", "1", "2"], ["0", "5e-324", "1e-323"]]))


@settings(max_examples=FEW, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(*driven_args)
def test_driven_paths_and_release_times_are_accepted_or_scene_errors(tmp_path, until, offsets, times):
    _driven_case(tmp_path, until, offsets, times[:len(offsets)])


@pytest.mark.fuzz
@settings(max_examples=MANY // 4, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(*driven_args)
def test_many_driven_paths(tmp_path, until, offsets, times):
    _driven_case(tmp_path, until, offsets, times[:len(offsets)])


@pytest.fixture(scope="module")
def fit_case(tmp_path_factory):
    """A 12-vertex ball and its 3-frame positions target (two frames after the start)."""
    scene = _small_fit_scene()
    d = tmp_path_factory.mktemp("fuzz_fit")
    target = make_target(scene, 20, FUZZ_DT, 10)
    target.save(d / "t.h5", scene)
    (d / "s.obj").write_text(icosphere_text(subdivisions=0, damping=500.0))
    return scene, target, d


def _controls_case(fit_case, tmp_path, until, value, times):
    scene, target, d = fit_case
    path = tmp_path / "c.h5"
    path.write_bytes((d / "t.h5").read_bytes())
    with h5py.File(path, "a") as f:
        g = f.create_group("controls")
        g["vertices"] = np.array([3])
        g["times"] = np.asarray(times, np.float64)
        g["positions"] = np.broadcast_to(scene.vertices[3] + value, (len(times), 1, 3)).copy()
        if until is not None:
            g.attrs["until"] = until
    try:
        loaded = load_target(path, scene)
    except TrajectoryError as e:
        assert e.path == str(path)
        return
    _build(scene, loaded)


controls_args = (st.one_of(st.none(), EXTREME), EXTREME,
                 st.sampled_from([[0.0, 0.01], [0.0], [0.0, 1e300], [1e-300, 2e-300], [0.0, 0.01, 0.02]]))


@settings(max_examples=FEW, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(*controls_args)
def test_controls_are_loaded_and_built_or_trajectory_errors(fit_case, tmp_path, until, value, times):
    _controls_case(fit_case, tmp_path, until, value, times)


@pytest.mark.fuzz
@settings(max_examples=MANY // 4, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(*controls_args)
def test_many_controls(fit_case, tmp_path, until, value, times):
    _controls_case(fit_case, tmp_path, until, value, times)


def _cloud_case(fit_case, tmp_path, kind, values, holes, index, noise):
    scene, target, d = fit_case
    path = tmp_path / "k.h5"
    t, m = 2, 4
    data = np.broadcast_to(np.asarray(values + [0.0] * (3 - len(values)))[:3], (t, m, 3)).copy()
    data += scene.vertices[:m][None] if np.all(np.isfinite(data)) and np.abs(data).max() < 1e3 else 0.0
    for frame, row in holes:                                        # NaN rows: no point / not seen
        data[frame % t, row % m] = np.nan
    with h5py.File(path, "w") as f:
        f[kind] = data
        f["times"] = np.array([0.005, 0.01])
        if kind == "tracks":
            f["track_vertex"] = np.array([0, 1, 2, index])
        if noise is not None:
            f.attrs["noise"] = noise
    try:
        loaded = load_target(path, scene, kind=kind)
    except TrajectoryError as e:
        assert e.path == str(path)
        return
    _build(scene, loaded)


cloud_args = (st.sampled_from(["points", "tracks"]), st.lists(EXTREME, min_size=1, max_size=3),
              st.lists(st.tuples(st.integers(0, 3), st.integers(0, 7)), max_size=6),
              st.sampled_from([3, 11, 12, -1, 2 ** 40]), st.one_of(st.none(), EXTREME))


@settings(max_examples=FEW, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(*cloud_args)
def test_tracks_and_ragged_clouds_are_loaded_and_built_or_trajectory_errors(fit_case, tmp_path, kind, values,
                                                                            holes, index, noise):
    _cloud_case(fit_case, tmp_path, kind, values, holes, index, noise)


@pytest.mark.fuzz
@settings(max_examples=MANY // 4, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(*cloud_args)
def test_many_tracks_and_clouds(fit_case, tmp_path, kind, values, holes, index, noise):
    _cloud_case(fit_case, tmp_path, kind, values, holes, index, noise)


def _fit_cli_case(fit_case, tmp_path, noise, shooting):
    """``jaxplush-fit`` with a --noise and a --shooting that between them always refuse (every
    --shooting is longer than the target's two frames after its start, or malformed; a valid
    --noise leaves the refusal to it): exit 2, one line, nothing written."""
    from jaxplush.fitting import cli as fit_cli
    _, _, d = fit_case
    out = tmp_path / "FIT.h5"
    err = io.StringIO()
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(err):
        rc = fit_cli.main([str(d / "s.obj"), str(d / "t.h5"), "--noise", noise, "--shooting", shooting,
                           "--out", str(out), "--quiet"])
    assert rc == 2, err.getvalue()
    lines = err.getvalue().strip().splitlines()      # argparse's own errors come after its usage line
    assert lines[-1].startswith("jaxplush-fit: error: ") and "Traceback" not in err.getvalue(), err.getvalue()
    assert len(lines) == 1 or lines[0].startswith("usage: "), err.getvalue()
    assert not out.exists()


fit_cli_args = (TOKEN, st.one_of(st.integers(3, 10 ** 18).map(str), st.integers(-5, 1).map(str),
                                 st.sampled_from(["1e9", "x", "", "2.5", "-", "auto0", "1e999"])))


@settings(max_examples=FEW, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(*fit_cli_args)
def test_fit_noise_and_shooting_options_are_refused_cleanly(fit_case, tmp_path, noise, shooting):
    _fit_cli_case(fit_case, tmp_path, noise, shooting)


@pytest.mark.fuzz
@settings(max_examples=MANY // 4, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(*fit_cli_args)
def test_many_fit_noise_and_shooting_options(fit_case, tmp_path, noise, shooting):
    _fit_cli_case(fit_case, tmp_path, noise, shooting)


@settings(max_examples=FEW, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(EXTREME)
def test_noise_values_build_or_are_refused(fit_case, noise):
    """The noise option of the API: a Problem with a finite, positive loss scale, or a JaxplushError."""
    scene, target, _ = fit_case
    _build(scene, target, noise=noise)


# --------------------------------------------------------------------------- the sweep's options
# `jaxplush-fit sweep`'s checks (fitting/sweep/cli.py `_check`) run before JAX starts, anything is
# written or a coordinator is contacted: every combination of grid specs, distributed options,
# checkpoint paths and step options is accepted or a JaxplushError, and leaves no file behind.

GRID = st.one_of(
    st.builds(lambda a, b, n: f"k_structural={a}:{b}:{n}", TOKEN, TOKEN,
              st.one_of(st.integers(-3, 10 ** 13).map(str), st.sampled_from(["x", "1e3", ""]))),
    st.builds(lambda vals: "nmol=" + ",".join(vals), st.lists(TOKEN, min_size=1, max_size=3)),
    st.sampled_from(["k_structural=50:150:3", "damping=", "=1:2:3", "bogus=1:2:3", "k_structural", "k_structural=1:2"]))
DISTRIBUTED = st.one_of(st.just([]), st.builds(
    lambda c, n, i, t: ["--distributed"] + c + n + i + t,
    st.one_of(st.just([]), st.sampled_from(["not-an-address", "127.0.0.1:99999", "127.0.0.1:0", ":", "[::1]:80",
                                            "host:-1", "a:b:c", "127.0.0.1:1234", ""]).map(lambda s: ["--coordinator", s])),
    st.one_of(st.just([]), st.integers(-2, 10 ** 12).map(lambda n: ["--num-processes", str(n)])),
    st.one_of(st.just([]), st.integers(-2, 10 ** 12).map(lambda n: ["--process-id", str(n)])),
    st.one_of(st.just([]), TOKEN.map(lambda s: ["--connect-timeout", s]))))


def _sweep_case(fit_case, tmp_path, grids, distributed, checkpoint, steps, dt):
    from jaxplush.errors import JaxplushError
    from jaxplush.fitting.sweep import cli as sweep_cli
    _, _, d = fit_case
    (tmp_path / "afile").write_text("x")
    out = tmp_path / "S.h5"
    argv = [str(d / "s.obj"), "--steps", steps, "--dt", dt, "--out", str(out)] + \
        [a for g in grids for a in ("--grid", g)] + distributed + \
        ([] if checkpoint is None else ["--checkpoint", checkpoint.replace("TMP", str(tmp_path))])
    before = sorted(p.name for p in tmp_path.iterdir())
    err = io.StringIO()
    try:
        with contextlib.redirect_stderr(err):
            args = sweep_cli._parser().parse_args(sweep_cli.attach_negative_values(argv))
    except SystemExit as e:
        assert e.code == 2 and "Traceback" not in err.getvalue()
        return
    try:
        sweep_cli._check(args)
    except (JaxplushError, NotImplementedError) as e:
        assert "\n" not in str(e), str(e)
    assert sorted(p.name for p in tmp_path.iterdir()) == before


sweep_args = (st.lists(GRID, min_size=0, max_size=2), DISTRIBUTED,
              st.one_of(st.none(), st.sampled_from(["TMP/afile/sub", "/proc/x", "TMP/new/deeper", "TMP", "",
                                                    "TMP/S.h5"])),
              st.sampled_from(["10", "0", "-1", "1e3", "99999999999999999999"]),
              st.one_of(TOKEN, st.just("5e-4")))


@settings(max_examples=FEW, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(*sweep_args)
def test_sweep_options_are_checked_before_anything_starts(fit_case, tmp_path, grids, distributed, checkpoint,
                                                          steps, dt):
    _sweep_case(fit_case, tmp_path, grids, distributed, checkpoint, steps, dt)


@pytest.mark.fuzz
@settings(max_examples=MANY // 4, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(*sweep_args)
def test_many_sweep_options(fit_case, tmp_path, grids, distributed, checkpoint, steps, dt):
    _sweep_case(fit_case, tmp_path, grids, distributed, checkpoint, steps, dt)


# --------------------------------------------------------------------------- capture and view
# `jaxplush capture`'s camera and noise options and `jaxplush view --target`: exit 0 with a file of
# finite points (a row of NaN is a missing point), or exit 2 with one line and nothing written;
# never a traceback or a numpy RuntimeWarning.

VEC = st.one_of(st.builds(lambda a, b, c: f"{a},{b},{c}", TOKEN, TOKEN, TOKEN),
                st.sampled_from(["0,0.3,1", "0,1,0", "0,0,1", "0,0,0", "1,2", "a,b,c", "0,0.3,0", "1e300,0,0"]))


@pytest.fixture(scope="module")
def capture_case(tmp_path_factory):
    """A dropped 42-vertex ball (3 frames), a target of another scene and a damaged copy."""
    d = tmp_path_factory.mktemp("fuzz_capture")
    scene = jaxplush.parse_scene(icosphere_text(1, 0.1, translate=(0, 0.3, 0), floor=0.0), str(d / "ball.obj"))
    jaxplush.simulate(scene, 20, 5e-4, 10, progress=False).save(d / "ball.h5")
    other = _small_fit_scene()
    make_target(other, 20, FUZZ_DT, 10).save(d / "other.h5", other)
    raw = bytearray((d / "ball.h5").read_bytes())
    raw[600:700] = b"\xff" * 100
    (d / "damaged.h5").write_bytes(bytes(raw))
    return d


def _cli_case(argv, out, prog):
    import warnings
    out.unlink(missing_ok=True)                       # tmp_path is shared by a test's examples
    err = io.StringIO()
    with warnings.catch_warnings(record=True) as caught, contextlib.redirect_stdout(io.StringIO()), \
            contextlib.redirect_stderr(err):
        warnings.simplefilter("always")
        try:
            rc = cli.main([str(a) for a in argv])
        except SystemExit as e:                       # argparse's own errors
            rc = e.code
    text = err.getvalue()
    assert rc in (0, 2), text
    assert "Traceback" not in text and not [w for w in caught if issubclass(w.category, RuntimeWarning)], text
    if rc == 2:
        lines = text.strip().splitlines()
        assert lines[-1].startswith(f"jaxplush {prog}: error: ") or lines[-1].startswith("jaxplush: error: "), text
        assert len(lines) == 1 or lines[0].startswith("usage: "), text
        assert not out.exists()
    return rc


def _capture_case(capture_case, tmp_path, eye, look, up, fov, seed, noise, dropout):
    out = tmp_path / "scan.h5"
    argv = ["capture", capture_case / "ball.h5", "--eye", eye, "--out", out]
    for opt, val in (("--look-at", look), ("--up", up), ("--fov", fov), ("--seed", seed), ("--noise", noise),
                     ("--dropout", dropout)):
        if val is not None:
            argv += [opt, val]
    if _cli_case(argv, out, "capture") == 0:
        with h5py.File(out) as f:
            pts = f["points"][()]
        finite = np.isfinite(pts).all(axis=-1)
        assert (finite | np.isnan(pts).all(axis=-1)).all()        # a row is a point or no point


capture_args = (VEC, st.one_of(st.none(), VEC), st.one_of(st.none(), VEC), st.one_of(st.none(), TOKEN),
                st.one_of(st.none(), st.integers(-2, 2 ** 70).map(str), st.just("x")), st.one_of(st.none(), TOKEN),
                st.one_of(st.none(), TOKEN))


@settings(max_examples=FEW, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(*capture_args)
def test_capture_options_give_finite_points_or_clean_refusals(capture_case, tmp_path, eye, look, up, fov, seed,
                                                               noise, dropout):
    _capture_case(capture_case, tmp_path, eye, look, up, fov, seed, noise, dropout)


@pytest.mark.fuzz
@settings(max_examples=MANY // 4, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(*capture_args)
def test_many_capture_options(capture_case, tmp_path, eye, look, up, fov, seed, noise, dropout):
    _capture_case(capture_case, tmp_path, eye, look, up, fov, seed, noise, dropout)


def _view_case(capture_case, tmp_path, shown, target, max_frames):
    out = tmp_path / "v.html"
    argv = ["view", capture_case / shown, "--html", out] + ([] if target is None else ["--target",
                                                                                       capture_case / target])
    _cli_case(argv + ([] if max_frames is None else ["--max-frames", max_frames]), out, "view")


view_args = (st.sampled_from(["ball.h5", "other.h5", "damaged.h5", "missing.h5"]),
             st.one_of(st.none(), st.sampled_from(["ball.h5", "other.h5", "damaged.h5", "missing.h5"])),
             st.one_of(st.none(), st.sampled_from(["0", "-1", "1", "x", "1e9", "99999999999999999999"])))


@settings(max_examples=FEW, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(*view_args)
def test_viewer_inputs_are_shown_or_refused_cleanly(capture_case, tmp_path, shown, target, max_frames):
    pytest.importorskip("viser")
    _view_case(capture_case, tmp_path, shown, target, max_frames)


@pytest.mark.fuzz
@settings(max_examples=MANY // 10, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(*view_args)
def test_many_viewer_inputs(capture_case, tmp_path, shown, target, max_frames):
    pytest.importorskip("viser")
    _view_case(capture_case, tmp_path, shown, target, max_frames)
