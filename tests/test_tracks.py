"""Tracked points as a fitting target ("tracks"): chosen vertices, or points on faces by barycentric
coordinates, observed with correspondence (NaN rows: not seen in that frame). They round-trip
through HDF5, are validated before tracing, give a loss and residuals that vanish at the truth
and agree with each other, a gradient that matches finite differences, a sweep whose minimum is
the truth, and a default fit that recovers k and nmol; ``jaxplush capture --tracks`` writes them."""

from __future__ import annotations

import dataclasses
import json
import warnings

import h5py
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxplush
from conftest import assert_gradient_matches_fd, icosphere_scene, icosphere_text
from jaxplush.errors import TrajectoryError
from jaxplush.fitting import fitter as F
from jaxplush.fitting.objective import losses
from jaxplush.fitting.judge.identifiability import frames_at_steps
from jaxplush.fitting.sweep import sweep
from jaxplush.fitting.targets import Target, load_target, make_target

DT, STEPS, EVERY = 1e-3, 60, 10
K, NMOL = 100.0, 2e-4


def _scene(**kw):
    """42-vertex pressurised ball hanging from vertex 0."""
    return icosphere_scene(subdivisions=1, k=K, nmol=NMOL, damping=2.0, fixed=(0,), **kw)


@pytest.fixture(scope="module")
def ball():
    scene = _scene()
    return scene, make_target(scene, STEPS, DT, EVERY, tracks=20, seed=3)


def _hide(target, rows):
    """The target with the given (frame, track) rows not seen (NaN)."""
    tr = target.tracks.copy()
    for t, i in rows:
        tr[t, i] = np.nan
    return dataclasses.replace(target, tracks=tr)


def _vertex_target(target, vertices):
    """A tracks target of the given vertices, taken from a positions target."""
    v = np.asarray(vertices)
    return Target(positions=None, points=None, steps=target.steps, times=target.times, dt=target.dt,
                  path="<vertices>", tracks=target.positions[:, v], track_vertices=np.repeat(v[:, None], 3, 1),
                  track_weights=np.tile([1.0, 0.0, 0.0], (len(v), 1)))


# --------------------------------------------------------------------------- files

def test_face_tracks_round_trip_and_load_from_the_face_form(ball, tmp_path):
    scene, target = ball
    assert target.kind == "tracks" and target.positions is None and target.tracks.shape == (6, 20, 3)
    t = _hide(target, [(1, 3), (4, 0)])
    path = tmp_path / "tracks.h5"
    t.save(path, scene)
    with h5py.File(path) as f:
        assert "track_vertices" in f and "track_weights" in f and "track_vertex" not in f
    back = load_target(path, scene)
    assert back.kind == "tracks" and back.data is back.tracks
    np.testing.assert_array_equal(back.tracks, t.tracks)
    np.testing.assert_array_equal(back.track_vertices, t.track_vertices)
    np.testing.assert_array_equal(back.track_weights, t.track_weights)
    assert back.observed.sum() == t.tracks.shape[0] * t.tracks.shape[1] - 2
    # the form a tracker (or jaxplush capture) writes: a face and barycentric coordinates
    faces = np.asarray(scene.faces)
    face = np.array([faces.tolist().index(row) for row in t.track_vertices.tolist()])
    alt = tmp_path / "faces.h5"
    with h5py.File(alt, "w") as f:
        f["tracks"], f["times"], f["track_face"], f["track_barycentric"] = t.tracks, t.times, face, t.track_weights
        f.attrs["dt"] = DT
    again = load_target(alt, scene)
    np.testing.assert_array_equal(again.track_vertices, t.track_vertices)
    np.testing.assert_array_equal(again.track_weights, t.track_weights)
    # select and on_grid keep the tracks
    sub = back.select([0, 2])
    assert sub.kind == "tracks" and sub.tracks.shape == (2, 20, 3)
    assert back.on_grid(DT / 2).kind == "tracks"


