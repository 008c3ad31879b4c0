"""Predictability: how far two runs of a scene that differ only by rounding drift apart.

Some motions are sensitive to their start: a torus or a bean dropped with the report's per-step
``damping`` (no dashpot) tumbles differently after a bounce, a bean hanging from one pinned
vertex swings chaotically. Two runs that differ by a rounding error then drift apart by
millimetres within a second. No fit can bring its residual below that drift, even at the true
parameters, so :func:`predictability` measures it before fitting:

* the scene is run twice in the working dtype, once as given and once from start positions
  moved by a relative :data:`PERTURBATION` (a seeded random direction, scaled per object by its
  size, the diagonal of its bounding box, and never below one float spacing at its largest
  coordinate, so the move survives rounding to the working dtype);
* with ``method="both"`` (or ``"x64"``) the scene is also run in float64 from the same start
  (``jax.enable_x64``, a program compiled of its own), and the drift of a frame is the larger
  of the two twins'. A float64 working dtype has no float64 twin: the perturbed run alone;
* the **drift** of a saved frame is the RMS over vertices, per coordinate, of the distance
  between the two runs (m; the measure of the fit's residual RMS,
  :func:`jaxplush.fitting.objective.losses.rms_metres`);
* the **threshold** is the noise sigma when given, else :data:`MOTION_FRACTION` of the motion
  (the RMS distance of the frames after the start from the start shape, the measure
  :mod:`jaxplush.fitting.judge.outcome` calls the motion);
* the **horizon** is the first saved frame whose drift exceeds the threshold (none: the whole
  run is predictable);
* the **floor** is the RMS of the drift over the saved frames after the start: the residual RMS
  a fit at the exact parameters would have against a target run like this one.

The runs are :func:`jaxplush.simulate` calls on one simulator (one compiled program for both),
or, given ``lanes``, the two working-dtype runs are lanes of one call of a caller's batched
program: a fit passes the batched simulator its search compiles anyway, so the measurement
compiles only its float64 twin.
"""

from __future__ import annotations

import dataclasses
import math
import time
import warnings
from typing import NamedTuple

import numpy as np

from jaxplush.errors import SimulationError

#: Relative size of the start perturbation (about float32's machine epsilon).
PERTURBATION = 1e-7
#: Threshold, as a fraction of the motion, for a run without a stated noise.
MOTION_FRACTION = 1e-3
#: "perturbed": two runs in the working dtype; "x64": the working dtype against float64;
#: "both": both twins, the larger drift at each frame.
METHODS = ("perturbed", "x64", "both")


@dataclasses.dataclass(frozen=True, eq=False)
class Predictability:
    """How predictable a run's positions are (module docstring).

    Attributes:
      times: (T,) saved frame times, s (frame 0 is the start); steps: (T,) their steps.
      drift_rms: (T,) RMS distance per coordinate between the two runs at each frame, m.
      motion_rms: (T,) RMS distance per coordinate of each frame from the start shape, m.
      motion: RMS of ``motion_rms`` over the frames after the start (or the value given), m.
      threshold: the drift above which positions count as unpredictable, m;
      threshold_kind: "noise" (the stated sigma) or "motion" (:data:`MOTION_FRACTION` of it).
      horizon_frame: index of the first frame whose drift exceeds the threshold, or None.
      horizon_time: its time, s (inf: never within the run).
      floor: RMS of the drift over the frames after the start, m.
      perturbation: RMS per coordinate of the start perturbation, m.
      method: the twins run (:data:`METHODS`); dtype: the working dtype's name.
      duration: the run's length, s; wall_time: seconds spent (compiles included).
      notes: messages of the runs (a volume clamp, a grown contact capacity).
    """

    times: np.ndarray
    steps: np.ndarray
    drift_rms: np.ndarray
    motion_rms: np.ndarray
    motion: float
    threshold: float
    threshold_kind: str
    horizon_frame: int | None
    horizon_time: float
    floor: float
    perturbation: float
    method: str
    dtype: str
    duration: float
    wall_time: float
    notes: tuple = ()

    @property
    def predictable(self):
        """True when the drift stays within the threshold for the whole run."""
        return self.horizon_frame is None

    def text(self):
        """One line for a person, e.g. "positions predictable to 0.1 mm for the first 0.4 s of 1 s; ..."."""
        within = f"positions predictable to {_mm(self.threshold)}"
        if self.predictable:
            span = f"{within} for the whole run ({self.duration:.4g} s)"
        else:
            span = f"{within} for the first {self.horizon_time:.4g} s of {self.duration:.4g} s"
        return f"{span}; the model's own reproducibility floor is {_mm(self.floor)} (residual RMS)"


def _mm(x):
    return f"{1e3 * x:.3g} mm"


