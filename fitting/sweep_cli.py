"""Command line ``jaxplush-fit sweep``: a batched parameter sweep, its summary and loss landscape.

    jaxplush-fit sweep SCENE.obj --grid k_structural=100:1000:16 --grid nmol=0.001:0.01:8 [--log]
        [--target TARGET.h5] --steps N [--dt DT] [--save-every K] [--batch B] --out SWEEP.h5
        [--plot PNG] [--x64] [--quiet] [--checkpoint DIR] [--distributed [--coordinator HOST:PORT
        --num-processes P --process-id I]]

A grid spec is ``NAME=a:b:n`` (n values from a to b, linearly spaced; geometrically with
``--log``) or ``NAME=v1,v2,...``; NAME is a parameter (``k`` = ``k_structural``), optionally
``NAME@OBJECT``. Every input is validated before anything runs; a bad one prints one message
(no traceback), writes nothing and exits 2. The sweep file is written atomically (schema in
:mod:`jaxplush.fitting.sweep`), and a summary table is printed at the end. Points that blow up are
recorded in the file (failure code and step) and listed; they do not stop the sweep.

Every finished batch is kept in a checkpoint directory (default ``SWEEP.h5.parts``, removed once
SWEEP.h5 is written), each batch written atomically: the same command run again after a kill,
even SIGKILL, resumes from the finished batches and writes the file an uninterrupted run would.

``--distributed`` shares the batches among processes through ``jax.distributed`` (on a SLURM or
other cluster JAX finds the processes itself; elsewhere give ``--coordinator``, ``--num-processes``
and ``--process-id``): process i runs every P-th batch into the checkpoint directory (on a
filesystem every process sees), and process 0 writes SWEEP.h5, the file one process would write.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
import warnings

import numpy as np

from jaxplush.cliargs import attach_negative_values
from jaxplush.io.trajectory import check_output_path

EXIT_USAGE = 2
EXIT_INTERRUPTED = 130


def _parser():
    p = argparse.ArgumentParser(
        prog="jaxplush-fit sweep",
        description="Simulate a scene over a grid of parameter values in compiled batches; store final shapes, "
                    "summaries and (with --target) the loss of every point, and plot the loss landscape.")
    p.add_argument("scene", help="extended-OBJ scene; parameters not swept keep its values")
    p.add_argument("--grid", action="append", default=[], metavar="NAME=SPEC",
                   help="a swept parameter: NAME=a:b:n (n values from a to b) or NAME=v1,v2,...; NAME is "
                        "k_structural (k), damping, dashpot, drag, nmol or total_weight, optionally NAME@OBJECT. "
                        "Repeat for a cartesian product.")
    p.add_argument("--log", action="store_true", help="space a:b:n specs geometrically")
    p.add_argument("--target", default=None, help="target HDF5 ('positions', 'points' or 'tracks', and 'times') to compute "
                                                   "the loss of every point against")
    p.add_argument("--steps", type=int, required=True, help="time steps per point")
    p.add_argument("--dt", type=float, default=None, help="time step, s (default: the target's)")
    p.add_argument("--save-every", type=int, default=None, help="also store every point's positions every K steps")
    p.add_argument("--batch", type=int, default=None,
                   help="points simulated together (default 64 on a CPU, 1024 on a GPU)")
    p.add_argument("--out", required=True, help="output SWEEP.h5")
    p.add_argument("--plot", default=None, help="also plot the loss landscape (or the final volume without "
                                                "--target) to this image (.png, .pdf, .svg)")
    p.add_argument("--x64", action="store_true", help="run in float64")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("--checkpoint", default=None, metavar="DIR",
                   help="keep finished batches here, to resume after a kill (default OUT.parts; removed "
                        "once OUT is written)")
    p.add_argument("--distributed", action="store_true",
                   help="share the sweep among processes with jax.distributed (cluster auto-detected, or "
                        "--coordinator/--num-processes/--process-id); process 0 writes OUT")
    p.add_argument("--coordinator", default=None, metavar="HOST:PORT", help="with --distributed: process 0's address")
    p.add_argument("--num-processes", type=int, default=None, help="with --distributed: number of processes")
    p.add_argument("--process-id", type=int, default=None, help="with --distributed: this process's index")
    return p


def parse_grid_spec(spec, log=False):
    """``NAME=a:b:n`` or ``NAME=v1,v2,...`` -> (NAME, values (n,) float64). ValueError if bad."""
    name, eq, rhs = spec.partition("=")
    name, rhs = name.strip(), rhs.strip()
    if not eq or not name or not rhs:
        raise ValueError(f"--grid {spec!r}: expected NAME=a:b:n or NAME=v1,v2,...")
    if ":" in rhs:
        parts = rhs.split(":")
        if len(parts) != 3:
            raise ValueError(f"--grid {spec!r}: a range is a:b:n (start, stop, number of values)")
        try:
            a, b = float(parts[0]), float(parts[1])
        except ValueError:
            raise ValueError(f"--grid {spec!r}: start and stop must be numbers") from None
        try:
            n = int(parts[2])
        except ValueError:
            raise ValueError(f"--grid {spec!r}: the number of values must be an integer, got {parts[2]!r}") from None
        if n < 1:
            raise ValueError(f"--grid {spec!r}: the number of values must be >= 1, got {n}")
        if not (np.isfinite(a) and np.isfinite(b)):
            raise ValueError(f"--grid {spec!r}: start and stop must be finite")
        if n == 1 and a != b:
            raise ValueError(f"--grid {spec!r}: one value cannot run from {a:g} to {b:g}; give n >= 2, "
                             f"or a single value as NAME=v")
        if n > 1 and a == b:
            raise ValueError(f"--grid {spec!r}: start and stop are equal, so the {n} values would all be {a:g}")
        if log:
            if a <= 0 or b <= 0:
                raise ValueError(f"--grid {spec!r}: --log needs start and stop > 0")
            return name, np.geomspace(a, b, n)
        return name, np.linspace(a, b, n)
    try:
        values = np.array([float(v) for v in rhs.split(",")])
    except ValueError:
        raise ValueError(f"--grid {spec!r}: values must be numbers separated by commas") from None
    return name, values


def main(argv=None):
    argv = sys.argv[1:] if argv is None else list(argv)
    try:
        args = _parser().parse_args(attach_negative_values(argv))
    except SystemExit as e:  # argparse has printed its message
        return int(e.code) if isinstance(e.code, int) else EXIT_USAGE
    from jaxplush.errors import JaxplushError
    if args.distributed:             # before anything starts a JAX backend
        try:
            _initialize_distributed(args)
        except JaxplushError as e:
            print(f"jaxplush-fit sweep: error: {e}", file=sys.stderr)
            return EXIT_USAGE
    from jaxplush.stepping.compiled import enable_persistent_cache
    enable_persistent_cache()          # a second run of the same scene reuses this one's compiles
    try:
        return _run(args)
    except (JaxplushError, NotImplementedError) as e:
        print(f"jaxplush-fit sweep: error: {e}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        print("jaxplush-fit sweep: interrupted; nothing written", file=sys.stderr)
        return EXIT_INTERRUPTED


def _initialize_distributed(args):
    """``jax.distributed.initialize`` from the explicit options, else from the cluster's environment."""
    from jaxplush.errors import JaxplushError
    given = (args.coordinator, args.num_processes, args.process_id)
    if any(v is not None for v in given) and not all(v is not None for v in given):
        raise JaxplushError("--coordinator, --num-processes and --process-id go together (or give none of "
                            "them on a cluster JAX detects)")
    if args.num_processes is not None and not 0 <= args.process_id < args.num_processes:
        raise JaxplushError(f"--process-id must be in 0..{args.num_processes - 1}, got {args.process_id}")
    import jax
    kw = {} if args.coordinator is None else dict(coordinator_address=args.coordinator,
                                                 num_processes=args.num_processes, process_id=args.process_id)
    try:
        jax.distributed.initialize(**kw)
    except (RuntimeError, ValueError) as e:
        raise JaxplushError(f"--distributed: jax.distributed.initialize failed: {e}") from None


