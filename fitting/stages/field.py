"""Fit a spatially varying spring stiffness: a field over the edges, or one value per face group.

A scene's ``k_structural`` may be an (E,) field over its springs (``Scene.edges`` order; scene
keywords ``g NAME``, ``k_region NAME K`` and ``k_edge I J K``, docs/formats.md §2.4). This module
recovers such a field from a target (positions, a depth camera's point clouds, tracks) together
with the material parameters that stay global (the damping model the scene uses and ``nmol``):

* the unknowns are log values, theta = (log k field, log globals): per edge, E values
  (``field="edges"``), or per region, one value per face group (``field="regions"``; an edge gets
  the mean of its two faces' regions, :meth:`jaxplush.scene.parse.Scene.region_edges`; an
  object's faces outside every group form one more region of that object), then each global
  per object;
* the objective is the data loss of :func:`jaxplush.fitting.objective.losses.make_loss` (the same
  normalised loss every fit uses) plus a smoothness regulariser on the log field,

      R(theta) = weight * sum over adjacent pairs (log k_a - log k_b)²,

  adjacent being edges that share a triangle (``edges``) or regions that share an edge
  (``regions``): :func:`edge_pairs`, :func:`region_pairs`. Its gradient is 2 weight L log k,
  L the graph Laplacian (:func:`laplacian`);
* gradients come from :func:`jaxplush.fitting.objective.gradients.rollout_loss` (the fused adjoint where the
  simulator supports it, else checkpointed reverse mode), the optimiser is optax's L-BFGS with
  its zoom line search (default) or Adam, in the loop of :mod:`jaxplush.fitting.stages.gradfit` (a step whose
  rollout blows up is rejected and halved; the same stopping rules), float32 unless x64 is on.

The default weight (:func:`default_weight`) reads the regulariser as a prior: with a known noise
the loss is L = chi² / N (N residuals; L ~ 1 at the noise level, :mod:`jaxplush.fitting.objective.losses`), so a
Gaussian prior of standard deviation tau on each neighbour difference of log k adds
sum (Δ log k)² / (N tau²): weight = 1 / (N tau²), with tau = :data:`DEFAULT_TAU`. A noise-free
target's loss is normalised by the target's motion instead (L = 1: no better than standing
still); the weight then takes the noise to be :data:`MOTION_NOISE` of the motion, a factor
MOTION_NOISE² smaller, so that the prior only fills in what exact data leave open.
benchmarks/bench_real_capture.py measured the choice of tau (docs/fitting.md, "A stiffness field").

:func:`fit_field` returns a :class:`FieldResult` (the field, the globals, the loss history and
the wall time); it writes FIT.h5 (:meth:`FieldResult.save`: the common layout plus
``fields/k_structural`` [E]), the fitted scene (:meth:`FieldResult.write_scene`: ``k_region`` or
``k_edge`` lines) and a picture of the field (:meth:`FieldResult.render`).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import os
import time
import types
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import optax

from jaxplush.compilestats import compile_clock
from jaxplush.errors import JaxplushError
from jaxplush.progress import Progress
from jaxplush.types import PARAM_NAMES, Params

from jaxplush.fitting.stages import gradfit as _gradfit
from jaxplush.fitting import options as _options
from jaxplush.fitting.errors import FitWarning
from jaxplush.fitting.judge.outcome import Stop
from jaxplush.fitting.objective.problem import build_problem, canonical_names, default_params

#: The kinds of field: one value per edge, or per face group (region).
FIELD_KINDS = ("edges", "regions")

#: beta of the preconditioner per kind of field (:func:`build_field_problem`): off. On the
#: acceptance bench's per-edge fit beta = 4 lowered the loss faster over the first 100 iterations
#: and ended where the plain fit ended (within 0.4%), so it is an option, not the default.
DEFAULT_PRECONDITION = {"edges": 0.0, "regions": 0.0}

#: L-BFGS's memory (optax's default is 10): on the bench's per-edge fit (1922 unknowns) 30 pairs
#: reached in 250 iterations a lower loss than 10 pairs in 400.
LBFGS_MEMORY = 30

#: The prior standard deviation of log k between neighbours that sets the default weight
#: (:func:`default_weight`).
DEFAULT_TAU = 0.5

#: The noise a noise-free (motion-normalised) target's default weight assumes, as a fraction of
#: the target's motion (:func:`default_weight`).
MOTION_NOISE = 1e-3


# --------------------------------------------------------------------------- the field's graph (numpy)

def face_edges(faces, edges):
    """(F, 3) int64: the index into ``edges`` (E, 2), sorted unique pairs as
    :func:`jaxplush.model.mesh.unique_edges` returns them, of each face's edges (a-b, b-c, c-a)."""
    from jaxplush.model.mesh import edge_index
    faces = np.asarray(faces, np.int64)
    out = np.stack([edge_index(edges, faces[:, a], faces[:, b]) for a, b in ((0, 1), (1, 2), (2, 0))], axis=1)
    if (out < 0).any():
        raise ValueError("a face's edge is missing from the edge list")
    return out


def edge_pairs(faces, edges):
    """(P, 2) int64 pairs of edges that share a triangle (i < j; P = 3 F, each pair once: two
    distinct edges share at most one triangle): the graph of the per-edge smoothness."""
    fe = face_edges(faces, edges)
    pairs = np.concatenate([fe[:, [0, 1]], fe[:, [1, 2]], fe[:, [0, 2]]])
    return np.unique(np.sort(pairs, axis=1), axis=0)