def predictability(scene, steps, dt, save_every=None, *, params=None, integrator="verlet", substeps=1, sim=None,
                   noise=None, motion=None, method="both", seed=0, lanes=None):
    """Measure how far two runs of ``scene`` that differ only by rounding drift apart.

    Args:
      scene: :class:`jaxplush.scene.parse.Scene`; steps: number of time steps; dt: time step, s.
      save_every: steps between saved frames (default: about 100 frames; the last step is saved).
      params: :class:`jaxplush.types.Params` overriding the scene's values.
      integrator, substeps: as :func:`jaxplush.simulate`; sim: a prebuilt simulator for the scene
        and dt (its integrator and substeps are used).
      noise: the target's noise sigma per coordinate (m), the threshold when above 0.
      motion: the target's RMS motion (m) that sets the threshold without noise (default: the
        run's own).
      method: one of :data:`METHODS` (module docstring).
      seed: seed of the perturbation's direction.
      lanes: optional ``lanes(params, starts) -> (N, T, V, 3)`` positions of N runs of the working
        dtype from the start positions ``starts`` ((N, V, 3), zero velocity) at the saved steps
        after the start (``save_every``, ``2 save_every``, ..., ``steps``, a multiple of
        ``save_every``), or None where a run failed: then the runs are :func:`jaxplush.simulate`
        calls after all (which say why). Not for scenes with driven vertices.

    Returns:
      :class:`Predictability`.

    Raises:
      ValueError: a bad argument (before anything is traced).
      SimulationError: a run blew up (saying which run).
    """
    from jaxplush.model.forces import Terms
    from jaxplush.stepping.step import make_simulator
    steps, save_every = _check(steps, dt, save_every, integrator, substeps, noise, motion, method)
    if sim is not None and sim.dt != dt:
        raise ValueError(f"sim was built for dt = {sim.dt:g} s, not the dt = {dt:g} s given")
    t0 = time.perf_counter()
    sim = sim or make_simulator(scene, dt, integrator, terms=Terms.for_scene(scene, params), substeps=substeps)
    if method != "perturbed" and np.dtype(sim.dtype) == np.float64:
        method = "perturbed"                      # a float64 run has no float64 twin
    x0 = np.asarray(sim.topology.x0, np.float64)
    delta = perturbation(scene, x0, sim.dtype, seed)
    run = _runner(scene, steps, save_every, params)
    pair = _lanes_pair(scene, steps, save_every, params, sim, x0, delta, lanes, method)
    if pair is not None:
        base, twin = pair
        notes = ()
        drifts = [] if twin is None else [_rms(twin.positions - base.positions)]
    else:
        base, notes = run(sim, None, "unperturbed")
        drifts = []
        if method in ("perturbed", "both"):
            twin, more = run(sim, x0 + delta, "perturbed")
            drifts.append(_rms(twin.positions - base.positions))
            notes += more
    if method in ("x64", "both"):
        twin, more = _run_x64(scene, sim, run)
        drifts.append(_rms(twin.positions - base.positions))
        notes += more
    drift = np.max(drifts, axis=0)
    return _result(base, drift, float(_rms(delta[None])[0]), noise, motion, method, sim.dtype,
                   time.perf_counter() - t0, tuple(dict.fromkeys(notes)))


class _Frames(NamedTuple):
    """The parts of a :class:`jaxplush.Trajectory` the measurement reads, of runs made by ``lanes``."""
    positions: np.ndarray
    times: np.ndarray
    steps: int
    dt: float
    save_every: int


def _lanes_pair(scene, steps, save_every, params, sim, x0, delta, lanes, method):
    """(base, perturbed twin or None) run as lanes of ``lanes`` (see :func:`predictability`),
    each with its start as frame 0; None without ``lanes``, for a scene with driven vertices
    (whose start is its paths' and not the rest shape), or where a lane failed."""
    if lanes is None or scene.driven or steps % save_every:
        return None
    starts = [x0] + ([x0 + delta] if method in ("perturbed", "both") else [])
    starts = np.asarray(np.stack(starts), np.dtype(sim.dtype))
    out = lanes(params, starts)
    n = steps // save_every
    if out is None or np.shape(out) != (len(starts), n) + x0.shape or not np.isfinite(out).all():
        return None
    times = np.arange(n + 1, dtype=np.float64) * save_every * sim.dt
    runs = [_Frames(np.concatenate([starts[i][None].astype(np.float64), np.asarray(out[i], np.float64)]),
                    times, steps, sim.dt, save_every) for i in range(len(starts))]
    return runs[0], (runs[1] if len(runs) > 1 else None)


