"""The recovery benchmark's oracle (benchmarks/oracle.py; bench_recovery.py --oracle-only): its
sensitivities are the rollout's (float64 finite differences at two step sizes), its standard
deviations follow the information (a degenerate pair is infinite, their combination is not;
more cloud points, smaller sd by their square root), and the benchmark judges fits against it."""

from __future__ import annotations

import math

import numpy as np
import pytest

import jax
from jaxplush.fitting.targets import scenarios as S

from conftest import load_benchmark

@pytest.fixture(scope="module")
def oracle():
    return load_benchmark("oracle.py", "oracle_under_test")


@pytest.fixture(scope="module")
def bench():
    return load_benchmark("bench_recovery.py", "bench_recovery_for_oracle")


def _pinned_ball(kind, damping_model):
    """A 42-vertex ball hanging from a pin, as the random draw makes it."""
    case = S.draw_case(np.random.default_rng(11), max_objects=1, kinds=(kind,), shapes=("ball",),
                       levels=(1,), settings=("pinned",), damping_models=(damping_model,))
    case.update(index=0, seed=0)
    return case


@pytest.fixture(scope="module")
def pair_case(bench, tmp_path_factory):
    """The ball damped by the report's damping and by drag (one regressor), 120 steps, positions."""
    case = _pinned_ball("positions", "damping+drag")
    truth, _, _ = bench.random_case_files(str(tmp_path_factory.mktemp("oracle")), case, steps=120)
    return case, truth


def test_sds_follow_the_information(oracle):
    """sd = sqrt of the inverse information's diagonal; a null direction makes every parameter in
    it infinite, while a combination orthogonal to it stays finite."""
    assert np.allclose(oracle.sds(np.diag([4.0, 1.0]), np.eye(2)), [0.5, 1.0])
    F = np.array([[1.0, 1.0], [1.0, 1.0]])              # only p0 + p1 is measured
    assert oracle.sds(F, np.eye(2)) == [math.inf, math.inf]
    assert np.isclose(oracle.sds(F, np.array([[0.5, 0.5]]))[0], math.sqrt(0.5 / 2))
    judged, ok, reason = oracle.judge({"k[a]": 0.001, "damping[a]": math.inf, "drag[a]": math.inf},
                                      {"rate[a]": 0.002}, 0.01)
    assert ok and judged == {"k[a]": True, "rate[a]": True} and reason is None
    judged, ok, reason = oracle.judge({"k[a]": 0.02}, {}, 0.01)
    assert not ok and "k[a] sd 2% > 0.5%" in reason


def test_segment_sensitivities_match_finite_differences(oracle, pair_case):
    """The forward sensitivities along a segment of several frames, restarted from a true state,
    are the float64 central differences of the same rollout (relative steps 1e-4 and 1e-5): so
    the information the oracle sums is that of the model, not of its own bookkeeping."""
    case, truth = pair_case
    saved = oracle.saved_steps(case["steps"], case["save_every"])
    with jax.enable_x64(True):
        states = oracle.truth_states(truth, case, case["dt"], saved)
        seg = (3, 8)                                      # frames 4..8 from the true state at frame 3
        weight = lambda k: np.ones(truth.n_vertices)     # noqa: E731
        F = oracle.segment_information(truth, case, case["dt"], saved, states, [seg], weight)
        sim, p0, params_at, advance = oracle._machinery(truth, case, case["dt"])
        State = type(sim.internal.to_internal(sim.init_fn(p0)))
        s0 = State(*(jax.numpy.asarray(c) for c in states[seg[0]]))
        lengths = [saved[k] - saved[k - 1] for k in range(seg[0] + 1, seg[1] + 1)]

        @jax.jit
        def frames(theta):
            p, s, out = params_at(theta), s0, []
            for n in lengths:
                s = advance(p, s, n)
                out.append(s.x)
            return jax.numpy.stack(out).reshape(-1)

        P = F.shape[0]
        base = np.asarray(frames(np.zeros(P)))
        assert np.allclose(base.reshape(len(lengths), 3, -1), np.stack([states[k][0] for k in range(4, 9)]),
                           rtol=0, atol=1e-12)            # the restart reproduces the truth
        for h in (1e-4, 1e-5):
            J = np.stack([(np.asarray(frames(h * e)) - np.asarray(frames(-h * e))) / (2 * h)
                          for e in np.eye(P)], axis=1)
            Ffd = J.T @ J
            assert np.abs(F - Ffd).max() <= 1e-5 * np.abs(Ffd).max(), h


