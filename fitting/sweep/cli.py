"""Command line ``jaxplush-fit sweep``: a batched parameter sweep, its summary and loss landscape.

    jaxplush-fit sweep SCENE.obj --grid k_structural=100:1000:16 --grid nmol=0.001:0.01:8 [--log]
        [--target TARGET.h5] --steps N [--dt DT] [--save-every K] [--batch B] --out SWEEP.h5
        [--plot PNG] [--x64] [--quiet] [--checkpoint DIR] [--distributed [--coordinator HOST:PORT
        --num-processes P --process-id I] [--connect-timeout SECONDS]]

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
Joining is bounded by ``--connect-timeout`` (default 60 s): a process other than 0 first waits
for the coordinator's port to accept a connection, then every process waits for the others to
join; past the timeout the command says so and exits 2 (JAX itself would abort the process with
a C++ stack dump after 300 s).
"""

from __future__ import annotations

import argparse
import errno
import math
import os
import re
import socket
import sys
import threading
import time
import warnings

import numpy as np

from jaxplush.cliargs import attach_negative_values
from jaxplush.io.trajectory import check_output_path

EXIT_USAGE = 2
EXIT_INTERRUPTED = 130
#: Seconds ``--distributed`` waits for the coordinator and the other processes (``--connect-timeout``).
DEFAULT_CONNECT_TIMEOUT = 60.0
#: The longest ``--connect-timeout``: one day.
MAX_CONNECT_TIMEOUT = 86400.0
#: Extra seconds JAX's own registration deadline gets beyond ours, so that ours always comes first
#: (JAX's ends the process with a C++ stack dump).
_JAX_DEADLINE_MARGIN = 30


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
    p.add_argument("--connect-timeout", type=float, default=None, metavar="SECONDS",
                   help=f"with --distributed: how long to wait for the coordinator to answer and for every "
                        f"process to join (default {DEFAULT_CONNECT_TIMEOUT:g} s); past it the command stops "
                        f"with a message and exit status 2")
    return p


def parse_grid_spec(spec, log=False):
    """``NAME=a:b:n`` or ``NAME=v1,v2,...`` -> (NAME, values (n,) float64). ValueError if bad."""
    name, _, make = _grid_spec(spec, log)
    return name, make()


def _grid_spec(spec, log=False):
    """A grid spec checked: (NAME, n, make), n its number of values and ``make()`` the values; n is
    known before anything is allocated (a:b:n with a huge n must not be built to be refused)."""
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
            return name, n, lambda: np.geomspace(a, b, n)
        return name, n, lambda: np.linspace(a, b, n)
    try:
        values = np.array([float(v) for v in rhs.split(",")])
    except ValueError:
        raise ValueError(f"--grid {spec!r}: values must be numbers separated by commas") from None
    return name, len(values), lambda: values


