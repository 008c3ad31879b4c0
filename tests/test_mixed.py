"""A scan with tracked points in one target (kind "mixed"): it round-trips through HDF5 and is the
default kind of a file holding both; malformed files are refused naming the file and the dataset;
its loss is the weighted sum of the two kinds' own losses (each normalised on its own) and its
residuals sum to it; the gradient matches finite differences; a default fit recovers k and nmol;
the identifiability report, the per-object residual owners (a coloured Jacobian equal to the
full one), a sweep and the command line (``--track-weight``) handle it."""

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
from jaxplush.errors import JaxplushError, TrajectoryError
from jaxplush.fitting import fitter as F
from jaxplush.fitting.objective import losses
from jaxplush.fitting.judge.identifiability import frames_at_steps
from jaxplush.fitting.targets import load_target, make_target

DT, STEPS, EVERY = 1e-3, 60, 10
K, NMOL = 100.0, 2e-4
N_POINTS, N_TRACKS = 60, 8


def _scene(**kw):
    """42-vertex pressurised ball hanging from vertex 0."""
    return icosphere_scene(subdivisions=1, k=K, nmol=NMOL, damping=2.0, fixed=(0,), **kw)


@pytest.fixture(scope="module")
def ball():
    scene = _scene()
    return scene, make_target(scene, STEPS, DT, EVERY, point_cloud=True, n_points=N_POINTS, tracks=N_TRACKS, seed=4)


def _hide(target, rows):
    """The target with the given (frame, track) rows of its tracks not seen (NaN)."""
    tr = target.tracks.copy()
    for t, i in rows:
        tr[t, i] = np.nan
    return dataclasses.replace(target, tracks=tr)


def _frames(scene, target, params=None):
    sim = jaxplush.make_simulator(scene, DT)
    p = sim.params(params)
    fr, _ = frames_at_steps(sim, p, sim.init_fn(p), [int(s) for s in target.steps])
    return sim, np.asarray(fr, np.float64)


# --------------------------------------------------------------------------- files

def test_round_trip_default_kind_and_parts(ball, tmp_path):
    scene, target = ball
    assert target.kind == "mixed" and target.positions is None
    assert target.data.shape == (6, N_POINTS + N_TRACKS, 3)
    pts, trk = target.parts
    assert pts.kind == "points" and trk.kind == "tracks" and pts.tracks is None and trk.points is None
    np.testing.assert_array_equal(target.data, np.concatenate([pts.points, trk.tracks], axis=1))
    path = tmp_path / "mixed.h5"
    _hide(target, [(2, 3)]).save(path, scene)
    back = load_target(path, scene)
    assert back.kind == "mixed" and back.track_weight == 1.0
    np.testing.assert_array_equal(back.points, target.points)
    np.testing.assert_array_equal(back.track_vertices, target.track_vertices)
    assert back.observed.sum() == back.data.shape[0] * back.data.shape[1] - 1
    assert load_target(path, scene, kind="points").kind == "points"
    assert load_target(path, scene, kind="tracks").kind == "tracks"
    assert back.select([0, 2]).kind == "mixed" and back.on_grid(DT / 2).kind == "mixed"
    with h5py.File(tmp_path / "scan.h5", "w") as f:
        f["points"], f["times"] = target.points, target.times
        f.attrs["dt"] = DT
    with pytest.raises(TrajectoryError, match=r"missing dataset 'tracks' \(a mixed target holds both") as e:
        load_target(tmp_path / "scan.h5", scene, kind="mixed")
    assert e.value.path == str(tmp_path / "scan.h5")


def _write(path, target, **changes):
    """A mixed file of ``target`` (tracks in the face form) with datasets replaced (None: left out)."""
    m = target.tracks.shape[1]
    data = dict(points=target.points, tracks=target.tracks, times=target.times, track_face=np.arange(m),
                track_barycentric=np.tile([0.2, 0.3, 0.5], (m, 1)))
    data.update(changes)
    with h5py.File(path, "w") as f:
        for k, v in data.items():
            if v is not None:
                f[k] = v
        f.attrs["dt"] = DT
    return path