def test_a_degenerate_pair_is_undetermined_and_its_rate_determined(oracle, pair_case):
    """damping and drag decay every velocity alike: the oracle calls each undetermined (infinite
    sd) and judges the case on their combined rate 1/(D dt) + drag, which the positions fix."""
    case, truth = pair_case
    o = oracle.oracle_case(truth, case, dt=case["dt"], steps=case["steps"], every=case["save_every"],
                           kind="positions", tolerance=0.01)
    assert o["sd"]["damping[ball0]"] == math.inf and o["sd"]["drag[ball0]"] == math.inf
    assert o["rate_sd"]["rate[ball0]"] < 0.005
    assert o["sd"]["k_structural[ball0]"] < 0.005 and o["sd"]["nmol[ball0]"] < 0.005
    assert o["case_determinable"] and set(o["determinable"]) == {"k_structural[ball0]", "nmol[ball0]", "rate[ball0]"}
    assert 0 < o["rounding"] < 1e-5 and o["segments"] == o["frames"]


def test_more_cloud_points_shrink_the_sd_by_their_square_root(oracle, bench, tmp_path):
    """For a cloud target the information is the points' (normal displacements at 2 mm): four
    times the points, half the sd; the twin segments are longer than one frame."""
    case = _pinned_ball("points", "dashpot")
    truth, _, _ = bench.random_case_files(str(tmp_path), case, steps=120)
    kw = dict(dt=case["dt"], steps=case["steps"], every=case["save_every"], kind="points", noise=0.002,
              tolerance=0.03)
    a = oracle.oracle_case(truth, case, n_points=100, **kw)
    b = oracle.oracle_case(truth, case, n_points=400, **kw)
    assert a["segments"] == b["segments"] < a["frames"]
    for lab in a["sd"]:
        assert 0 < b["sd"][lab] < math.inf
        assert a["sd"][lab] / b["sd"][lab] == pytest.approx(2.0, rel=1e-6)


def test_the_benchmark_judges_fits_against_the_oracle(bench):
    """A case the oracle cannot determine is excluded, not failed; a damping+drag fit that says
    undetermined only in the pair is recovered when the rate and the rest are within tolerance."""
    row = dict(kind="positions", budget=120.0, wall=10.0, exit=0, status="undetermined",
               undetermined=["damping[ball0]", "drag[ball0]"], combined_rate_errors=[0.002],
               errors={"k_structural[ball0]": 0.001, "damping[ball0]": 0.4, "drag[ball0]": -0.3,
                       "nmol[ball0]": -0.002})
    orc = dict(case_determinable=True, oracle=dict(determinable={"k_structural[ball0]": True, "nmol[ball0]": True,
                                                                 "rate[ball0]": True}))
    assert bench.oracle_verdict(dict(row), orc)["judged"] == "recovered"
    assert bench.oracle_verdict(dict(row, combined_rate_errors=[0.02]), orc)["judged"] == "failed"
    assert bench.oracle_verdict(dict(row, undetermined=["nmol[ball0]"]), orc)["judged"] == "failed"
    assert bench.oracle_verdict(dict(row, wall=200.0), orc)["judged"] == "failed"
    out = bench.oracle_verdict(dict(row), dict(case_determinable=False, oracle_reason="rate[ball0] sd 3% > 0.5%"))
    assert out["judged"] == "excluded" and "sd 3%" in out["oracle_reason"]
    assert bench.oracle_verdict(dict(row), None)["judged"] == "excluded"