def region_pairs(faces, face_regions, n_regions):
    """(P, 2) int64 pairs of regions that share an edge (i < j, each pair once): the graph of the
    per-region smoothness. ``face_regions`` (F,): each face's region, 0 .. n_regions - 1."""
    faces = np.asarray(faces, np.int64)
    regions = np.asarray(face_regions, np.int64)
    if regions.shape != (len(faces),) or (len(regions) and (regions.min() < 0 or regions.max() >= n_regions)):
        raise ValueError(f"face_regions must be ({len(faces)},) indices in 0..{n_regions - 1}")
    und = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    owner = np.concatenate([regions, regions, regions])
    n = int(faces.max()) + 1
    keys = und[:, 0] * n + und[:, 1]
    order = np.argsort(keys, kind="stable")
    k_sorted, r_sorted = keys[order], owner[order]
    same = k_sorted[1:] == k_sorted[:-1]                 # a closed mesh: each edge twice, side by side
    a, b = r_sorted[:-1][same], r_sorted[1:][same]
    cross = a != b
    if not cross.any():
        return np.zeros((0, 2), np.int64)
    return np.unique(np.sort(np.stack([a[cross], b[cross]], axis=1), axis=1), axis=0)


def smoothness(log_k, pairs, weight):
    """The smoothness regulariser ``weight * sum over pairs (log k_a - log k_b)²`` of a log field
    (jax or numpy). Its gradient is ``2 weight L log_k``, L = :func:`laplacian` of ``pairs``."""
    pairs = np.asarray(pairs)
    if not len(pairs):
        return weight * (log_k[:0] ** 2).sum()
    d = log_k[pairs[:, 0]] - log_k[pairs[:, 1]]
    return weight * (d * d).sum()


def laplacian(pairs, n):
    """(n, n) dense graph Laplacian (degree minus adjacency) of ``pairs`` (numpy float64)."""
    lap = np.zeros((n, n))
    pairs = np.asarray(pairs, np.int64)
    np.add.at(lap, (pairs[:, 0], pairs[:, 1]), -1.0)
    np.add.at(lap, (pairs[:, 1], pairs[:, 0]), -1.0)
    lap[np.arange(n), np.arange(n)] = -lap.sum(axis=1)
    return lap


def face_values(k_edge, faces, edges):
    """(F,) each face's mean log10 stiffness over its three edges (what
    :func:`jaxplush.io.render.render_field` colours and :func:`patch_iou` thresholds)."""
    fe = face_edges(faces, edges)
    return np.log10(np.asarray(k_edge, np.float64))[fe].mean(axis=1)


def face_areas(vertices, faces):
    """(F,) triangle areas (numpy)."""
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces)
    return 0.5 * np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)


def patch_iou(k_fit, k_true, vertices, faces, edges, threshold):
    """Area-weighted intersection over union of the stiff patch: faces whose mean log stiffness
    (:func:`face_values`) lies above log10(``threshold``), fitted against true."""
    area = face_areas(vertices, faces)
    lt = np.log10(threshold)
    fit = face_values(k_fit, faces, edges) > lt
    true = face_values(k_true, faces, edges) > lt
    union = area[fit | true].sum()
    return float(area[fit & true].sum() / union) if union > 0 else 1.0


# --------------------------------------------------------------------------- the problem

@dataclasses.dataclass(frozen=True, eq=False)
class FieldProblem:
    """A stiffness-field fit, built and validated before anything is traced.

    Attributes:
      prob: the :class:`jaxplush.fitting.objective.problem.Problem` of the global parameters (its scene,
        target, simulator and loss; its ``base`` holds the start field as ``k_structural``).
      kind: "edges" or "regions".
      matrix: (E, R) float64 region -> edge averaging matrix (``regions``), None for ``edges``.
      region_names: (R,) names of the regions (``regions``; an object's faces outside every group
        are the region "<object>:rest").
      face_regions: (F,) each face's region (``regions``), None for ``edges``.
      pairs: (P, 2) adjacent pairs of the field's unknowns (:func:`edge_pairs`, :func:`region_pairs`).
      weight: the smoothness weight; n_field: the field's unknowns (E or R).
      smoother: (n_field, n_field) float64 S = (I + beta L)^-1 of the preconditioner (module
        docstring), or None (beta = 0): the optimiser's variables are z with log field = S z.
      theta0: (n_field + P_n O_f,) float64 start values of the optimiser's variables: z0 (the log
        start field where there is no preconditioner), then the log globals.
    """

    prob: object
    kind: str
    matrix: np.ndarray | None
    region_names: tuple
    face_regions: np.ndarray | None
    pairs: np.ndarray
    weight: float
    n_field: int
    theta0: np.ndarray
    smoother: np.ndarray | None = None

    @property
    def sim(self):
        return self.prob.sim

    @property
    def names(self):
        """The global parameters' names."""
        return self.prob.names

    def split(self, theta):
        """(log field (n_field,), log globals (P_n, O_f)) of the optimiser's variables theta (jax or numpy)."""
        n = self.n_field
        field = theta[:n]
        if self.smoother is not None:
            xp = np if isinstance(theta, np.ndarray) else jnp
            field = xp.matmul(xp.asarray(self.smoother, field.dtype), field, precision=jax.lax.Precision.HIGHEST) \
                if xp is jnp else self.smoother @ field
        return field, theta[n:].reshape(len(self.prob.names), len(self.prob.objects))

    def k_edges(self, log_field):
        """(E,) per-edge stiffness from the log field (jax or numpy, as given)."""
        xp = np if isinstance(log_field, np.ndarray) else jnp
        k = xp.exp(log_field)
        if self.matrix is None:
            return k
        return xp.asarray(self.matrix, k.dtype) @ k

    def to_params(self, theta):
        """Full :class:`Params` (jnp, the simulator's dtype) at log values theta."""
        field, glob = self.split(theta)
        p = self.prob.to_params(glob)
        return p._replace(k_structural=self.k_edges(field).astype(self.sim.dtype))

    def data_loss(self, theta):
        """The normalised data loss at theta (jax; differentiable)."""
        from jaxplush.fitting.objective.gradients import rollout_loss
        p = self.to_params(theta)
        lo = self.prob.loss
        return rollout_loss(self.sim, p, self.sim.init_fn(p), lo.frame_steps, lo.loss_fn, lo.aux,
                            method=self.prob.method)

    def regulariser(self, theta):
        """The smoothness term at theta (jax)."""
        return smoothness(self.split(theta)[0], self.pairs, jnp.asarray(self.weight, theta.dtype))

    def loss_fn(self, theta):
        """The objective: data loss + smoothness (jax; differentiable)."""
        return self.data_loss(theta) + self.regulariser(theta)

    def values(self, theta):
        """dict of the globals' (O_f,) values (float64), for progress lines."""
        _, glob = self.split(np.asarray(theta, np.float64))
        return {n: np.exp(glob[i]) for i, n in enumerate(self.prob.names)}

    def field_values(self, theta):
        """(E,) float64 per-edge stiffness at theta; and the (R,) region values (``regions``) or None."""
        field, _ = self.split(np.asarray(theta, np.float64))
        return self.k_edges(field), (np.exp(field) if self.matrix is not None else None)

    def valid(self, theta):
        """Finite, and the Verlet damping D >= 1 where it is fitted."""
        th = np.asarray(theta, np.float64)
        if not np.all(np.isfinite(th)):
            return False
        _, glob = self.split(th)
        if "damping" in self.prob.names and np.any(np.exp(glob[self.prob.names.index("damping")]) < 1.0):
            return False
        return True

    def frames(self, theta):
        """(T, V, 3) simulated positions at the target's steps and (T, O) health codes (jax)."""
        from jaxplush.fitting.judge import identifiability as _ident
        p = self.to_params(theta)
        return _ident.frames_at_steps(self.sim, p, self.sim.init_fn(p), self.prob.loss.frame_steps)


