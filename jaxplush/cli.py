"""Command line: ``jaxplush simulate | render | info | capture | view``.

Every user error prints one clear message (no traceback), exits non-zero and leaves no
partial output.
"""

from __future__ import annotations

import argparse
import gc
import sys
import time
import warnings

import numpy as np

from jaxplush.cliargs import attach_negative_values
from jaxplush.io.trajectory import check_output_path

EXIT_USAGE = 2
EXIT_FAILED = 3
#: Most steps a run may take (the rollout's step counters are int32).
MAX_STEPS = 2 ** 31 - 1
#: Largest trajectory file ``simulate`` writes (and largest 'tracks' dataset ``capture`` writes).
MAX_OUTPUT_BYTES = 8 * 2 ** 30
#: Most rays (pixels) of a ``capture`` image.
MAX_PIXELS = 2 ** 22
#: ``capture``: the largest --noise and the camera's range, in multiples of the scene's extent
#: (the same numbers as jaxplush.io.capture.MAX_NOISE_EXTENTS and CAMERA_RANGE, which a test
#: compares; repeated here so that --help imports no JAX)
MAX_NOISE_EXTENTS = 1.0
CAMERA_RANGE = 1e4


def _times(factor):
    """A multiple of a length in words: nothing for 1, else "F times "."""
    return "" if factor == 1 else f"{factor:g} times "


