"""FIT.h5: the fit's result, its history and a resumable checkpoint (HDF5, written atomically).

Layout:

* attributes: ``status`` ("running" while checkpointing, "interrupted" after Ctrl-C, and once
  the fit ends its outcome, one of :data:`jaxplush.fitting.judge.outcome.STATUSES`), ``outcome_*`` (its fields),
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
  ``warnings`` (JSON), ``weakest``, ``summary``, ``jac_noise`` (the Jacobian's rounding noise,
  m; NaN: not known), ``undetermined`` (JSON list of the labels the target does not determine);
* ``intervals/`` (the default fit, :mod:`jaxplush.fitting.judge.intervals`): ``theta`` (log values),
  ``sd`` (the spread of each log value: its relative error; inf: undetermined), ``lower``,
  ``upper`` (the 95% interval in parameter units) datasets; attributes ``labels``, ``method``
  (``twins`` or ``residuals``), ``level``, ``quantile``, ``n_twins``, ``note``; ``scan`` where
  the twins' scan ran (how far each value can move and fit as well as rounding twins do, where
  that widened its interval; 0 elsewhere, inf: undetermined) and ``twin_sd`` (the twins' own
  spreads, before it);
* ``combinations/`` (the default fit, where the target determines a combination of fitted
  parameters but not its parts: the report's ``damping`` with ``drag``): ``value``, ``sd``,
  ``lower``, ``upper`` datasets, one entry per combination; attributes ``labels``, ``parts``
  (JSON), ``units``, ``notes`` (JSON);
* ``fitted/positions`` [T, V, 3], ``fitted/steps``, ``fitted/times``: the fitted rollout at the
  target frames;
* ``search/`` (the default fit): ``global/<name>`` and ``global/loss`` of every global sample,
  ``local/NNN/`` the path of each local search;
* ``predictability/`` (when measured, :func:`jaxplush.predictability` at the start values):
  ``times``, ``steps``, ``drift_rms``, ``motion_rms`` datasets; attributes ``horizon_time``
  (inf: never), ``horizon_frame`` (-1: never), ``floor_rms``, ``threshold``, ``threshold_kind``,
  ``motion``, ``perturbation``, ``method``, ``dtype``, ``duration``, ``text``;
* ``shooting/`` (the default fit, :mod:`jaxplush.fitting.objective.shooting`): attributes ``segment_frames``
  (0: one rollout), ``floor_rms``, ``single_floor_rms``, ``refine``, ``text``;
* ``timing/`` (a finished fit): attributes ``wall_s``, ``compile_s``, ``trace_s``, ``programs``,
  ``cache_hits``: the whole fit call in the process that finished it, its XLA compiles (and loads
  from the persistent cache) apart from the rest (:class:`jaxplush.compilestats.Timing`);
* ``checkpoint/``: the fit's complete state (the gradient loop's log values, optimiser state,
  history and counters; the default fit's stage driver and its stage's searches), a pytree as
  :mod:`jaxplush.fitting.io.treeio` writes it, with attributes ``format`` and ``settings``: enough
  for ``--resume`` to continue to the same answer.

Format: docs/formats.md §5.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import os

import h5py
import numpy as np

from jaxplush.errors import ContactCapacityWarning, JaxplushError, Note, TrajectoryError
from jaxplush.fitting.options import TUNING
from jaxplush.fitting.judge.outcome import Status
from jaxplush.fitting.io.treeio import read_tree, write_tree
from jaxplush.io.trajectory import atomic_path, open_hdf5
from jaxplush.types import PARAM_NAMES

#: Settings that must agree between a checkpoint and the fit resuming it.
_RESUME_KEYS = ("optimizer", "lr", "names", "objects", "dt", "noise_free", "noise", "method", "frame_steps",
                "target_kind", "target_hash", "scene_hash", "params_hash", "dtype", "gtol", "rtol", "xtol", "ftol",
                "patience", "optax_state")
#: ... and for Adam, whose cosine learning-rate schedule spans the iterations, also these.
_RESUME_KEYS_ADAM = ("iterations",)
#: ... and for a stiffness field's fit, the field, its smoothness weight and its unknowns.
_RESUME_KEYS_FIELD = ("field", "weight", "n_unknowns", "preconditioned", "theta0_hash")
#: ... and for the default fit, its search box, global design and tuning knobs.
_RESUME_KEYS_LM = ("box_lo", "box_hi", "samples", "starts", "seed", "local", "continuation", "smoothing",
                   "multiple_shooting", "solver")
#: Settings a checkpoint written before they were recorded ran with (the defaults of the time).
_RESUME_DEFAULTS = {group: dataclasses.asdict(cls()) for group, cls in TUNING.items()}
_RESUME_HINTS = {"iterations": "; Adam's learning-rate schedule spans all the iterations",
                 "dtype": "; give --x64 as the checkpointed fit did, or leave it out likewise"}


def fingerprint(prob):
    """Hashes of the scene text and the target data, to recognise the same fit on resume."""
    scene_hash = hashlib.sha1(prob.scene.text.encode()).hexdigest()
    h = hashlib.sha1(np.ascontiguousarray(prob.target.data, np.float64).tobytes())
    h.update(np.asarray(prob.target.steps, np.int64).tobytes())
    t = prob.target
    if t.tracks is not None:          # which points the tracks are
        h.update(np.asarray(t.track_vertices, np.int64).tobytes())
        h.update(np.asarray(t.track_weights, np.float64).tobytes())
    if t.kind.compound:               # and how they weigh against the scan
        h.update(repr((t.kind.value, int(t.points.shape[1]), float(t.track_weight))).encode())
    if t.controls is not None:        # the driven vertices' path
        c = t.controls
        h.update(repr(("controls", c.until)).encode())
        for a in c.datasets().values():
            h.update(np.ascontiguousarray(a).tobytes())
    return scene_hash, h.hexdigest()


def _settings(prob, settings):
    s = dict(settings)
    s["scene_hash"], s["target_hash"] = fingerprint(prob)
    # the start values and the values held fixed (a `start` override is not in the scene text)
    # (the bytes of the (P, O) stack of old; k_structural may be an (E,) stiffness field)
    s["params_hash"] = hashlib.sha1(np.ascontiguousarray(np.concatenate([np.asarray(getattr(prob.base, n), np.float64)
                                                                         .ravel() for n in PARAM_NAMES])).tobytes()).hexdigest()
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


def save_checkpoint(path, prob, state, settings, status="running", *, theta=None, history=None, **attrs):
    """Write a fit's ``state`` (a pytree, :func:`jaxplush.fitting.io.treeio.write_tree`) to ``path`` atomically,
    with what a person reads of it: the best values so far (log values ``theta``), ``history``
    (name -> array) and ``attrs`` (loss, iterations, rejected). A default fit's checkpoint with
    values also gets ``intervals/``: its search box (``method`` ``box``), all a fit that has not
    finished can say of where the truth lies."""
    with atomic_path(path, ".h5") as tmp:
        with h5py.File(tmp, "w") as f:
            _common_attrs(f, prob, settings, status)
            for k, v in attrs.items():
                f.attrs[k] = v
            if theta is not None:
                _write_values(f.create_group("params"), prob, prob.values(theta))
                if "box_lo" in settings and "box_hi" in settings:
                    # the default fit, not finished: all it can say of where the truth lies is its
                    # search box (jaxplush.fitting.judge.intervals.box)
                    from jaxplush.fitting.judge import intervals as _intervals
                    from jaxplush.fitting.stages.search import Box
                    th = np.asarray(theta, np.float64)
                    box = Box(np.reshape(settings["box_lo"], th.shape), np.reshape(settings["box_hi"], th.shape))
                    write_intervals(f, _intervals.box(prob.labels, th, box, status))
            _write_values(f.create_group("start"), prob, prob.start)
            if history is not None:
                hg = f.create_group("history")
                for k, v in history.items():
                    hg.create_dataset(k, data=np.asarray(v))
            _write_state(f, prob, state, settings)
    return os.fspath(path)


def write_identifiability(f, rep):
    """The ``identifiability`` group of FIT.h5 (module docstring) from an
    :class:`jaxplush.fitting.judge.identifiability.IdentifiabilityReport`, in the open file ``f``."""
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
    ig.attrs["jac_noise"] = float(rep.jac_noise)
    ig.attrs["undetermined"] = json.dumps(list(rep.undetermined))
    ig.attrs["summary"] = rep.summary()


def write_intervals(f, iv):
    """The ``intervals`` group of FIT.h5 (module docstring) from an
    :class:`jaxplush.fitting.judge.intervals.Intervals`, in the open file ``f``."""
    g = f.create_group("intervals")
    for k in ("theta", "sd", "lower", "upper"):
        g.create_dataset(k, data=np.asarray(getattr(iv, k), np.float64))
    g.attrs["labels"] = np.asarray(iv.labels, dtype=object)
    g.attrs["method"] = iv.method
    g.attrs["level"] = float(iv.level)
    g.attrs["quantile"] = float(iv.quantile)
    g.attrs["n_twins"] = int(iv.n_twins)
    g.attrs["note"] = iv.note
    if getattr(iv, "scan", None) is not None:
        g.create_dataset("scan", data=np.asarray(iv.scan, np.float64))
    if getattr(iv, "twin_sd", None) is not None:
        g.create_dataset("twin_sd", data=np.asarray(iv.twin_sd, np.float64))


def save_fit(result, path):
    """Write a :class:`jaxplush.fitting.judge.result.FitResult` as FIT.h5 atomically; its ``status`` attribute is the
    fit's outcome (jaxplush.fitting.judge.outcome: "converged", "poor_fit", "stalled", ...)."""
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
            if result.identifiability is not None:
                write_identifiability(f, result.identifiability)
            if getattr(result, "intervals", None) is not None:
                write_intervals(f, result.intervals)
            if getattr(result, "combinations", ()):
                cg = f.create_group("combinations")
                for k in ("value", "sd", "lower", "upper"):
                    cg.create_dataset(k, data=np.asarray([getattr(c, k) for c in result.combinations], np.float64))
                cg.attrs["labels"] = np.asarray([c.label for c in result.combinations], dtype=object)
                cg.attrs["parts"] = json.dumps([list(c.parts) for c in result.combinations])
                cg.attrs["units"] = np.asarray([c.unit for c in result.combinations], dtype=object)
                cg.attrs["notes"] = json.dumps([c.note for c in result.combinations])
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
            if getattr(result, "timing", None) is not None:
                write_timing(f, result.timing)
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
            if loop is not None:    # a gradient fit's LoopState, or the default fit's driver state (LMRun.state)
                _write_state(f, prob, getattr(loop, "state", loop), result.settings)
    return os.fspath(path)


