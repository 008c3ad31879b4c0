"""95% intervals of the fitted values from twins: a linearised parametric bootstrap.

The standard errors of the identifiability report (:mod:`jaxplush.fitting.judge.identifiability`) treat
the residuals at the optimum as independent noise of their RMS. That is right for a target with
measurement noise that the model reproduces, and wrong where what is left is the model's own
rounding drift: that drift is correlated over frames and vertices, and a noise-free fit that
reproduces its target to 0.1 micrometres can report +-0.0002% and be 0.06% off.

Twins measure the spread instead of assuming it. At the fitted values theta:

* the fit's own batched rollout is run B + 1 times as lanes of one call: lane 0 from the scene's
  start, lane b from the start moved by a rounding-level perturbation (seed b; the
  predictability measurement's :func:`jaxplush.stepping.predictability.perturbation`);
* each twin b is a target the model reproduces exactly up to rounding: its frames, plus, for a
  target with noise sigma, noise of that sigma drawn afresh;
* a fit of twin b that starts at theta would take the Gauss-Newton step
  ``delta_b = -(J^T J)^-1 J^T (r_0 - r_b)``, with J the fit's own Jacobian (log space) and
  r_0 - r_b the difference of lane 0's residual and twin b's: where the fitted values would land
  had the target been twin b;
* the interval of parameter i is ``theta_i +- t * s_i``, s_i the RMS of delta_b,i over the
  twins (about zero: a twin's mean offset counts as error too) and, in quadrature, the
  Gauss-Newton step from theta to the optimum of the target itself (a fit stops once that step
  is below its tolerance, which can be more than the twins' spread) and the working dtype's
  resolution of the value (:func:`_resolution`: the report's damping D is held as 1 - 1/D, which
  float32 resolves D to about D x 2^-24), t the 97.5% quantile of Student's t with B degrees of
  freedom (s_i is estimated from B twins).

So an interval is as wide as rounding and noise, propagated through the same rollout and the same
Jacobian as the fit, move the values. It costs one batched call of B + 1 lanes (the fit's
compiled program) and no Jacobian.

It is linear, and where the motion amplifies rounding (a torus bouncing with the report's
damping, a tumbling bean) the linear model is the chaos's: the Jacobian is huge, each twin's step
tiny, while values far away fit the target as well as the twins do. So the twins' own fit of the
target is the yardstick of a scan (:func:`scan`): where the twins fit it differently from the fit
itself, each value (and each damping+drag rate) is moved on its own to levels from twice the
twins' half-width up to 64%, and its interval reaches at least as far as the farthest level that
fits no worse than the worst twin (infinite where the last does: undetermined). A fit whose
interval that widens past 4x the twins' and past 1% is judged ``at_floor`` rather than converged
(:func:`jaxplush.fitting.judge.outcome.limited_by_rounding`). One or two more batched calls.

Twins apply to ``positions``, ``tracks`` and ``points`` targets on the batched engine, with single
shooting. A point's residual is its distance to the simulated surface: the difference between
a twin's residual and the fit's is how far the twin's surface lies from the fit's there (to first
order, as the Jacobian sees it), and the noise drawn afresh is the point's noise along the
normal. Elsewhere (a mixed target, a fit in segments, a scene off the batched engine)
:func:`from_report` gives the identifiability report's standard errors as the interval
(``method == "residuals"``), and says so.

All of that measures the neighbourhood of the fitted values, which says where the truth lies only
when the fit reached the data there. A fit that stopped short of them (:data:`SHORT`: stalled, at
a bound of its box, or at its iteration limit) can sit in a
minimum that does not reproduce the data at all: one of two clouds fitted 28% off in drag stopped
at its iteration limit with a twins' spread of 0.015%, its smoothing designs agreeing to 0.04%
(benchmarks/RESULTS.md, 2026-12-01). Its interval is the search box instead (:func:`box`,
``method == "box"``): all such a fit can say is that it searched there. A fit at the model's
reproducibility floor (``at_floor``: within 1.4x of it, where no values do better) has done what
the data allow and reports twins.
"""

from __future__ import annotations

import dataclasses
import math
import statistics