def _parser():
    p = argparse.ArgumentParser(prog="jaxplush", description="Pressurised mass-spring plushies in JAX.")
    sub = p.add_subparsers(dest="cmd", required=True)

    s = sub.add_parser("simulate", help="simulate a scene and write an HDF5 trajectory")
    s.add_argument("scene", help="extended-OBJ scene file")
    s.add_argument("--steps", type=int, required=True, help="number of time steps")
    s.add_argument("--dt", type=float, required=True, help="time step in seconds")
    s.add_argument("--save-every", type=int, default=None, help="steps between saved frames (default: steps/100)")
    s.add_argument("--integrator", default="verlet",
                   help="euler, symplectic_euler, rk4, verlet (default), mesit (unsound, for comparison) "
                        "or implicit_euler")
    s.add_argument("--substeps", type=int, default=1, help="integrator steps of dt/substeps per time step (default 1)")
    s.add_argument("--out", required=True, help="output trajectory (.h5)")
    s.add_argument("--x64", action="store_true", help="run in float64 (reference runs)")
    s.add_argument("--quiet", action="store_true", help="no progress bar")

    r = sub.add_parser("render", help="render a trajectory to an animation or a still image")
    r.add_argument("trajectory", help="trajectory .h5 from 'jaxplush simulate'")
    r.add_argument("--out", required=True, help="output .gif/.mp4 (animation) or .png/.jpg/.pdf/.svg with --frame")
    r.add_argument("--frame", type=int, default=None, help="render only this frame (negative counts from the end)")
    r.add_argument("--fps", type=float, default=None,
                   help="playback frames per second (default: real time: each drawn frame is shown for the "
                        "simulated time it spans; a GIF shows at most 50 frames per simulated second)")
    r.add_argument("--max-frames", type=int, default=200,
                   help="most frames drawn (default 200); a longer trajectory is subsampled evenly, keeping the "
                        "first and last frame, and the command says how many it drew")

    i = sub.add_parser("info", help="describe a scene: counts, parameters, volume, pressure, stable dt; with --dt "
                                    "and --steps also how predictable its motion is")
    i.add_argument("scene", help="extended-OBJ scene file")
    i.add_argument("--dt", type=float, default=None, help="check this dt against the stability limit")
    i.add_argument("--steps", type=int, default=None,
                   help="with --dt: also run the scene for this many steps, twice (once from start positions "
                        "perturbed by a relative 1e-7) and once in float64, and report the predictable horizon "
                        "(when the runs drift apart by more than 0.1%% of the motion) and the reproducibility floor "
                        "(the RMS of that drift: the residual a fit at the exact parameters would have)")
    i.add_argument("--save-every", type=int, default=None,
                   help="with --steps: steps between the compared frames (default: steps/100)")
    i.add_argument("--exact", action="store_true",
                   help="also estimate the exact explicit limit by power iteration (compiles; a few seconds) "
                        "instead of only the closed-form safe bound")
    c = sub.add_parser("capture", help="what one depth camera would record of a trajectory: a point-cloud "
                                       "fit target (partial, noisy, frames of different sizes); with --tracks, "
                                       "also tracked surface points")
    c.add_argument("trajectory", help="trajectory .h5 from 'jaxplush simulate'")
    c.add_argument("--out", required=True, help="output target (.h5), points padded with NaN rows")
    c.add_argument("--eye", required=True,
                   help="camera position X,Y,Z in m, within %g times the scene's extent (the diagonal of the "
                        "box holding every vertex of every frame) of the scene's centre" % CAMERA_RANGE)
    c.add_argument("--look-at", default=None,
                   help="the point the camera looks at, X,Y,Z in m, not at --eye and within the same range "
                        "(default: the first frame's centre)")
    c.add_argument("--up", default="0,1,0",
                   help="the image's up direction X,Y,Z, not parallel to the viewing direction from --eye to the "
                        "look-at point (default 0,1,0)")
    c.add_argument("--fov", type=float, default=60.0,
                   help="vertical field of view, degrees, in (0, 180) (default 60)")
    c.add_argument("--size", default="64x48",
                   help="image WIDTHxHEIGHT in pixels, one ray each, at most %s pixels in all (default 64x48)"
                        % f"{MAX_PIXELS:,}")
    c.add_argument("--noise", type=float, default=0.0,
                   help="depth noise sigma along each ray, m: from 0 (default) to %sthe scene's extent "
                        "(the diagonal of the box holding every vertex of every frame)" % _times(MAX_NOISE_EXTENTS))
    c.add_argument("--dropout", type=float, default=0.0,
                   help="probability in [0, 1) that a pixel's hit returns nothing (default 0)")
    c.add_argument("--seed", type=int, default=0,
                   help="seed of the noise and dropout, an integer >= 0 (default 0)")
    c.add_argument("--tracks", type=int, default=0,
                   help="also write N tracked surface points (random faces and barycentric coordinates from "
                        "--seed, Gaussian noise --noise per coordinate, each dropped from a frame with probability "
                        "--dropout) as 'tracks' with 'track_face' and 'track_barycentric' (default 0: none); "
                        "with the scan, a mixed target (jaxplush-fit fits both)")
    c.add_argument("--controls", action="store_true",
                   help="also write the scene's driven vertices' paths (its 'driven' lines) as the target's "
                        "'controls', as if measured alongside the object: fit it with the scene without those lines")
    v = sub.add_parser("view", help="interactive 3-D view of a trajectory or a fit in the browser (viser, the "
                                    "optional extra 'viewer'): served on 127.0.0.1, or written as one HTML file")
    v.add_argument("file", help="trajectory .h5 from 'jaxplush simulate', or FIT.h5 from 'jaxplush-fit' (its fitted "
                                "rollout against its target)")
    v.add_argument("--target", default=None,
                   help="overlay this fit target's positions, points or tracks at the frames whose times it has "
                        "(default with a FIT.h5: the fit's target, when found); it must belong to FILE: as many "
                        "vertices (positions), the same objects, faces and object_id where it records them, and "
                        "the same objects at the same rest positions where both files store a scene")
    v.add_argument("--color", choices=("object", "strain"), default="object",
                   help="object: one colour per object (default); strain: edges coloured by edge length / rest "
                        "length (blue compressed, white 1, red stretched)")
    v.add_argument("--max-frames", type=int, default=300,
                   help="most frames shown (default 300); a longer trajectory is subsampled evenly, keeping the "
                        "first and last frame, and the command says how many it shows")
    v.add_argument("--port", type=int, default=0, help="port on 127.0.0.1 (default: a free one)")
    v.add_argument("--html", default=None,
                   help="write the view as one self-contained HTML file (plays offline in any browser) and exit "
                        "instead of serving it")
    return p