def _regions(scene):
    """(matrix (E, R), region names (R,), face regions (F,), object of each region (R,)): the
    scene's face groups, plus one region "<object>:rest" per object with faces outside every group."""
    fg = np.asarray(scene.face_groups if scene.face_groups is not None else np.full(len(scene.faces), -1), np.int64)
    names = list(scene.group_names)
    owner = list(scene.group_object)
    regions = fg.copy()
    face_object = np.asarray(scene.object_id)[np.asarray(scene.faces)[:, 0]]
    for o, name in enumerate(scene.object_names):
        rest = (fg < 0) & (face_object == o)
        if rest.any():
            regions[rest] = len(names)
            names.append(f"{name}:rest")
            owner.append(o)
    if not len(scene.group_names):
        raise JaxplushError(f"{scene.path}: a fit per region needs face groups ('g NAME' lines inside the "
                            "object after its 'o' line); this scene has none (fit per edge instead)")
    edges = scene.edges
    fe = face_edges(scene.faces, edges)
    matrix = np.zeros((len(edges), len(names)))
    np.add.at(matrix, (fe.ravel(), np.repeat(regions, 3)), 0.5)     # two faces per edge, half each
    if not np.allclose(matrix.sum(axis=1), 1.0):
        raise JaxplushError(f"{scene.path}: an edge does not lie on exactly two faces")
    return matrix, tuple(names), regions, np.asarray(owner, np.int64)


def default_weight(n_residuals, tau=DEFAULT_TAU, normalisation="noise"):
    """The default smoothness weight for a loss of N residuals (module docstring): 1 / (N tau²)
    for a noise-normalised loss, MOTION_NOISE² / (N tau²) for a motion-normalised one."""
    if not tau > 0:
        raise JaxplushError(f"tau must be > 0, got {tau!r}")
    scale = 1.0 if normalisation == "noise" else MOTION_NOISE ** 2
    return scale / (float(n_residuals) * tau * tau)


def n_residuals(target):
    """N, the number of residuals behind the normalised loss: 3 per observed vertex or track, 1
    per observed point."""
    return int(target.observed.sum()) * target.kind.components