def main(argv=None):
    argv = sys.argv[1:] if argv is None else list(argv)
    try:
        args = _parser().parse_args(attach_negative_values(argv))
    except SystemExit as e:  # argparse has printed its message
        return int(e.code) if isinstance(e.code, int) else EXIT_USAGE
    from jaxplush.errors import JaxplushError
    try:
        checked = _check(args)          # every option and input, before JAX starts or anything is written
        if args.distributed:            # before anything starts a JAX backend
            _initialize_distributed(args, checked)
        from jaxplush.stepping.compiled import enable_persistent_cache
        enable_persistent_cache()       # a second run of the same scene reuses this one's compiles
        return _run(args, checked)
    except (JaxplushError, NotImplementedError) as e:
        print(f"jaxplush-fit sweep: error: {e}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        print("jaxplush-fit sweep: interrupted; nothing written", file=sys.stderr)
        return EXIT_INTERRUPTED


# --------------------------------------------------------------------------- checks (no JAX, nothing written)

def _why(e):
    """An OSError's reason in a message's words ("permission denied", "read-only file system")."""
    text = e.strerror or str(e)
    return text[:1].lower() + text[1:]


def _coordinator_address(text):
    """``--coordinator HOST:PORT`` -> (host, port); ``[ADDR]:PORT`` for an IPv6 address."""
    from jaxplush.errors import JaxplushError
    usage = (f"--coordinator: must be HOST:PORT (process 0's host name or address and a port in 1..65535; "
             f"[ADDR]:PORT for IPv6), got {text!r}")
    host, sep, port = text.strip().rpartition(":")
    if not sep or not host or not port or any(c.isspace() for c in host):
        raise JaxplushError(usage)
    if host.startswith("[") or host.endswith("]"):
        if not (host.startswith("[") and host.endswith("]") and len(host) > 2):
            raise JaxplushError(usage)
        host = host[1:-1]
    elif ":" in host:
        raise JaxplushError(f"--coordinator: an IPv6 address goes in brackets, [ADDR]:PORT, got {text!r}")
    if not re.fullmatch(r"[0-9]+", port):
        raise JaxplushError(f"--coordinator: the port must be a number in 1..65535, got {port!r} in {text!r}")
    if not 1 <= int(port) <= 65535:
        raise JaxplushError(f"--coordinator: port {int(port)} is out of range 1..65535 in {text!r}")
    return host, int(port)


def _check_distributed(args):
    """The ``--distributed`` options: (host, port) or None, and the connect timeout in seconds."""
    from jaxplush.errors import JaxplushError
    options = (("--coordinator", args.coordinator), ("--num-processes", args.num_processes),
               ("--process-id", args.process_id), ("--connect-timeout", args.connect_timeout))
    if not args.distributed:
        for name, value in options:
            if value is not None:
                raise JaxplushError(f"{name}: only with --distributed")
        return None, None
    given = (args.coordinator, args.num_processes, args.process_id)
    if any(v is not None for v in given) and not all(v is not None for v in given):
        raise JaxplushError("--coordinator, --num-processes and --process-id go together (or give none of "
                            "them on a cluster JAX detects)")
    address = None
    if args.coordinator is not None:
        address = _coordinator_address(args.coordinator)
        if args.num_processes < 1:
            raise JaxplushError(f"--num-processes: must be >= 1, got {args.num_processes}")
        if not 0 <= args.process_id < args.num_processes:
            raise JaxplushError(f"--process-id: must be in 0..{args.num_processes - 1} (--num-processes "
                                f"{args.num_processes}), got {args.process_id}")
    timeout = DEFAULT_CONNECT_TIMEOUT if args.connect_timeout is None else args.connect_timeout
    if not (math.isfinite(timeout) and 0 < timeout <= MAX_CONNECT_TIMEOUT):
        raise JaxplushError(f"--connect-timeout: must be a number of seconds in (0, {MAX_CONNECT_TIMEOUT:g}], "
                            f"got {timeout:g}")
    return address, timeout


def _check_checkpoint(path):
    """``--checkpoint DIR``: an existing directory this process may write in, or one it can create
    (probed by making its first missing level and removing it again: nothing is left behind)."""
    from jaxplush.errors import JaxplushError
    where = f"--checkpoint {path}"
    full = os.path.abspath(path)
    if os.path.lexists(full):
        if not os.path.exists(full):
            raise JaxplushError(f"{where}: is a symbolic link to {os.readlink(full)}, which does not exist")
        if not os.path.isdir(full):
            raise JaxplushError(f"{where}: {path} is a file, not a directory")
        if not os.access(full, os.W_OK | os.X_OK):
            raise JaxplushError(f"{where}: cannot write in this directory: permission denied")
        return
    missing, parent = full, os.path.dirname(full)
    while not os.path.lexists(parent):
        missing, parent = parent, os.path.dirname(parent)
    shown = (lambda p: p) if os.path.isabs(path) else os.path.relpath      # in the user's terms
    if not os.path.exists(parent):
        raise JaxplushError(f"{where}: {shown(parent)} is a symbolic link to {os.readlink(parent)}, "
                            "which does not exist")
    if not os.path.isdir(parent):
        raise JaxplushError(f"{where}: {shown(parent)} is a file, not a directory")
    try:
        os.mkdir(missing)
    except FileExistsError:              # made meanwhile (another process of a distributed sweep)
        return
    except OSError as e:
        why = (f"{shown(parent)} does not take new directories" if e.errno == errno.ENOENT
               else f"cannot create directory {shown(missing)}: {_why(e)}")
        raise JaxplushError(f"{where}: {why}") from None
    try:
        os.rmdir(missing)
    except OSError:
        pass


def _check(args):
    """Every option and input, before anything is traced, written or connected: the grid (its size
    against memory before its values are made), the scene and the paths. Returns what ``_run`` needs."""
    from jaxplush.errors import JaxplushError
    address, timeout = _check_distributed(args)
    if not args.grid:
        raise JaxplushError("give at least one --grid NAME=SPEC")
    specs = []
    for spec in args.grid:
        try:
            name, n, make = _grid_spec(spec, args.log)
        except ValueError as e:
            raise JaxplushError(str(e)) from None
        if name in (s[0] for s in specs):
            raise JaxplushError(f"--grid {name} given twice")
        specs.append((name, n, make))
    if args.plot is not None and len(specs) > 2:
        raise JaxplushError(f"--plot draws one or two swept parameters (a curve or a heat map), this sweep has "
                            f"{len(specs)} ({', '.join(s[0] for s in specs)}); drop --plot and plot a slice of "
                            f"{args.out} yourself")
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
    _check_checkpoint(checkpoint)
    import jaxplush
    from jaxplush.fitting import sweep as _sweep

    scene = jaxplush.load_scene(args.scene)           # numpy only: no JAX backend starts here
    n_frames = 0 if args.save_every is None else args.steps // args.save_every + 2
    try:                                 # the points' memory, before the grid's values are made
        _sweep.check_sweep_size(scene, math.prod(s[1] for s in specs), len(specs), n_frames,
                                8 if args.x64 else 4)
    except _sweep.SweepError as e:
        shape = " x ".join(f"{s[1]:,}" for s in specs)
        raise JaxplushError(f"--grid: {shape} = {e}" if len(specs) > 1 else f"--grid: {e}") from None
    grid = {name: make() for name, _, make in specs}
    try:                                 # names, objects and values, before the target is read
        _sweep._axes(scene, grid, "grid")
        _sweep.batched.check_terms(_sweep.batched.terms_for(scene))
    except (_sweep.SweepError, NotImplementedError) as e:
        raise JaxplushError(f"{args.scene}: {e}") from None
    return dict(grid=grid, scene=scene, checkpoint=checkpoint, address=address, timeout=timeout)


# --------------------------------------------------------------------------- jax.distributed

def _wait_for_coordinator(args, host, port, deadline, timeout):
    """Until ``deadline``: try a plain TCP connection to the coordinator (process 0 hosts it);
    return once its port accepts one. (JAX's own wait ends the process with a C++ stack dump.)"""
    from jaxplush.errors import JaxplushError
    last = None
    while True:
        left = deadline - time.monotonic()
        if left <= 0:
            break
        try:
            with socket.create_connection((host, port), timeout=min(left, 2.0)):
                return
        except OSError as e:
            last = e
        time.sleep(max(0.0, min(0.25, deadline - time.monotonic())))
    why = "" if last is None else f" ({_why(last)})"
    raise JaxplushError(f"--coordinator: no coordinator answered at {args.coordinator} within --connect-timeout "
                        f"{timeout:g} s{why}; start process 0 (--process-id 0 hosts it) on {host}, or check "
                        f"HOST:PORT")


def _check_port_free(args, port):
    """Process 0 hosts the coordinator on ``port`` (every interface): refuse a port in use."""
    from jaxplush.errors import JaxplushError
    for family, anywhere in ((socket.AF_INET6, "::"), (socket.AF_INET, "0.0.0.0")):
        try:
            s = socket.socket(family, socket.SOCK_STREAM)
        except OSError:
            continue
        with s:
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            try:
                s.bind((anywhere, port))
                return
            except OSError as e:
                if e.errno == errno.EADDRINUSE:
                    raise JaxplushError(f"--coordinator: port {port} is in use on this machine, where process 0 "
                                        f"hosts the coordinator; give another port ({args.coordinator})") from None
                if e.errno in (errno.EACCES, errno.EPERM):
                    raise JaxplushError(f"--coordinator: process 0 may not open port {port} (permission "
                                        f"denied); give a port above 1023 ({args.coordinator})") from None


def _initialize_distributed(args, checked):
    """``jax.distributed.initialize`` from the explicit options, else from the cluster's environment,
    within ``--connect-timeout``: a process other than 0 first waits for the coordinator's port;
    then a watchdog ends the process with one message (exit 2) if the processes have not all joined
    when the timeout expires, before JAX's own deadline (a C++ abort with a stack dump)."""
    from jaxplush.errors import JaxplushError
    import inspect
    import jax
    timeout, address = checked["timeout"], checked["address"]
    deadline = time.monotonic() + timeout
    kw = {}
    if args.coordinator is not None:
        kw = dict(coordinator_address=args.coordinator.strip(), num_processes=args.num_processes,
                  process_id=args.process_id)
        host, port = address
        if args.process_id == 0:
            _check_port_free(args, port)
        else:
            _wait_for_coordinator(args, host, port, deadline, timeout)
    left = max(1.0, deadline - time.monotonic())
    if "initialization_timeout" in inspect.signature(jax.distributed.initialize).parameters:
        kw["initialization_timeout"] = int(math.ceil(left)) + _JAX_DEADLINE_MARGIN
    if args.coordinator is not None:
        late = (f"--coordinator: the {args.num_processes} processes did not all join {args.coordinator} within "
                f"--connect-timeout {timeout:g} s; start every --process-id 0..{args.num_processes - 1} with "
                f"the same --coordinator and --num-processes")
    else:
        late = f"--distributed: the cluster's processes did not all join within --connect-timeout {timeout:g} s"
    joined = threading.Event()

    def watchdog():                      # JAX waits in C++ with the GIL released: this thread runs
        if not joined.wait(left):
            print(f"jaxplush-fit sweep: error: {late}", file=sys.stderr, flush=True)
            os._exit(EXIT_USAGE)         # nothing is written yet; JAX's threads cannot be stopped otherwise

    threading.Thread(target=watchdog, name="jaxplush-connect-timeout", daemon=True).start()
    try:
        jax.distributed.initialize(**kw)
    except (RuntimeError, ValueError) as e:
        raise JaxplushError(f"--distributed: jax.distributed.initialize failed: {e}") from None
    finally:
        joined.set()


def _run(args, checked):
    grid, scene, checkpoint = checked["grid"], checked["scene"], checked["checkpoint"]
    if args.x64:
        import jax
        jax.config.update("jax_enable_x64", True)
    from jaxplush.errors import JaxplushError
    from jaxplush.fitting import sweep as _sweep
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