def test_the_twin_ratio_counts_the_frames_within_the_horizon(bench, oracle):
    """Several objects in contact are judged on their re-simulated frames: the RMS misfit at the
    fitted values over that of the float64 truth twin, over the frames within the fit's horizon."""
    orc = dict(case_determinable=True, oracle=dict(twin_rms=[1.0, 1.0, 100.0]))
    row = dict(fit_rms=[1.0, 1.5, 1.0], frame_times=[0.1, 0.2, 0.3], horizon_time=0.2)
    assert bench.twin_ratio(row, orc) == pytest.approx(math.sqrt((1 + 2.25) / 2))
    assert row["twin_frames"] == 2
    row = dict(fit_rms=[1.0, 1.5, 1.0], frame_times=[0.1, 0.2, 0.3])     # no horizon: every frame
    assert bench.twin_ratio(row, orc) == pytest.approx(math.sqrt(4.25 / 10002))
    assert bench.twin_ratio(dict(fit_rms=[1.0]), orc) is None                       # no frame times
    # a fit cut at a predictable horizon: over its frames, the target's first
    row = dict(fit_rms=[1.0, 1.5], frame_times=[0.1, 0.2, 0.3])
    assert bench.twin_ratio(row, orc) == pytest.approx(math.sqrt(3.25 / 2)) and row["twin_frames"] == 2
    assert bench.twin_ratio(dict(fit_rms=[1.0] * 4, frame_times=[0.1, 0.2, 0.3]), orc) is None
    # the measure itself: the RMS of the coordinates per frame for positions
    tgt = type("T", (), dict(positions=np.zeros((2, 3, 3))))()
    frames = np.zeros((2, 3, 3))
    frames[1, 0, 0] = 3.0
    assert np.allclose(oracle.frame_rms(frames, tgt, None), [0.0, 1.0])
    # a fit cut at a predictable horizon: its frames against the target's first
    assert np.allclose(oracle.frame_rms(frames[:1], tgt, None), [0.0])
    # and of the points' distances to the surface for clouds
    faces = np.array([[0, 1, 2]])
    x = np.array([[[0.0, 0, 0], [1, 0, 0], [0, 1, 0]]])
    cloud = type("T", (), dict(positions=None, points=np.array([[[0.2, 0.2, 0.01], [0.1, 0.3, -0.02]]])))()
    assert np.allclose(oracle.frame_rms(x, cloud, faces), [math.sqrt((0.01 ** 2 + 0.02 ** 2) / 2)], rtol=1e-5)


def test_the_category_table_counts_determinable_and_recovered_cases(bench):
    rows = [dict(n_objects=1, kind="positions", description="ball162 pinned dashpot positions", judged="recovered"),
            dict(n_objects=2, kind="points", description="ball162+bean162 floor drag points", judged="failed"),
            dict(n_objects=2, kind="points", description="ball162+bean162 floor drag points", judged="excluded")]
    table = "\n".join(bench.category_table(rows))
    assert "| one object | 1 | 1 | 1 of 1 |" in table
    assert "| several objects on a floor (contact) | 2 | 1 | 0 of 1 |" in table
    assert "| several objects, clouds | 2 | 1 | 0 of 1 |" in table
    oracle_only = [dict(r, case_determinable=r["judged"] != "excluded") for r in rows]
    for r in oracle_only:
        del r["judged"]
    assert "| two objects | 2 | 1 |" in "\n".join(bench.category_table(oracle_only))


def test_a_well_determined_parameter_does_not_make_another_look_undetermined(oracle):
    """Scales a million-fold apart (a stack's top object against the one below it): each sd is
    its own, not infinite because the other's information dwarfs it."""
    F = np.diag([1e18, 1.0, 4.0])
    F[1, 2] = F[2, 1] = 1.0
    sd = oracle.sds(F, np.eye(3))
    assert sd[0] == pytest.approx(1e-9)
    assert np.allclose(sd[1:], np.sqrt(np.diag(np.linalg.inv(F[1:, 1:]))))
    assert oracle.sds(np.diag([1.0, 0.0]), np.eye(2)) == [1.0, math.inf]     # no information at all
