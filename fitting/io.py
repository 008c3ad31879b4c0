"""FIT.h5: the fit's result, its history and a resumable checkpoint (HDF5, written atomically).

Layout:

* attributes: ``status`` ("running" while checkpointing, "interrupted" after Ctrl-C, and once
  the fit ends its outcome, one of :data:`jaxplush.fitting.outcome.STATUSES`), ``outcome_*`` (its fields),
  ``loss``, ``loss_start``, ``iterations``, ``rejected``, ``converged``, ``reason``,
  ``optimizer``, ``lr`` (NaN: default), ``dt``, ``normalisation``, ``scale2``, ``noise`` (NaN:
  unknown), ``wall_time``, ``scene`` (the scene text, start values), ``scene_path``,
  ``target_path``, ``fitted_scene`` (the scene text with the fitted values, when done),
  ``settings`` (JSON), ``warnings`` (JSON list), ``jaxplush_version``;
* ``params/<name>`` [n_objects]: every fitted parameter's values for all objects (objects not
  fitted keep the scene's); attribute ``objects`` the fitted objects, ``object_names`` all;
  ``start/<name>`` likewise for the start values;
* ``history/loss``, ``history/iteration``, ``history/grad_norm``, ``history/time`` [n] and
  ``history/<name>`` [n, n_fitted_objects] over accepted iterations; ``history/rejected``;
* ``identifiability/``: ``jtj``, ``eigenvalues``, ``eigenvectors``, ``sensitivity``, ``stderr``,
  ``determined`` datasets; attributes ``labels``, ``condition``, ``sigma``, ``n_data``,
  ``warnings`` (JSON), ``weakest``, ``summary``;
* ``fitted/positions`` [T, V, 3], ``fitted/steps``, ``fitted/times``: the fitted rollout at the
  target frames;
* ``search/`` (the default fit): ``global/<name>`` and ``global/loss`` of every global sample,
  ``local/NNN/`` the path of each local search;
* ``predictability/`` (when measured, :func:`jaxplush.predictability` at the start values):
  ``times``, ``steps``, ``drift_rms``, ``motion_rms`` datasets; attributes ``horizon_time``
  (inf: never), ``horizon_frame`` (-1: never), ``floor_rms``, ``threshold``, ``threshold_kind``,
  ``motion``, ``perturbation``, ``method``, ``dtype``, ``duration``, ``text``;
* ``shooting/`` (the default fit, :mod:`jaxplush.fitting.shooting`): attributes ``segment_frames``
  (0: one rollout), ``floor_rms``, ``single_floor_rms``, ``refine``, ``text``;
* ``checkpoint/``: the optimisation loop's complete state (log values, optimiser state leaves,
  history, counters, RNG-free), enough for ``--resume`` to continue to the same answer.

Format: docs/formats.md §5.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import os

import h5py
import jax
import jax.numpy as jnp
import numpy as np

from jaxplush.errors import JaxplushError, TrajectoryError
from jaxplush.fitting.options import TUNING
from jaxplush.fitting.outcome import Status, Stop
from jaxplush.io.trajectory import atomic_path, open_hdf5
from jaxplush.types import PARAM_NAMES

#: Settings that must agree between a checkpoint and the fit resuming it.
_RESUME_KEYS = ("optimizer", "lr", "names", "objects", "dt", "noise_free", "noise", "method", "frame_steps",
                "target_kind", "target_hash", "scene_hash", "params_hash", "dtype", "gtol", "rtol", "xtol", "ftol",
                "patience", "optax_state")
#: ... and for Adam, whose cosine learning-rate schedule spans the iterations, also these.
_RESUME_KEYS_ADAM = ("iterations",)
#: ... and for the default fit, its search box, global design and tuning knobs.
_RESUME_KEYS_LM = ("box_lo", "box_hi", "samples", "starts", "seed", "local", "continuation", "smoothing")
#: Settings a checkpoint written before they were recorded ran with (the defaults of the time).
_RESUME_DEFAULTS = {group: dataclasses.asdict(cls()) for group, cls in TUNING.items()}
_RESUME_HINTS = {"iterations": "; Adam's learning-rate schedule spans all the iterations",
                 "dtype": "; give --x64 as the checkpointed fit did, or leave it out likewise"}


def fingerprint(prob):
    """Hashes of the scene text and the target data, to recognise the same fit on resume."""
    scene_hash = hashlib.sha1(prob.scene.text.encode()).hexdigest()
    h = hashlib.sha1(np.ascontiguousarray(prob.target.data, np.float64).tobytes())
    h.update(np.asarray(prob.target.steps, np.int64).tobytes())
    return scene_hash, h.hexdigest()


def _settings(prob, settings):
    s = dict(settings)
    s["scene_hash"], s["target_hash"] = fingerprint(prob)
    # the start values and the values held fixed (a `start` override is not in the scene text)
    s["params_hash"] = hashlib.sha1(np.ascontiguousarray(np.stack([np.asarray(getattr(prob.base, n), np.float64)
                                                                   for n in PARAM_NAMES])).tobytes()).hexdigest()
    s["dtype"] = np.dtype(prob.sim.dtype).name
    return s


def _write_values(group, prob, values_by_name):
    names = prob.scene.object_names
    for n in prob.names:
        full = np.array(getattr(prob.base, n), np.float64)
        full[list(prob.objects)] = values_by_name[n]
        group.create_dataset(n, data=full)
    group.attrs["objects"] = np.asarray([names[o] for o in prob.objects], dtype=object)
    group.attrs["object_names"] = np.asarray(names, dtype=object)


def _write_loop(f, prob, loop, settings):
    g = f.create_group("checkpoint")
    g.create_dataset("theta", data=np.asarray(loop.theta))
    if loop.anchor is not None:
        g.create_dataset("anchor", data=np.asarray(loop.anchor))
    g.create_dataset("best_theta", data=np.asarray(loop.best_theta))
    for key in ("scale", "best_loss", "wall"):
        g.attrs[key] = float(getattr(loop, key))
    for key in ("iteration", "rejected", "rejected_in_row", "stall"):
        g.attrs[key] = int(getattr(loop, key))
    g.attrs["done"] = bool(loop.done)
    g.attrs["reason"] = loop.reason
    g.attrs["stopped"] = Stop(loop.stopped).value
    g.attrs["settings"] = json.dumps(_settings(prob, settings))
    leaves = jax.tree_util.tree_leaves(loop.opt_state)
    og = g.create_group("opt_state")
    og.attrs["n_leaves"] = len(leaves)
    for i, leaf in enumerate(leaves):
        og.create_dataset(f"{i:05d}", data=np.asarray(leaf))
    hg = g.create_group("history")
    n_p = len(prob.names) * len(prob.objects)
    hg.create_dataset("iteration", data=np.asarray(loop.h_iter, np.int64))
    hg.create_dataset("loss", data=np.asarray(loop.h_loss, np.float64))
    hg.create_dataset("theta", data=np.asarray(loop.h_theta, np.float64).reshape(-1, n_p))
    hg.create_dataset("grad_norm", data=np.asarray(loop.h_gnorm, np.float64))
    hg.create_dataset("time", data=np.asarray(loop.h_time, np.float64))
    hg.create_dataset("rejected", data=np.asarray(loop.h_rejected, np.int64))


def _history(f, prob, loop):
    hg = f.create_group("history")
    th = np.asarray(loop.h_theta, np.float64).reshape(-1, len(prob.names), len(prob.objects))
    hg.create_dataset("loss", data=np.asarray(loop.h_loss, np.float64))
    hg.create_dataset("iteration", data=np.asarray(loop.h_iter, np.int64))
    hg.create_dataset("grad_norm", data=np.asarray(loop.h_gnorm, np.float64))
    hg.create_dataset("time", data=np.asarray(loop.h_time, np.float64))
    hg.create_dataset("rejected", data=np.asarray(loop.h_rejected, np.int64))
    for i, n in enumerate(prob.names):
        hg.create_dataset(n, data=np.exp(th[:, i]))


def _common_attrs(f, prob, settings, status):
    from jaxplush import __version__
    a = f.attrs
    a["status"] = status
    a["scene"] = prob.scene.text
    a["scene_path"] = prob.scene.path
    a["target_path"] = os.fspath(prob.target.path)
    a["dt"] = float(prob.target.dt)
    a["optimizer"] = settings["optimizer"]
    a["lr"] = math.nan if settings["lr"] is None else float(settings["lr"])
    a["normalisation"] = prob.loss.normalisation
    a["scale2"] = float(prob.loss.scale2)
    a["noise"] = math.nan if prob.noise is None else float(prob.noise)
    a["settings"] = json.dumps(_settings(prob, settings))
    a["jaxplush_version"] = __version__


def save_checkpoint(path, prob, loop, settings, status="running"):
    """Write the loop state (and the best values so far) to ``path`` atomically."""
    with atomic_path(path, ".h5") as tmp:
        with h5py.File(tmp, "w") as f:
            _common_attrs(f, prob, settings, status)
            f.attrs["loss"] = float(loop.best_loss)
            f.attrs["iterations"] = int(loop.iteration)
            f.attrs["rejected"] = int(loop.rejected)
            _write_values(f.create_group("params"), prob, prob.values(loop.best_theta))
            _write_values(f.create_group("start"), prob, prob.start)
            _history(f, prob, loop)
            _write_loop(f, prob, loop, settings)
    return os.fspath(path)


def save_fit(result, path):
    """Write a :class:`jaxplush.fitting.fitter.FitResult` as FIT.h5 atomically; its ``status`` attribute is the
    fit's outcome (jaxplush.fitting.outcome: "converged", "poor_fit", "stalled", ...)."""
    loop = result.loop
    prob = result.problem
    with atomic_path(path, ".h5") as tmp:
        with h5py.File(tmp, "w") as f:
            _common_attrs(f, prob, result.settings, "done")
            a = f.attrs
            a["loss"] = float(result.loss)
            a["loss_start"] = float(result.loss_start)
            a["iterations"] = int(result.iterations)
            a["rejected"] = int(result.rejected)
            a["converged"] = bool(result.converged)
            a["reason"] = result.reason
            a["wall_time"] = float(result.wall_time)
            a["warnings"] = json.dumps(list(result.warnings) + (
                list(result.identifiability.warnings) if result.identifiability is not None else []))
            a["fitted_scene"] = fitted_scene_text(result)
            _write_values(f.create_group("params"), prob, result.values)
            _write_values(f.create_group("start"), prob, result.start)
            hg = f.create_group("history")
            for k, v in result.history.items():
                hg.create_dataset(k, data=np.asarray(v))
            rep = result.identifiability
            if rep is not None:
                ig = f.create_group("identifiability")
                for k in ("jtj", "eigenvalues", "eigenvectors", "sensitivity", "stderr"):
                    ig.create_dataset(k, data=np.asarray(getattr(rep, k), np.float64))
                ig.create_dataset("determined", data=np.asarray(rep.determined, bool))
                ig.attrs["labels"] = np.asarray(rep.labels, dtype=object)
                ig.attrs["condition"] = float(rep.condition)
                ig.attrs["sigma"] = float(rep.sigma)
                ig.attrs["n_data"] = int(rep.n_data)
                ig.attrs["warnings"] = json.dumps(list(rep.warnings))
                ig.attrs["weakest"] = rep.weakest
                ig.attrs["summary"] = rep.summary()
            fg = f.create_group("fitted")
            fg.create_dataset("positions", data=np.asarray(result.frames), compression="gzip", compression_opts=1)
            fg.create_dataset("steps", data=np.asarray(result.steps, np.int64))
            fg.create_dataset("times", data=np.asarray(result.steps, np.float64) * result.dt)
            if result.outcome is not None:
                for k, v in result.outcome.as_dict().items():
                    if k not in ("status", "message"):
                        a[f"outcome_{k}"] = json.dumps(list(v)) if isinstance(v, tuple) else v
            a["status"] = Status(result.status).value
            if getattr(result, "predictability", None) is not None:
                _write_predictability(f.create_group("predictability"), result.predictability)
            if getattr(prob, "shooting", None) is not None:
                _write_shooting(f.create_group("shooting"), prob.shooting)
            if result.search:
                sg = f.create_group("search")
                srch = result.search
                n_p = len(prob.names)
                for i, n in enumerate(prob.names):
                    sg.create_dataset(f"global/{n}", data=np.exp(np.asarray(srch["global_thetas"])[:, i]))
                sg.create_dataset("global/loss", data=np.asarray(srch["global_loss"], np.float64))
                sg.create_dataset("global/ok", data=np.asarray(srch["global_ok"], bool))
                sg.create_dataset("global/substeps", data=np.asarray(srch["global_substeps"], np.int64))
                for j, (path_j, loss_j) in enumerate(zip(srch["local_paths"], srch["local_losses"])):
                    lg = sg.create_group(f"local/{j:03d}")
                    lg.create_dataset("loss", data=np.asarray(loss_j, np.float64))
                    for i, n in enumerate(prob.names):
                        lg.create_dataset(n, data=np.exp(np.asarray(path_j).reshape(len(loss_j), n_p, -1)[:, i]))
                    lg.attrs["reason"] = srch["local_reasons"][j]
                    lg.attrs["stage"] = int(srch["local_stages"][j])
                sg.attrs["horizons"] = np.asarray(srch["horizons"], np.int64)
                for i, n in enumerate(prob.names):
                    sg.attrs[f"bounds_{n}"] = np.exp(np.stack([np.asarray(srch["box_lo"])[i],
                                                               np.asarray(srch["box_hi"])[i]]))
                sg.attrs["grad"] = np.asarray(srch["grad"], np.float64)
                sg.attrs["grad_start"] = np.asarray(srch["grad0"], np.float64)
            if loop is not None:
                if result.optimizer == "lm":
                    _write_lm(f, prob, light_copy(loop), result.settings)
                    f["checkpoint"].attrs["done"] = True
                else:
                    _write_loop(f, prob, loop, result.settings)
    return os.fspath(path)


