"""Scale-out: several local devices, several processes, resumable sweeps.

Several local devices: with more than one device, the
batched engine runs a batch's chunks one per device through ``jax.shard_map`` over a "batch"
mesh axis, so the sweep and the fit's global stage use every device with no thread pool. Each
device runs the one-chunk program, so results are bit-identical to one device. Checked here on
this CPU with XLA_FLAGS=--xla_force_host_platform_device_count=4 in a subprocess, against the
same runs in this (one-device) process: a contact rollout with a padded last group, bounding-box
separations and a lane that blows up; the fit's Evaluator; and a sweep against a target.

Several processes: ``jaxplush-fit sweep --distributed`` in two local processes (jax.distributed on
127.0.0.1, CPU collectives for the barriers) writes the file one process writes. Resumable: a
sweep killed by SIGKILL part-way resumes from its finished batches and writes the file of an
uninterrupted run.
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time

import h5py

import jax
import numpy as np
import pytest

from jaxplush.stepping import batched

HERE = os.path.dirname(__file__)


def _run_with_devices(n, out):
    env = dict(os.environ)
    env["XLA_FLAGS"] = (env.get("XLA_FLAGS", "") + f" --xla_force_host_platform_device_count={n}").strip()
    env["JAX_PLATFORMS"] = "cpu"
    r = subprocess.run([sys.executable, os.path.join(HERE, "sharding_worker.py"), str(out)], env=env,
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    return dict(np.load(out))


# CI's heavy tier: a subprocess with four forced devices compiles every program again (XLA_FLAGS key the
# cache), 2-5 min on 2 cores. The default run covers the grouping of chunks over devices in
# test_a_batch_is_split_one_chunk_per_device and two processes in test_two_processes_write_the_one_process_file.
@pytest.mark.heavy
@pytest.mark.skipif(jax.default_backend() != "cpu" or len(jax.local_devices()) != 1,
                    reason="compares a forced 4-device CPU run with this one-device CPU process")
def test_four_devices_give_the_one_device_results_bit_for_bit(tmp_path):
    import sharding_worker
    four = _run_with_devices(4, tmp_path / "four.npz")
    assert int(four.pop("devices")) == 4
    assert int(four.pop("sharded_calls")) >= 3           # the rollout, the Evaluator and the sweep
    one = sharding_worker.collect()
    assert int(one.pop("devices")) == 1
    assert set(one) == set(four)
    for name in one:
        assert one[name].shape == four[name].shape, name
        assert np.array_equal(one[name], four[name], equal_nan=True), name
    # the runs are not trivial: lane 7 blew up (and only it), the others moved and met
    code = one["code"]
    assert np.all(code[:, 7] != 0) and np.count_nonzero(code.any(axis=0)) <= 2
    assert np.all(np.isfinite(one["frames"][:, [0, 19]]))
    assert np.max(one["sep"][0, [0, 19]]) < 0.01               # the balls, 4 cm apart, met
    assert one["ev_ok"].all() and np.ptp(one["ev_loss"]) > 0 and np.isfinite(one["sweep_loss"]).all()
    assert one["ev_pieces_ok"].all()
    np.testing.assert_allclose(one["ev_pieces_loss"], one["ev_loss"], rtol=1e-4)   # pieces: the same run


def test_a_batch_is_split_one_chunk_per_device(monkeypatch):
    # the grouping, without devices: 5 chunks of 16 over 4 devices run as 2 sharded calls of 4
    # chunks each (the last group padded), on a mesh of 4
    calls = []

    class Seen(Exception):
        pass

    def fake(bsim, mesh, params, *a, **k):
        calls.append((mesh, params.k_structural.shape[-1]))
        if len(calls) == 2:
            raise Seen
        return ()

    monkeypatch.setattr(batched, "local_devices", lambda: tuple(jax.devices()) * 4)
    monkeypatch.setattr(batched, "_mesh", lambda devices: len(devices))
    monkeypatch.setattr(batched, "_sharded_jit", fake)
    from conftest import icosphere_scene
    bsim = batched.make_batched_simulator(icosphere_scene(subdivisions=0), 2e-4, 80, chunk=16)
    p = bsim.params()
    with pytest.raises(Seen):
        batched.rollout(bsim, p, bsim.init_fn(p), 1, 1)
    assert calls == [(4, 64), (4, 64)]


SWEEP = ["scenes/ball_drop.obj", "--grid", "k=100:1000:6", "--grid", "nmol=0.001:0.01:2", "--log", "--dt", "2e-4",
         "--quiet"]
ROOT = os.path.dirname(HERE)


def _sweep_cmd(out, *extra, steps=200, batch=2):
    return [sys.executable, "-m", "jaxplush.fitting.cli", "sweep", *SWEEP, "--steps", str(steps), "--batch",
            str(batch), "--out", str(out), *extra]


def _cli(*cmd, **kw):
    r = subprocess.run(list(cmd), cwd=ROOT, capture_output=True, text=True, timeout=600, **kw)
    assert r.returncode == 0, r.stderr[-3000:]
    return r


def _same_sweep_files(a, b):
    """Every dataset and attribute equal, bit for bit (the wall time apart)."""
    with h5py.File(a) as fa, h5py.File(b) as fb:
        names = []
        fa.visit(lambda n: names.append(n) if isinstance(fa[n], h5py.Dataset) else None)
        other = []
        fb.visit(lambda n: other.append(n) if isinstance(fb[n], h5py.Dataset) else None)
        assert sorted(names) == sorted(other)
        for n in names:
            assert np.array_equal(fa[n][()], fb[n][()]), n
        assert set(fa.attrs) == set(fb.attrs)
        for k in fa.attrs:
            if k != "wall_time":
                assert np.array_equal(fa.attrs[k], fb.attrs[k]), k


def _free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_two_processes_write_the_one_process_file(tmp_path):
    one, two = tmp_path / "one.h5", tmp_path / "two.h5"
    port = _free_port()
    cpu = dict(os.environ, JAX_PLATFORMS="cpu")           # CPU collectives, whatever else the machine has
    _cli(*_sweep_cmd(one), env=cpu)
    procs = [subprocess.Popen(_sweep_cmd(two, "--distributed", "--coordinator", f"127.0.0.1:{port}",
                                         "--num-processes", "2", "--process-id", str(i)),
                              cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=cpu)
             for i in range(2)]
    outs = [p.communicate(timeout=600) for p in procs]
    for p, (o, e) in zip(procs, outs):
        assert p.returncode == 0, e[-3000:]
    assert "wrote" in outs[0][0] and "wrote" not in outs[1][0]           # process 0 writes and reports
    _same_sweep_files(one, two)
    assert not os.path.exists(str(two) + ".parts")                     # the checkpoint is gone


def test_a_sweep_killed_by_sigkill_resumes_to_the_uninterrupted_file(tmp_path):
    whole, resumed = tmp_path / "whole.h5", tmp_path / "resumed.h5"
    parts = str(resumed) + ".parts"
    steps = 1500                                                       # 6 batches of 2 points
    proc = subprocess.Popen(_sweep_cmd(resumed, steps=steps), cwd=ROOT, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    done = []
    deadline = time.time() + 300
    while time.time() < deadline and proc.poll() is None:
        done = [n for n in os.listdir(parts) if n.endswith(".npz")] if os.path.isdir(parts) else []
        if done:
            proc.send_signal(signal.SIGKILL)
            break
        time.sleep(0.005)
    proc.wait()
    assert proc.returncode == -signal.SIGKILL, "the sweep finished before it could be killed"
    done = sorted(n for n in os.listdir(parts) if n.endswith(".npz"))
    assert 1 <= len(done) < 6 and not os.path.exists(resumed)
    r = _cli(*[a for a in _sweep_cmd(resumed, steps=steps) if a != "--quiet"])       # with its messages
    assert f"resuming from {len(done)} of 6 finished batches" in r.stderr
    _cli(*_sweep_cmd(whole, steps=steps))
    _same_sweep_files(whole, resumed)
    assert not os.path.exists(parts)


def test_a_checkpoint_resumes_only_its_own_sweep(tmp_path, monkeypatch):
    from conftest import icosphere_scene
    from jaxplush.fitting import sweep as S
    scene = icosphere_scene(subdivisions=1, nmol=1e-3, floor=-0.12)
    grid = {"k": [100.0, 150.0, 200.0, 300.0, 400.0]}
    ck = tmp_path / "ck"
    first = S.sweep(scene, grid, steps=40, dt=2e-4, batch=2, checkpoint=ck, progress=False)
    assert sorted(os.listdir(ck)) == ["batch_000000.npz", "batch_000001.npz", "batch_000002.npz", "plan.json"]
    # run again: every batch is read back, none simulated, and the result is the same
    monkeypatch.setattr(S, "_run_chunk", lambda *a: pytest.fail("a finished batch ran again"))
    again = S.sweep(scene, grid, steps=40, dt=2e-4, batch=2, checkpoint=ck, progress=False)
    for name in ("final_positions", "fail_code", "volume"):
        assert np.array_equal(getattr(first, name), getattr(again, name)), name
    # another sweep (other values, steps or batch) refuses the directory
    for kw in (dict(steps=41), dict(batch=1)):
        with pytest.raises(S.SweepError, match="another sweep"):
            S.sweep(scene, grid, **dict(dict(steps=40, dt=2e-4, batch=2), **kw), checkpoint=ck, progress=False)
    with pytest.raises(S.SweepError, match="another sweep"):
        S.sweep(scene, {"k": [100.0, 150.0]}, steps=40, dt=2e-4, batch=2, checkpoint=ck, progress=False)
    # removal deletes the checkpoint's files only
    (ck / "notes.txt").write_text("mine")
    S.remove_checkpoint(ck)
    assert os.listdir(ck) == ["notes.txt"]


def test_distributed_options_are_checked_before_anything_runs(tmp_path):
    from jaxplush.fitting.sweep.cli import main
    out = tmp_path / "s.h5"
    assert main([*SWEEP, "--steps", "10", "--out", str(out), "--distributed", "--coordinator", "127.0.0.1:1"]) == 2
    assert main([*SWEEP, "--steps", "10", "--out", str(out), "--distributed", "--coordinator", "127.0.0.1:1",
                 "--num-processes", "2", "--process-id", "2"]) == 2
    assert not out.exists()
