"""A worker process killed during `shapegen fit` (SIGKILL, as the out-of-memory killer
would) ends the command with exit status 2 and one line: the shape, the signal, the
likely cause and what to try; no traceback, no output file, no temporary folder.
The worker kills itself through the test hook `pool.KILL_ON_SHAPE_VARIABLE`."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import tempfile
import time

from shapegen_core.app.cli import main
from shapegen_core.correspond.pool import KILL_ON_SHAPE_VARIABLE
from shapegen_core.demo_data import make_vases, write_collection


def test_a_killed_worker_is_one_line_naming_the_shape_the_signal_and_what_to_try(tmp_path, capsys, monkeypatch):
    folder = tmp_path / "vases"
    shapes = make_vases(3, seed=1, resolution=(6, 8))
    write_collection(shapes, folder)
    victim = shapes[1].name
    monkeypatch.setenv(KILL_ON_SHAPE_VARIABLE, victim)  # inherited by the spawned workers
    private_temp = tmp_path / "temp"  # this run's temporary folder (other runs share the system's)
    private_temp.mkdir()
    monkeypatch.setenv("TMPDIR", str(private_temp))
    monkeypatch.setattr(tempfile, "tempdir", str(private_temp))
    output = tmp_path / "model.npz"
    status = main(["fit", str(folder), "-o", str(output), "--landmarks", "30", "--align", "none", "--jobs", "2",
                   "--model", "ppca", "--latent-dim", "1"])
    err = capsys.readouterr().err
    errors = [line for line in err.splitlines() if line.startswith("shapegen fit:")]
    assert status == 2, err
    assert "Traceback" not in err
    assert len(errors) == 1, errors
    line = errors[0]
    assert line.startswith(f"shapegen fit: error: {victim}: ")
    assert "signal 9 (SIGKILL)" in line and "memory" in line and "--jobs" in line and "used 2" in line
    assert not output.exists() and sorted(tmp_path.iterdir()) == [private_temp, folder]
    assert list(private_temp.iterdir()) == []  # the run's spill store removed


def test_a_terminated_command_removes_its_temporary_folders(tmp_path):
    """`kill` (SIGTERM) during `shapegen fit` ends it as Ctrl-C does: status 130, its spill
    store and pool closed, nothing left in its temporary folder, no output."""
    folder = tmp_path / "vases"
    write_collection(make_vases(3, seed=1, resolution=(6, 8)), folder)
    private_temp = tmp_path / "temp"
    private_temp.mkdir()
    output = tmp_path / "model.npz"
    environment = dict(os.environ, TMPDIR=str(private_temp), PYTHONPATH=os.pathsep.join(sys.path))
    process = subprocess.Popen([sys.executable, "-m", "shapegen_core.app.cli", "fit", str(folder), "-o", str(output),
                                "--landmarks", "30", "--align", "none", "--jobs", "2", "--model", "ppca"],
                               stderr=subprocess.PIPE, text=True, env=environment)
    deadline = time.monotonic() + 60
    while not any(private_temp.iterdir()) and time.monotonic() < deadline:  # its spill store exists
        time.sleep(0.05)
    time.sleep(0.2)  # inside the run (its worker pool takes longer than this to start)
    process.send_signal(signal.SIGTERM)
    _, err = process.communicate(timeout=60)
    assert process.returncode == 130, err
    assert "Traceback" not in err and err.strip().splitlines()[-1] == "shapegen fit: cancelled"
    assert list(private_temp.iterdir()) == [] and not output.exists()


def test_the_dead_worker_is_told_from_the_siblings_the_broken_pool_terminated():
    """Under load the message named a sibling the pool had ended with SIGTERM after the
    killed worker broke it (vase_002, SIGTERM instead of vase_001, SIGKILL)."""
    from shapegen_core.correspond.pool import dead_worker_task

    started = [(0, 100), (1, 101), (2, 102)]  # task index, worker pid, in start order
    sigkill, sigterm = -int(signal.SIGKILL), -int(signal.SIGTERM)
    assert dead_worker_task(started, {100: sigkill, 101: sigterm, 102: sigterm}) == (0, 100)
    assert dead_worker_task(started, {100: sigterm, 101: sigterm, 102: None}) == (1, 101)  # only the pool's
    assert dead_worker_task(started, {100: None, 101: 3, 102: None}) == (2, 102)  # no signal: the last started
