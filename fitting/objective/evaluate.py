"""Residuals of a fit at many parameter points at once, every point simulated stably.

:class:`Evaluator` runs a :class:`jaxplush.fitting.objective.problem.Problem` at N points theta (log-parameters)
and returns each point's residual vector (:func:`jaxplush.fitting.objective.losses.make_residual`: sum(r²) is the
fit's loss), its loss and whether it ran. Points run in compiled batches of the batched
simulator (:mod:`jaxplush.stepping.batched`, one compile per batch width and substep count) where the
scene allows it (Verlet, at most 8 runs of equally spaced target frames; soft-soft contact
included), otherwise one at a time. A point whose contact candidates overflow their capacity is
run again with a grown capacity (:meth:`Evaluator._frames_batched`).

Stability: before a point runs, its explicit stability limit is predicted from the closed-form
bound (:func:`jaxplush.stepping.stability.bound`, O(V) numpy), calibrated once against the power-iteration
estimate at the start values; a point whose limit is below the target's dt runs with substeps
(h = dt / n, n a power of two; the target grid does not change, and the report's per-step
``damping`` keeps its meaning per dt, :func:`jaxplush.stepping.integrators.damping_keep`). A point that
blows up anyway is run again with twice the substeps, up to :data:`MAX_SUBSTEPS`; only a point
that fails even then is reported as failed (``ok`` False, loss inf), never as NaN residuals
that an optimiser would read as data.
"""

from __future__ import annotations

import functools
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxplush.errors import ContactCapacityWarning, warn
from jaxplush.stepping import batched
from jaxplush.stepping import diagnostics
from jaxplush.stepping import stability
from jaxplush.types import Params

from jaxplush.fitting.objective import losses as _losses

#: Largest substep count a point may be run with.
MAX_SUBSTEPS = 16
#: Times the batched path grows the soft-soft contact capacity for one call's overflowing points
#: before it runs those still overflowing one at a time.
MAX_CAPACITY_GROWTHS = 3
#: Points simulated together by the batched simulator, in two chunks run on two cores: a call
#: of 32 points at 642 vertices costs little more than one of 16 (see benchmarks/RESULTS.md); above
#: LARGE_MESH vertices the chunks outgrow the caches and 16 points a call are cheaper.
DEFAULT_BATCH = 32
LARGE_MESH = 1500
#: With soft-soft contact, scenes of at least this many vertices (and at most LARGE_MESH) run in
#: chunks of 16 points, their calls of a few points on a narrow simulator (:meth:`Evaluator._chunk`).
CONTACT_WIDE_MESH = 600


class Evaluation(NamedTuple):
    """Results at N points.

    Attributes:
      residuals: (N, n) float64 normalised residuals (rows of failed points are NaN).
      loss: (N,) float64 sum of squared residuals (inf where the point failed).
      ok: (N,) bool, the point ran without blowing up.
      substeps: (N,) int, the substeps it ran with.
      clamped: (N,) bool, the volume clamp was active at a target frame.
      frames: (N, T, V, 3) float64 simulated positions at the target frames, if asked for.
      separation: (N,) float64, with soft-soft contact between several objects on the batched
        simulator: the closest the bounding boxes of any contact pair came over every step of the
        run, in units of that pair's contact reach (2 thicknesses); NaN where not measured (a
        point run one at a time), None without such pairs. Above 1 + CLEARANCE_SAFETY
        (:mod:`jaxplush.fitting.stages.objects`), no object felt another.
    """

    residuals: np.ndarray
    loss: np.ndarray
    ok: np.ndarray
    substeps: np.ndarray
    clamped: np.ndarray
    frames: np.ndarray | None = None
    separation: np.ndarray | None = None


def _runs(steps):
    """[(gap, count), ...]: the target steps as runs of equal gaps from step 0."""
    out = []
    prev = 0
    for s in steps:
        g = int(s) - prev
        prev = int(s)
        if out and out[-1][0] == g:
            out[-1][1] += 1
        else:
            out.append([g, 1])
    return [tuple(r) for r in out]


def _pad_frames(a, size, axis):
    """``a`` padded to ``size`` frames along ``axis`` with copies of its last frame."""
    short = size - a.shape[axis]
    if short <= 0:
        return a
    last = np.take(a, [-1], axis=axis)
    return np.concatenate([a, np.repeat(last, short, axis=axis)], axis=axis)