def _run(args):
    from jaxplush.errors import JaxplushError
    # --- everything checked before anything is traced or written
    if not args.grid:
        raise JaxplushError("give at least one --grid NAME=SPEC")
    grid = {}
    for spec in args.grid:
        try:
            name, values = parse_grid_spec(spec, args.log)
        except ValueError as e:
            raise JaxplushError(str(e)) from None
        if name in grid:
            raise JaxplushError(f"--grid {name} given twice")
        grid[name] = values
    if args.plot is not None and len(grid) > 2:
        raise JaxplushError(f"--plot draws one or two swept parameters (a curve or a heat map), this sweep has "
                            f"{len(grid)} ({', '.join(grid)}); drop --plot and plot a slice of {args.out} yourself")
    if args.steps < 1:
        raise JaxplushError(f"--steps must be >= 1, got {args.steps}")
    if args.dt is not None and not (np.isfinite(args.dt) and args.dt > 0):
        raise JaxplushError(f"--dt must be a positive number, got {args.dt}")
    if args.dt is None and args.target is None:
        raise JaxplushError("--dt is required without --target")
    if args.save_every is not None and args.save_every < 1:
        raise JaxplushError(f"--save-every must be >= 1, got {args.save_every}")
    if args.batch is not None and args.batch < 1:
        raise JaxplushError(f"--batch must be >= 1, got {args.batch}")
    check_output_path(args.out, (".h5", ".hdf5"), "--out")
    checkpoint = args.checkpoint if args.checkpoint is not None else args.out + ".parts"
    for inp in (args.scene, args.target, args.out):
        if inp is not None and os.path.abspath(checkpoint) == os.path.abspath(inp):
            raise JaxplushError(f"--checkpoint {checkpoint}: must not be an input or the output")
    if args.plot is not None:
        check_output_path(args.plot, (".png", ".pdf", ".svg", ".jpg", ".jpeg"), "--plot")
    for out in (args.out, args.plot):
        for inp in (args.scene, args.target):
            if out is not None and inp is not None and os.path.abspath(out) == os.path.abspath(inp):
                raise JaxplushError(f"{out}: an output must not overwrite an input")
    if args.x64:
        import jax
        jax.config.update("jax_enable_x64", True)
    import jaxplush
    from jaxplush.fitting import sweep as _sweep

    scene = jaxplush.load_scene(args.scene)
    try:                                 # names, objects and values, before the target is read
        _sweep._axes(scene, grid, "grid")
        _sweep.batched.check_terms(_sweep.batched.terms_for(scene))
    except (_sweep.SweepError, NotImplementedError) as e:
        raise JaxplushError(f"{args.scene}: {e}") from None
    target, dt = None, args.dt
    if args.target is not None:
        from jaxplush.fitting.targets import load_target
        target = load_target(args.target, scene, args.dt)
        dt = float(target.dt)
        if int(np.max(target.steps)) > args.steps:
            raise JaxplushError(f"{args.target}: the target reaches step {int(np.max(target.steps))} "
                                f"(t = {float(np.max(target.times)):g} s) but --steps is {args.steps}")
    if args.plot is not None:
        import matplotlib
        matplotlib.use("Agg")

    # --- run
    t0 = time.perf_counter()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        res = _sweep.sweep(scene, grid, steps=args.steps, dt=dt, save_every=args.save_every, target=target,
                           progress=not args.quiet, batch=args.batch, checkpoint=checkpoint)
    import jax
    lead = jax.process_index() == 0              # several processes: process 0 writes and reports
    if lead:
        for w in caught:
            print(f"warning: {w.message}", file=sys.stderr)
        res.save(args.out)
        if args.plot is not None:
            res.plot(args.plot)
    _sweep.remove_checkpoint(checkpoint)
    if not lead:
        return 0
    wall = time.perf_counter() - t0
    print(f"swept {res.n_points} points x {res.steps} steps of {res.dt:g} s in {wall:.2f} s wall "
          f"({res.n_points * res.steps / wall:,.0f} point-steps/s incl. compile); wrote {args.out}"
          + (f" and {args.plot}" if args.plot else ""))
    print(res.table())
    return 0


if __name__ == "__main__":
    sys.exit(main())
