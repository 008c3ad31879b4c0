"""Batched simulation: B parameter points of one scene advanced together, batch on the last axis.

``make_batched_simulator(scene, dt, batch)`` builds the same physics as
:func:`jaxplush.make_simulator` (springs, edge dashpot, air drag, gas, gravity, the floor and its
optional friction/restitution, pinned and driven vertices, the report's Verlet damping, several
objects, soft-soft contact with its friction and self-collision; only the terms the scene or the
parameter batch needs are traced) for a static batch of B
parameter points. It exists for throughput: a plain ``jax.vmap`` of the single-scene step puts
the batch on the leading axis, so every one-ring gather moves single floats B times over, and
batching then gains little over one scene at a time. Here every array carries the batch on
its *last* axis:

* positions and velocities are component-major, batch-last: a tuple ``(x, y, z)`` of three
  (V, B) arrays (the public layout is (B, V, 3));
* parameters are a :class:`jaxplush.types.Params` of (O, B) arrays (the spring stiffness of a
  scene with a per-edge field, ``terms.k_field``: an (E, B) field per point);
* the one-ring gather is one row gather over the flattened (K V,) neighbour table from the
  three components side by side, each row 3 B contiguous floats, and every force term is
  elementwise on (V, B) arrays, which XLA's CPU backend vectorises along B (benchmarks/RESULTS.md,
  "Batch sweeps").

:func:`rollout` runs a batch as independent chunks of ``bsim.chunk`` points (16 at B = 64,
:func:`default_chunk`), one compiled call each, dispatched concurrently from a thread pool, one
thread per CPU core: a 16-point step keeps its working set in a core's L2 cache, and the chunks
use every core, where one call on the whole batch keeps about one core busy (its XLA
operations mostly wait on each other). The rollout is compiled with two XLA:CPU options of its
own (:data:`ROLLOUT_COMPILER_OPTIONS`), and carries the positions folded to rows of at least 48
floats (:func:`_folded`: at 16 points a row, XLA:CPU leaves the small in-place position update
scalar; folded, it vectorises it; see benchmarks/RESULTS.md). Points are independent, so
chunking changes the results only by rounding (chunks of another width vectorise differently).

All of that is CPU tuning (:func:`on_cpu`): on a GPU a batch runs in one call with XLA's default
options. With several local devices (GPUs, or forced host devices) :func:`rollout` runs the
chunks one per device instead, through ``jax.shard_map`` over a "batch" mesh axis
(:func:`_sharded`): every device runs the one-chunk program, so results are bit-identical to
one device (tests/test_scale_out.py).

Soft-soft contact is the one term not written out on (V, B) slots: its candidate lists and
closest-face search are per scene, so the single-scene functions of :mod:`jaxplush.model.contact`
run ``jax.vmap``-ed over the points (:func:`_make_contact`), on each point's positions
transposed to the single-scene (3, V) layout and back (the transposes cost little next to the
contact term itself; benchmarks/RESULTS.md, "Batched contact"). The rollout carries every
point's candidate lists (:class:`BatchedCoherent`), rebuilt per point where the single scene
rebuilds them, so a batched point follows ``jaxplush.simulate`` to rounding.

Only the Verlet integrator is batched. A scene whose :class:`jaxplush.model.forces.Terms` selects
something this module does not implement (a Terms field added later) raises
``NotImplementedError`` before anything is traced.

Health is tracked per batch point and object exactly as in :mod:`jaxplush.stepping.rollouts`: the
rollout carries (O, B) status codes, the step at which each failure was seen and the last
healthy state of every point; :func:`locate_failures` then finds the exact failing step of each
failed point. One point blowing up never touches the others (nothing is reduced across B). A
point whose contact candidates overflow their capacity gets the code ``CONTACT_OVERFLOW`` for
that object at the next saved frame (its cache's sticky flag), as in a single-scene rollout;
:class:`jaxplush.fitting.objective.evaluate.Evaluator` then grows the capacity and runs it again, and a
sweep reports it per point.
"""

from __future__ import annotations

import collections
import dataclasses
import functools
import os
import threading
from concurrent.futures import ThreadPoolExecutor
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxplush.stepping import compiled
from jaxplush.stepping import constraints
from jaxplush.stepping import diagnostics
from jaxplush.stepping import integrators
from jaxplush.stepping.rollouts import Health, _traced
from jaxplush.model import contact as _contact
from jaxplush.model import forces as model
from jaxplush.model import terms as T
from jaxplush.model.layout import per_vertex, vertex_mass
from jaxplush.types import Params, State

#: Terms this module implements (:data:`jaxplush.model.terms.REGISTRY`, ``batched``). Any other
#: term switched on raises ``NotImplementedError`` (a term added to the single-scene step later
#: must not be silently dropped here).
SUPPORTED_TERMS = T.supported("batched")

#: Points per compiled rollout call of a larger batch (:func:`default_chunk`).
MAX_CHUNK = 16


@dataclasses.dataclass(frozen=True, eq=False)
class BatchedSimulator:
    """A simulator for B parameter points of one scene (see the module docstring for layouts).

    Attributes:
      init_fn: (params, x0=None, v0=None, step0=0) -> internal State; params leaves (O, B); x0, v0
        (V, 3) shared or (B, V, 3) per point; defaults: rest positions, zero velocity. ``step0``
        (scalar or (B,)): the step index of the start, read only by driven vertices, which are put
        where their path has them then (at step 0 as ``jaxplush.make_simulator``'s init).
      step_fn: (params, state, step=None) -> state, one time step of every point (internal
        layout); ``step``: the (B,) (or scalar) index of the step each point advances, required
        with driven vertices (their paths depend on time, and each lane may be at its own step:
        the segments of multiple shooting), ignored otherwise.
      status_fn: (params, x) -> (O, B) int32 health codes (:mod:`jaxplush.stepping.diagnostics`).
      force_fn: (params, x, v) -> (f, volume): internal forces (tuple of 3 (V, B)), volumes
        (O, B) or None without gas.
      topology, terms, dt, substeps, batch, scene, dtype: how it was built (``substeps`` None: the
        count is data of each :func:`rollout`, see ``at_substeps``).
      chunk: points per compiled rollout call (see :func:`rollout`).
      coherent: with soft-soft contact between objects, a :class:`BatchedCoherent` (the step with
        every point's contact candidate lists carried, which :func:`rollout` scans), else None.
      drive, step_rows: with driven vertices, their :class:`_Drive` and ``step_rows(params, state,
        rows)``, the step reading the path from ``drive.rows_of_steps`` (which :func:`rollout`
        computes once per saved frame); else None.
      at_substeps: with the substep count as data (built with ``substeps=None``), ``at_substeps(n)
        -> (init_fn, substep_fn, coherent)`` for n substeps of h = dt / n per time step, ``n`` a
        traced int32 scalar: the init, one substep of h, and the :class:`BatchedCoherent` whose
        ``step`` is one substep (None without object pairs). :func:`rollout` builds them inside its
        trace from its ``substeps`` argument, so one compiled program serves every count; the
        ``init_fn`` then takes ``substeps=n`` too, and ``step_fn`` and ``force_fn`` are those of
        one substep of dt. None otherwise.
    """

    init_fn: Callable
    step_fn: Callable
    status_fn: Callable
    force_fn: Callable
    topology: model.Topology
    terms: model.Terms
    dt: float
    substeps: int
    batch: int
    scene: object
    dtype: object
    chunk: int = None
    integrator: str = "verlet"
    coherent: object = None
    drive: object = None
    step_rows: Callable = None
    at_substeps: Callable = None

    def params(self, values=None):
        """Broadcast parameters to a batch: ``values`` is a Params of scalars, (O,) or (O, B)
        arrays (default: the scene's); returns a Params of (O, B) arrays of this dtype. The
        spring stiffness of a simulator built for a per-edge field (``terms.k_field``) is an
        (E,) field shared by every point or an (E, B) one per point, and comes back (E, B)."""
        values = self.scene.params if values is None else values
        shape = (self.topology.n_objects, self.batch)
        out = []
        for name, a in zip(Params._fields, values):
            a = np.asarray(a, np.float64)
            want = shape
            if name == "k_structural" and self.terms.k_field:
                want = (self.topology.n_edges, self.batch)
                if a.ndim and a.shape[0] == shape[0] and not model.is_field(self.topology, a[..., 0] if a.ndim == 2 else a):
                    a = a[self.topology.edge_object]          # one k per object: the uniform field
            elif name == "k_structural" and a.ndim == 1 and model.is_field(self.topology, a):
                raise NotImplementedError(FIELD_REFUSAL + f" (k_structural of shape {a.shape})")
            if a.ndim == 1:
                a = a[:, None]
            try:
                out.append(jax.device_put(np.asarray(np.broadcast_to(a, want), self.dtype)))   # converted on the host
            except ValueError:
                raise ValueError(f"parameter {name}: shape {a.shape} does not broadcast to "
                                 f"{'(n_edges' if want != shape else '(n_objects'}, batch) = {want}") from None
        return Params(*out)

    def to_public(self, state):
        """Internal state -> State of (B, V, 3) arrays."""
        return State(*(jnp.stack(comp, axis=-1).transpose(1, 0, 2) for comp in state))

    def to_internal(self, state):
        """State of (V, 3) or (B, V, 3) arrays -> internal state (tuples of three (V, B))."""
        return State(*(_to_soa(a, self.batch, self.dtype) for a in state))


