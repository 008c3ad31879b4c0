"""The random-scene recovery benchmark (benchmarks/bench_recovery.py --random N; the generator
jaxplush.fitting.targets.scenarios.draw_case): the draws are deterministic, cover every shape, damping
model, object count, setting and target kind, and give valid scenes whose objects start apart;
and one tiny case run through the benchmark's case runner gives an honest record."""

from __future__ import annotations

import importlib.util
import json
import math
import os
import sys

import numpy as np
import pytest

import jax
import jaxplush
from jaxplush.fitting.judge import outcome
from jaxplush.fitting.targets import scenarios as S
from jaxplush.fitting.fitter import default_params

from conftest import load_benchmark

_BENCH = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "benchmarks",
                      "bench_recovery.py")
N_DRAWS = 200


@pytest.fixture(scope="module")
def bench():
    return load_benchmark("bench_recovery.py", "bench_recovery_under_test")


@pytest.fixture(scope="module")
def cases(bench):
    return bench.draw_cases(N_DRAWS, 7)


def test_the_draws_are_deterministic(bench, cases):
    """Same seed: the same cases and the same scene text (truth and start); another seed differs;
    case i does not depend on how many are drawn."""
    again = bench.draw_cases(N_DRAWS, 7)
    assert json.dumps(again) == json.dumps(cases)
    for a, b in zip(cases[:20], again[:20]):
        assert S.case_scene_text(a) == S.case_scene_text(b)
        assert S.case_start_text(a) == S.case_start_text(b)
    assert json.dumps(bench.draw_cases(5, 7)) == json.dumps(cases[:5])
    assert json.dumps(bench.draw_cases(5, 8)) != json.dumps(cases[:5])


def test_the_draws_cover_every_shape_model_count_setting_and_kind(cases):
    objs = [o for c in cases for o in c["objects"]]
    assert {o["shape"] for o in objs} == set(S.SHAPES) == {"ball", "torus", "bean", "cushion", "capsule"}
    assert {o["level"] for o in objs} == {2, 3}
    assert {c["damping_model"] for c in cases} == set(S.DAMPING_MODELS)
    assert {c["n_objects"] for c in cases} == {1, 2, 3}
    assert {c["kind"] for c in cases} == {"positions", "points"}
    assert {c["setting"] for c in cases} == {"floor", "pinned"}
    floors = [c for c in cases if c["setting"] == "floor"]
    assert any(c["floor_friction"] for c in floors) and any(not c["floor_friction"] for c in floors)
    assert any(c["n_objects"] > 1 for c in cases if c["setting"] == "pinned")
    assert any(o["tilt_deg"] > 0 for o in objs) and any(o["tilt_deg"] == 0 for o in objs)
    assert len({o["total_weight"] for o in objs}) > N_DRAWS // 2                     # masses vary
    for c in cases:
        for n, fs in c["start"].items():
            assert len(fs) == c["n_objects"] and all(0.5 <= f <= 2.0 for f in fs), (n, fs)
    factors = [f for c in cases for fs in c["start"].values() for f in fs]
    assert min(factors) < 0.55 and max(factors) > 1.8                                  # the whole range
    # --max-vertices keeps to the coarse meshes
    coarse = [S.draw_case(np.random.default_rng([7, i]), max_vertices=200) for i in range(40)]
    assert all(o["vertices"] <= 200 and o["level"] == 2 for c in coarse for o in c["objects"])


def _boxes_apart(a, b):
    lo_a, hi_a, lo_b, hi_b = a.min(0), a.max(0), b.min(0), b.max(0)
    return bool(np.any((hi_a < lo_b) | (hi_b < lo_a)))


