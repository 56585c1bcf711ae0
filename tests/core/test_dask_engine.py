"""The optional Dask engine: registrations on a LocalCluster of two workers give
the local process pool's results; addresses are checked; the core imports without Dask."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from shapegen_core.base.cluster import ClusterError, parse_scheduler
from shapegen_core.preprocess.collection import PrepareSettings, prepare_meshes
from shapegen_core.correspond import CorrespondenceSettings, correspond
from shapegen_core.correspond.settings import IterationSettings
from shapegen_core.demo_data import make_vases

distributed = pytest.importorskip("distributed")


@pytest.fixture(scope="module")
def cluster():
    """Two single-threaded workers in this process (processes=False: they start in well
    under a second; tasks are pickled all the same)."""
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=False,
                                  dashboard_address=None) as local:
        yield local


SETTINGS = CorrespondenceSettings(iterations=IterationSettings(max_iterations=8))


@pytest.fixture(scope="module")
def pooled():
    """Five prepared vases and their correspondence on the local process pool."""
    prepared = prepare_meshes([s.mesh for s in make_vases(5, seed=4, resolution=(14, 20))],
                              PrepareSettings(n_landmarks=120))
    return prepared, correspond(prepared, SETTINGS, jobs=2)


def test_dask_registrations_equal_the_process_pool(cluster, pooled):
    prepared, pool = pooled
    messages = []
    on_dask = correspond(prepared, SETTINGS, scheduler=cluster.scheduler_address,
                         progress=lambda fraction, message: messages.append((fraction, message)))
    assert on_dask.names == pool.names and on_dask.template_name == pool.template_name
    np.testing.assert_allclose(on_dask.points, pool.points, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(on_dask.face_index, pool.face_index)
    np.testing.assert_allclose(on_dask.residuals, pool.residuals, rtol=0, atol=1e-12)
    fractions = [f for f, _ in messages]
    assert fractions == sorted(fractions) and fractions[-1] == 1.0
    assert any("registered" in m for _, m in messages)


def test_cancel_on_dask_stops_the_registrations(cluster, pooled):
    """Cancel asked once the first shape is registered raises Cancelled; nothing is returned."""
    import threading

    from shapegen_core.base.errors import Cancelled

    prepared, _ = pooled
    stop = threading.Event()
    with pytest.raises(Cancelled):
        correspond(prepared, SETTINGS, scheduler=cluster.scheduler_address, should_cancel=stop,
                   progress=lambda fraction, message: "registered" in message and stop.set())


def test_dense_shapes_on_dask_equal_the_pool(cluster):
    """The proxy and placement steps (one dense mesh per task) run on Dask alike."""
    meshes = [s.mesh for s in make_vases(3, seed=5, resolution=(30, 34))]
    prepared = prepare_meshes(meshes, PrepareSettings(n_landmarks=100, align="none"))
    settings = CorrespondenceSettings(iterations=IterationSettings(max_iterations=6), proxy_faces=500)
    assert all(s.mesh.n_faces > 2.5 * settings.proxy_faces for s in prepared.shapes)
    pool = correspond(prepared, settings, jobs=2)
    on_dask = correspond(prepared, settings, scheduler=cluster.scheduler_address)
    np.testing.assert_allclose(on_dask.points, pool.points, rtol=0, atol=1e-12)


@pytest.mark.parametrize("text, expected", [("local:3", ("local", 3)),
                                            ("tcp://10.0.0.5:8786", ("address", "tcp://10.0.0.5:8786"))])
def test_scheduler_addresses(text, expected):
    assert parse_scheduler(text) == expected


@pytest.mark.parametrize("text", ["local:0", "local:x", "10.0.0.5:8786", "http://host:8786", "tcp://"])
def test_bad_scheduler_addresses_are_refused(text):
    with pytest.raises(ClusterError, match="--scheduler"):
        parse_scheduler(text)


def test_core_imports_and_runs_without_dask():
    """Dask is an optional extra: with it hidden, the core imports, corresponds locally,
    and --scheduler names the package to install."""
    code = (
        "import sys; sys.modules['distributed'] = None; sys.modules['dask'] = None\n"
        "import shapegen_core.app.pipeline, shapegen_core.app.cli\n"
        "from shapegen_core.base.cluster import connect, ClusterError\n"
        "try:\n"
        "    with connect('local:1'): pass\n"
        "except ClusterError as exc: print(exc)\n"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert 'pip install "dask[distributed]"' in done.stdout


def test_batch_sampling_on_dask_writes_the_pools_meshes(cluster, pooled, tmp_path):
    """`shapegen sample --scheduler` writes the same files as the local process pool."""
    from shapegen_core.app.cli import main
    from shapegen_core.app.fit_settings import FitSettings
    from shapegen_core.app.pipeline import fit_shape_model

    prepared, corr = pooled
    settings = FitSettings(prepare=prepared.settings, model="ppca")
    model_path = fit_shape_model([s.mesh for s in prepared.shapes], corr, settings).save(tmp_path / "model.npz")
    common = ["sample", str(model_path), "-n", "16", "--seed", "3"]
    assert main(common + ["-o", str(tmp_path / "pool"), "--jobs", "2"]) == 0
    assert main(common + ["-o", str(tmp_path / "dask"), "--scheduler", cluster.scheduler_address]) == 0
    pool_files = sorted(p.name for p in (tmp_path / "pool").iterdir())
    assert pool_files == sorted(p.name for p in (tmp_path / "dask").iterdir()) and len(pool_files) == 17
    for name in pool_files:
        if name.endswith(".obj"):
            assert (tmp_path / "pool" / name).read_bytes() == (tmp_path / "dask" / name).read_bytes(), name