@pytest.mark.parametrize("change, message", [
    (lambda t: dict(tracks=t.tracks[:-1]), r"'tracks' has 5 frames but 'points' has 6: a mixed target's scan and "
                                           r"tracks share the frames of 'times'"),
    (lambda t: dict(tracks=t.tracks[..., :2]), r"'tracks' must have shape \[T, M, 3\], got \[6, 8, 2\]"),
    (lambda t: dict(points=t.points[0]), r"'points' must have shape \[T, M, 3\], got \[60, 3\]"),
    (lambda t: dict(times=t.times[:-1]), r"'times' must have shape \[6\] \(one per frame of 'points' and 'tracks'\)"),
    (lambda t: dict(track_face=None, track_barycentric=None), r"'tracks' needs its correspondence"),
    (lambda t: dict(track_barycentric=np.tile([0.5, 0.6, -0.1], (8, 1))), r"'track_barycentric' row 0"),
    (lambda t: dict(track_face=np.full(8, 80)),
     r"'track_face' has 80 at track 0: not an index of the scene's 80 faces"),
    (lambda t: dict(tracks=np.where(np.arange(8)[None, :, None] == 5, np.array([np.nan, 0.0, 0.0]), t.tracks)),
     r"'tracks' has non-finite values \(first at frame 0, track 5\)"),
    (lambda t: dict(points=np.where(np.arange(60)[None, :, None] == 7, np.array([0.0, np.inf, 0.0]), t.points)),
     r"'points' has non-finite values \(first at frame 0, point 7\)"),
    (lambda t: dict(tracks=np.full_like(t.tracks, np.nan)), r"'tracks' holds no points"),
    (lambda t: dict(points=np.asarray(t.points.astype(str), dtype=object).astype(bytes)), r"'points' must be numeric"),
])
def test_malformed_mixed_targets_are_refused_naming_file_and_dataset(ball, tmp_path, change, message):
    scene, target = ball
    path = _write(tmp_path / "bad.h5", target, **change(target))
    with pytest.raises(TrajectoryError, match=message) as e:
        load_target(path, scene)
    assert e.value.path == str(path)


# --------------------------------------------------------------------------- loss and residuals

def test_the_loss_is_the_weighted_sum_of_its_parts_and_the_residuals_sum_to_it(ball, x64):
    """L = (L_points + w L_tracks) / (1 + w), each term normalised by its own motion (or noise), by
    hand: the points' mean squared distance to the surface over their own rest-shape mean, the
    tracks' mean squared distance over theirs; sum(r²) = L, each residual with its own norm."""
    scene, target = ball
    target = _hide(target, [(0, 1), (3, 5)])
    sim, frames = _frames(scene, target)
    wrong = frames * 1.02 + 0.003
    topo = sim.topology
    vf = losses.vertex_faces(topo.faces, topo.n_vertices)

    per_frame = jax.jit(jax.vmap(lambda x, p: jnp.mean(losses.point_surface_distance2(x, p, topo.faces, vf))))

    def points_term(x_frames):
        return float(np.mean(per_frame(jnp.asarray(x_frames), jnp.asarray(target.points))))

    seen = target.observed[:, N_POINTS:]

    def tracks_term(x_frames):
        sim_tr = np.stack([losses.track_positions(x, target.track_vertices, target.track_weights) for x in x_frames])
        return np.sum((sim_tr - target.tracks)[seen] ** 2) / seen.sum()

    rest = np.broadcast_to(topo.x0, frames.shape)
    s2_p, s2_t = points_term(rest), tracks_term(rest)
    total = jax.jit(lambda x, aux, fn: jnp.sum(jax.vmap(fn)(x, aux)), static_argnums=2)
    for w in (1.0, 3.0):
        t = dataclasses.replace(target, track_weight=w)
        loss = losses.make_loss(t, topo, sim.dtype)
        assert loss.kind == "mixed" and loss.normalisation == "motion"
        (a, c_p), (b, c_t) = loss.parts
        assert (c_p, c_t) == pytest.approx((1 / (1 + w), w / (1 + w)), rel=1e-15)
        assert (a, b) == pytest.approx((s2_p, s2_t), rel=1e-9)
        value = float(total(jnp.asarray(wrong), loss.aux, loss.loss_fn))
        by_hand = (points_term(wrong) / s2_p + w * tracks_term(wrong) / s2_t) / (1 + w)
        assert value > 1e-2 and value == pytest.approx(by_hand, rel=1e-9)
        # ... and the two kinds' own losses, weighed
        parts = [losses.make_loss(p, topo, sim.dtype) for p in t.parts]
        alone = [float(total(jnp.asarray(wrong), lo.aux, lo.loss_fn)) for lo in parts]
        assert value == pytest.approx(c_p * alone[0] + c_t * alone[1], rel=1e-12)
        # at the truth: (nearly) zero (a point whose face is not around its nearest vertex: not quite)
        assert float(total(jnp.asarray(frames), loss.aux, loss.loss_fn)) < 1e-4 * value
        res = losses.make_residual(t, topo, loss)
        assert res.per_frame == N_POINTS + 3 * N_TRACKS and res.n == 6 * res.per_frame and res.norm.shape == (res.n,)
        r = np.asarray(res.fn(jnp.asarray(wrong)), np.float64).reshape(6, res.per_frame)
        assert np.sum(r * r) == pytest.approx(value, rel=1e-9)
        assert np.all(r[:, N_POINTS:].reshape(6, N_TRACKS, 3)[~seen] == 0)
        # the normaliser: the RMS per coordinate (or point distance) that the loss stands for
        delta = 1e-3
        assert losses.rms_metres((delta ** 2 / s2_p + w * 3 * delta ** 2 / s2_t) / (1 + w), loss.scale2,
                                 "mixed") == pytest.approx(delta, rel=1e-12)