def test_vertex_tracks_round_trip_as_track_vertex(tmp_path):
    scene = _scene()
    t = _vertex_target(make_target(scene, STEPS, DT, EVERY), [0, 7, 41])
    path = tmp_path / "v.h5"
    t.save(path, scene)
    with h5py.File(path) as f:
        assert f["track_vertex"][()].tolist() == [0, 7, 41] and "track_weights" not in f
    back = load_target(path, scene)
    np.testing.assert_array_equal(back.track_vertices, t.track_vertices)
    np.testing.assert_array_equal(back.track_weights, t.track_weights)
    np.testing.assert_array_equal(back.tracks, t.tracks)


def test_a_file_with_several_kinds_prefers_positions_then_mixed(ball, tmp_path):
    scene, target = ball
    path = tmp_path / "both.h5"
    target.save(path, scene, extra={"points": target.tracks})
    assert load_target(path, scene).kind == "mixed"                 # points and tracks: fitted together
    assert load_target(path, scene, kind="points").kind == "points"
    assert load_target(path, scene, kind="tracks").kind == "tracks"
    target.save(path, scene, extra={"points": target.tracks, "positions": make_target(scene, STEPS, DT, EVERY).positions})
    assert load_target(path, scene).kind == "positions"
    with pytest.raises(TrajectoryError, match="'tracks'"):
        load_target(path, scene, kind="markers")


def _write(path, target, **changes):
    """A face-form tracks file of ``target`` with datasets replaced (None: left out)."""
    data = dict(tracks=target.tracks, times=target.times, track_face=np.arange(target.tracks.shape[1]),
                track_barycentric=np.tile([0.2, 0.3, 0.5], (target.tracks.shape[1], 1)))
    data.update(changes)
    with h5py.File(path, "w") as f:
        for k, v in data.items():
            if v is not None:
                f[k] = v
        f.attrs["dt"] = DT
    return path


@pytest.mark.parametrize("change, match", [
    (dict(track_face=lambda m: np.r_[np.arange(m - 1), 80]), r"'track_face' has 80 at track 19.*80 faces"),
    (dict(track_face=lambda m: np.arange(m - 1)), r"'track_face' must have shape \[20\]"),
    (dict(track_barycentric=lambda m: np.tile([0.5, 0.6, -0.1], (m, 1))), r"'track_barycentric' row 0"),
    (dict(track_barycentric=lambda m: np.tile([0.3, 0.3, 0.3], (m, 1))), r"'track_barycentric' row 0.*sum to 1"),
    (dict(track_barycentric=lambda m: np.ones((m, 2))), r"'track_barycentric' must have shape \[20, 3\]"),
    (dict(track_barycentric=lambda m: None), r"missing dataset 'track_barycentric'"),
    (dict(track_face=lambda m: None, track_barycentric=lambda m: None), r"needs its correspondence"),
    (dict(track_vertex=lambda m: np.arange(m)), r"two correspondences"),
    (dict(track_face=lambda m: None, track_barycentric=lambda m: None, track_vertex=lambda m: np.full(m, 42)),
     r"'track_vertex' has 42 at track 0.*42 vertices"),
])
def test_bad_correspondences_are_refused_naming_the_dataset(ball, tmp_path, change, match):
    scene, target = ball
    m = target.tracks.shape[1]
    path = _write(tmp_path / "bad.h5", target, **{k: f(m) for k, f in change.items()})
    with pytest.raises(TrajectoryError, match=match) as e:
        load_target(path, scene)
    assert "bad.h5" in str(e.value)