def main(argv=None):
    """Run the command in ``argv`` (default ``sys.argv[1:]``) and return its exit status.

    Called as the program (``argv`` None: the ``jaxplush`` script, ``python -m jaxplush``), it
    first freezes the garbage collector's view of everything imported so far (``gc.freeze``):
    jax and the rest live until the process ends, and the collector need not walk them again,
    neither during the run nor at exit (a tenth of a second or more each time)."""
    args = _parser().parse_args(attach_negative_values(sys.argv[1:] if argv is None else argv))
    if argv is None:
        gc.freeze()
    from jaxplush.stepping.compiled import enable_persistent_cache
    enable_persistent_cache()          # a second run of the same scene reuses this one's compiles
    from jaxplush.errors import JaxplushError, SimulationError
    try:
        if args.cmd == "simulate":
            return _simulate(args)
        if args.cmd == "render":
            return _render(args)
        if args.cmd == "capture":
            return _capture(args)
        if args.cmd == "view":
            return _view(args)
        return _info(args)
    except JaxplushError as e:
        print(f"jaxplush {args.cmd}: error: {e}", file=sys.stderr)
        return EXIT_FAILED if isinstance(e, SimulationError) else EXIT_USAGE
    except KeyboardInterrupt:
        print(f"jaxplush {args.cmd}: interrupted; nothing written", file=sys.stderr)
        return 130


def _simulate(args):
    from jaxplush.errors import JaxplushError
    if not 1 <= args.steps <= MAX_STEPS:
        raise JaxplushError(f"--steps must be between 1 and {MAX_STEPS:,} (a step counter is 32-bit), "
                            f"got {args.steps}")
    if not (np.isfinite(args.dt) and args.dt > 0):
        raise JaxplushError(f"--dt must be a positive number, got {args.dt}")
    if args.save_every is not None and args.save_every < 1:
        raise JaxplushError(f"--save-every must be >= 1, got {args.save_every}")
    if args.substeps < 1:
        raise JaxplushError(f"--substeps must be >= 1, got {args.substeps}")
    check_output_path(args.out, (".h5", ".hdf5"))
    if args.x64:
        import jax
        jax.config.update("jax_enable_x64", True)
    import jaxplush
    if args.integrator not in jaxplush.INTEGRATORS:
        raise JaxplushError(f"unknown integrator {args.integrator!r}; available: {', '.join(jaxplush.INTEGRATORS)}")
    scene = jaxplush.load_scene(args.scene)
    frames = args.steps // (args.save_every or max(1, args.steps // 100)) + 2
    size = frames * scene.n_vertices * 3 * (8 if args.x64 else 4)
    if size > MAX_OUTPUT_BYTES:
        raise JaxplushError(f"--steps {args.steps} would write {frames:,} frames of {scene.n_vertices} vertices "
                            f"({size / 2 ** 30:.3g} GiB, more than {MAX_OUTPUT_BYTES / 2 ** 30:.0f} GiB); "
                            "raise --save-every")
    if args.steps > PROBE_ABOVE:
        _warn_if_long(scene, args)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            traj = jaxplush.simulate(scene, args.steps, args.dt, args.save_every, args.integrator,
                                     progress=not args.quiet, substeps=args.substeps)
        finally:  # also when the run fails: the dt warning explains the blow-up
            for w in caught:
                print(f"warning: {w.message}", file=sys.stderr)
    t = time.perf_counter()
    traj.save(args.out)
    vols = ", ".join(f"{n}: {v * 1e6:.6g} cm³ ({v / v0:.3f}× rest)" for n, v, v0 in
                     zip(traj.object_names, traj.volumes[-1], traj.volumes[0]))
    print(f"simulated {args.steps} steps of {args.dt:g} s ({args.steps * args.dt:.4g} s) in {traj.wall_time:.2f} s "
          f"wall ({args.steps / traj.wall_time:,.0f} steps/s incl. compile); wrote {len(traj.times)} frames to "
          f"{args.out} ({time.perf_counter() - t:.2f} s); final volume {vols}")
    return 0