def write_timing(f, timing):
    """The ``timing`` group of FIT.h5 (module docstring) from a
    :class:`jaxplush.compilestats.Timing`, in the open file ``f``: attributes ``wall_s``,
    ``compile_s``, ``trace_s`` (s) and ``programs``, ``cache_hits``."""
    g = f.create_group("timing")
    for k in ("wall_s", "compile_s", "trace_s"):
        g.attrs[k] = float(getattr(timing, k))
    for k in ("programs", "cache_hits"):
        g.attrs[k] = int(getattr(timing, k))


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
    """The ``shooting`` group of FIT.h5 (a :class:`jaxplush.fitting.objective.shooting.Shooting`): attributes
    ``segment_frames`` (0: single shooting), ``floor_rms`` and ``single_floor_rms`` (m; NaN: not
    measured), ``refine`` and ``text``; where multiple shooting's own bias was taken off the fitted
    values (:func:`jaxplush.fitting.objective.shooting.debias`), ``bias``: the relative bias per fitted
    parameter (rows) and object (columns), as the values' layout."""
    g.attrs["segment_frames"] = int(sh.segment_frames or 0)
    g.attrs["floor_rms"] = float("nan") if sh.floor is None else float(sh.floor)
    g.attrs["single_floor_rms"] = float("nan") if sh.single_floor is None else float(sh.single_floor)
    g.attrs["refine"] = int(sh.refine)
    g.attrs["text"] = sh.reason
    if sh.bias is not None:
        g.attrs["bias"] = np.expm1(np.asarray(sh.bias, np.float64))


