"""Fitting a stiffness field (jaxplush.fitting.stages.field): the smoothness graph and its regulariser
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
from jaxplush.fitting.stages import field as F
from jaxplush.fitting.targets import scenarios
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


# --------------------------------------------------------------------------- fits on a small plush

DT = 5e-4
TRUE_K = {"front": 60.0, "back": 240.0}


def _two_region_text(k=TRUE_K, height=0.04):
    """A 42-vertex plush of two face groups (the panels facing +z and -z), dropped from ``height``
    onto a floor, with gas and a dashpot; ``k`` the groups' stiffness (None: no k_region lines)."""
    from jaxplush.scene.write import format_scene
    v, f, panel = scenarios.panel_ball(1)
    front = scenarios._icosahedron_normals()[panel, 2] > 0
    groups = ["front" if x else "back" for x in front]
    obj = dict(name="plush", vertices=v, faces=f, total_weight=0.1, k_structural=100.0, dashpot=0.02,
               nmol=3e-4, translate=[0.0, height - v[:, 1].min(), 0.0], groups=groups,
               k_region=dict(k) if k is not None else None)
    return format_scene([obj], gravity=(0.0, -9.81, 0.0), floor=0.0, temperature=293.15)


@pytest.fixture(scope="module")
def two_regions():
    truth = jaxplush.parse_scene(_two_region_text(), "<truth>")
    start = jaxplush.parse_scene(_two_region_text(k=None), "<start>")
    return truth, start


def _start(truth):
    p = truth.params
    return dict(k_structural=120.0, dashpot=float(p.dashpot[0]) * 0.7, nmol=float(p.nmol[0]) * 1.3)


def _check_recovered(res, truth, rtol):
    names = res.region_names
    got = dict(zip(names, res.k_regions))
    for g, k in TRUE_K.items():
        assert abs(got[g] / k - 1) < rtol, (g, got[g])
    for n in ("dashpot", "nmol"):
        true = float(getattr(truth.params, n)[0])
        assert abs(res.values[n][0] / true - 1) < rtol, (n, res.values[n][0], true)
    # the per-edge field is the regions' means (half and half on the border)
    assert np.allclose(res.k_structural, truth.params.k_structural, rtol=rtol)


def test_two_region_field_from_exact_positions(two_regions):
    truth, start = two_regions
    assert truth.has_k_field and set(truth.group_names) == {"front", "back"}
    target = fitting_target(truth, point_cloud=False)
    res = F.fit_field(start, target, "regions", weight=0.0, start=_start(truth), iterations=80, noise_free=True)
    assert res.kind == "regions" and len(res.k_regions) == 2 and res.k_structural.shape == (len(truth.edges),)
    assert res.loss < 1e-3 * res.loss_start
    _check_recovered(res, truth, 0.01)
    assert res.history["loss"][0] == res.loss_start and np.all(np.diff(res.history["time"]) >= 0)


def test_an_interrupted_field_fit_resumes_to_the_same_answer(two_regions, tmp_path):
    """A field fit checkpoints its loop (every 3 iterations here, and on Ctrl-C); killed part-way
    and resumed, it takes the same steps as the run that was never stopped (the same values to
    rounding, the same history), and a resume with another smoothness weight is refused."""
    from jaxplush.fitting.options import CheckpointOptions, FitOptions
    truth, start = two_regions
    target = fitting_target(truth, point_cloud=False)
    kw = dict(weight=1e-3, start=_start(truth), iterations=12, noise_free=True)
    whole = F.fit_field(start, target, "regions", **kw)
    path = tmp_path / "FIT.h5"
    opts = FitOptions(checkpoint=CheckpointOptions(path=str(path), every=3))

    def stop(info):
        if info["iteration"] == 7:
            raise KeyboardInterrupt
    with pytest.raises(KeyboardInterrupt):
        F.fit_field(start, target, "regions", options=opts, callback=stop, **kw)
    with h5py.File(path) as f:
        assert f.attrs["status"] == "interrupted" and "checkpoint" in f and f.attrs["iterations"] >= 7
    seen = []
    resumed = F.fit_field(start, target, "regions", options=FitOptions(
        checkpoint=CheckpointOptions(path=str(path), every=3, resume=True)), callback=lambda i: seen.append(i["iteration"]),
        **kw)
    assert seen and seen[0] >= 7                  # it went on from the checkpoint, not from the start
    assert resumed.iterations == whole.iterations
    np.testing.assert_allclose(resumed.history["loss"], whole.history["loss"], rtol=1e-5)
    np.testing.assert_allclose(resumed.k_regions, whole.k_regions, rtol=1e-5)
    # the finished FIT.h5 keeps its loop: a resume on it returns the same result, with no new step
    with h5py.File(path) as f:
        assert f.attrs["status"] != "interrupted" and "checkpoint" in f
    more = []
    again = F.fit_field(start, target, "regions", options=FitOptions(
        checkpoint=CheckpointOptions(path=str(path), resume=True)), callback=lambda i: more.append(i), **kw)
    assert not more and again.iterations == resumed.iterations
    np.testing.assert_array_equal(again.k_regions, resumed.k_regions)
    with pytest.raises(JaxplushError, match="different fit .weight"):
        F.fit_field(start, target, "regions", options=FitOptions(
            checkpoint=CheckpointOptions(path=str(path), resume=True)), **dict(kw, weight=2e-3))