def _to_soa(a, batch, dtype):
    a = jnp.asarray(a, dtype)
    if a.ndim == 2:
        a = jnp.broadcast_to(a[None], (batch,) + a.shape)
    if a.shape[0] != batch or a.ndim != 3 or a.shape[2] != 3:
        raise ValueError(f"expected (V, 3) or ({batch}, V, 3) positions/velocities, got {a.shape}")
    return tuple(a[:, :, c].T for c in range(3))


#: Why a per-edge stiffness field is refused by a simulator built without one.
FIELD_REFUSAL = ("this batched simulator was built for one spring stiffness per object ((O, B) parameters), not "
                 "a per-edge stiffness field (k_region/k_edge): build it for the field's terms "
                 "(terms_for(scene, params) switches k_field on)")


def check_terms(terms):
    """Raise NotImplementedError if ``terms`` selects anything this module does not implement."""
    extra = T.unsupported(terms, "batched")
    if extra:
        raise NotImplementedError(
            f"the batched simulator does not implement the term(s) {', '.join(extra)} that this scene "
            f"needs; simulate such scenes one at a time with jaxplush.simulate")


def terms_for(scene, params=None):
    """The :class:`jaxplush.model.forces.Terms` a batch of parameters needs (``Terms.for_scene(scene,
    params)``): the scene's selection, plus the dashpot, drag and Verlet damping wherever any
    point of ``params`` (a Params of (O, B) arrays) switches them on."""
    return model.Terms.for_scene(scene, params)


def make_batched_simulator(scene, dt, batch, integrator="verlet", terms=None, substeps=1, chunk=None):
    """Build the batched step for a scene.

    Args:
      scene: :class:`jaxplush.scene.parse.Scene`.
      dt: time step, s (static).
      batch: number of parameter points B advanced together (static).
      integrator: only "verlet" is batched.
      terms: the :class:`jaxplush.model.forces.Terms` to compile (default: :func:`terms_for` the scene).
      substeps: Verlet steps of dt / substeps per ``step_fn`` call (as in make_simulator); None:
        the count is data of each :func:`rollout` call (``rollout(..., substeps=n)``), so runs at
        any count share one compiled program (``BatchedSimulator.at_substeps``; not with driven
        vertices, whose paths are tabulated per substep length).
      chunk: points per compiled rollout call (:func:`rollout` runs the batch as independent
        chunks, concurrently on the CPU's cores); default :func:`default_chunk` (16 on a CPU,
        the whole batch on a GPU).

    Returns:
      :class:`BatchedSimulator` (float64 when ``jax_enable_x64`` is on, else float32).

    Raises:
      NotImplementedError: another integrator, or terms this module does not implement.
      ValueError: bad dt, batch, substeps or chunk.
    """
    dt, batch, substeps, chunk = _checked_batch_args(integrator, dt, batch, substeps, chunk)
    terms = terms_for(scene) if terms is None else terms
    check_terms(terms)
    dynamic = substeps is None
    if dynamic and terms.driven:
        raise ValueError("a scene with driven vertices needs a fixed substep count (substeps=n): its paths are "
                         "tabulated per substep length")
    dtype = jnp.result_type(float)
    topo = compiled.topology(scene)
    model.check_precision(topo, dtype, scene.path, getattr(scene, "driven", ()))
    kernel = _make_force_fn(topo, terms, scene.temperature)
    h = dt if dynamic else dt / substeps
    touch = _make_contact(topo, terms, h)
    drive = _make_drive(scene, terms, h, 1 if dynamic else substeps)
    init_fn, step_fn, step_rows, coherent = _make_verlet(topo, terms, scene, kernel, touch, drive, h,
                                                          1 if dynamic else substeps, batch, dtype)
    if dynamic:
        friction = bool(terms.contact) and terms.contact.friction > 0

        def at_substeps(n):
            # built inside the caller's trace, h = dt / n traced: the contact term is built again
            # only where its friction clamp reads h
            n = jnp.asarray(n, jnp.int32)
            h_n = jnp.asarray(dt, dtype) / n.astype(dtype)
            t = _make_contact(topo, terms, h_n) if friction else touch
            init, substep, _, coh = _make_verlet(topo, terms, scene, kernel, t, None, h_n, n, batch, dtype,
                                                 repeat=False)
            return init, substep, coh

        def init_fn(params, x0=None, v0=None, step0=0, substeps=1):
            return at_substeps(substeps)[0](params, x0, v0, step0)
    else:
        at_substeps = None

    def status_fn(params, x):
        code = diagnostics.status_codes(topo, terms, x)
        if touch is not None and touch.overflow is not None:
            code = diagnostics.with_overflow(code, touch.overflow(x))
        return code

    def force_fn(params, x, v):
        f, volume = kernel(params, x, v)
        return (f if touch is None else touch.add(params, x, v, f)), volume

    # the start and the forces jitted (a direct call, as a sweep's start or a test's, is one program,
    # not one per operation); the step and the status stay plain: the rollout traces them
    return BatchedSimulator(init_fn=compiled.jit_once(init_fn), step_fn=step_fn, status_fn=status_fn,
                            force_fn=jax.jit(force_fn),
                            topology=topo, terms=terms, dt=dt, substeps=substeps, batch=batch, scene=scene,
                            dtype=dtype, chunk=chunk, coherent=coherent, drive=drive, step_rows=step_rows,
                            at_substeps=at_substeps)


#: Batched simulators that :func:`shared_simulator` keeps alive for reuse, least recently used
#: first out; :func:`jaxplush.stepping.compiled.clear` empties it.
SHARED = 8
_SHARED: "collections.OrderedDict" = compiled.register(collections.OrderedDict())


