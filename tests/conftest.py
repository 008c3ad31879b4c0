"""Shared test helpers: small icosphere scenes built in memory, a float64 switch, a compile
counter; and one persistent compilation cache for the whole run (every worker process, and the
command-line runs and notebooks the tests start, reuse each other's compiles)."""

from __future__ import annotations

import contextlib
import logging
import os
import sys
import tempfile

# `python -m pytest` puts the checkout's root on sys.path, where `fitting/` would import as a
# top-level package; drop it, so that imports resolve as for a user (the installed jaxplush and
# jaxplush.fitting) and a stray `import fitting` in a test, README block or docstring fails.
_ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path[:] = [p for p in sys.path if os.path.abspath(p or os.curdir) != _ROOT]

os.environ.setdefault("JAXPLUSH_CACHE_DIR", os.path.join(tempfile.gettempdir(), f"jaxplush-tests-xla-{os.getuid()}"))

import jaxplush  # noqa: I001  (first: it sets the options jax reads when imported)
import jax
import numpy as np
import pytest
import trimesh

#: Test files whose assertions rest on iterative float code (fits and their outcomes, gradients and
#: finite differences, stability limits and blow-ups, integrator agreement, batched against single
#: runs). They carry the marker ``numeric``; CI (.ci/run) runs them a second time under another
#: ``XLA_FLAGS=--xla_cpu_max_isa=...`` than the CPU's own, so that a test which holds only on one
#: CPU's rounding fails in CI rather than on a user's machine.
NUMERIC_FILES = frozenset({
    "test_fit.py", "test_fit_robust.py", "test_fit_cli.py", "test_gradients.py", "test_term_vjp.py",
    "test_terms.py", "test_integrators.py", "test_hard_cases.py", "test_physics.py", "test_step.py",
    "test_smooth_floor.py", "test_sweep.py", "test_targets.py", "test_batched_contact.py",
    "test_recovery_random.py", "test_predictability.py", "test_objects_stage.py", "test_tracks.py",
    "test_driven.py", "test_partial_targets.py", "test_mixed.py", "test_controls.py", "test_kfield.py",
    "test_user_grad.py", "test_kfield_fit.py", "test_equation_error.py", "test_intervals.py",
    "test_recovery_oracle.py",
})


#: Test files by what they cost in a cold run (seconds on 2 cores, empty compilation cache, measured
#: with ``--durations``), most first. The parallel run hands work out in this order, so the long
#: files start first and the two workers finish together instead of one waiting on a long file that
#: started last. A file goes to one worker whole (``--dist loadfile --no-loadscope-reorder``,
#: pyproject.toml), so its module fixtures and compiled programs are built once and
#: tests/test_docs.py runs its blocks in document order. (``--dist loadgroup`` with an
#: ``xdist_group`` mark per file does not group under pytest 9.2, which no longer lets pytest-xdist
#: 3.8 rename node ids.) A file not listed runs after these, in collection order; the list only
#: orders, it never selects.
COST_ORDER = (
    "test_user_grad.py", "test_kfield.py", "test_kfield_fit.py", "test_objects_stage.py",
    "test_partial_targets.py", "test_batched_contact.py", "test_docs.py", "test_driven.py", "test_shooting.py",
    "test_exact_jacobian.py", "test_contact.py", "test_fit_robust.py", "test_integrators.py", "test_physics.py",
    "test_gradients.py", "test_mixed.py", "test_fit.py", "test_sweep.py", "test_term_vjp.py",
    "test_recovery_random.py", "test_scale_out.py", "test_controls.py", "test_smooth_floor.py",
    "test_fit_cli.py", "test_tracks.py", "test_predictability.py", "test_targets.py",
)


@pytest.hookimpl(tryfirst=True)
def pytest_collection_modifyitems(config, items):
    for item in items:
        if item.path.name in NUMERIC_FILES:
            item.add_marker(pytest.mark.numeric)
    rank = {name: i for i, name in enumerate(COST_ORDER)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))     # stable: file order kept within


def load_benchmark(file, name):
    """A script of benchmarks/ (``file``) loaded as the module ``name``; sys.path is restored after
    it (a bench puts the checkout's root on it), so conftest's own order holds."""
    import importlib.util
    here = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "benchmarks", file)
    path = list(sys.path)
    try:
        spec = importlib.util.spec_from_file_location(name, here)
        mod = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(mod)
    finally:
        sys.path[:] = path
    return mod


