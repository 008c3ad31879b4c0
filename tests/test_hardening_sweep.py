"""Hardening of ``jaxplush-fit sweep``'s command line, found by fuzzing: every bad option exits 2
with one line ``jaxplush-fit sweep: error: <option>: <problem>``, no traceback, nothing written
(no SWEEP.h5, no checkpoint directory), and before anything is compiled or connected.

Rows: a --coordinator that is not HOST:PORT (was an IndexError); ports, --num-processes and
--process-id out of range (were accepted); a coordinator nobody runs (was 300 s of silence, then a
C++ abort with a stack dump: now --connect-timeout bounds the wait); a --checkpoint that cannot be
a directory (were NotADirectoryError / FileNotFoundError tracebacks); a grid of 10^12 points (was
a MemoryError).
"""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import time

import numpy as np
import pytest

from conftest import icosphere_text
from jaxplush.fitting.sweep.cli import DEFAULT_CONNECT_TIMEOUT, main as sweep_main

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
PREFIX = "jaxplush-fit sweep: error: "


@pytest.fixture
def scene_file(tmp_path):
    obj = tmp_path / "ball.obj"
    obj.write_text(icosphere_text(subdivisions=0, nmol=1e-3))
    return obj


def _argv(scene_file, *extra, grid=("k=100:200:2",)):
    out = scene_file.parent / "out.h5"
    argv = [str(scene_file)]
    for g in grid:
        argv += ["--grid", g]
    return argv + ["--steps", "10", "--dt", "1e-4", "--out", str(out), "--quiet", *extra]


def _refused(capsys, argv, option, *words, limit=5.0):
    """main(argv) exits 2 within ``limit`` s with one line naming ``option`` (and ``words``)."""
    t = time.perf_counter()
    rc = sweep_main(argv)
    wall = time.perf_counter() - t
    err = capsys.readouterr().err
    assert rc == 2, err
    _one_line(err, option, *words)
    assert wall < limit, f"the check took {wall:.1f} s: it must fire before anything runs"
    return err


def _one_line(err, option, *words):
    assert "Traceback" not in err and "Check failed" not in err, err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith(PREFIX + option), err
    for w in words:
        assert w in lines[0], (w, err)


def _nothing_written(tmp_path, *inputs):
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(inputs)