def shared_simulator(scene, dt, batch, terms, substeps=1, chunk=None):
    """:func:`make_batched_simulator` (Verlet), one per program in a process: every caller with the
    same scene geometry, dt, width, terms, substeps (None: as data), chunk and dtype gets the same simulator, so
    they run the same compiled code (a fit's evaluators, its predictability measurement, a later
    fit of the scene). The key is what the compiled code depends on (the scene's fingerprint, as
    :mod:`jaxplush.stepping.compiled` keys single simulators), not the scene's values: pass
    parameter values to :meth:`BatchedSimulator.params` (its default, the first scene's values,
    is not the caller's)."""
    key = (scene.fingerprint, float(dt), int(batch), terms, None if substeps is None else int(substeps),
           None if chunk is None else int(chunk),
           jnp.dtype(jnp.result_type(float)).str)
    hit = _SHARED.get(key)
    if hit is None:
        hit = _SHARED[key] = make_batched_simulator(scene, dt, batch, terms=terms, substeps=substeps, chunk=chunk)
        while len(_SHARED) > SHARED:
            _SHARED.popitem(last=False)
    else:
        _SHARED.move_to_end(key)
    return hit


def _checked_batch_args(integrator, dt, batch, substeps, chunk):
    """(dt as a float, batch, substeps and chunk as ints: chunk defaulted and at most batch;
    substeps None stays None), or the errors :func:`make_batched_simulator` raises for bad ones."""
    if integrator != "verlet":
        raise NotImplementedError(f"the batched simulator implements only the 'verlet' integrator, "
                                  f"not {integrator!r}")
    dt = float(dt)
    if not (np.isfinite(dt) and dt > 0):
        raise ValueError(f"dt must be a positive number, got {dt!r}")
    checked = (("batch", batch),) + ((("substeps", substeps),) if substeps is not None else ()) + \
        ((("chunk", chunk),) if chunk is not None else ())
    for name, value in checked:
        if isinstance(value, bool) or int(value) != value or value < 1:
            raise ValueError(f"{name} must be a positive integer, got {value!r}")
    batch, substeps = int(batch), None if substeps is None else int(substeps)
    chunk = default_chunk(batch) if chunk is None else min(int(chunk), batch)
    return dt, batch, substeps, chunk


def _make_verlet(topo, terms, scene, kernel, touch, drive, h, substeps, batch, dtype, repeat=True):
    """The batched damped Verlet scheme on the internal layout: (init_fn, step_fn, step_rows,
    coherent) of :class:`BatchedSimulator`, ``substeps`` steps of h per ``step_fn`` call; ``touch``:
    the :class:`_Contact` of :func:`_make_contact` (None without soft-soft contact); ``drive``: the
    :class:`_Drive` of :func:`_make_drive` (None without driven vertices). ``repeat`` False
    (``BatchedSimulator.at_substeps``: h and ``substeps`` traced, no driven vertices): ``step_fn``
    and the coherent step are one substep of h, the report's damping that of one of ``substeps``."""
    gravity = tuple(float(g) for g in scene.gravity)
    fixed = topo.fixed
    x0_fixed = np.ascontiguousarray(topo.x0[fixed].T)                 # (3, P)
    floor = _make_floor(topo, terms, scene, h)

    def accel(params, x, v, cache=None):
        f, volume = kernel(params, x, v)
        if touch is not None:
            f = touch.add(params, x, v, f, cache)
        inv_m = 1.0 / vertex_mass(topo, params)
        a = tuple(fc * inv_m for fc in f)
        if terms.gravity:
            with jax.named_scope("gravity"):
                a = tuple(ac + jnp.asarray(g, ac.dtype) for ac, g in zip(a, gravity))
        return a, volume

    def pin(comps, values=None):
        if not terms.fixed:
            return comps
        with jax.named_scope("fixed"):
            return tuple(c.at[fixed].set(0.0 if values is None else jnp.asarray(values[i], c.dtype)[:, None])
                         for i, c in enumerate(comps))

    def init_fn(params, x0=None, v0=None, step0=0):
        x = _to_soa(topo.x0 if x0 is None else x0, batch, dtype)
        v = tuple(jnp.zeros_like(c) for c in x) if v0 is None else _to_soa(v0, batch, dtype)
        if drive is not None:              # the driven vertices where their path has them at step0
            x, v = drive.start(x, v, step0)
        a0, _ = accel(params, x, v)
        u = pin(tuple(integrators.verlet_start(vc, ac, h) for vc, ac in zip(v, a0)))
        if drive is not None:              # and the path's velocity, as the single-scene init carries
            u = drive.start(x, u, step0)[1]
        return State(x, u)

    def substep(params, state, cache=None, rows=None):
        x, u = state
        a, _ = accel(params, x, u, cache)
        keep = None
        if terms.verlet_damping:
            with jax.named_scope("verlet_damping"):
                keep = per_vertex(topo, integrators.damping_keep(params.damping, substeps))
        if drive is None:
            u_new = tuple(integrators.verlet_kick(uc, ac, h, keep) for uc, ac in zip(u, a))
            x_new = tuple(_folded(lambda xc, uc: integrators.verlet_drift(xc, uc, h), xc, uc)
                          for xc, uc in zip(x, u_new))
            if terms.floor:
                x_new, u_new = floor(x, x_new, u_new)
            return State(pin(x_new, x0_fixed), pin(u_new))
        # driven vertices: the path's position and velocity blended into the update itself
        # (_Drive.blend), the floor leaving them alone; the path wins over the floor and every force
        free, px, pu = drive.blend(rows, x[0].shape[0])
        u_new = tuple(integrators.verlet_kick(uc, ac, h, keep) * free + pc for uc, ac, pc in zip(u, a, pu))
        x_new = tuple(_folded(lambda xc, uc, fc, pc: integrators.verlet_drift(xc, uc, h) * fc + pc, xc, uc, free, pc)
                      for xc, uc, pc in zip(x, u_new, px))
        if terms.floor:
            x_new, u_new = floor(x, x_new, u_new, (free, px[1]))
        return State(pin(x_new, x0_fixed), pin(u_new))

    if not repeat:
        return init_fn, substep, None, _coherent_step(touch, substep, 1)
    if drive is None:
        return init_fn, integrators.repeat_substeps(substep, substeps), None, _coherent_step(touch, substep, substeps)

    def step_rows(params, state, rows):
        # one time step, substep j reading rows[j] (_Drive.rows)
        if substeps == 1:
            return substep(params, state, None, rows[0])
        return jax.lax.fori_loop(0, substeps, lambda j, s: substep(params, s, None, rows[j]), state)

    def step_fn(params, state, step=None):
        if step is None:
            raise constraints.missing_step_error()
        return step_rows(params, state, drive.rows_of_steps(_lane_steps(step, state), 1)[0])
    return init_fn, step_fn, step_rows, _coherent_step(touch, substep, substeps, drive)


class BatchedCoherent(NamedTuple):
    """The batched step with every point's soft-soft contact candidate lists carried between steps,
    as :class:`jaxplush.stepping.step.CoherentStep` for one scene.

    ``init(x) -> cache``: a fresh search of every point at internal positions x (three (V, B)): a
    :class:`jaxplush.model.contact.ContactCache` whose leaves carry the batch on their *leading*
    axis (those of ``jax.vmap``; its ``overflow`` is (B, O)); ``step(params, state, cache,
    step=None) -> (state, cache)``: one time step with the carried lists, updated after every
    substep (``step``: the (B,) step indices, needed with driven vertices as for ``step_fn``).
    """

    init: Callable
    step: Callable
    step_rows: Callable = None