#: Runs of more steps than this are timed on a short probe first, and a run expected to take
#: longer than LONG_RUN seconds is announced before it starts.
PROBE_ABOVE = 200_000
PROBE_STEPS = 500
LONG_RUN = 1800.0


def _warn_if_long(scene, args):
    """Time PROBE_STEPS compiled steps of the scene (thrown away) and print a warning to stderr,
    before the run, when ``--steps`` would take longer than LONG_RUN at that rate."""
    import jax
    import jaxplush
    from jaxplush.model.forces import Terms
    sim = jaxplush.make_simulator(scene, args.dt, args.integrator, terms=Terms.for_scene(scene),
                                  substeps=args.substeps)
    p = sim.params()
    s0 = sim.init_fn(p)
    jax.block_until_ready(sim.rollout(p, s0, 1, PROBE_STEPS))          # compile
    t = time.perf_counter()
    jax.block_until_ready(sim.rollout(p, s0, 1, PROBE_STEPS))
    rate = PROBE_STEPS / max(time.perf_counter() - t, 1e-9)
    eta = args.steps / rate
    if eta > LONG_RUN:
        print(f"warning: --steps {args.steps:,} will take about {_duration(eta)} at the measured {rate:,.0f} steps/s "
              f"({args.steps * args.dt:.4g} s simulated); Ctrl-C stops it and writes nothing", file=sys.stderr,
              flush=True)


def _duration(seconds):
    if seconds >= 86400:
        return f"{seconds / 86400:.1f} days"
    if seconds >= 3600:
        return f"{seconds / 3600:.1f} h"
    return f"{seconds / 60:.0f} min"


def _render(args):
    from jaxplush.io.render import render
    t = time.perf_counter()
    out = render(args.trajectory, args.out, frame=args.frame, fps=args.fps, max_frames=args.max_frames,
                 report=print)
    print(f"wrote {out} ({time.perf_counter() - t:.1f} s)")
    return 0


def _view(args):
    """Serve the view until Ctrl-C (exit 130), or with --html write it and exit."""
    from jaxplush.errors import JaxplushError
    from jaxplush.io.view import TargetMismatch, require_viser, view
    if args.max_frames < 2:
        raise JaxplushError(f"--max-frames must be >= 2, got {args.max_frames}")
    if not 0 <= args.port <= 65535:
        raise JaxplushError(f"--port must be 0 (a free one) to 65535, got {args.port}")
    require_viser()                                 # the install hint before any reading
    t = time.perf_counter()
    try:
        v = view(args.file, target=args.target, color=args.color, max_frames=args.max_frames, html=args.html,
                 port=args.port, report=print)
    except TargetMismatch as e:                     # only a given --target raises it
        raise JaxplushError(f"--target {e.target}: {e.reason}") from None
    if args.html:
        print(f"wrote {args.html} ({len(v.html) / 2 ** 20:.1f} MiB, {time.perf_counter() - t:.1f} s): open it in "
              "any browser, offline")
        return 0
    print(f"viewing {args.file} at {v.url} (Ctrl-C stops)", flush=True)
    try:
        v.wait()
    except KeyboardInterrupt:
        print("jaxplush view: stopped", file=sys.stderr)
        return 130
    return 0