def test_every_drawn_scene_is_valid_and_its_objects_start_apart(cases):
    """Every truth and start scene parses; the scene has what the case says (objects, floor or
    pins, friction, contact with several objects, the damping model's parameters switched on),
    jaxplush-fit's default fits exactly the case's parameters, the start is the truth times the
    factors, and the objects' bounding boxes are apart at the start."""
    for c in cases:
        truth = jaxplush.parse_scene(S.case_scene_text(c), "<truth>")
        start = jaxplush.parse_scene(S.case_start_text(c), "<start>")
        assert truth.n_objects == c["n_objects"]
        assert [o.name for o in truth.objects] == [o["name"] for o in c["objects"]]
        assert truth.n_vertices == sum(o["vertices"] for o in c["objects"])
        if c["setting"] == "floor":
            assert truth.floor == 0.0 and len(truth.fixed) == 0
            assert truth.vertices[:, 1].min() > 0.019
            assert (truth.floor_friction or None) == c["floor_friction"]
        else:
            assert truth.floor is None and len(truth.fixed) == c["n_objects"]
        if c["n_objects"] > 1:
            assert truth.contact
        assert default_params(truth)[0] == tuple(c["params"])
        values = S.case_truth(c)
        for n in c["params"]:
            assert np.allclose(getattr(truth.params, n), values[n], rtol=1e-12)
            assert np.allclose(getattr(start.params, n), np.asarray(values[n]) * c["start"][n], rtol=1e-12)
        assert np.array_equal(truth.vertices, start.vertices)
        parts = [truth.vertices[slice(*o.vertex_slice)] for o in truth.objects]
        for i in range(len(parts)):
            for j in range(i + 1, len(parts)):
                assert _boxes_apart(parts[i], parts[j]), (S.describe_case(c), i, j)


def _tiny_case():
    """A 42-vertex ball (level 1) resting 1 cm above the floor, with a dashpot, positions."""
    case = S.draw_case(np.random.default_rng(3), max_objects=1, kinds=("positions",), shapes=("ball",),
                       levels=(1,), settings=("floor",), damping_models=("dashpot",))
    obj = case["objects"][0]
    v, _ = S._placed(obj)
    obj["position"][1] = round(obj["position"][1] - (v[:, 1].min() - 0.01), 6)
    case.update(index=0, seed=0)
    return case


def test_one_tiny_case_gives_an_honest_record(bench, tmp_path):
    """The case runner fits a 42-vertex drop (300 steps) and records what happened: the fit's
    status, exit code and time, the errors against the truth, and a verdict that follows from
    them (no fitted number is asserted: the outcome may differ between CPUs)."""
    case = _tiny_case()
    row = bench.run_random_case(str(tmp_path), case, steps=300, stop_after=0)
    assert row["vertices"] == [42] and row["shapes"] == ["ball"] and row["n_objects"] == 1
    assert row["kind"] == "positions" and row["damping_model"] == "dashpot" and row["floor"] and not row["pinned"]
    assert row["steps"] == 300 and row["dt"] > 0 and row["save_every"] >= 1
    assert row["description"].startswith("ball42 floor") and row["budget"] == 120.0
    assert row["status"] in outcome.STATUSES and not row["stopped"]
    assert row["exit"] in (0, outcome.EXIT_NOT_CONVERGED)
    assert (row["exit"] == 0) == (row["status"] in outcome.DONE)
    assert row["wall"] > 0
    assert set(row["errors"]) == {f"{n}[ball0]" for n in ("k_structural", "dashpot", "nmol")}
    assert math.isfinite(row["max_error"]) and row["max_error"] == max(abs(e) for e in row["errors"].values())
    ok = row["status"] == "converged" and row["max_error"] <= 0.01 and row["wall"] <= 120.0
    assert (row["verdict"] == "recovered") == ok
    if ok:
        assert row["reason"] is None
    else:
        assert row["verdict"] == "failed" and row["reason"] in bench.REASONS
        assert (row["reason"] == "floor") == (row["status"] == "at_floor")
    # the reported 95% intervals are read back per fitted parameter (truth inside or not)
    assert set(row["covered"]) == set(row["errors"]) and row["interval_method"] in ("twins", "residuals")
    json.dumps(row, default=float)                                   # what --json writes
    line = bench._random_line(row)
    assert line.startswith("| 0 | ball42 floor") and row["verdict"] in line
    summary = bench._summary([row])
    assert summary[0] == f"recovered {int(ok)}/1 (positions {int(ok)}/1, clouds 0/0)"