def _coherent_step(touch, substep, substeps, drive=None):
    """The :class:`BatchedCoherent` of the Verlet ``substep`` (None without object pairs): as
    :func:`jaxplush.stepping.step._coherent_step`, the force reading the carried lists and the
    lists updated after each substep (``drive``: driven vertices, the path's rows passed on)."""
    if touch is None or touch.init is None:
        return None

    def coherent_substep(params, state, cache, rows=None):
        state = substep(params, state, cache, rows)
        return state, touch.update(cache, state.x)

    if drive is not None:
        def step_rows(params, state, cache, rows):
            if substeps == 1:
                return coherent_substep(params, state, cache, rows[0])
            return jax.lax.fori_loop(0, substeps, lambda j, c: coherent_substep(params, *c, rows[j]), (state, cache))

        def step(params, state, cache, step=None):
            if step is None:
                raise constraints.missing_step_error()
            return step_rows(params, state, cache, drive.rows_of_steps(_lane_steps(step, state), 1)[0])
        return BatchedCoherent(init=touch.init, step=step, step_rows=step_rows)
    repeated = integrators.repeat_substeps(lambda params, c: coherent_substep(params, *c), substeps)
    return BatchedCoherent(init=touch.init, step=lambda params, state, cache, step=None: repeated(params, (state, cache)))


def _lane_steps(step, state):
    """``step`` (scalar or (B,)) as (B,) int32 step indices for the lanes of ``state``."""
    return jnp.broadcast_to(jnp.asarray(step, jnp.int32), state.x[0].shape[1:])


class _Drive(NamedTuple):
    """Driven vertices on the batched layout, on the path of
    :class:`jaxplush.stepping.constraints.Drive` (one interpolation for every engine), each lane at
    its own step index.

    rows_of_steps: (first, n) -> (n, substeps, 7, D, B): for the n time steps from ``first`` ((B,)
      or scalar step indices), per substep the rows (on, on p (3), on w (3)): ``on`` 1 where a
      vertex is driven in the substep (0 once released), p its path position at the substep's
      end, w the path's velocity over it. :func:`rollout` computes them once per saved frame,
      so the step itself does no search along the path.
    blend: (rows (7, D, B), V) -> (free, px, pu): (V, B) arrays, free 0 at the vertices driven
      in the substep and 1 elsewhere, px and pu (three components each) the path's position and
      velocity there and 0 elsewhere; u' free + pu and x' free + px are then the step's update
      with the path applied, exactly (as ``Drive.apply``: the path wins).
    start: (x, v, step0) -> (x, v) for lanes at step ``step0`` (scalar or (B,) time steps): at
      step 0 ``Drive.start`` (the path's first position and velocity), at step n > 0 the state
      that the step leaves after step n - 1 (so a lane started from a state at step n continues
      the single-scene run).
    """

    rows_of_steps: Callable
    blend: Callable
    start: Callable


def _make_drive(scene, terms, h, substeps):
    """The :class:`_Drive` of a scene with driven vertices (None without)."""
    if not terms.driven:
        return None
    drive = constraints.Drive(scene, h)
    idx = drive.index

    def at(k, dtype):
        """(position at t_{k+1} (3, D) + k.shape, velocity over substep k (same), on (D,) + k.shape)."""
        k = jnp.asarray(k, jnp.int32)
        p0 = drive.position(k.astype(dtype) * drive.h, dtype)
        p1 = drive.position((k + 1).astype(dtype) * drive.h, dtype)
        act = drive.active(k)
        on = jnp.ones((len(idx),) + k.shape, dtype) if act is None else act.astype(dtype)
        return p1, (p1 - p0) * (1.0 / drive.h), on

    def rows_of_steps(first, n):
        with jax.named_scope("driven"):
            first = jnp.asarray(first, jnp.int32)
            k = (first[None] * substeps + jnp.arange(n * substeps, dtype=jnp.int32).reshape(
                (-1,) + (1,) * first.ndim))                                       # (n substeps,) + first.shape
            p, w, on = at(k, jnp.result_type(float))
            rows = jnp.concatenate([on[None], p * on[None], w * on[None]])       # (7, D, n substeps, ...)
            rows = jnp.moveaxis(rows, 2, 0)                                      # (n substeps, 7, D, ...)
            return rows.reshape((n, substeps) + rows.shape[1:])

    def blend(rows, n_vertices):
        # one scatter of every row into (V, 7, B) (slices of it fuse into the update): not a
        # scatter into x and u after the update, into whose operand XLA:CPU fused the whole
        # Verlet kick (the step ran at 0.6x the undriven step's speed; benchmarks/RESULTS.md,
        # "Driven vertices and stiffness fields in the batched engine")
        with jax.named_scope("driven"):
            z = jnp.zeros((n_vertices,) + rows.shape[::2], rows.dtype).at[idx].set(jnp.swapaxes(rows, 0, 1))
            return 1.0 - z[:, 0], tuple(z[:, 1 + c] for c in range(3)), tuple(z[:, 4 + c] for c in range(3))

    def put(x, v, p, w, on):
        out_x, out_v = [], []
        for c in range(3):
            keep = on > 0
            out_x.append(x[c].at[idx].set(jnp.where(keep, p[c], x[c][idx])))
            out_v.append(v[c].at[idx].set(jnp.where(keep, w[c], v[c][idx])))
        return tuple(out_x), tuple(out_v)

    def start(x, v, step0=0):
        with jax.named_scope("driven"):
            dtype = x[0].dtype
            n = jnp.broadcast_to(jnp.asarray(step0, jnp.int32), x[0].shape[1:])
            p, w, on = at(jnp.maximum(n * substeps - 1, 0), dtype)
            first = n == 0
            p = jnp.where(first, jnp.asarray(drive.x_start, dtype)[..., None], p)
            w = jnp.where(first, jnp.asarray(drive.v_start, dtype)[..., None], w)
            return put(x, v, p, w, jnp.where(first, 1.0, on))

    return _Drive(rows_of_steps, blend, start)


class _Contact(NamedTuple):
    """Soft-soft contact (and self-collision) on the batched layout: the single-scene functions of
    :func:`jaxplush.model.contact.make_contact`, ``jax.vmap``-ed over the points.

    add: (params, x, v, f, cache=None) -> f plus the contact force (x, v, f three (V, B); cache
      batched as :class:`BatchedCoherent`'s; None: every point searches afresh).
    init, update: a fresh batched cache at x, and the cache for new positions x (None without
      object pairs).
    overflow: x -> (O, B) bool, the objects whose candidates a fresh search at x would overflow
      (:func:`jaxplush.model.contact.make_overflow_check`), or None without object pairs.
    """

    add: Callable
    init: Callable
    update: Callable
    overflow: Callable


def _lanes(comps):
    """Three (V, B) components -> (B, 3, V): each point on the single-scene internal layout."""
    return jnp.stack(comps).transpose(2, 0, 1)


def _make_contact(topo, terms, h):
    """The :class:`_Contact` of ``terms.contact``, or None when nothing can touch.

    One definition of the physics: the single-scene force and candidate cache, vmapped over the
    batch, with the positions (and, with contact friction, the velocities) transposed to
    (B, 3, V) for them and the force back to (V, B) components (benchmarks/RESULTS.md, "Batched
    contact", measures the transposes). A cache is rebuilt per point exactly where the single
    scene rebuilds it, and the rebuild's search runs only for the points that need it.
    """
    cfg = terms.contact
    if not cfg:
        return None
    force, ops = _contact.make_contact(topo, cfg, h)
    check = _contact.make_overflow_check(topo, cfg)
    friction = cfg.friction > 0

    def add(params, x, v, f, cache=None):
        with jax.named_scope("contact"):
            if cache is None:
                one = lambda p, xl, vl: force(p, xl, vl)                      # noqa: E731
                g = jax.vmap(one, in_axes=(1, 0, 0 if friction else None))(
                    params, _lanes(x), _lanes(v) if friction else None)
            else:
                # the blocks of query slots that hold a valid query in any point (one lax.cond
                # for the whole batch, :func:`jaxplush.model.contact.make_contact`)
                g = force.lanes(params, _lanes(x), _lanes(v) if friction else None, cache)
            g = g.transpose(1, 2, 0)                                       # (3, V, B)
            return tuple(fc + g[c] for c, fc in enumerate(f))

    if ops is None:
        return _Contact(add, None, None, None)

    def init(x):
        return jax.vmap(ops.init)(_lanes(x))

    def update(cache, x):
        # every point walked, then the points due a rebuild rebuilt one at a time (ops.update, which
        # rebuilds them): the search costs only the points that need it, as in the single scene
        xl = _lanes(x)
        stale = jax.vmap(ops.stale)(cache, xl)
        walked = ops.walk_lanes(cache, xl)

        def rebuild_one(c):
            out, todo = c
            b = jnp.argmax(todo)
            one = ops.update(jax.tree_util.tree_map(lambda a: a[b], cache), xl[b])
            return jax.tree_util.tree_map(lambda a, o: a.at[b].set(o), out, one), todo.at[b].set(False)

        return jax.lax.while_loop(lambda c: jnp.any(c[1]), rebuild_one, (walked, stale))[0]

    def overflow(x):
        return jax.vmap(check)(_lanes(x)).T

    return _Contact(add, init, update, overflow)