def _info(args):
    import jaxplush
    from jaxplush.errors import JaxplushError
    from jaxplush.stepping import stability
    scene = jaxplush.load_scene(args.scene)
    if args.dt is not None and not (np.isfinite(args.dt) and args.dt > 0):
        raise JaxplushError(f"--dt must be a positive number, got {args.dt}")
    _check_predictability_args(args)
    sim = jaxplush.make_simulator(scene, args.dt or 1e-4)
    p = sim.params()
    topo = sim.topology
    vols = scene.volumes()
    press = scene.rest_pressure()
    print(f"scene {scene.path}: {scene.n_objects} object(s), {scene.n_vertices} vertices, "
          f"{len(topo.edges)} springs, {len(scene.faces)} faces")
    g = scene.gravity
    print(f"  gravity ({g[0]:g}, {g[1]:g}, {g[2]:g}) m/s², floor "
          f"{'none' if scene.floor is None else f'y = {scene.floor:g} m'}, temperature {scene.temperature:g} K")
    print(f"  compiled terms: {', '.join(sim.terms.names())}")
    from jaxplush.stepping import compiled
    print(f"  program bucket: {compiled.bucket(scene, sim.terms).text()}; padding: ring slots to the largest "
          f"valence, vertex counts exact (scenes of one bucket, with the same terms and step options, share "
          f"their compiled programs)")
    for i, o in enumerate(scene.objects):
        e = int((topo.edge_object == i).sum())
        print(f"  object {i} {o.name!r}: {o.n_vertices} vertices, {e} edges, {o.n_faces} faces, "
              f"{len(o.fixed)} fixed")
        print(f"    k_structural {_k_text(topo, p.k_structural, i)}, damping {p.damping[i]:g}, "
              f"dashpot {p.dashpot[i]:g} N s/m, "
              f"drag {p.drag[i]:g} 1/s, total_weight {p.total_weight[i]:g} kg, "
              f"nmol {p.nmol[i]:g}{'' if o.has_gas else ' (no gas)'}")
        print(f"    volume {vols[i] * 1e6:.6g} cm³, rest pressure {press[i]:.6g} Pa, "
              f"edge length {topo.rest_length[topo.edge_object == i].min():.4g}–"
              f"{topo.rest_length[topo.edge_object == i].max():.4g} m")
    b = stability.bound(sim, p)
    print(f"  stability (Verlet): closed-form bounds omega_max <= {b.omega_max:.5g} rad/s, damping rate "
          f"<= {b.gamma_max:.4g} 1/s; every dt <= {b.dt_max:.4g} s is stable")
    limit = b.dt_max
    if args.exact:
        est = stability.estimate(sim, p)
        limit = est.dt_max
        print(f"  exact (power iteration, at rest and inflated): omega_max {est.omega_max:.5g} rad/s, damping rate "
              f"{est.gamma_max:.4g} 1/s; largest stable dt {est.dt_max:.4g} s (use <= {0.9 * est.dt_max:.4g} s)")
    else:
        print("  (the exact limit is larger, typically 1.3-1.5x the bound: --exact estimates it)")
    if args.dt:
        if args.dt <= limit:
            verdict = "within the " + ("estimated limit" if args.exact else "safe bound")
        else:
            verdict = "ABOVE the estimated limit" if args.exact else "above the safe bound (use --exact to decide)"
        print(f"  dt {args.dt:g} s is {verdict}; real time needs >= {1 / args.dt:,.0f} steps/s")
    if args.steps is not None:
        _info_predictability(scene, args)
    return 0


def _k_text(topo, k, i):
    """Object ``i``'s spring stiffness for ``jaxplush info``: its value, or a field's mean and range."""
    from jaxplush.model.layout import is_field, object_stiffness
    k = np.asarray(k, np.float64)
    if not is_field(topo, k):
        return f"{k[i]:g} N/m"
    a, b = topo.edge_slices[i]
    return f"{object_stiffness(topo, k)[i]:g} N/m (mean of a per-edge field, {k[a:b].min():g}–{k[a:b].max():g})"