def build_field_problem(scene, target, field="regions", params=None, *, weight=None, tau=DEFAULT_TAU,
                        precondition=None, dt=None, start=None, noise=None, noise_free=False, method="auto"):
    """Validate a field fit's inputs and build its :class:`FieldProblem`.

    Args:
      scene: the start scene: its stiffness (per object, or a field) is the field's start.
      target: :class:`jaxplush.fitting.targets.Target` or a path.
      field: "edges" or "regions".
      params: the global parameters fitted with the field (default: the damping the scene uses and
        nmol where there is gas, :func:`jaxplush.fitting.objective.problem.default_params` without k); () none.
      weight: the smoothness weight (default :func:`default_weight` with ``tau``).
      precondition: beta of the smoothing preconditioner S = (I + beta L)^-1 (module docstring;
        default :data:`DEFAULT_PRECONDITION`; 0: none). It changes the path, not the optimum.
      dt, noise, noise_free, method: as :func:`jaxplush.fitting.fit`.
      start: start values {name: value}; ``k_structural`` (a number, or an (E,) or (R,) array)
        replaces the scene's stiffness as the field's start.
    """
    if field not in FIELD_KINDS:
        raise JaxplushError(f"unknown field kind {field!r}; expected {' or '.join(FIELD_KINDS)}")
    if params is None:
        names, _ = default_params(scene)
        names = tuple(n for n in names if n != "k_structural")
    else:
        names = canonical_names(params) if len(params) else ()
        if "k_structural" in names:
            raise JaxplushError("k_structural is the field; name only the global parameters in params")
        if "total_weight" in names:
            raise JaxplushError("a field fit does not fit total_weight (it scales with k; docs/model.md §9.1)")
    if weight is not None and not (np.isfinite(weight) and weight >= 0):
        raise JaxplushError(f"the field weight must be a number >= 0, got {weight!r}")
    start = dict(start or {})
    k_start = start.pop("k_structural", None)
    for key in list(start):
        if canonical_names([key])[0] == "k_structural":
            k_start = start.pop(key)
    edges = scene.edges
    n_e = len(edges)
    if field == "regions":
        matrix, region_names, face_regions, owner = _regions(scene)
        k0 = _region_start(scene, k_start, region_names, owner)
        pairs = region_pairs(scene.faces, face_regions, len(region_names))
        n_field = len(region_names)
        k_edge0 = matrix @ k0
    else:
        matrix, region_names, face_regions = None, (), None
        k0 = _edge_start(scene, k_start, n_e)
        pairs = edge_pairs(scene.faces, edges)
        n_field = n_e
        k_edge0 = k0
    if not np.all(np.isfinite(k0) & (k0 > 0)):
        raise JaxplushError("every start value of the stiffness field must be > 0 (fitting works in log space)")
    # the globals' problem: the scene with the start field as its k_structural (so that the simulator
    # compiles the per-edge kernels), the globals' start values and the target
    field_scene = scene.replace(params=scene.params._replace(k_structural=np.asarray(k_edge0, np.float64)))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")      # default_params' note: the field fit names its own
        prob = build_problem(field_scene, target, names if names else ("k_structural",), dt=dt, start=start,
                             noise=noise, noise_free=noise_free, method=method)
    if not names:
        prob = dataclasses.replace(prob, names=(), theta0=np.zeros((0, len(prob.objects))))
    if prob.sim.topology.n_edges != n_e:
        raise JaxplushError("the simulator's edges differ from the scene's")
    if weight is None:
        weight = default_weight(n_residuals(prob.target), tau, prob.loss.normalisation)
    beta = DEFAULT_PRECONDITION[field] if precondition is None else float(precondition)
    if not (np.isfinite(beta) and beta >= 0):
        raise JaxplushError(f"precondition must be a number >= 0, got {precondition!r}")
    z0 = np.log(np.asarray(k0, np.float64))
    smoother = None
    if beta > 0:
        op = np.eye(n_field) + beta * laplacian(pairs, n_field)
        smoother = np.linalg.inv(op)
        z0 = op @ z0                                    # S z0 = the log start field
    theta0 = np.concatenate([z0, np.asarray(prob.theta0, np.float64).ravel()])
    return FieldProblem(prob=prob, kind=field, matrix=matrix, region_names=region_names, face_regions=face_regions,
                        pairs=pairs, weight=float(weight), n_field=int(n_field), theta0=theta0, smoother=smoother)


def _edge_start(scene, k_start, n_e):
    if k_start is None:
        k = np.asarray(scene.params.k_structural, np.float64)
        return k.copy() if k.shape == (n_e,) else k[scene.edge_object]
    k = np.asarray(k_start, np.float64)
    if k.ndim == 0:
        return np.full(n_e, float(k))
    if k.shape != (n_e,):
        raise JaxplushError(f"the start field of a fit per edge must be a number or ({n_e},) values, got shape "
                            f"{k.shape}")
    return k.copy()


def _region_start(scene, k_start, names, owner):
    r = len(names)
    if k_start is None:
        k_obj = np.asarray(scene.k_object if scene.k_object is not None else scene.params.k_structural, np.float64)
        kr = np.asarray(scene.k_region, np.float64) if scene.k_region is not None else np.zeros(0)
        out = k_obj[owner].copy()
        g = len(kr)
        out[:g] = np.where(np.isnan(kr), out[:g], kr)
        return out
    k = np.asarray(k_start, np.float64)
    if k.ndim == 0:
        return np.full(r, float(k))
    if k.shape != (r,):
        raise JaxplushError(f"the start field of a fit per region must be a number or ({r},) values (regions "
                            f"{', '.join(names)}), got shape {k.shape}")
    return k.copy()


# --------------------------------------------------------------------------- the fit

