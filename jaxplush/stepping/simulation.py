"""High-level driver: ``simulate(scene, steps, dt, save_every) -> Trajectory``."""

from __future__ import annotations

import dataclasses
import time
import warnings

import jax
import numpy as np

from jaxplush.stepping import compiled
from jaxplush.stepping import diagnostics
from jaxplush.stepping import rollouts as _rollout
from jaxplush.stepping import stability
from jaxplush.errors import (ContactCapacityWarning, Note, SimulationError, TimeStepWarning,
                             VolumeClampWarning)
from jaxplush.errors import warn as _warn
from jaxplush.model.forces import Terms
from jaxplush.progress import Progress
from jaxplush.stepping.step import make_simulator


@dataclasses.dataclass(frozen=True, eq=False)
class Trajectory:
    """Saved frames of a run (numpy), with what is needed to reproduce it.

    Attributes:
      positions: (T, V, 3) positions at ``times``; frame 0 is the initial state.
      times: (T,) seconds.
      faces, object_id, object_names: the scene's topology.
      volumes: (T, O) enclosed volume of each object per frame.
      params: per-object parameters used (numpy Params).
      dt, steps, save_every, integrator, floor, gravity, temperature, scene_text, scene_path.
      wall_time: seconds spent running (compilation included).
      warnings: messages about the run (e.g. the volume clamp), already issued as warnings.
      substeps: integrator steps per time step dt (each dt / substeps long).
    """

    positions: np.ndarray
    times: np.ndarray
    faces: np.ndarray
    object_id: np.ndarray
    object_names: tuple
    volumes: np.ndarray
    params: object
    dt: float
    steps: int
    save_every: int
    integrator: str
    floor: object
    gravity: np.ndarray
    temperature: float
    scene_text: str
    scene_path: str
    wall_time: float
    warnings: tuple = ()
    substeps: int = 1

    def save(self, path):
        from jaxplush.io.trajectory import save_trajectory
        return save_trajectory(self, path)


def simulate(scene, steps, dt, save_every=None, integrator="verlet", params=None, x0=None, v0=None,
             progress=False, check_dt=True, sim=None, substeps=1):
    """Simulate a scene and return its saved frames.

    Args:
      scene: :class:`jaxplush.scene.parse.Scene` (from :func:`jaxplush.load_scene`).
      steps: number of time steps.
      dt: time step, s.
      save_every: steps between saved frames (default: about 100 frames in all). The last
        step is always saved.
      integrator: integrator name (see :data:`jaxplush.stepping.step.INTEGRATORS`).
      params: :class:`jaxplush.types.Params` overriding the scene's values.
      x0, v0: (V, 3) initial positions/velocities (default: the scene's, at rest).
      progress: draw a progress bar on stderr.
      check_dt: warn when dt / substeps exceeds the integrator's estimated stability limit.
      sim: a prebuilt :class:`jaxplush.stepping.step.Simulator` to reuse (must match scene and dt; its
        integrator and substeps are used).
      substeps: integrator steps of dt / substeps per time step (the floor and pins act after
        each).

    Returns:
      :class:`Trajectory`.

    Soft-soft contact keeps fixed-capacity candidate lists (:mod:`jaxplush.model.contact`); if a pair
    overflows them (the rollout's health code ``diagnostics.CONTACT_OVERFLOW``), the run is
    repeated with a larger capacity (up to :data:`MAX_CAPACITY_RETRIES` times), with a warning
    naming the capacity to set in the scene.

    Raises:
      SimulationError: the run blew up (which step, which object, why).
    """
    sim = sim or make_simulator(scene, dt, integrator, terms=Terms.for_scene(scene, params), substeps=substeps)
    traj, _, notes = _growing_capacity(scene, sim, lambda s, retry: _simulate(
        scene, steps, save_every, params, x0, v0, progress, check_dt, s, retry=retry), warn=True)
    return dataclasses.replace(traj, warnings=notes + traj.warnings) if notes else traj


#: How often :func:`simulate` raises the contact capacity and reruns before giving up.
MAX_CAPACITY_RETRIES = 4


def _growing_capacity(scene, sim, run, warn):
    """``run(sim, retry)``, rerun with a simulator of larger soft-soft contact capacity after each
    overflow (up to MAX_CAPACITY_RETRIES times; the last try reports an overflow as a failure).
    Returns (run's result, the simulator it succeeded with, the messages about the reruns)."""
    notes = ()
    for attempt in range(MAX_CAPACITY_RETRIES + 1):
        try:
            return run(sim, attempt < MAX_CAPACITY_RETRIES), sim, notes
        except _CapacityOverflow as e:
            # The candidate lists of soft-soft contact were too short: the step cannot be exact.
            # The result does not depend on the capacity, so rerun with a larger one.
            from jaxplush.model import contact
            need = contact.grown_capacity(e.need)
            msg = (f"contact candidates overflowed at step {e.step} ({e.need} needed, capacity "
                   f"{max(sim.terms.contact.capacity)}); reran with contact_capacity {need} "
                   f"(set it in the scene to skip the rerun)")
            if warn:
                warnings.warn(msg, ContactCapacityWarning, stacklevel=3)   # the caller of simulate
            notes += (Note(msg, ContactCapacityWarning),)
            terms = contact.with_capacity(sim.terms, need, contact.object_sizes(scene))
            sim = make_simulator(scene, sim.dt, sim.integrator, terms=terms, substeps=sim.substeps)