def _check_predictability_args(args):
    """--steps and --save-every of ``info``: in range, and each with what it needs."""
    from jaxplush.errors import JaxplushError
    if args.steps is not None:
        if args.dt is None:
            raise JaxplushError("--steps needs --dt (the predictability is measured over steps of dt)")
        if not 1 <= args.steps <= MAX_STEPS:
            raise JaxplushError(f"--steps must be between 1 and {MAX_STEPS:,}, got {args.steps}")
    if args.save_every is not None:
        if args.steps is None:
            raise JaxplushError("--save-every needs --steps")
        if args.save_every < 1:
            raise JaxplushError(f"--save-every must be >= 1, got {args.save_every}")


def _info_predictability(scene, args):
    """Print the predictable horizon and the reproducibility floor of ``args.steps`` steps of dt."""
    import jaxplush
    from jaxplush.stepping.predictability import MOTION_FRACTION
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")         # a volume clamp or a grown capacity: simulate reports them
        pred = jaxplush.predictability(scene, args.steps, args.dt, args.save_every)
    frac = f"{100 * MOTION_FRACTION:g}% of the motion"
    if pred.predictable:
        horizon = (f"beyond the run's {pred.duration:.4g} s (the drift of two runs that differ by rounding stays "
                   f"within {frac})")
    else:
        horizon = (f"{pred.horizon_time:.4g} s (drift of two runs that differ by rounding exceeds {frac} at "
                   f"{pred.horizon_time:.4g} s)")
    print(f"  predictable horizon: {horizon}; reproducibility floor {1e3 * pred.floor:.3g} mm over {args.steps} "
          f"steps ({pred.wall_time:.1f} s to measure)")


def _vector(text, option):
    """Three comma-separated numbers, or a JaxplushError naming ``option``."""
    from jaxplush.errors import JaxplushError
    try:
        v = [float(t) for t in text.split(",")]
    except ValueError:
        v = []
    if len(v) != 3 or not all(np.isfinite(v)):
        raise JaxplushError(f"{option} must be three finite numbers X,Y,Z, got {text!r}")
    return tuple(v)