@pytest.mark.parametrize("edit, match", [
    (lambda tr: tr.__setitem__((2, 5, 1), np.nan), r"'tracks' has non-finite values \(first at frame 2, track 5\)"
                                                    r".*all three coordinates"),
    (lambda tr: tr.__setitem__((3, 1, 0), np.inf), r"'tracks' has non-finite values \(first at frame 3, track 1\)"),
    (lambda tr: tr.__setitem__((slice(None), 4), np.nan), r"'tracks' never sees track 4"),
    (lambda tr: tr.fill(np.nan), r"'tracks' holds no points"),
])
def test_bad_track_values_are_refused_and_an_unseen_frame_is_not(ball, tmp_path, edit, match):
    scene, target = ball
    tr = target.tracks.copy()
    edit(tr)
    with pytest.raises(TrajectoryError, match=match):
        load_target(_write(tmp_path / "v.h5", target, tracks=tr), scene)
    tr = target.tracks.copy()
    tr[2] = np.nan                                                 # a frame that sees nothing: fine
    assert load_target(_write(tmp_path / "ok.h5", target, tracks=tr), scene).observed[2].sum() == 0
    with pytest.raises(TrajectoryError, match=r"'tracks' must have shape \[T, M, 3\]"):
        load_target(_write(tmp_path / "s.h5", target, tracks=target.tracks[..., :2]), scene)


# --------------------------------------------------------------------------- positions, loss, residuals

def test_track_positions_of_vertices_and_of_points_on_faces():
    rng = np.random.default_rng(0)
    x = rng.normal(size=(10, 3))
    v = np.array([[4, 4, 4], [1, 2, 3]])
    w = np.array([[1.0, 0.0, 0.0], [0.2, 0.3, 0.5]])
    expect = np.stack([x[4], 0.2 * x[1] + 0.3 * x[2] + 0.5 * x[3]])
    np.testing.assert_allclose(losses.track_positions(x, v, w), expect, rtol=1e-15)
    got = np.asarray(losses.track_positions(jnp.asarray(x, jnp.float32), v, jnp.asarray(w, jnp.float32)))
    np.testing.assert_allclose(got, expect, rtol=1e-6, atol=1e-6 * np.abs(expect).max())


def _frames(scene, target, params=None):
    sim = jaxplush.make_simulator(scene, DT)
    p = sim.params(params)
    fr, _ = frames_at_steps(sim, p, sim.init_fn(p), tuple(int(s) for s in target.steps))
    return sim, np.asarray(fr, np.float64)


def test_loss_and_residuals_vanish_at_the_truth_and_agree_elsewhere(ball, x64):
    scene, _ = ball
    target = make_target(scene, STEPS, DT, EVERY, tracks=20, seed=3)   # float64
    t = _hide(target, [(0, 1), (0, 2), (3, 7), (5, 19)])           # frames see different numbers of tracks
    sim, frames = _frames(scene, t)
    assert sim.dtype == jnp.float64
    loss = losses.make_loss(t, sim.topology, sim.dtype)
    res = losses.make_residual(t, sim.topology, loss)
    assert res.kind == "tracks" and res.per_frame == 3 * 20 and res.n == t.n_frames * 60 and res.near_fn is None
    total = jax.jit(lambda x, aux: jnp.sum(jax.vmap(loss.loss_fn)(x, aux)))
    motion = np.sqrt(loss.scale2)                                  # RMS track motion from the rest shape, m
    assert abs(float(total(jnp.asarray(frames), loss.aux))) < 1e-20
    assert np.abs(np.asarray(res.fn(jnp.asarray(frames)))).max() < 1e-10   # normalised: relative to the motion
    # a wrong shape: sum(r²) is the loss, every seen track weighed alike, unseen rows 0
    wrong = frames * 1.02 + 0.003
    r = np.asarray(res.fn(jnp.asarray(wrong)), np.float64)
    value = float(total(jnp.asarray(wrong), loss.aux))
    assert value > 1e-3 and np.sum(r * r) == pytest.approx(value, rel=1e-10)
    seen = t.observed
    assert np.all(r.reshape(t.n_frames, 20, 3)[~seen] == 0)
    sim_tr = np.stack([losses.track_positions(x, t.track_vertices, t.track_weights) for x in wrong])
    by_hand = np.sum((sim_tr - t.tracks)[seen] ** 2) / (seen.sum() * loss.scale2)
    assert value == pytest.approx(by_hand, rel=1e-10)
    assert motion > 0 and loss.normalisation == "motion"
    g = jax.grad(total)(jnp.asarray(wrong), loss.aux)
    assert np.all(np.isfinite(np.asarray(g))) and float(jnp.abs(g).max()) > 0