def test_two_region_field_from_a_partial_point_cloud(two_regions):
    """One depth camera in front: the back group is seen only at its rim, yet the fit recovers it."""
    from jaxplush.io.capture import Camera, depth_capture
    truth, start = two_regions
    exact = fitting_target(truth, point_cloud=False)
    cam = Camera(eye=(0.0, 0.15, 0.5), target=(0.0, 0.08, 0.0), fov_deg=40, width=48, height=36)
    frames = np.concatenate([truth.vertices[None], exact.positions])
    cap = depth_capture(frames, truth.faces, cam, seed=0)
    assert 0 < cap.counts.min()
    steps = np.concatenate([[0], exact.steps])
    target = Target(positions=None, points=cap.points, steps=steps, times=steps * DT, dt=DT, path="<capture>")
    res = F.fit_field(start, target, "regions", weight=0.0, start=_start(truth), iterations=80, noise_free=True)
    _check_recovered(res, truth, 0.03)


def fitting_target(truth, point_cloud=False):
    from jaxplush import fitting
    return fitting.make_target(truth, steps=600, dt=DT, save_every=30, point_cloud=point_cloud)


def test_field_problem_checks_and_start(two_regions):
    """Bad inputs are refused before tracing; the start field and the preconditioner's variables."""
    truth, start = two_regions
    target = fitting_target(truth)
    with pytest.raises(JaxplushError, match="unknown field kind"):
        F.build_field_problem(start, target, "faces")
    with pytest.raises(JaxplushError, match="k_structural is the field"):
        F.build_field_problem(start, target, "edges", params=("k", "nmol"))
    with pytest.raises(JaxplushError, match="weight must be"):
        F.build_field_problem(start, target, "edges", weight=-1.0)
    with pytest.raises(JaxplushError, match=r"\(2,\) values"):
        F.build_field_problem(start, target, "regions", start=dict(k_structural=[1.0, 2.0, 3.0]))
    plain = jaxplush.parse_scene(scenarios.panel_scene_text(1, stiff=None).replace("g panel", "# g panel"), "<p>")
    with pytest.raises(JaxplushError, match="needs face groups"):
        F.build_field_problem(plain, target, "regions")
    fp = F.build_field_problem(start, target, "edges", precondition=3.0, start=dict(k_structural=80.0))
    assert fp.names == ("dashpot", "nmol") and fp.n_field == len(start.edges)
    field, glob = fp.split(fp.theta0)
    assert np.allclose(np.exp(field), 80.0) and np.allclose(np.exp(glob[:, 0]), [0.02, 3e-4])
    n = 3 * target.positions.shape[0] * start.n_vertices            # exact positions: motion-normalised
    assert fp.weight == pytest.approx(F.MOTION_NOISE ** 2 / (n * F.DEFAULT_TAU ** 2))
    assert F.default_weight(n) == pytest.approx(1 / (n * 0.25)) and fp.prob.loss.normalisation == "motion"
    fr = F.build_field_problem(truth, target, "regions")
    assert np.allclose(fr.k_edges(fr.split(fr.theta0)[0]), truth.params.k_structural)


