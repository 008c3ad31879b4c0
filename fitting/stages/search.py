"""The default fit: a global stage over a box, Levenberg-Marquardt from the best candidates, smoothing.

Both stages work in theta = log(parameters) and only ever *simulate* (batched forward runs,
:class:`jaxplush.fitting.objective.evaluate.Evaluator`); neither differentiates through the rollout.

Why no autodiff here: a dropped plush excites vertex-level modes that ring for the whole target
(hundreds to thousands of radians of phase), so the loss carries a ripple whose wavelength in
log k is about 1e-3 on top of a smooth bowl (benchmarks/RESULTS.md, "roughness"). The exact
gradient and the JVP Jacobian are the derivatives of that ripple, so a gradient line search
(L-BFGS) can stall far from the truth and report convergence. Central differences taken at
the scale of the step (the trust radius, between ``h_min`` and ``h_max`` of
:class:`jaxplush.fitting.options.LocalOptions`) see the bowl;
as the steps shrink near the optimum, so does the difference step, where the loss is smooth.

Global stage (:func:`global_stage`): a scrambled Sobol design (scipy.stats.qmc) of ``n``
points in the box, plus the start itself, all run in compiled batches; failed points (which
even :data:`jaxplush.fitting.objective.evaluate.MAX_SUBSTEPS` substeps cannot run) are kept with an infinite loss.

Local stage (:func:`lm_round`): a box-constrained Levenberg-Marquardt on the residual
vector r (sum(r²) = loss) with a trust radius in log space:

* J by central differences at step h = clip(radius / 4, h_min, h_max) (2 P runs, one batch);
* three trial steps (JᵀJ + mu diag(JᵀJ)) delta = -Jᵀ r for mu/10, mu and 10 mu, each cut to the
  trust radius and projected into the box, run together; the best one is accepted if it
  lowers the loss (mu and the radius follow the ratio of actual to predicted decrease; a step
  that beats its prediction also doubles a radius below ``radius0``, since the radius sets the
  difference step too), else mu grows tenfold and the radius shrinks fourfold;
* it stops when an accepted step changes theta by less than ``xtol`` or the loss by less than
  ``ftol`` (relative), when the radius falls below ``xtol`` without an accepted step (stalled),
  or at ``max_iter`` iterations. The outcome is judged afterwards (jaxplush.fitting.fitter), not here.
* where an object's report ``damping`` and air ``drag`` are both fitted (:class:`Ties`), the steps
  move the pair along their combined rate only, the only thing a target determines of the two.

Smoothing stage (:func:`smooth`, noisy targets only): Gauss-Newton on an affine regression model
of the residuals over a Sobol design at the scale of the standard errors, which averages out the
ripple that a single difference stencil sees.

Every tuning constant comes from the options (:class:`jaxplush.fitting.options.LocalOptions`,
:class:`jaxplush.fitting.options.SmoothingOptions`), passed down to each function (None: the defaults).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from jaxplush.fitting.options import DEFAULT_ITERATIONS, DEFAULT_SAMPLES, LocalOptions, SmoothingOptions
from jaxplush.fitting.judge.outcome import Stop

#: The default options (what None stands for).
_LOCAL, _SMOOTHING = LocalOptions(), SmoothingOptions()
#: Aliases of two defaults (``LocalOptions().h_min``, ``SmoothingOptions().points``), read by
#: nothing here: the smallest difference step of the Jacobian, and the smoothing design's points.
H_MIN = _LOCAL.h_min
SMOOTH_POINTS = _SMOOTHING.points


@dataclasses.dataclass
class Box:
    """Bounds of the search in log space: ``lo`` and ``hi`` shaped like theta."""

    lo: np.ndarray
    hi: np.ndarray

    def clip(self, theta):
        return np.clip(theta, self.lo, self.hi)

    def contains(self, theta):
        return bool(np.all(theta >= self.lo - 1e-12) and np.all(theta <= self.hi + 1e-12))

    def at_bound(self, theta, tol=1e-6):
        """Bool mask (theta's shape): on the box's edge."""
        return (theta <= self.lo + tol) | (theta >= self.hi - tol)


@dataclasses.dataclass(frozen=True)
class Ties:
    """The pairs of fitted values that a local search moves only together: an object's report
    ``damping`` D and air ``drag`` gamma, both fitted. Both take the same share of every vertex's
    velocity off at every step (D as the rate 1/(D dt)), so a target determines their combined
    rate r = gamma + 1/(D dt) and not its split; a search free to move both wanders along the
    split, which the loss does not see, into the box's edge or into rounding noise (seed 1101 of
    the recovery benchmark: a fit of two cushions ended ``at_bound`` with drag at its lower bound
    and the combined rates 0.9% and 0.6% off).

    So the search fits the combined rate: each pair moves along the line on which drag's share
    s = gamma / r of the rate holds, (log D, log gamma) + t (-1, +1) in log space, t = the
    change of log r. Its starts are put on the line of the start values' share, the rate kept
    (:meth:`project`), so the values it reports split the rate as the start did; the fit's
    identifiability report says the split is undetermined, and its combinations the rate.

    Attributes:
      shape: theta's shape (P_n, O_f); damping, drag: flat indices of the pairs' entries;
      share: (pairs,) drag's share of the start's rate; dt: the target's time step, s (the
        simulation's step; a substep count changes the rate, not the line).
    """

    shape: tuple
    damping: tuple
    drag: tuple
    share: np.ndarray
    dt: float

    @staticmethod
    def of(evaluator, shape=None):
        """The ties of ``evaluator.prob`` (a :class:`jaxplush.fitting.objective.problem.Problem`),
        or None where it fits not both ``damping`` and ``drag`` (or has no problem, or ``shape``
        is not its theta's)."""
        ties = Ties.for_problem(getattr(evaluator, "prob", None))
        if ties is None or (shape is not None and tuple(shape) != ties.shape):
            return None
        return ties

    @staticmethod
    def for_problem(prob):
        """The ties of a :class:`jaxplush.fitting.objective.problem.Problem` (None: it does not fit
        both ``damping`` and ``drag``)."""
        names = tuple(getattr(prob, "names", ()))
        if "damping" not in names or "drag" not in names:
            return None
        th_shape = tuple(np.shape(prob.theta0))
        o_f = th_shape[1]
        i_d, i_g = names.index("damping"), names.index("drag")
        dt = float(prob.target.dt)
        start = prob.start
        rate_d = 1.0 / (np.asarray(start["damping"], np.float64) * dt)
        gamma = np.asarray(start["drag"], np.float64)
        return Ties(shape=th_shape, damping=tuple(i_d * o_f + j for j in range(o_f)),
                    drag=tuple(i_g * o_f + j for j in range(o_f)), share=gamma / (gamma + rate_d), dt=dt)

    @property
    def basis(self):
        """(P, P - pairs): the directions a search moves in, one per free value, the damping's
        column replaced by the pair's (-1 at D, +1 at gamma)."""
        p = int(np.prod(self.shape))
        cols = [j for j in range(p) if j not in self.drag]
        out = np.zeros((p, len(cols)))
        for c, j in enumerate(cols):
            out[j, c] = 1.0
        for d, g in zip(self.damping, self.drag):
            c = cols.index(d)
            out[d, c], out[g, c] = -1.0, 1.0
        return out

    def spread(self, per_column):
        """(P,) a value per direction of :attr:`basis` (a standard error, say) given to each
        value that direction moves."""
        b = np.abs(self.basis)
        return (b * np.asarray(per_column, np.float64)[None]).max(axis=1)

    def project(self, theta):
        """``theta`` with each pair split as the start's share splits its combined rate, the rate
        kept; pairs within 1e-9 (log space) of that line are left exactly as they are."""
        flat = np.array(theta, np.float64).ravel()
        for d, g, s in zip(self.damping, self.drag, self.share):
            rate = math.exp(flat[g]) + math.exp(-flat[d]) / self.dt
            new_g = math.log(s * rate)
            new_d = -math.log((1.0 - s) * rate * self.dt)
            if abs(new_g - flat[g]) > 1e-9 or abs(new_d - flat[d]) > 1e-9:
                flat[g], flat[d] = new_g, new_d
        return flat.reshape(np.shape(theta))

    def along(self, theta, trial):
        """``trial`` (a step from ``theta`` along :attr:`basis`, then clipped into a box) with each
        pair's two changes made equal and opposite again at the smaller of the two, so that a
        clip on one keeps the pair on its line."""
        a = np.asarray(theta, np.float64).ravel()
        flat = np.array(trial, np.float64).ravel()
        for d, g in zip(self.damping, self.drag):
            tg, td = flat[g] - a[g], a[d] - flat[d]
            t = math.copysign(min(abs(tg), abs(td)), tg) if tg * td > 0 else 0.0
            flat[g], flat[d] = a[g] + t, a[d] - t
        return flat.reshape(np.shape(trial))


@dataclasses.dataclass
class GlobalResult:
    """The global stage: ``thetas`` (N, P_n, O_f), ``loss`` (N,), ``ok`` (N,), ``substeps`` (N,)."""

    thetas: np.ndarray
    loss: np.ndarray
    ok: np.ndarray
    substeps: np.ndarray

    def best(self, k, min_distance):
        """Indices of up to k lowest-loss points that ran, each at least ``min_distance`` (max-norm,
        log space) from those chosen before it."""
        order = [i for i in np.argsort(self.loss) if self.ok[i] and np.isfinite(self.loss[i])]
        chosen = []
        for i in order:
            if all(np.max(np.abs(self.thetas[i] - self.thetas[j])) >= min_distance for j in chosen):
                chosen.append(int(i))
            if len(chosen) == k:
                break
        return chosen


def sobol_design(box, n, seed=0):
    """(n, *theta.shape) points of a scrambled Sobol sequence in the box (n rounded up to a power
    of two inside scipy, the first n kept)."""
    from scipy.stats import qmc
    shape = box.lo.shape
    d = int(np.prod(shape))
    m = max(int(math.ceil(math.log2(max(n, 2)))), 1)
    u = qmc.Sobol(d, scramble=True, seed=seed).random_base2(m)[:n]
    lo, hi = box.lo.ravel(), box.hi.ravel()
    return (lo + u * (hi - lo)).reshape((n,) + shape)


def global_stage(evaluator, box, start, n=DEFAULT_SAMPLES, seed=0, progress=None, retries=None, extra=()):
    """Evaluate the start, the ``extra`` points (clipped into the box) and ``n`` Sobol points of the
    box (a point that blows up retried at most ``retries`` times,
    :class:`jaxplush.fitting.objective.evaluate.Evaluator`). Returns :class:`GlobalResult`."""
    extra = [box.clip(np.asarray(t, np.float64)) for t in extra]
    thetas = np.concatenate([np.asarray(start, np.float64)[None]] + [t[None] for t in extra] + [sobol_design(box, n, seed)])
    ev = evaluator(thetas) if retries is None else evaluator(thetas, retries=retries)
    if progress is not None:
        progress(len(thetas))
    return GlobalResult(thetas, ev.loss, ev.ok, ev.substeps)


@dataclasses.dataclass
class LMState:
    """One Levenberg-Marquardt run (everything a checkpoint needs to continue it).

    theta: current point (shape of theta); loss: its loss; mu: damping; radius: trust radius;
    iteration: iterations done; done, reason: whether and why it stopped (``reason`` in words for
    a person, ``stopped`` a :class:`jaxplush.fitting.judge.outcome.Stop`); history: list of
    (loss, theta) of accepted points (the first is the start); evaluations: simulated points.
    """

    theta: np.ndarray
    loss: float
    mu: float = _LOCAL.mu0          # a search's options set these (:func:`start_states`)
    radius: float = _LOCAL.radius0
    iteration: int = 0
    done: bool = False
    reason: str = ""
    stopped: Stop = Stop.NONE     # why it stopped (:class:`jaxplush.fitting.judge.outcome.Stop`)
    history: list = dataclasses.field(default_factory=list)
    jac: np.ndarray | None = None     # (n, P) at theta, if computed there
    jac_h: float = _LOCAL.h_max
    residual: np.ndarray | None = None
    substeps: int = 1
    evaluations: int = 0
    rescues: int = 0              # axis scans (:func:`rescue`) done in this stage
    separation: float = math.nan  # the run at theta: how close objects came (Evaluation.separation)
    updates: int = 0              # secant updates of ``jac`` since it was differenced (:func:`lm_round`)


def _separation(ev, i):
    """Point i's measured separation of an evaluation (NaN: not measured; stand-in evaluations
    have none)."""
    sep = getattr(ev, "separation", None)
    return math.nan if sep is None else float(sep[i])


def fd_step(radius, options=None):
    """The central-difference step at trust radius ``radius``: radius x ``h_fraction`` clipped to
    [``h_min``, ``h_max``] of ``options`` (:class:`LocalOptions`)."""
    o = options or _LOCAL
    return float(min(max(radius * o.h_fraction, o.h_min), o.h_max))


def _stencil(box, theta, h):
    """The 2 P central-difference points around theta (clipped into the box) and their spans."""
    flat = theta.ravel()
    pts, spans = [], []
    for j in range(flat.size):
        lo_t, hi_t = flat.copy(), flat.copy()
        lo_t[j] = max(flat[j] - h, box.lo.ravel()[j])
        hi_t[j] = min(flat[j] + h, box.hi.ravel()[j])
        pts += [lo_t.reshape(theta.shape), hi_t.reshape(theta.shape)]
        spans.append(hi_t[j] - lo_t[j])
    return pts, spans


#: Coloured stencils that came near contact (and were run again in full) after which an
#: evaluator stops trying them: the default of :attr:`LocalOptions.colour_misses`.
COLOUR_MISSES = _LOCAL.colour_misses


def _coloured_stencil(box, theta, h):
    """The 2 P_n central-difference points of a coloured stencil: row i of theta (one parameter
    of every fitted object) moved by -h and +h at once (clipped into the box), and the spans
    (P_n, O_f) of each entry."""
    lo_b, hi_b = box.lo.reshape(theta.shape), box.hi.reshape(theta.shape)
    pts, spans = [], np.zeros(theta.shape)
    for i in range(theta.shape[0]):
        lo_t, hi_t = theta.copy(), theta.copy()
        lo_t[i] = np.maximum(theta[i] - h, lo_b[i])
        hi_t[i] = np.minimum(theta[i] + h, hi_b[i])
        pts += [lo_t, hi_t]
        spans[i] = hi_t[i] - lo_t[i]
    return pts, spans


def _jacobians(evaluator, box, states, options=None):
    """Central-difference Jacobians (n, P) of every state at its own step h, all stencils run in
    one evaluation; a stencil runs at the substeps its points need (at least its centre's).
    Columns whose stencil fails are zero.

    With several fitted objects (``evaluator.colourable()``), the stencil is first *coloured*:
    each parameter is moved for every object at once (2 P_n points instead of 2 P_n O_f), and
    each object's column is read off its own residuals: its vertices' for a position target, for
    a point cloud the points measured from its vertices (``evaluator.point_owners``), which must
    be the same points in every run of the stencil. That is exact when the objects do not
    interact, which is checked in every run of the stencil (no two objects within reach of
    contact); a state whose coloured stencil is not clear gets the full stencil (a second
    evaluation)."""
    colourable = getattr(evaluator, "colourable", None)        # stand-in evaluators have no colouring
    owners = evaluator.owners() if colourable is not None and colourable() else None
    points = colourable is not None and owners is None and colourable()
    rest = list(states)
    misses = getattr(evaluator, "colour_misses", 0)
    if (owners is not None or points) and misses < (options or _LOCAL).colour_misses:
        # only states whose own run kept the objects apart: by its separation, measured at every
        # step, where known; else by its frames (positions; a point cloud's are not kept)
        def apart(st):
            if np.isfinite(st.separation):
                return bool(evaluator.clear_by_separation([st.separation])[0])
            return points or st.residual is None or bool(evaluator.clear(np.asarray(st.residual)[None])[0])
        try_ = [st for st in states if st.theta.ndim == 2 and st.theta.shape[1] > 1 and apart(st)]
        if try_:
            done = _coloured_jacobians(evaluator, box, try_, owners, options)
            evaluator.colour_misses = misses + done.count(False)
            ok = {id(st) for st, d in zip(try_, done) if d}
            rest = [st for st in states if id(st) not in ok]
    if not rest:
        return
    ev, spans = _run_stencils(evaluator, box, rest, _stencil, options)
    k = 0
    for i, st in enumerate(rest):
        p = len(spans[i])
        jac = np.zeros((evaluator.residual.n, p))
        for j in range(p):
            a, b = k + 2 * j, k + 2 * j + 1
            if ev.ok[a] and ev.ok[b] and spans[i][j] > 0:
                jac[:, j] = (ev.residuals[b] - ev.residuals[a]) / spans[i][j]
        st.jac = jac
        st.evaluations += 2 * p
        k += 2 * p


def _forward_jacobians(evaluator, states, options):
    """Set the exact Jacobian (:meth:`jaxplush.fitting.objective.evaluate.Evaluator.forward_jacobian`) of
    every state it serves, with ``jac_h`` the smallest difference step (the stopping rules read
    it as a local Jacobian); return the states left for differences. A forward pass costs about
    P rollouts, counted as P evaluations."""
    rest = []
    for st in states:
        jac = evaluator.forward_jacobian(st.theta, st.substeps)
        if jac is None:
            rest.append(st)
            continue
        st.jac, st.jac_h = jac, options.h_min
        st.evaluations += st.theta.size
    return rest


def _run_stencils(evaluator, box, states, stencil, options=None, keep_frames=False):
    """Run every state's ``stencil(box, theta, h)`` points at its own step h (recorded as
    ``jac_h``) in one evaluation, each stencil at the substeps its points need (at least its
    centre's); returns (the :class:`Evaluation`, each stencil's spans)."""
    pts, subs, spans = [], [], []
    for st in states:
        h = fd_step(st.radius, options)
        p, sp = stencil(box, st.theta, h)
        n = max(int(evaluator.substeps_for(np.asarray(p)).max()), st.substeps)
        pts += p
        subs += [n] * len(p)
        spans.append(sp)
        st.jac_h = h
    if keep_frames:
        return evaluator(np.asarray(pts), substeps=np.asarray(subs), keep_frames=True), spans
    return evaluator(np.asarray(pts), substeps=np.asarray(subs)), spans


def _coloured_jacobians(evaluator, box, states, owners, options=None):
    """The coloured stencils of :func:`_jacobians`, all in one evaluation: sets ``jac`` of each
    state whose stencil ran and stayed clear of contact; returns which did."""
    points = owners is None                    # a point cloud: owners from each run's frames
    ev, spans = _run_stencils(evaluator, box, states, _coloured_stencil, options, keep_frames=points)
    if points:
        frames = None if ev.frames is None else np.where(ev.ok[:, None, None, None], ev.frames, 0.0)
        clear = evaluator.clear_frames(frames, ev.ok, ev.separation)
        point_owners = evaluator.point_owners(frames) if ev.ok.any() else None
    else:
        clear = evaluator.clear(ev.residuals, ev.separation)
    done = []
    k = 0
    for st, sp in zip(states, spans):
        p_n, o_f = st.theta.shape
        rows = slice(k, k + 2 * p_n)
        k += 2 * p_n
        st.evaluations += 2 * p_n
        if not (ev.ok[rows].all() and clear[rows].all()):
            done.append(False)
            continue
        if points:
            owners = point_owners[rows.start]
            if not (point_owners[rows] == owners).all():    # a point changed object: not exact
                done.append(False)
                continue
        jac = np.zeros((evaluator.residual.n, p_n * o_f))
        for i in range(p_n):
            diff = ev.residuals[rows.start + 2 * i + 1] - ev.residuals[rows.start + 2 * i]
            for o in range(o_f):
                if sp[i, o] > 0:
                    mine = owners == o
                    jac[mine, i * o_f + o] = diff[mine] / sp[i, o]
        st.jac = jac
        done.append(True)
    return done


def jacobian(evaluator, box, theta, h, substeps=1, options=None, separation=math.nan):
    """(n, P) central-difference Jacobian of the residuals at theta with step h (log space; clipped
    to [``h_min``, ``h_max``] of ``options``). ``separation``: how close the objects came in the run
    at theta (:attr:`jaxplush.fitting.objective.evaluate.Evaluation.separation`; NaN: not known); where they
    came within reach of contact, the coloured stencil is not tried (it would be run again in full)."""
    st = LMState(theta=np.asarray(theta, np.float64), loss=np.nan, radius=h / (options or _LOCAL).h_fraction,
                 substeps=substeps,
                 separation=float(separation))
    _jacobians(evaluator, box, [st], options)
    return st.jac


def _steps(jac, r, mus, radius, box, theta, ties=None):
    """Trial points for each mu: the LM step cut to the trust radius, projected into the box.
    With ``ties`` (:class:`Ties`), the step moves along their basis only."""
    basis = None if ties is None else ties.basis
    jr = jac if basis is None else jac @ basis
    jtj = jr.T @ jr
    g = jr.T @ r
    scale = np.maximum(np.diag(jtj), 1e-12 * max(float(np.max(np.diag(jtj))), 1e-300))
    out = []
    for mu in mus:
        a = jtj + mu * np.diag(scale)
        try:
            delta = -np.linalg.solve(a, g)
        except np.linalg.LinAlgError:
            delta = -np.linalg.lstsq(a, g, rcond=None)[0]
        if basis is not None:
            delta = basis @ delta
        big = float(np.max(np.abs(delta)))
        if big > radius:
            delta = delta * (radius / big)
        trial = box.clip((theta.ravel() + delta).reshape(theta.shape))
        if ties is not None:
            trial = ties.along(theta, trial)
        step = trial.ravel() - theta.ravel()
        pred = float(r @ r - np.sum((r + jac @ step) ** 2))
        out.append((trial, step, pred, mu))
    return out


def scan_points(box, theta, n_total=_LOCAL.scan_points):
    """Points on lines through theta along each parameter's axis across the whole box:
    (points (M, *theta.shape), spacing per axis (P,)), ``n_total`` in all (split evenly over the
    parameters; one batch of the evaluator), at least 4 per axis."""
    flat = np.asarray(theta, np.float64).ravel()
    lo, hi = box.lo.ravel(), box.hi.ravel()
    per = max(4, n_total // flat.size)
    pts, spacing = [], []
    for j in range(flat.size):
        for v in np.linspace(lo[j], hi[j], per):
            t = flat.copy()
            t[j] = v
            pts.append(t.reshape(np.shape(theta)))
        spacing.append((hi[j] - lo[j]) / (per - 1))
    return np.asarray(pts), np.asarray(spacing)


def rescue(evaluator, box, states, limit=2, options=None):
    """Restart stalled searches from the lowest point of an axis scan through them.

    A search stalls when no step down to ``xtol`` lowers the loss although the gradient is not
    small: the loss of a body in hard floor contact jumps where a contact event moves by a step,
    and the search stands on such a jump, not at an optimum. Every stalled state gets one scan
    across the box along each parameter's axis (:func:`scan_points`, all states in one
    evaluation); where a scan point is lower by more than ``rescue_gain`` of ``options``
    (:class:`LocalOptions`; its ``scan_points`` size the scan), the search restarts
    there with the scan's spacing as its trust radius (the jump goes into its history). A search
    is restarted at most ``limit`` times, and is not scanned again once a scan found nothing
    lower. Returns the states restarted."""
    o = options or _LOCAL
    states = [st for st in states if st.stopped == Stop.STALLED and st.rescues < limit]
    if not states:
        return []
    pts, owner, spacing = [], [], []
    for i, st in enumerate(states):
        p, sp = scan_points(box, st.theta, o.scan_points)
        pts.append(p)
        owner += [i] * len(p)
        spacing.append(sp)
    pts = np.concatenate(pts)
    ev = evaluator(pts)
    owner = np.asarray(owner)
    ties = Ties.of(evaluator, np.shape(states[0].theta))
    restarted = []
    for i, st in enumerate(states):
        idx = np.nonzero(owner == i)[0]
        st.evaluations += len(idx)
        st.rescues += 1
        loss = np.where(ev.ok[idx], ev.loss[idx], np.inf)
        j = int(idx[np.argmin(loss)])
        if not (ev.loss[j] < (1.0 - o.rescue_gain) * st.loss):
            st.reason += "; an axis scan across the box found nothing lower"
            st.rescues = limit
            continue
        old = st.loss
        st.theta = pts[j].copy()
        st.loss, st.residual, st.substeps = float(ev.loss[j]), ev.residuals[j], int(ev.substeps[j])
        on_line = st.theta if ties is None else ties.project(st.theta)
        if not np.array_equal(on_line, st.theta):
            # an axis scan moves one of a tied pair: back on the pair's line, the rate kept (its
            # residuals are evaluated again before the search goes on)
            st.theta, st.residual = on_line, None
        st.separation = _separation(ev, j)
        st.jac, st.updates, st.mu = None, 0, o.mu0
        st.radius = float(np.max(spacing[i]))
        st.done, st.stopped = False, Stop.NONE
        st.reason = f"restarted from an axis scan (loss {old:.4g} -> {st.loss:.4g})"
        st.history.append((st.loss, st.theta.copy()))
        restarted.append(st)
    return restarted


def start_states(evaluator, thetas, losses=None, options=None):
    """:class:`LMState` s at the given points, their residuals evaluated (one evaluation); their
    trust radius and damping are ``radius0`` and ``mu0`` of ``options`` (:class:`LocalOptions`)."""
    o = options or _LOCAL
    thetas = np.asarray(thetas, np.float64)
    ties = Ties.of(evaluator, thetas.shape[1:])
    if ties is not None:             # on their tied pairs' lines (:class:`Ties`)
        thetas = np.asarray([ties.project(t) for t in thetas])
    ev = evaluator(thetas)
    out = []
    for i, th in enumerate(thetas):
        st = LMState(theta=th.copy(), loss=float(ev.loss[i]), residual=ev.residuals[i],
                     substeps=int(ev.substeps[i]), evaluations=1, mu=o.mu0, radius=o.radius0,
                     separation=_separation(ev, i))
        if not ev.ok[i]:
            st.done, st.stopped = True, Stop.FAILED
            st.reason = "the start of the local search does not run (blows up at every substep count)"
        else:
            st.history.append((st.loss, st.theta.copy()))
        out.append(st)
    return out


def gauss_newton(jac, residual):
    """(the Gauss-Newton step -(JᵀJ)⁻¹ Jᵀ r, the standard errors sqrt(s² diag (JᵀJ)⁻¹)) in log
    space, s² = |r|² / (n - P) (NaN residuals count as 0); (None, None) when JᵀJ is singular."""
    r = np.nan_to_num(np.asarray(residual, np.float64))
    j = np.asarray(jac, np.float64)
    try:
        inv = np.linalg.inv(j.T @ j)
    except np.linalg.LinAlgError:
        return None, None
    diag = np.diag(inv)
    if not (np.all(np.isfinite(inv)) and np.all(diag > 0)):
        return None, None
    s2 = float(r @ r) / max(len(r) - j.shape[1], 1)
    return -inv @ (j.T @ r), np.sqrt(s2 * diag)


def _gn_within_noise(jac, r, ties=None):
    """max_i |GN step_i| / standard error_i at a point (None when JᵀJ is singular or s² is 0);
    with ``ties`` (:class:`Ties`), along their basis."""
    step, se = gauss_newton(jac if ties is None else jac @ ties.basis, r)
    if step is None or not np.all(se > 0):
        return None
    return float(np.max(np.abs(step) / se))


def lm_round(evaluator, box, states, max_iter=DEFAULT_ITERATIONS["lm"], options=None, *, noise_stop=None, floor=None):
    """One Levenberg-Marquardt iteration of every unfinished state (two evaluations in all: the
    Jacobians that are missing, then three trial steps per state). ``options``
    (:class:`LocalOptions`, None: the defaults) hold the stopping rules; a state stops once its
    Gauss-Newton step is at most ``noise_stop`` (default ``options.noise_stop``) of every
    parameter's standard error, or once its loss is at most ``floor`` (the model's reproducibility
    floor as a loss; None: not known) and its Gauss-Newton step at most ``options.floor_step``."""
    o = options or _LOCAL
    noise_stop = o.noise_stop if noise_stop is None else noise_stop
    active = []
    for st in states:
        if st.done:
            continue
        if st.iteration >= max_iter:
            st.done, st.stopped = True, Stop.ITERATIONS
            st.reason = f"reached the iteration limit ({max_iter})"
        elif st.loss == 0.0:
            st.done, st.stopped = True, Stop.EXACT
            st.reason = "the residuals are exactly zero"
        else:
            active.append(st)
    if not active:
        return
    limit = int(o.secant_updates)    # iterations a secant-updated Jacobian may serve

    def differenced(st):
        # a secant-updated Jacobian serves up to ``limit`` iterations, whatever the radius
        if st.jac is None:
            return True
        if st.updates:
            return st.updates >= limit
        if forward and st.jac_h == o.h_min:        # exact, or as local as differences get: no new step
            return False
        return st.jac_h != fd_step(st.radius, o)

    forward = o.jacobian == "forward" and getattr(evaluator, "forward_jacobian", None) is not None
    need = [st for st in active if differenced(st)]
    if need:
        _jacobians(evaluator, box, _forward_jacobians(evaluator, need, o) if forward else need, o)
        for st in need:
            st.updates = 0
    trials, owner = [], []
    for i, st in enumerate(active):
        stop = None
        ties = Ties.of(evaluator, np.shape(st.theta))
        within = _gn_within_noise(st.jac, st.residual, ties) if st.jac_h <= o.noise_stop_h else None
        if within is not None and within <= noise_stop:
            stop = (Stop.NOISE, f"the Gauss-Newton step is {within:.2g} of the parameters' standard errors "
                                f"(<= {noise_stop:g}): the optimum is resolved to the noise")
        gn = None if stop else _floor_step(st, floor, o.floor_step, ties)
        if gn is not None:
            stop = (Stop.FLOOR, f"the loss {st.loss:.4g} is at the model's reproducibility floor ({floor:.4g}) and the "
                                f"Gauss-Newton step is {gn:.2g} (<= {o.floor_step:g}): no step can be told from rounding")
        t = None
        if stop is None:
            t = _steps(st.jac, st.residual, tuple(st.mu * f for f in o.trial_mu), st.radius, box, st.theta, ties)
            best_pred = max(x[2] for x in t)
            if best_pred <= o.pred_tol * st.loss and st.jac_h <= o.h_min * (1 + 1e-9):
                stop = (Stop.PREDICTED, f"the Gauss-Newton model predicts a decrease of at most "
                                        f"{best_pred / st.loss:.2g} of the loss {st.loss:.4g} (<= {o.pred_tol:g})")
        if stop is not None:
            if st.updates:
                st.jac = None            # judged on a secant update: difference the Jacobian, judge again
            else:
                st.done, (st.stopped, st.reason) = True, stop
            continue
        trials += t
        owner += [i] * len(t)
    if not trials:
        return
    ev = evaluator(np.asarray([t[0] for t in trials]))
    owner = np.asarray(owner)
    for i, st in enumerate(active):
        idx = np.nonzero(owner == i)[0]
        if idx.size:
            _take_step(st, ev, idx, trials, o, secant=limit > 0)


def broyden(jac, step, dr):
    """The Jacobian (n, P) updated so that it maps ``step`` (P,) to the residuals' change ``dr``
    (n,) and is unchanged on every direction orthogonal to it (Broyden's rank-one secant update)."""
    ss = float(step @ step)
    if not ss > 0.0:
        return jac
    return jac + np.outer(dr - jac @ step, step / ss)


def _floor_step(st, floor, limit, ties=None):
    """The largest |Gauss-Newton step| (log space) of a state whose loss is at most ``floor``
    and whose step is at most ``limit``; None otherwise (or when either is None). With ``ties``
    (:class:`Ties`), along their basis."""
    if floor is None or limit is None or not st.loss <= floor:
        return None
    step, _ = gauss_newton(st.jac if ties is None else st.jac @ ties.basis, st.residual)
    if step is None:
        return None
    size = float(np.max(np.abs(step))) if step.size else 0.0
    return size if size <= limit else None


def _take_step(st, ev, idx, trials, options=None, secant=False):
    """Accept the best of a state's evaluated trial steps (rows ``idx`` of ``ev`` and ``trials``) if
    it lowers the loss, adapting mu and the trust radius, else shrink the radius; sets the stops
    on ``xtol`` (step), ``ftol`` (relative loss change) and a radius below ``xtol`` (stalled), all
    of ``options`` (:class:`LocalOptions`, whose fields also set how mu and the radius adapt).

    With ``secant``, an accepted step updates the Jacobian (:func:`broyden`) instead of dropping
    it. A step taken on an updated Jacobian that fails is not held against the search (its
    radius and mu stay): the Jacobian is differenced and the next round tries again.

    A step that does better than the model promised (ratio above ``ratio_good``) also grows a
    radius below ``radius0`` (a fresh search's) by ``radius_grow``: the radius sets the Jacobian's difference step too,
    and a small one (a later horizon starts with one) resolves rounding ripple rather than the
    slope, so the steps it gives stay short while each does better than predicted."""
    o = options or _LOCAL
    xtol, ftol = o.xtol, o.ftol
    st.evaluations += len(idx)
    st.iteration += 1
    best = int(idx[np.argmin(np.where(ev.ok[idx], ev.loss[idx], np.inf))])
    trial, step, pred, mu = trials[best]
    new = float(ev.loss[best])
    size = float(np.max(np.abs(step))) if step.size else 0.0
    updated = st.updates > 0                 # this step was taken on a secant-updated Jacobian
    if ev.ok[best] and new < st.loss:
        rho = (st.loss - new) / pred if pred > 0 else 0.0
        rel = (st.loss - new) / max(st.loss, 1e-300)
        if secant and st.jac is not None and st.residual is not None:
            st.jac = broyden(st.jac, np.asarray(step, np.float64).ravel(),
                             np.asarray(ev.residuals[best], np.float64) - np.asarray(st.residual, np.float64))
            st.updates += 1
        else:
            st.jac, st.updates = None, 0
        st.theta, st.loss = trial, new
        st.residual, st.substeps = ev.residuals[best], int(ev.substeps[best])
        st.separation = _separation(ev, best)
        st.mu = mu * (o.mu_good if rho > o.ratio_good else (1.0 if rho > o.ratio_poor else o.mu_poor))
        if rho > o.ratio_good:
            st.radius = max(st.radius, o.radius_grow * size, min(o.radius_grow * st.radius, o.radius0))
        elif rho < o.ratio_poor:
            st.radius = max(size / 2.0, xtol / 2)
        st.history.append((st.loss, st.theta.copy()))
        if size <= xtol:
            st.done, st.stopped = True, Stop.STEP
            st.reason = f"step {size:.2g} <= xtol {xtol:g} (log space)"
        elif rel <= ftol:
            st.done, st.stopped = True, Stop.LOSS
            st.reason = f"relative loss change {rel:.2g} <= ftol {ftol:g}"
    elif updated:
        st.jac, st.updates = None, 0             # the updated Jacobian failed: difference it, same radius
    else:
        st.mu = max(mu, st.mu) * o.mu_fail
        st.radius = (size if size > 0 else st.radius) * o.radius_fail
        if st.radius < xtol:
            st.done, st.stopped = True, Stop.STALLED
            st.reason = (f"stalled: no step down to {st.radius:.2g} (log space) lowers the loss "
                         f"{st.loss:.4g}")


@dataclasses.dataclass
class Smoothed:
    """The smoothing stage's result.

    Attributes:
      theta: the smoothed optimum (shape of theta): the last design's centre plus its step;
      centre: that centre; jac (n, P), residual (n,): the regression's slope and intercept there;
      step (P,): the smoothed Gauss-Newton step at the centre; stderr (P,): standard errors from
      the regression (log space); converged: the step is within ``stop`` standard errors
      (:class:`SmoothingOptions`);
      path: [(loss at the centre, centre)] per iteration; evaluations: points simulated.
    """

    theta: np.ndarray
    centre: np.ndarray
    jac: np.ndarray
    residual: np.ndarray
    step: np.ndarray
    stderr: np.ndarray
    converged: bool
    path: list
    evaluations: int


def regression(thetas, residuals, centre):
    """Least-squares affine model r(theta) ~ a + B (theta - centre) of residual vectors sampled at
    points around a centre: (a (n,), B (n, P)). Rows of ``thetas`` (M, P) and ``residuals`` (M, n)."""
    x = np.asarray(thetas, np.float64).reshape(len(thetas), -1) - np.asarray(centre, np.float64).ravel()[None]
    design = np.hstack([np.ones((len(x), 1)), x])
    coef = np.linalg.lstsq(design, np.asarray(residuals, np.float64), rcond=None)[0]
    return coef[0], coef[1:].T


def smooth(evaluator, box, theta, jac, residual, seed=0, progress=None, options=None):
    """Gauss-Newton on a regression model of the residuals at the scale of the standard errors.

    With a noisy target, the loss of a body in floor contact carries a ripple (contact events
    that move by a step) whose dips lie several standard errors from the optimum of the smooth
    bowl beneath it, and a local search stops in whichever dip it reaches, so far starts end
    several standard errors apart (benchmarks/RESULTS.md, "Fitting from far starts").
    A central difference only sees the ripple's slope. This stage instead samples
    ``points`` scrambled Sobol points within ±``width`` standard errors of the centre (one batch;
    the fields of ``options``, :class:`SmoothingOptions`), fits an affine model of the residual vector over them (:func:`regression`),
    which averages the ripple out, and steps to that model's Gauss-Newton optimum (cut to the
    design's half-width, kept in the box). The standard errors come from the model and size the
    next design; while the step reaches past the design (a start many standard errors off), the
    next design is twice as wide, up to ``grow`` times, so the stage crosses the distance in a
    few designs, and it is back at the errors' scale once a step stays inside or the model's loss
    at the new centre rose. It stops once the step is within ``stop`` standard errors, or after
    ``iterations`` designs.

    Args:
      evaluator: :class:`jaxplush.fitting.objective.evaluate.Evaluator` of the full target; box: :class:`Box`;
      theta: the start (the local search's result); jac, residual: its Jacobian and residuals,
        which size the first design; progress: ``progress(1, extra=text)`` after each design;
      options: :class:`SmoothingOptions` (None: the defaults).
    Returns:
      :class:`Smoothed`, or None when the first design cannot be sized (singular Jacobian).
    """
    from scipy.stats import qmc
    o = options or _SMOOTHING
    sigma_range = tuple(o.sigma)
    shape = np.shape(theta)
    x = np.asarray(theta, np.float64).ravel().copy()
    ties = Ties.of(evaluator, shape)

    def newton(b, a):
        # the Gauss-Newton step and standard errors (P,), along the ties' basis where there are
        # ties (each tied value gets its pair's standard error)
        if ties is None:
            return gauss_newton(b, a)
        step, sig = gauss_newton(b @ ties.basis, a)
        return (None, None) if step is None else (ties.basis @ step, ties.spread(sig))

    sigma = newton(jac, residual)[1]
    if sigma is None:
        return None
    m = max(int(math.ceil(math.log2(o.points))), 1)
    u = qmc.Sobol(x.size, scramble=True, seed=seed).random_base2(m)[:o.points] * 2.0 - 1.0
    u = np.vstack([np.zeros((1, x.size)), u])
    lo, hi = box.lo.ravel(), box.hi.ravel()
    path, evaluations, out, scale, last_model = [], 0, None, 1.0, np.inf
    for _ in range(o.iterations):
        half = scale * o.width * np.clip(sigma, *sigma_range)
        pts = np.clip(x[None] + u * half[None], lo, hi)
        ev = evaluator(pts.reshape((-1,) + shape))
        evaluations += len(pts)
        ok = ev.ok & np.isfinite(ev.loss)
        if not ok[0] or ok.sum() < 2 * (x.size + 1):
            break
        path.append((float(ev.loss[0]), x.reshape(shape).copy()))
        a, b = regression(pts[ok], ev.residuals[ok], x)
        model = float(a @ a)             # the smoothed loss at the centre (a single point's carries the ripple)
        if model > last_model:
            scale = 1.0                  # the last long step overshot: back to the standard errors' scale
            half = o.width * np.clip(sigma, *sigma_range)
        last_model = model
        step, sig = newton(b, a)
        if sig is None:
            break
        # converged: the step is within the standard errors, and the design that measured them
        # spanned at least half its intended width in them (a design sized by a Jacobian that saw
        # the ripple's slope is too narrow to average it out)
        sized = bool(np.all(half >= 0.5 * o.width * np.clip(sig, *sigma_range)))
        converged = sized and bool(np.all(np.abs(step) <= o.stop * sig))
        cut = np.clip(x + np.clip(step, -half, half), lo, hi)
        if ties is not None:
            cut = ties.along(x, cut).ravel()
        # far from the optimum the step reaches past the design: widen the next one (a trust
        # region that grows while the model's direction holds), else back to the errors' scale
        scale = min(2.0 * scale, o.grow) if np.any(np.abs(step) > half) else 1.0
        out = Smoothed(theta=cut.reshape(shape), centre=x.reshape(shape).copy(), jac=b, residual=a,
                       step=step, stderr=sig, converged=converged, path=path, evaluations=evaluations)
        if progress is not None:
            progress(1, extra=f"step {float(np.max(np.abs(step) / sig)):.2g} standard errors")
        if converged:
            break
        x, sigma = cut, sig
    if out is not None:
        out.evaluations = evaluations
    return out