def _pow2_at_least(n):
    return 1 << max(int(math.ceil(n)) - 1, 0).bit_length()


class Evaluator:
    """Evaluate a problem's residuals at many points (see the module docstring).

    Args:
      prob: :class:`jaxplush.fitting.objective.problem.Problem`.
      batch: points per batched call (static; default :data:`DEFAULT_BATCH`, half that above
        :data:`LARGE_MESH` vertices).
      calibrate: calibrate the closed-form stability bound against the power-iteration estimate
        at the start values (one compile); False uses the bound alone (more substeps than needed).
      calibration: a calibration to reuse (:meth:`calibration` of an evaluator of the same scene).
      share: an evaluator of the same scene and dt (another horizon of the same fit) whose
        compiled batched simulators this one reuses.
      chunk_frames: run the target's frames in chunks of this many, every chunk on one compiled
        rollout of this many frames (with the chunk's length and spacing as data), for every
        horizon; None: that of ``share`` (the same program), else each run of frames in one piece.
    """

    def __init__(self, prob, batch=None, calibrate=True, calibration=None, share=None, chunk_frames=None):
        self.prob = prob
        if batch is None:
            batch = DEFAULT_BATCH if prob.scene.n_vertices <= LARGE_MESH else DEFAULT_BATCH // 2
        self.batch = int(batch)
        self.residual = _losses.make_residual(prob.target, prob.sim.topology, prob.loss)
        self.steps = np.asarray(prob.loss.frame_steps, np.int64)
        self.runs = _runs(self.steps)
        sim = prob.sim
        self.batched = sim.integrator == "verlet" and len(self.runs) <= 8 and _batchable(sim.terms)
        # batched simulators depend on the scene, dt, terms, substeps and width, not on the
        # target's frames: evaluators of one fit over different horizons share them (``share``),
        # and run their frames in chunks of ``chunk_frames``, so one compiled rollout serves all
        self._bsims = share._bsims if share is not None else {}
        if chunk_frames is None and share is not None:
            chunk_frames = share.chunk_frames
        self.chunk_frames = int(chunk_frames) if chunk_frames else None
        self._single = {}
        self._forward = None            # (problem, compiled forward-mode Jacobian): forward_jacobian
        # residuals in chunks of frames, by one compiled function per chunk length and width that
        # the evaluators of a fit's horizons share (the target data is an argument, not a constant)
        self._res_fns = share._res_fns if share is not None else {}
        self._calibration = calibration
        self._calibrate = calibrate
        self.notes = []               # messages about the run (a grown contact capacity)
        self.evaluations = 0          # points run (each substep retry counted)
        self.colour_misses = 0        # coloured Jacobian stencils that came near contact (search.py)
        self._owners = False          # residual owners, computed on first use (:meth:`owners`)
        # per contact pair, its reach (2 thicknesses): the batched runs measure how close pairs
        # come, in these units (Evaluation.separation)
        cfg = sim.terms.contact
        self._contact = self.batched and cfg is not None and bool(cfg.pairs)
        self._reach = (2.0 * np.asarray(cfg.thickness, np.float64)[:, None]
                       if self._contact and len(prob.objects) > 1 else None)

    # ------------------------------------------------------------------ stability

    def calibration(self):
        """(c_omega, c_gamma) of this evaluator (computed if needed), to share with another."""
        return self._calibrated()

    def _calibrated(self):
        """(c_omega, c_gamma): exact / bound at the start values (<= 1), computed once."""
        if self._calibration is None:
            if not self._calibrate or self.prob.sim.integrator != "verlet":
                self._calibration = (1.0, 1.0)
            else:
                p0 = self.prob.params_at(self.prob.theta0)
                b = stability.bound(self.prob.sim, p0)
                e = stability.estimate(self.prob.sim, self.prob.sim.params(p0))
                cw = min(1.0, e.omega_max / b.omega_max) if b.omega_max > 0 else 1.0
                cg = min(1.0, e.gamma_forces / b.gamma_forces) if b.gamma_forces > 0 else 1.0
                self._calibration = (cw if np.isfinite(cw) else 1.0, cg if np.isfinite(cg) else 1.0)
        return self._calibration

    def limit(self, theta):
        """Predicted largest stable (sub)step at log values theta, s."""
        cw, cg = self._calibrated()
        lim = stability.calibrated_limit(self.prob.sim, self.prob.params_at(theta), cw, cg)
        return lim if np.isfinite(lim) or lim == math.inf else 0.0

    def substeps_for(self, thetas):
        """(N,) substeps (powers of two, at least 1) that keep each point below its limit."""
        dt = self.prob.target.dt
        out = []
        for th in thetas:
            lim = self.limit(th)
            n = MAX_SUBSTEPS if lim <= 0 else _pow2_at_least(dt / lim)
            out.append(int(min(max(n, 1), MAX_SUBSTEPS)))
        return np.asarray(out, np.int64)

    def forward_jacobian(self, theta, substeps=1):
        """(n, P) exact Jacobian of the residuals at one point theta (P_n, O_f) in log space, by
        forward mode: one rollout of ``prob.frames`` with P tangents beside it (vmapped JVPs; one
        compile per evaluator). None where it does not apply or did not run: a point that needs
        substeps (``substeps`` > 1, or its predicted count), a rollout whose health codes flag
        a blow-up, or non-finite entries; the caller then takes differences."""
        th = np.asarray(theta, np.float64)
        if substeps > 1 or int(self.substeps_for(th[None])[0]) > 1:
            return None
        fwd = self._forward
        if fwd is None or fwd[0] is not self.prob:       # a grown contact capacity makes a new problem
            prob, res, shape = self.prob, self.residual, th.shape

            def run(flat):
                def f(t):
                    frames, codes = prob.frames(t.reshape(shape))
                    return res.fn(frames), codes
                basis = jnp.eye(flat.size, dtype=flat.dtype)
                _, tangents, codes = jax.vmap(lambda t: jax.jvp(f, (flat,), (t,), has_aux=True),
                                              out_axes=(None, 0, None))(basis)
                return tangents, codes
            fwd = self._forward = (prob, jax.jit(run))
        tangents, codes = fwd[1](jnp.asarray(th.ravel(), self.prob.sim.dtype))
        jac = np.asarray(tangents, np.float64).T
        if np.any(np.asarray(codes) >= diagnostics.NON_FINITE) or not np.isfinite(jac).all():
            return None
        return jac

    # ------------------------------------------------------------------ running

    def __call__(self, thetas, substeps=None, keep_frames=False, retries=None):
        """Evaluate N points.

        Args:
          thetas: (N, P_n, O_f) log-parameters (any leading count).
          substeps: (N,) substeps to start from (default: predicted, :meth:`substeps_for`);
            a point that blows up is retried with twice as many, up to :data:`MAX_SUBSTEPS`.
          keep_frames: also return the simulated frames.
          retries: a point is retried at most this many times (None: up to :data:`MAX_SUBSTEPS`).
            A global search's design needs no point at any price: each further substep count is
            one more compiled simulator (5-20 s with contact), for a point or two.

        Returns:
          :class:`Evaluation`.
        """
        thetas = np.asarray(thetas, np.float64)
        n_pts = len(thetas)
        subs = self.substeps_for(thetas) if substeps is None else np.asarray(substeps, np.int64).copy()
        res = np.full((n_pts, self.residual.n), np.nan)
        ok = np.zeros(n_pts, bool)
        clamped = np.zeros(n_pts, bool)
        separation = None if self._reach is None else np.full(n_pts, np.nan)
        frames = None
        todo = np.arange(n_pts)
        inverted = np.full(n_pts, -1, np.int64)          # the step a point's volume inverted at, -1: not so
        tries = np.zeros(n_pts, np.int64)
        while todo.size:
            retry = []
            for n in np.unique(subs[todo]):
                idx = todo[subs[todo] == n]
                fr, good, clamp, sep, inv = self._frames(thetas[idx], int(n))
                if good.any():
                    r = self._residuals(fr[good])
                    res[idx[good]] = r
                    ok[idx[good]] = np.isfinite(r).all(axis=1)
                    clamped[idx[good]] = clamp[good]
                    if separation is not None:
                        separation[idx[good]] = sep[good]
                    if keep_frames:
                        if frames is None:
                            frames = np.full((n_pts,) + fr.shape[1:], np.nan)
                        frames[idx[good]] = fr[good]
                for i, at in zip(idx[~good], inv[~good]):
                    # a volume that inverted no later with twice the substeps was crushed, not
                    # unstable: more substeps would only cost more (seconds per retry at 2000
                    # vertices with contact)
                    persistent = at >= 0 and 0 <= inverted[i] and at <= inverted[i]
                    inverted[i] = at
                    if subs[i] < MAX_SUBSTEPS and not persistent and (retries is None or tries[i] < retries):
                        subs[i] *= 2
                        tries[i] += 1
                        retry.append(i)
            todo = np.asarray(retry, np.int64)
        loss = np.where(ok, np.sum(np.where(np.isfinite(res), res, 0.0) ** 2, axis=1), np.inf)
        res[~ok] = np.nan
        return Evaluation(res, loss, ok, subs, clamped, frames, separation)

    # ------------------------------------------------------------------ per-object structure

    def owners(self):
        """(n,) the fitted object each residual belongs to (-1: an object not fitted), when the
        residuals are vertex or track positions of more than one fitted object; else None. What a coloured
        finite-difference Jacobian (:func:`jaxplush.fitting.stages.search.jacobian`) needs."""
        if self._owners is False:
            from jaxplush.fitting.objective import objects as _objects
            prob = self.prob
            self._owners = (_objects.residual_objects(prob) if len(prob.objects) > 1
                            and prob.target.kind.material_points else None)
        return self._owners

    def colourable(self):
        """Whether coloured Jacobian stencils (:func:`jaxplush.fitting.stages.search.jacobian`) can serve this
        problem: several fitted objects, and residuals that each belong to one of them, fixed for
        a position target (:meth:`owners`), or read off each run's frames for a point cloud
        (:meth:`point_owners`)."""
        return len(self.prob.objects) > 1 and (self.owners() is not None or self.residual.near_fn is not None)

    def point_owners(self, frames):
        """(N, n) for a point-cloud target: the fitted object (an index into ``prob.objects``; -1: an
        object not fitted) of the vertex each point's residual is measured from, in N runs' frames
        ((N, T, V, 3), as :meth:`__call__` keeps them). A point's residual depends on that object's
        motion alone."""
        from jaxplush.fitting.objective import objects as _objects
        res = self.residual
        vobj = np.asarray(self.prob.sim.topology.vertex_object, np.int64)
        fitted = _objects.fitted_index(self.prob)
        x = np.asarray(frames)
        t = x.shape[1]
        size = self.chunk_frames or t
        key = ("near", size)
        if key not in self._res_fns:
            self._res_fns[key] = jax.jit(res.near_fn)
        dtype = self.prob.sim.dtype
        out = np.empty((len(x), res.n), np.int64)
        for i in range(len(x)):
            cols = []
            for a in range(0, t, size):
                c = min(size, t - a)
                xs, ys = _pad_frames(x[i, a:a + c], size, 0), _pad_frames(res.data[a:a + c], size, 0)
                near = np.asarray(self._res_fns[key](jnp.asarray(xs, dtype), jnp.asarray(ys, dtype)))
                cols.append(near[:c * res.per_frame])
            out[i] = fitted[vobj[np.concatenate(cols)]]
        return out

    def clear_by_separation(self, separation):
        """(N,) bool: runs that stayed clear of contact by their measured ``separation``
        (:func:`jaxplush.fitting.stages.objects.clear_by_separation`; NaN: not clear)."""
        from jaxplush.fitting.objective import objects as _objects
        return _objects.clear_by_separation(separation)

    def clear_frames(self, frames, ok, separation=None):
        """(N,) whether N runs ((N, T, V, 3) frames; ``ok``: which ran) stayed clear of contact: by
        their measured ``separation`` where every run that ran has one, else by the frames
        (:func:`jaxplush.fitting.stages.objects.clear_of_contact`). Runs that did not run are not clear."""
        from jaxplush.fitting.objective import objects as _objects
        ok = np.asarray(ok, bool)
        if not ok.any():
            return ok.copy()
        measured = _clear_measured(ok, separation)
        return measured if measured is not None else ok & _objects.clear_of_contact(self.prob, frames)

    def clear(self, residuals, separation=None):
        """(N,) whether, in the runs behind N rows of position residuals, no two objects came within
        reach of contact: from the ``separation`` measured at every step where given and finite
        (:class:`Evaluation`), else from the frames (:func:`jaxplush.fitting.stages.objects.clear_of_contact`;
        rebuilt from the residuals and the target). Failed rows (NaN) are not clear."""
        from jaxplush.fitting.objective import objects as _objects
        prob = self.prob
        r = np.asarray(residuals, np.float64)
        measured = _clear_measured(np.isfinite(r).all(axis=1), separation)
        if measured is not None:
            return measured
        data = np.asarray(prob.target.data, np.float64)
        t, m = data.shape[:2]
        frames = data[None] + r.reshape((len(r),) + data.shape) * np.sqrt(t * m * prob.loss.scale2)
        ok = np.isfinite(r).all(axis=1)
        return ok & _objects.clear_of_contact(prob, np.where(ok[:, None, None, None], frames, 0.0))

    def _residuals(self, frames):
        """(N, n) float64 residuals of (N, T, V, 3) frames, jitted over pieces of one batch (XLA
        spreads each piece over the cores), or of the narrow batch for a few points (as the batched
        simulator runs them: a local search's calls hold a few points, and residuals of padded
        copies cost as much as real ones; a point cloud's cost as much as its simulation)."""
        n_pts = len(frames)
        narrow = max(1, self.batch // 4)
        piece = narrow if n_pts <= narrow else self.batch
        pad = -n_pts % piece
        x = np.concatenate([frames, np.repeat(frames[-1:], pad, axis=0)]) if pad else frames
        dtype = self.prob.sim.dtype
        res = self.residual
        t = x.shape[1]
        size = self.chunk_frames or t
        out = []
        for i in range(0, len(x), piece):
            cols = []
            for a in range(0, t, size):
                c = min(size, t - a)
                # a last, shorter chunk is padded to the chunk length (one compiled function for
                # every chunk); the padding's columns are dropped
                xs, ys = _pad_frames(x[i:i + piece, a:a + c], size, 1), _pad_frames(res.data[a:a + c], size, 0)
                key = (piece, size, res.kind, res.normalisation, res.scale2)
                if key not in self._res_fns:
                    self._res_fns[key] = jax.jit(jax.vmap(res.frame_fn, in_axes=(0, None)))
                r = np.asarray(self._res_fns[key](np.asarray(xs, dtype), np.asarray(ys, dtype)), np.float64)
                cols.append(r[:, :c * res.per_frame])
            out.append(np.concatenate(cols, axis=1) * res.norm)
        return np.concatenate(out)[:n_pts]

    def _frames(self, thetas, n):
        """(frames (N, T, V, 3) float64, ok (N,), clamped (N,), separation (N,): NaN where not
        measured, inverted (N,): the step of a failure that was an inverted volume alone, -1
        otherwise) at ``n`` substeps."""
        self.evaluations += len(thetas)
        if self.batched:
            return self._frames_batched(thetas, n)
        fr, good, clamp, inv = self._frames_single(thetas, n)
        return fr, good, clamp, np.full(len(thetas), np.nan), inv

    def _chunk(self):
        """Points per compiled call of the batched simulator.

        With soft-soft contact between objects of at most :data:`LARGE_MESH` vertices in all:
        16 from :data:`CONTACT_WIDE_MESH` vertices up, whose contact term costs about half as much
        per point-step in chunks of 16 as in chunks of 4 once objects touch (its many small
        operations then serve 16 points a dispatch: 54 against 104 us at 964 vertices, 54 against
        118 at 1282), and about as much while they are apart (21 against 25 us on a pinned scene
        of 966; 3-5% more on another; benchmarks/RESULTS.md, "Chunks of 16 with contact"). Their
        calls of a few points (a local search's trial steps) then run on a narrow simulator of
        chunks of 4 (:meth:`_width`): one more compiled rollout and init, about 14 s cold, where
        a call of 3 points over seed 601's case 70's whole target takes 5.1 s instead of 13.7 s.
        Smaller contact scenes keep chunks of 4 and with them one simulator for every call (a
        fit of three 162-vertex objects stays within 20 s of compiles).
        Without contact: 8 with a dashpot (which gathers velocities too: a chunk of 16 outgrows
        the caches) and 16 without."""
        if self._contact and self.prob.scene.n_vertices <= LARGE_MESH:
            return 16 if self.prob.scene.n_vertices >= CONTACT_WIDE_MESH else 4
        return 8 if self.prob.sim.terms.dashpot else 16

    def _width(self, left, n=1):
        """The batch width of a call with ``left`` points still to run at ``n`` substeps: the full
        batch, or a narrow one (a quarter) for a remainder that fits in it (a local search's calls
        hold a few points, and a padded wide batch would simulate copies), unless the full batch
        runs in chunks as narrow as the narrow batch's: then it runs a few points as cheaply (only
        the lanes their chunks need), with no simulator of its own to compile. Runs at more than
        one substep (the few points the stability limit or a blow-up sends there) always take the
        narrow width, in as many calls as they need: the program the local search's few points
        run, the count being data of it (:meth:`_bsim`; a compile costs 5-20 s with contact,
        benchmarks/RESULTS.md)."""
        narrow = max(1, self.batch // 4)
        if self._chunk_of(self.batch) <= self._chunk_of(narrow):
            return self.batch
        return self.batch if left > narrow and n == 1 else narrow

    def _chunk_of(self, b):
        """The chunk of a batched simulator of width ``b``: on a CPU, two chunks at least, one per
        core; on another backend (a GPU) the whole width in one call, split over the local devices
        (batched.default_chunk)."""
        if not batched.on_cpu():
            return batched.default_chunk(b)
        return max(1, min(b // 2, self._chunk()))

    def _bsim(self, n, b):
        """(batched simulator, its jitted init) for ``n`` substeps and batch width ``b``: built once
        per process for a program (:func:`jaxplush.stepping.batched.shared_simulator`), so every
        evaluator of the scene (another horizon, the predictability measurement, a later fit)
        runs the same compiled code. The substep count is data of that program (``substeps=None``,
        the count given to each rollout): the points the stability limit or a blow-up sends to
        more substeps run the same compiled code as the rest (seed 601's case 70, three objects
        with contact, cold: 19.3 s of compiles, against 39.7 s with a program per count). Not with
        driven vertices, whose paths are tabulated per substep length: a simulator per count."""
        dynamic = not self.prob.sim.terms.driven
        key = (None if dynamic else n, b, self.prob.sim.terms, self.prob.target.dt)
        if key not in self._bsims:
            bsim = batched.shared_simulator(self.prob.scene, self.prob.target.dt, b, self.prob.sim.terms,
                                            None if dynamic else n, self._chunk_of(b))
            self._bsims[key] = (bsim, bsim.init_fn)
        bsim, init = self._bsims[key]
        return (bsim, functools.partial(init, substeps=int(n))) if dynamic else (bsim, init)

    def _frames_batched(self, thetas, n):
        """(frames, ok, clamped) of :meth:`_frames` on the batched simulator. Points whose soft-soft
        contact candidates overflowed (health code ``CONTACT_OVERFLOW``) are run again: the capacity
        is doubled (:meth:`_grow_contact`, a warning names it; later batches compile with it) and they rerun batched, up to :data:`MAX_CAPACITY_GROWTHS` times;
        any still overflowing then run one at a time (:meth:`_frames_single`, which grows on)."""
        fr, good, clamp, over, sep, inv = self._run_batches(thetas, n)
        for _ in range(MAX_CAPACITY_GROWTHS):
            idx = np.flatnonzero(over)
            if not idx.size or not self._grow_contact(thetas[idx[0]]):
                break
            fr[idx], good[idx], clamp[idx], over[idx], sep[idx], inv[idx] = self._run_batches(thetas[idx], n)
        idx = np.flatnonzero(over)
        if idx.size:
            fr[idx], good[idx], clamp[idx], inv[idx] = self._frames_single(thetas[idx], n)
            sep[idx] = np.nan
        return fr, good, clamp, sep, inv

    def _run_batches(self, thetas, n):
        """(frames, ok, clamped, overflowed (N,), separation (N,), inverted (N,)) of the points run
        in batches."""
        return self._run_lanes([self.prob.params_at(th) for th in thetas], n, self.runs, separation=True,
                               failures=True)

    def _run_lanes(self, values, n, runs, x0=None, v0=None, step0=None, separation=False, failures=False,
                   width=None):
        """(frames (N, T, V, 3), ok, clamped, overflowed) of N independent runs ("lanes") on the
        batched simulator at ``n`` substeps: lane i with parameter values ``values[i]``
        (:class:`Params` of numpy arrays), from positions ``x0[i]`` and velocities ``v0[i]``
        ((N, V, 3); None: the scene's start) at step ``step0[i]`` (None: 0), saving frames in
        ``runs`` [(gap, count), ...] (steps between frames, frames). With ``separation``, also
        (N,) the closest any contact pair came over the run's steps, in units of its reach
        (:class:`Evaluation`; NaN without such pairs); with ``failures``, then (N,) the step at
        which a lane failed by an inverted volume alone (-1: it did not, or failed otherwise).
        ``width``: the batch width to run at (default :meth:`_width`'s choice)."""
        out, good, clamp, over, seps, invs = [], [], [], [], [], []
        # the closest approach is measured in every run that can have one, asked for or not: one
        # compiled rollout serves both (its cost is a minimum over the pairs the contact finds)
        track = self._reach is not None
        n_lanes = len(values)
        start = 0
        while start < n_lanes:
            b = width or self._width(n_lanes - start, n)
            bsim, init = self._bsim(n, b)
            idx = np.arange(start, min(start + b, n_lanes))
            start += len(idx)
            live = len(idx)
            idx = np.concatenate([idx, np.repeat(idx[-1:], b - live)])        # pad with copies of the last
            p = bsim.params(Params(*(np.stack([np.asarray(getattr(values[i], f), np.float64) for i in idx], axis=1)
                                     for f in Params._fields)))
            start0 = np.zeros(len(idx), np.int32) if step0 is None else np.asarray(step0, np.int32)[idx]
            if x0 is None:
                # the rest shape at rest, given as every lane's start: one compiled init serves
                # these runs, multiple shooting's node states and the predictability's twins
                xs = np.broadcast_to(np.asarray(bsim.topology.x0, bsim.dtype), (b,) + np.shape(bsim.topology.x0))
                state = init(p, xs, np.zeros_like(xs), step0=start0)
            else:
                state = init(p, np.asarray(x0)[idx], np.asarray(v0)[idx], step0=start0)
            # only as many lanes as whole chunks need: the same compiled rollout runs them (17
            # points in a batch of 32 and chunks of 8 cost 3 chunks, not 4)
            m = min(b, -(-live // bsim.chunk) * bsim.chunk)
            if m < b:
                p, state = batched.take_lanes((p, state), m)
            first = 0 if step0 is None else np.asarray(step0, np.int64)[idx[:m]]
            health = batched.initial_health(bsim, state, first)
            chunks = []
            done = 0
            closest = np.inf
            # every piece (a shorter last one, another frame spacing) runs one compiled rollout
            # with its length and spacing as data (batched.rollout's pad_to): of ``chunk_frames``
            # frames in chunks, else of the longest run's where the runs differ (a last frame
            # closer to the one before); a program of its own would be a compile of seconds, for
            # every substep count
            pad = self.chunk_frames or (max(c for _, c in runs) if len(runs) > 1 else None)
            for gap, count in runs:
                size = self.chunk_frames or count
                while count > 0:
                    n_fr = min(size, count)
                    state, obs, health, *sep = batched.rollout(
                        bsim, p, state, n_fr, gap, health=health, step0=first + done,
                        observe=batched.positions_observer, separation=track, pad_to=pad,
                        substeps=int(n))
                    if track:
                        closest = np.minimum(closest, np.min(np.asarray(sep[0], np.float64) / self._reach, axis=0))
                    chunks.append(np.asarray(obs, np.float64)[:n_fr])     # (n_fr, B, V, 3)
                    done += gap * n_fr
                    count -= n_fr
            fr = np.concatenate(chunks, axis=0).transpose(1, 0, 2, 3)[:live]
            end = np.asarray(first) + done                                # the last target step, per lane
            bad = np.asarray(health.bad_step)
            seen = (bad >= 0) & (bad <= end)                               # (O, B): failures up to the end
            warn = np.asarray(health.warn_step)
            failed = seen.any(axis=0)[:live]
            out.append(fr)
            good.append(~failed & np.isfinite(fr).all(axis=(1, 2, 3)))
            clamp.append(((warn >= 0) & (warn <= end)).any(axis=0)[:live])
            code = np.asarray(health.code)
            over.append((seen & (code == diagnostics.CONTACT_OVERFLOW)).any(axis=0)[:live])
            invs.append(first_inversion(seen, code, bad)[:live])
            seps.append(np.broadcast_to(closest, (m,))[:live] if track else np.full(live, np.nan))
        result = np.concatenate(out), np.concatenate(good), np.concatenate(clamp), np.concatenate(over)
        result += (np.concatenate(seps),) if separation else ()
        return result + (np.concatenate(invs),) if failures else result

    def _single_fn(self, n):
        if n not in self._single:
            import jaxplush
            from jaxplush.fitting.judge.identifiability import frames_at_steps
            prob = self.prob
            sim = prob.sim if n == 1 else jaxplush.make_simulator(prob.scene, prob.target.dt, prob.sim.integrator,
                                                                   terms=prob.sim.terms, substeps=n)
            steps = tuple(int(s) for s in self.steps)
            self._single[n] = (sim, jax.jit(lambda p: frames_at_steps(sim, p, sim.init_fn(p), steps)))
        return self._single[n]

    def _frames_single(self, thetas, n):
        """(frames, ok, clamped, inverted) of :meth:`_frames`, one point at a time."""
        out, good, clamp, inv = [], [], [], []
        for th in thetas:
            for _ in range(2):
                sim, fn = self._single_fn(n)
                fr, codes = fn(sim.params(self.prob.params_at(th)))
                fr, codes = np.asarray(fr, np.float64), np.asarray(codes)
                bad = diagnostics.first_failure(codes)
                ok = bad is None and np.isfinite(fr).all()
                # soft-soft contact candidates that overflowed are a status (finite, inexact frames),
                # not a blow-up: grow the capacity and run the point again
                if ok or bad is None or not (codes[bad[0]] == diagnostics.CONTACT_OVERFLOW).any() \
                        or not self._grow_contact(th):
                    break
            out.append(fr)
            good.append(ok)
            clamp.append(bool((codes == diagnostics.VOLUME_CLAMPED).any()))
            failed = codes[bad[0]] if bad is not None else None
            only = failed is not None and set(failed[failed >= diagnostics.ERROR].tolist()) == {diagnostics.INVERTED}
            inv.append(int(self.steps[bad[0]]) if only else -1)
        return np.stack(out), np.asarray(good), np.asarray(clamp), np.asarray(inv, np.int64)

    def _grow_contact(self, theta):
        """After a run at theta whose contact candidates overflowed (health code
        ``CONTACT_OVERFLOW``): rebuild with twice the capacity (at least the default minimum
        ``MIN_CAPACITY``, at most each object's vertex count; a warning names it) and return True
        (run it again); False when there is no soft-soft contact or the capacity is already that
        of whole objects (which cannot overflow). Doubling
        needs no run to measure the need (a single-scene simulation and its compiles), and the
        problem starts with headroom (:func:`jaxplush.fitting.objective.problem.build_problem`), so this is rare."""
        import dataclasses
        import jaxplush
        from jaxplush.model import contact
        prob = self.prob
        if not prob.sim.terms.contact:
            return False
        old = prob.sim.terms.contact.capacity
        terms = contact.with_headroom(prob.sim.terms, contact.object_sizes(prob.scene), least=contact.MIN_CAPACITY)
        if terms.contact.capacity == old:
            return False
        new_sim = jaxplush.make_simulator(prob.scene, prob.target.dt, prob.sim.integrator, terms=terms)
        self.prob = dataclasses.replace(prob, sim=new_sim)
        self._single.clear()
        msg = (f"contact candidates overflowed (capacity {max(old)}) at {_values_text(prob.values(theta))}; "
               f"refitting with contact_capacity {max(terms.contact.capacity)} (set it in the scene to skip this)")
        self.notes.append(warn(msg, ContactCapacityWarning, stacklevel=4))
        return True


def first_inversion(seen, code, bad_step):
    """(B,) the first step at which an object of each lane inverted, where inversion is the only
    failure seen in that lane (``seen``: (O, B) failures up to the target's end; ``code``: the
    health codes; ``bad_step``: each object's failing step, any integer dtype), else -1."""
    bad = np.asarray(bad_step, np.int64)           # the sentinel below does not fit in int32
    inv = seen & (np.asarray(code) == diagnostics.INVERTED)
    only = inv.any(axis=0) & ~(seen & ~inv).any(axis=0)
    return np.where(only, np.where(inv, bad, np.iinfo(np.int64).max).min(axis=0), -1)


def _clear_measured(ok, separation):
    """``ok & clear_by_separation(separation)`` when every run that ran (``ok``) has a measured
    separation; else None (the frames must tell)."""
    from jaxplush.fitting.objective import objects as _objects
    if separation is None or not np.isfinite(np.asarray(separation)[ok]).all():
        return None
    return ok & _objects.clear_by_separation(separation)


def _values_text(vals):
    return " ".join(("k" if n == "k_structural" else n) + " " + ",".join(f"{x:.4g}" for x in np.atleast_1d(v))
                    for n, v in vals.items())


def _batchable(terms):
    try:
        batched.check_terms(terms)
    except NotImplementedError:
        return False
    return True