def _write_predictability(g, pred):
    """The ``predictability`` group of FIT.h5 (a :class:`jaxplush.Predictability`)."""
    for k in ("times", "drift_rms", "motion_rms"):
        g.create_dataset(k, data=np.asarray(getattr(pred, k), np.float64))
    g.create_dataset("steps", data=np.asarray(pred.steps, np.int64))
    g.attrs["horizon_time"] = float(pred.horizon_time)
    g.attrs["horizon_frame"] = -1 if pred.horizon_frame is None else int(pred.horizon_frame)
    g.attrs["floor_rms"] = float(pred.floor)
    for k in ("threshold", "motion", "perturbation", "duration"):
        g.attrs[k] = float(getattr(pred, k))
    for k in ("threshold_kind", "method", "dtype"):
        g.attrs[k] = str(getattr(pred, k))
    g.attrs["text"] = pred.text()


def _write_shooting(g, sh):
    """The ``shooting`` group of FIT.h5 (a :class:`jaxplush.fitting.shooting.Shooting`): attributes
    ``segment_frames`` (0: single shooting), ``floor_rms`` and ``single_floor_rms`` (m; NaN: not
    measured), ``refine`` and ``text``."""
    g.attrs["segment_frames"] = int(sh.segment_frames or 0)
    g.attrs["floor_rms"] = float("nan") if sh.floor is None else float(sh.floor)
    g.attrs["single_floor_rms"] = float("nan") if sh.single_floor is None else float(sh.single_floor)
    g.attrs["refine"] = int(sh.refine)
    g.attrs["text"] = sh.reason