def icosphere_text(subdivisions=1, radius=0.1, *, k=100.0, mass=0.05, nmol=None, dashpot=None, drag=None,
                   damping=None, gravity=(0.0, -9.81, 0.0), floor=None, translate=(0, 0, 0), fixed=(),
                   extra="", name="ball", offset=0, header=True):
    """Scene text of one icosphere object; ``offset`` shifts its global vertex indices and
    ``header=False`` leaves out the scene-level lines (to append a second object)."""
    m = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    out = [f"gravity {gravity[0]!r} {gravity[1]!r} {gravity[2]!r}"] if header else []
    if floor is not None and header:
        out.append(f"floor {floor!r}")
    out += [f"o {name}", f"k_structural {k!r}", f"total_weight {mass!r}"]
    for key, val in (("nmol", nmol), ("dashpot", dashpot), ("drag", drag), ("damping", damping)):
        if val is not None:
            out.append(f"{key} {val!r}")
    out.append("translate {} {} {}".format(*translate))
    out += [f"v {float(a)!r} {float(b)!r} {float(c)!r}" for a, b, c in m.vertices]
    out += [f"f {a + 1 + offset} {b + 1 + offset} {c + 1 + offset}" for a, b, c in m.faces]
    out += [f"fixed {i + 1 + offset}" for i in fixed]
    if extra:
        out.append(extra)
    out.append("END_OBJECT")
    return "\n".join(out) + "\n"


def icosphere_scene(**kw):
    return jaxplush.parse_scene(icosphere_text(**kw), "<test>")


@contextlib.contextmanager
def compiles():
    """Collect the names of the functions JAX traces or compiles inside the block."""
    seen = []

    class Catch(logging.Handler):
        def emit(self, record):
            msg = record.getMessage()
            if msg.startswith(("Compiling ", "Finished tracing")):
                seen.append(msg.split("\n")[0])

    handler, logger = Catch(level=logging.DEBUG), logging.getLogger("jax")
    old_level = logger.level
    logger.addHandler(handler)
    logger.setLevel(logging.DEBUG)
    try:
        with jax.log_compiles(True):
            yield seen
    finally:
        logger.removeHandler(handler)
        logger.setLevel(old_level)


@pytest.fixture
def ctrl_c():
    """Ctrl-C (SIGINT) raises KeyboardInterrupt in this test, as in an interactive Python, also
    in a parallel test worker (which is started with SIGINT ignored)."""
    import signal
    old = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, old)


def hanging_ball(**kw):
    """The 42-vertex hanging ball of the recovery scenes (values as keywords)."""
    from jaxplush.fitting.targets.recovery import recovery_scene_text
    return jaxplush.parse_scene(recovery_scene_text(1, **kw), "<hanging>")


@pytest.fixture(scope="session")
def hanging_case():
    """(truth, start, target) of the 42-vertex hanging ball: a noise-free target of 200 steps of
    1 ms every 20th saved, a start k x1.4 and nmol x0.8. Shared by the stage and polish tests,
    which then share their compiled programs."""
    from jaxplush.fitting.targets import make_target
    truth = hanging_ball()
    p = truth.params
    start = hanging_ball(k_structural=1.4 * p.k_structural[0], nmol=0.8 * p.nmol[0])
    return truth, start, make_target(truth, 200, 1e-3, 20)


@pytest.fixture
def x64():
    with jax.enable_x64(True):
        yield


def assert_gradient_matches_fd(f, x, grad, h=1e-5, ratio=10.0, rtol=1e-6, fd_rtol=None, directions=None):
    """Whole-vector gradient check (:func:`jaxplush.gradcheck.check_gradient`): the central
    differences at steps h and h/ratio must first agree with each other (else the function is
    rough at that scale: reported as such), then ``grad`` must match them to ``rtol`` of their
    norm. Returns the :class:`jaxplush.gradcheck.GradCheck`."""
    from jaxplush.gradcheck import check_gradient
    res = check_gradient(f, x, grad, h=h, ratio=ratio, rtol=rtol, fd_rtol=fd_rtol, directions=directions)
    assert res.converged, res.message()
    assert res.ok, res.message()
    return res