# --------------------------------------------------------------------------- the checkpoint

#: The checkpoint's format: the state pytree of :mod:`jaxplush.fitting.io.treeio` (a file without it
#: was written by an older jaxplush, in a format of its own).
CHECKPOINT_FORMAT = "tree-1"
#: The checkpoint group's own attributes (a state's fields must not take these names).
_CHECKPOINT_ATTRS = ("format", "settings")


def _write_state(f, prob, state, settings):
    """The ``checkpoint`` group: the format, the settings a resume must match, and the state pytree."""
    names = {fld.name for fld in dataclasses.fields(state)} if dataclasses.is_dataclass(state) else set()
    if names & set(_CHECKPOINT_ATTRS):
        raise TypeError(f"a checkpointed state must not have the fields {sorted(names & set(_CHECKPOINT_ATTRS))}")
    g = f.create_group("checkpoint")
    write_tree(g, state)
    g.attrs["format"] = CHECKPOINT_FORMAT
    g.attrs["settings"] = json.dumps(_settings(prob, settings))


def load_checkpoint(path, prob, settings, conform=None):
    """The state pytree checkpointed in ``path``, checked to belong to this fit (its settings);
    ``conform(state)`` (optional) checks it further and returns the state to use."""
    path = os.fspath(path)
    if not os.path.exists(path):
        raise JaxplushError(f"{path}: no checkpoint to resume (the file does not exist); run without --resume")
    try:
        f = h5py.File(path, "r")
    except OSError:
        raise TrajectoryError(path, "not an HDF5 file: cannot resume from it") from None
    try:
        with f:
            if "checkpoint" not in f:
                raise TrajectoryError(path, "holds no checkpoint group: not a resumable FIT.h5")
            g = f["checkpoint"]
            if g.attrs.get("format") != CHECKPOINT_FORMAT:
                raise JaxplushError(f"{path}: cannot resume: its checkpoint was written by an older jaxplush; "
                                    "run without --resume to start over")
            _check_settings(path, g, prob, settings)
            state = read_tree(g)
            return conform(state) if conform is not None else state
    except (KeyError, ValueError, TypeError, OSError) as e:  # damaged, or written by another version
        raise TrajectoryError(path, f"cannot read the checkpoint ({e}); run without --resume to start over") from None


