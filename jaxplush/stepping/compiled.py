"""Compiled functions, cached per program: compile once, run many.

A :class:`jaxplush.stepping.step.Simulator` compares equal to another exactly when both would compile to
the same program: the same geometry and topology, terms, dt, integrator, substeps, dtype and
step options (``Simulator.key``). Scene values (k, damping, nmol, ...) and initial states are
never part of the key: they are traced inputs. :func:`get` keeps the jitted functions of the
last :data:`SIZE` simulators used (least recently used first out), so rebuilding a simulator for
the same scene, as :func:`jaxplush.simulate` does on every call, reuses the compiled rollout,
and a loop over many different scenes keeps at most :data:`SIZE` programs alive.

Across processes, :func:`enable_persistent_cache` points JAX's persistent compilation cache at
a user cache directory: the command-line tools do this on start, and ``import jaxplush`` does
it when ``JAXPLUSH_CACHE_DIR`` is set (the test suite sets it, so its worker processes, the
command-line runs and the notebooks it starts share their compiles).

Environment:
  ``JAXPLUSH_COMPILED_SIMULATORS``: how many simulators keep their compiled functions (default 16).
  ``JAXPLUSH_CACHE_DIR``: the persistent cache's directory (default
  ``$XDG_CACHE_HOME/jaxplush/xla``, else ``~/.cache/jaxplush/xla``); ``off`` (or ``0``) turns
  it off.
"""

from __future__ import annotations

import collections
import dataclasses
import os

import numpy as np

SIZE = max(1, int(os.environ.get("JAXPLUSH_COMPILED_SIMULATORS", "16") or 16))

_CACHE: "collections.OrderedDict" = collections.OrderedDict()


def get(sim, name, build):
    """The function ``name`` of ``sim``'s program, built by ``build()`` on first use.

    ``build`` must return a function that depends on ``sim`` only through what ``sim.key``
    covers (its closures, not its scene's values)."""
    entry = _CACHE.get(sim)
    if entry is None:
        entry = _CACHE[sim] = {}
        while len(_CACHE) > SIZE:
            _CACHE.popitem(last=False)
    else:
        _CACHE.move_to_end(sim)
    fn = entry.get(name)
    if fn is None:
        fn = entry[name] = build()
    return fn


#: XLA options of programs that run once per call (the batched engine's init, a stability
#: estimate): the backend's optimisation level 0 compiles them in about half the time, and they
#: run a few milliseconds longer, once (benchmarks/RESULTS.md, "A fit's float32 twins on the batched
#: engine").
ONCE_COMPILER_OPTIONS = {"xla_backend_optimization_level": 0}
_ONCE_REFUSED = []


def jit_once(fn, **kw):
    """``jax.jit(fn, **kw)`` for a function that runs once per call (an init, an estimate), with
    :data:`ONCE_COMPILER_OPTIONS` on XLA:CPU. Where the installed jax or XLA refuses them (found at
    the first call, no probe compile at start-up), it is a plain jit from then on; called inside
    another trace (a user's jit, vmap or grad), it is the plain jit (JAX takes compiler options
    on the outermost jit only)."""
    import jax
    plain = jax.jit(fn, **kw)
    if _ONCE_REFUSED or jax.default_backend() != "cpu":
        return plain
    try:
        tuned = jax.jit(fn, compiler_options=dict(ONCE_COMPILER_OPTIONS), **kw)
    except TypeError:                               # a jax without compiler_options
        _ONCE_REFUSED.append(True)
        return plain
    state = []

    def call(*args, **kwargs):
        if not _top_level():
            return plain(*args, **kwargs)       # inside a trace: options belong to the outer jit
        if state:
            return state[0](*args, **kwargs)
        try:
            out = tuned(*args, **kwargs)
        except Exception:
            # refused options, or an error of the call itself, which the plain jit raises again
            # (and then nothing is marked refused)
            out = plain(*args, **kwargs)
            _ONCE_REFUSED.append(True)
            state.append(plain)
            return out
        state.append(tuned)
        return out
    return call


_REGISTERED = []


def register(cache):
    """``cache`` (a dict of compiled things kept for reuse elsewhere, such as the batched
    simulators of :func:`jaxplush.stepping.batched.shared_simulator`), emptied by :func:`clear` too."""
    _REGISTERED.append(cache)
    return cache


def _top_level():
    """True outside any JAX trace (jit, vmap, grad, ...): only there may a jit carry compiler options."""
    try:
        from jax._src import core
        return bool(core.trace_state_clean())
    except Exception:                               # a jax without it: never nest options
        return False


def clear():
    """Drop every cached compiled function (their executables are freed with them)."""
    _CACHE.clear()
    _TOPOLOGY.clear()
    for cache in _REGISTERED:
        cache.clear()


_TOPOLOGY: "collections.OrderedDict" = collections.OrderedDict()


