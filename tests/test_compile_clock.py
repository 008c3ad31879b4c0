"""jaxplush.compilestats: the process-wide clock on JAX's compile events (what a fit reports as
its compile time apart from the rest, and FIT.h5 keeps in ``timing/``)."""

from __future__ import annotations

import io
import threading

import jax
import jax.numpy as jnp
import pytest

from jaxplush import compilestats
from jaxplush.compilestats import Timing, compile_clock
from jaxplush.progress import Progress


def _fresh():
    """A jitted function no one has called yet (a new function object: JAX traces, lowers and
    compiles it, or loads its program from the persistent cache, on its first call)."""
    def f(x):
        return jnp.sin(x) * 3.0 + jnp.cumsum(x)
    return jax.jit(f)


def test_a_fresh_function_is_one_program_and_a_second_call_none():
    x = jnp.arange(7.0)
    f = _fresh()
    with compile_clock() as first:
        f(x).block_until_ready()
    t = first.timing()
    assert t.programs >= 1 and t.compile_s > 0.0 and t.trace_s > 0.0
    assert t.compile_s + t.trace_s <= t.wall_s
    assert 0.0 <= t.rest_s <= t.wall_s
    with compile_clock() as again:
        f(x).block_until_ready()
    assert again.programs == 0 and again.compile_s == 0.0 and again.cache_hits == 0
    # stopped clocks keep their reading
    assert first.timing() == t and first.stop() == t


def test_clocks_nest_and_a_live_clock_reads_as_it_goes():
    x = jnp.arange(5.0)
    outer = compile_clock()
    with compile_clock() as inner:
        _fresh()(x).block_until_ready()
    mid = outer.timing()                      # read live, the clock still running
    _fresh()(x + 1).block_until_ready()
    end = outer.stop()
    assert inner.programs >= 1
    assert mid.programs >= inner.programs and end.programs >= mid.programs + 1
    assert end.compile_s >= inner.compile_s and end.wall_s >= mid.wall_s >= inner.wall_s


def test_a_program_from_the_persistent_cache_counts_as_a_hit():
    """Two function objects with the same body lower to the same program: the second is loaded
    from the persistent compilation cache (on in the test suite: JAXPLUSH_CACHE_DIR)."""
    if not jax.config.jax_compilation_cache_dir:
        pytest.skip("the persistent compilation cache is off")
    x = jnp.arange(9.0)
    _fresh()(x).block_until_ready()           # compiled and written (or already there)
    with compile_clock() as c:
        _fresh()(x).block_until_ready()
    assert c.programs == 1 and c.cache_hits == 1


def test_counts_from_many_threads_add_up():
    """The listeners are called in whatever thread compiles: no count is lost."""
    compilestats.install()
    before = compilestats.totals()
    n_threads, n_events = 8, 500

    def record():
        for _ in range(n_events):
            jax.monitoring.record_event_duration_secs(compilestats.BACKEND_COMPILE, 0.5)
            jax.monitoring.record_event(compilestats.CACHE_HIT)

    with compile_clock() as c:
        threads = [threading.Thread(target=record) for _ in range(n_threads)]
        for th in threads:
            th.start()
        for th in threads:
            th.join()
    assert c.programs == c.cache_hits == n_threads * n_events
    assert c.compile_s == pytest.approx(0.5 * n_threads * n_events)
    after = compilestats.totals()
    assert after.programs - before.programs == n_threads * n_events


def test_timing_in_words():
    t = Timing(wall_s=10.0, compile_s=6.0, trace_s=1.0, programs=3, cache_hits=1)
    assert t.rest_s == pytest.approx(3.0)
    assert t.text() == ("10.0 s: XLA compiles 6.0 s (3 programs, 1 from the persistent cache), tracing 1.0 s; "
                        "simulation and the rest 3.0 s")
    assert Timing(wall_s=1.0, compile_s=2.0).rest_s == 0.0      # concurrent compiles: never negative
    assert t.as_dict() == dict(wall_s=10.0, compile_s=6.0, trace_s=1.0, programs=3, cache_hits=1)


def test_a_progress_bar_tells_its_compiles_apart():
    buf = io.StringIO()
    x = jnp.arange(3.0)
    with Progress(1, "stage", stream=buf, unit="it", interactive=False, compiles=True) as bar:
        _fresh()(x).block_until_ready()
        bar.update(1)
    last = buf.getvalue().splitlines()[-1]
    assert "XLA compiles" in last and "program" in last
    buf = io.StringIO()
    with Progress(1, "stage", stream=buf, unit="it", interactive=False, compiles=True) as bar:
        bar.update(1)
    assert buf.getvalue().splitlines()[-1].endswith("no XLA compiles")


def test_a_fits_data_movement_compiles_nothing():
    """Issue 52 (few programs per fit): what moves data between a fit's programs (a batch cut into
    chunks and joined, lane cuts, fresh health records, dtype conversions of targets and
    parameters, a positions target's rest distance) runs on the host. Before, each was a one-op
    program per shape: 40 of a two-ball fit's 52. Three 12-vertex balls (a vertex count no other
    test uses, so these shapes are new to the process and any such program would compile here)."""
    import warnings
    import jaxplush
    from jaxplush.fitting import fitter as F
    from jaxplush.fitting.targets import make_target
    from conftest import compiles, icosphere_text

    def scene(k):
        text = "contact off\n" + "".join(
            icosphere_text(subdivisions=0, k=k * (1 + 0.3 * i), damping=400.0, name=f"b{i}", offset=12 * i,
                           header=i == 0, translate=(0.3 * i, 0.0, 0.0)) for i in range(3))
        return jaxplush.parse_scene(text, "<three>")
    target = make_target(scene(80.0), 40, 1e-3, 10)
    with compiles() as seen, warnings.catch_warnings():
        warnings.simplefilter("ignore")
        F.fit(scene(50.0), target, ("k_structural",), noise_free=True, identifiability=False, predictability=False,
              samples=6, starts=1, iterations=2)
    names = {s.split(" ")[1].split("(")[-1].rstrip(")") for s in seen if s.startswith("Compiling ")}
    host_side = {"_split", "_join", "broadcast_in_dim", "dynamic_slice", "convert_element_type", "squared_distance",
                 "_mean", "slice", "concatenate"}
    assert names and not names & host_side, sorted(names)


def test_a_once_per_call_program_compiles_with_its_options_or_falls_back():
    """``compiled.jit_once``: the same values as a plain jit; an error of the call itself is
    raised as a plain jit raises it and does not turn the options off for later programs."""
    import numpy as np
    from jaxplush.stepping import compiled
    f = compiled.jit_once(lambda a, b: jnp.sin(a) * b + 1.0)
    a = np.linspace(0.0, 1.0, 7, dtype=np.float32)
    np.testing.assert_allclose(np.asarray(f(a, 2.0)), np.sin(a) * 2.0 + 1.0, rtol=1e-6)
    # inside another trace (JAX takes compiler options on the outermost jit only): the plain jit
    np.testing.assert_allclose(np.asarray(jax.jit(lambda b: f(b, 2.0))(a)), np.sin(a) * 2.0 + 1.0, rtol=1e-6)
    np.testing.assert_allclose(np.asarray(jax.vmap(lambda b: f(b, 2.0))(a)), np.sin(a) * 2.0 + 1.0, rtol=1e-6)
    refused = list(compiled._ONCE_REFUSED)
    g = compiled.jit_once(lambda a: a @ a)
    with pytest.raises(TypeError):
        g(np.ones((2, 3), np.float32))                 # a shape error of the call
    assert compiled._ONCE_REFUSED == refused
