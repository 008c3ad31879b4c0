"""Synthetic depth captures: what one depth camera would record of a simulated trajectory.

Real observations of a soft object are partial: a depth camera sees only the side facing it,
its depth is noisy, and some pixels return nothing. :func:`depth_capture` turns a trajectory into
such data, so that fits and tests can use realistic partial targets without downloading any:

* the camera is a pinhole (:class:`Camera`: eye, look-at point, up, vertical field of view and
  an image of ``width`` x ``height`` pixels); one ray leaves the eye through each pixel centre;
* each ray keeps its first hit on the simulated surface (every object's triangles, so objects
  hide each other and each object hides its own far side); the floor is not part of the capture,
  as a segmentation of the plush from its surroundings would leave it out;
* the depth along the ray gets Gaussian noise of ``noise`` (m; a depth sensor's error lies mainly
  along its rays), and each hit is dropped with probability ``dropout``;
* frames keep different numbers of points. They are stored padded: ``points`` (T, M, 3) holds each
  frame's points first and NaN rows after them, and ``counts`` (T,) says how many are real.

:func:`track_capture` adds what a marker or feature tracker would record: N points on the surface
(faces drawn by area at the first frame, uniform barycentric coordinates) followed through every
frame, with Gaussian noise per coordinate and the same per-frame dropout (a dropped track is a
NaN row: not seen in that frame).

The ray casting is a Moeller-Trumbore test of every ray against every triangle, in blocks of rays
under ``jax.jit`` (a few milliseconds per frame at 642 vertices and 64 x 48 pixels on two cores).
A ray that grazes a triangle's plane (:data:`GRAZING`) misses it: its determinant would be rounding
noise, and so would the hit it gives.
Random draws come from a numpy generator seeded by ``seed`` (an integer >= 0), so a capture is
reproducible. Every coordinate a capture returns is finite: a noise so large that a point would
overflow is refused (ValueError), never written as inf. ``jaxplush capture`` checks its options
against the trajectory's :func:`extent` first (:data:`MAX_NOISE_EXTENTS`, :data:`CAMERA_RANGE`).
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np

from jaxplush.model.contact import _cross, _dot

#: Rays tested per block (bounds the memory of the ray x triangle table).
RAY_BLOCK = 512
#: cos of the angle between a ray and a triangle's normal below which the ray grazes the triangle
#: and counts as a miss (1e-4: within 0.006 degrees of its plane)
GRAZING = 1e-4
#: sin of the angle between a camera's up direction and its view direction at or below which the
#: two count as parallel (the image's sideways axis would be undefined or rounding noise)
PARALLEL = 1e-6
#: ``jaxplush capture``: the largest --noise, as a multiple of the trajectory's :func:`extent`
MAX_NOISE_EXTENTS = 1.0
#: ``jaxplush capture``: --eye and --look-at lie within this many times the trajectory's
#: :func:`extent` of its centre (beyond it the float32 ray casting loses the object, and a
#: camera's vectors could overflow)
CAMERA_RANGE = 1e4


class NonFiniteCapture(ValueError):
    """The noise would put a captured point at a non-finite position (nothing is returned)."""


def extent(frames):
    """(centre (3,), extent) of (T, V, 3) or (V, 3) positions: the centre of the axis-aligned box
    that holds every vertex of every frame, and the length of its diagonal, m (ValueError when
    the positions are not finite or their box overflows)."""
    x = np.asarray(frames, np.float64).reshape(-1, 3)
    if x.size == 0 or not np.all(np.isfinite(x)):
        raise ValueError("frames hold no positions or non-finite ones")
    lo, hi = x.min(axis=0), x.max(axis=0)
    with np.errstate(over="ignore", invalid="ignore"):
        centre, diag = lo / 2 + hi / 2, norm(hi - lo)
    if not (np.all(np.isfinite(centre)) and math.isfinite(diag)):
        raise ValueError(f"frames span a box too large to compute with (from {lo.min():.3g} to {hi.max():.3g} m)")
    return centre, float(diag)


def norm(v):
    """Euclidean length of the vector ``v`` without overflow or underflow on the way (inf only when
    the length itself overflows)."""
    v = np.asarray(v, np.float64)
    m = float(np.max(np.abs(v))) if v.size else 0.0
    if m == 0 or not math.isfinite(m):
        return m
    return m * float(np.sqrt(np.sum((v / m) ** 2)))


def _unit(v):
    """``v`` / its length (as ``v / np.linalg.norm(v)`` where that neither overflows nor underflows)."""
    v = np.asarray(v, np.float64)
    with np.errstate(over="ignore", under="ignore"):
        n = np.linalg.norm(v)
    if not (math.isfinite(n) and n > 1e-150):
        v = v / np.max(np.abs(v))
        n = np.linalg.norm(v)
    return v / n


def parallel(a, b):
    """True when the 3-vectors ``a`` and ``b`` are parallel within :data:`PARALLEL` (or one is zero)."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    na, nb = norm(a), norm(b)
    if na == 0 or nb == 0:
        return True
    return norm(np.cross(a / na, b / nb)) <= PARALLEL