def fit_field(scene, target, field="regions", params=None, *, optimizer="lbfgs", weight=None, tau=DEFAULT_TAU,
              precondition=None, options=None, progress=False, callback=None, **overrides):
    """Fit a stiffness field (per edge or per region) and the global parameters to a target.

    Args:
      scene, target, field, params, weight, tau, precondition: as :func:`build_field_problem`.
      optimizer: "lbfgs" (default: optax's L-BFGS with its zoom line search) or "adam" (cosine-decayed
        learning rate ``lr``, default 0.05 in log space), or an optax transformation.
      options: :class:`jaxplush.fitting.FitOptions`; the fields used: iterations (default 200), lr,
        dt, start, noise, noise_free, gtol, rtol, xtol, ftol, patience, method, identifiability
        (the report of a fit per region, :func:`field_identifiability`). Keywords override single
        fields, as for :func:`jaxplush.fitting.fit`.
      progress: a progress bar with the loss and the globals on stderr.
      callback: called after every accepted iteration with a dict (iteration, loss, values,
        grad_norm); returning True stops the fit.

    Returns:
      :class:`FieldResult`.

    Raises:
      JaxplushError: bad input (before anything is traced); FitError: the rollout blows up at the
      start, or too many steps in a row.
    """
    t_start = time.perf_counter()
    clock = compile_clock()                 # the whole fit's XLA compiles, apart from the rest
    opts = _options.resolve(options, overrides)
    kind = _gradfit.optimizer_kind(optimizer)
    if kind == "lm":
        raise JaxplushError("a field fit descends gradients: optimizer 'lbfgs' (default) or 'adam'")
    fp = build_field_problem(scene, target, field, params, weight=weight, tau=tau, precondition=precondition,
                             dt=opts.dt, start=opts.start,
                             noise=opts.noise, noise_free=opts.noise_free, method=opts.method)
    iterations = opts.iteration_limit(kind)
    if kind == "lbfgs":
        opt = optax.lbfgs(learning_rate=opts.lr, memory_size=LBFGS_MEMORY)
    else:
        opt = optimizer if kind == "optax" else _gradfit.make_optimizer(kind, opts.lr, iterations)
    shape = jax.eval_shape(opt.init, jax.ShapeDtypeStruct(np.shape(fp.theta0), fp.sim.dtype))
    stage = _gradfit.Gradient.from_options(opt, opts, iterations)
    objective = types.SimpleNamespace(prob=fp)
    settings = _field_settings(fp, kind, opts, iterations)
    if kind == "optax":            # what a resume can check of a user's transformation: its state's structure
        settings["optax_state"] = str(jax.tree_util.tree_structure(shape))
    ck = opts.checkpoint
    loop = _resumed(fp, settings, ck.path) if ck.resume else stage.init(objective, fp.theta0)
    bar = Progress(iterations, f"fit field ({field})", enabled=progress, unit="it", compiles=True)

    def save(state, status):
        # Ctrl-C (or SIGTERM from the command line) saves the state before the step it landed in,
        # and --resume continues from it
        if ck.path is not None:
            _save_checkpoint(fp, state, settings, ck.path, status)

    with bar:
        bar.update(min(loop.iteration, iterations))
        loop = _gradfit.drive(objective, stage, loop, bar=bar, callback=callback, save=save, every=ck.every)
        bar.finish(loop.reason if loop.done else "iteration limit")
    result = _field_result(fp, loop, kind, opts, iterations, time.perf_counter() - t_start,
                           report=opts.identifiability)
    result = dataclasses.replace(result, timing=clock.stop())
    if ck.path is not None:
        result.save(ck.path)        # finished, with its loop: a --resume on it returns this result
    if progress:
        from jaxplush.fitting.fitter import say_timing
        say_timing(result.timing, f"fit field ({field})")
    return result


def _field_settings(fp, kind, opts, iterations):
    """What a field fit's FIT.h5 records of its settings (and a resume must match: :data:`RESUME_KEYS`)."""
    prob = fp.prob
    return dict(optimizer=kind, lr=opts.lr, iterations=int(iterations), field=fp.kind, weight=fp.weight,
                names=list(prob.names), objects=[prob.scene.object_names[o] for o in prob.objects],
                dt=prob.target.dt, noise_free=bool(opts.noise_free),
                noise=-1.0 if prob.noise is None else float(prob.noise), method=opts.method,
                frame_steps=list(prob.loss.frame_steps), target_kind=prob.target.kind,
                gtol=opts.gtol, rtol=opts.rtol, xtol=opts.xtol, ftol=opts.ftol, patience=int(opts.patience),
                n_unknowns=int(np.size(fp.theta0)), preconditioned=fp.smoother is not None,
                theta0_hash=hashlib.sha1(np.ascontiguousarray(fp.theta0, np.float64).tobytes()).hexdigest())


def _save_checkpoint(fp, loop, settings, path, status="running"):
    """A field fit's checkpoint: FIT.h5's attributes, the globals at the best point so far, the
    field there, and the loop's state (:class:`jaxplush.fitting.stages.gradfit.LoopState`), written
    atomically by :func:`jaxplush.fitting.io.save_checkpoint`."""
    from jaxplush.fitting import io as _io
    best = loop.best_theta if loop.h_loss else np.asarray(fp.theta0)
    _io.save_checkpoint(path, fp.prob, loop, settings, status=status, theta=fp.split(np.asarray(best))[1],
                        history=dict(iteration=np.asarray(loop.h_iter, np.int64),
                                     loss=np.asarray(loop.h_loss, np.float64)),
                        loss=float(loop.best_loss), iterations=int(loop.iteration), rejected=int(loop.rejected),
                        field=fp.kind)


def _resumed(fp, settings, path):
    """The :class:`jaxplush.fitting.stages.gradfit.LoopState` checkpointed in ``path`` for this fit (its
    settings checked by :func:`jaxplush.fitting.io.load_checkpoint`)."""
    from jaxplush.fitting import io as _io

    def check(loop):
        if not isinstance(loop, _gradfit.LoopState):
            raise TypeError(f"the checkpoint holds a {type(loop).__name__}, not a gradient fit's LoopState")
        if np.shape(loop.theta) != np.shape(fp.theta0):
            raise ValueError(f"its unknowns have shape {np.shape(loop.theta)}, this fit's {np.shape(fp.theta0)}")
        return loop

    return _io.load_checkpoint(path, fp.prob, settings, conform=check)


