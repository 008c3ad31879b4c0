"""Scale-out of a sweep: 1, 2 and 4 local devices, 1 and 2 processes, and a paper estimate.

Each configuration runs ``jaxplush.fitting.sweep.sweep`` of the ball-drop plush of bench_step.py
(642 vertices by default; k_structural spread over the points) in fresh subprocesses:

* ``devices N``: one process with ``XLA_FLAGS=--xla_force_host_platform_device_count=N``: the
  batched engine spreads each batch over the N devices with ``jax.shard_map`` (one 16-point chunk
  per device; with one device, its thread pool runs the chunks, one per core);
* ``processes N``: N processes on 127.0.0.1 joined by ``jax.distributed`` (CPU collectives), each
  running every N-th batch into a shared checkpoint directory, one device each.

Every configuration sweeps the same points twice in one process; the second sweep (compiled
already) is timed, so the figure is throughput, not compile time. Printed: points, wall time of
the timed sweep (the slowest process), total point-steps/s and the speed-up over one device.

``--estimate`` then prints the estimate asked for in issue 28: a 10^5-point, 2562-vertex,
3000-step sweep on 8 GPUs, from a measured one-GPU throughput (``--gpu-rate``, point-steps/s at
2562 vertices; default: the H200 figure in RESULTS.md) and the data the processes exchange
(each point's final positions and summaries, written to the shared checkpoint and read by
process 0; no collective moves simulation data).

Usage: python benchmarks/bench_scale.py [--points 64] [--steps 500] [--subdivisions 3]
       [--devices 1,2,4] [--processes 1,2] [--estimate] [--gpu-rate R]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import socket
import subprocess
import sys
import tempfile
import time

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)

#: One H200's total point-steps/s of the batched engine at 2562 vertices, 4096 points in one call
#: (`bench_sweep.py --subdivisions 4 --batches 1024,4096 --steps 300`, 2026-11-28; RESULTS.md);
#: used by --estimate unless --gpu-rate is given.
H200_RATE_2562 = 9_253_043


def _worker(args):
    """Run in a subprocess: two identical sweeps, the second timed; print one JSON line."""
    import jax
    if args.num_processes > 1:
        jax.distributed.initialize(f"127.0.0.1:{args.port}", num_processes=args.num_processes,
                                   process_id=args.process_id)
    import numpy as np
    sys.path.insert(0, HERE)
    from bench_step import ball_scene
    from jaxplush.fitting.sweep import remove_checkpoint, sweep
    scene = ball_scene(args.subdivisions)
    grid = {"k": np.linspace(300.0, 700.0, args.points)}
    times = []
    for i in range(2):
        ck = None if args.checkpoint is None else os.path.join(args.checkpoint, f"run{i}")
        t0 = time.perf_counter()
        res = sweep(scene, grid, steps=args.steps, dt=2e-4, progress=False, checkpoint=ck)
        times.append(time.perf_counter() - t0)
        if ck is not None:
            remove_checkpoint(ck)
    assert not res.failed.any()
    print(json.dumps(dict(devices=len(jax.local_devices()), processes=jax.process_count(), rank=jax.process_index(),
                          first_s=times[0], wall_s=times[1], vertices=scene.n_vertices)), flush=True)


def _free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _launch(args, devices=1, processes=1):
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    env["XLA_FLAGS"] = (env.get("XLA_FLAGS", "") + f" --xla_force_host_platform_device_count={devices}").strip()
    base = [sys.executable, os.path.abspath(__file__), "--worker", "--points", str(args.points), "--steps",
            str(args.steps), "--subdivisions", str(args.subdivisions)]
    with tempfile.TemporaryDirectory() as tmp:
        extra = []
        if processes > 1:
            extra = ["--num-processes", str(processes), "--port", str(_free_port()), "--checkpoint", tmp]
        procs = [subprocess.Popen(base + extra + (["--process-id", str(i)] if processes > 1 else []), cwd=ROOT,
                                  env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
                 for i in range(processes)]
        outs = [p.communicate(timeout=1800) for p in procs]
    rows = []
    for p, (o, e) in zip(procs, outs):
        if p.returncode != 0:
            raise SystemExit(f"worker failed:\n{e[-3000:]}")
        rows.append(json.loads(o.strip().splitlines()[-1]))
    return dict(rows[0], wall_s=max(r["wall_s"] for r in rows), first_s=max(r["first_s"] for r in rows))


def estimate(rate, n_points=100_000, vertices=2562, steps=3000, gpus=8, bandwidth=1e9, objects=1, batch=4096,
             compile_s=2.0):
    """(rows of (quantity, value)) of the paper estimate: compute time from the one-GPU rate (whole
    batches of ``batch`` points, dealt round-robin to the GPUs), one compile per process, and the
    data exchanged through the shared checkpoint (final positions float32 + summaries and failure
    record per point: every process writes its batches, process 0 reads them all) at
    ``bandwidth`` bytes/s. No collective moves simulation data: the barriers carry nothing."""
    work = n_points * steps
    batches = -(-n_points // batch)
    per_gpu = -(-batches // gpus)                          # the busiest GPU's batches
    compute = per_gpu * batch * steps / rate
    per_point = vertices * 3 * 4 + objects * (3 * 4 + 3 * 8) + 8 + 8
    volume = n_points * per_point
    io = 2 * volume / bandwidth                            # written once, read once by process 0
    return [("point-steps", f"{work:.3g}"), ("one-GPU rate (point-steps/s)", f"{rate:,.0f}"),
            ("compute on one GPU", f"{work / rate:,.1f} s"),
            (f"batches of {batch} points; on the busiest of {gpus} GPUs", f"{batches}; {per_gpu}"),
            (f"compute on {gpus} GPUs", f"{compute:,.1f} s"),
            ("compile, once per process (in parallel)", f"{compile_s:.1f} s"),
            ("data through the checkpoint (final positions + records)", f"{volume / 1e9:.2f} GB"),
            (f"written and read at {bandwidth / 1e9:g} GB/s (shared filesystem)", f"{io:.1f} s"),
            ("estimated wall time", f"{compute + compile_s + io:,.1f} s")]


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--points", type=int, default=64)
    ap.add_argument("--steps", type=int, default=500)
    ap.add_argument("--subdivisions", type=int, default=3, help="icosphere subdivisions (3: 642 vertices)")
    ap.add_argument("--devices", default="1,2,4")
    ap.add_argument("--processes", default="1,2")
    ap.add_argument("--estimate", action="store_true")
    ap.add_argument("--gpu-rate", type=float, default=None,
                    help="one GPU's point-steps/s at 2562 vertices for --estimate")
    ap.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--num-processes", type=int, default=1, help=argparse.SUPPRESS)
    ap.add_argument("--process-id", type=int, default=0, help=argparse.SUPPRESS)
    ap.add_argument("--port", type=int, default=0, help=argparse.SUPPRESS)
    ap.add_argument("--checkpoint", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.worker:
        return _worker(args)
    import jax
    print(f"# jax {jax.__version__}, {os.cpu_count()} cores, {platform.processor() or platform.machine()}; "
          f"float32; {args.points} points x {args.steps} steps, ball-drop plush, subdivisions {args.subdivisions}; "
          "the second of two sweeps in each process timed")
    print("| configuration | vertices | wall (s) | point-steps/s | vs 1 device | first sweep incl. compile (s) |")
    print("|---|---:|---:|---:|---:|---:|")
    base = None
    configs = [("devices", int(n)) for n in args.devices.split(",") if n] + \
              [("processes", int(n)) for n in args.processes.split(",") if n and int(n) > 1]
    for kind, n in configs:
        r = _launch(args, devices=n if kind == "devices" else 1, processes=n if kind == "processes" else 1)
        rate = args.points * args.steps / r["wall_s"]
        base = base or rate
        print(f"| {n} {kind[:-1] if n == 1 else kind} | {r['vertices']} | {r['wall_s']:.2f} | {rate:,.0f} | "
              f"{rate / base:.2f}x | {r['first_s']:.2f} |", flush=True)
    if args.estimate:
        rate = args.gpu_rate or H200_RATE_2562
        print("\nEstimate: 10^5 points x 3000 steps at 2562 vertices on 8 GPUs\n")
        print("| quantity | value |\n|---|---:|")
        for q, v in estimate(rate):
            print(f"| {q} | {v} |")


if __name__ == "__main__":
    main()
