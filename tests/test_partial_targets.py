"""Point-cloud targets whose frames hold different numbers of points (a depth camera's partial,
noisy captures): NaN rows are padding. They load, weigh every observed point alike in the loss,
the residuals and the Chamfer distance, leave gradients finite, and a fit to one synthetic
depth camera's view recovers the ball's parameters."""

from __future__ import annotations

import dataclasses
import warnings

import h5py
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxplush
from jaxplush.errors import TrajectoryError
from jaxplush.fitting import fitter as F
from jaxplush.fitting.objective import losses
from jaxplush.fitting.targets.scenarios import drop_scene_text
from jaxplush.fitting.targets import Target, load_target, make_target
from jaxplush.io.capture import Camera, depth_capture

DT, STEPS, EVERY = 4e-4, 1000, 25           # the dropped 162-vertex ball of test_fit_robust.py
CAMERA = Camera(eye=(0.35, 0.3, 0.45), target=(0.0, 0.1, 0.0), fov_deg=45.0, width=64, height=48)


@pytest.fixture(scope="module")
def drop():
    truth = jaxplush.parse_scene(drop_scene_text("ball", 2), "<drop>")
    return truth, make_target(truth, STEPS, DT, EVERY)


def _capture_target(truth, target, noise=0.002, dropout=0.1, seed=1):
    cap = depth_capture(target.positions, truth.faces, CAMERA, noise=noise, dropout=dropout, seed=seed)
    return cap, Target(positions=None, points=cap.points, steps=target.steps, times=target.times, dt=DT,
                       path="<capture>", noise=noise)


def test_a_capture_target_is_ragged_and_round_trips_through_hdf5(drop, tmp_path):
    truth, target = drop
    cap, t = _capture_target(truth, target)
    assert t.ragged and len(set(cap.counts.tolist())) > 1           # the ball nears the camera as it falls
    np.testing.assert_array_equal(t.observed.sum(axis=1), cap.counts)
    path = str(tmp_path / "capture.h5")
    t.save(path, truth)
    back = load_target(path, truth)
    assert back.kind == "points" and back.ragged
    np.testing.assert_array_equal(back.points, t.points)


def test_partly_nan_rows_and_all_padding_are_refused_with_the_file_and_row(drop, tmp_path):
    truth, target = drop
    _, t = _capture_target(truth, target)
    for name, change, match in (
            ("half.h5", lambda p: p.__setitem__((2, 0, 1), np.nan), "frame 2, point 0.*all three coordinates"),
            ("inf.h5", lambda p: p.__setitem__((3, 1, 0), np.inf), "frame 3, point 1"),
            ("empty.h5", lambda p: p.fill(np.nan), "every row is NaN padding")):
        pts = t.points.copy()
        change(pts)
        path = str(tmp_path / name)
        t.save(path, truth)
        with h5py.File(path, "r+") as f:
            f["points"][...] = pts
        with pytest.raises(TrajectoryError, match=match) as e:
            load_target(path, truth)
        assert name in str(e.value)


def _pad(t, extra):
    """The same target with ``extra`` more NaN rows in every frame."""
    pts = np.concatenate([t.points, np.full((t.n_frames, extra, 3), np.nan)], axis=1)
    return dataclasses.replace(t, points=pts)


def test_the_loss_and_residuals_weigh_every_observed_point_alike_whatever_the_padding(drop):
    truth, target = drop
    keep = [0, 13, 26, 39]                                          # frames of 267 to 441 points
    cap, t = _capture_target(truth, target)
    t = t.select(keep)
    sim = jaxplush.make_simulator(truth, DT)
    topo = sim.topology
    frames = jnp.asarray(target.positions[keep] * 1.01, sim.dtype)  # a slightly wrong shape: distances > 0
    vf = losses.vertex_faces(topo.faces, topo.n_vertices)
    faces = np.asarray(topo.faces, np.int32)
    # by hand: every observed point's squared distance, over all frames, over N sigma²
    d2 = [np.asarray(losses.point_surface_distance2(frames[i], jnp.asarray(cap.frame(j), sim.dtype), faces, vf))
          for i, j in enumerate(keep)]
    assert len({len(d) for d in d2}) == len(keep)
    expect = sum(float(np.sum(d, dtype=np.float64)) for d in d2) / (sum(len(d) for d in d2) * 0.002 ** 2)
    for tt in (t, _pad(t, 37)):
        loss = losses.make_loss(tt, topo, sim.dtype)
        total = jax.jit(lambda x, aux: jnp.sum(jax.vmap(loss.loss_fn)(x, aux)))   # noqa: B023
        assert float(total(frames, loss.aux)) == pytest.approx(expect, rel=1e-4)
        res = losses.make_residual(tt, topo, loss)
        r = np.asarray(res.fn(frames), np.float64)
        assert np.all(np.isfinite(r)) and r.size == tt.n_frames * tt.points.shape[1]
        assert np.all(r.reshape(tt.n_frames, -1)[~tt.observed] == 0)
        # signed distances with the noise's curvature offset taken off: close to, not equal to, the loss
        assert float(np.sum(r * r)) == pytest.approx(expect, rel=0.05)
        g = jax.jit(jax.grad(total))(frames, loss.aux)
        assert np.all(np.isfinite(np.asarray(g))) and float(jnp.abs(g).max()) > 0


def test_the_chamfer_distance_ignores_the_padding():
    rng = np.random.default_rng(0)
    x = jnp.asarray(rng.normal(size=(40, 3)), jnp.float32)
    p = rng.normal(size=(25, 3))
    padded = np.concatenate([p, np.full((9, 3), np.nan)])
    a = float(losses.chamfer(x, jnp.asarray(p, jnp.float32)))
    b = float(losses.chamfer(x, jnp.asarray(padded, jnp.float32)))
    assert b == pytest.approx(a, rel=1e-5)
    g = jax.grad(lambda y: losses.chamfer(y, jnp.asarray(padded, jnp.float32)))(x)
    assert np.all(np.isfinite(np.asarray(g)))


def test_a_fit_to_one_depth_cameras_view_recovers_the_ball(drop):
    """k and nmol of the dropped ball from one synthetic depth camera (2 mm depth noise, 10% dropout,
    64 x 48 pixels: only the side facing it, 267-441 points a frame), from k x1.6 and nmol x0.7:
    within 1% (0.01-0.04% on this machine), and the residual is at the noise."""
    truth, target = drop
    _, t = _capture_target(truth, target)
    names = ("k_structural", "nmol")
    p = truth.params
    start = truth.replace(params=p._replace(k_structural=p.k_structural * 1.6, nmol=p.nmol * 0.7))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = F.fit(start, t, names)
    errors = {n: res.values[n][0] / getattr(p, n)[0] - 1 for n in names}
    assert max(abs(e) for e in errors.values()) < 0.01, (errors, res.status)
    assert res.outcome.reached and res.outcome.reference_kind == "noise"