def test_gradient_matches_finite_differences(ball, x64):
    scene, target = ball
    t = _hide(target, [(0, 1), (3, 7)])
    start = _scene().replace(params=scene.params._replace(k_structural=scene.params.k_structural * 1.3,
                                                           nmol=scene.params.nmol * 0.8))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        prob = F.build_problem(start, t, ("k_structural", "nmol"), noise_free=True)
    assert prob.sim.dtype == jnp.float64
    f = jax.jit(prob.loss_fn)
    theta = np.asarray(prob.theta0, np.float64)
    g = np.asarray(jax.grad(f)(jnp.asarray(theta)), np.float64)
    assert np.all(np.isfinite(g)) and np.linalg.norm(g) > 0
    assert_gradient_matches_fd(lambda th: float(f(jnp.asarray(th))), theta, g, h=1e-4, rtol=1e-6)


# --------------------------------------------------------------------------- sweep and fit

def test_a_sweep_against_tracks_has_its_minimum_at_the_truth(ball):
    scene, target = ball
    t = _hide(target, [(0, 1), (3, 7), (5, 19)])
    res = sweep(scene, {"k": [70.0, 85.0, K, 115.0, 130.0]}, steps=STEPS, dt=DT, target=t, progress=False, batch=8)
    assert res.target_kind == "tracks"
    best = res.best()
    assert best["k_structural"] == K
    second = np.sort(res.loss)[1]
    assert best["loss"] < 1e-6 * second
    # one point against a direct evaluation: the mean over every seen track of its squared distance
    _, frames = _frames(scene, t, scene.params._replace(k_structural=np.array([70.0])))
    sim_tr = np.stack([losses.track_positions(x, t.track_vertices, t.track_weights) for x in frames])
    direct = np.mean(np.sum((sim_tr - t.tracks)[t.observed] ** 2, axis=-1))
    assert res.loss[0] == pytest.approx(direct, rel=1e-3)


def test_a_default_fit_to_20_tracked_points_recovers_k_and_nmol(ball):
    scene, target = ball
    names = ("k_structural", "nmol")
    p = scene.params
    start = scene.replace(params=p._replace(k_structural=p.k_structural * 1.5, nmol=p.nmol * 0.7))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = F.fit(start, target, names)
    errors = {n: res.values[n][0] / getattr(p, n)[0] - 1 for n in names}
    assert max(abs(e) for e in errors.values()) < 0.02, (errors, res.status)
    assert res.settings["target_kind"] == "tracks"
    assert res.identifiability is not None and res.identifiability.determined.all()


# --------------------------------------------------------------------------- capture CLI

def simulated_capture(tmp_path, *capture_args):
    """A pinned 42-vertex ball (``ball.obj``) simulated for 40 steps (``ball.h5``) and captured by
    ``jaxplush capture`` (camera at (0, 0, 0.8), 32 x 24 rays, 1 mm noise, seed 2, and
    ``capture_args``) into ``scan.h5``: (scene path, capture path, the capture's stdout)."""
    from test_cli import run_cli
    scene_path = tmp_path / "ball.obj"
    scene_path.write_text(icosphere_text(subdivisions=1, k=K, nmol=NMOL, damping=2.0, fixed=(0,)))
    traj = tmp_path / "ball.h5"
    rc, _, err = run_cli("simulate", scene_path, "--steps", 40, "--dt", DT, "--save-every", 10, "--out", traj,
                         "--quiet")
    assert rc == 0, err
    out = tmp_path / "scan.h5"
    rc, stdout, err = run_cli("capture", traj, "--eye", "0,0,0.8", "--size", "32x24", "--noise", "0.001",
                              "--seed", "2", *capture_args, "--out", out)
    assert rc == 0, err
    return scene_path, out, stdout