def _check_settings(path, g, prob, settings):
    saved = json.loads(g.attrs["settings"])
    mine = _settings(prob, settings)
    keys = _RESUME_KEYS + (_RESUME_KEYS_ADAM if mine.get("optimizer") == "adam" else ()) + (
        _RESUME_KEYS_LM if mine.get("optimizer") == "lm" else ()) + (_RESUME_KEYS_FIELD if "field" in mine else ())
    for k in keys:
        was = saved.get(k, _RESUME_DEFAULTS.get(k))
        if isinstance(was, dict) and k in _RESUME_DEFAULTS:
            was = {**_RESUME_DEFAULTS[k], **was}     # knobs added since: their defaults of the time
        if _norm(was) != _norm(mine.get(k)):
            raise JaxplushError(f"{path}: the checkpoint is of a different fit ({k}: checkpoint "
                                f"{saved.get(k)!r}, now {mine.get(k)!r}{_RESUME_HINTS.get(k, '')}); "
                                "run without --resume to start over")


def _norm(v):
    """Settings compared after a JSON round trip (tuples -> lists, floats exact)."""
    return json.loads(json.dumps(v))


def load_fit(path):
    """Read FIT.h5 into a dict: attributes, params, start, history, identifiability, intervals,
    fitted, predictability, fields, timing (each group present: its datasets, and its attributes under
    "<group>_attrs")."""
    path = os.fspath(path)
    out = {}
    with open_hdf5(path) as f:
        out["attrs"] = {k: _attr(f.attrs[k]) for k in f.attrs}
        for grp in ("params", "start", "history", "identifiability", "intervals", "combinations", "fitted",
                    "predictability", "fields", "timing"):
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


def controls_files(result, path):
    """{(object index, entry): path file} for the driven paths of a fit's scene that came from the
    target's controls (:func:`jaxplush.fitting.targets.scene_with_controls`): the HDF5 path files
    (``times``, ``positions``) that :func:`write_fitted_scene` writes beside the scene ``path``,
    ``STEM.controls-I.h5`` for object I; empty without controls."""
    from jaxplush.fitting.targets import from_controls
    stem = os.path.splitext(os.fspath(path))[0]
    return {(i, j): f"{stem}.controls-{i}.h5" for i, o in enumerate(result.problem.scene.objects)
            for j, d in enumerate(o.driven) if from_controls(d)}