def on_cpu():
    """Whether the default backend is XLA:CPU. The chunking, the thread pool and the compiler
    options of this module are tuned for CPU cores and caches; on an accelerator a batch runs as
    one compiled call (:func:`default_chunk`) with XLA's default options."""
    return jax.default_backend() == "cpu"


def default_chunk(batch):
    """Points per compiled rollout call for a batch of ``batch``.

    On XLA:CPU: the whole batch up to :data:`MAX_CHUNK` points, else chunks of MAX_CHUNK (the
    last one padded), which run concurrently, one per core. At 642 vertices (float32) a 16-point
    chunk's step keeps its working set in a core's L2 cache and fills whole 512-bit vectors;
    wider and narrower chunks, and widths that are no multiple of 8, cost more CPU time per
    point-step (benchmarks/bench_sweep.py; figures in benchmarks/RESULTS.md).

    On any other backend (a GPU): the whole batch in one call, split evenly over the local
    devices when there are several (:func:`rollout`). There a step is bound by launch latency, so
    the widest call is the fastest (benchmarks/RESULTS.md, "GPU")."""
    if not on_cpu():
        return -(-batch // len(local_devices()))
    return batch if batch <= MAX_CHUNK else MAX_CHUNK


def _n_cores():
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:                 # not on Linux
        return os.cpu_count() or 1


def _make_floor(topo, terms, scene, h):
    """The floor projection of :mod:`jaxplush.stepping.constraints` on component tuples.

    The plain projection (y >= H, vertical velocity set to the one that lands the vertex on the
    floor) is written out on the (V, B) y-component. With floor friction or restitution the
    shared single-scene hook itself is applied to stacked (3, V, B) arrays (every operation in
    it is elementwise), so both stay one implementation.
    """
    if not terms.floor:
        return None
    height = float(scene.floor)
    if terms.floor_friction or terms.floor_restitution:
        shared = constraints.make_constrain(topo, dataclasses.replace(terms, fixed=False, driven=False), scene, h)

        def floor(x_old, x, v, driven=None):
            xs, vs = shared(jnp.stack(x_old), jnp.stack(x), jnp.stack(v))
            xs, vs = tuple(xs), tuple(vs)
            if driven is not None:         # the driven vertices where the update put them
                keep = driven[0] == 0
                xs = tuple(jnp.where(keep, a, b) for a, b in zip(x, xs))
                vs = tuple(jnp.where(keep, a, b) for a, b in zip(v, vs))
            return xs, vs
        return floor

    def floor(x_old, x, v, driven=None):
        with jax.named_scope("floor"):
            # below = x[1] < height, written out: x[1] is computed on the folded view (_folded),
            # and reading it here made XLA copy the projected velocity every step.
            below = x_old[1] + v[1] * h < height
            if driven is not None:         # (free, path y) of _Drive.blend: a driven vertex is not moved
                below = below & (driven[0] > 0)
            vy = jnp.where(below, constraints.landing_velocity(x_old[1], height, h), v[1])
            if driven is not None:
                y = _folded(lambda yc, vc, fc, pc: jnp.maximum(yc + vc * h, height) * fc + pc, x_old[1], vy, *driven)
                return (x[0], y, x[2]), (v[0], vy, v[2])
            # y from the projected velocity, not from x[1]: then the (expensive) unprojected
            # velocity has one consumer and XLA does not compute the forces twice. Identical
            # where the vertex is above the floor; on it, max(.) returns the floor up to 1 ulp.
            y = _folded(lambda yc, vc: jnp.maximum(yc + vc * h, height), x_old[1], vy)
            return (x[0], y, x[2]), (v[0], vy, v[2])
    return floor


#: Minimum row width (floats) of the position update (see :func:`_folded`).
_FOLD_WIDTH = 48


def _fold_factor(n_rows, width):
    """Smallest r dividing ``n_rows`` with r * width >= _FOLD_WIDTH (1 if none up to 64)."""
    for r in range(1, 65):
        if r * width >= _FOLD_WIDTH and n_rows % r == 0:
            return r
    return 1


def _folded(fn, *arrays):
    """``fn`` (elementwise) applied to (V, B) arrays viewed as (V / r, r B) (r = :func:`_fold_factor`).

    A bare reshape, so the result is identical. It exists for XLA:CPU's code generation: an
    elementwise loop over rows of 16 floats (a 16-point chunk) with a body as small as the position
    update x + h u is fully unrolled by LLVM and then left scalar, while rows of 48 floats keep
    the loop and vectorise it (see benchmarks/RESULTS.md). :func:`_core` carries the positions in
    the same folded shape, so the update stays in place.
    """
    v, b = arrays[0].shape
    r = _fold_factor(v, b)
    if r == 1:
        return fn(*arrays)
    return fn(*(a.reshape(v // r, r * b) for a in arrays)).reshape(v, b)


def _make_force_fn(topo, terms, temperature):
    """Batched ring force kernel: (params, x, v) -> (f, volume) with x, v, f tuples of 3 (V, B).

    The single-scene ring kernel's assembly (:func:`jaxplush.model.forces.make_force_fn`) on the
    batch-last layout: the same term functions (:mod:`jaxplush.model.terms`) on (V, B) arrays,
    one ring slot at a time."""
    ring = np.ascontiguousarray(topo.ring.T)                            # (K, V)
    mask = np.ascontiguousarray(topo.ring_mask.T)
    rest = np.ascontiguousarray(topo.ring_rest.T)
    n_ring = ring.shape[0]
    flat = ring.reshape(-1)
    slot_edge = np.ascontiguousarray(topo.ring_edge.T).reshape(-1)     # (K V,): the edge of each ring slot
    full = [bool(mask[k].all()) for k in range(n_ring)]

    def neighbours(a):
        """K x C x (V, B): component c of a (C (V, B) arrays) at every vertex's k-th ring neighbour.
        One row gather over the flattened (K V,) table from the components side by side (rows of
        C B contiguous floats): one XLA op instead of C K (each op costs a dispatch in
        XLA:CPU's while loop, as much as a gather's own work at small B)."""
        b, n_c = a[0].shape[1], len(a)
        g = jnp.concatenate(a, axis=1).at[flat].get(mode="promise_in_bounds").reshape(n_ring, -1, n_c * b)
        return [[g[k, :, c * b:(c + 1) * b] for c in range(n_c)] for k in range(n_ring)]

    def force_fn(params, x, v):
        dtype = x[0].dtype
        eps2 = model.length_eps2(topo, dtype)
        with jax.named_scope("spring"):
            d = [[n[c] - x[c] for c in range(3)] for n in neighbours(x)]            # K x 3 x (V, B)
            # each edge term's coefficient per vertex (V, B), once for every slot
            spread = {f: per_vertex(topo, getattr(params, f)) for f in T.edge_fields(terms)
                      if not (f == "k_structural" and terms.k_field)}
            if terms.k_field:
                # an (E, B) field: each ring slot's edge, one row gather (padded slots name a real
                # edge and are masked below), as ring_stiffness for one scene
                k_slots = params.k_structural.at[slot_edge].get(mode="promise_in_bounds").reshape(n_ring, -1, x[0].shape[1])
            if terms.dashpot:
                vn = neighbours(v)
            f = [0.0, 0.0, 0.0]
            for k in range(n_ring):
                inv_l = T.inv_length(d[k], eps2)
                w = T.edge_weight(terms, lambda field, k=k: k_slots[k] if field == "k_structural" and terms.k_field
                                  else spread[field], jnp.asarray(rest[k], dtype)[:, None], d[k], inv_l,
                                  dv=lambda k=k: [vn[k][c] - v[c] for c in range(3)])
                if not full[k]:
                    w = jnp.where(mask[k][:, None], w, 0.0)
                f = [fc + w * dc for fc, dc in zip(f, d[k])]

        def fan_sums():
            fans = [0.0, 0.0, 0.0]
            for k in range(n_ring):
                fans = [s + a for s, a in zip(fans, T.fan(d[k], d[(k + 1) % n_ring]))]
            return fans

        f, volume = model.vertex_terms(topo, terms, temperature, params, x, v, f, fan_sums)
        return tuple(f), volume

    return force_fn


# --------------------------------------------------------------------------- rollout

def lanes(state):
    """The number of points (lanes) an internal state holds: its positions' last axis."""
    return int(state.x[0].shape[-1])


def take_lanes(tree, m):
    """The first ``m`` lanes of a batched pytree whose leaves carry the batch on their last axis
    (params (O, B), an internal state's (V, B) components)."""
    if _traced(tree):
        return jax.tree_util.tree_map(lambda a: a[..., :m], tree)
    # concrete: cut in numpy (a compiled slice per shape cost more than the copy)
    return jax.tree_util.tree_map(lambda a: jax.device_put(np.asarray(a)[..., :m]), tree)


def initial_health(bsim, state, step0=0):
    """A fresh :class:`jaxplush.stepping.rollouts.Health` (batched) for ``state`` (internal, any
    number of lanes) at step ``step0`` (scalar or per lane)."""
    b = lanes(state)
    shape = (bsim.topology.n_objects, b)
    if _traced((state, step0)):
        neg = jnp.full(shape, -1, jnp.int32)
        good_step = jnp.broadcast_to(jnp.asarray(step0, jnp.int32), (b,))
        return Health(jnp.zeros(shape, jnp.int32), neg, neg, state, good_step)
    # concrete: made in numpy and put on the device (no one-op program per shape)
    neg = jax.device_put(np.full(shape, -1, np.int32))
    good_step = jax.device_put(np.broadcast_to(np.asarray(step0, np.int32), (b,)).copy())
    return Health(jax.device_put(np.zeros(shape, np.int32)), neg, neg, state, good_step)


def contact_pairs(bsim):
    """The object pairs (a, b) with soft-soft contact between them (() without it)."""
    cfg = bsim.terms.contact
    return tuple(cfg.pairs) if cfg is not None and cfg.pairs else ()


def _pair_separation(bsim, x):
    """(n_pairs, B) separation of every contact pair's bounding boxes (the largest gap along an
    axis; negative where they overlap) at internal positions x (3 (V, B) arrays). An object's
    surface lies within its vertices' box, so every point of one object is at least this far
    from the other's surface."""
    slices = bsim.topology.vertex_slices
    lo = [[xc[a:b].min(axis=0) for xc in x] for a, b in slices]
    hi = [[xc[a:b].max(axis=0) for xc in x] for a, b in slices]
    seps = []
    for a, b in contact_pairs(bsim):
        gap = [jnp.maximum(lo[b][c] - hi[a][c], lo[a][c] - hi[b][c]) for c in range(3)]
        seps.append(jnp.maximum(jnp.maximum(gap[0], gap[1]), gap[2]))
    return jnp.stack(seps)


def _core(bsim, params, state, health, step0, aux, timing=None, *, n_frames, save_every, observe, separation=False):
    """The batched rollout (:func:`rollout`): ``n_frames`` frames of ``save_every`` steps, or with
    ``timing`` (traced (2,) int32: live frames, steps per frame; ``save_every`` then unused) a scan
    of ``n_frames`` frames of which only the first ``timing[0]`` run, ``timing[1]`` steps each.
    A simulator with the substep count as data (``bsim.substeps`` None) takes it as ``timing[2]``:
    each step is then that many substeps of dt / timing[2]."""
    coherent = bsim.coherent
    track = bool(separation) and bool(contact_pairs(bsim))
    driven = bsim.drive is not None        # then every step reads the path's rows at its lanes' steps
    n_sub = None
    step_fn = bsim.step_fn
    if bsim.substeps is None:
        # one substep of h = dt / n_sub, run n_sub times per step (the candidate lists, as their
        # fresh search below, do not depend on h)
        n_sub = timing[2]
        _, step_fn, by_h = bsim.at_substeps(n_sub)
    if coherent is None:
        def one(s, cache, rows):
            return (bsim.step_rows(params, s, rows) if driven else step_fn(params, s)), cache
        cache0 = None
    else:
        # soft-soft contact: every point's candidate lists ride along in the carry, as in
        # jaxplush.stepping.rollouts (searched afresh at the start of each call), with their
        # sticky per-object overflow flags
        stepper = coherent if n_sub is None else by_h

        def one(s, cache, rows):
            return coherent.step_rows(params, s, cache, rows) if driven else stepper.step(params, s, cache)
        cache0 = coherent.init(state.x)

    def steps(s, cache, first, gap=None):
        # The positions are carried folded (see _folded): the in-place position update then runs
        # on rows of >= _FOLD_WIDTH floats, which XLA:CPU vectorises. ``first``: the (B,) step
        # index of s (read with driven vertices only: the path's rows of the frame's steps).
        # ``gap``: a traced step count (``timing``), run as a loop of that many steps (the path's
        # rows then read step by step).
        v, b = s.x[0].shape
        r = _fold_factor(v, b)
        fold = lambda st: State(tuple(a.reshape(v // r, r * b) for a in st.x), st.v)       # noqa: E731
        unfold = lambda st: State(tuple(a.reshape(v, b) for a in st.x), st.v)              # noqa: E731

        def body(c, n, step_end=None):
            if track:                  # the closest the pairs' boxes came, after every step
                (cache, sep) = c[1]
                s, cache = one(unfold(c[0]), cache, n)
                closer = jnp.minimum(sep, _pair_separation(bsim, s.x))
                if step_end is not None:           # (substeps as data: after a step's last substep)
                    closer = jnp.where(step_end, closer, sep)
                return (fold(s), (cache, closer)), None
            s, cache = one(unfold(c[0]), c[1], n)
            return (fold(s), cache), None
        if gap is not None:
            def loop(j, c):
                if n_sub is not None:             # j counts substeps
                    return body(c, None, (j + 1) % n_sub == 0)[0]
                return body(c, bsim.drive.rows_of_steps(first + j, 1)[0] if driven else None)[0]
            s, cache = jax.lax.fori_loop(0, gap, loop, (fold(s), cache))
            return unfold(s), cache
        rows = bsim.drive.rows_of_steps(first, save_every) if driven else None     # once per frame
        s, cache = jax.lax.scan(body, (fold(s), cache), rows, length=save_every)[0]
        return unfold(s), cache

    every = save_every if timing is None else timing[1]

    def frame(carry, i):
        s, cache, h0 = carry
        if timing is None:
            s, cache = steps(s, cache, step0 + i * every)
        else:                           # a frame past the live ones runs no step
            live = i < timing[0]
            count = jnp.where(live, every, 0)
            s, cache = steps(s, cache, step0 + i * every, count if n_sub is None else count * n_sub)
        if track:
            cache, sep = cache
        step = step0 + (i + 1) * every                                       # (B,)
        if coherent is None:
            code = bsim.status_fn(params, s.x)
        else:
            # a contact overflow since the start of this call is the object's code
            code = diagnostics.with_overflow(diagnostics.status_codes(bsim.topology, bsim.terms, s.x),
                                             cache.overflow.T)
        h = h0.advance(code, step, s)
        if timing is not None:          # and is not checked
            h = jax.tree_util.tree_map(lambda a, b: jnp.where(live, a, b), h, h0)
        out = None if observe is None else observe(params, i, s.x, aux)
        return (s, (cache, sep) if track else cache, h), out

    if track:
        cache0 = (cache0, _pair_separation(bsim, state.x))
    (state, cache, health), out = jax.lax.scan(frame, (state, cache0, health), jnp.arange(n_frames, dtype=jnp.int32))
    if separation:
        sep = cache[1] if track else jnp.full((0, lanes(state)), jnp.inf, state.x[0].dtype)
        return state, out, health, sep
    return state, out, health


#: XLA:CPU compiler options of the rollout, set on this one function (no process-wide flag),
#: each measured with benchmarks/bench_sweep.py (figures in benchmarks/RESULTS.md): 512-bit
#: vectors (XLA prefers 256 even where AVX-512 exists), and XLA's own loop for the volume
#: reduction instead of a YNNPACK call (the call costs more than the sum it does). Results
#: agree with the defaults to rounding.
#: Where the installed XLA rejects them, the rollout compiles with the defaults.
ROLLOUT_COMPILER_OPTIONS = {"xla_cpu_prefer_vector_width": 512, "xla_cpu_experimental_ynn_fusion_type": ""}


class _LazyJit:
    """``jax.jit(fn, compiler_options=ROLLOUT_COMPILER_OPTIONS)`` on XLA:CPU, built at first use
    after checking that this jax/XLA accepts the options (a tiny compile), else (or on another
    backend, for which these options mean nothing) a plain jit."""

    def __init__(self, fn, static_argnames):
        self._fn, self._static, self._jit = fn, static_argnames, None
        self._lock = threading.Lock()

    def _get(self):
        with self._lock:
            if self._jit is None:
                kw = dict(compiler_options=dict(ROLLOUT_COMPILER_OPTIONS)) if on_cpu() else {}
                try:
                    if kw:
                        jax.jit(lambda a: a + 1, **kw).lower(np.float32(0)).compile()
                except Exception:                       # unknown option, or no compiler_options
                    kw = {}
                self._jit = jax.jit(self._fn, static_argnames=self._static, **kw)
            return self._jit

    def __call__(self, *args, **kwargs):
        return self._get()(*args, **kwargs)

    def __getattr__(self, name):
        return getattr(self._get(), name)


_core_jit = _LazyJit(_core, ("bsim", "n_frames", "save_every", "observe", "separation"))


def _split(tree, n, chunk):
    """Every leaf (batch on its last axis) padded to n * chunk points by repeating its last point,
    then cut into n chunks: a list of n trees. Concrete arrays are cut in numpy (on the CPU a
    view of the device buffer): a compiled program per batch size cost more than the copies."""
    xp = jnp if _traced(tree) else np

    def cut(a, i):
        a = xp.asarray(a)
        pad = n * chunk - a.shape[-1]
        if pad:
            a = xp.concatenate([a, xp.repeat(a[..., -1:], pad, axis=-1)], axis=-1)
        return a[..., i * chunk:(i + 1) * chunk]
    return [jax.tree_util.tree_map(lambda a: cut(a, i), tree) for i in range(n)]


def _join(parts, batch):
    """Inverse of _split for rollout outputs (padding dropped): state and health leaves (and the
    separations, if any) joined on their last axis, observations (frames first, then the batch)
    on axis 1. Concrete outputs are joined in numpy and handed back as jax arrays."""
    traced = _traced(parts)
    xp = jnp if traced else np

    def cat(axis):
        def join(*a):
            out = xp.concatenate([xp.asarray(x) for x in a], axis=axis)
            keep = [slice(None)] * out.ndim
            keep[axis] = slice(0, batch)                         # the padding dropped
            out = out[tuple(keep)]
            return out if traced else jax.device_put(out)
        return join
    (states, outs, healths) = list(zip(*parts))[:3]
    out = None if outs[0] is None else jax.tree_util.tree_map(cat(1), *outs)
    joined = (jax.tree_util.tree_map(cat(-1), *states), out, jax.tree_util.tree_map(cat(-1), *healths))
    if len(parts[0]) > 3:
        joined += (cat(-1)(*[p[3] for p in parts]),)
    return joined


def _batch_spec(a, axis=-1):
    """The PartitionSpec of a leaf whose ``axis`` is the batch: split over the mesh's "batch"."""
    names = [None] * a.ndim
    names[axis] = "batch"
    return jax.sharding.PartitionSpec(*names)


@functools.lru_cache(maxsize=None)
def _mesh(devices):
    """A 1-D :class:`jax.sharding.Mesh` named "batch" over ``devices`` (a tuple)."""
    return jax.sharding.Mesh(np.asarray(devices, dtype=object), ("batch",))


def local_devices():
    """The devices a batched rollout spreads its lanes over: the default backend's local devices
    (one on a plain CPU; ``XLA_FLAGS=--xla_force_host_platform_device_count=N`` makes N)."""
    return tuple(jax.local_devices())


def _sharded(bsim, mesh, params, state, health, step0, aux, timing, *, n_frames, save_every, observe, separation=False):
    """:func:`_core` on ``mesh``'s devices, each running the same program on its own
    ``bsim.chunk`` lanes (``jax.shard_map`` over the batch axis; ``aux`` is replicated). Lanes are
    independent and every device compiles the one-chunk program, so each lane's result is that
    of a one-device chunked run bit for bit (tests/test_scale_out.py)."""
    last = lambda tree: jax.tree_util.tree_map(_batch_spec, tree)          # noqa: E731
    replicated = lambda tree: jax.tree_util.tree_map(lambda a: jax.sharding.PartitionSpec(), tree)  # noqa: E731
    ins = (last(params), last(state), last(health), _batch_spec(step0), replicated(aux), replicated(timing))
    static = dict(n_frames=n_frames, save_every=save_every, observe=observe, separation=separation)
    n = mesh.devices.size
    local = jax.tree_util.tree_map(
        lambda a: jax.ShapeDtypeStruct(a.shape[:-1] + (a.shape[-1] // n,), a.dtype), (params, state, health, step0))
    shapes = jax.eval_shape(lambda *a: _core(bsim, *a, aux, timing, **static), *local)
    outs = (last(shapes[0]), jax.tree_util.tree_map(lambda a: _batch_spec(a, 1), shapes[1]), last(shapes[2]))
    if separation:
        outs += (_batch_spec(shapes[3]),)
    body = lambda *a: _core(bsim, *a, **static)                             # noqa: E731
    return jax.shard_map(body, mesh=mesh, in_specs=ins, out_specs=outs, check_vma=False)(
        params, state, health, step0, aux, timing)


_sharded_jit = _LazyJit(_sharded, ("bsim", "mesh", "n_frames", "save_every", "observe", "separation"))

_pool_lock = threading.Lock()
_pool = None


def _executor():
    global _pool
    with _pool_lock:
        if _pool is None:
            _pool = ThreadPoolExecutor(max_workers=_n_cores(), thread_name_prefix="jaxplush-batched")
        return _pool


def rollout(bsim, params, state, n_frames, save_every=1, *, health=None, step0=0, observe=None, aux=None,
            separation=False, pad_to=None, substeps=None):
    """Run ``n_frames * save_every`` steps of every point, checking health every ``save_every``.

    Compiled once per (simulator, n_frames, save_every, observe); new parameter values, states
    or ``aux`` reuse it. The B points (lanes) run as ceil(B / bsim.chunk) independent chunks (the
    last one padded with copies of the last point), one compiled call each, dispatched from a pool
    of threads (one per CPU core) so that they run concurrently; points are independent, so the
    result is that of one call on the whole batch (to rounding). With several local devices
    (:func:`local_devices`) the chunks instead run one per device, a group of as many chunks as
    devices per sharded call (:func:`_sharded`), bit-identical to the one-device run. B is the state's lane count
    (:func:`lanes`): ``bsim.batch``, or any other number (:func:`take_lanes` of a full batch),
    with no new compile.

    Args:
      bsim: :class:`BatchedSimulator`.
      params: Params of (O, B) arrays (:meth:`BatchedSimulator.params`).
      state: internal state (from ``bsim.init_fn`` or a previous rollout).
      n_frames, save_every: number of frames and steps per frame (static).
      health: a :class:`jaxplush.stepping.rollouts.Health` (batched) to continue; default fresh.
      step0: step number of ``state`` (scalar or (B,)), for chunked runs.
      observe: optional static ``observe(params, i, x, aux) -> pytree`` evaluated after frame i
        (0-based within this call) on the internal positions x; its outputs are stacked over
        frames. Every output leaf must have the batch on its leading axis (as
        :func:`positions_observer`'s (B, V, 3)). Default: no per-frame output.
      aux: traced data passed to ``observe`` (e.g. target frames), shared by all points.
      separation: also return, per soft-soft contact pair and point, the smallest separation of
        the two objects' bounding boxes over every step of the call, its start included
        (:func:`contact_pairs` order; (0, B) without such pairs): where it exceeds a pair's
        contact reach, neither object felt the other.
      pad_to: a static frame count (at least ``n_frames``): compile one program of ``pad_to``
        frames in which ``n_frames`` and ``save_every`` are data, so that every piece of a run
        cut into pieces of at most ``pad_to`` frames, whatever its length and frame spacing,
        runs the same compiled code (a new program costs seconds). The frames past ``n_frames``
        run no step: the state and health are those after ``n_frames`` frames, and the
        observations have ``pad_to`` frames, the ones past ``n_frames`` repeating the last.
      substeps: with a simulator built with ``substeps=None``, the substeps per step of this call
        (required; data of the program, as ``n_frames`` and ``save_every`` are with ``pad_to``,
        which then defaults to ``n_frames``); the state must come from its ``init_fn`` at the same
        count. Otherwise None or the simulator's own count.

    Returns:
      (final internal state, stacked observations (frames, B, ...) or None, health), and the
      separations ((n_pairs, B)) with ``separation``.
    """
    if n_frames < 1 or save_every < 1:
        raise ValueError(f"n_frames and save_every must be >= 1, got {n_frames} and {save_every}")
    if bsim.substeps is None:
        if substeps is None:
            raise ValueError("this simulator takes its substep count per call (built with substeps=None): "
                             "pass rollout(..., substeps=n), the count its state was initialised at")
        if isinstance(substeps, bool) or int(substeps) != substeps or substeps < 1:
            raise ValueError(f"substeps must be a positive integer, got {substeps!r}")
        pad_to = n_frames if pad_to is None else pad_to
    elif substeps is not None and substeps != bsim.substeps:
        raise ValueError(f"this simulator runs {bsim.substeps} substeps per step (built with substeps="
                         f"{bsim.substeps}), not {substeps}: build it with substeps=None to give the count per call")
    batch = lanes(state)
    step0 = jnp.broadcast_to(jnp.asarray(step0, jnp.int32), (batch,)) if _traced(step0) else \
        jax.device_put(np.broadcast_to(np.asarray(step0, np.int32), (batch,)).copy())    # no one-op program
    if health is None:
        health = initial_health(bsim, state, step0)
    if pad_to is None:
        static = dict(n_frames=int(n_frames), save_every=int(save_every), observe=observe, separation=bool(separation))
        timing = None
    else:
        if pad_to < n_frames:
            raise ValueError(f"pad_to ({pad_to}) must be at least n_frames ({n_frames})")
        static = dict(n_frames=int(pad_to), save_every=0, observe=observe, separation=bool(separation))
        timing = [n_frames, save_every] + ([int(substeps)] if bsim.substeps is None else [])
        timing = jax.device_put(np.asarray(timing, np.int32))
    chunk = bsim.chunk or bsim.batch
    n = -(-batch // chunk)
    if batch == chunk:
        return _core_jit(bsim, params, state, health, step0, aux, timing, **static)
    # any other number of lanes runs as chunks of the compiled width (the last one padded): one
    # compiled core serves every lane count, so a call of a few points costs what its chunks do,
    # not the whole batch
    devices = local_devices()
    if len(devices) > 1:
        # several local devices: groups of one chunk per device, each group one sharded call
        # (dispatched asynchronously, one after another; the devices run a group's chunks at once)
        d = min(len(devices), n)
        groups = -(-n // d)
        mesh = _mesh(devices[:d])
        parts = _split((params, state, health, step0), groups, d * chunk)
        return _join([_sharded_jit(bsim, mesh, *part, aux, timing, **static) for part in parts], batch)
    parts = _split((params, state, health, step0), n, chunk)
    out = [None] * n
    todo = iter(range(1, n))
    lock = threading.Lock()

    def work():                       # run chunks until none is left, one at a time
        while True:
            with lock:
                i = next(todo, None)
            if i is None:
                return
            out[i] = jax.block_until_ready(_core_jit(bsim, *parts[i], aux, timing, **static))

    # Chunk 0 here first (it compiles, once), then this thread and (cores - 1) pool threads each
    # run one chunk at a time: as many chunks in flight as cores.
    out[0] = _core_jit(bsim, *parts[0], aux, timing, **static)
    helpers = [_executor().submit(work) for _ in range(min(_n_cores(), n) - 1)]
    jax.block_until_ready(out[0])
    work()
    for h in helpers:
        h.result()
    return _join(out, batch)


def positions_observer(params, i, x, aux):
    """``observe`` for :func:`rollout` keeping each frame's positions as (B, V, 3)."""
    return jnp.stack(x, axis=-1).transpose(1, 0, 2)


def locate_failures(bsim, params, health, substeps=None):
    """Find the exact failing step of every failed point by re-running it from its last healthy
    state one step at a time (points are independent, so all are re-run together).

    Returns:
      (step (O, B), code (O, B)) int numpy arrays: the first step at which each object of each
      point was unhealthy and why (-1 / diagnostics.OK where none). ``substeps``: as :func:`rollout`'s.
    """
    bad = np.asarray(health.bad_step)
    code = np.asarray(health.code)
    if not (bad >= 0).any():
        return bad, code
    start = np.asarray(health.good_step)
    span = int(np.max(np.where(bad >= 0, bad - start[None], 0)))
    fresh = initial_health(bsim, health.good_state, start)
    _, _, h = rollout(bsim, params, health.good_state, max(span, 1), 1, health=fresh, step0=start,
                      substeps=substeps)
    b, c = np.asarray(h.bad_step), np.asarray(h.code)
    found = (bad >= 0) & (b >= 0)
    # (found is all of bad >= 0 for a deterministic step; otherwise keep the frame-level record)
    return np.where(found, b, bad), np.where(found, c, code)


@functools.lru_cache(maxsize=None)
def _public_fn():
    return jax.jit(lambda x: jnp.stack(x, axis=-1).transpose(1, 0, 2))


def positions(state):
    """(B, V, 3) numpy positions of an internal state (or of its ``x`` tuple)."""
    x = state.x if isinstance(state, State) else state
    return np.asarray(_public_fn()(tuple(x)))