def contact_capacity_needed(scene, steps, dt, params=None, sim=None):
    """The soft-soft contact capacity a run of ``steps`` steps needs, if ``sim``'s is too small.

    Runs the simulation as :func:`simulate` does (from the scene's rest state, with ``params``,
    raising the capacity after each overflow) and returns the capacity it finished with, or None
    when the scene has no soft-soft contact or the simulator's capacity never overflowed. A run
    that blows up for another reason ends the search (it returns what it has). For callers that
    build their own rollouts, such as :func:`fitting.fit`, which must rebuild with the capacity
    instead of rerunning (its rollouts report an overflow as the ``CONTACT_OVERFLOW`` health code,
    and its losses as NaN).

    Args:
      scene: :class:`jaxplush.scene.parse.Scene`; steps: number of time steps; dt: time step, s.
      params: :class:`jaxplush.types.Params` overriding the scene's values.
      sim: the :class:`jaxplush.stepping.step.Simulator` whose capacity is in question (default: built
        from the scene and dt).
    """
    sim = sim or make_simulator(scene, dt, terms=Terms.for_scene(scene, params))
    if sim.terms.contact is None:
        return None
    start = max(sim.terms.contact.capacity)
    last = [sim]

    def run(s, retry):
        last[0] = s
        _simulate(scene, steps, int(steps), params, None, None, False, False, s, retry=retry)

    try:
        _growing_capacity(scene, sim, run, warn=False)
    except SimulationError:
        pass                            # a blow-up of another kind (or still too short): as far as it got
    cap = max(last[0].terms.contact.capacity)
    return None if cap == start else cap


class _CapacityOverflow(Exception):
    def __init__(self, step, need):
        super().__init__(f"contact capacity overflow at step {step}: {need} candidates needed")
        self.step, self.need = step, need