def _driven_entries(o, a, out_path, controls=None):
    """An object's ``driven`` lines for the writer: each path file relative to the directory of the
    scene being written (``out_path``), or absolute (``out_path`` None, or no relative path).
    ``controls``: {entry: path file} of the entries that came from the target's controls (the
    others of them are left out)."""
    from jaxplush.fitting.targets import from_controls
    out = []
    for k, d in enumerate(o.driven):
        if from_controls(d) and k not in (controls or {}):
            continue
        file = controls[k] if from_controls(d) else d.file
        path = file
        if out_path is not None:
            try:
                path = os.path.relpath(file, os.path.dirname(os.path.abspath(os.fspath(out_path))))
            except ValueError:                  # another drive (Windows)
                path = file
        out.append(dict(path=path, vertices=[j - a for j in d.vertices], until=d.until))
    return out or None


def fitted_scene_text(result, path=None):
    """The scene text with the fitted values, in the extended OBJ format. ``path``: where it will
    be written (driven vertices' path files are named relative to its directory; None: absolute).
    Vertices driven by the target's controls get ``driven`` lines naming the path files
    :func:`write_fitted_scene` writes beside ``path`` (:func:`controls_files`); with ``path`` None,
    none (the header says which vertices the target's controls drive)."""
    from jaxplush.fitting.targets import from_controls
    from jaxplush.scene.write import format_scene, stiffness_keys
    scene = result.problem.scene
    files = controls_files(result, path) if path is not None else {}
    objects = []
    p = result.params
    for i, o in enumerate(scene.objects):
        a, b = o.vertex_slice
        fa, fb = o.face_slice
        mine = {j: f for (oi, j), f in files.items() if oi == i}
        obj = dict(name=o.name, vertices=scene.vertices[a:b], faces=scene.faces[fa:fb] - a,
                   fixed=[j - a for j in o.fixed] or None, driven=_driven_entries(o, a, path, mine))
        # k: per object, or a per-edge field (k_region / k_edge lines that read back bit for bit)
        obj.update(stiffness_keys(scene, i, p.k_structural))
        for n in ("dashpot", "drag", "total_weight"):
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
    ctrl = [i for d in scene.driven if from_controls(d) for i in d.vertices]
    if ctrl and path is None:
        lines.append(f"vertices {' '.join(str(i + 1) for i in ctrl)} were driven by the target's controls "
                     "(not written here)")
    # the scene's floor and contact settings carry over; the contact capacity is the one the fit
    # ran with (raised above the scene's if its candidates overflowed: fitting.fit)
    settings = dict(floor_friction=scene.floor_friction or None, floor_restitution=scene.floor_restitution or None,
                    contact=False if not scene.contact else None, self_collision=True if scene.self_collision else None,
                    contact_stiffness=scene.contact_stiffness, contact_thickness=scene.contact_thickness,
                    contact_friction=scene.contact_friction or None, contact_capacity=scene.contact_capacity,
                    floor_model=scene.floor_model if scene.floor_model != "projection" else None,
                    floor_stiffness=scene.floor_stiffness)
    cfg = result.problem.sim.terms.contact
    grown = any(isinstance(w, Note) and issubclass(w.category, ContactCapacityWarning) for w in result.warnings)
    if cfg is not None and (scene.contact_capacity is not None or grown):
        settings["contact_capacity"] = max(cfg.capacity)
    return format_scene(objects, gravity=scene.gravity, floor=scene.floor, temperature=scene.temperature,
                        header="\n".join(lines), **settings)


def write_fitted_scene(result, path):
    """Write :func:`fitted_scene_text` to ``path`` atomically, and the target's controls, if any, as
    the path files its ``driven`` lines name (:func:`controls_files`)."""
    scene = result.problem.scene
    for (i, j), file in controls_files(result, path).items():
        d = scene.objects[i].driven[j]
        with atomic_path(file, ".h5") as tmp:
            with h5py.File(tmp, "w") as f:
                f.create_dataset("times", data=np.asarray(d.times, np.float64))
                f.create_dataset("positions", data=np.asarray(d.positions, np.float64))
    text = fitted_scene_text(result, path)
    with atomic_path(path, ".obj") as tmp:
        with open(tmp, "w", encoding="utf-8", newline="\n") as fh:
            fh.write(text)
    return os.fspath(path)