def check_seed(seed):
    """``seed`` as an int, or ValueError unless it is an integer >= 0 (numpy's generators take no other)."""
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed must be an integer >= 0, got {seed!r}")
    return int(seed)


@dataclasses.dataclass(frozen=True)
class Camera:
    """A pinhole depth camera.

    Attributes:
      eye: (3,) camera position, m.
      target: (3,) the point it looks at, m.
      up: (3,) the direction that is up in the image (non-zero, not parallel to the view
        direction: within :data:`PARALLEL`).
      fov_deg: vertical field of view, degrees (0 < fov < 180).
      width, height: image size in pixels (one ray per pixel).
    """

    eye: tuple
    target: tuple = (0.0, 0.0, 0.0)
    up: tuple = (0.0, 1.0, 0.0)
    fov_deg: float = 60.0
    width: int = 64
    height: int = 48

    def __post_init__(self):
        eye, target, up = (np.asarray(v, np.float64) for v in (self.eye, self.target, self.up))
        if eye.shape != (3,) or target.shape != (3,) or up.shape != (3,):
            raise ValueError("eye, target and up must each be 3 numbers")
        if not (np.all(np.isfinite(eye)) and np.all(np.isfinite(target)) and np.all(np.isfinite(up))):
            raise ValueError("eye, target and up must be finite")
        with np.errstate(over="ignore", invalid="ignore"):
            view = target - eye
        if not np.all(np.isfinite(view)) or not math.isfinite(norm(view)):
            raise ValueError("the camera's eye and target lie too far apart (their difference overflows)")
        if norm(view) == 0:
            raise ValueError("the camera's eye and target coincide")
        if norm(up) == 0:
            raise ValueError("the camera's up direction is zero")
        if parallel(view, up):
            raise ValueError("the camera's up direction is parallel to its view direction")
        if not 0 < self.fov_deg < 180:
            raise ValueError(f"fov_deg must lie in (0, 180), got {self.fov_deg!r}")
        if int(self.width) != self.width or int(self.height) != self.height or self.width < 1 or self.height < 1:
            raise ValueError(f"width and height must be positive integers, got {self.width!r} x {self.height!r}")

    def basis(self):
        """(forward, right, up) unit vectors of the camera frame."""
        eye, target, up = (np.asarray(v, np.float64) for v in (self.eye, self.target, self.up))
        f = _unit(target - eye)
        r = _unit(np.cross(f, _unit(up)))
        return f, r, np.cross(r, f)

    def rays(self):
        """(R, 3) unit directions through the pixel centres, row by row from the image's top left
        (R = width x height); every ray starts at ``eye``."""
        f, r, u = self.basis()
        half = math.tan(math.radians(self.fov_deg) / 2)
        aspect = self.width / self.height
        px = ((np.arange(self.width) + 0.5) / self.width * 2 - 1) * half * aspect
        py = (1 - (np.arange(self.height) + 0.5) / self.height * 2) * half
        gx, gy = np.meshgrid(px, py)
        d = f + gx.reshape(-1, 1) * r + gy.reshape(-1, 1) * u
        return d / np.linalg.norm(d, axis=1, keepdims=True)


@dataclasses.dataclass(frozen=True)
class Capture:
    """A depth capture of a trajectory (:func:`depth_capture`).

    Attributes:
      points: (T, M, 3) float64, each frame's captured points first, then NaN rows (M the largest count).
      counts: (T,) int, the number of real points in each frame.
      camera: the :class:`Camera`; noise: depth noise sigma (m); dropout: the drop probability.
    """

    points: np.ndarray
    counts: np.ndarray
    camera: Camera
    noise: float
    dropout: float

    def frame(self, t):
        """(counts[t], 3) the real points of frame t."""
        return self.points[t, : self.counts[t]]