@dataclasses.dataclass(frozen=True, eq=False)
class FieldResult:
    """The outcome of :func:`fit_field`.

    Attributes:
      kind: "edges" or "regions".
      k_structural: (E,) float64 the fitted per-edge stiffness, N/m (``Scene.edges`` order).
      k_regions: (R,) the fitted region values (``regions``), else None; region_names: (R,).
      k_start: (E,) the start field.
      values: dict global name -> (O_f,) fitted values; start: the same at the start.
      params: full :class:`Params` (numpy float64) with the fitted field and globals.
      loss: the objective at the fit (data + smoothness); data_loss, smoothness: its parts;
        loss_start: the objective at the start.
      weight: the smoothness weight used.
      history: dict of arrays over accepted iterations: "iteration", "loss", "grad_norm", "time" (s),
        each global's values (n, O_f), and "rejected".
      iterations, rejected: evaluations done and rejected (blow-ups).
      reason: why the optimiser stopped, in words; stopped: the same as a
        :class:`jaxplush.fitting.judge.outcome.Stop`; wall_time: s.
      frames: (T, V, 3) the fitted rollout at the target's frames; steps, dt.
      problem: the :class:`FieldProblem`; optimizer: its name.
      identifiability: for a fit per region, the
        :class:`jaxplush.fitting.judge.identifiability.IdentifiabilityReport` at the fit
        (:func:`field_identifiability`: each region's and global's standard error, the data and
        the smoothness prior together); None per edge (a tangent per edge costs too much) or
        when switched off (``identifiability=False``).
      loop: the optimiser's final :class:`jaxplush.fitting.stages.gradfit.LoopState`, written to FIT.h5
        as its checkpoint (a ``--resume`` on a finished FIT.h5 returns this result).
      timing: :class:`jaxplush.compilestats.Timing` of the whole :func:`fit_field` call in this
        process: its wall time, XLA compiles and programs apart from the rest (as
        :attr:`jaxplush.fitting.judge.result.FitResult.timing`); None when not measured.
      outcome: the judge's :class:`jaxplush.fitting.judge.outcome.Outcome` (its data residual
        against the noise or the target's motion, its gradient against the start's; ``status``),
        as every fit family's.
    """

    kind: str
    k_structural: np.ndarray
    k_regions: np.ndarray | None
    region_names: tuple
    k_start: np.ndarray
    values: dict
    start: dict
    params: Params
    loss: float
    data_loss: float
    smoothness: float
    loss_start: float
    weight: float
    history: dict
    iterations: int
    rejected: int
    reason: str
    stopped: Stop
    wall_time: float
    frames: np.ndarray
    steps: np.ndarray
    dt: float
    problem: FieldProblem
    optimizer: str
    settings: dict
    identifiability: object = None
    loop: object = None
    timing: object = None
    outcome: object = None

    @property
    def status(self):
        """How the fit ended (:class:`jaxplush.fitting.judge.outcome.Status`), as the judge says."""
        return (self.outcome or _outcome(self)).status

    @property
    def normalisation(self):
        return self.problem.prob.loss.normalisation

    @property
    def rms(self):
        """The data loss as an RMS residual, m (per coordinate, or per point distance)."""
        from jaxplush.fitting.objective.losses import rms_metres
        lo = self.problem.prob.loss
        return rms_metres(self.data_loss, lo.scale2, lo.kind)

    def table(self):
        """The globals (start, fitted), the field's range and the loss, as text."""
        rows = [f"{'parameter':<14} {'object':<14} {'start':>12} {'fitted':>12}"]
        objs = [self.problem.prob.scene.object_names[o] for o in self.problem.prob.objects]
        for n in self.values:
            for j, o in enumerate(objs):
                rows.append(f"{n:<14} {o:<14} {self.start[n][j]:>12.6g} {self.values[n][j]:>12.6g}")
        k = self.k_structural
        what = f"{len(k)} edges" if self.kind == "edges" else f"{len(self.k_regions)} regions"
        rows.append(f"k_structural field ({what}): start {np.min(self.k_start):.4g}..{np.max(self.k_start):.4g}, "
                    f"fitted {np.min(k):.4g}..{np.max(k):.4g} N/m (median {np.median(k):.4g})")
        if self.kind == "regions":
            for name, v in zip(self.region_names, self.k_regions):
                rows.append(f"  k_region {name:<20} {v:>12.6g}")
        rows.append(f"loss {self.loss_start:.4g} -> {self.loss:.4g} (data {self.data_loss:.4g}, "
                    f"{self.normalisation}-normalised, RMS {1e3 * self.rms:.3g} mm; smoothness {self.smoothness:.3g}, "
                    f"weight {self.weight:.3g}) after {self.iterations} iterations ({self.rejected} rejected), "
                    f"{self.wall_time:.1f} s")
        if self.timing is not None:
            rows.append(f"time: {self.timing.text()}")
        rows.append(f"stopped: {self.reason}")
        if self.outcome is not None:
            rows.append(f"outcome: {self.outcome.text}")
        return "\n".join(rows)

    def save(self, path):
        """Write FIT.h5 atomically (:mod:`jaxplush.fitting.io` layout, plus ``fields/k_structural`` [E])."""
        return save_field_fit(self, path)

    def scene_text(self, path=None):
        """The scene with the fitted field (``k_region`` or ``k_edge`` lines) and globals."""
        return fitted_field_scene_text(self, path)

    def write_scene(self, path):
        """Write :meth:`scene_text` to ``path`` atomically."""
        from jaxplush.io.trajectory import atomic_path
        text = self.scene_text(path)
        with atomic_path(path, ".obj") as tmp:
            with open(tmp, "w", encoding="utf-8", newline="\n") as fh:
                fh.write(text)
        return os.fspath(path)

    def render(self, path, truth=None, **kw):
        """A picture of the fitted field on the rest mesh (and ``truth``, an (E,) field, beside it):
        :func:`jaxplush.io.render.render_field`."""
        from jaxplush.io.render import render_field
        scene = self.problem.prob.scene
        fields = [("fitted", self.k_structural)] + ([("true", np.asarray(truth, np.float64))] if truth is not None
                                                    else [("start", self.k_start)])
        return render_field(scene.vertices, scene.faces, scene.edges, fields, path, **kw)