# --------------------------------------------------------------------------- the default fit (lm)

def light_copy(run):
    """A copy of a :class:`jaxplush.fitting.lmfit.LMRun` without the residuals and Jacobians (which a
    resumed fit recomputes, identically): what a checkpoint holds."""
    import copy
    states = [dataclasses.replace(st, history=list(st.history), residual=None, jac=None) for st in run.states]
    run = dataclasses.replace(run, paths=[list(p) for p in run.paths])
    out = dataclasses.replace(run, states=states, best=None, jac=None, residual=None)
    out.global_result = copy.copy(run.global_result)
    return out


def _write_lm(f, prob, run, settings):
    g = f.create_group("checkpoint")
    g.attrs["kind"] = "lm"
    g.attrs["settings"] = json.dumps(_settings(prob, settings))
    g.attrs["phase"] = run.phase if run.phase in ("global", "local") else "final"
    g.attrs["stage"] = int(run.stage)
    g.attrs["horizons"] = np.asarray(run.horizons, np.int64)
    g.attrs["rounds"] = int(run.rounds)
    pg = g.create_group("paths")
    k = 0
    for stage, stage_paths in enumerate(run.paths):
        for hist, reason in stage_paths:
            one = pg.create_group(f"{k:04d}")
            one.attrs["stage"] = stage
            one.attrs["reason"] = reason
            one.create_dataset("loss", data=np.asarray([l for l, _ in hist], np.float64))
            one.create_dataset("theta", data=np.asarray([t for _, t in hist], np.float64).reshape(
                (len(hist),) + np.shape(prob.theta0)))
            k += 1
    g.attrs["wall"] = float(run.wall)
    g.attrs["evaluations"] = int(run.evaluations)
    gr = run.global_result
    if gr is not None:
        gg = g.create_group("global")
        for k in ("thetas", "loss", "ok", "substeps"):
            gg.create_dataset(k, data=np.asarray(getattr(gr, k)))
    for i, st in enumerate(run.states):
        sg = g.create_group(f"state_{i:03d}")
        sg.create_dataset("theta", data=np.asarray(st.theta, np.float64))
        for k in ("loss", "mu", "radius", "jac_h"):
            sg.attrs[k] = float(getattr(st, k))
        for k in ("iteration", "substeps", "evaluations", "rescues"):
            sg.attrs[k] = int(getattr(st, k))
        sg.attrs["done"] = bool(st.done)
        sg.attrs["reason"] = st.reason
        sg.attrs["stopped"] = Stop(st.stopped).value
        sg.create_dataset("history_loss", data=np.asarray([l for l, _ in st.history], np.float64))
        sg.create_dataset("history_theta", data=np.asarray([t for _, t in st.history], np.float64).reshape(
            (len(st.history),) + np.shape(st.theta)))
    g.attrs["n_states"] = len(run.states)


