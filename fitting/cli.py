"""Command line ``jaxplush-fit``: fit parameters to a target, or (``jaxplush-fit sweep ...``) sweep them.

    jaxplush-fit SCENE.obj TARGET.h5 [--params k_structural,damping,nmol] [--objects NAMES]
        [--optimizer lm|adam|lbfgs] [--bounds NAME=LO:HI,...] [--iterations N] [--lr LR] [--dt DT]
        [--noise SIGMA | --noise-free] [--shooting auto|off|FRAMES] --out FIT.h5
        [--out-scene FITTED.obj] [--resume]
    jaxplush-fit SCENE.obj TARGET.h5 --field edges|regions [--field-weight W] [--field-png PNG]
        [--field-true TRUE.obj] [--params dashpot,nmol] [--optimizer lbfgs|adam] ... --out FIT.h5

With ``--field`` the spring stiffness is fitted as a field (one value per edge, or per face group
of the scene's ``g`` lines) with the global parameters, by gradients through the rollout
(:mod:`jaxplush.fitting.stages.field`); FIT.h5 gains ``fields/k_structural`` [E], ``--out-scene`` writes the
field (``k_region`` or ``k_edge`` lines), and a picture of the field on the mesh is written next
to FIT.h5 (``FIT.field.png``, or ``--field-png``), beside the true field of ``--field-true``.

Before fitting it prints the predictability of the start values over the target (stderr): how
long the positions stay predictable and the model's own reproducibility floor (the result table
repeats it; a fit whose residual lies at that floor ends ``at_floor``, not ``poor_fit``), and how
the default fit shoots (``--shooting``, :mod:`jaxplush.fitting.objective.shooting`): one rollout over the
target, or segments no longer than the horizon, restarted from the observed positions.

Every input is validated before anything is traced or written; a bad input prints one message
(no traceback), writes nothing and exits 2. A fit that cannot proceed (the rollout blows up)
exits 3; a fit that finished without reaching the data or the model's reproducibility floor
(jaxplush.fitting.judge.outcome) writes FIT.h5 with its status and exits 4. One
that has done what the data allow exits 0: converged, or reproducing the target with some
parameters undetermined (``undetermined``, said on stderr), or at the reproducibility floor
(``at_floor``, said on stderr with the predictable horizon), its values, and the combinations the
target determines, reported with their intervals. Ctrl-C (or SIGTERM) saves the state to FIT.h5 and exits 130;
``--resume`` continues it.
"""

from __future__ import annotations

import argparse
import math
import os
import signal
import sys
import warnings

from jaxplush.cliargs import attach_negative_values
from jaxplush.io.trajectory import check_output_path

EXIT_USAGE = 2
EXIT_FAILED = 3
EXIT_NOT_CONVERGED = 4     # the fit finished but did not converge to the data (jaxplush.fitting.judge.outcome)
EXIT_INTERRUPTED = 130