@dataclasses.dataclass(frozen=True)
class TrackCapture:
    """Tracked surface points of a trajectory (:func:`track_capture`).

    Attributes:
      tracks: (T, N, 3) float64 each track's observed position, NaN rows where it was dropped.
      face: (N,) int64 the face each track lies on; barycentric: (N, 3) its coordinates there.
    """

    tracks: np.ndarray
    face: np.ndarray
    barycentric: np.ndarray


def sample_barycentric(x, faces, n, rng):
    """(face (n,) int64, barycentric (n, 3)) of n points drawn uniformly by area on the triangle
    mesh (x (V, 3), faces (F, 3)) with the numpy generator ``rng``."""
    x, faces = np.asarray(x, np.float64), np.asarray(faces)
    a, b, c = x[faces[:, 0]], x[faces[:, 1]], x[faces[:, 2]]
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    f = rng.choice(len(faces), size=n, p=area / area.sum())
    r1, r2 = rng.random(n), rng.random(n)
    s = np.sqrt(r1)
    return f.astype(np.int64), np.stack([1 - s, s * (1 - r2), s * r2], axis=1)


def track_capture(frames, faces, n, *, noise=0.0, dropout=0.0, seed=0):
    """N tracked surface points of each frame (module docstring); a track dropped from every frame
    is kept in the frame where its dropout draw came closest to keeping it (every track is seen).

    Args:
      frames: (T, V, 3) positions, m; faces: (F, 3) triangles over those vertices.
      n: number of tracks (>= 1).
      noise: Gaussian noise sigma per coordinate, m (>= 0); dropout: probability in [0, 1) that a
        track is not seen in a frame.
      seed: seed of the draws, an integer >= 0 (the surface points, noise and dropout;
        independent of :func:`depth_capture`'s draws with the same seed).

    Raises:
      ValueError: a bad argument; :class:`NonFiniteCapture` (a ValueError): a ``noise`` that would
        put a track at a non-finite position.
    """
    x = np.asarray(frames, np.float64)
    faces = np.asarray(faces)
    if x.ndim != 3 or x.shape[-1] != 3 or x.shape[0] < 1:
        raise ValueError(f"frames must be (T, V, 3), got shape {np.shape(frames)}")
    if int(n) != n or n < 1:
        raise ValueError(f"the number of tracks must be an integer >= 1, got {n!r}")
    if not (math.isfinite(noise) and noise >= 0):
        raise ValueError(f"noise must be a number >= 0 (m), got {noise!r}")
    if not 0 <= dropout < 1:
        raise ValueError(f"dropout must lie in [0, 1), got {dropout!r}")
    rng = np.random.default_rng([check_seed(seed), 1])     # a stream of its own beside depth_capture's
    face, bary = sample_barycentric(x[0], faces, int(n), rng)
    tracks = np.einsum("nk,tnkc->tnc", bary, x[:, faces[face]])
    with np.errstate(over="ignore", invalid="ignore"):
        tracks = tracks + noise * rng.standard_normal(tracks.shape)
    _check_finite(tracks, "tracked point", noise)
    draw = rng.random(tracks.shape[:2])
    drop = draw < dropout
    drop[np.argmax(draw, axis=0), np.arange(tracks.shape[1])] = False
    tracks[drop] = np.nan
    return TrackCapture(tracks=tracks, face=face, barycentric=bary)


def _check_finite(points, what, noise, frame=None):
    """ValueError unless every row of ``points`` (..., 3) is finite, or NaN in all three coordinates
    (a dropped track): a non-finite coordinate means the noise overflowed it."""
    p = np.asarray(points)
    bad = ~np.isfinite(p).all(axis=-1) & ~np.isnan(p).all(axis=-1)
    if bad.any():
        where = f" in frame {frame}" if frame is not None else f" in frame {int(np.argwhere(bad)[0][0])}"
        raise NonFiniteCapture(f"noise {noise!r} m puts a {what}{where} at a non-finite position; the capture "
                               "would hold inf or NaN coordinates")