def save_lm_checkpoint(path, prob, run, settings, status="running"):
    """Write a default fit's state (:class:`jaxplush.fitting.lmfit.LMRun`) to ``path`` atomically."""
    with atomic_path(path, ".h5") as tmp:
        with h5py.File(tmp, "w") as f:
            _common_attrs(f, prob, settings, status)
            states = run.states
            if states:
                best = min(states, key=lambda st: st.loss)
                f.attrs["loss"] = float(best.loss)
                _write_values(f.create_group("params"), prob, prob.values(best.theta))
            f.attrs["iterations"] = int(run.evaluations)
            _write_values(f.create_group("start"), prob, prob.start)
            _write_lm(f, prob, run, settings)
    return os.fspath(path)


def load_lm_checkpoint(path, prob, settings):
    """The :class:`jaxplush.fitting.lmfit.LMRun` saved in ``path``, checked to belong to this fit."""
    path = os.fspath(path)
    if not os.path.exists(path):
        raise JaxplushError(f"{path}: no checkpoint to resume (the file does not exist); run without --resume")
    try:
        f = h5py.File(path, "r")
    except OSError:
        raise TrajectoryError(path, "not an HDF5 file: cannot resume from it") from None
    try:
        with f:
            return _read_lm(path, f, prob, settings)
    except (KeyError, ValueError, TypeError, OSError) as e:
        raise TrajectoryError(path, f"cannot read the checkpoint ({e}); run without --resume to start over") from None