def _field_result(fp, loop, kind, opts, iterations, wall, report=False):
    """The :class:`FieldResult` at the best accepted point of ``loop``; with ``report`` (and
    regions) its identifiability report."""
    best = loop.best_theta if loop.h_loss else np.asarray(fp.theta0)
    th = jnp.asarray(best, fp.sim.dtype)
    parts = jax.jit(lambda t: (fp.data_loss(t), fp.regulariser(t)))(th)
    frames, _ = jax.jit(fp.frames)(th)
    k_edge, k_reg = fp.field_values(best)
    k0, _ = fp.field_values(fp.theta0)
    prob = fp.prob
    vals = fp.values(best)
    full = {n: np.array(getattr(prob.base, n), np.float64) for n in PARAM_NAMES}
    for n in prob.names:
        full[n][list(prob.objects)] = vals[n]
    full["k_structural"] = k_edge
    hist = dict(iteration=np.asarray(loop.h_iter, np.int64), loss=np.asarray(loop.h_loss, np.float64),
                grad_norm=np.asarray(loop.h_gnorm, np.float64), time=np.asarray(loop.h_time, np.float64),
                rejected=np.asarray(loop.h_rejected, np.int64))
    thetas = np.asarray(loop.h_theta, np.float64).reshape(len(loop.h_theta), -1)
    for i, n in enumerate(prob.names):
        hist[n] = np.exp(thetas[:, fp.n_field:].reshape(len(thetas), len(prob.names), -1)[:, i]) if len(thetas) \
            else np.zeros((0, len(prob.objects)))
    settings = _field_settings(fp, kind, opts, iterations)
    result = FieldResult(kind=fp.kind, k_structural=k_edge, k_regions=k_reg, region_names=fp.region_names,
                         k_start=k0, values=vals, start=fp.values(fp.theta0), params=Params(**full),
                         loss=float(parts[0] + parts[1]), data_loss=float(parts[0]), smoothness=float(parts[1]),
                         loss_start=float(loop.h_loss[0]) if loop.h_loss else math.nan, weight=fp.weight,
                         history=hist, iterations=int(loop.iteration), rejected=int(loop.rejected), reason=loop.reason,
                         stopped=loop.stopped,
                         wall_time=float(wall), frames=np.asarray(frames, np.float64),
                         steps=np.asarray(prob.loss.frame_steps, np.int64), dt=float(prob.target.dt), problem=fp,
                         optimizer=kind, settings=settings,
                         identifiability=field_identifiability(fp, best) if report and fp.kind == "regions" else None,
                         loop=loop)
    # the judge, as every fit family's: the outcome, warned unless converged
    out = _outcome(result)
    if not out.converged:
        warnings.warn(out.text, FitWarning, stacklevel=3)
    return dataclasses.replace(result, outcome=out)


# --------------------------------------------------------------------------- identifiability (regions)

def field_jacobian(fp, theta):
    """(jac (n, P) m per unit log, residual (n,) m, labels (P,)) of a fit per region at the
    optimiser's variables ``theta``, in the coordinates log k per region, then the log globals.

    The rows are the data's residuals (:func:`jaxplush.fitting.objective.losses.make_residual`, in metres),
    by forward mode (one rollout with a tangent per unknown), then the smoothness prior as
    pseudo-residuals: sqrt(weight) (log k_a - log k_b) per adjacent pair, in the data's metres,
    so that the sum of squares of all rows, scaled back, is the fit's objective."""
    from jaxplush.fitting.judge import identifiability as _ident
    from jaxplush.fitting.objective import losses as _losses
    if fp.kind != "regions":
        raise ValueError("field_jacobian serves a fit per region (a tangent per unknown)")
    prob = fp.prob
    res = _losses.make_residual(prob.target, fp.sim.topology, prob.loss)
    field, glob = fp.split(np.asarray(theta, np.float64))
    coords = np.concatenate([field, glob.ravel()])
    n_f, shape = fp.n_field, glob.shape

    def f(c):
        p = prob.to_params(c[n_f:].reshape(shape))
        p = p._replace(k_structural=fp.k_edges(c[:n_f]).astype(fp.sim.dtype))
        frames, codes = _ident.frames_at_steps(fp.sim, p, fp.sim.init_fn(p), prob.loss.frame_steps)
        return res.fn(frames), codes

    def run(c):
        basis = jnp.eye(c.size, dtype=c.dtype)
        return jax.vmap(lambda t: jax.jvp(f, (c,), (t,), has_aux=True), out_axes=(None, 0, None))(basis)

    r, tangents, _ = jax.jit(run)(jnp.asarray(coords, fp.sim.dtype))
    norm = np.asarray(res.norm, np.float64)                   # normalised residual = metres x norm
    scale = norm if norm.ndim == 0 else norm[:, None]
    jac = np.asarray(tangents, np.float64).T / scale
    resid = np.asarray(r, np.float64) / norm
    # the prior's rows, in the data's metres: weight (d)^2 = (sqrt(weight) d / norm)^2 norm^2
    unit = float(np.sqrt(fp.weight) / (norm if norm.ndim == 0 else np.sqrt(np.mean(norm ** 2))))
    pairs = np.asarray(fp.pairs, np.int64)
    prior = np.zeros((len(pairs), coords.size))
    prior[np.arange(len(pairs)), pairs[:, 0]] = unit
    prior[np.arange(len(pairs)), pairs[:, 1]] = -unit
    prior_r = unit * (field[pairs[:, 0]] - field[pairs[:, 1]])
    objs = [prob.scene.object_names[o] for o in prob.objects]
    labels = [f"k_structural[{r_}]" for r_ in fp.region_names] + [f"{n}[{o}]" for n in prob.names for o in objs]
    if fp.weight > 0 and len(pairs):
        jac, resid = np.concatenate([jac, prior]), np.concatenate([resid, prior_r])
    return jac, resid, tuple(labels)


def field_identifiability(fp, theta):
    """The :class:`jaxplush.fitting.judge.identifiability.IdentifiabilityReport` of a fit per region at
    ``theta`` (:func:`field_jacobian`): each region's and global's approximate standard error
    (relative), the condition of JᵀJ and its weakest combination. The smoothness prior counts as
    data: a region the target barely sees is held by its neighbours, and its standard error says
    how much."""
    from jaxplush.fitting.judge import identifiability as _ident
    jac, resid, labels = field_jacobian(fp, theta)
    return _ident.analyse(jac, resid, labels, noise=fp.prob.noise)