import numpy as np

from jaxplush.fitting.judge.outcome import SHORT  # noqa: F401 (re-exported: the statuses box() is for)
from jaxplush.fitting.targets.kinds import TargetKind

#: Twins per fit (B): the interval's spread is estimated from B draws (with the fit's own lane,
#: 32 lanes: whole chunks of the batched engine). With 31 the estimated spread is within 0.68-1.33x
#: the true one 99% of the time; 8 twins were tried first, and gave 0.55x for one parameter of a
#: noisy target whose true spread is known (the residuals' standard error; 64 twins: 0.99-1.01x).
N_TWINS = 31
#: The intervals' coverage.
LEVEL = 0.95
#: Singular values of the Jacobian below this fraction of the largest are dropped from the twins'
#: minimum-norm steps (:attr:`Intervals.steps`): directions the target does not determine.
RCOND = 1e-6
#: Fewest twins that must run (a twin that blows up is dropped) for a spread to be estimated.
MIN_TWINS = 4


def t_quantile(p, dof):
    """The ``p`` quantile of Student's t with ``dof`` degrees of freedom (Cornish-Fisher expansion
    about the normal quantile; within 0.3% of the exact value for dof >= 4 at p = 0.975)."""
    z = _normal_quantile(p)
    if not math.isfinite(dof):
        return z
    v = float(dof)
    return (z + (z ** 3 + z) / (4 * v) + (5 * z ** 5 + 16 * z ** 3 + 3 * z) / (96 * v ** 2)
            + (3 * z ** 7 + 19 * z ** 5 + 17 * z ** 3 - 15 * z) / (384 * v ** 3))


def _normal_quantile(p):
    return statistics.NormalDist().inv_cdf(p)