def _read_lm(path, f, prob, settings):
    from jaxplush.fitting.lmfit import LMRun
    from jaxplush.fitting.search import GlobalResult, LMState
    if "checkpoint" not in f:
        raise TrajectoryError(path, "holds no checkpoint group: not a resumable FIT.h5")
    g = f["checkpoint"]
    if g.attrs.get("kind", "loop") != "lm":
        raise JaxplushError(f"{path}: the checkpoint is of a different fit (optimizer: checkpoint "
                            f"{json.loads(g.attrs['settings']).get('optimizer')!r}, now 'lm'); run without "
                            "--resume to start over")
    _check_settings(path, g, prob, settings)
    run = LMRun(phase=str(g.attrs["phase"]), stage=int(g.attrs["stage"]),
                horizons=tuple(int(h) for h in g.attrs["horizons"]), rounds=int(g.attrs["rounds"]),
                wall=float(g.attrs["wall"]), evaluations=int(g.attrs["evaluations"]))
    paths = {}
    for key in sorted(g["paths"].keys()):
        one = g["paths"][key]
        hist = [(float(a), np.asarray(b)) for a, b in zip(one["loss"][()], one["theta"][()])]
        paths.setdefault(int(one.attrs["stage"]), []).append((hist, str(one.attrs["reason"])))
    run.paths = [paths[k] for k in sorted(paths)]
    if "global" in g:
        gg = g["global"]
        run.global_result = GlobalResult(*(np.asarray(gg[k][()]) for k in ("thetas", "loss", "ok", "substeps")))
    for i in range(int(g.attrs["n_states"])):
        sg = g[f"state_{i:03d}"]
        hl, ht = sg["history_loss"][()], sg["history_theta"][()]
        run.states.append(LMState(
            theta=np.asarray(sg["theta"][()]), loss=float(sg.attrs["loss"]), mu=float(sg.attrs["mu"]),
            radius=float(sg.attrs["radius"]), iteration=int(sg.attrs["iteration"]), done=bool(sg.attrs["done"]),
            reason=str(sg.attrs["reason"]), stopped=Stop(str(sg.attrs["stopped"])),
            history=[(float(a), np.asarray(b)) for a, b in zip(hl, ht)], jac_h=float(sg.attrs["jac_h"]),
            substeps=int(sg.attrs["substeps"]), evaluations=int(sg.attrs["evaluations"]),
            rescues=int(sg.attrs.get("rescues", 0))))
    return run