def test_field_identifiability_jacobian_matches_differences_and_the_report_is_saved(two_regions, tmp_path):
    """The identifiability report of a fit per region: in float64 its Jacobian's data rows (forward
    mode, metres per unit log) agree with central differences of the residuals, the smoothness
    prior adds one row per adjacent pair, and a short fit's report (finite standard errors for
    both regions and the globals) reaches FIT.h5."""
    from jaxplush.fitting.objective import losses as L
    truth, start = two_regions
    target = fitting_target(truth)
    with jax.enable_x64(True):
        fp = F.build_field_problem(start, target, "regions", start=_start(truth))
        theta = np.asarray(fp.theta0, np.float64)
        jac, resid, labels = F.field_jacobian(fp, theta)
        res = L.make_residual(fp.prob.target, fp.sim.topology, fp.prob.loss)
        n = res.n
        assert set(labels[:2]) == {"k_structural[back]", "k_structural[front]"}
        assert labels[2:] == ("dashpot[plush]", "nmol[plush]")
        assert jac.shape == (n + len(fp.pairs), 4) and resid.shape == (n + len(fp.pairs),)
        field, glob = fp.split(theta)
        coords = np.concatenate([field, glob.ravel()])

        def residual_m(c):
            p = fp.prob.to_params(c[2:].reshape(glob.shape))._replace(k_structural=fp.k_edges(jnp.asarray(c[:2])))
            from jaxplush.fitting.judge import identifiability as I
            frames, _ = I.frames_at_steps(fp.sim, p, fp.sim.init_fn(p), fp.prob.loss.frame_steps)
            return np.asarray(res.fn(frames), np.float64) / res.norm
        assert np.allclose(resid[:n], residual_m(coords), rtol=1e-9, atol=1e-12)
        for j in range(4):
            errs = []
            for h in (1e-3, 2.5e-4):
                e = np.zeros(4)
                e[j] = h
                fd = (residual_m(coords + e) - residual_m(coords - e)) / (2 * h)
                errs.append(np.linalg.norm(fd - jac[:n, j]) / np.linalg.norm(jac[:n, j]))
            assert errs[1] < 1e-4, (j, errs)
        # the prior's rows: sqrt(weight) / norm per pair, on the two regions' columns only
        unit = np.sqrt(fp.weight) / res.norm
        assert np.allclose(np.abs(jac[n:, :2]), unit) and np.all(jac[n:, 2:] == 0)
    out = F.fit_field(start, target, "regions", start=_start(truth), iterations=5, noise_free=True)
    rep = out.identifiability
    assert rep is not None and len(rep.labels) == 4
    assert np.all(np.isfinite(rep.stderr)) and np.all(rep.stderr > 0)
    out.save(tmp_path / "F.h5")
    with h5py.File(tmp_path / "F.h5", "r") as f:
        assert list(f["identifiability"].attrs["labels"]) == list(rep.labels)
        assert np.allclose(f["identifiability/stderr"][()], rep.stderr)
        timing = dict(f["timing"].attrs)           # the field fit's compile time apart from the rest
    assert 0.0 <= timing["compile_s"] <= timing["wall_s"] and timing["programs"] >= 0
    assert timing["wall_s"] == out.timing.wall_s and f"time: {out.timing.text()}" in out.table()
    edges = F.fit_field(start, target, "edges", start=_start(truth), iterations=2, noise_free=True)
    assert edges.identifiability is None


# --------------------------------------------------------------------------- the command line and the picture

@pytest.mark.heavy
def test_cli_field_regions_writes_the_field_and_a_scene_that_reads_back(tmp_path, two_regions):
    """``jaxplush-fit START TARGET --field regions``: FIT.h5 holds fields/k_structural [E] (and the
    regions), the fitted scene reads back with that field (k_region lines), the picture is written."""
    from jaxplush.fitting.cli import main
    truth, _ = two_regions
    (tmp_path / "start.obj").write_text(_two_region_text(k=None))
    (tmp_path / "truth.obj").write_text(_two_region_text())
    fitting_target(truth).save(tmp_path / "target.h5", truth)
    out, scene_out = tmp_path / "FIT.h5", tmp_path / "fitted.obj"
    code = main([str(tmp_path / "start.obj"), str(tmp_path / "target.h5"), "--field", "regions", "--field-weight",
                 "0", "--start", "k=120", "--iterations", "60", "--noise-free", "--quiet", "--out", str(out),
                 "--out-scene", str(scene_out), "--field-true", str(tmp_path / "truth.obj")])
    assert code in (0, 4)
    with h5py.File(out, "r") as f:
        field = f["fields/k_structural"][()]
        assert field.shape == (len(truth.edges),) and f["fields/k_region"].shape == (2,)
        assert f.attrs["field"] == "regions" and f.attrs["field_weight"] == 0.0
        assert f["params/k_structural"].shape == (1,) and f["history/loss"].shape[0] >= 1
        assert f["fitted/positions"].shape[1:] == (truth.n_vertices, 3)
        assert f.attrs["fitted_scene"] == scene_out.read_text() or "k_region" in f.attrs["fitted_scene"]
    assert np.allclose(field, truth.params.k_structural, rtol=0.01)
    back = jaxplush.load_scene(scene_out)
    assert back.has_k_field and np.array_equal(back.params.k_structural, field)
    assert "k_region" in scene_out.read_text() and "k_edge" not in scene_out.read_text()
    assert (tmp_path / "FIT.field.png").stat().st_size > 10_000


