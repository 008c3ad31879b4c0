"""How much of a run is compiling: a process-wide clock on JAX's own compile events.

JAX reports every step of turning a jitted function into a program to the listeners of
:mod:`jax.monitoring` (jax 0.10.2: ``jax/_src/dispatch.py``, ``jax/_src/interpreters/pxla.py``,
``jax/_src/compiler.py``):

* ``/jax/core/compile/jaxpr_trace_duration``: tracing a function to a jaxpr (the outermost trace
  only, so nested jits are not counted twice);
* ``/jax/core/compile/jaxpr_to_mlir_module_duration``: lowering the jaxpr to an MLIR module;
* ``/jax/core/compile/backend_compile_duration``: XLA building one executable, or loading it from
  the persistent compilation cache (:func:`jaxplush.stepping.compiled.enable_persistent_cache`):
  one event per program;
* ``/jax/compilation_cache/cache_hits`` (an event without a duration): the program was loaded
  from the persistent cache instead of compiled.

:func:`totals` adds them up for the whole process since the listeners were registered (once, on
first use, thread-safely); a :class:`CompileClock` (``with compile_clock() as c: ...``) is the
difference across a block, with the block's wall time: ``c.compile_s`` (XLA compiles and cache
loads, s), ``c.trace_s`` (tracing and lowering, s), ``c.programs`` (executables built or
loaded: the distinct programs the block compiled), ``c.cache_hits`` (how many of those came from
the persistent cache) and ``c.wall_s``. Clocks nest and may run at once in several threads: each
keeps only its own start. The counts are process-wide, so a clock also sees what other threads
compile during its block (two programs compiling at the same time in two threads can then make
``compile_s`` exceed ``wall_s``); a run that compiles only in its own thread, as a fit does, sees
its own. A compile that was already under way when a clock started counts whole if it ends inside
the block.

This module imports no JAX until a clock is used.
"""

from __future__ import annotations

import dataclasses
import threading
import time

BACKEND_COMPILE = "/jax/core/compile/backend_compile_duration"
TRACE = "/jax/core/compile/jaxpr_trace_duration"
LOWER = "/jax/core/compile/jaxpr_to_mlir_module_duration"
CACHE_HIT = "/jax/compilation_cache/cache_hits"

_lock = threading.Lock()
# compile_s, trace_s, programs, cache_hits since the listeners were registered
_totals = [0.0, 0.0, 0, 0]
_registered = False


def _on_duration(event, duration, **_):
    if event == BACKEND_COMPILE:
        with _lock:
            _totals[0] += float(duration)
            _totals[2] += 1
    elif event == TRACE or event == LOWER:
        with _lock:
            _totals[1] += float(duration)


def _on_event(event, **_):
    if event == CACHE_HIT:
        with _lock:
            _totals[3] += 1


def install():
    """Register the listeners with :mod:`jax.monitoring` (once per process; later calls do
    nothing). Compiles before this are not counted. Returns True when they are registered."""
    global _registered
    if _registered:
        return True
    with _lock:
        if not _registered:
            from jax import monitoring
            monitoring.register_event_duration_secs_listener(_on_duration)
            monitoring.register_event_listener(_on_event)
            _registered = True
    return True


@dataclasses.dataclass(frozen=True)
class Timing:
    """Where a run's time went: ``wall_s`` (s, the whole run), ``compile_s`` (s in XLA compiles,
    loads from the persistent cache included), ``trace_s`` (s tracing and lowering to MLIR),
    ``programs`` (executables compiled or loaded) and ``cache_hits`` (how many of those were
    loaded from the persistent cache)."""

    wall_s: float = 0.0
    compile_s: float = 0.0
    trace_s: float = 0.0
    programs: int = 0
    cache_hits: int = 0

    @property
    def rest_s(self):
        """The wall time that was neither compiling nor tracing (simulation and the rest), s."""
        return max(self.wall_s - self.compile_s - self.trace_s, 0.0)

    def parts(self):
        """The breakdown in words, e.g. "XLA compiles 12.3 s (17 programs, 5 from the persistent
        cache), tracing 1.1 s; simulation and the rest 28.7 s"."""
        cached = f", {self.cache_hits} from the persistent cache" if self.cache_hits else ""
        return (f"XLA compiles {self.compile_s:.1f} s ({self.programs} program{'' if self.programs == 1 else 's'}"
                f"{cached}), tracing {self.trace_s:.1f} s; simulation and the rest {self.rest_s:.1f} s")

    def text(self):
        """The wall time and its breakdown, e.g. "42.1 s: XLA compiles 12.3 s (17 programs), ..."."""
        return f"{self.wall_s:.1f} s: {self.parts()}"

    def as_dict(self):
        return dataclasses.asdict(self)


def totals():
    """The process's :class:`Timing` since the listeners were registered (``wall_s`` 0); registers
    them on first use."""
    install()
    with _lock:
        c, t, p, h = _totals
    return Timing(0.0, c, t, p, h)


class CompileClock:
    """The compiles of a block of code and its wall time, from its creation (or ``with``) until
    :meth:`stop` (or the end of the ``with`` block); read live before that. Attributes as
    :class:`Timing`'s (``wall_s``, ``compile_s``, ``trace_s``, ``programs``, ``cache_hits``)."""

    def __init__(self):
        self._stopped = None
        self._start()

    def _start(self):
        self._c0 = totals()
        self._t0 = time.perf_counter()

    def __enter__(self):
        if self._stopped is None:
            self._start()            # a clock made for a ``with`` block starts with the block
        return self

    def __exit__(self, *exc):
        self.stop()
        return False

    def timing(self):
        """The :class:`Timing` so far (or up to :meth:`stop`)."""
        if self._stopped is not None:
            return self._stopped
        now = totals()
        return Timing(wall_s=time.perf_counter() - self._t0, compile_s=now.compile_s - self._c0.compile_s,
                      trace_s=now.trace_s - self._c0.trace_s, programs=now.programs - self._c0.programs,
                      cache_hits=now.cache_hits - self._c0.cache_hits)

    def stop(self):
        """Freeze the clock; returns its :class:`Timing`."""
        if self._stopped is None:
            self._stopped = self.timing()
        return self._stopped

    def __getattr__(self, name):
        # wall_s, compile_s, trace_s, programs, cache_hits: read off the Timing so far
        if name in Timing.__dataclass_fields__:
            return getattr(self.timing(), name)
        raise AttributeError(name)


def compile_clock():
    """A started :class:`CompileClock`: ``with compile_clock() as c: ...``, then ``c.compile_s``,
    ``c.programs``, ...; or ``c = compile_clock()`` and ``c.timing()`` whenever wanted."""
    return CompileClock()
