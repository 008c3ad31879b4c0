"""Warnings, errors, statuses and target kinds as types: every warning jaxplush issues has a
category a caller can filter on, a fit's notes keep theirs (through a checkpoint too), an error
that is added to is rebuilt from its fields, not its text, and no status or target kind is
compared by its name outside the module that defines it."""

from __future__ import annotations

import ast
import pathlib
import warnings

import h5py
import numpy as np
import pytest

import jaxplush
import jaxplush.fitting
from jaxplush import errors
from jaxplush.fitting import errors as fit_errors
from conftest import icosphere_scene

ROOTS = (pathlib.Path(jaxplush.__path__[0]), pathlib.Path(jaxplush.fitting.__path__[0]))
STATUS_VALUES = ("converged", "poor_fit", "stalled", "iteration_limit", "at_bound", "at_floor", "undetermined")


def _sources():
    seen = set()
    for root in ROOTS:
        for path in sorted(root.rglob("*.py")):
            if path.resolve() not in seen:
                seen.add(path.resolve())
                yield path


def _warn_calls(tree):
    for node in ast.walk(tree):
        if (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr == "warn"
                and isinstance(node.func.value, ast.Name) and node.func.value.id == "warnings"):
            yield node


def test_every_warning_the_package_issues_names_a_jaxplush_category():
    checked = 0
    for path in _sources():
        tree = ast.parse(path.read_text())
        for call in _warn_calls(tree):
            cat = call.args[1] if len(call.args) > 1 else next(
                (k.value for k in call.keywords if k.arg == "category"), None)
            where = f"{path.name}:{call.lineno}"
            assert cat is not None, f"{where}: warnings.warn without a category"
            if isinstance(cat, ast.Name) and cat.id == "category" and path.name == "errors.py":
                pass                # jaxplush.errors.warn: its caller names the category (checked below)
            elif isinstance(cat, ast.Name):
                cls = getattr(errors, cat.id, None) or getattr(fit_errors, cat.id, None)
                assert cls is not None and issubclass(cls, errors.JaxplushWarning), f"{where}: {cat.id}"
            else:       # re-issued with the category it was caught with (w.category) or a parameter's
                assert isinstance(cat, ast.Attribute) and cat.attr == "category", where
            checked += 1
        for call in ast.walk(tree):       # calls of jaxplush.errors.warn(text, category, ...)
            if (isinstance(call, ast.Call) and isinstance(call.func, ast.Name) and call.func.id == "warn"
                    and path.name != "errors.py"):
                cat = call.args[1]
                assert isinstance(cat, ast.Name) and issubclass(getattr(errors, cat.id), errors.JaxplushWarning)
                checked += 1
    assert checked >= 15        # the scan sees the package's warnings (not an empty walk)


def test_no_status_string_is_compared_outside_the_outcome_module():
    for path in _sources():
        if path.name == "outcome.py":
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Compare):
                for side in [node.left] + list(node.comparators):
                    consts = side.elts if isinstance(side, (ast.Tuple, ast.List, ast.Set)) else [side]
                    for c in consts:
                        assert not (isinstance(c, ast.Constant) and c.value in STATUS_VALUES), (
                            f"{path.name}:{node.lineno}: compares with the status string {c.value!r}; "
                            "use jaxplush.fitting.judge.outcome.Status")


KIND_VALUES = ("positions", "points", "tracks", "mixed")


