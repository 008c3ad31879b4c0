"""Which object each residual belongs to, and whether objects came into contact: what the
objective needs to score several fitted objects apart (the per-object global stage,
:mod:`jaxplush.fitting.stages.objects`, and the coloured Jacobians of
:mod:`jaxplush.fitting.objective.evaluate`)."""

from __future__ import annotations

import numpy as np


def fitted_index(prob):
    """(O,) each scene object's index among the fitted objects (``prob.objects``), -1 if not fitted."""
    n = int(np.max(np.asarray(prob.sim.topology.vertex_object))) + 1
    fitted = np.full(n, -1, np.int64)
    fitted[list(prob.objects)] = np.arange(len(prob.objects))
    return fitted


def residual_objects(prob, frames=None):
    """(n,) the fitted object (an index into ``prob.objects``) that each residual belongs to, -1 for
    residuals of objects that are not fitted.

    Positions: the residuals are (frame, vertex, xyz) flattened (:func:`jaxplush.fitting.losses.make_residual`),
    and each vertex belongs to its object (the topology's ``vertex_object``). Tracks: (frame,
    track, xyz), each track to the object of its vertices. Points: (frame,
    point), each point assigned to the object of its nearest vertex in ``frames`` ((T, V, 3), the
    simulated frames at the target's steps, e.g. the rollout at the start values; required).
    Mixed (a scan and tracks): per frame, its points' then its tracks' (frames required).
    """
    vobj = np.asarray(prob.sim.topology.vertex_object, np.int64)
    fitted = fitted_index(prob)
    target = prob.target
    near = target.kind.residual_vertices(target, prob.sim.topology, frames)
    if near is None:              # a kind that does not say: every residual belongs to every object
        return None
    near = np.asarray(near, np.int64)
    return np.where(near >= 0, fitted[vobj[np.maximum(near, 0)]], -1)


#: Extra clearance, as a fraction of a pair's contact reach, that :func:`clear_of_contact` asks for.
CLEARANCE_SAFETY = 0.5


def clear_by_separation(separation):
    """(N,) bool: runs whose contact pairs never came within 1 + :data:`CLEARANCE_SAFETY` of their
    reach, from the separation the batched simulator measures at every step
    (:class:`jaxplush.fitting.objective.evaluate.Evaluation`: the closest approach of two objects' bounding
    boxes, in units of the pair's reach, 2 thicknesses); NaN (not measured) is not clear."""
    s = np.asarray(separation, np.float64)
    return np.isfinite(s) & (s > 1.0 + CLEARANCE_SAFETY)


def clear_of_contact(prob, frames):
    """Whether no two objects came within reach of soft-soft contact in ``frames`` ((T, V, 3)
    positions at the target's frames, or (N, T, V, 3) for N runs: (N,) bools).

    The reach of a pair is 2 delta (its contact thickness): a vertex farther than that from the
    other object's surface feels a contact force below about 2e-10 of the force at touching
    (:mod:`jaxplush.model.contact`: the ramp softplus(beta (delta - s)) / beta, beta = 10 / delta),
    and at 1 + :data:`CLEARANCE_SAFETY` times the reach below 1e-17 of it, far below float32
    rounding. The other object's surface (its triangles) lies inside the bounding box of its
    vertices, so a vertex outside that box inflated by a margin is farther than the margin from
    the surface, however coarse its triangles. A pair is clear when, at every frame, every vertex
    of each object lies outside the other's bounding box inflated by (1 + CLEARANCE_SAFETY) x
    the reach plus how far the two objects' vertices move (the largest chord, each object's own)
    over the frame intervals on either side: the frames do not show the steps between them. In
    a run where every pair is clear, each object moves with its own parameters only. A scene
    without soft-soft contact between objects is always clear."""
    x = np.asarray(frames, np.float64)
    single = x.ndim == 3
    x = x[None] if single else x
    cfg = prob.sim.terms.contact
    out = np.ones(len(x), bool)
    if cfg is None or not cfg.pairs:
        return bool(out[0]) if single else out
    vobj = np.asarray(prob.sim.topology.vertex_object, np.int64)

    def moves(xo):
        """(N, T) the object's largest vertex move over the frame intervals next to each frame."""
        chord = np.abs(np.diff(xo, axis=1)).max(axis=(2, 3)) if xo.shape[1] > 1 else np.zeros((len(xo), 0))
        pad = np.zeros((len(xo), 1))
        return np.maximum(np.concatenate([pad, chord], 1), np.concatenate([chord, pad], 1))

    for (a, b), delta in zip(cfg.pairs, cfg.thickness):
        reach = 2.0 * float(delta)
        xa, xb = x[:, :, vobj == a], x[:, :, vobj == b]
        margin = (1.0 + CLEARANCE_SAFETY) * reach + moves(xa) + moves(xb)          # (N, T)

        def outside(p, q):
            m = margin[:, :, None, None]
            lo, hi = q.min(axis=2, keepdims=True) - m, q.max(axis=2, keepdims=True) + m
            return np.any((p < lo) | (p > hi), axis=-1).all(axis=(1, 2))
        out &= outside(xa, xb) & outside(xb, xa)
    return bool(out[0]) if single else out