def _check(steps, dt, save_every, integrator, substeps, noise, motion, method):
    """Validated (steps, save_every); ValueError naming the first bad argument."""
    from jaxplush.stepping.step import INTEGRATORS
    if isinstance(steps, bool) or int(steps) != steps or not 1 <= int(steps) < 2 ** 31:
        raise ValueError(f"steps must be an integer between 1 and 2**31 - 1, got {steps!r}")
    steps = int(steps)
    if not (isinstance(dt, (int, float, np.floating, np.integer)) and math.isfinite(dt) and dt > 0):
        raise ValueError(f"dt must be a positive number of seconds, got {dt!r}")
    save_every = max(1, steps // 100) if save_every is None else save_every
    if isinstance(save_every, bool) or int(save_every) != save_every or int(save_every) < 1:
        raise ValueError(f"save_every must be an integer >= 1, got {save_every!r}")
    if integrator not in INTEGRATORS:
        raise ValueError(f"unknown integrator {integrator!r}; available: {', '.join(INTEGRATORS)}")
    if isinstance(substeps, bool) or int(substeps) != substeps or int(substeps) < 1:
        raise ValueError(f"substeps must be an integer >= 1, got {substeps!r}")
    for name, val in (("noise", noise), ("motion", motion)):
        if val is not None and not (math.isfinite(val) and val >= 0):
            raise ValueError(f"{name} must be a number >= 0 (m) or None, got {val!r}")
    if method not in METHODS:
        raise ValueError(f"unknown method {method!r}; expected one of {', '.join(METHODS)}")
    return steps, int(save_every)


def perturbation(scene, x0, dtype, seed=0):
    """(V, 3) start perturbation, m: a seeded normal direction, per object :data:`PERTURBATION`
    times its bounding-box diagonal per coordinate, and at least one float spacing of ``dtype``
    at the object's largest coordinate (a smaller move would round away in the working dtype)."""
    rng = np.random.default_rng(seed)
    d = rng.standard_normal(x0.shape)
    for o in scene.objects:
        a, b = o.vertex_slice
        x = x0[a:b]
        size = float(np.linalg.norm(x.max(axis=0) - x.min(axis=0)))
        ulp = float(np.finfo(np.dtype(dtype)).eps) * float(np.max(np.abs(x)))
        d[a:b] *= max(PERTURBATION * size, ulp)
    return d


def _runner(scene, steps, save_every, params):
    """run(sim, x0, which) -> (Trajectory, notes): one quiet :func:`simulate`; a blow-up is
    re-raised saying which run of the measurement it was."""
    from jaxplush.stepping.simulation import simulate

    def run(sim, x0, which):
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            try:
                traj = simulate(scene, steps, sim.dt, save_every, params=params, x0=x0, sim=sim, check_dt=False)
            except SimulationError as e:
                raise _which(e, which) from e
        if not np.isfinite(traj.positions).all():       # (the health checks catch this first)
            t = int(np.argmax(~np.isfinite(traj.positions).all(axis=(1, 2))))
            raise _which(SimulationError(int(round(traj.times[t] / sim.dt)), 0, scene.object_names[0],
                                         "non-finite positions"), which)
        return traj, tuple(str(w.message) for w in caught)
    return run


def _which(e, which):
    """``e`` with the run of the measurement it happened in added to its hint."""
    hint = e.hint
    where = f"in the {which} run of the predictability measurement"
    return SimulationError(e.step, e.object, e.object_name, e.reason, hint=f"{hint} ({where})" if hint else where)


def _run_x64(scene, sim, run):
    """The float64 twin: the same simulator rebuilt (and compiled) in float64, run from the scene's start."""
    import jax
    from jaxplush.stepping.step import make_simulator
    with jax.enable_x64(True):
        sim64 = make_simulator(scene, sim.dt, sim.integrator, terms=sim.terms, substeps=sim.substeps)
        return run(sim64, None, "float64")


def _rms(d):
    """(T,) RMS per coordinate over vertices of (T, V, 3) differences, m."""
    d = np.asarray(d, np.float64)
    return np.sqrt(np.mean(np.sum(d * d, axis=-1), axis=-1) / 3.0)


def _saved_steps(traj):
    """(T,) int64 step of each saved frame of a Trajectory (every save_every, and the last step)."""
    saved = np.arange(len(traj.times), dtype=np.int64) * traj.save_every
    saved[-1] = traj.steps
    return saved


def _result(base, drift, delta_rms, noise, motion, method, dtype, wall, notes):
    """The :class:`Predictability` of a run (``base``, its Trajectory) and its per-frame drift."""
    x = base.positions.astype(np.float64)
    motion_rms = _rms(x - x[:1])
    after = base.times > 0
    if motion is None:
        motion = float(np.sqrt(np.mean(motion_rms[after] ** 2)))
    if noise is not None and noise > 0:
        threshold, kind = float(noise), "noise"
    else:
        # a run that does not move: the start shape's own spread sets the scale
        scale = motion if motion > 0 else float(np.sqrt(np.mean(np.var(x[0], axis=0))))
        threshold, kind = MOTION_FRACTION * scale, "motion"
    over = np.nonzero(after & (drift > threshold))[0]
    frame = int(over[0]) if over.size else None
    return Predictability(
        times=np.asarray(base.times, np.float64), steps=_saved_steps(base),
        drift_rms=drift, motion_rms=motion_rms, motion=float(motion), threshold=threshold, threshold_kind=kind,
        horizon_frame=frame, horizon_time=float(base.times[frame]) if frame is not None else math.inf,
        floor=float(np.sqrt(np.mean(drift[after] ** 2))), perturbation=delta_rms, method=method,
        dtype=np.dtype(dtype).name, duration=float(base.steps * base.dt), wall_time=float(wall), notes=notes)