def _check_settings(path, g, prob, settings):
    saved = json.loads(g.attrs["settings"])
    mine = _settings(prob, settings)
    keys = _RESUME_KEYS + (_RESUME_KEYS_ADAM if mine.get("optimizer") == "adam" else ()) + (
        _RESUME_KEYS_LM if mine.get("optimizer") == "lm" else ())
    for k in keys:
        if _norm(saved.get(k, _RESUME_DEFAULTS.get(k))) != _norm(mine.get(k)):
            raise JaxplushError(f"{path}: the checkpoint is of a different fit ({k}: checkpoint "
                                f"{saved.get(k)!r}, now {mine.get(k)!r}{_RESUME_HINTS.get(k, '')}); "
                                "run without --resume to start over")


def load_checkpoint(path, prob, opt, settings):
    """The :class:`LoopState` saved in ``path``, checked to belong to this fit."""
    path = os.fspath(path)
    if not os.path.exists(path):
        raise JaxplushError(f"{path}: no checkpoint to resume (the file does not exist); run without --resume")
    try:
        f = h5py.File(path, "r")
    except OSError:
        raise TrajectoryError(path, "not an HDF5 file: cannot resume from it") from None
    try:
        with f:
            return _read_checkpoint(path, f, prob, opt, settings)
    except (KeyError, ValueError, TypeError, OSError) as e:  # damaged, or written by another version
        raise TrajectoryError(path, f"cannot read the checkpoint ({e}); run without --resume to start over") from None