def _first_hits(origin, dirs, tri):
    """(R,) distance along each unit ray to its first triangle hit (inf: none).

    Moeller-Trumbore for every ray against every triangle ``tri`` (F, 3, 3), in blocks of rays,
    written out per component (x, y, z arrays) with the contact code's helpers."""
    a, b, c = (tuple(tri[:, k, i] for i in range(3)) for k in range(3))
    e1 = tuple(bi - ai for ai, bi in zip(a, b))
    e2 = tuple(ci - ai for ai, ci in zip(a, c))
    s = tuple(origin[i] - a[i] for i in range(3))                       # (F,) each
    q = _cross(s, e1)
    t_num = _dot(e2, q)                                                  # (F,)
    # det = -d.(e1 x e2) = -|e1 x e2| cos(angle of the ray to the normal): a ray within GRAZING of
    # the triangle's plane is a miss (its det is rounding noise, and u, v, t with it)
    n = _cross(e1, e2)
    eps = GRAZING * jnp.sqrt(_dot(n, n))

    def block(d):                                                        # d (B, 3)
        dd = tuple(d[:, i, None] for i in range(3))                      # (B, 1) each
        det = -_dot(dd, n)                                               # e1.(d x e2) = -d.(e1 x e2)
        ok = jnp.abs(det) > eps
        inv = jnp.where(ok, 1.0 / jnp.where(ok, det, 1.0), 0.0)
        u = _dot(dd, _cross(e2, s)) * inv                                # s.(d x e2) = d.(e2 x s)
        v = _dot(dd, q) * inv
        t = t_num * inv
        hit = ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0)
        return jnp.min(jnp.where(hit, t, jnp.inf), axis=1)

    count = dirs.shape[0]
    pad = (-count) % RAY_BLOCK
    d = jnp.concatenate([dirs, jnp.broadcast_to(dirs[:1], (pad, 3))]) if pad else dirs
    return jax.lax.map(block, d.reshape(-1, RAY_BLOCK, 3)).reshape(-1)[:count]


@jax.jit
def _frames_first_hits(origin, dirs, tris):
    """(T, R) :func:`_first_hits` of every frame's triangles ``tris`` (T, F, 3, 3), one compiled call."""
    return jax.lax.map(lambda tri: _first_hits(origin, dirs, tri), tris)


def depth_capture(frames, faces, camera, *, noise=0.0, dropout=0.0, seed=0):
    """What ``camera`` records of each frame (module docstring).

    Args:
      frames: (T, V, 3) positions (a trajectory's frames) or (V, 3) for one frame, m.
      faces: (F, 3) triangles over those vertices (a scene's ``faces``, every object's).
      camera: :class:`Camera`.
      noise: depth noise sigma along each ray, m (>= 0).
      dropout: probability that a hit returns nothing, in [0, 1).
      seed: seed of the noise and dropout draws, an integer >= 0.

    Returns:
      :class:`Capture`; frames that see nothing have count 0. Every real point is finite.

    Raises:
      ValueError: a bad argument; :class:`NonFiniteCapture` (a ValueError): a ``noise`` that would
        put a point at a non-finite position.
    """
    x = np.asarray(frames, np.float64)
    if x.ndim == 2:
        x = x[None]
    faces = np.asarray(faces)
    if x.ndim != 3 or x.shape[-1] != 3 or x.shape[0] < 1:
        raise ValueError(f"frames must be (T, V, 3) or (V, 3), got shape {np.shape(frames)}")
    if faces.ndim != 2 or faces.shape[1] != 3 or faces.size == 0:
        raise ValueError(f"faces must be (F, 3), got shape {faces.shape}")
    if faces.min() < 0 or faces.max() >= x.shape[1]:
        raise ValueError(f"faces index vertices outside 0..{x.shape[1] - 1}")
    if not np.all(np.isfinite(x)):
        raise ValueError("frames hold non-finite positions")
    if not (math.isfinite(noise) and noise >= 0):
        raise ValueError(f"noise must be a number >= 0 (m), got {noise!r}")
    if not 0 <= dropout < 1:
        raise ValueError(f"dropout must lie in [0, 1), got {dropout!r}")
    rng = np.random.default_rng(check_seed(seed))
    eye = np.asarray(camera.eye, np.float64)
    dirs = camera.rays()
    hits = np.asarray(_frames_first_hits(jnp.asarray(eye), jnp.asarray(dirs), jnp.asarray(x[:, faces])), np.float64)
    kept = []
    for t in hits:
        hit = np.isfinite(t)
        keep = hit & (rng.random(t.shape) >= dropout)
        with np.errstate(over="ignore", invalid="ignore"):
            depth = t[keep] + noise * rng.standard_normal(int(keep.sum()))
            kept.append(eye + depth[:, None] * dirs[keep])
        _check_finite(kept[-1], "point", noise, frame=len(kept) - 1)
    counts = np.array([len(k) for k in kept], np.int64)
    points = np.full((len(kept), max(1, int(counts.max())), 3), np.nan)
    for i, k in enumerate(kept):
        points[i, : len(k)] = k
    return Capture(points=points, counts=counts, camera=camera, noise=float(noise), dropout=float(dropout))
