"""The ``jaxplush-fit`` command line: a fit end to end (FIT.h5 layout, fitted scene), bad input
(exit 2, one message, no traceback, nothing written), SIGKILL and resume, Ctrl-C."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
import types

import h5py
import numpy as np
import pytest

import jaxplush
from jaxplush.fitting import cli
from jaxplush.fitting import fitter as F
from jaxplush.fitting.targets import make_target
from test_targets import BAD, _copy_with

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    """A 42-vertex hanging-ball scene with start values off by x2 / x0.5, and its target."""
    d = tmp_path_factory.mktemp("fitcli")
    truth = jaxplush.parse_scene(F.recovery_scene_text(1), "<truth>")
    p = truth.params
    scene = d / "start.obj"
    scene.write_text(F.recovery_scene_text(1, k_structural=2 * p.k_structural[0], damping=0.5 * p.damping[0],
                                           nmol=2 * p.nmol[0]))
    target = d / "target.h5"
    make_target(truth, 200, 1e-3, 20).save(target, truth)
    return dict(dir=d, scene=str(scene), target=str(target), truth=p)


def _leftovers(d):
    return sorted(n for n in os.listdir(d) if n.startswith(".tmp-") or n.endswith(".tmp"))


@pytest.mark.heavy
def test_fit_end_to_end(files, tmp_path, capsys):
    """The default fit, as a user runs it: jaxplush-fit SCENE TARGET --out FIT.h5 (no other options):
    the scene's material parameters recovered from starts x2 / x0.5, a converged status, FIT.h5 and
    the fitted scene."""
    out, obj = tmp_path / "FIT.h5", tmp_path / "fitted.obj"
    rc = cli.main([files["scene"], files["target"], "--out", str(out), "--out-scene", str(obj), "--quiet"])
    text = capsys.readouterr()
    assert rc == 0, text.err
    assert "fitting k_structural, damping, nmol (the material parameters the scene switches on)" in text.err
    assert "k_structural" in text.out and "identifiability" in text.out and "outcome: converged" in text.out
    start = jaxplush.load_scene(files["scene"]).params
    with h5py.File(out) as f:
        assert f.attrs["status"] == "converged" and f.attrs["scene"].startswith("# fitting recovery scenario")
        assert f.attrs["target_path"] == files["target"] and f.attrs["optimizer"] == "lm"
        fitted_vals = {}
        for n in ("k_structural", "damping", "nmol"):
            assert f["params"][n].shape == (1,) and f["start"][n][0] == getattr(start, n)[0]
            fitted_vals[n] = f["params"][n][0]
            assert fitted_vals[n] == pytest.approx(getattr(files["truth"], n)[0], rel=0.01)
            # the search: every global sample (the start, the linear start and 64 Sobol points) and the
            # local paths, for plots
            assert f["search"]["global"][n].shape == (66, 1) and f["search"]["global"]["loss"].shape == (66,)
            assert f["history"][n][-1, 0] == pytest.approx(fitted_vals[n], rel=1e-6)
        assert f.attrs["loss"] == pytest.approx(f["history"]["loss"][-1]) and f.attrs["loss"] < f.attrs["loss_start"]
        ig = f["identifiability"]
        assert ig["jtj"].shape == (3, 3) and ig["stderr"].shape == (3,) and ig.attrs["condition"] > 1
        assert f["fitted"]["positions"].shape == (10, 42, 3)
        # the values' 95% intervals from twins of the fitted values (jaxplush.fitting.judge.intervals)
        iv = f["intervals"]
        assert iv.attrs["method"] == "twins" and iv["lower"].shape == (3,) and np.all(iv["lower"][()] < iv["upper"][()])
        assert "95% interval" in text.out
        assert "checkpoint" in f
    fitted = jaxplush.load_scene(obj)
    for n, v in fitted_vals.items():
        assert getattr(fitted.params, n)[0] == v
    assert fitted.n_vertices == 42 and len(fitted.fixed) == 1 and fitted.fixed[0] == jaxplush.load_scene(
        files["scene"]).fixed[0]
    assert _leftovers(tmp_path) == []


def test_a_fit_that_did_not_converge_says_so_and_exits_4(files, tmp_path, capsys):
    """Adam stopped at 8 iterations has not reached the data: exit 4, the status in FIT.h5 and in the
    table, no standard errors, and no "converged" anywhere."""
    out = tmp_path / "FIT.h5"
    rc = cli.main([files["scene"], files["target"], "--optimizer", "adam", "--iterations", "8", "--lr", "0.1",
                   "--out", str(out)])
    text = capsys.readouterr()
    assert rc == cli.EXIT_NOT_CONVERGED == 4
    # the captured stderr is no terminal: the progress bar leaves plain lines, no redraws
    assert "\r" not in text.err and 1 <= text.err.count("fit [") <= 2, text.err
    rows = text.out.split("loss")[0].split("\n", 1)[1]           # the table's rows, below its header
    assert "outcome: iteration limit: " in text.out and "n/a" in rows and "%" not in rows
    assert "standard errors: not meaningful" in text.out and "converged:" not in text.out
    assert "the fit did not reach the data (iteration_limit)" in text.err
    assert "Traceback" not in text.err
    with h5py.File(out) as f:
        assert f.attrs["status"] == "iteration_limit" and not f.attrs["converged"]
        assert f.attrs["iterations"] == 8 and f["history"]["loss"].shape == (8,)


def _bad_cli_cases(files, d):
    good = [files["scene"], files["target"]]
    return {
        "unknown parameter": (good + ["--params", "k,stiffness2"], "unknown parameter 'stiffness2'"),
        "mass jointly": (good + ["--params", "k,total_weight"], "refusing to fit total_weight jointly"),
        "unknown object": (good + ["--objects", "bear"], "unknown object 'bear'"),
        "iterations": (good + ["--iterations", "0"], "--iterations must be >= 1"),
        "optimizer": (good + ["--optimizer", "sgd"], "--optimizer must be lm, adam or lbfgs"),
        "bounds syntax": (good + ["--bounds", "k=100"], "bounds: expected NAME=LO:HI"),
        "bounds order": (good + ["--bounds", "k=900:100"], "bounds of k_structural must satisfy 0 < lo < hi"),
        "bounds start": (good + ["--bounds", "k=1:2"], "lies outside its bounds 1:2"),
        "bounds unfitted": (good + ["--params", "k", "--bounds", "nmol=1e-4:1e-2"], "bounds given for nmol"),
        "bounds adam": (good + ["--optimizer", "adam", "--bounds", "k=1:2"], "--bounds belongs to the default fit"),
        "samples": (good + ["--samples", "-1"], "--samples must be >= 0"),
        "jacobian adam": (good + ["--optimizer", "adam", "--jacobian", "forward"],
                          "local options apply to the default fit (optimizer 'lm'), not to adam"),
        "out extension": (good + ["--out", str(d / "fit.txt")], "--out must end in .h5"),
        "out directory": (good + ["--out", str(d / "nodir" / "FIT.h5")], "does not exist"),
        "resume without file": (good + ["--resume"], "no checkpoint to resume"),
        "scene missing": ([str(d / "none.obj"), files["target"]], "none.obj: no such file"),
        "target missing": ([files["scene"], str(d / "none.h5")], "none.h5: no such file"),
        "dt off grid": (good + ["--dt", "3e-4"], "not on the dt = 0.0003 s grid"),
        "out overwrites input": ([files["scene"], files["target"], "--out", files["target"]],
                                 "must not overwrite an input"),
        "unknown method": (good + ["--method", "fast"], "unknown gradient method 'fast'"),
        "no parameters": (good + ["--params", ","], "no parameters to fit"),
        "negative dt": (good + ["--dt", "-5e-4"], "--dt must be a positive number"),
        "negative lr": (good + ["--lr", "-1e-2"], "--lr must be a positive number"),
        "bad start": (good + ["--start", "k=abc"], "--start: k='abc' is not a number"),
        "negative start": (good + ["--start", "k=-5e2"], "--start: k must be a positive number"),
        "start name": (good + ["--start", "stiffness2=3"], "unknown parameter 'stiffness2'"),
    }


@pytest.mark.parametrize("case", ["unknown parameter", "mass jointly", "unknown object", "iterations", "optimizer",
                                  "out extension", "out directory", "resume without file", "scene missing",
                                  "target missing", "dt off grid", "out overwrites input", "unknown method",
                                  "no parameters", "negative dt", "negative lr", "bad start", "negative start",
                                  "start name", "bounds syntax", "bounds order", "bounds start", "bounds unfitted",
                                  "bounds adam", "samples", "jacobian adam"])
def test_bad_input_exits_2_and_writes_nothing(files, tmp_path, capsys, case):
    argv, message = _bad_cli_cases(files, tmp_path)[case]
    if "--out" not in argv:
        argv = argv + ["--out", str(tmp_path / "FIT.h5")]
    before = sorted(os.listdir(tmp_path)) + sorted(os.listdir(files["dir"]))
    assert cli.main(argv + ["--quiet"]) == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err and err.startswith("jaxplush-fit: error:")
    assert sorted(os.listdir(tmp_path)) + sorted(os.listdir(files["dir"])) == before


@pytest.fixture(scope="module")
def sim_src(files):
    """A target file of the scene in the trajectory schema (5 frames), to be damaged."""
    src = files["dir"] / "sim.h5"
    scene = jaxplush.load_scene(files["scene"])
    make_target(scene, 40, 1e-3, 10, frames=slice(None)).save(src, scene)
    return src


@pytest.mark.parametrize("case", sorted(BAD))
def test_bad_target_exits_2_and_writes_nothing(files, sim_src, tmp_path, capsys, case):
    edit, message = BAD[case]
    bad = _copy_with(sim_src, tmp_path / "bad.h5", edit)
    out = tmp_path / "FIT.h5"
    assert cli.main([files["scene"], str(bad), "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert str(bad) in err and message in err and "Traceback" not in err
    assert not out.exists() and _leftovers(tmp_path) == []


def test_sigkill_then_resume_reaches_the_same_answer(files, tmp_path):
    """A fit killed with SIGKILL mid-way resumes from its last checkpoint to the same answer as an
    uninterrupted fit."""
    out = tmp_path / "FIT.h5"
    args = [files["scene"], files["target"], "--optimizer", "adam", "--iterations", "40", "--checkpoint-every", "2",
            "--out", str(out), "--quiet"]
    env = dict(os.environ, PYTHONPATH=REPO + os.pathsep + os.environ.get("PYTHONPATH", ""))
    proc = subprocess.Popen([sys.executable, "-m", "jaxplush.fitting.cli"] + args, cwd=REPO, env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    killed_at = None
    try:
        deadline = time.time() + 300
        while time.time() < deadline and proc.poll() is None:
            if out.exists():
                try:
                    with h5py.File(out, "r") as f:
                        it = int(f.attrs["iterations"])
                except (OSError, KeyError):
                    it = 0
                if it >= 4:
                    proc.send_signal(signal.SIGKILL)
                    killed_at = it
                    break
            time.sleep(0.01)
    finally:
        if proc.poll() is None and killed_at is None:
            proc.kill()
        proc.wait()
    assert killed_at is not None, f"the fit ended before it could be killed: {proc.stderr.read().decode()}"
    assert proc.returncode == -signal.SIGKILL
    with h5py.File(out) as f:
        assert f.attrs["status"] == "running" and 4 <= f.attrs["iterations"] < 40

    assert cli.main(args + ["--resume"]) in (0, cli.EXIT_NOT_CONVERGED)
    ref = F.fit(jaxplush.load_scene(files["scene"]), files["target"], ("k_structural", "damping", "nmol"),
                optimizer="adam", iterations=40, identifiability=False, check_dt=False)
    with h5py.File(out) as f:
        assert f.attrs["status"] == ref.status and f.attrs["iterations"] == 40
        np.testing.assert_array_equal(f["history"]["loss"][()], ref.history["loss"])
        for n in ref.names:
            np.testing.assert_array_equal(f["params"][n][()], getattr(ref.params, n))


def test_a_fit_that_cannot_proceed_exits_3(files, tmp_path, capsys):
    """Gradient descent (Adam) cannot start from values whose rollout blows up: exit 3, nothing
    written. (The default fit substeps such a start instead: tests/test_fit_robust.py.)"""
    stiff = tmp_path / "stiff.obj"         # k = 3000 N/m: dt = 1 ms is far beyond the stability limit
    stiff.write_text(F.recovery_scene_text(1, k_structural=3000.0))
    out = tmp_path / "FIT.h5"
    assert cli.main([str(stiff), files["target"], "--optimizer", "adam", "--out", str(out), "--quiet"]) == 3
    err = capsys.readouterr().err
    assert "blows up" in err and "exceeds the estimated stability limit" in err and "Traceback" not in err
    assert not out.exists() and _leftovers(tmp_path) == []


def test_ctrl_c_exits_130_with_a_message(files, tmp_path, capsys, monkeypatch):
    def interrupted(*a, **k):
        raise KeyboardInterrupt
    monkeypatch.setattr(F, "fit", interrupted)
    out = tmp_path / "FIT.h5"
    assert cli.main([files["scene"], files["target"], "--out", str(out), "--quiet"]) == 130
    err = capsys.readouterr().err
    assert "interrupted" in err and "Traceback" not in err


def test_ctrl_c_before_the_first_checkpoint_does_not_claim_a_stale_file(files, tmp_path, capsys, monkeypatch):
    """An older FIT.h5 at --out is not "state saved" by a fit interrupted before it wrote anything."""
    def interrupted(*a, **k):
        raise KeyboardInterrupt
    monkeypatch.setattr(F, "fit", interrupted)
    out = tmp_path / "FIT.h5"
    out.write_bytes(b"an older fit")
    args = [files["scene"], files["target"], "--out", str(out), "--quiet"]
    assert cli.main(args) == 130
    err = capsys.readouterr().err
    assert "nothing written" in err and "state saved" not in err and "Traceback" not in err
    assert cli.main(args + ["--resume"]) == 130      # resuming: the checkpoint it resumes is still there
    assert "state saved to" in capsys.readouterr().err


def test_an_output_through_a_symlink_must_not_overwrite_an_input(files, tmp_path, capsys):
    link = tmp_path / "link.h5"
    os.symlink(files["target"], link)
    assert cli.main([files["scene"], files["target"], "--out", str(link), "--quiet"]) == 2
    assert "must not overwrite an input" in capsys.readouterr().err


def test_sweep_is_dispatched(monkeypatch):
    seen = []
    fake = types.ModuleType("jaxplush.fitting.sweep.cli")
    fake.main = lambda argv: seen.append(argv) or 7
    monkeypatch.setitem(sys.modules, "jaxplush.fitting.sweep.cli", fake)
    assert cli.main(["sweep", "scene.obj", "--steps", "3"]) == 7
    assert seen == [["scene.obj", "--steps", "3"]]