def _parser():
    p = argparse.ArgumentParser(
        prog="jaxplush-fit",
        description="Fit material parameters of a jaxplush scene to a target deformation (HDF5) by gradients "
                    "through the rollout. 'jaxplush-fit sweep ...' runs batched parameter sweeps.")
    p.add_argument("scene", help="extended-OBJ scene; its values of the fitted parameters are the start")
    p.add_argument("target", help="target HDF5: 'positions' [T, V, 3], 'points' [T, M, 3] and/or 'tracks' [T, M, 3] "
                                  "(with 'track_vertex' or 'track_face' and 'track_barycentric'), and 'times' "
                                  "[T] (any 'jaxplush simulate' output); optionally the group 'controls' (driven "
                                  "vertices' measured path)")
    p.add_argument("--target-kind", default=None, choices=("positions", "mixed", "points", "tracks"),
                   help="which frames of a target that holds several to fit (default: positions; else, with "
                        "both points and tracks, mixed: the two together; else whichever it holds)")
    p.add_argument("--track-weight", type=float, default=None,
                   help="a mixed target's weight w of its tracks against its scan: the loss is (L_points + "
                        "w L_tracks) / (1 + w), each normalised on its own (default 1)")
    p.add_argument("--params", default=None,
                   help="comma-separated parameters to fit (k = k_structural; damping, dashpot, drag, nmol; "
                        "total_weight only with a warning). Default: the material parameters the scene switches "
                        "on: k_structural, its damping (damping, dashpot and/or drag, whichever is above 0) and "
                        "nmol where there is gas")
    p.add_argument("--objects", default=None, help="comma-separated object names to fit (default: all)")
    p.add_argument("--start", default=None, metavar="NAME=VALUE,...",
                   help="start values overriding the scene's, e.g. k=800,nmol=0.002 (applied to every fitted "
                        "object)")
    p.add_argument("--optimizer", default=None,
                   help="lm (default: a global stage over the search box, then Levenberg-Marquardt from the best "
                        "candidates), adam or lbfgs (gradient descent from the start values; lbfgs is the default "
                        "with --field)")
    p.add_argument("--bounds", default=None, metavar="NAME=LO:HI,...",
                   help="search box of the default fit, e.g. k=100:2000,nmol=1e-3:1e-2 (every fitted object); "
                        "default: each fitted parameter from start/4 to start*4")
    p.add_argument("--samples", type=int, default=None, help="global-stage Sobol points (default 64)")
    p.add_argument("--starts", type=int, default=None, help="local starts from the global stage (default 5)")
    p.add_argument("--no-linear-start", dest="linear_start", action="store_false",
                   help="leave out of the global stage the start estimated from the model's linear force balance "
                        "(position targets; docs/fitting.md, 'A start from the model's linearity')")
    p.add_argument("--iterations", type=int, default=None,
                   help="maximum iterations (default: 40 Levenberg-Marquardt iterations per start; 200 for adam "
                        "and lbfgs)")
    p.add_argument("--lr", type=float, default=None, help="learning rate in log space (adam default 0.05)")
    p.add_argument("--dt", type=float, default=None, help="time step, s (default: the target's)")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--noise", type=float, default=None,
                   help="measurement noise per coordinate, m (default: the target's 'noise' attribute)")
    g.add_argument("--noise-free", action="store_true", help="the target is exact (synthetic)")
    p.add_argument("--shooting", default="auto", metavar="auto|off|FRAMES",
                   help="position targets: 'auto' (default) runs segments restarted from the observed positions "
                        "where the motion is not predictable over the whole target and that measures better; "
                        "'off' one rollout; or FRAMES per segment")
    p.add_argument("--jacobian", default=None, choices=("difference", "forward"),
                   help="how the default fit's Levenberg-Marquardt takes its Jacobians: difference (default: "
                        "central differences on the batched engine) or forward (exact, by forward mode)")
    p.add_argument("--field", default=None, choices=("edges", "regions"),
                   help="fit k_structural as a field: one value per edge, or per face group ('g' lines); --params "
                        "then names the global parameters fitted with it (default: the scene's damping and nmol)")
    p.add_argument("--field-weight", type=float, default=None, metavar="W",
                   help="with --field: weight of the smoothness term W * sum over neighbours (log k_a - log k_b)^2 "
                        "(default 1/(N tau^2), N the target's residuals, tau = 0.5; docs/fitting.md)")
    p.add_argument("--field-png", default=None,
                   help="with --field: where to draw the fitted field (default: next to --out, FIT.field.png)")
    p.add_argument("--field-true", default=None, metavar="SCENE",
                   help="with --field: a scene holding the true field, drawn beside the fitted one")
    p.add_argument("--out", required=True, help="output FIT.h5 (also the checkpoint file)")
    p.add_argument("--out-scene", default=None, help="also write the scene with the fitted values (.obj)")
    p.add_argument("--resume", action="store_true", help="continue the interrupted fit saved in --out")
    p.add_argument("--checkpoint-every", type=int, default=10, help="iterations between checkpoints (default 10)")
    p.add_argument("--force", action="store_true", help="allow fitting total_weight jointly with k/dashpot/nmol")
    p.add_argument("--method", default="auto", help="gradient method: auto, checkpoint, plain, adjoint")
    p.add_argument("--x64", action="store_true", help="fit in float64")
    p.add_argument("--polish", choices=("off", "float64"), default="off",
                   help="float64: after the default fit, its local stages again in float64 from its best "
                        "point, judged in float64 (where float32 rounding leaves the loss rough; about 1.4-2x "
                        "the search's time per iteration)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    return p


def main(argv=None):
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv and argv[0] == "sweep":
        from jaxplush.fitting.sweep.cli import main as sweep_main
        return sweep_main(argv[1:])
    try:
        args = _parser().parse_args(attach_negative_values(argv))
    except SystemExit as e:  # argparse has printed its usage message
        return int(e.code) if isinstance(e.code, int) else EXIT_USAGE
    from jaxplush.stepping.compiled import enable_persistent_cache
    enable_persistent_cache()          # a second run of the same scene reuses this one's compiles
    from jaxplush.errors import JaxplushError
    try:
        return _fit(args)
    except JaxplushError as e:
        code = EXIT_FAILED if _failed(e) else EXIT_USAGE
        print(f"jaxplush-fit: error: {e}", file=sys.stderr)
        return code
    except KeyboardInterrupt:  # before or after the fit itself (loading, compiling, writing --out-scene)
        print("jaxplush-fit: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED


def _failed(error):
    """Whether ``error`` says the fit or a simulation failed (exit :data:`EXIT_FAILED`), not bad input."""
    from jaxplush.errors import SimulationError
    from jaxplush.fitting.errors import FitError
    return isinstance(error, (FitError, SimulationError))


def _fit(args):
    _check_args(args)
    if args.x64:
        import jax
        jax.config.update("jax_enable_x64", True)
    import jaxplush
    from jaxplush.fitting import fitter as _fit_mod
    from jaxplush.fitting.targets import load_target

    names = _fit_mod.canonical_names(args.params) if args.params is not None else None
    options = _options(args, names)
    scene = jaxplush.load_scene(args.scene)
    if args.noise is not None and not args.noise_free:
        from jaxplush.fitting.objective.problem import check_noise
        check_noise(args.noise, scene, "--noise")
    if args.field:
        return _fit_field(args, scene, names, options)
    target = load_target(args.target, scene, args.dt, kind=args.target_kind)
    result = _run(args, lambda: _fit_mod.fit(scene, target, names, args.objects, optimizer=args.optimizer,
                                             options=options, progress=not args.quiet, report=_note))
    if result is None:
        return EXIT_INTERRUPTED
    return _report(args, result)


def _fit_field(args, scene, names, options):
    """``--field``: the stiffness field's fit, FIT.h5, --out-scene and the picture of the field."""
    import jaxplush
    from jaxplush.errors import JaxplushError
    from jaxplush.fitting.stages import field as _field
    from jaxplush.fitting.targets import load_target
    truth = None
    if args.field_true is not None:
        true_scene = jaxplush.load_scene(args.field_true)
        if not (true_scene.faces.shape == scene.faces.shape and (true_scene.faces == scene.faces).all()):
            raise JaxplushError(f"--field-true {args.field_true}: its faces differ from the scene's {args.scene}")
        truth = _field_of(true_scene)
    target = load_target(args.target, scene, args.dt, kind=args.target_kind)
    # every input checked before the fit: the problem builds (and raises) before anything is traced
    result = _run(args, lambda: _field.fit_field(scene, target, args.field, names, optimizer=args.optimizer,
                                                 weight=args.field_weight, options=options,
                                                 progress=not args.quiet))
    if result is None:
        return EXIT_INTERRUPTED
    result.save(args.out)
    if args.out_scene:
        result.write_scene(args.out_scene)
    png = args.field_png or os.path.splitext(args.out)[0] + ".field.png"
    result.render(png, truth=truth, title=f"k_structural per {args.field[:-1]}: fitted"
                  + (" and true" if truth is not None else " and start"))
    print(result.table())
    status = _field._outcome(result)
    if result.identifiability is not None:     # standard errors only for a fit that reached the data
        print(result.identifiability.summary(standard_errors=status.converged))
    print(f"wrote {args.out}, {png}" + (f" and {args.out_scene}" if args.out_scene else ""))
    if not status.converged:
        print(f"jaxplush-fit: {status.text} (exit {EXIT_NOT_CONVERGED})", file=sys.stderr)
        return EXIT_NOT_CONVERGED
    return 0


def _field_of(scene):
    """(E,) a scene's per-edge stiffness (its field, or each object's value on every edge)."""
    import numpy as np
    k = np.asarray(scene.params.k_structural, np.float64)
    return k if k.shape == (len(scene.edges),) and scene.has_k_field else k[scene.edge_object]


def _note(line):
    """A line about the fit before it starts (the predictability of the start values), on stderr."""
    print(line, file=sys.stderr, flush=True)


def _check_args(args):
    """Everything checked before anything is traced or written (JaxplushError with the first problem)."""
    from jaxplush.errors import JaxplushError
    if args.optimizer is None:
        args.optimizer = "lbfgs" if args.field else "lm"
    if args.field:
        _check_field_args(args)
    elif args.field_weight is not None or args.field_png is not None or args.field_true is not None:
        raise JaxplushError("--field-weight, --field-png and --field-true go with --field")
    if args.iterations is not None and args.iterations < 1:
        raise JaxplushError(f"--iterations must be >= 1, got {args.iterations}")
    if args.checkpoint_every < 1:
        raise JaxplushError(f"--checkpoint-every must be >= 1, got {args.checkpoint_every}")
    if args.optimizer not in ("lm", "adam", "lbfgs"):
        raise JaxplushError(f"--optimizer must be lm, adam or lbfgs, got {args.optimizer!r}")
    if args.samples is not None and args.samples < 0:
        raise JaxplushError(f"--samples must be >= 0, got {args.samples}")
    if args.starts is not None and args.starts < 1:
        raise JaxplushError(f"--starts must be >= 1, got {args.starts}")
    if args.optimizer != "lm":
        for name, val in (("--bounds", args.bounds), ("--samples", args.samples), ("--starts", args.starts)):
            if val is not None:
                raise JaxplushError(f"{name} belongs to the default fit (--optimizer lm), not {args.optimizer}")
    for name, val in (("--lr", args.lr), ("--dt", args.dt)):
        if val is not None and not (val == val and 0 < val < float("inf")):
            raise JaxplushError(f"{name} must be a positive number, got {val}")
    args.shooting = _shooting_arg(args.shooting)
    if args.optimizer != "lm" and args.shooting not in ("auto", "off"):
        raise JaxplushError(f"--shooting {args.shooting} belongs to the default fit (--optimizer lm), "
                            f"not {args.optimizer}")
    if args.noise is not None and not (args.noise == args.noise and 0 <= args.noise < float("inf")):
        raise JaxplushError(f"--noise must be a number >= 0, got {args.noise}")
    if args.track_weight is not None and not (args.track_weight == args.track_weight
                                              and 0 < args.track_weight < float("inf")):
        raise JaxplushError(f"--track-weight must be a positive number, got {args.track_weight}")
    check_output_path(args.out, (".h5", ".hdf5"), "--out")
    if args.out_scene is not None:
        check_output_path(args.out_scene, (".obj",), "--out-scene")
    for a, b in ((args.out, args.target), (args.out, args.scene), (args.out_scene, args.scene),
                 (args.out_scene, args.target)):
        if a is not None and os.path.realpath(a) == os.path.realpath(b):
            raise JaxplushError(f"{a}: an output must not overwrite an input")
    if args.resume and not os.path.exists(args.out):
        raise JaxplushError(f"{args.out}: no checkpoint to resume (the file does not exist); run without --resume")


def _check_field_args(args):
    """The options that go with --field (and those that do not)."""
    from jaxplush.errors import JaxplushError
    if args.optimizer not in ("lbfgs", "adam"):
        raise JaxplushError(f"--field fits by gradients: --optimizer lbfgs (default) or adam, not {args.optimizer}")
    if args.objects is not None:
        raise JaxplushError("--objects does not go with --field (the field spans every object)")
    if args.shooting not in ("auto", "off"):
        raise JaxplushError("--shooting does not go with --field (one rollout over the target)")
    w = args.field_weight
    if w is not None and not (w == w and 0 <= w < float("inf")):
        raise JaxplushError(f"--field-weight must be a number >= 0, got {w}")
    if args.field_png is not None:
        check_output_path(args.field_png, (".png", ".pdf", ".svg", ".jpg", ".jpeg"), "--field-png")


def _shooting_arg(text):
    """--shooting: "auto", "off" or frames per segment (an int >= 2)."""
    from jaxplush.errors import JaxplushError
    if text in ("auto", "off"):
        return text
    try:
        n = int(text)
    except ValueError:
        n = 0
    if n < 2:
        raise JaxplushError(f"--shooting must be auto, off or frames per segment (an integer >= 2), got {text!r}")
    return n


def _options(args, names):
    """The :class:`fitting.FitOptions` of the command line (--start and --bounds parsed and checked)."""
    from jaxplush.fitting import fitter as _fit_mod
    from jaxplush.fitting.options import CheckpointOptions, FitOptions, LocalOptions, SearchOptions
    start = parse_start(args.start) if args.start is not None else None
    bounds = _fit_mod.parse_bounds(args.bounds, names or _fit_mod.PARAM_NAMES) if args.bounds is not None else None
    return FitOptions(iterations=args.iterations, lr=args.lr, start=start, noise=args.noise,
                      noise_free=args.noise_free, track_weight=args.track_weight, method=args.method, force=args.force,
                      shooting=args.shooting, polish=args.polish,
                      search=SearchOptions(bounds=bounds, samples=args.samples, starts=args.starts,
                                           linear=args.linear_start),
                      local=LocalOptions() if args.jacobian is None else LocalOptions(jacobian=args.jacobian),
                      checkpoint=CheckpointOptions(path=args.out, every=args.checkpoint_every, resume=args.resume))


def _run(args, run_fit):
    """``run_fit()`` with its warnings printed once each, SIGTERM taken as Ctrl-C; the result, or
    None after an interrupt (reported: whether the state was saved to --out)."""
    from jaxplush.errors import JaxplushError

    # SIGTERM behaves like Ctrl-C: save, then exit
    def _term(signum, frame):
        raise KeyboardInterrupt
    old = signal.signal(signal.SIGTERM, _term) if hasattr(signal, "SIGTERM") else None
    before = _stamp(args.out)   # an interrupted fit says "saved" only if it wrote --out (or it resumes it)
    printed = set()

    def show(ws):
        for w in ws:
            msg = str(w.message)
            if msg not in printed:
                printed.add(msg)
                print(f"warning: {msg}", file=sys.stderr)

    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            try:
                result = run_fit()
            except JaxplushError as e:
                if _failed(e):
                    show(caught)              # e.g. the dt warning that explains a blow-up
                raise                         # bad input: its one message alone
            except BaseException:
                show(caught)
                raise
        # the identifiability warnings are printed with its summary below
        printed.update(result.identifiability.warnings if result.identifiability is not None else ())
        show(caught)
    except KeyboardInterrupt:
        saved = os.path.exists(args.out) and (args.resume or _stamp(args.out) != before)
        print("jaxplush-fit: interrupted; " + (f"state saved to {args.out}; continue with --resume"
                                                 if saved else "nothing written"), file=sys.stderr)
        return None
    finally:
        if old is not None:
            signal.signal(signal.SIGTERM, old)
    return result


def _report(args, result):
    """Write --out-scene, print the table and the identifiability summary; the exit code."""
    if args.out_scene:
        result.write_scene(args.out_scene)
    print(result.table())
    from jaxplush.fitting.judge.outcome import DONE, REPORTED, Status
    if result.identifiability is not None:
        print(result.identifiability.summary(standard_errors=result.status in REPORTED))
    print(f"wrote {args.out}" + (f" and {args.out_scene}" if args.out_scene else ""))
    if result.status not in DONE:
        print(f"jaxplush-fit: the fit did not reach the data ({result.status}); see FIT.h5 and the message "
              f"above (exit {EXIT_NOT_CONVERGED})", file=sys.stderr)
        return EXIT_NOT_CONVERGED
    undetermined = _undetermined(result)
    if result.status == Status.UNDETERMINED:
        which = ", ".join(undetermined) or "some parameters"
        print(f"jaxplush-fit: the fit reproduces the target but does not determine {which} (undetermined); "
              "the values it determines, and any combination it determines, are in the table with their "
              "intervals", file=sys.stderr)
    if result.status == Status.AT_FLOOR:
        o = result.outcome
        horizon = (f"; the motion is predictable for {o.horizon:.3g} s of the target" if math.isfinite(o.horizon)
                   else "")
        which = (f"; at this floor it does not determine {', '.join(undetermined)}, whose intervals are "
                 "infinite" if undetermined else "")
        print(f"jaxplush-fit: the fit reached the model's reproducibility floor (at_floor): no values do better "
              f"than rounding allows{horizon}; its values are in the table with their intervals{which}",
              file=sys.stderr)
    return 0


def _undetermined(result):
    """Labels of the parameters a result does not determine: the identifiability report's, and
    those whose interval is infinite (the twins' scan found every value it tried fits as well)."""
    rep, iv = result.identifiability, getattr(result, "intervals", None)
    out = list(rep.undetermined) if rep is not None else []
    if iv is not None and getattr(iv, "scan", None) is not None:
        out += [lab for lab, w in zip(iv.labels, iv.scan) if not math.isfinite(w) and lab not in out]
    return out


def parse_start(spec):
    """``"k=800,nmol=0.002"`` -> {canonical name: float}; JaxplushError naming the bad part."""
    from jaxplush.errors import JaxplushError
    from jaxplush.fitting.fitter import canonical_names
    out = {}
    for part in (p.strip() for p in spec.split(",")):
        if not part:
            continue
        name, eq, val = part.partition("=")
        if not eq or not name.strip():
            raise JaxplushError(f"--start: expected NAME=VALUE, got {part!r}")
        try:
            v = float(val)
        except ValueError:
            raise JaxplushError(f"--start: {name.strip()}={val!r} is not a number") from None
        if not (v == v and 0 < v < float("inf")):
            raise JaxplushError(f"--start: {name.strip()} must be a positive number, got {val}")
        n = canonical_names([name.strip()])[0]
        if n in out:
            raise JaxplushError(f"--start: {n} given twice")
        out[n] = v
    if not out:
        raise JaxplushError("--start: no values given")
    return out


def _stamp(path):
    """Identity of the file at ``path`` (atomic writes replace it), or None."""
    try:
        st = os.stat(path)
    except OSError:
        return None
    return st.st_ino, st.st_mtime_ns, st.st_size


if __name__ == "__main__":
    sys.exit(main())