def test_no_target_kind_string_is_compared_outside_the_kinds_module():
    """The kinds of target are one protocol (jaxplush.fitting.targets.kinds.TargetKind): code asks a kind
    what it is instead of comparing its name."""
    found = []
    for path in _sources():
        if path.name == "kinds.py":
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if not isinstance(node, ast.Compare):
                continue
            # a kind against a name (==, !=), or a kind in a tuple of names; not a name looked up
            # in a file or a dict ("positions" in f: a dataset of that name)
            sides = [node.left] + list(node.comparators)
            if any(isinstance(op, (ast.In, ast.NotIn)) for op in node.ops):
                sides = node.comparators
            for side in sides:
                consts = side.elts if isinstance(side, (ast.Tuple, ast.List, ast.Set)) else [side]
                if any(isinstance(op, (ast.In, ast.NotIn)) for op in node.ops) and consts == [side]:
                    continue
                found += [f"{path.name}:{node.lineno}: {c.value!r}" for c in consts
                          if isinstance(c, ast.Constant) and c.value in KIND_VALUES]
    assert not found, "target kind names compared (ask jaxplush.fitting.targets.kinds.TargetKind):\n" + "\n".join(found)


def test_a_time_step_above_the_limit_warns_by_category_and_the_trajectory_keeps_the_note():
    scene = icosphere_scene(subdivisions=1, k=5000.0, nmol=1e-3)
    with pytest.warns(errors.TimeStepWarning, match="stability limit") as rec:
        traj = jaxplush.simulate(scene, 2, 6e-4, 2)
    assert all(issubclass(w.category, errors.JaxplushWarning) for w in rec)
    assert any("stability limit" in n for n in traj.warnings)
    # a caller silences that category and no other
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        warnings.filterwarnings("ignore", category=errors.TimeStepWarning)
        jaxplush.simulate(scene, 2, 6e-4, 2)
    assert not [w for w in caught if issubclass(w.category, errors.TimeStepWarning)]


def test_a_scene_with_unused_vertices_warns_a_scene_warning(tmp_path):
    p = tmp_path / "s.obj"
    p.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nv 5 5 5\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n")
    with pytest.warns(errors.SceneWarning, match="not used by any face"):
        jaxplush.load_scene(p)


def test_a_notes_category_survives_pickling_and_a_checkpoint(tmp_path):
    import copy
    import pickle
    from jaxplush.fitting.io.treeio import read_tree, write_tree
    note = errors.Note("contact candidates overflowed", errors.ContactCapacityWarning)
    assert note == "contact candidates overflowed" and isinstance(note, str)
    for back in (pickle.loads(pickle.dumps(note)), copy.deepcopy(note)):
        assert back == note and back.category is errors.ContactCapacityWarning
    with h5py.File(tmp_path / "t.h5", "w") as f:
        write_tree(f.create_group("g"), {"notes": [note, "plain"]})
    with h5py.File(tmp_path / "t.h5") as f:
        back = read_tree(f["g"])["notes"]
    assert back == [note, "plain"] and back[0].category is errors.ContactCapacityWarning
    assert type(back[1]) is str
    with pytest.warns(errors.ContactCapacityWarning):
        made = errors.warn("grew", errors.ContactCapacityWarning)
    assert made.category is errors.ContactCapacityWarning


def test_the_damping_drag_note_of_a_fit_is_a_parameter_warning():
    from jaxplush.fitting.objective.problem import build_problem
    from jaxplush.fitting.targets import make_target
    scene = icosphere_scene(subdivisions=1, nmol=1e-3, damping=200.0, drag=0.5)
    target = make_target(scene, 20, 1e-3, 10)
    with pytest.warns(jaxplush.fitting.ParameterWarning, match="drag"):
        build_problem(scene, target, ["k", "damping", "drag"], None)


def test_the_predictability_measurement_adds_to_an_errors_hint_from_its_field():
    from jaxplush.stepping.predictability import _which
    e = jaxplush.SimulationError(12, 1, "ball", "non-finite positions", hint="try a smaller dt")
    assert e.hint == "try a smaller dt"
    out = _which(e, "float64")
    assert (out.step, out.object, out.object_name, out.reason) == (12, 1, "ball", "non-finite positions")
    assert out.hint.startswith("try a smaller dt (") and "float64 run" in out.hint
    assert str(out).endswith(out.hint)
    bare = _which(jaxplush.SimulationError(3, 0, "b", "r"), "float32")
    assert bare.hint.startswith("in the float32 run")
    np.testing.assert_equal(bare.step, 3)