@dataclasses.dataclass(frozen=True, eq=False)
class Intervals:
    """The fitted values' intervals (module docstring).

    Attributes:
      labels: (P,) "name[object]" of each fitted parameter.
      theta: (P,) the fitted values in log space.
      sd: (P,) the spread of log p (relative error of p): the RMS Gauss-Newton step of the twins,
        or the identifiability report's standard error; inf where the target does not determine it.
      quantile: the multiplier of ``sd`` for the level (Student's t with the twins as degrees of
        freedom; the normal quantile for ``residuals``).
      level: the coverage, 0.95.
      method: "twins", "residuals" or "box" (:func:`box`: the interval is the search box, and
        ``sd`` the larger distance from the value to the box's ends over ``quantile``, so that
        value +- quantile * sd holds the whole box).
      n_twins: twins that ran (0 for ``residuals``).
      note: one line on how they were measured.
      offset: (P,) the Gauss-Newton step from theta to the optimum the fit stopped short of
        (``twins`` only, else None), part of ``sd`` in quadrature.
      resolution: (P,) how finely the working dtype resolves each value (``twins`` only, else
        None; :func:`_resolution`), part of ``sd`` in quadrature.
      box_lo, box_hi: (P,) the search box's ends in log space (``box`` only, else None): the
        interval's ends.
      scan: (P,) ``twins`` only, else None: how far (log space) :func:`scan` found each value can
        move and fit the target as well as the twins do, where that widened its interval (``sd``
        at least scan / quantile; inf: undetermined); 0 elsewhere; None where the scan did not
        run (the twins fit the target alike: no chaos to widen by).
      twin_sd: (P,) the twins' own spreads, before the scan widened them (None where it did not
        run).
      limited: (P,) bool, where the scan widened the interval past what the noise sets
        (:func:`floor_limited`); None where the scan did not run.
      combo_scan: ((label, width), ...) the scan's half-width of each damping+drag rate
        (:func:`rate_directions`; 0: not widened), which :func:`combinations` widens its interval
        to; () where the scan did not run or there are none.
      steps: (B, P) each twin's Gauss-Newton step in log space (``twins`` only, else None), the
        minimum-norm step over every parameter the frames are sensitive to (singular values below
        :data:`RCOND` of the largest dropped): a combination of parameters that the target
        determines although its parts are not (the report's damping with drag) gets its spread
        from them (:meth:`spread_of`).
    """

    labels: tuple
    theta: np.ndarray
    sd: np.ndarray
    quantile: float
    level: float
    method: str
    n_twins: int
    note: str
    steps: np.ndarray | None = None
    offset: np.ndarray | None = None
    resolution: np.ndarray | None = None
    box_lo: np.ndarray | None = None
    box_hi: np.ndarray | None = None
    scan: np.ndarray | None = None
    twin_sd: np.ndarray | None = None
    combo_scan: tuple = ()
    limited: np.ndarray | None = None

    def spread_of(self, fn, h=1e-6):
        """(value, spread) of a positive function ``fn(theta)`` of the (P,) log values: its value at
        the fitted values, and the RMS over the twins of the change of log fn that each twin's step
        makes, linearised as the steps are (central differences of step ``h``): its relative error.
        Spread NaN without twins."""
        value = float(fn(self.theta))
        if self.steps is None or not len(self.steps) or not value > 0:
            return value, math.nan
        grad = np.zeros(len(self.theta))
        for i in np.flatnonzero(np.any(self.steps != 0, axis=0)):
            e = np.zeros(len(self.theta))
            e[i] = h
            grad[i] = (math.log(fn(self.theta + e)) - math.log(fn(self.theta - e))) / (2 * h)
        off = 0.0 if self.offset is None else float(self.offset @ grad)
        res = 0.0 if self.resolution is None else float(np.sum((self.resolution * grad) ** 2))
        return value, float(np.sqrt(np.mean((self.steps @ grad) ** 2) + off ** 2 + res))

    @property
    def lower(self):
        """(P,) lower ends in parameter units (0 where undetermined)."""
        if self.box_lo is not None:
            return np.exp(self.box_lo)
        return np.exp(self.theta - self.quantile * self.sd)

    @property
    def upper(self):
        """(P,) upper ends in parameter units (inf where undetermined)."""
        with np.errstate(over="ignore"):
            if self.box_hi is not None:
                return np.exp(self.box_hi)
            return np.exp(self.theta + self.quantile * self.sd)

    def contains(self, label, value, width=None):
        """Whether ``value`` lies in the interval of ``label`` (``width``: a multiple of ``sd``
        instead of the level's quantile, say 4)."""
        i = self.labels.index(label)
        if self.box_lo is not None:
            return bool(self.box_lo[i] <= math.log(value) <= self.box_hi[i])
        q = self.quantile if width is None else float(width)
        return bool(abs(math.log(value) - self.theta[i]) <= q * self.sd[i])

    def text(self, label):
        """"[lo, hi]" of ``label``, "box [lo, hi]" for a search box (``method == "box"``), or
        "undetermined"."""
        i = self.labels.index(label)
        if self.box_lo is not None:
            return f"box [{self.lower[i]:.6g}, {self.upper[i]:.6g}]"
        if not np.isfinite(self.sd[i]):
            return "undetermined"
        return f"[{self.lower[i]:.6g}, {self.upper[i]:.6g}]"

    def scan_text(self, label):
        """How far the scan widened the interval of ``label``, for a person: "+-8.33%", or
        "undetermined (...)"."""
        return _width_text(self.scan[self.labels.index(label)])

    def as_dict(self):
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}


def from_report(report, theta, note=None):
    """:class:`Intervals` from an identifiability report's standard errors (``method ==
    "residuals"``): the residuals treated as independent, normal quantile."""
    sd = np.asarray(report.stderr, np.float64).copy()
    sd[~np.isfinite(sd)] = np.inf
    return Intervals(labels=tuple(report.labels), theta=np.asarray(theta, np.float64).ravel(), sd=sd,
                     quantile=_normal_quantile(0.5 + LEVEL / 2), level=LEVEL, method="residuals", n_twins=0,
                     note=note or "from the residuals at the optimum, treated as independent noise")