def test_noise_normalises_each_term_by_its_own_variance(ball, x64):
    """With a noise sigma both terms are normalised by it (sigma² per point distance, 3 sigma² per
    track), so the loss is near 1 at the truth and the normaliser is sigma²."""
    scene, _ = ball
    sigma = 1e-3
    noisy = make_target(scene, STEPS, DT, EVERY, point_cloud=True, n_points=400, tracks=200, seed=5, noise=sigma)
    sim, frames = _frames(scene, noisy)
    loss = losses.make_loss(noisy, sim.topology, sim.dtype)
    assert loss.normalisation == "noise" and loss.scale2 == pytest.approx(sigma ** 2, rel=1e-12)
    assert [s2 for s2, _ in loss.parts] == pytest.approx([sigma ** 2, 3 * sigma ** 2], rel=1e-12)
    value = float(jnp.sum(jax.vmap(loss.loss_fn)(jnp.asarray(frames), loss.aux)))
    # points: a normal component of the noise (1 per point on average); tracks: chi² / 3 (1 on average)
    assert 0.8 < value < 1.2, value


def test_gradient_matches_finite_differences(ball, x64):
    scene, target = ball
    t = _hide(target, [(0, 1), (3, 5)])
    start = _scene().replace(params=scene.params._replace(k_structural=scene.params.k_structural * 1.3,
                                                           nmol=scene.params.nmol * 0.8))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        prob = F.build_problem(start, t, ("k_structural", "nmol"), noise_free=True, track_weight=2.0)
    assert prob.sim.dtype == jnp.float64 and prob.target.track_weight == 2.0
    f = jax.jit(prob.loss_fn)
    theta = np.asarray(prob.theta0, np.float64)
    g = np.asarray(jax.grad(f)(jnp.asarray(theta)), np.float64)
    assert np.all(np.isfinite(g)) and np.linalg.norm(g) > 0
    assert_gradient_matches_fd(lambda th: float(f(jnp.asarray(th))), theta, g, h=1e-4, rtol=1e-6)


def test_a_shorter_horizon_holds_an_observation_of_each_part(ball):
    """The default fit's continuation fits the first frames first: a horizon reaches at least the
    first frame in which the tracks (here unseen in the first three) are seen."""
    scene, target = ball
    t = _hide(target, [(f, i) for f in range(3) for i in range(N_TRACKS)])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        prob = F.build_problem(scene, t, ("k_structural",), noise_free=True)
    assert prob.truncated(2).target.n_frames == 4 and prob.truncated(5).target.n_frames == 5
    assert prob.truncated(2).loss.kind == "mixed" and prob.truncated(2).target.parts[1].observed.sum() == N_TRACKS


