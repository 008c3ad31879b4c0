"""Identifiability at the optimum: the Gauss-Newton matrix in log-parameters (docs/model.md §9).

With theta = log(fitted parameters) and the residual features r(theta) = simulated positions at
the target's frames minus the target, J = dr/dtheta is computed column by column with
forward-mode JVPs through the rollout (:func:`frames_at_steps`; one JVP per fitted parameter).
From J^T J:

* the condition number; above :data:`COND_WARN` (1e6) the weakest parameter combinations are
  described in words ("only the ratio k_structural/nmol is determined");
* the sensitivity of the frames to each parameter, RMS metres per unit change of log p; a
  parameter whose sensitivity is below :data:`SENSITIVITY_WARN` of the largest one is "not
  determined by the target" (damping from a settled, static shape);
* approximate standard errors of log p (relative errors of p), from the residual variance times
  (J^T J)^-1;
* with the rounding noise of a finite-difference J (``jac_noise``: a float32 rollout's own
  reproducibility drift over the fitted frames, the RMS distance of two runs that differ by
  rounding, divided by 2 h for central differences of step h), the parameter combinations J
  does not resolve: an eigen-direction of J^T J whose
  effect on the frames, RMS metres per unit step in log space, is at most
  :data:`RESOLVE_FACTOR` times that noise is rounding, not signal. The condition number alone
  cannot tell: two exactly degenerate parameters (the report's ``damping`` and air ``drag``
  both decay every velocity uniformly) give a float32 J^T J a condition number of only about
  1e5-1e6, set by the noise. Their standard errors are infinite and they are "not determined
  individually". For a noise-free target the residual variance is rounding too, so these
  standard errors alone would call such a pair determined to 1e-5.

For point-cloud targets J is that of the simulated vertex positions and the residuals are the
distances from each vertex to its nearest target point (the Gauss-Newton view of the
vertex-to-cloud half of the Chamfer loss). For tracks targets J is mapped to the tracked points
(linear in the vertices) and the residuals are the seen tracks' simulated minus observed positions.
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np

from jaxplush.stepping import diagnostics

#: Condition number of J^T J above which the weakest combination is reported.
COND_WARN = 1e6
#: A parameter whose sensitivity is below this fraction of the largest is "not determined".
SENSITIVITY_WARN = 1e-3
#: Eigenvalues below this fraction of the largest count as weak directions.
WEAK_EIG = 1.0 / COND_WARN
#: Relative standard error above which a parameter is "poorly determined".
STDERR_WARN = 0.5
#: Eigenvalues below this fraction of the largest are treated as zero (a float32 Jacobian resolves
#: J^T J to about (1e-6)² of its largest eigenvalue): the standard errors along them are infinite.
SINGULAR_EIG = 1e-10
#: A parameter combination is resolved only when a unit step along it (log space) moves the frames
#: by more than this many times the Jacobian's rounding noise (RMS m per unit step).
RESOLVE_FACTOR = 3.0
#: A parameter whose squared weight in the unresolved combinations exceeds this (a component of
#: about 0.03: a unit step along them moves it by 3%) is not determined individually.
UNRESOLVED_WEIGHT = 1e-3


def frames_at_steps(sim, params, state0, steps, step0=0):
    """Positions at the given steps of one rollout, with each frame's health.

    Differentiable in forward and reverse mode (``jax.jvp``/``jax.jacfwd`` give the trajectory
    features' Jacobian). The rollout advances in blocks of g = gcd of the frame spacings and
    writes each frame into a (T, 3, V) buffer, so memory is O(T V), not O(steps V).

    Args:
      sim: :class:`jaxplush.stepping.step.Simulator`.
      params: :class:`jaxplush.types.Params`.
      state0: public initial state (step 0).
      steps: static increasing step indices (>= 0).
      step0: the step index of ``state0`` (static; read only by scenes with driven vertices,
        whose paths depend on time; ``steps`` count from ``state0``).

    Returns:
      (frames (T, V, 3), codes (T, O) int32 health codes, :mod:`jaxplush.stepping.diagnostics`). With
      soft-soft contact, an object whose candidates overflowed their capacity in some step up to a
      frame (a fresh search's count at the positions each step starts from) has the code
      ``CONTACT_OVERFLOW`` there and at every later frame.
    """
    steps = [int(s) for s in steps]
    if not steps or steps[0] < 0 or any(b <= a for a, b in zip(steps, steps[1:])):
        raise ValueError(f"steps must be increasing and >= 0, got {steps}")
    g = 0
    prev = 0
    for s in steps:
        g = math.gcd(g, s - prev)
        prev = s
    g = g or 1
    n_blocks = steps[-1] // g
    slot = np.full(n_blocks + 1, len(steps), np.int32)  # block b ends at step b*g; len(steps) = discard
    for j, s in enumerate(steps):
        slot[s // g] = j
    s0 = sim.internal.to_internal(state0)
    buf = jnp.zeros((len(steps) + 1,) + s0.x.shape, s0.x.dtype)
    buf = buf.at[slot[0]].set(s0.x)
    # soft-soft contact (searched afresh every step): a sticky per-object flag of the search's
    # capacity overflow at the positions each step starts from, recorded with each frame
    check = sim.internal.overflow
    n_obj = sim.topology.n_objects
    flag0 = jnp.zeros((n_obj,), bool)
    fbuf = jnp.zeros((len(steps) + 1, n_obj), bool)
    slot = jnp.asarray(slot)

    driven = bool(sim.terms.driven)

    def block(carry, b):
        state, flag, buf, fbuf = carry

        def one(i, c):                      # step (b - 1) g + i of the rollout
            s, flag = c
            n = step0 + (b - 1) * g + i if driven else None
            return sim.internal.step(params, s, n), (flag | check(s.x)) if check is not None else flag
        state, flag = jax.lax.fori_loop(0, g, one, (state, flag))
        buf = buf.at[slot[b]].set(state.x)
        fbuf = fbuf.at[slot[b]].set(flag)
        return (state, flag, buf, fbuf), None

    if n_blocks:
        (_, _, buf, fbuf), _ = jax.lax.scan(block, (s0, flag0, buf, fbuf), jnp.arange(1, n_blocks + 1))
    frames = jnp.swapaxes(buf[:-1], 1, 2)
    codes = jax.vmap(lambda x: diagnostics.object_status(sim.topology, sim.terms, x))(frames)
    if check is not None:
        codes = diagnostics.with_overflow(codes, fbuf[:-1])
    return frames, codes


@dataclasses.dataclass(frozen=True, eq=False)
class IdentifiabilityReport:
    """The Gauss-Newton view of a fit at its optimum.

    Attributes:
      labels: (P,) "name[object]" of each fitted parameter (the columns of J).
      jtj: (P, P) J^T J in log-parameters (m² per unit log²).
      eigenvalues: (P,) ascending; eigenvectors: (P, P) columns (of the determined block,
        embedded; undetermined parameters get zero rows).
      condition: condition number of J^T J over the determined parameters (inf if singular).
      sensitivity: (P,) RMS change of the frames (m) per unit change of log p (= ||J_i||/sqrt(n)).
      stderr: (P,) approximate standard error of log p, i.e. the relative error of p (inf when
        not determined).
      sigma: residual RMS per coordinate used for the standard errors (m).
      n_data: number of residuals (3 x vertices x frames).
      determined: (P,) bool.
      weak: list of (eigenvalue / largest, {label: component}) weak directions (cond > 1e6).
      weakest: the weakest parameter combination (eigenvector of the smallest eigenvalue), in words.
      warnings: list of messages.
      jac_noise: the Jacobian's rounding noise, RMS m per unit step in log space (NaN: not known).
      unresolved: list of (RMS effect per unit step (m), {label: component}) combinations within
        :data:`RESOLVE_FACTOR` of ``jac_noise``.
    """

    labels: tuple
    jtj: np.ndarray
    eigenvalues: np.ndarray
    eigenvectors: np.ndarray
    condition: float
    sensitivity: np.ndarray
    stderr: np.ndarray
    sigma: float
    n_data: int
    determined: np.ndarray
    weak: list
    weakest: str
    warnings: list
    jac_noise: float = math.nan
    unresolved: list = dataclasses.field(default_factory=list)

    @property
    def undetermined(self):
        """Labels of the parameters the target does not determine: insensitive ones, those in an
        unresolved combination (infinite standard error) and those whose standard error exceeds
        :data:`STDERR_WARN`."""
        bad = ~np.asarray(self.determined, bool) | ~np.isfinite(self.stderr) | (np.asarray(self.stderr) > STDERR_WARN)
        return tuple(lab for lab, b in zip(self.labels, bad) if b)

    def summary(self, standard_errors=True):
        """Several lines of text: standard errors (or "n/a" when ``standard_errors`` is False: for a
        fit that did not reach the data they mean nothing), condition number, warnings."""
        lines = [f"identifiability (Gauss-Newton J^T J in log-parameters, {self.n_data} residuals, "
                 f"residual RMS {self.sigma:.3g} m): condition number {self.condition:.3g}"]
        for lab, s, e, d in zip(self.labels, self.sensitivity, self.stderr, self.determined):
            if not standard_errors:
                err = "n/a (not converged)"
            else:
                err = f"+-{100 * e:.3g}%" if np.isfinite(e) else "undetermined"
            lines.append(f"  {lab:<28} sensitivity {s:.3g} m per e-fold   std. error {err}"
                         + ("" if d else "   NOT DETERMINED"))
        if self.weakest:
            lines.append(f"  weakest combination: {self.weakest}")
        lines += [f"  warning: {w}" for w in self.warnings]
        return "\n".join(lines)

    def as_dict(self):
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}


def frames_and_jacobian(frames_fn, theta):
    """Frames, health codes and the Jacobian of the frames, in one compiled forward-mode pass.

    Args:
      frames_fn: ``theta -> (frames (T, V, 3), codes (T, O))`` (e.g. built on
        :func:`frames_at_steps`).
      theta: (P_n, O_f) log-parameters.

    Returns:
      (frames (T, V, 3) float64, codes (T, O), jac (3 T V, P) float64): one JVP per entry of
      theta, vmapped; the primal rollout is shared by all of them.
    """
    theta = jnp.asarray(theta)
    shape, n = theta.shape, theta.size

    def run(flat):
        f = lambda t: frames_fn(t.reshape(shape))  # noqa: E731
        basis = jnp.eye(n, dtype=flat.dtype)
        return jax.vmap(lambda t: jax.jvp(f, (flat,), (t,), has_aux=True), out_axes=(None, 0, None))(basis)

    frames, tangents, codes = jax.jit(run)(theta.ravel())
    jac = np.asarray(tangents, np.float64).reshape(n, -1).T
    return np.asarray(frames, np.float64), np.asarray(codes), jac


def analyse(jac, residual, labels, noise=None, jac_noise=None):
    """Build the :class:`IdentifiabilityReport` from J and the residuals at the optimum.

    Args:
      jac: (n, P) Jacobian of the residual features with respect to log-parameters.
      residual: (n,) residuals at the optimum (m).
      labels: P names for the columns.
      noise: known measurement noise per coordinate (m), to compare with the residuals.
      jac_noise: the rounding noise of J's columns, RMS m per unit step in log space
        (:func:`fd_noise`), or None (not known: every direction counts as resolved).
    """
    jac = np.asarray(jac, np.float64)
    residual = np.asarray(residual, np.float64).ravel()
    n, p = jac.shape
    labels = tuple(labels)
    warnings = []
    finite = np.isfinite(jac).all()
    if not finite:
        jac = np.nan_to_num(jac, nan=0.0, posinf=0.0, neginf=0.0)
        warnings.append("the Jacobian has non-finite entries (set to 0): the rollout is unstable near the optimum")
    sens = np.linalg.norm(jac, axis=0) / math.sqrt(max(n, 1))
    smax = sens.max() if p else 0.0
    determined = sens > SENSITIVITY_WARN * smax if smax > 0 else np.zeros(p, bool)
    for i in np.nonzero(~determined)[0]:
        ratio = sens[i] / smax if smax > 0 else 0.0
        warnings.append(f"{labels[i]} is not determined by the target: a 10% change moves the fitted "
                        f"frames by {0.1 * sens[i]:.2g} m RMS ({ratio:.1e} of the most sensitive "
                        "parameter's effect)")
    jtj = jac.T @ jac
    dof = max(n - p, 1)
    sigma2 = float(residual @ residual) / dof
    sigma = math.sqrt(sigma2)
    idx = np.nonzero(determined)[0]
    evals = np.zeros(p)
    evecs = np.zeros((p, p))
    stderr = np.full(p, np.inf)
    weak = []
    unresolved = []
    weakest = ""
    cond = math.inf
    if idx.size:
        sub = jtj[np.ix_(idx, idx)]
        w, v = np.linalg.eigh(sub)
        evals[:idx.size] = w
        evecs[np.ix_(idx, np.arange(idx.size))] = v
        wmax = w.max()
        cond = float(wmax / w.min()) if w.min() > 0 else math.inf
        good = w > wmax * SINGULAR_EIG
        inv_diag = (v[:, good] ** 2 / w[good]).sum(axis=1)
        bad_dirs = (v[:, ~good] ** 2).sum(axis=1) > 1e-6
        se = np.sqrt(sigma2 * inv_diag)
        se[bad_dirs] = np.inf

        def direction(k):
            vk = v[:, k] * np.sign(v[np.argmax(np.abs(v[:, k])), k])   # largest component positive
            return {labels[i]: float(vk[j]) for j, i in enumerate(idx)}

        if jac_noise is not None and np.isfinite(jac_noise) and jac_noise > 0:
            effect = np.sqrt(np.maximum(w, 0.0) / max(n, 1))            # RMS m per unit step along v_k
            lost = effect <= RESOLVE_FACTOR * jac_noise
            unresolved = [(float(effect[k]), direction(k)) for k in np.nonzero(lost)[0]]
            weight = (v[:, lost] ** 2).sum(axis=1)
            se[weight > UNRESOLVED_WEIGHT] = np.inf
            if unresolved:
                names = [labels[i] for j, i in enumerate(idx) if weight[j] > UNRESOLVED_WEIGHT]
                worst = max(e for e, _ in unresolved)
                warnings.append(
                    f"{', '.join(names)} {'is' if len(names) == 1 else 'are'} not determined individually: along "
                    f"{len(unresolved)} combination(s) of them a unit step in log space moves the frames by at most "
                    f"{worst:.2g} m RMS, within {RESOLVE_FACTOR:g}x the rounding noise of the finite-difference "
                    f"Jacobian ({jac_noise:.2g} m); the target does not tell these values apart"
                    + ("" if len(unresolved) > 1 else f" ({describe_direction(unresolved[0][1])})"))
        stderr[idx] = se

        if idx.size > 1:
            comp = direction(0)
            terms = ", ".join(f"{c:+.2f} log {k}" for k, c in sorted(comp.items(), key=lambda kv: -abs(kv[1])))
            weakest = (f"{terms} (eigenvalue {w[0] / wmax:.2g} of the largest)" if cond <= COND_WARN
                       else describe_direction(comp))
        if cond > COND_WARN:
            for k in np.nonzero(w <= wmax * WEAK_EIG)[0]:
                comp = direction(k)
                weak.append((float(w[k] / wmax), comp))
                warnings.append(f"J^T J is ill-conditioned (condition number {cond:.2g}): "
                                f"{describe_direction(comp)}")
    for i in idx:
        if np.isfinite(stderr[i]) and stderr[i] > STDERR_WARN and sigma > 0:
            warnings.append(f"{labels[i]} is poorly determined: standard error about {100 * stderr[i]:.0f}%")
    if noise is not None and noise > 0 and sigma > 3 * noise:
        warnings.append(f"the residuals ({sigma:.3g} m RMS per coordinate) are well above the stated noise "
                        f"({noise:.3g} m): the model does not reproduce the target")
    for pair in shared_regressors(labels):
        # exactly one regressor for the two (the model's own algebra, whatever a rounded Jacobian
        # shows): neither value is determined, only their rate (jaxplush.fitting.judge.intervals.combinations)
        stderr[list(pair)] = np.inf          # (still sensitive: twins step along the pair, which moves the rate)
        a, b = (labels[i] for i in pair)
        warnings.append(f"{a} and {b} take the same share of every vertex's velocity off at every step, so the "
                        f"target determines only their combined rate (reported as damping+drag rate), not the "
                        "split between them")
    return IdentifiabilityReport(labels=labels, jtj=jtj, eigenvalues=evals, eigenvectors=evecs, condition=cond,
                                 sensitivity=sens, stderr=stderr, sigma=sigma, n_data=n, determined=determined,
                                 weak=weak, weakest=weakest, warnings=warnings,
                                 jac_noise=math.nan if jac_noise is None else float(jac_noise), unresolved=unresolved)


def shared_regressors(labels):
    """Pairs (i, j) of column indices of ``labels`` ("name[object]") that share one regressor in
    the model, so that no target tells them apart: the report's ``damping`` and air ``drag`` of one
    object (the Verlet update takes 1/D of the half-step velocity off per step, and drag gamma dt
    of it; docs/model.md)."""
    index = {lab: i for i, lab in enumerate(labels)}
    out = []
    for lab, i in index.items():
        if lab.startswith("damping["):
            j = index.get("drag[" + lab[len("damping["):])
            if j is not None:
                out.append((i, j))
    return out


def fd_noise(drift, h):
    """The rounding noise of a central-difference Jacobian column (RMS m per unit step in log
    space). ``drift`` is the RMS distance between two rollouts that differ only by rounding (RMS m,
    as :mod:`jaxplush.stepping.predictability` measures it, and as a fit's residual against a
    target that is itself a rollout is): the column differences two such rollouts, over 2 h.
    Measured on a 642-vertex bean at the truth (drift 0.032 mm, h = 1e-3, eight steps from 1e-3
    to 1.09e-3): 9.5-18.6 mm per column, against 16 mm from this formula."""
    return float(drift) / (2.0 * float(h))


def describe_direction(comp):
    """Words for a weak direction {label: component} in log-parameters."""
    big = {k: c for k, c in comp.items() if abs(c) >= 0.2}
    if len(big) == 1:
        (k, _), = big.items()
        return f"{k} is (nearly) undetermined"
    terms = ", ".join(f"{c:+.2f} log {k}" for k, c in sorted(big.items(), key=lambda kv: -abs(kv[1])))
    if len(big) == 2:
        (a, ca), (b, cb) = big.items()
        same = ca * cb > 0
        if abs(abs(ca) - abs(cb)) < 0.2 * max(abs(ca), abs(cb)):
            combo = f"{a}/{b}" if same else f"{a}*{b}"
        else:
            ea, eb = abs(cb) / max(abs(ca), abs(cb)), abs(ca) / max(abs(ca), abs(cb))
            combo = f"{a}^{ea:.2f}/{b}^{eb:.2f}" if same else f"{a}^{ea:.2f}*{b}^{eb:.2f}"
        how = "grow together" if same else "trade off (one up, the other down)"
        return (f"{a} and {b} can {how} with almost no change of the trajectory: only the "
                f"{'ratio' if same else 'product'} {combo} is determined (weak direction {terms})")
    return f"only combinations orthogonal to the weak direction {terms} are determined"