def box(labels, theta, search_box, status):
    """:class:`Intervals` of a fit that stopped short of the data (``status``, one of :data:`SHORT`,
    or a checkpoint's "running" or "interrupted")
    at log values ``theta``: the search box ``search_box`` (``.lo``, ``.hi`` in log space, shaped
    as theta) itself, ``method == "box"`` (module docstring). Not a 95% interval of the data: the
    values' neighbourhood does not say where the truth lies, and the box is where the fit looked."""
    th = np.asarray(theta, np.float64).ravel()
    lo = np.minimum(np.asarray(search_box.lo, np.float64).ravel(), th)
    hi = np.maximum(np.asarray(search_box.hi, np.float64).ravel(), th)
    q = _normal_quantile(0.5 + LEVEL / 2)
    return Intervals(labels=tuple(labels), theta=th, sd=np.maximum(th - lo, hi - th) / q, quantile=q, level=LEVEL,
                     method="box", n_twins=0, box_lo=lo, box_hi=hi,
                     note=f"the search box: the fit {_ENDED.get(str(status), 'ended ' + str(status).replace('_', ' '))}, "
                          "short of the data, where the values' neighbourhood (twins, standard errors) does not say "
                          "where the truth lies; it lies in the box if the box holds it at all")


#: How :func:`box`'s note says a checkpoint's status (a fit that has not finished).
_ENDED = {"running": "had not finished (a checkpoint)", "interrupted": "was interrupted"}


def _resolution(prob, theta, dtype):
    """(P,) the relative resolution of each fitted value in the working ``dtype``: the spread of a
    value's quantisation where it acts. The report's damping D acts through Verlet's factor
    keep = 1 - 1/D, which the dtype holds to a spacing u (2^-24 in float32 just below 1): the
    damping 1 - keep then carries an error of up to u/2, D a relative error of up to D u/2, and a
    fit cannot tell D apart more finely than that (D = 622 in float32: 0.0019%). As a spread,
    D u / sqrt(12) (a uniform quantisation). Every other parameter acts as a factor of its term,
    resolved to the dtype's epsilon / sqrt(12)."""
    th = np.asarray(theta, np.float64)
    eps = float(np.finfo(np.dtype(dtype)).eps)
    out = np.full(th.shape, eps / math.sqrt(12.0))
    if "damping" in prob.names:
        i = list(prob.names).index("damping")
        d = np.exp(th[i])
        keep = np.where(d > 1.0, 1.0 - 1.0 / np.maximum(d, 1.0), 0.5)
        u = np.spacing(keep.astype(np.dtype(dtype))).astype(np.float64)
        out[i] = np.maximum(out[i], d * u / math.sqrt(12.0))
    return out.ravel()


def applies(prob, ev):
    """Why twins do not apply to this fit (a phrase), or None when they do."""
    if TargetKind(prob.target.kind).compound:
        return f"a {prob.target.kind} target mixes residuals of two kinds"
    if prob.shooting is not None and prob.shooting.on:
        return "the fit ran in segments (multiple shooting)"
    if not getattr(ev, "batched", False):
        return "the scene does not run on the batched engine"
    return None