@dataclasses.dataclass
class LoopState:
    """The complete state of the optimisation loop (what a checkpoint holds).

    ``theta`` is the next point to evaluate, with ``opt_state`` the optimiser state to use
    there; ``anchor`` the last accepted point it was reached from (None before the first).
    """

    theta: np.ndarray
    opt_state: object
    anchor: np.ndarray | None = None
    scale: float = 1.0
    iteration: int = 0           # evaluations done (accepted + rejected)
    rejected: int = 0
    rejected_in_row: int = 0
    stall: int = 0
    best_theta: np.ndarray | None = None
    best_loss: float = math.inf
    done: bool = False
    reason: str = ""             # why it stopped, in words for a person
    stopped: Stop = Stop.NONE    # ... and as a :class:`jaxplush.fitting.outcome.Stop`
    h_iter: list = dataclasses.field(default_factory=list)
    h_loss: list = dataclasses.field(default_factory=list)
    h_theta: list = dataclasses.field(default_factory=list)
    h_gnorm: list = dataclasses.field(default_factory=list)
    h_time: list = dataclasses.field(default_factory=list)
    h_rejected: list = dataclasses.field(default_factory=list)
    wall: float = 0.0

    def snapshot(self):
        """A copy that later iterations do not change (lists copied; arrays are never mutated)."""
        return dataclasses.replace(self, **{f.name: list(getattr(self, f.name)) for f in dataclasses.fields(self)
                                            if f.name.startswith("h_")})


def _read_checkpoint(path, f, prob, opt, settings):
    if "checkpoint" not in f:
        raise TrajectoryError(path, "holds no checkpoint group: not a resumable FIT.h5")
    g = f["checkpoint"]
    if g.attrs.get("kind", "loop") == "lm":
        raise JaxplushError(f"{path}: the checkpoint is of a different fit (optimizer: checkpoint 'lm', now "
                            f"{settings.get('optimizer')!r}); run without --resume to start over")
    _check_settings(path, g, prob, settings)
    template = opt.init(jnp.asarray(np.asarray(g["theta"])))
    leaves, treedef = jax.tree_util.tree_flatten(template)
    og = g["opt_state"]
    if int(og.attrs["n_leaves"]) != len(leaves):
        raise JaxplushError(f"{path}: optimizer state does not match this optax version / optimizer")
    restored = []
    for i, leaf in enumerate(leaves):
        arr = np.asarray(og[f"{i:05d}"][()])
        if arr.shape != np.shape(leaf):
            raise JaxplushError(f"{path}: optimizer state leaf {i} has shape {arr.shape}, expected "
                                f"{np.shape(leaf)}")
        restored.append(jnp.asarray(arr, dtype=jnp.asarray(leaf).dtype))
    hg = g["history"]
    n_p = len(prob.names) * len(prob.objects)
    shape = (len(prob.names), len(prob.objects))
    loop = LoopState(
        theta=np.asarray(g["theta"][()]),
        opt_state=jax.tree_util.tree_unflatten(treedef, restored),
        anchor=np.asarray(g["anchor"][()]) if "anchor" in g else None,
        scale=float(g.attrs["scale"]), iteration=int(g.attrs["iteration"]), rejected=int(g.attrs["rejected"]),
        rejected_in_row=int(g.attrs["rejected_in_row"]), stall=int(g.attrs["stall"]),
        best_theta=np.asarray(g["best_theta"][()]), best_loss=float(g.attrs["best_loss"]),
        done=bool(g.attrs["done"]), reason=str(g.attrs["reason"]), stopped=_stopped(g.attrs),
        h_iter=[int(i) for i in hg["iteration"][()]], h_loss=[float(x) for x in hg["loss"][()]],
        h_theta=[t.reshape(shape) for t in np.asarray(hg["theta"][()]).reshape(-1, n_p)],
        h_gnorm=[float(x) for x in hg["grad_norm"][()]], h_time=[float(x) for x in hg["time"][()]],
        h_rejected=[int(i) for i in hg["rejected"][()]], wall=float(g.attrs["wall"]))
    return loop


