"""Per-frame losses between simulated positions and a target (pure jax; no IO).

* :func:`squared_distance`: mean squared vertex distance, for ``positions`` targets (the
  vertices correspond one to one).
* :func:`chamfer`: symmetric Chamfer distance, for ``points`` targets (a scan: M points with no
  correspondence to the V vertices).

:func:`make_loss` builds the frame loss that :func:`fitting.gradients.rollout_loss` sums over
the target frames, with a noise-aware normalisation: the summed loss is

    L = (1 / T) sum_j d_j / s²,

d_j the frame's squared distance (m²). With a known measurement noise sigma per coordinate,
s² = 3 sigma² (so L ~ 1 when the model fits to the noise level, and L - 1 reads as the misfit
in units of the noise); otherwise (noise-free or unknown) s² is the mean of d_j between the
scene's rest shape and the target, so L is the squared error relative to how far the target
moves (L = 1 for "no better than standing still").

Frames whose objects are inverted (a gas object's volume <= 0, a blown-up rollout) get a NaN
loss, so the optimiser sees the failure instead of a finite but meaningless number.
"""

from __future__ import annotations

from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np


def squared_distance(x, y):
    """Mean over vertices of |x_i - y_i|² (m²); x, y: (V, 3)."""
    d = x - y
    return jnp.mean(jnp.sum(d * d, axis=-1))


def pairwise_sq_distances(x, p):
    """(V, M) squared distances between the rows of x (V, 3) and p (M, 3).

    Expanded as |x|² + |p|² - 2 x.p about the cloud's centroid (which keeps the cancellation
    small in float32: the operands are object-sized, not world-sized), clamped at 0.
    """
    c = jax.lax.stop_gradient(jnp.mean(p, axis=0))
    xc, pc = x - c, p - c
    d2 = jnp.sum(xc * xc, axis=1)[:, None] + jnp.sum(pc * pc, axis=1)[None, :] - 2.0 * xc @ pc.T
    return jnp.maximum(d2, 0.0)


def chamfer(x, p):
    """Symmetric Chamfer distance (m²): mean_i min_k |x_i - p_k|² + mean_k min_i |x_i - p_k|².

    Args:
      x: (V, 3) simulated vertex positions.
      p: (M, 3) target points (M unrelated to V).
    """
    d2 = pairwise_sq_distances(x, p)
    return jnp.mean(jnp.min(d2, axis=1)) + jnp.mean(jnp.min(d2, axis=0))


def frame_distance(kind):
    """The per-frame distance for a target kind: "positions" or "points"."""
    if kind == "positions":
        return squared_distance
    if kind == "points":
        return chamfer
    raise ValueError(f"unknown target kind {kind!r}; expected 'positions' or 'points'")


class Loss(NamedTuple):
    """A frame loss ready for :func:`fitting.gradients.rollout_loss`.

    Attributes:
      loss_fn: ``(x (V, 3), aux_j) -> scalar``: the frame's normalised contribution.
      aux: (T, V or M, 3) target frames (the pytree rollout_loss slices per frame).
      frame_steps: (T,) tuple of step indices.
      scale2: the normaliser s² (m²).
      normalisation: "noise" or "motion" (see the module docstring).
      kind: "positions" or "points".
    """

    loss_fn: Callable
    aux: object
    frame_steps: tuple
    scale2: float
    normalisation: str
    kind: str


def rest_distance(target, x_rest):
    """Mean over the target's frames of the frame distance (m²) between the rest shape and the
    target (numpy, float64; nothing is compiled)."""
    x = np.asarray(x_rest, np.float64)
    out = []
    for y in np.asarray(target.data, np.float64):
        if target.kind == "positions":
            out.append(np.mean(np.sum((x - y) ** 2, axis=1)))
        else:
            a = np.full(len(x), np.inf)
            b = np.full(len(y), np.inf)
            for i in range(0, len(x), 256):
                d2 = np.sum((x[i:i + 256, None, :] - y[None, :, :]) ** 2, axis=2)
                a[i:i + 256] = d2.min(axis=1)
                b = np.minimum(b, d2.min(axis=0))
            out.append(a.mean() + b.mean())
    return float(np.mean(out))


def make_loss(target, topology, dtype, *, noise=None, noise_free=False, check_volume=True):
    """Build the normalised frame loss for a target.

    Args:
      target: :class:`fitting.targets.Target`.
      topology: the simulator's :class:`jaxplush.model.Topology` (rest shape, faces, objects).
      dtype: float dtype of the simulation.
      noise: measurement noise sigma per coordinate (m); default: the target's, if known.
      noise_free: treat the target as exact (normalise by its motion, ignore any noise value).
      check_volume: make the loss NaN at frames where an object's volume is <= 0 (for scenes
        with gas; an inverted mesh is a blow-up).

    Returns:
      :class:`Loss`.
    """
    sigma = None if noise_free else (target.noise if noise is None else float(noise))
    n = target.n_frames
    if sigma is not None and sigma > 0:
        scale2 = 3.0 * sigma * sigma
        how = "noise"
    else:
        scale2 = rest_distance(target, topology.x0)
        if not scale2 > 0:  # the target is the rest shape itself: any positive scale will do
            scale2 = float(np.mean(np.var(topology.x0, axis=0)))
        how = "motion"
    dist = frame_distance(target.kind)
    inv = 1.0 / (n * scale2)
    volumes = None
    if check_volume:
        from jaxplush.model import face_volumes
        volumes = lambda x: face_volumes(topology, x)  # noqa: E731

    def loss_fn(x, y):
        d = dist(x, y) * jnp.asarray(inv, x.dtype)
        if volumes is not None:
            d = jnp.where(jnp.all(volumes(x) > 0), d, jnp.nan)
        return d

    aux = jnp.asarray(target.data, dtype)
    return Loss(loss_fn, aux, tuple(int(s) for s in target.steps), float(scale2), how, target.kind)
