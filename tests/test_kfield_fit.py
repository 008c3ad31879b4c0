"""Fitting a stiffness field (jaxplush.fitting.field): the smoothness graph and its regulariser
against finite differences, a two-region field recovered from exact positions and from a
partial point cloud, the command line's ``--field``, the rendering, and the acceptance bench at
its small size."""

from __future__ import annotations

import os
import subprocess
import sys

import h5py
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxplush
from jaxplush.errors import JaxplushError
from jaxplush.fitting import field as F
from jaxplush.fitting import scenarios
from jaxplush.fitting.targets import Target
from jaxplush.model.mesh import unique_edges

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


# --------------------------------------------------------------------------- the graph and the regulariser

def test_edge_and_region_pairs():
    """Edges sharing a triangle: 3 pairs a face, 4 neighbours an edge on a closed mesh; the panels
    of the icosahedron share its 30 edges; the Laplacian's rows sum to 0."""
    v, f, panel = scenarios.panel_ball(2)
    edges = unique_edges(f)
    pairs = F.edge_pairs(f, edges)
    assert len(pairs) == 3 * len(f) and (pairs[:, 0] < pairs[:, 1]).all()
    assert np.array_equal(np.bincount(pairs.ravel(), minlength=len(edges)), np.full(len(edges), 4))
    fe = F.face_edges(f, edges)
    assert np.array_equal(np.sort(edges[fe[:, 0]], axis=1), np.sort(f[:, [0, 1]], axis=1))
    rp = F.region_pairs(f, panel, scenarios.N_PANELS)
    assert len(rp) == 30 and np.array_equal(np.bincount(rp.ravel()), np.full(20, 3))
    lap = F.laplacian(rp, 20)
    assert np.allclose(lap.sum(axis=1), 0) and np.allclose(np.diag(lap), 3)
    assert len(scenarios.patch_panels((0, 0, 1))) == 4


def test_smoothness_gradient_matches_finite_differences():
    """d/dtheta of weight sum (theta_a - theta_b)² (float64, jax.grad) against central differences
    at several steps, and against its closed form 2 weight L theta."""
    with jax.enable_x64(True):
        v, f, _ = scenarios.panel_ball(1)
        edges = unique_edges(f)
        pairs = F.edge_pairs(f, edges)
        rng = np.random.default_rng(0)
        theta = rng.normal(size=len(edges))
        w = 0.37
        g = np.asarray(jax.grad(lambda t: F.smoothness(t, pairs, w))(jnp.asarray(theta)))
        assert np.allclose(g, 2 * w * F.laplacian(pairs, len(edges)) @ theta, rtol=1e-12, atol=1e-12)
        d = rng.normal(size=len(edges))
        for h in (1e-3, 1e-4, 1e-5):
            fd = (F.smoothness(theta + h * d, pairs, w) - F.smoothness(theta - h * d, pairs, w)) / (2 * h)
            assert abs(fd - g @ d) <= 1e-8 * max(1.0, abs(g @ d))
        assert F.smoothness(np.ones(len(edges)) * 3.0, pairs, w) == 0.0