def twins(prob, ev, theta, jac, report, n_twins=N_TWINS, seed=0, residual=None):
    """:class:`Intervals` of a fit ending at log values ``theta`` ((P_n, O_f)) from ``n_twins``
    twins (module docstring), with ``jac`` (n, P) the Jacobian of ``ev``'s residuals at theta
    (log space) and ``report`` the identifiability report (its undetermined parameters get an
    infinite spread). ``residual``: ``ev``'s residual at theta (the fit's own), whose Gauss-Newton
    step says how far theta lies from the optimum the fit stopped short of: it is added to each
    spread in quadrature (a fit stops once that step is below its tolerance, which can exceed the
    twins' spread). Falls back to :func:`from_report` (and says why in ``note``) where twins do
    not apply or fewer than :data:`MIN_TWINS` ran."""
    from jaxplush.stepping import predictability as _pred
    theta = np.asarray(theta, np.float64)
    why = applies(prob, ev)
    if why is not None:
        return from_report(report, theta, note=f"from the residuals, treated as independent noise: twins do not "
                                              f"apply ({why})")
    values = prob.params_at(theta)
    n = int(ev.substeps_for(theta[None])[0])
    x0 = np.asarray(prob.sim.topology.x0, np.float64)
    dtype = prob.sim.dtype
    starts = np.stack([x0] + [x0 + _pred.perturbation(prob.scene, x0, dtype, seed=seed + 1 + b)
                              for b in range(n_twins)])
    # with the contact separation tracked, as the fit's own evaluations run: the same compiled
    # rollout serves them (its result is not read here); without it the twins compiled a program
    # of their own, about a quarter of a cold contact fit's compile time (benchmarks/RESULTS.md)
    frames, good, *_ = ev._run_lanes([values] * (n_twins + 1), n, ev.runs, x0=starts, v0=np.zeros_like(starts),
                                     separation=True)
    if not good[0] or good[1:].sum() < MIN_TWINS:
        return from_report(report, theta, note="from the residuals, treated as independent noise: the twins did "
                                              "not run")
    frames = frames[np.concatenate([[True], good[1:]])]
    # each lane's residual against the target itself (no noise drawn): how well rounding twins of
    # the fitted values fit it, the yardstick of the scan below
    clean = ev._residuals(frames)
    rng = np.random.default_rng(seed)
    points = not TargetKind(prob.target.kind).sees_vertices
    if prob.noise and not points:
        frames[1:] = frames[1:] + rng.normal(0.0, float(prob.noise), frames[1:].shape)
        res = ev._residuals(frames)
    else:
        res = clean.copy()
    if prob.noise and points:
        # a point's residual is its distance to the surface, which a twin's surface shifts by as
        # much as it moves along the normal there (to first order, as the Jacobian sees it); the
        # noise drawn afresh is a point's noise along that normal: sigma per observed point
        seen = np.isfinite(res[0]) & (res[0] != 0)
        norm = np.broadcast_to(np.asarray(ev.residual.norm, np.float64), res[0].shape)
        res[1:] = res[1:] + rng.normal(0.0, float(prob.noise), res[1:].shape) * norm * seen
    diff = np.nan_to_num(res[0][None] - res[1:])                 # (B, n): the fit at theta against twin b
    j = np.nan_to_num(np.asarray(jac, np.float64))
    sd = np.full(j.shape[1], np.inf)
    ok = np.asarray(report.determined, bool) & np.isfinite(np.asarray(report.stderr, np.float64))
    if ok.any():
        steps = -np.linalg.lstsq(j[:, ok], diff.T, rcond=None)[0]      # (P_ok, B)
        sd[ok] = np.sqrt(np.mean(steps ** 2, axis=1))
    sens = np.asarray(report.determined, bool)
    all_steps = np.zeros((len(diff), j.shape[1]))
    offset = np.zeros(j.shape[1])
    if sens.any():
        all_steps[:, sens] = -np.linalg.lstsq(j[:, sens], diff.T, rcond=RCOND)[0].T
        if residual is not None:
            offset[sens] = -np.linalg.lstsq(j[:, sens], np.nan_to_num(np.asarray(residual, np.float64)),
                                            rcond=RCOND)[0]
    resolution = _resolution(prob, theta, dtype)
    sd = np.sqrt(sd ** 2 + offset ** 2 + resolution ** 2)
    b = len(frames) - 1
    q = t_quantile(0.5 + LEVEL / 2, b)
    what = "rounding" + (f" and noise of sigma {1e3 * float(prob.noise):.3g} mm drawn afresh" if prob.noise else "")
    note = (f"from {b} twins of the fitted values that differ by {what}, each propagated by one Gauss-Newton step "
            "of the fit's Jacobian, and the step to the optimum the fit stopped short of")
    # the combinations a target determines where its parts are not (the damping+drag rate) are
    # scanned along the move that scales them, with their own twins' spread
    rates = rate_directions(prob)
    rate_sd = [float(np.sqrt(np.mean((all_steps @ v) ** 2))) for _, v in rates]
    widths = scan(prob, ev, theta, n, clean, sd, q, width=ev._width(n_twins + 1, n),
                  directions=[(v, s) for (_, v), s in zip(rates, rate_sd)])
    own = sd
    combo_scan = ()
    if widths is not None:
        widths, combo = widths[:len(sd)], widths[len(sd):]
        combo_scan = tuple((lab, float(w)) for (lab, _), w in zip(rates, combo))
    if widths is not None and np.any(widths > 0):
        sd = np.where(widths > 0, np.maximum(sd, widths / q), sd)
        note += ("; widened where values that far away fit the target as well as the rounding twins do (a scan "
                 "of each value: " + ", ".join(f"{lab} {_width_text(w)}" for lab, w in zip(report.labels, widths)
                                                if w > 0) + ")")
    return Intervals(labels=tuple(report.labels), theta=theta.ravel(), sd=sd, quantile=q,
                     level=LEVEL, method="twins", n_twins=b, note=note, steps=all_steps, offset=offset,
                     resolution=resolution, scan=widths, twin_sd=own if widths is not None else None,
                     combo_scan=combo_scan, limited=None if widths is None else floor_limited(widths, own, q))