def test_a_truth_that_cannot_be_simulated_is_drawn_again_and_listed(bench, tmp_path, monkeypatch):
    """A truth that blows up at every dt is no fitting case: the case is drawn again from its own
    generator (at most MAX_DRAWS draws), every discarded draw is listed, and a case that never
    gives a truth is a failure ("no target"), never dropped."""
    from jaxplush.errors import SimulationError
    seen = []

    def crushed(d, case, **kw):
        seen.append((case["attempt"], S.describe_case(case)))
        raise SimulationError(10, 0, "torus0", "the enclosed volume became zero or negative")

    monkeypatch.setattr(bench, "random_case_files", crushed)
    case = bench.draw_cases(1, 11, max_objects=1)[0]
    row = bench.run_random_case(str(tmp_path), case, stop_after=0)
    assert [a for a, _ in seen] == list(range(bench.MAX_DRAWS))
    assert seen[0][1] == S.describe_case(case)
    assert bench.redraw(0, 11, 1, max_objects=1)["objects"] != case["objects"]
    assert row["status"] == "no target" and row["verdict"] == "failed" and row["reason"] == "other"
    assert len(row["redrawn"]) == bench.MAX_DRAWS - 1 and "volume" in row["redrawn"][0]
    assert row["redrawn"][0].startswith(seen[0][1])
    assert any("drawn again" in line for line in bench._summary([row]))
    json.dumps(row, default=float)


def test_the_verdict_follows_status_error_time_and_reports(bench):
    """The verdict's rules on hand-made records: within tolerance and time is recovered; then
    floor, horizon, identifiability, time and other, in that order."""
    base = dict(kind="points", budget=120.0, exit=0, status="converged", max_error=0.02, wall=10.0, steps=1000,
                dt=5e-4)

    def v(**kw):
        r = bench.verdict(dict(base, **kw))
        return r["verdict"], r["reason"]

    assert v() == ("recovered", None)
    assert v(kind="positions") == ("failed", "other")                # 2% > 1%
    assert v(wall=130.0) == ("failed", "time")
    assert v(stopped=True, exit=130, status="interrupted") == ("failed", "time")
    assert v(exit=4, status="at_floor", horizon_time=0.1) == ("failed", "floor")
    assert v(exit=4, status="poor_fit", horizon_time=0.3, undetermined=["drag[ball0]"]) == ("failed", "horizon")
    assert v(exit=4, status="poor_fit", horizon_time=math.inf, undetermined=["drag[ball0]"]) == \
        ("failed", "identifiability")
    assert v(exit=4, status="poor_fit", identifiability_warnings=["J^T J is ill-conditioned"]) == \
        ("failed", "identifiability")
    # a converged fit outside the tolerance: identifiability when the fit's own standard error of
    # that parameter is at least half the tolerance (the noise alone can put it there), else other
    miss = dict(errors={"dashpot[c]": 0.063, "k_structural[c]": -0.0015})
    assert v(**miss, max_error=0.063, stderr={"dashpot[c]": 0.021, "k_structural[c]": 0.0007}) == \
        ("failed", "identifiability")
    assert v(**miss, max_error=0.063, stderr={"dashpot[c]": 0.01, "k_structural[c]": 0.0007}) == ("failed", "other")
    assert v(**miss, max_error=0.063) == ("failed", "other")
    assert v(exit=4, status="stalled", wall=200.0) == ("failed", "time")
    assert v(exit=4, status="stalled") == ("failed", "other")