def test_cli_field_bad_options(tmp_path, capsys):
    """--field refuses the default fit's and the checkpoint's options before anything runs."""
    from jaxplush.fitting.cli import main
    (tmp_path / "s.obj").write_text(_two_region_text(k=None))
    base = [str(tmp_path / "s.obj"), str(tmp_path / "t.h5"), "--out", str(tmp_path / "F.h5")]
    for extra, message in ((["--field", "regions", "--optimizer", "lm"], "fits by gradients"),
                           (["--field", "edges", "--objects", "plush"], "does not go with --field"),
                           (["--field", "edges", "--field-weight", "-1"], "must be a number >= 0"),
                           (["--field-weight", "1"], "go with --field"),
                           (["--field", "edges", "--field-png", str(tmp_path / "x.txt")], "must end in")):
        assert main(base + extra) == 2
        assert message in capsys.readouterr().err
    assert not (tmp_path / "F.h5").exists()


def test_render_field(tmp_path):
    from jaxplush.io.render import face_log_stiffness, render_field
    v, f, panel = scenarios.panel_ball(1)
    edges = unique_edges(f)
    k = np.linspace(50.0, 500.0, len(edges))
    fl = face_log_stiffness(f, edges, k)
    fe = F.face_edges(f, edges)
    assert np.allclose(fl, np.log10(k[fe]).mean(axis=1)) and np.allclose(F.face_values(k, f, edges), fl)
    out = render_field(v, f, edges, [("a", k), ("b", k[::-1])], tmp_path / "k.png", title="t")
    assert os.path.getsize(out) > 10_000
    with pytest.raises(JaxplushError, match="finite values > 0"):
        render_field(v, f, edges, [("a", -k)], tmp_path / "k2.png")
    with pytest.raises(JaxplushError, match="extension"):
        render_field(v, f, edges, [("a", k)], tmp_path / "k.gif")
    assert not (tmp_path / "k2.png").exists()


def test_patch_iou():
    v, f, panel = scenarios.panel_ball(1)
    edges = unique_edges(f)
    k_true = np.where(np.isin(np.arange(len(edges)), F.face_edges(f, edges)[panel < 4].ravel()), 300.0, 60.0)
    assert F.patch_iou(k_true, k_true, v, f, edges, 134.0) == 1.0
    assert F.patch_iou(np.full(len(edges), 60.0), k_true, v, f, edges, 134.0) == 0.0


@pytest.mark.heavy
def test_bench_real_capture_small(tmp_path):
    """The acceptance bench at its small size runs and its per-region fit meets the targets."""
    r = subprocess.run([sys.executable, os.path.join(ROOT, "benchmarks", "bench_real_capture.py"), "--small",
                        "--quiet", "--out-dir", str(tmp_path), "--bound"], capture_output=True, text=True, timeout=900)
    assert r.returncode == 0, r.stderr[-3000:]
    lines = r.stdout.splitlines()
    line = next(x for x in lines if x.startswith("(a) regions") and "targets" in x)
    assert "meets the targets" in line, r.stdout
    assert (tmp_path / "field_regions.png").exists() and (tmp_path / "fit_edges.h5").exists()
    # the Cramer-Rao bound: tracking every vertex can only lower each standard error; the
    # vertices chosen for the dashpot bound it no worse than a typical random choice; and the
    # fit of case (c) reports a dashpot standard error no better than the bound allows
    bound = {key: [float(v.rstrip("%")) for v in next(x for x in lines if x.startswith(start)).split()[-3:]]
             for key, start in (("random", "20 random"), ("chosen", "20 vertices chosen"), ("every", "every vertex"))}
    assert all(0 < e <= c and e <= rnd for e, c, rnd in zip(bound["every"], bound["chosen"], bound["random"]))
    assert bound["chosen"][1] <= bound["random"][1]
    fit_se = next(x for x in lines if x.startswith("(c) tracks: standard errors"))
    dashpot_se = float(fit_se.split("dashpot ")[1].split("%")[0])
    assert dashpot_se >= 0.5 * bound["random"][1], (fit_se, bound)