def _simulate(scene, steps, save_every, params, x0, v0, progress, check_dt, sim, retry=True):
    steps = int(steps)
    if not 1 <= steps < 2 ** 31:
        raise ValueError(f"steps must be between 1 and 2**31 - 1 (the step counters are int32), got {steps}")
    if save_every is None:
        save_every = max(1, steps // 100)
    save_every = int(save_every)
    if save_every < 1:
        raise ValueError(f"save_every must be >= 1, got {save_every}")
    t0 = time.perf_counter()
    p = sim.params(params)
    notes = []
    if check_dt:
        msg = stability.check_dt(sim, p)
        if msg:
            notes.append(_warn(msg, TimeStepWarning, stacklevel=2))
    # explicit arrays, so a default and a given initial state share one compiled init
    x0 = np.asarray(sim.topology.x0 if x0 is None else x0, np.float64)
    v0 = np.zeros_like(x0) if v0 is None else np.asarray(v0, np.float64)
    # one compile per program; at XLA's default optimisation (not jit_once's level 0), so that
    # simulate's runs are bit for bit those of earlier versions: a reference run or a target
    # made by simulate does not move by a rounding when the code is updated
    init = compiled.get(sim, "init", lambda: jax.jit(sim.init_fn))
    state = init(p, x0, v0)
    health = _rollout.initial_health(sim, state)
    x_init = state.x
    frames, volumes = [], []                 # (n, V, 3) host frames of each chunk; their volumes
    n_full, rem = divmod(steps, save_every)
    # Chunks of equal size reuse one compiled rollout; about 50 updates of the progress bar.
    per_chunk = max(1, n_full // 50) if progress else max(n_full, 1)
    chunks = [(min(per_chunk, n_full - done), save_every, done * save_every) for done in range(0, n_full, per_chunk)]
    if rem:
        chunks.append((1, rem, n_full * save_every))

    def volumes_so_far():
        for block in frames[len(volumes):]:
            volumes.append([scene.volumes(x) for x in block])

    def take(chunk_frames, chunk_health, n_steps, queued):
        """The host's part of a finished chunk: its frames and the progress bar; while another
        chunk is ``queued`` behind it and the run is healthy (so the frames are finite), also
        the volumes of the frames so far. Returns whether the run has failed."""
        if not frames:
            frames.append(np.asarray(x_init)[None])
        frames.append(np.asarray(chunk_frames))
        bar.update(n_steps)
        if chunk_health.failed:
            return True
        if queued:
            volumes_so_far()
        return False

    with Progress(steps, "simulate", enabled=progress) as bar:
        # each chunk is queued behind the one before, and only then does the host take that one:
        # the rollouts run back to back while the host copies frames and draws the bar
        last = None
        for n, every, step0 in chunks:
            out = _rollout.rollout(sim, p, state, n, every, health=health, step0=step0)
            if last is not None and take(*last, queued=True):
                break                        # the previous chunk failed: this one goes unused
            state, fr, health = out
            last = (fr, health, n * every)
        else:
            take(*last, queued=False)
    jax.block_until_ready(state)
    wall = time.perf_counter() - t0
    if health.failed:
        rerun = _rollout.rerun_from_good(sim, p, health)
        step, obj, code = _rollout.locate_failure(sim, p, health, rerun=rerun)
        bad, codes = np.asarray(health.bad_step), np.asarray(health.code)
        first = (bad >= 0) & (bad == bad[bad >= 0].min())
        if (first & (codes == diagnostics.CONTACT_OVERFLOW)).any():
            # Soft-soft contact candidates overflowed (a status of the rollout, not a NaN): find the
            # capacity the states from the last healthy one to the failure need.
            step, obj, need, report = _overflow_need(sim, health, rerun, step, obj, code, first, codes)
            if retry:
                raise _CapacityOverflow(step, need)
            raise SimulationError(step, obj, scene.objects[obj].name,
                                  diagnostics.MESSAGES[diagnostics.CONTACT_OVERFLOW], hint=report)
        # (the stability hint compiles an estimate: only for a failure that is reported)
        raise SimulationError(step, obj, scene.objects[obj].name, diagnostics.MESSAGES[code], hint=_hint(sim, p))
    positions = np.concatenate(frames, axis=0)
    saved = np.arange(len(positions)) * save_every
    saved[-1] = steps
    warn = np.asarray(health.warn_step)
    for o in np.nonzero(warn >= 0)[0]:
        msg = (f"object {scene.objects[o].name!r}: {diagnostics.MESSAGES[diagnostics.VOLUME_CLAMPED]} "
               f"(first seen at step {int(warn[o])})")
        notes.append(_warn(msg, VolumeClampWarning, stacklevel=2))
    volumes_so_far()
    return Trajectory(
        positions=positions, times=saved * sim.dt, faces=scene.faces, object_id=scene.object_id,
        object_names=scene.object_names, volumes=np.stack([v for block in volumes for v in block]),
        params=p.as_numpy(), dt=sim.dt, steps=steps, save_every=save_every, integrator=sim.integrator,
        floor=scene.floor, gravity=scene.gravity, temperature=scene.temperature, scene_text=scene.text,
        scene_path=scene.path, wall_time=wall, warnings=tuple(notes), substeps=sim.substeps)


def _overflow_need(sim, health, rerun, step, obj, code, first, codes):
    """(step, object, capacity needed, report) of a contact overflow the rollout's health reports.

    The candidate counts are those of a fresh search (:func:`jaxplush.model.contact.needed_capacity`) at
    every state from the last healthy one to the failure (the step-by-step re-run of
    :func:`jaxplush.stepping.rollouts.rerun_from_good`); the capacity needed is at least one above the
    current, so a rerun always grows it."""
    from jaxplush.model import contact
    start, frames, _ = rerun
    if code != diagnostics.CONTACT_OVERFLOW:
        # the re-run's freshly built lists did not overflow first: report the saved frame's record
        obj = int(np.argmax(first & (codes == diagnostics.CONTACT_OVERFLOW)))
        step = int(np.asarray(health.bad_step)[obj])
    last = max(step, int(np.asarray(health.bad_step)[first][0])) - start
    states = [np.asarray(health.good_state.x)] + list(np.asarray(frames[:last]))
    states = [x for x in states if np.isfinite(x).all()]
    counts = [contact.needed_capacity(sim, x) for x in states]
    cap = max(sim.terms.contact.capacity)
    need = max(counts + [cap + 1])
    report = next((r for r in (contact.capacity_report(sim, x) for x in states[::-1]) if r), None)
    if report is None:
        report = f"raise 'contact_capacity' above {cap}"
    return step, obj, need, report


def _hint(sim, params):
    if sim.integrator in stability.UNCONDITIONAL:
        return "try a smaller dt or more substeps"
    try:
        limit = stability.integrator_limit(stability.estimate(sim, params), sim.integrator)
    except Exception:  # the hint is a courtesy; never mask the real error
        return "try a smaller dt"
    used = f"dt/substeps = {sim.h:g} s" if sim.substeps > 1 else f"dt = {sim.dt:g} s"
    return f"estimated stable {sim.integrator} step limit is {limit:.3g} s (this run used {used})"