# --------------------------------------------------------------------------- FIT.h5 and the fitted scene

def _outcome(result):
    """The :class:`jaxplush.fitting.judge.outcome.Outcome` of a field fit: its data residual against the noise
    (or the target's motion) and its gradient against the start's."""
    from jaxplush.fitting.judge import outcome as _out
    from jaxplush.fitting.judge.result import _motion
    prob = result.problem.prob
    h = result.history
    if not len(h["loss"]):
        return _out.judge(rms=np.inf, noise=prob.noise, motion=_motion(prob), grad=np.inf, grad0=1.0,
                          stopped=Stop.ITERATIONS)
    best = int(np.argmin(h["loss"]))
    return _out.judge(rms=result.rms, noise=prob.noise, motion=_motion(prob), grad=h["grad_norm"][best],
                      grad0=h["grad_norm"][0], stopped=result.stopped)


def save_field_fit(result, path):
    """Write a :class:`FieldResult` as FIT.h5 atomically: the attributes, ``params``, ``start``,
    ``history`` and ``fitted`` groups of :mod:`jaxplush.fitting.io` (``params/k_structural`` holds
    the objects' mean stiffness), and ``fields/k_structural`` [E] (the fitted field, ``Scene.edges``
    order), ``fields/k_start`` [E], ``fields/edges`` [E, 2]; with regions also
    ``fields/k_region`` [R] and attribute ``region_names``; attributes ``field`` and
    ``field_weight``."""
    import h5py
    from jaxplush.fitting import io as _io
    from jaxplush.io.trajectory import atomic_path
    from jaxplush.model.layout import object_stiffness
    fp = result.problem
    prob = fp.prob
    topo = prob.sim.topology
    out = result.outcome or _outcome(result)
    with atomic_path(path, ".h5") as tmp:
        with h5py.File(tmp, "w") as f:
            _io._common_attrs(f, prob, result.settings, out.status.value)
            a = f.attrs
            a["loss"], a["loss_start"] = float(result.loss), float(result.loss_start)
            a["data_loss"], a["smoothness"] = float(result.data_loss), float(result.smoothness)
            a["iterations"], a["rejected"] = int(result.iterations), int(result.rejected)
            a["converged"] = bool(out.converged)
            a["reason"] = f"{out.text} (the optimiser stopped: {result.reason})"
            a["wall_time"] = float(result.wall_time)
            a["warnings"] = json.dumps([] if out.converged else [out.text])
            a["field"], a["field_weight"] = result.kind, float(result.weight)
            a["fitted_scene"] = result.scene_text()
            for grp, vals, k in (("params", result.values, result.k_structural),
                                 ("start", result.start, result.k_start)):
                g = f.create_group(grp)
                g.create_dataset("k_structural", data=np.asarray(object_stiffness(topo, np.asarray(k)), np.float64))
                _io._write_values(g, prob, vals)          # the globals, as every FIT.h5 writes them
            hg = f.create_group("history")
            for k, v in result.history.items():
                hg.create_dataset(k, data=np.asarray(v))
            fg = f.create_group("fields")
            fg.create_dataset("k_structural", data=np.asarray(result.k_structural, np.float64))
            fg.create_dataset("k_start", data=np.asarray(result.k_start, np.float64))
            fg.create_dataset("edges", data=np.asarray(prob.scene.edges, np.int64))
            if result.k_regions is not None:
                fg.create_dataset("k_region", data=np.asarray(result.k_regions, np.float64))
                fg.attrs["region_names"] = np.asarray(result.region_names, dtype=object)
            fg.attrs["kind"] = result.kind
            fg.attrs["weight"] = float(result.weight)
            if result.identifiability is not None:
                _io.write_identifiability(f, result.identifiability)
            gg = f.create_group("fitted")
            gg.create_dataset("positions", data=np.asarray(result.frames), compression="gzip", compression_opts=1)
            gg.create_dataset("steps", data=np.asarray(result.steps, np.int64))
            gg.create_dataset("times", data=np.asarray(result.steps, np.float64) * result.dt)
            for k, v in out.as_dict().items():
                if k not in ("status", "message"):
                    a[f"outcome_{k}"] = json.dumps(list(v)) if isinstance(v, tuple) else v
            if result.timing is not None:
                _io.write_timing(f, result.timing)
            if result.loop is not None:
                # the finished loop, as a checkpoint: --resume on this file returns this result
                _io._write_state(f, prob, result.loop, result.settings)
    return os.fspath(path)


def fitted_field_scene_text(result, path=None):
    """The scene text with the fitted field and globals (:func:`jaxplush.fitting.io.fitted_scene_text`:
    face groups carry over; ``k_region`` lines for a fit per region, ``k_edge`` lines for a fit per
    edge, each reading back bit for bit)."""
    from types import SimpleNamespace
    from jaxplush.fitting import io as _io
    prob = result.problem.prob
    what = (f"{len(result.k_regions)} regions" if result.kind == "regions" else f"{len(result.k_structural)} edges")
    view = SimpleNamespace(problem=prob, params=result.params, scene_path=prob.scene.path,
                           target_path=prob.target.path, loss=result.loss, normalisation=result.normalisation,
                           reason=f"stiffness field per {result.kind[:-1]} ({what}, smoothness weight "
                                  f"{result.weight:.3g}); {result.reason}",
                           names=prob.names, objects=[prob.scene.object_names[o] for o in prob.objects],
                           start=result.start, values=result.values, warnings=())
    return _io.fitted_scene_text(view, path)