def test_roughness_case_variants_are_the_drawn_scene_with_one_change(bench):
    """benchmarks/roughness.py --case: its scene variants parse, and each changes only what it
    says (one object alone; a set contact thickness; the smooth penalty floor)."""
    path, x64 = list(sys.path), jax.config.jax_enable_x64
    try:
        spec = importlib.util.spec_from_file_location(
            "roughness_under_test", os.path.join(os.path.dirname(_BENCH), "roughness.py"))
        rough = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(rough)
    finally:
        sys.path[:] = path
    case = next(c for c in bench.draw_cases(40, 29) if c["n_objects"] == 3 and c["setting"] == "floor")
    text = S.case_scene_text(case)
    drawn = jaxplush.parse_scene(text, "drawn")
    assert rough._case_text(text, "drawn", 0, 0.02) == text
    for o in range(3):
        alone = jaxplush.parse_scene(rough._case_text(text, "alone", o, 0.02), "alone")
        assert alone.n_objects == 1 and alone.object_names[0] == drawn.object_names[o]
        mine = np.asarray(drawn.object_id) == o
        np.testing.assert_array_equal(alone.vertices, drawn.vertices[mine])
        first = int(np.argmax(mine))
        faces = drawn.faces[np.all(mine[drawn.faces], axis=1)] - first
        np.testing.assert_array_equal(alone.faces, faces)
        for a, b in zip(alone.params, drawn.params):
            np.testing.assert_array_equal(a, np.asarray(b)[o:o + 1])
        assert alone.floor == drawn.floor and alone.floor_model == "projection"
    thick = jaxplush.parse_scene(rough._case_text(text, "thick", 0, 0.02), "thick")
    assert thick.contact_thickness == pytest.approx(0.02) and drawn.contact_thickness is None
    smooth = jaxplush.parse_scene(rough._case_text(text, "thick+smooth", 0, 0.02), "smooth")
    assert smooth.floor_model == "smooth" and smooth.contact_thickness == pytest.approx(0.02)
    np.testing.assert_array_equal(smooth.vertices, drawn.vertices)
    np.testing.assert_array_equal(smooth.faces, drawn.faces)
    for a, b in zip(smooth.params, drawn.params):
        np.testing.assert_array_equal(a, b)
    assert jax.config.jax_enable_x64 == x64          # importing the script left the precision alone


def test_a_random_run_resumes_from_its_json_lines(bench, tmp_path, monkeypatch, capsys):
    """``--json F --resume`` keeps the cases of the same draw already in F (one JSON line each,
    written as each case ends; a line cut short by a stop is skipped) and runs only the others, so
    100 cases can run across sittings; the lines of another draw are not taken."""
    ran = []

    def fake(args, case):
        ran.append(case["index"])
        return dict(index=case["index"], description="d", n_objects=1, kind="positions", vertices=[42],
                    start_factors={"k_structural": [1.0]}, status="converged", exit=0, wall=1.0, budget=120.0,
                    max_error=0.0, errors={}, verdict="recovered", reason=None, steps=10, dt=1e-3)
    monkeypatch.setattr(bench, "_case_in_child", fake)
    out = tmp_path / "r.jsonl"
    bench.main(["--random", "3", "--seed", "5", "--json", str(out)])
    assert ran == [0, 1, 2]
    lines = out.read_text().splitlines()
    assert len(lines) == 3 and all(json.loads(ln)["draw"].startswith("--random 3 --seed 5") for ln in lines)
    out.write_text(lines[0] + "\n" + lines[1][:25])             # stopped while writing case 1
    ran.clear()
    bench.main(["--random", "3", "--seed", "5", "--json", str(out), "--resume"])
    assert ran == [1, 2]
    assert "resumed: 1 of 3 cases" in capsys.readouterr().out
    ran.clear()
    bench.main(["--random", "3", "--seed", "6", "--json", str(out), "--resume"])
    assert ran == [0, 1, 2]
