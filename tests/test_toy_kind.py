"""A new target kind is one class in one file: silhouettes (2-D outline points of an orthographic
view), defined here, outside the package, and fitted with the default fit through the public API."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxplush
from jaxplush import fitting
from jaxplush.fitting.targets.recovery import recovery_scene_text

#: The camera's image plane: x and y (an orthographic camera on the z axis; gravity along -y).
VIEW = (0, 1)
#: The outline: the vertices of the rest shape within this fraction of its half-depth of its
#: middle plane (they are what the camera sees as the object's silhouette at rest).
RIM = 0.35


def rim(x0):
    """(M,) the outline's vertices of a rest shape x0 (V, 3), seen along z."""
    z = np.asarray(x0, np.float64)[:, 2]
    return np.flatnonzero(np.abs(z - 0.5 * (z.min() + z.max())) <= RIM * 0.5 * np.ptp(z))


class Silhouettes(fitting.Kind):
    """A camera's view of the object's outline: per frame, the 2-D image points (x, y) of the
    vertices on the rest shape's outline (:func:`rim`), in vertex order. A point's residual is its
    vertex's simulated image point less the observed one (m); a point not seen is a NaN row."""

    name = "silhouettes"
    components = 2
    unit = "outline point"
    noun = "silhouette points"

    def residual(self, target, topology, scale2, normalisation):
        idx = rim(topology.x0)
        if len(idx) != np.shape(target.data)[1]:
            raise ValueError(f"{target.path}: {np.shape(target.data)[1]} outline points, the scene's outline has {len(idx)}")

        def frame_fn(frames, ys):
            valid = jnp.all(jnp.isfinite(ys), axis=-1)                          # (C, M)
            d = frames[:, idx][..., VIEW] - jnp.where(valid[..., None], ys, 0.0)
            return jnp.where(valid[..., None], d, 0.0).reshape(-1)
        return frame_fn, 2 * len(idx), None

    def residual_vertices(self, target, topology, frames=None):
        return np.tile(np.repeat(rim(topology.x0), 2), target.n_frames)      # for a split by object


def _hanging(**kw):
    return jaxplush.parse_scene(recovery_scene_text(1, **kw), "<hanging>")


def test_a_kind_of_ones_own_is_fitted(tmp_path):
    truth = _hanging()
    k_true, n_true = float(truth.params.k_structural[0]), float(truth.params.nmol[0])
    full = fitting.make_target(truth, 200, 1e-3, 20)
    target = fitting.Target.of_kind(Silhouettes(), full.positions[:, rim(truth.vertices)][..., VIEW], full.times, full.dt)
    assert target.kind == "silhouettes" and fitting.Kind("silhouettes") is target.kind
    assert target.observed.all() and target.n_frames == full.n_frames

    start = _hanging(k_structural=1.5 * k_true, nmol=0.8 * n_true)
    res = fitting.fit(start, target, ["k_structural", "nmol"], noise_free=True, predictability=False)
    assert res.status == fitting.Status.CONVERGED, res
    for name, true in (("k_structural", k_true), ("nmol", n_true)):
        assert abs(float(res.values[name][0]) / true - 1.0) < 1e-3, (name, res.values)
    # judged as any fit: the identifiability report from the kind's own residual (T frames x M
    # points x 2 coordinates) and the twins' intervals, which hold the truth
    assert res.identifiability.n_data == target.n_frames * target.data.shape[1] * 2
    assert all(res.identifiability.determined)
    assert res.intervals.method == "twins"
    theta = np.log([k_true, n_true])
    assert np.all(np.abs(res.intervals.theta - theta) <= 4 * res.intervals.sd + 1e-9), res.intervals
    path = res.save(tmp_path / "FIT.h5")
    saved = fitting.load_fit(path)
    assert saved["attrs"]["status"] == res.status
    assert saved["fitted"]["positions"].shape == full.positions.shape


def test_a_kind_without_a_residual_is_refused():
    class Nothing(fitting.Kind):
        name = "nothing"

    with pytest.raises(NotImplementedError, match="nothing"):
        Nothing().residual(None, None, 0.0, "motion")
    with pytest.raises(ValueError, match="unknown target kind"):
        fitting.Kind("no such kind")

    class Points(fitting.Kind):
        name = "points"

    with pytest.raises(TypeError, match="built in"):
        Points()
    assert fitting.Kind("points") is fitting.TargetKind.POINTS