def floor_limited(widths, twin_sd, q):
    """(P,) bool: where the scan's half-widths ``widths`` exceed both :data:`SCAN_FLOOR` times the
    twins' own half-width (``q`` x ``twin_sd``) and :data:`SCAN_PRECISE`: there the model's
    reproducibility, not the noise, sets how closely the target determines the value."""
    w = np.asarray(widths, np.float64)
    return (w > SCAN_FLOOR * float(q) * np.asarray(twin_sd, np.float64)) & (w > SCAN_PRECISE)


def rate_directions(prob):
    """[(label, v)] for every fitted object whose report's ``damping`` and air ``drag`` are both
    fitted: v ((P,) in the flat log values) the move that scales their combined rate
    (:func:`combinations`) by e^delta for a step delta, drag and the damping's rate 1/(D dt) alike
    (log drag up, log D down), the split kept."""
    names = tuple(prob.names)
    if "damping" not in names or "drag" not in names:
        return []
    i_d, i_g = names.index("damping"), names.index("drag")
    shape = (len(names), len(prob.objects))
    out = []
    for j, o in enumerate(prob.objects):
        v = np.zeros(shape)
        v[i_g, j], v[i_d, j] = 1.0, -1.0
        out.append((f"damping+drag rate[{prob.scene.object_names[o]}]", v.ravel()))
    return out


#: The scan's farthest level (:func:`scan`): a distance from a fitted value in log space (x1.9);
#: a value that fits as well there is undetermined.
SCAN_MAX = 0.64
#: The scan's nearest level: this many times the twins' half-width (quantile x spread), at least
#: :data:`SCAN_MIN`; each level after it twice the one before, up to :data:`SCAN_MAX`. Nearer
#: than that is the linear twins' own business.
SCAN_MATERIAL = 2.0
#: The scan's nearest level at the least (log space, 0.05%).
SCAN_MIN = 5e-4
#: Where the scan widens a value's interval past this many times the twins' half-width, the
#: model's reproducibility rather than the noise sets how closely the target determines it
#: (:func:`jaxplush.fitting.judge.outcome.limited_by_rounding`: not converged but at_floor).
SCAN_FLOOR = 4.0
#: ... and past this half-width (log space, 1%): a value the scan still puts within +-1% is
#: measured, floor or not (seed 1701's case 7, two objects on a floor as 2 mm clouds, every value
#: within 0.22% of the truth, had one interval widened from the twins' +-0.05% to +-0.78%).
SCAN_PRECISE = 0.01


def scan_levels(half_width):
    """The scan's levels (log space) for a value whose twins' half-width is ``half_width``: from
    :data:`SCAN_MATERIAL` x half_width (at least :data:`SCAN_MIN`), each twice the one before,
    and :data:`SCAN_MAX` last; empty where the nearest would be past :data:`SCAN_MAX`."""
    first = max(SCAN_MATERIAL * float(half_width), SCAN_MIN)
    if not first < SCAN_MAX:
        return np.zeros(0)
    n = int(math.ceil(math.log2(SCAN_MAX / first)))
    return np.append(first * 2.0 ** np.arange(n), SCAN_MAX)