def _free_port():
    """A port nothing listens on (bound by the kernel, then closed again)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


# --------------------------------------------------------------------------- 1: --coordinator not HOST:PORT

@pytest.mark.parametrize("address", ["not-an-address", "127.0.0.1", ":1234", "host:", "::1:1234", "[::1:1234"])
def test_coordinator_must_be_host_port(scene_file, tmp_path, capsys, address):
    argv = _argv(scene_file, "--distributed", "--coordinator", address, "--num-processes", "2", "--process-id", "1")
    err = _refused(capsys, argv, "--coordinator: ")
    assert "HOST:PORT" in err or "[ADDR]:PORT" in err
    _nothing_written(tmp_path, "ball.obj")


# --------------------------------------------------------------------------- 2: ports, process counts, ids

@pytest.mark.parametrize("extra, option, words", [
    (("--coordinator", "127.0.0.1:99999", "--num-processes", "2", "--process-id", "0"), "--coordinator",
     ("port 99999", "1..65535")),
    (("--coordinator", "127.0.0.1:0", "--num-processes", "2", "--process-id", "0"), "--coordinator",
     ("port 0", "1..65535")),
    (("--coordinator", "127.0.0.1:http", "--num-processes", "2", "--process-id", "0"), "--coordinator",
     ("1..65535",)),
    (("--coordinator", "127.0.0.1:1234", "--num-processes", "0", "--process-id", "0"), "--num-processes",
     (">= 1", "got 0")),
    (("--coordinator", "127.0.0.1:1234", "--num-processes", "-3", "--process-id", "0"), "--num-processes",
     (">= 1", "got -3")),
    (("--coordinator", "127.0.0.1:1234", "--num-processes", "2", "--process-id", "-1"), "--process-id",
     ("0..1", "got -1")),
    (("--coordinator", "127.0.0.1:1234", "--num-processes", "2", "--process-id", "2"), "--process-id",
     ("0..1", "got 2")),
    (("--coordinator", "127.0.0.1:1234", "--num-processes", "2", "--process-id", "1", "--connect-timeout", "0"),
     "--connect-timeout", ("got 0",)),
    (("--connect-timeout", "-5"), "--connect-timeout", ("got -5",)),
    (("--connect-timeout", "inf"), "--connect-timeout", ("got inf",)),
])
def test_distributed_values_are_checked_for_range(scene_file, tmp_path, capsys, extra, option, words):
    _refused(capsys, _argv(scene_file, "--distributed", *extra), option + ": ", *words)
    _nothing_written(tmp_path, "ball.obj")


def test_distributed_options_need_distributed(scene_file, tmp_path, capsys):
    for extra in (("--coordinator", "127.0.0.1:1234"), ("--connect-timeout", "5")):
        _refused(capsys, _argv(scene_file, *extra), extra[0] + ": ", "only with --distributed")
    _nothing_written(tmp_path, "ball.obj")


# --------------------------------------------------------------------------- 3: nobody runs the coordinator

def _sweep_process(scene_file, *extra):
    cmd = [sys.executable, "-m", "jaxplush.fitting.cli", "sweep", *_argv(scene_file, *extra)]
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    t = time.perf_counter()
    r = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=120)
    return r, time.perf_counter() - t


def test_unreachable_coordinator_stops_within_connect_timeout(scene_file, tmp_path):
    port = _free_port()
    r, wall = _sweep_process(scene_file, "--distributed", "--coordinator", f"127.0.0.1:{port}",
                             "--num-processes", "2", "--process-id", "1", "--connect-timeout", "2")
    assert r.returncode == 2, r.stderr[-3000:]
    _one_line(r.stderr, "--coordinator: ", f"127.0.0.1:{port}", "--connect-timeout 2 s")
    assert wall < 30, wall                          # 2 s of waiting plus the interpreter's start
    _nothing_written(tmp_path, "ball.obj")


def test_processes_that_never_join_stop_process_0_within_connect_timeout(scene_file, tmp_path):
    # process 0 hosts the coordinator and waits for process 1, which never comes: JAX would abort
    # with a C++ stack dump after 300 s; --connect-timeout ends it with one line
    port = _free_port()
    r, wall = _sweep_process(scene_file, "--distributed", "--coordinator", f"127.0.0.1:{port}",
                             "--num-processes", "2", "--process-id", "0", "--connect-timeout", "2")
    assert r.returncode == 2, r.stderr[-3000:]
    _one_line(r.stderr, "--coordinator: ", "did not all join", "--connect-timeout 2 s")
    assert wall < 30, wall
    _nothing_written(tmp_path, "ball.obj")


def test_a_coordinator_port_in_use_is_refused(scene_file, tmp_path, capsys):
    with socket.socket() as busy:
        busy.bind(("0.0.0.0", 0))
        busy.listen()
        port = busy.getsockname()[1]
        # process 0 checks its port before jax.distributed starts: in this process is safe
        _refused(capsys, _argv(scene_file, "--distributed", "--coordinator", f"127.0.0.1:{port}",
                               "--num-processes", "2", "--process-id", "0"), "--coordinator: ", f"port {port}",
                 "in use")
    _nothing_written(tmp_path, "ball.obj")


def test_connect_timeout_is_documented_in_help(capsys):
    assert sweep_main(["--help"]) == 0
    out = " ".join(capsys.readouterr().out.split())
    assert "--connect-timeout SECONDS" in out and f"default {DEFAULT_CONNECT_TIMEOUT:g} s" in out


# --------------------------------------------------------------------------- 4: a checkpoint that cannot be a directory

def test_checkpoint_under_a_file_is_refused(scene_file, tmp_path, capsys):
    regular = tmp_path / "notes.txt"
    regular.write_text("mine")
    for ck in (regular / "sub", regular / "sub" / "deeper", regular):
        _refused(capsys, _argv(scene_file, "--checkpoint", str(ck)), f"--checkpoint {ck}: ",
                 f"{regular} is a file, not a directory")
    _nothing_written(tmp_path, "ball.obj", "notes.txt")
    assert regular.read_text() == "mine"


def test_checkpoint_through_a_dangling_link_is_refused(scene_file, tmp_path, capsys):
    link = tmp_path / "gone"
    link.symlink_to(tmp_path / "nowhere")
    for ck in (link, link / "sub"):
        _refused(capsys, _argv(scene_file, "--checkpoint", str(ck)), f"--checkpoint {ck}: ",
                 "symbolic link", "does not exist")
    _nothing_written(tmp_path, "ball.obj", "gone")


@pytest.mark.skipif(not os.path.isdir("/proc/self"), reason="needs a /proc filesystem")
def test_checkpoint_where_no_directory_can_be_made_is_refused(scene_file, tmp_path, capsys):
    for ck in ("/proc/x", "/proc/x/y"):
        _refused(capsys, _argv(scene_file, "--checkpoint", ck), f"--checkpoint {ck}: ", "/proc")
        assert not os.path.exists(ck)
    _nothing_written(tmp_path, "ball.obj")


def test_a_creatable_checkpoint_is_probed_without_leaving_it(scene_file, tmp_path, capsys):
    # a good --checkpoint in a new directory passes the check, and a later error leaves nothing
    ck = tmp_path / "new" / "parts"
    _refused(capsys, _argv(scene_file, "--checkpoint", str(ck), grid=("spring=1",)), f"{scene_file}: ",
             "unknown parameter 'spring'")
    _refused(capsys, _argv(scene_file, "--checkpoint", str(ck), grid=("k=100:1000:1000000",
                                                                        "nmol=0.001:0.01:1000000")),
             "--grid: ", "points")
    _nothing_written(tmp_path, "ball.obj")


# --------------------------------------------------------------------------- 5: a grid too large for memory

def test_a_grid_of_a_trillion_points_is_refused_before_allocating(scene_file, tmp_path, capsys):
    grid = ("k=100:1000:1000000", "nmol=0.001:0.01:1000000")
    _refused(capsys, _argv(scene_file, grid=grid), "--grid: ", "1,000,000 x 1,000,000",
             "1,000,000,000,000 points", "at most")
    _refused(capsys, _argv(scene_file, grid=("k=100:1000:1000000000000",)), "--grid: ",
             "1,000,000,000,000 points", "at most")
    _nothing_written(tmp_path, "ball.obj")


def test_saved_frames_count_against_memory(scene_file, tmp_path, capsys):
    # 1000 points are small, but 10^9 steps saved every step would keep 10^9 frames of each
    argv = _argv(scene_file, "--save-every", "1", grid=("k=100:1000:1000",))
    argv[argv.index("--steps") + 1] = "1000000000"
    _refused(capsys, argv, "--grid: ", "1,000 points", "saved frames", "at most")
    _nothing_written(tmp_path, "ball.obj")


def test_the_python_sweep_refuses_a_huge_grid_too():
    import jaxplush
    from jaxplush.fitting.sweep import SweepError, sweep
    scene = jaxplush.parse_scene(icosphere_text(subdivisions=0, nmol=1e-3), "<ball>")
    grid = {"k": np.linspace(100.0, 1000.0, 10 ** 6), "nmol": np.linspace(1e-3, 1e-2, 10 ** 6)}
    t = time.perf_counter()
    with pytest.raises(SweepError, match=r"grid: 1,000,000,000,000 points would need about .* at most"):
        sweep(scene, grid, steps=10, dt=1e-4, progress=False)
    assert time.perf_counter() - t < 5.0