def _stopped(attrs):
    """The :class:`Stop` of a gradient loop's checkpoint (a file written before it was stored: from
    the reason's words, as those versions judged it)."""
    if "stopped" in attrs:
        return Stop(str(attrs["stopped"]))
    reason = str(attrs["reason"])
    if reason.startswith("reached the iteration limit"):
        return Stop.ITERATIONS
    return Stop.CALLBACK if reason.startswith("stopped by") else Stop.NONE


def _norm(v):
    """Settings compared after a JSON round trip (tuples -> lists, floats exact)."""
    return json.loads(json.dumps(v))


def load_fit(path):
    """Read FIT.h5 into a dict: attributes, params, start, history, identifiability, fitted,
    predictability (each group present: its datasets, and its attributes under "<group>_attrs")."""
    path = os.fspath(path)
    out = {}
    with open_hdf5(path) as f:
        out["attrs"] = {k: _attr(f.attrs[k]) for k in f.attrs}
        for grp in ("params", "start", "history", "identifiability", "fitted", "predictability"):
            if grp in f:
                out[grp] = {k: f[grp][k][()] for k in f[grp].keys()}
                out[grp + "_attrs"] = {k: _attr(f[grp].attrs[k]) for k in f[grp].attrs}
    return out


def _attr(v):
    if isinstance(v, bytes):
        return v.decode()
    if isinstance(v, np.ndarray) and v.dtype == object:
        return [x.decode() if isinstance(x, bytes) else x for x in v]
    return v


def fitted_scene_text(result):
    """The scene text with the fitted values, in the extended OBJ format."""
    from jaxplush.scene.write import format_scene
    scene = result.problem.scene
    objects = []
    p = result.params
    for i, o in enumerate(scene.objects):
        a, b = o.vertex_slice
        fa, fb = o.face_slice
        obj = dict(name=o.name, vertices=scene.vertices[a:b], faces=scene.faces[fa:fb] - a,
                   fixed=[j - a for j in o.fixed] or None)
        for n in ("k_structural", "dashpot", "drag", "total_weight"):
            obj[n] = float(p[PARAM_NAMES.index(n)][i])
        d = float(p.damping[i])
        obj["damping"] = d if d > 0 else None
        if o.has_gas:
            obj["nmol"] = float(p.nmol[i])
        objects.append(obj)
    lines = [f"fitted by jaxplush-fit from scene {result.scene_path} and target {result.target_path}",
             f"loss {result.loss:.6g} ({result.normalisation}-normalised); {result.reason}"]
    for n in result.names:
        for j, o in enumerate(result.objects):
            lines.append(f"{n} of {o}: start {result.start[n][j]:.6g}, fitted {result.values[n][j]:.6g}")
    # the scene's floor and contact settings carry over; the contact capacity is the one the fit
    # ran with (raised above the scene's if its candidates overflowed: fitting.fit)
    settings = dict(floor_friction=scene.floor_friction or None, floor_restitution=scene.floor_restitution or None,
                    contact=False if not scene.contact else None, self_collision=True if scene.self_collision else None,
                    contact_stiffness=scene.contact_stiffness, contact_thickness=scene.contact_thickness,
                    contact_friction=scene.contact_friction or None, contact_capacity=scene.contact_capacity,
                    floor_model=scene.floor_model if scene.floor_model != "projection" else None,
                    floor_stiffness=scene.floor_stiffness)
    cfg = result.problem.sim.terms.contact
    grown = any(w.startswith("contact candidates overflowed") for w in result.warnings)
    if cfg is not None and (scene.contact_capacity is not None or grown):
        settings["contact_capacity"] = max(cfg.capacity)
    return format_scene(objects, gravity=scene.gravity, floor=scene.floor, temperature=scene.temperature,
                        header="\n".join(lines), **settings)


def write_fitted_scene(result, path):
    """Write :func:`fitted_scene_text` to ``path`` atomically."""
    text = fitted_scene_text(result)
    with atomic_path(path, ".obj") as tmp:
        with open(tmp, "w", encoding="utf-8", newline="\n") as fh:
            fh.write(text)
    return os.fspath(path)