def _capture(args):
    from jaxplush.errors import JaxplushError
    from jaxplush.fitting.targets import Target
    from jaxplush.io.capture import Camera, NonFiniteCapture, depth_capture, track_capture
    from jaxplush.io.trajectory import load_trajectory
    check_output_path(args.out, (".h5", ".hdf5"))
    _check_capture_options(args)
    eye, up = _vector(args.eye, "--eye"), _vector(args.up, "--up")
    if not any(up):
        raise JaxplushError(f"--up must be a non-zero direction X,Y,Z, got {args.up!r}")
    look = None if args.look_at is None else _vector(args.look_at, "--look-at")
    size = args.size.lower().split("x")
    if len(size) != 2 or not all(t.isdigit() and int(t) >= 1 for t in size):
        raise JaxplushError(f"--size must be WIDTHxHEIGHT in whole pixels, e.g. 64x48, got {args.size!r}")
    width, height = int(size[0]), int(size[1])
    if width * height > MAX_PIXELS:
        raise JaxplushError(f"--size {args.size} is {width * height:,} pixels, more than {MAX_PIXELS:,} "
                            "(one ray each)")
    traj = load_trajectory(args.trajectory)
    meta, scene = _capture_metadata(args.trajectory, traj)      # checked before the casting
    controls = None
    if args.controls:
        from jaxplush.fitting.targets import controls_of_scene
        if scene is None or not scene.driven:
            raise JaxplushError(f"--controls: the scene of {args.trajectory} drives no vertices (no 'driven' line)")
        try:
            controls = controls_of_scene(scene)
        except ValueError as e:
            raise JaxplushError(f"--controls: {e}") from None
    pos = np.asarray(traj["positions"], np.float64)
    if args.tracks and len(pos) * args.tracks * 24 > MAX_OUTPUT_BYTES:
        raise JaxplushError(f"--tracks {args.tracks:,} would write {len(pos)} frames of {args.tracks:,} points "
                            f"({len(pos) * args.tracks * 24 / 2 ** 30:.3g} GiB, more than "
                            f"{MAX_OUTPUT_BYTES / 2 ** 30:.0f} GiB)")
    look = _check_camera(args, pos, eye, look, up)
    try:
        camera = Camera(eye=eye, target=look, up=up, fov_deg=args.fov, width=width, height=height)
    except ValueError as e:                         # _check_camera has said why already; a safety net
        raise JaxplushError(f"--eye, --look-at, --up, --fov, --size: {e}") from None
    try:
        cap = depth_capture(pos, traj["faces"], camera, noise=args.noise, dropout=args.dropout, seed=args.seed)
        tracks = None if not args.tracks else track_capture(pos, traj["faces"], args.tracks, noise=args.noise,
                                                            dropout=args.dropout, seed=args.seed)
    except NonFiniteCapture as e:
        raise JaxplushError(f"--noise {args.noise:g}: {e}; nothing written") from None
    except ValueError as e:                         # the options are checked: what is left is the file's
        raise JaxplushError(f"{args.trajectory}: {e}") from None
    if cap.counts.max() == 0:
        raise JaxplushError(f"the camera at {args.eye} looking at {','.join(f'{a:g}' for a in look)} sees no "
                            f"object in any of the {len(pos)} frames: check --eye, --look-at and --fov")
    _check_capture_finite(args, cap, tracks)        # never write an inf or NaN point (depth_capture checks too)
    extra = {}
    if tracks is not None:    # the faces they index travel with them
        extra = dict(tracks=tracks.tracks, track_face=tracks.face, track_barycentric=tracks.barycentric)
        if scene is None:
            extra["faces"] = np.asarray(traj["faces"], np.int32)
    Target(positions=None, points=cap.points, path=args.out, noise=float(args.noise) if args.noise > 0 else None,
           controls=controls, **meta).save(args.out, scene, extra=extra)
    seen = "" if tracks is None else (
        f"; {args.tracks} tracked points, {np.isfinite(tracks.tracks).all(axis=2).sum(axis=1).mean():.1f} "
        "seen a frame")
    if controls is not None:
        seen += f"; the paths of {len(controls.vertices)} driven vertices as 'controls'"
    print(f"captured {len(pos)} frames of {args.trajectory} with a {camera.width}x{camera.height} depth camera: "
          f"{cap.counts.min()}-{cap.counts.max()} points a frame (mean {cap.counts.mean():.0f}), depth noise "
          f"{args.noise:g} m, dropout {args.dropout:g}{seen}; wrote {args.out}")
    return 0


def _check_capture_options(args):
    """The options of ``capture`` that need no trajectory: in range, each error naming its option."""
    from jaxplush.errors import JaxplushError
    if args.tracks < 0:
        raise JaxplushError(f"--tracks must be a number of points >= 0, got {args.tracks}")
    if args.seed < 0:
        raise JaxplushError(f"--seed must be a non-negative integer, got {args.seed}")
    if not 0 < args.fov < 180:
        raise JaxplushError(f"--fov must be in (0, 180) degrees, got {args.fov:g}")
    if not 0 <= args.dropout < 1:
        raise JaxplushError(f"--dropout must lie in [0, 1) (a probability), got {args.dropout:g}")
    if not (np.isfinite(args.noise) and args.noise >= 0):
        raise JaxplushError(f"--noise must be a finite number >= 0 (m), got {args.noise:g}")


def _point_text(p):
    return ",".join(f"{a:g}" for a in p)