def topology(scene):
    """``jaxplush.model.forces.build_topology(scene)``, shared by scenes of equal
    :attr:`jaxplush.scene.parse.Scene.fingerprint` at one precision (the last :data:`SIZE`), so a rebuilt
    simulator does not redo the ring tables, nor the stability bound its rest geometry."""
    import jax.numpy as jnp
    from jaxplush.model import forces as model
    # per precision too: JAX caches the conversion of a closed-over numpy constant, so one
    # topology's arrays must not be traced in both float32 and float64 (the second would get
    # the first's dtype)
    key = (scene.fingerprint, jnp.dtype(jnp.result_type(float)).str)
    topo = _TOPOLOGY.get(key)
    if topo is None:
        topo = _TOPOLOGY[key] = model.build_topology(scene)
        while len(_TOPOLOGY) > SIZE:
            _TOPOLOGY.popitem(last=False)
    else:
        _TOPOLOGY.move_to_end(key)
    return topo


@dataclasses.dataclass(frozen=True)
class Bucket:
    """The sizes that decide a scene's compiled programs (topology as data).

    A program takes the scene's topology (ring tables, edges, faces, rest lengths and volumes,
    contact tables, pins) and the values derived from its geometry (softening length, contact
    margins, valences) as arguments (:func:`jaxplush._xla.hoist_constants`), so what it is
    compiled for is only their sizes: two scenes with equal buckets, equal switched-on terms and
    equal step options (dt, substeps, integrator, batch width, dtype) lower to the same program,
    and the second loads it from the persistent compilation cache.

    Attributes:
      objects: per object (vertices, edges, faces, pinned vertices).
      ring_width: slots of the one-ring tables (the largest valence; rings of smaller valence are
        padded by repeating their last neighbour).
      valence: the smallest valence: every slot below it is real at every vertex, which the
        batched kernel uses to skip masking those slots.
      near_faces: with soft-soft contact, the width of the reference energy's near-face table.
      capacity: with soft-soft contact, the candidate capacity of each object.
      walk_width: with soft-soft contact between objects, the slots of the carried lists' walk
        table (:func:`jaxplush.model.contact.two_ring_width`: 19 for any mesh of valence at most 6).
      softening: the exponent of the edge-length softening eps = 2**softening m
        (:func:`jaxplush.model.forces.softening_length`: 1e-6 of the shortest rest edge, to the
        nearest power of two), a constant of the programs.
    """

    objects: tuple
    ring_width: int
    valence: int
    softening: int = 0
    near_faces: int | None = None
    capacity: tuple | None = None
    walk_width: int | None = None

    def text(self):
        """One line for ``jaxplush info``."""
        sizes = collections.Counter(self.objects)
        parts = []
        for (v, e, f, p), n in sizes.items():
            pins = f", {p} pinned" if p else ""
            parts.append(f"{n} x ({v} vertices, {e} edges, {f} faces{pins})")
        out = (f"{' + '.join(parts)}; ring width {self.ring_width} (valence {self.valence}-{self.ring_width}); "
               f"softening 2^{self.softening} m")
        if self.capacity is not None:
            out += f"; contact capacity {'/'.join(str(c) for c in self.capacity)}, near faces {self.near_faces}"
            if self.walk_width is not None:
                out += f", walk width {self.walk_width}"
        return out


def bucket(scene, terms=None):
    """The :class:`Bucket` of ``scene`` (with soft-soft contact as ``terms``, default the scene's)."""
    from jaxplush.model import contact as _contact
    from jaxplush.model import forces as model
    topo = topology(scene)
    terms = model.Terms.for_scene(scene) if terms is None else terms
    fixed = np.asarray(topo.fixed)
    objects = tuple((int(b - a), int(eb - ea), int(fb - fa), int(((fixed >= a) & (fixed < b)).sum()))
                    for (a, b), (ea, eb), (fa, fb) in zip(topo.vertex_slices, topo.edge_slices, topo.face_slices))
    valence = topo.ring_mask.sum(axis=1)
    near, capacity, walk = None, None, None
    if terms.contact:
        near = int(_contact._tables(topo, terms.contact).near_faces.shape[1])
        capacity = tuple(int(c) for c in terms.contact.capacity)
        if terms.contact.pairs:
            walk = _contact.two_ring_width(topo.ring)
    return Bucket(objects=objects, ring_width=int(topo.ring.shape[1]), valence=int(valence.min()),
                  softening=int(np.round(np.log2(topo.length_eps))), near_faces=near, capacity=capacity,
                  walk_width=walk)


def size():
    """Simulators whose compiled functions are cached now."""
    return len(_CACHE)


def default_cache_dir():
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return os.path.join(base, "jaxplush", "xla")


def enable_persistent_cache(path=None):
    """Turn on JAX's persistent compilation cache in ``path`` (default ``JAXPLUSH_CACHE_DIR``, else
    :func:`default_cache_dir`), so a second process reuses the first one's compiled programs.
    Returns the directory, or None when ``JAXPLUSH_CACHE_DIR`` is ``off``/``0`` or the directory
    cannot be created (the run then compiles as usual)."""
    import jax
    path = path or os.environ.get("JAXPLUSH_CACHE_DIR") or default_cache_dir()
    if path.strip().lower() in ("off", "0", "none", "false"):
        return None
    try:
        os.makedirs(path, exist_ok=True)
    except OSError:
        return None
    jax.config.update("jax_compilation_cache_dir", path)
    # every compile counts toward a quick start, and the small ones are the many
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    return path