def _width_text(w):
    """A scan's half-width (log space) for a person: "+-8.33%", or "undetermined" (inf)."""
    if not np.isfinite(w):
        return f"undetermined (every value within x{math.exp(SCAN_MAX):.3g} fits as well)"
    return f"+-{100 * math.expm1(w):.3g}%"


def twin_rms(prob, residuals):
    """(B + 1,) the residual RMS (m) of each lane's ``residuals`` (a row each, the noise not drawn)."""
    from jaxplush.fitting.objective import losses as _losses
    loss = np.sum(np.nan_to_num(np.asarray(residuals, np.float64)) ** 2, axis=1)
    return np.asarray([_losses.rms_metres(x, prob.loss.scale2, prob.target.kind) for x in loss])


def scan(prob, ev, theta, n, clean, sd, q, width=None, directions=()):
    """(P + D,) how far each fitted value, then each of the D ``directions`` ((v, spread): a move
    v in the flat log values and its twins' spread), can move (log space, in units of v) and
    still fit the target as well as the rounding twins of the fitted values do: 0 where the scan
    does not widen the twins' interval, inf where every level fits; None where it does not run.

    Twins propagate their differences through one Gauss-Newton step of the fit's Jacobian. Where
    the motion amplifies rounding (a torus bouncing with the report's damping, a tumbling bean),
    that Jacobian is the chaos's: huge, and a twin's step tiny, although a refit of the twin could
    land anywhere in a wide, rough valley. Seed 1501's case 4 (a 2 mm cloud) converged 11.4% off
    in damping with a twins' spread of 0.019%; twins of its fitted values fit the target at
    2.12-2.44 mm, and so does the damping at every level tried from 15% below the fitted one to
    x1.9 above it (benchmarks/RESULTS.md, 2026-12-02).

    The yardstick is the twins themselves: ``clean`` ((B + 1, n): each lane's residual against the
    target, no noise drawn; lane 0 the fit's own). A value fits as well as they do when its RMS²
    is at most the largest twin's plus what the noise resolves over the residual's samples
    (z² s² / samples, z the level's normal quantile, s the noise sigma or, noise-free, the fit's
    own RMS). Where the twins' RMS² spread is within that resolution there is nothing to widen by
    and the scan does not run. Otherwise each parameter (``sd`` (P,) finite: the twins' spreads,
    ``q`` their quantile) is moved on its own, the others at their fitted values, to the levels of
    :func:`scan_levels` on either side: first the nearest (2P lanes); the parameters that fit as
    well there, to every farther level (one more call). The half-width is the farthest level that
    fits as well, inf where that is :data:`SCAN_MAX`. One or two
    batched calls of the fit's compiled rollout at its ``n`` substeps (``width``: the twins'
    batch width), run as lanes; a lane that fails does not fit."""
    from jaxplush.fitting.objective.losses import residual_samples
    rms = twin_rms(prob, clean)
    samples = residual_samples(prob)
    s = float(prob.noise) if prob.noise else float(rms[0])
    resolved = _normal_quantile(0.5 + LEVEL / 2) ** 2 * s * s / max(samples, 1)
    if not np.all(np.isfinite(rms)) or float(np.max(rms ** 2)) - float(rms[0]) ** 2 <= resolved:
        return None
    limit2 = float(np.max(rms ** 2)) + resolved
    th = np.asarray(theta, np.float64)
    flat = th.ravel()
    sd = np.asarray(sd, np.float64)
    moves = [np.eye(flat.size)[i] for i in range(flat.size)] + [np.asarray(v, np.float64).ravel()
                                                               for v, _ in directions]
    spreads = np.concatenate([sd, [float(x) for _, x in directions]])
    levels = {int(i): scan_levels(q * spreads[i]) for i in np.flatnonzero(np.isfinite(spreads))}
    levels = {i: lv for i, lv in levels.items() if lv.size}

    def fits(points):
        ths = []
        for i, j, sign in points:
            ths.append((flat + sign * levels[i][j] * moves[i]).reshape(th.shape))
        frames, good, *_ = ev._run_lanes([prob.params_at(t) for t in ths], n, ev.runs, separation=True, width=width)
        out = np.zeros(len(points), bool)
        if good.any():
            out[good] = twin_rms(prob, ev._residuals(frames[good])) ** 2 <= limit2
        return out

    widths = np.zeros(len(moves))
    pts = [(i, 0, sign) for i in levels for sign in (-1, 1)]
    if not pts:
        return widths
    near = sorted({i for (i, _, _), o in zip(pts, fits(pts)) if o})
    for i in near:
        widths[i] = levels[i][0]
    far = [(i, j, sign) for i in near for j in range(1, len(levels[i])) for sign in (-1, 1)]
    if far:
        for (i, j, _), o in zip(far, fits(far)):
            if o:
                widths[i] = max(widths[i], levels[i][j])
    widths[widths >= SCAN_MAX] = np.inf
    return widths