def _check_camera(args, pos, eye, look, up):
    """--noise, --eye, --look-at and --up against the trajectory's positions ``pos`` (T, V, 3); returns
    the look-at point. The default look-at point is the first frame's centre; every rule is the same
    with it as with a given --look-at."""
    from jaxplush.errors import JaxplushError
    from jaxplush.io import capture
    try:
        centre, size = capture.extent(pos)
    except ValueError as e:
        raise JaxplushError(f"{args.trajectory}: 'positions' {e}") from None
    size = max(size, 1e-9)                          # every vertex at one point: still a scale to measure by
    box = "the diagonal of the box holding every vertex of every frame"
    if args.noise > MAX_NOISE_EXTENTS * size:
        raise JaxplushError(f"--noise must be at most {_times(MAX_NOISE_EXTENTS)}the scene's extent "
                            f"({MAX_NOISE_EXTENTS * size:.3g} m; the extent is {box}), got {args.noise:g}")
    given = look is not None
    if not given:
        look = tuple(float(a) for a in pos[0].mean(axis=0))
    look_name = (f"--look-at {args.look_at}" if given
                 else f"the default look-at point {_point_text(look)} (the first frame's centre)")
    points = [("--eye", args.eye, eye)] + ([("--look-at", args.look_at, look)] if given else [])
    for option, text, p in points:
        with np.errstate(over="ignore", invalid="ignore"):
            off = capture.norm(np.subtract(p, centre))
        if not off <= CAMERA_RANGE * size:
            far = (f"{off:.3g} m from its centre {_point_text(centre)}" if np.isfinite(off)
                   else f"the distance from its centre {_point_text(centre)} overflows")
            raise JaxplushError(f"{option} {text} is too far from the scene: {far}, more than {CAMERA_RANGE:g} times "
                                f"its extent of {size:.3g} m ({box})")
    view = np.subtract(look, eye)
    if capture.norm(view) == 0:
        raise JaxplushError(f"--eye {args.eye} is at the look-at point ({look_name}): the camera has no viewing "
                            "direction; " + ("move one of them" if given else "give --look-at"))
    if capture.parallel(view, up):
        raise JaxplushError(f"--up {args.up} must not be parallel to the viewing direction (from --eye {args.eye} to "
                            f"{look_name}): give another --up")
    return look


def _check_capture_finite(args, cap, tracks):
    """No real point of the capture, nor any seen track, has a non-finite coordinate."""
    from jaxplush.errors import JaxplushError
    real = np.arange(cap.points.shape[1])[None, :] < cap.counts[:, None]
    bad = real & ~np.isfinite(cap.points).all(axis=2)
    what = "'points'"
    if not bad.any() and tracks is not None:
        t = tracks.tracks
        bad = ~np.isfinite(t).all(axis=2) & ~np.isnan(t).all(axis=2)
        what = "'tracks'"
    if bad.any():
        frame = int(np.argwhere(bad)[0][0])
        raise JaxplushError(f"--noise {args.noise:g}: the capture's {what} would hold non-finite coordinates "
                            f"(first in frame {frame}); nothing written")


def _capture_metadata(path, traj):
    """(Target fields steps, times, dt, params; the trajectory's Scene or None) of a trajectory."""
    import jaxplush
    from jaxplush.errors import JaxplushError
    from jaxplush.fitting.targets import _grid_steps
    from jaxplush.types import PARAM_NAMES
    attrs = traj["attrs"]
    if "dt" not in attrs or "times" not in traj:
        raise JaxplushError(f"{path}: needs 'times' and the attribute 'dt' (a 'jaxplush simulate' output)")
    times = np.asarray(traj["times"], np.float64)
    dt = float(attrs["dt"])
    steps = _grid_steps(path, times, dt, traj["times"].dtype)
    scene = None
    if "scene" in attrs:
        scene = jaxplush.parse_scene(str(attrs["scene"]), str(attrs.get("scene_path", path)))
    params = {n: np.asarray(attrs[n], np.float64) for n in PARAM_NAMES if n in attrs}
    return dict(steps=steps, times=times, dt=dt, params=params), scene


if __name__ == "__main__":
    sys.exit(main())

