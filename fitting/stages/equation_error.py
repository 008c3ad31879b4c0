"""A start that needs no start values: the model's linearity, and indirect inference.

Given positions and velocities, every force of the model is linear in its parameter: the springs in
k, the edge dashpot in its coefficient c, the gas in nmol (P = nRT/V), air drag in gamma; the
report's per-step damping D enters Verlet's update as the rate gamma_D = 1/(D dt) (:func:`damping_rate`),
with the same regressor as drag (docs/model.md §5, docs/fitting.md "A start from the model's
linearity").

**The equation-error estimate** (:func:`equation_error`). From a positions target's frames, the
velocities and accelerations of every vertex at every interior frame by second-order finite
differences (the frames' own spacing, uneven allowed); then, per object, the linear least-squares
fit of

    m a - m g - F_known(x, v) = k R_k(x) + c R_c(x, v) + nmol R_n(x) - (gamma + gamma_D) m v

over the vertices whose forces are all known: pinned and driven vertices, vertices near the floor
and vertices near another object (soft-soft contact) are left out, frame by frame. The regressors
R are the force kernel of :mod:`jaxplush.model.forces` itself, evaluated with one parameter at 1
and the others at 0 (each force is linear in its own parameter), so no force is written twice.
It is global (no start values, no rollout) and costs one pass over the frames.

**Indirect inference** (:func:`indirect_inference`). Frames saved every 15-200 steps alias the
fast modes: the finite-difference accelerations carry false components correlated with the
regressors, and the estimate is biased (k mostly low). Applying the same estimator to frames
simulated at theta and iterating, in log values,

    theta <- theta + J^-1 [s(target) - s(simulated at theta)]

cancels what the sampling, the masking and the noise do to both alike (Gourieroux, Monfort and
Renault 1993): a few rollouts in all. Where the fast modes stay excited between frames (light
damping, impacts, soft-soft contact at 10 ms frames), the statistic follows their aliased phases
more than the parameters and the iteration does not converge (benchmarks/RESULTS.md).

The report's damping and air drag share one regressor: only their combined rate is determined.
Where both are fitted, the combined rate is estimated and the start's split between them is kept
(:attr:`IndirectInference.undetermined` names the pair).
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np

from jaxplush.model import forces as model
from jaxplush.types import PARAM_NAMES

#: The parameters the estimator fits (the others are held at their scene values).
LINEAR = ("k_structural", "dashpot", "nmol", "drag", "damping")


@dataclasses.dataclass(frozen=True)
class Estimate:
    """One equation-error estimate.

    Attributes:
      values: dict name -> (O_f,) float64 estimated values of the problem's fitted parameters
        (per fitted object; positive: where a coefficient is estimated at or below zero, the
        frames say nothing usable about it, and the start value stands in, named in ``clamped``).
      rate: (O_f,) the combined velocity-decay rate gamma + gamma_D, 1/s (NaN where neither the
        drag nor the damping is fitted).
      rows: (O_f,) how many vertex-frame rows each object's fit used (three equations each).
      masked: the fraction of interior vertex-frames left out (contact, floor, pins).
      clamped: names (with object index) whose estimate was not positive.
      coef: dict name -> (O_f,) the least-squares coefficients themselves, unclamped (k, c, nmol;
        the combined rate for the drag and the damping).
    """

    values: dict
    rate: np.ndarray
    rows: np.ndarray
    masked: float
    clamped: tuple = ()
    coef: dict = None


#: The step in log values of :func:`indirect_inference`'s finite-difference Jacobian.
FD_STEP = 0.05

#: The largest change of a log value in one iteration of :func:`indirect_inference`.
MAX_STEP = 1.0

def _fd(x_prev, x, x_next, h1, h2):
    """Second-order velocity and acceleration at the middle of three frames h1 and h2 apart."""
    v = (-h2 / (h1 * (h1 + h2))) * x_prev + ((h2 - h1) / (h1 * h2)) * x + (h1 / (h2 * (h1 + h2))) * x_next
    a = 2.0 * (x_prev / (h1 * (h1 + h2)) - x / (h1 * h2) + x_next / (h2 * (h1 + h2)))
    return v, a


def _kernel(prob):
    """The force kernel without contact and the smooth floor (those vertices are masked),
    vmapped over frames: (params, x (T, 3, V), v (T, 3, V)) -> f (T, 3, V); jitted once per
    simulator program (:func:`jaxplush.stepping.compiled.get`: every call of an indirect inference
    reuses it)."""
    from jaxplush.stepping import compiled
    terms = dataclasses.replace(prob.sim.terms, contact=None, floor_smooth=None, k_field=False)

    def build():
        kernel = model.make_force_fn(prob.sim.topology, terms, prob.scene.temperature)
        return jax.jit(jax.vmap(lambda p, x, v: kernel(p, x, v)[0], in_axes=(None, 0, 0)))
    return compiled.get(prob.sim, "equation_error_forces", build), terms


def _masks(prob, xs):
    """(T-2, V) bool: the interior vertex-frames whose forces are all known."""
    topo, scene = prob.sim.topology, prob.scene
    t, n = xs.shape[0] - 2, topo.n_vertices
    ok = np.ones((t, n), bool)
    ok[:, np.asarray(topo.fixed, np.int64)] = False
    for d in getattr(scene, "driven", ()):
        ok[:, np.asarray(d.vertices, np.int64)] = False
    edge = float(np.mean(topo.rest_length))
    step = np.maximum(np.linalg.norm(xs[1:-1] - xs[:-2], axis=-1), np.linalg.norm(xs[2:] - xs[1:-1], axis=-1))
    if scene.floor is not None:
        low = np.min(xs[:, :, 1][np.arange(t)[:, None] + np.arange(3)[None, :]], axis=1)      # (T-2, V)
        ok &= low > scene.floor + 0.5 * edge + step
    if prob.sim.terms.contact is not None and topo.n_objects > 1:
        thick = max(prob.sim.terms.contact.thickness) if prob.sim.terms.contact.thickness else edge
        reach = thick + 2.0 * edge
        vobj = np.asarray(topo.vertex_object)
        for i in range(t):
            x = xs[i + 1]
            for o in range(topo.n_objects):
                mine, other = vobj == o, vobj != o
                d2 = np.min(np.sum((x[mine][:, None, :] - x[other][None, :, :]) ** 2, axis=-1), axis=1)
                ok[i, np.flatnonzero(mine)] &= np.sqrt(d2) > reach + 2.0 * step[i, mine]
    return ok


def frames_with_start(prob, frames=None):
    """(T+1, V, 3) float64 positions and (T+1,) times, s: the scene's start at step 0, then the
    target's frames (or ``frames``, on the target's steps)."""
    x = np.asarray(prob.target.positions if frames is None else frames, np.float64)
    x0 = np.asarray(prob.sim.topology.x0, np.float64)[None]
    steps = np.concatenate([[0], np.asarray(prob.target.steps, np.int64)])
    return np.concatenate([x0, x]), steps * float(prob.target.dt)


def equation_error(prob, frames=None):
    """The equation-error estimate of ``prob``'s fitted parameters from its target's frames (or
    from ``frames``, (T, V, 3) positions on the target's steps): :class:`Estimate`.

    Needs a positions target (every vertex observed in every frame) and the parameters fitted
    among :data:`LINEAR`; raises ValueError otherwise."""
    if not prob.target.kind.every_vertex:
        raise ValueError(f"the equation-error estimate needs a positions target, not {prob.target.kind!r}")
    bad = [n for n in prob.names if n not in LINEAR]
    if bad:
        raise ValueError(f"the equation-error estimate fits {', '.join(LINEAR)}; not {', '.join(bad)}")
    xs, times = frames_with_start(prob, frames)
    if len(xs) < 3:
        raise ValueError("the equation-error estimate needs at least two frames after the start")
    topo = prob.sim.topology
    h1 = (times[1:-1] - times[:-2])[:, None, None]
    h2 = (times[2:] - times[1:-1])[:, None, None]
    v, a = _fd(xs[:-2], xs[1:-1], xs[2:], h1, h2)                            # (T-1, V, 3)
    # frames one step apart: the velocity the step's forces see is Verlet's half-step velocity
    # u_n = (x_n - x_(n-1)) / dt, which makes the balance exact for the model (to rounding)
    one = np.isclose(h1, prob.target.dt, rtol=1e-9) & np.isclose(h2, prob.target.dt, rtol=1e-9)
    v = np.where(one, (xs[1:-1] - xs[:-2]) / h1, v)
    ok = _masks(prob, xs)
    base = prob.base
    vobj = np.asarray(topo.vertex_object)
    mass = (np.asarray(base.total_weight, np.float64) / np.asarray(topo.count, np.float64))[vobj]      # (V,)
    kernel, terms = _kernel(prob)
    dtype = prob.sim.dtype
    # (converted on the host and put on the device: no one-op conversion program to compile)
    host = np.dtype(dtype)
    xt = jax.device_put(np.ascontiguousarray(np.swapaxes(xs[1:-1], 1, 2), host))
    vt = jax.device_put(np.ascontiguousarray(np.swapaxes(v, 1, 2), host))

    def force(**on):
        vals = {n: np.zeros_like(np.asarray(getattr(base, n), np.float64)) for n in PARAM_NAMES}
        vals["total_weight"] = np.asarray(base.total_weight, np.float64)
        for n, val in on.items():
            vals[n] = np.broadcast_to(np.asarray(val, np.float64), (topo.n_objects,)).copy()
        p = type(base)(**{n: jax.device_put(np.asarray(vals[n], host)) for n in PARAM_NAMES})
        return np.swapaxes(np.asarray(kernel(p, xt, vt), np.float64), 1, 2)      # (T-1, V, 3)

    fitted = set(prob.names)
    if np.shape(base.k_structural) != (topo.n_objects,):
        raise ValueError("the equation-error estimate needs one spring stiffness per object, not a field")
    reg = {"k_structural": force(k_structural=1.0)}
    if terms.dashpot:
        reg["dashpot"] = force(dashpot=1.0)
    if terms.gas:
        reg["nmol"] = force(nmol=1.0)
    rate_fitted = bool(fitted & {"drag", "damping"})
    dt = float(prob.target.dt)
    rate_d = damping_rate(base.damping, dt)
    rate_known = np.zeros(topo.n_objects)
    if not rate_fitted:
        rate_known = rate_known + (np.asarray(base.drag, np.float64) if terms.drag else 0.0) + (
            rate_d if terms.verlet_damping else 0.0)
    known = np.zeros_like(a)
    for n, r in reg.items():
        if n not in fitted:
            known += np.asarray(getattr(base, n), np.float64)[vobj][None, :, None] * r
    gravity = np.asarray(prob.scene.gravity, np.float64) if terms.gravity else np.zeros(3)
    lhs = a - gravity - known / mass[None, :, None] + rate_known[vobj][None, :, None] * v
    cols = [n for n in ("k_structural", "dashpot", "nmol") if n in fitted and n in reg]
    out = {n: np.full(len(prob.objects), np.nan) for n in prob.names}
    rate = np.full(len(prob.objects), np.nan)
    rows = np.zeros(len(prob.objects), np.int64)
    clamped = []
    for j, o in enumerate(prob.objects):
        sel = ok & (vobj == o)[None, :]                                      # (T-1, V)
        design = [(reg[n] / mass[None, :, None])[sel] for n in cols]
        if rate_fitted:
            design.append(-v[sel])
        rows[j] = int(sel.sum())
        if rows[j] == 0 or not design:
            continue
        A = np.stack([d.reshape(-1) for d in design], axis=1)
        b = lhs[sel].reshape(-1)
        scale = np.linalg.norm(A, axis=0)
        scale[scale == 0] = 1.0
        coef = np.linalg.lstsq(A / scale, b, rcond=None)[0] / scale
        for c, n in enumerate(cols):
            out[n][j] = coef[c]
        if rate_fitted:
            rate[j] = coef[-1]
            drag0 = float(np.asarray(base.drag, np.float64)[o]) if terms.drag else 0.0
            rd0 = float(rate_d[o]) if terms.verlet_damping else 0.0
            if "drag" in fitted and "damping" in fitted:
                # one rate, two names: the start's split kept
                share = drag0 / (drag0 + rd0) if drag0 + rd0 > 0 else 0.5
                out["drag"][j] = share * rate[j]
                out["damping"][j] = _damping_of_rate((1 - share) * rate[j], dt)
            elif "drag" in fitted:
                out["drag"][j] = rate[j] - rd0
            else:
                out["damping"][j] = _damping_of_rate(rate[j] - drag0, dt)
    coef = {n: (rate if n in ("drag", "damping") else out[n]).copy() for n in prob.names}
    start = prob.start
    for n in prob.names:
        bad = ~(np.isfinite(out[n]) & (out[n] > 0))
        for j in np.flatnonzero(bad):
            clamped.append(f"{n}[{prob.objects[j]}]")
        out[n] = np.where(bad, start[n], out[n])
    masked = 1.0 - float(ok.sum()) / max(ok.size, 1)
    return Estimate(values=out, rate=rate, rows=rows, masked=masked, clamped=tuple(clamped), coef=coef)


def damping_rate(damping, dt, substeps=1):
    """(numpy, float64) the report's damping D as a velocity-decay rate, 1/s: f / dt with f = 1/D
    (0 for D <= 0). Verlet's update gives (x_(n+1) - 2 x_n + x_(n-1)) / dt^2 = a_n - (f / dt) u_n
    exactly, the same form as drag's -gamma u_n, so the balance is linear in f / dt (which is
    -ln(1 - f) / dt, the decay rate, to first order in f), and f / dt + gamma is exactly what a
    target determines of the two. With s substeps of h = dt / s each keeps (1 - f)^(1/s) of u:
    the rate is s (1 - (1 - f)^(1/s)) / dt."""
    d = np.asarray(damping, np.float64)
    f = np.where(d > 0, 1.0 / np.where(d > 0, d, 1.0), 0.0)
    if int(substeps) == 1:
        return f / float(dt)
    s = int(substeps)
    return s * (1.0 - np.power(1.0 - np.minimum(f, 1.0), 1.0 / s)) / float(dt)


def _damping_of_rate(rate, dt):
    """The report's damping D of a rate f / dt (:func:`damping_rate`); NaN where the rate is not
    positive."""
    if not (np.isfinite(rate) and rate > 0):
        return math.nan
    return 1.0 / (rate * dt)


@dataclasses.dataclass(frozen=True)
class IndirectInference:
    """The result of :func:`indirect_inference`.

    Attributes:
      theta: (P_n, O_f) log values of the problem's fitted parameters.
      values: dict name -> (O_f,) the same, as values.
      raw: the :class:`Estimate` of the target (the first theta).
      history: per iteration, (theta, the largest log change it made).
      rollouts: rollouts run.
      converged: the last change was below ``tol``.
      undetermined: the pair ("damping", "drag") when both are fitted (their split is the start's).
    """

    theta: np.ndarray
    values: dict
    raw: Estimate
    history: tuple
    rollouts: int
    converged: bool
    undetermined: tuple = ()


def _stat(prob, est, ref):
    """The statistic indirect inference matches: per fitted name and object, asinh(c / ref) of the
    estimated coefficient c (k, c, nmol, or the combined decay rate for the drag and the damping):
    about log c + const where c >> ref, and smooth and signed through zero, where a log would break
    on an estimate at or below zero."""
    return np.stack([np.arcsinh(np.nan_to_num(est.coef[n]) / ref[i]) for i, n in enumerate(prob.names)])


def _references(prob):
    """(P_n, O_f) the scales of :func:`_stat`: each start value (for the drag and the damping, the
    start's combined rate), and (P_n,) the sign of d stat / d log value (-1 for the
    damping D, whose rate falls as D grows)."""
    start, dt, objs = prob.start, float(prob.target.dt), list(prob.objects)
    terms = prob.sim.terms
    drag0 = np.asarray(prob.base.drag, np.float64)[objs] if terms.drag else 0.0
    rd0 = (damping_rate(np.asarray(prob.base.damping, np.float64)[objs], dt)
           if terms.verlet_damping else 0.0)
    rate0 = np.maximum(np.broadcast_to(drag0 + rd0, (len(objs),)), 1e-12)
    ref = np.stack([rate0 if n in ("drag", "damping") else np.abs(start[n]) for n in prob.names])
    return ref, np.array([-1.0 if n == "damping" else 1.0 for n in prob.names])


def indirect_inference(prob, iterations=8, tol=1e-3, seed=0, frames_fn=None, fd_jacobian=True, theta=None):
    """Indirect inference on the equation-error estimate: a start for ``prob`` from its target alone.

    Starts at the target's own estimate (or ``theta``) and iterates theta <- theta + J^-1 [s(target)
    - s(simulated at theta)], s the :func:`_stat` of :func:`equation_error` and J its Jacobian in
    the log values: measured once by differences (``fd_jacobian``; one batch of rollouts, one per
    fitted value), then updated by Broyden's rule. At most ``iterations`` rounds; stops when no
    statistic differs by more than ``tol``. A rollout that fails halves the step back towards the
    last good theta. Where the problem has measurement noise (``prob.noise``), noise of that sigma
    (drawn once, from ``seed``) is added to the simulated frames, so that it biases both sides
    alike.

    ``frames_fn(thetas (N, P_n, O_f)) -> (frames (N, T, V, 3), ok (N,))``: how frames are simulated
    on the target's steps (default: the problem's own rollout,
    :meth:`jaxplush.fitting.objective.problem.Problem.frames`, one point at a time; a fit passes its batched
    evaluator, :func:`evaluator_frames`)."""
    if frames_fn is None:
        def frames_fn(thetas):
            out, oks = [], []
            for th in np.asarray(thetas, np.float64):
                frames, codes = prob.frames(jnp.asarray(th, prob.sim.dtype))
                frames = np.asarray(frames, np.float64)
                out.append(frames)
                oks.append(bool(np.all(np.asarray(codes) == 0)) and bool(np.all(np.isfinite(frames))))
            return np.stack(out), np.asarray(oks)

    def one(th):
        fr, ok = frames_fn(np.asarray(th, np.float64)[None])
        return fr[0], bool(ok[0])
    raw = equation_error(prob)
    ref, sign = _references(prob)
    s_target = _stat(prob, raw, ref)
    theta = np.stack([np.log(raw.values[n]) for n in prob.names]) if theta is None else np.array(theta, np.float64)
    noise = None
    if prob.noise:
        noise = np.random.default_rng(seed).normal(0.0, float(prob.noise), prob.target.positions.shape)
    history, rollouts, converged = [], 0, False
    good = None                      # (theta, s_sim) of the last rollout that ran
    jac0 = np.diag(np.repeat(sign, theta.shape[1]))
    jac = jac0.copy()                # Broyden's estimate of d s_sim / d theta (flattened)
    for _ in range(int(iterations)):
        frames, ok = one(theta)
        rollouts += 1
        if not ok:
            if good is None:
                if np.array_equal(theta, prob.theta0):
                    break
                theta = np.array(prob.theta0, np.float64)     # the estimate does not run: the given start
                history.append((theta.copy(), math.nan))
                continue
            theta = good[0] + 0.5 * (theta - good[0])
            history.append((theta.copy(), math.nan))
            continue
        if noise is not None:
            frames = frames + noise
        s_sim = _stat(prob, equation_error(prob, frames), ref)
        if good is None and fd_jacobian:
            # the estimator's sensitivities are far from the identity where frames alias (they mix
            # the parameters of one object): measured once, one batch with a rollout per fitted value
            pts = theta.ravel()[None] + FD_STEP * np.eye(theta.size)
            fr, ok_j = frames_fn(pts.reshape((theta.size,) + theta.shape))
            rollouts += theta.size
            if np.all(ok_j):
                cols = [(_stat(prob, equation_error(prob, f if noise is None else f + noise), ref) - s_sim).ravel()
                        / FD_STEP for f in fr]
                jac = np.stack(cols, axis=1)
                jac0 = jac.copy()
        elif good is not None:
            d_theta, d_s = (theta - good[0]).ravel(), (s_sim - good[1]).ravel()
            if d_theta @ d_theta > 0:
                jac = jac + np.outer(d_s - jac @ d_theta, d_theta) / (d_theta @ d_theta)
        good = (theta.copy(), s_sim)
        change = s_target - s_sim
        big = float(np.max(np.abs(change)))
        if big < tol:
            converged = True
            history.append((theta.copy(), big))
            break
        step = np.linalg.lstsq(jac, change.ravel(), rcond=1e-8)[0].reshape(theta.shape)
        if not np.all(np.isfinite(step)) or np.max(np.abs(step)) > 4 * max(big, 0.05):
            jac = jac0.copy()                                  # Broyden went astray: start it afresh
            step = np.linalg.lstsq(jac, change.ravel(), rcond=1e-8)[0].reshape(theta.shape)
        step = step * min(1.0, MAX_STEP / max(float(np.max(np.abs(step))), 1e-300))
        theta = theta + step
        history.append((theta.copy(), big))
    values = {n: np.exp(theta[i]) for i, n in enumerate(prob.names)}
    undetermined = ()
    if {"damping", "drag"} <= set(prob.names):
        # one rate, two names: the rate found, split as at the start
        undetermined = ("damping", "drag")
        theta = _split_as_start(prob, theta)
        values = {n: np.exp(theta[i]) for i, n in enumerate(prob.names)}
    return IndirectInference(theta=theta, values=values, raw=raw, history=tuple(history), rollouts=rollouts,
                             converged=converged, undetermined=undetermined)


def suits(prob):
    """Whether :func:`indirect_inference` applies to a problem: a positions target of at least two
    frames, every fitted parameter in :data:`LINEAR`, one spring stiffness per object, and single
    shooting (multiple shooting's evaluator runs segments, not the free run the statistic needs)."""
    sh = getattr(prob, "shooting", None)
    return (prob.target.kind.every_vertex and prob.target.n_frames >= 2 and set(prob.names) <= set(LINEAR)
            and np.shape(prob.base.k_structural) == (prob.sim.topology.n_objects,)
            and not (sh is not None and getattr(sh, "on", False)))


def evaluator_frames(evaluator):
    """``frames_fn`` of :func:`indirect_inference` on a fit's batched evaluator
    (:class:`jaxplush.fitting.objective.evaluate.Evaluator`): the points' frames on its target's steps, each
    point run once at its predicted substeps (no retries)."""
    def frames_fn(thetas):
        e = evaluator(np.asarray(thetas, np.float64), keep_frames=True, retries=0)
        if e.frames is None:
            return np.full((len(thetas),) + evaluator.prob.target.positions.shape, np.nan), np.zeros(len(thetas), bool)
        return np.asarray(e.frames, np.float64), np.asarray(e.ok, bool)
    return frames_fn


def _split_as_start(prob, theta):
    """``theta`` with its drag and damping re-split, object by object, as the start values split
    their combined decay rate (drag + the damping's rate), the rate kept
    (:meth:`jaxplush.fitting.stages.search.Ties.project`, the line the local searches keep to)."""
    from jaxplush.fitting.stages.search import Ties
    return Ties.for_problem(prob).project(np.asarray(theta, np.float64))


def design_point(objective):
    """The global stage's design point from indirect inference
    (:func:`indirect_inference`, its rollouts on the objective's batched evaluator): log values,
    or all NaN where it does not suit the problem or found nothing that runs (so that a resumed
    stage does not try again)."""
    prob = objective.prob
    nothing = np.full(np.shape(prob.theta0), np.nan)
    if not suits(prob):
        return nothing
    try:
        ii = indirect_inference(prob, frames_fn=evaluator_frames(objective.evaluator))
    except (ValueError, np.linalg.LinAlgError, FloatingPointError):
        return nothing
    if not ii.history or not np.all(np.isfinite(ii.theta)):
        return nothing
    return ii.theta