def test_track_weight_applies_to_mixed_targets_only(ball):
    scene, target = ball
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for bad in (0.0, -1.0, float("nan"), True):
            with pytest.raises(JaxplushError, match="track weight must be a finite number > 0"):
                F.build_problem(scene, target, ("k_structural",), track_weight=bad)
        with pytest.raises(JaxplushError, match="this target is tracks alone"):
            F.build_problem(scene, target.parts[1], ("k_structural",), track_weight=2.0)


# --------------------------------------------------------------------------- fit, report, objects

def test_a_default_fit_to_a_scan_with_tracks_recovers_k_and_nmol(ball):
    from jaxplush.fitting.objective import shooting
    scene, target = ball
    names = ("k_structural", "nmol")
    p = scene.params
    start = scene.replace(params=p._replace(k_structural=p.k_structural * 1.5, nmol=p.nmol * 0.7))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = F.fit(start, target, names)
    errors = {n: res.values[n][0] / getattr(p, n)[0] - 1 for n in names}
    assert max(abs(e) for e in errors.values()) < 0.02, (errors, res.status)
    assert res.settings["target_kind"] == "mixed" and res.problem.loss.kind == "mixed"
    assert res.identifiability is not None and res.identifiability.determined.all()
    assert "scan with tracked points" in shooting.why_not(res.problem)


def test_the_identifiability_report_counts_the_scan_and_each_seen_track_coordinate(ball):
    from jaxplush.fitting.judge.result import identifiability_at
    scene, target = ball
    t = _hide(target, [(0, 1), (3, 5)])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        prob = F.build_problem(scene, t, ("k_structural", "nmol"), noise_free=True)
    rep = identifiability_at(prob, prob.theta0)
    assert rep.n_data == 3 * t.n_frames * scene.n_vertices + 3 * int(t.parts[1].observed.sum())
    assert rep.determined.all() and np.all(rep.sensitivity > 0) and np.isfinite(rep.condition)


def _two_balls(k_b=80.0):
    two = icosphere_text(name="a", translate=(-1, 0, 0), nmol=1e-4, fixed=(0,), extra="contact off") + icosphere_text(
        name="b", translate=(1, 0, 0), nmol=1e-4, k=k_b, offset=42, header=False, fixed=(0,))
    return jaxplush.parse_scene(two, "<two>")


def test_residuals_belong_to_their_objects_and_a_coloured_jacobian_is_the_full_one():
    """Each scan point's residual belongs to the object of its nearest vertex, each track's to its
    own object (per frame: the points, then the tracks); the evaluator reads the same owners off
    each run, so a coloured stencil gives the full stencil's Jacobian."""
    from jaxplush.fitting.stages import lmfit, objects, search
    from jaxplush.fitting.objective.evaluate import Evaluator
    scene = _two_balls()
    t = make_target(scene, 20, DT, 10, point_cloud=True, n_points=50, tracks=12, seed=1)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        prob = F.build_problem(scene, t, ("k_structural",), noise_free=True)
    assert not objects.suits(prob)
    ev = Evaluator(prob)
    assert ev.owners() is None and ev.colourable()
    theta = prob.theta0 + np.array([[0.05, -0.03]])
    e = ev(theta[None], keep_frames=True)
    owner = ev.point_owners(e.frames)[0]
    np.testing.assert_array_equal(owner, objects.residual_objects(prob, e.frames[0]))
    per_frame = owner.reshape(t.n_frames, 50 + 3 * 12)
    x = np.asarray(t.points, np.float64)[..., 0]
    np.testing.assert_array_equal(per_frame[:, :50], np.where(x < 0, 0, 1))
    expect = np.asarray(scene.object_id)[t.track_vertices[:, 0]]
    assert set(expect.tolist()) == {0, 1}
    np.testing.assert_array_equal(per_frame[:, 50:], np.tile(np.repeat(expect, 3), (t.n_frames, 1)))
    box = lmfit.default_box(prob)
    coloured = search.jacobian(ev, box, theta, 1e-3)
    full_ev = Evaluator(prob, share=ev, calibration=ev.calibration())
    full_ev.colour_misses = search.COLOUR_MISSES                        # colouring off
    full = search.jacobian(full_ev, box, theta, 1e-3)
    for j in range(theta.size):
        assert np.linalg.norm(full[:, j]) > 0 and np.max(np.abs(full[owner != j, j])) == 0.0
        np.testing.assert_allclose(coloured[:, j], full[:, j], rtol=0, atol=1e-6 * np.linalg.norm(full[:, j]))


