"""Synthetic depth captures (jaxplush.io.capture): the points lie on the visible surface, a sphere
covers the pixels its silhouette covers, objects hide each other, noise lies along the rays with
the stated sigma, dropout drops the stated fraction, and frames keep their own point counts."""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np
import pytest
import trimesh

from jaxplush.io.capture import Camera, depth_capture
from jaxplush.model.contact import closest_point_distance2

R = 0.1


def _sphere(sub=3, centre=(0.0, 0.0, 0.0), radius=R):
    m = trimesh.creation.icosphere(subdivisions=sub, radius=radius)
    return np.asarray(m.vertices) + np.asarray(centre), np.asarray(m.faces)


def _surface_distance(p, x, f):
    """(M,) distance of each point to the nearest triangle (every triangle tried)."""
    tri = [tuple(jnp.asarray(x[f][None, :, k, i]) for i in range(3)) for k in range(3)]
    pp = tuple(jnp.asarray(p[:, None, i]) for i in range(3))
    return np.sqrt(np.min(np.asarray(closest_point_distance2(pp, *tri)), axis=1))


def test_points_lie_on_the_side_facing_the_camera_and_fill_its_silhouette():
    x, f = _sphere()
    cam = Camera(eye=(0.0, 0.0, 0.6), width=80, height=60, fov_deg=40.0)
    cap = depth_capture(x, f, cam)
    p = cap.frame(0)
    assert np.max(_surface_distance(p, x, f)) < 1e-5              # on the surface (float32 ray casting)
    eye = np.asarray(cam.eye)
    assert np.all(np.einsum("ij,ij->i", p / np.linalg.norm(p, axis=1, keepdims=True), eye - p) > 0)   # facing the eye
    # the rays that hit are those inside the silhouette: the sphere's angular radius seen from the eye
    # (the icosphere is inscribed in the sphere: its silhouette is a little smaller; compare with both radii)
    ang = np.arccos(np.clip(-cam.rays() @ (eye / np.linalg.norm(eye)), -1, 1))
    d = np.linalg.norm(eye)
    outer = int(np.sum(ang < math.asin(R / d)))
    inner_r = R * math.cos(math.radians(6.0))                     # a level-3 icosphere's faces span < 6 degrees
    inner = int(np.sum(ang < math.asin(inner_r / d)))
    assert inner <= cap.counts[0] <= outer and inner > 300


def test_a_nearer_object_hides_the_one_behind_it():
    a, fa = _sphere(centre=(0.0, 0.0, 0.2))
    b, fb = _sphere(centre=(0.0, 0.0, -0.2), radius=0.05)         # smaller, right behind a
    x = np.concatenate([a, b])
    f = np.concatenate([fa, fb + len(a)])
    cap = depth_capture(x, f, Camera(eye=(0.0, 0.0, 1.0), width=48, height=48, fov_deg=40.0))
    p = cap.frame(0)
    assert len(p) > 100 and np.all(p[:, 2] > 0.2 - 1e-6)           # only the near sphere's front
    side = depth_capture(x, f, Camera(eye=(1.0, 0.0, 0.0), width=48, height=48, fov_deg=50.0)).frame(0)
    assert np.any(side[:, 2] < -0.1) and np.any(side[:, 2] > 0.1)  # seen from the side, both


def test_noise_lies_along_the_rays_with_its_sigma_and_dropout_drops_its_share():
    x, f = _sphere()
    cam = Camera(eye=(0.0, 0.3, 0.6), width=96, height=72, fov_deg=40.0)
    clean = depth_capture(x, f, cam)
    noisy = depth_capture(x, f, cam, noise=0.002, seed=3)
    assert np.array_equal(noisy.counts, clean.counts)
    p0, p1 = clean.frame(0), noisy.frame(0)
    dirs = (p0 - cam.eye) / np.linalg.norm(p0 - cam.eye, axis=1, keepdims=True)
    along = np.einsum("ij,ij->i", p1 - p0, dirs)
    across = np.linalg.norm(p1 - p0 - along[:, None] * dirs, axis=1)
    assert np.max(across) < 1e-6 * (1 + np.max(np.abs(along)))
    n = len(along)
    assert abs(np.std(along) / 0.002 - 1) < 4 / math.sqrt(2 * n) + 0.02
    assert abs(np.mean(along)) < 4 * 0.002 / math.sqrt(n)
    dropped = depth_capture(x, f, cam, dropout=0.3, seed=5)
    share = 1 - dropped.counts[0] / clean.counts[0]
    assert abs(share - 0.3) < 4 * math.sqrt(0.3 * 0.7 / clean.counts[0])
    again = depth_capture(x, f, cam, noise=0.002, dropout=0.3, seed=5)
    assert np.array_equal(again.points, depth_capture(x, f, cam, noise=0.002, dropout=0.3, seed=5).points,
                          equal_nan=True)


def test_frames_keep_their_own_counts_padded_with_nan():
    x, f = _sphere(sub=2)
    cam = Camera(eye=(0.0, 0.0, 1.0), width=40, height=30, fov_deg=30.0)
    frames = np.stack([x, x + [0.0, 0.0, 0.4], x + [5.0, 0.0, 0.0]])   # nearer (bigger), out of view
    cap = depth_capture(frames, f, cam)
    assert cap.points.shape == (3, cap.counts.max(), 3)
    assert cap.counts[1] > cap.counts[0] > 0 and cap.counts[2] == 0
    for t in range(3):
        assert np.all(np.isfinite(cap.points[t, : cap.counts[t]]))
        assert np.all(np.isnan(cap.points[t, cap.counts[t]:]))


@pytest.mark.parametrize("kw, match", [
    (dict(eye=(0, 0, 0)), "coincide"),
    (dict(eye=(0, 1, 0)), "parallel"),
    (dict(eye=(0, 0, 1), fov_deg=180), "fov_deg"),
    (dict(eye=(0, 0, 1), width=0), "positive integers"),
    (dict(eye=(0, 0)), "3 numbers"),
])
def test_bad_cameras_are_refused(kw, match):
    with pytest.raises(ValueError, match=match):
        Camera(**kw)


def test_bad_capture_arguments_are_refused():
    x, f = _sphere(sub=1)
    cam = Camera(eye=(0, 0, 1))
    with pytest.raises(ValueError, match="dropout"):
        depth_capture(x, f, cam, dropout=1.0)
    with pytest.raises(ValueError, match="noise"):
        depth_capture(x, f, cam, noise=-1.0)
    with pytest.raises(ValueError, match="faces index"):
        depth_capture(x, f + 100, cam)
    with pytest.raises(ValueError, match="non-finite"):
        depth_capture(np.where(np.arange(len(x))[:, None] == 0, np.nan, x), f, cam)