def test_capture_writes_a_loadable_tracks_target(tmp_path):
    from jaxplush import cli
    from test_cli import run_cli
    scene_path, out, stdout = simulated_capture(tmp_path, "--dropout", "0.3", "--tracks", "25")
    traj = tmp_path / "ball.h5"
    assert "25 tracked points" in stdout
    scene = jaxplush.load_scene(scene_path)
    assert load_target(out, scene).kind == "mixed"                 # the scan and the tracks, together
    assert load_target(out, scene, kind="points").kind == "points"
    t = load_target(out, scene, kind="tracks")
    assert t.kind == "tracks" and t.tracks.shape == (5, 25, 3) and t.noise == 0.001
    seen = t.observed
    assert seen.any(axis=0).all() and 0.4 < seen.mean() < 0.95      # dropped at about 30%, each seen once
    with h5py.File(out) as f, h5py.File(traj) as g:
        face, bary = f["track_face"][()], f["track_barycentric"][()]
        pos = g["positions"][()]
    np.testing.assert_array_equal(t.track_vertices, np.asarray(scene.faces)[face])
    truth = np.stack([losses.track_positions(x, t.track_vertices, bary) for x in pos])
    err = np.abs(t.tracks - truth)[seen]
    assert err.max() < 6 * 0.001 and 0.5e-3 < np.sqrt(np.mean(err ** 2)) < 1.5e-3
    rc, _, err = run_cli("capture", traj, "--eye", "0,0,0.8", "--tracks", "-1", "--out", tmp_path / "no.h5")
    assert rc == cli.EXIT_USAGE and "--tracks" in err and not (tmp_path / "no.h5").exists()
    # jaxplush-fit fits them when asked (--target-kind), from a start 30% off in k
    from jaxplush.fitting import cli as fit_cli
    from jaxplush.fitting.io import load_fit
    start = tmp_path / "start.obj"
    start.write_text(icosphere_text(subdivisions=1, k=1.3 * K, nmol=NMOL, damping=2.0, fixed=(0,)))
    fit = tmp_path / "fit.h5"
    rc = fit_cli.main([str(start), str(out), "--target-kind", "tracks", "--params", "k", "--out", str(fit),
                       "--quiet"])
    assert rc in (0, fit_cli.EXIT_NOT_CONVERGED)
    assert json.loads(load_fit(fit)["attrs"]["settings"])["target_kind"] == "tracks"


def test_tracks_belong_to_their_objects_and_have_no_node_states_to_shoot_from():
    """The per-object global stage scores each object by its own tracks; multiple shooting falls
    back as for point clouds (no node states)."""
    from conftest import icosphere_text
    from jaxplush.fitting.stages import objects
    from jaxplush.fitting.objective import shooting
    two = icosphere_text(name="a", translate=(-1, 0, 0), nmol=1e-4, fixed=(0,)) + icosphere_text(
        name="b", translate=(1, 0, 0), nmol=1e-4, k=80.0, offset=42, header=False, fixed=(0,))
    scene = jaxplush.parse_scene(two, "<two>")
    t = make_target(scene, 20, DT, 10, tracks=12, seed=1)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        prob = F.build_problem(scene, t, ("k_structural",), noise_free=True)
    owner = objects.residual_objects(prob)
    expect = np.asarray(scene.object_id)[t.track_vertices[:, 0]]
    np.testing.assert_array_equal(owner, np.tile(np.repeat(expect, 3), t.n_frames))
    assert objects.suits(prob) and set(expect.tolist()) == {0, 1}
    assert "tracked points" in shooting.why_not(prob)


def test_the_identifiability_report_counts_each_seen_track_coordinate(ball):
    from jaxplush.fitting.judge.result import identifiability_at
    scene, target = ball
    t = _hide(target, [(0, 1), (3, 7), (5, 19)])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        prob = F.build_problem(scene, t, ("k_structural", "nmol"), noise_free=True)
    rep = identifiability_at(prob, prob.theta0)
    assert rep.n_data == 3 * int(t.observed.sum())
    assert rep.determined.all() and np.all(rep.sensitivity > 0) and np.isfinite(rep.condition)
    assert rep.sigma < 1e-3 * np.sqrt(prob.loss.scale2)              # at the truth: rounding only