@dataclasses.dataclass(frozen=True)
class Combination:
    """A combination of fitted parameters that the target determines although its parts are not.

    Attributes:
      label: e.g. "damping+drag rate[ball]"; parts: the labels of the parameters it combines.
      value: its value at the fitted values; unit: its unit.
      sd: its spread (relative error) from the twins (NaN: not measured); lower, upper: its 95%
        interval (NaN: not measured).
      note: one line: what it is, and that the split between its parts is undetermined.
    """

    label: str
    parts: tuple
    value: float
    unit: str
    sd: float
    lower: float
    upper: float
    note: str

    def text(self):
        iv = (f"[{self.lower:.6g}, {self.upper:.6g}]" if np.isfinite(self.lower) else "interval not measured")
        return f"{self.label} = {self.value:.6g} {self.unit}, 95% interval {iv}: {self.note}"


def combinations(prob, theta, iv, substeps=1):
    """The determined combinations of a fit ending at log values ``theta`` ((P_n, O_f)), with their
    twin intervals from ``iv`` (:class:`Intervals`; NaN intervals without twins): for every fitted
    object whose report's ``damping`` and air ``drag`` are both fitted, their combined rate
    :func:`jaxplush.fitting.stages.equation_error.damping_rate` + drag (at the ``substeps`` the fitted values ran with), which is all a
    target determines of the two: both take the same share of every vertex's velocity off at every
    step. A tuple of :class:`Combination`."""
    from jaxplush.fitting.stages.equation_error import damping_rate
    names = tuple(prob.names)
    if "damping" not in names or "drag" not in names:
        return ()
    th = np.asarray(theta, np.float64)
    shape, dt = th.shape, float(prob.target.dt)
    i_d, i_g = names.index("damping"), names.index("drag")
    q = iv.quantile if iv is not None else math.nan
    out = []
    for j, o in enumerate(prob.objects):
        name = prob.scene.object_names[o]

        def rate(flat, j=j):
            t = np.asarray(flat, np.float64).reshape(shape)
            d = math.exp(t[i_d, j])
            return (float(damping_rate(d, dt, substeps)) if d > 1.0 else math.inf) + math.exp(t[i_g, j])

        if iv is not None and iv.steps is not None:
            value, sd = iv.spread_of(rate)
            wide = dict(getattr(iv, "combo_scan", ()) or ()).get(f"damping+drag rate[{name}]", 0.0)
            if wide > 0:
                # the scan (twins()): rates that far away fit as well as the rounding twins do
                sd = max(sd, wide / q)
        else:
            value, sd = rate(th.ravel()), math.nan
        if np.isfinite(sd):
            lo, hi = value * math.exp(-q * sd), value * math.exp(q * sd)
        else:
            lo, hi = (0.0, math.inf) if sd == math.inf else (math.nan, math.nan)
        out.append(Combination(
            label=f"damping+drag rate[{name}]", parts=(f"damping[{name}]", f"drag[{name}]"), value=value, unit="1/s",
            sd=sd, lower=lo, upper=hi,
            note=(f"the rate 1/(D dt) + drag at which the two take velocity off (dt = {dt:g} s"
                  + (f", {substeps} substeps: s (1 - (1 - 1/D)^(1/s))/dt + drag" if substeps > 1 else "")
                  + "), which is all the target determines of the two; the split between damping and drag is "
                  "undetermined")))
    return tuple(out)
