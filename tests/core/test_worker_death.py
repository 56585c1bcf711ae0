"""A worker process killed during `shapegen fit` (SIGKILL, as the out-of-memory killer
would) ends the command with exit status 2 and one line: the shape, the signal, the
likely cause and what to try; no traceback, no output file, no temporary folder (issue 32).
The worker kills itself through the test hook `pool.KILL_ON_SHAPE_VARIABLE`."""

from __future__ import annotations

import tempfile

from shapegen_core.cli import main
from shapegen_core.correspond.pool import KILL_ON_SHAPE_VARIABLE
from shapegen_core.datasets import make_vases, write_collection


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