# --------------------------------------------------------------------------- sweep and command line

def test_a_sweep_against_a_mixed_target_weighs_the_two_sweeps_as_the_fit(ball):
    """A sweep's loss against a mixed target is the fit's loss times its normaliser s² (m²): its
    scan's and its tracks' sweep losses, each over its own normaliser, weighed 1 / (1 + w) and
    w / (1 + w), so the weight moves the sweep's landscape exactly as it moves the fit's."""
    from jaxplush.fitting.objective import losses
    from jaxplush.fitting.sweep import sweep
    scene, target = ball
    topology = jaxplush.make_simulator(scene, DT).topology
    grid = {"k": [70.0, 85.0, K, 115.0, 130.0]}
    alone = [sweep(scene, grid, steps=STEPS, dt=DT, target=p, progress=False, batch=8).loss for p in target.parts]
    assert np.argmin(alone[1]) == 2                                    # the tracks: zero at the truth
    scales = [losses.loss_scale(p, topology)[0] for p in target.parts]
    for w in (3.0, 1e4):
        t = dataclasses.replace(target, track_weight=w)
        res = sweep(scene, grid, steps=STEPS, dt=DT, target=t, progress=False, batch=8)
        assert res.target_kind == "mixed"
        fit_loss = sum(c * a / s2 for c, a, s2 in zip(losses.part_weights(t), alone, scales))
        s2 = losses.make_loss(t, topology, np.float64).scale2
        np.testing.assert_allclose(res.loss, fit_loss * s2, rtol=1e-5)
        assert res.best()["k_structural"] == K


def test_capture_with_tracks_is_a_mixed_target_and_the_cli_weighs_it(tmp_path):
    from jaxplush.fitting import cli as fit_cli
    from jaxplush.fitting.io import load_fit
    from test_tracks import simulated_capture
    scene_path, out, _ = simulated_capture(tmp_path, "--tracks", "12")
    t = load_target(out, jaxplush.load_scene(scene_path))
    assert t.kind == "mixed" and t.tracks.shape == (5, 12, 3) and t.noise == 0.001
    start = tmp_path / "start.obj"
    start.write_text(icosphere_text(subdivisions=1, k=1.3 * K, nmol=NMOL, damping=2.0, fixed=(0,)))
    fit = tmp_path / "fit.h5"
    rc = fit_cli.main([str(start), str(out), "--params", "k", "--track-weight", "2", "--out", str(fit), "--quiet"])
    assert rc in (0, fit_cli.EXIT_NOT_CONVERGED)
    settings = json.loads(load_fit(fit)["attrs"]["settings"])
    assert settings["target_kind"] == "mixed"
    again = tmp_path / "again.h5"
    for args, message in ((["--track-weight", "0"], "--track-weight must be a positive number"),
                          (["--target-kind", "tracks", "--track-weight", "2"], "this target is tracks alone")):
        rc, _, err = run_cli_fit(fit_cli, [str(start), str(out), "--params", "k", "--out", str(again), *args])
        assert rc == fit_cli.EXIT_USAGE and message in err, err
    assert not again.exists()


def run_cli_fit(fit_cli, argv):
    """(exit code, stdout, stderr) of jaxplush-fit in this process."""
    import contextlib
    import io
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        rc = fit_cli.main(argv)
    return rc, out.getvalue(), err.getvalue()
