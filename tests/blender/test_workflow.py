"""Fit in the background through the installed extension.

Timers never fire in the bpy module, so these tests drive the add-on's polling loop
(`jobs.poll_job`) themselves, exactly as the UI timer would.
"""

from __future__ import annotations

import importlib
import json
import os
import re
import signal
import time
from pathlib import Path

import bpy
import numpy as np
import pytest
from conftest import add_vase_collection, addon_module, fast_fit_json, load_model


@pytest.fixture
def jobs(extension):
    module = addon_module(extension, "shapegen_addon.jobs")
    yield module
    module.MANAGER.kill()  # never leave a worker behind


def _pump(jobs, until, timeout=120.0, poll=None):
    """Poll like the UI timer (or a script, through `poll`) until `until(status)` holds;
    returns (statuses, longest poll)."""
    poll = poll or jobs.poll_job
    statuses, longest = [], 0.0
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        start = time.perf_counter()
        status = poll()
        longest = max(longest, time.perf_counter() - start)
        statuses.append(status)
        if until(status):
            return statuses, longest
        time.sleep(0.02)
    raise AssertionError(f"timed out; last status {statuses[-1] if statuses else None}")


def test_fit_runs_in_a_worker_and_progress_reaches_100_percent(extension, jobs):
    collection = add_vase_collection(extension)
    settings = bpy.context.scene.shapegen
    settings.fit.model = "ppca"
    objects_before = {o.name for o in bpy.data.objects}
    assert bpy.ops.shapegen.fit(extra_settings=fast_fit_json()) == {"FINISHED"}
    assert settings.job_state == "RUNNING"
    # Fit is disabled while the job runs, and says why; Cancel is available
    assert not bpy.ops.shapegen.fit.poll()
    assert bpy.ops.shapegen.fit_cancel.poll()
    with pytest.raises(RuntimeError, match="already running"):
        bpy.ops.shapegen.fit()
    assert settings.model_text is None  # nothing is applied before the job ends

    # the README's scripting entry point drives the job to its end, as the UI timer would
    poll_fit = addon_module(extension, "shapegen_addon.fitting").poll_fit
    statuses, _ = _pump(jobs, lambda s: s is not None and s.finished, poll=poll_fit)
    fractions = [s.fraction for s in statuses]
    assert fractions == sorted(fractions)  # progress only moves forward
    assert statuses[-1].state == "done" and fractions[-1] == 1.0
    assert any(0.0 < f < 1.0 for f in fractions)  # intermediate progress was seen
    assert settings.job_state == "DONE" and settings.job_fraction == 1.0
    assert "Fitted ppca to 6 shapes" in settings.job_message
    text = settings.model_text
    assert text is not None and text["shapegen_model_type"] == "ppca" and text["shapegen_latent_dim"] == 2
    assert len(settings.latents) == 2
    assert {o.name for o in bpy.data.objects} == objects_before  # the fit adds no objects
    assert bpy.ops.shapegen.fit.poll()  # enabled again
    model = addon_module(extension, "shapegen_addon.store").get_model(bpy.context.scene)
    assert sorted(model.names) == sorted(o.name for o in collection.objects)


def test_fit_reuses_a_current_prepared_collection_and_not_a_stale_one(extension, jobs):
    """Prepare's result with the panel's settings is what Fit starts from (no second
    Prepare in the worker); after a source object is edited, or with other settings, Fit
    prepares again."""
    collection = add_vase_collection(extension)
    settings = bpy.context.scene.shapegen
    settings.fit.model = "ppca"
    assert bpy.ops.shapegen.prepare(wait=True) == {"FINISHED"}
    prepared = bpy.data.collections["vases Prepared"]
    copies = {o["shapegen_source"]: o for o in prepared.objects if "shapegen_landmarks" in o}

    assert bpy.ops.shapegen.fit(wait=True, extra_settings=fast_fit_json()) == {"FINISHED"}
    assert "reusing 'vases Prepared'" in settings.job_message
    store = addon_module(extension, "shapegen_addon.store")
    model = store.get_model(bpy.context.scene)
    assert sorted(model.names) == sorted(o.name for o in collection.objects)
    for name in model.names:  # the model's meshes are exactly the prepared copies
        copy = copies[name]
        local = np.empty(len(copy.data.vertices) * 3)
        copy.data.vertices.foreach_get("co", local)
        np.testing.assert_allclose(model.meshes[model.shape_index(name)].vertices, local.reshape(-1, 3), atol=1e-6)

    settings.prepare.seed += 1  # other Prepare settings: not reused
    assert bpy.ops.shapegen.fit(wait=True, extra_settings=fast_fit_json()) == {"FINISHED"}
    assert "reusing" not in settings.job_message
    settings.prepare.seed -= 1
    source = sorted(collection.objects, key=lambda o: o.name)[2]
    source.data.vertices[0].co.z += 0.05  # an edit after Prepare: stale
    assert bpy.ops.shapegen.fit(wait=True, extra_settings=fast_fit_json()) == {"FINISHED"}
    assert "reusing" not in settings.job_message



def test_changing_only_the_model_type_reuses_the_correspondence(extension, jobs):
    """After a fit on a current Prepare, a fit that changes only the model part (type,
    latent dimension) starts from the scene's model's correspondence; other correspondence
    settings, or an edited shape, correspond again."""
    collection = add_vase_collection(extension)
    settings = bpy.context.scene.shapegen
    store = addon_module(extension, "shapegen_addon.store")
    settings.fit.model = "ppca"
    assert bpy.ops.shapegen.prepare(wait=True) == {"FINISHED"}
    assert bpy.ops.shapegen.fit(wait=True, extra_settings=fast_fit_json()) == {"FINISHED"}
    first = store.get_model(bpy.context.scene)
    assert "correspondence of model" not in settings.job_message

    settings.fit.model, settings.fit.latent_dim = "gplvm", 1  # and another run option: how a run is scheduled
    assert bpy.ops.shapegen.fit(wait=True, extra_settings=fast_fit_json(jobs=2)) == {"FINISHED"}
    assert "reusing 'vases Prepared' and the correspondence of model 'vases'" in settings.job_message
    second = store.get_model(bpy.context.scene)
    assert second.model_type == "gplvm" and second.latent_dim == 1
    np.testing.assert_array_equal(second.correspondence.points, first.correspondence.points)
    assert second.names == first.names

    other = fast_fit_json(correspondence={**json.loads(fast_fit_json())["correspondence"], "max_iterations": 5})
    assert bpy.ops.shapegen.fit(wait=True, extra_settings=other) == {"FINISHED"}
    assert "correspondence of model" not in settings.job_message
    sorted(collection.objects, key=lambda o: o.name)[1].data.vertices[0].co.z += 0.05  # Prepare is stale now
    assert bpy.ops.shapegen.fit(wait=True, extra_settings=other) == {"FINISHED"}
    assert "reusing" not in settings.job_message

def test_cancel_mid_fit_keeps_the_scene_and_the_earlier_model(extension, jobs, model_files):
    load_model("ppca", model_files)
    add_vase_collection(extension)
    settings = bpy.context.scene.shapegen
    earlier = settings.model_text
    earlier_id = earlier["shapegen_model_id"]
    texts_before = {t.name for t in bpy.data.texts}
    objects_before = {o.name for o in bpy.data.objects}
    slow = json.dumps({"jobs": 1, "correspondence": {"alpha_steps": 5, "max_iterations": 40, "groupwise_rounds": 2}})
    assert bpy.ops.shapegen.fit(extra_settings=slow) == {"FINISHED"}
    _pump(jobs, lambda s: s is not None and s.fraction > 0.0)  # the worker is busy
    assert bpy.ops.shapegen.fit_cancel() == {"FINISHED"}
    statuses, _ = _pump(jobs, lambda s: s is not None and s.finished, timeout=30)
    assert statuses[-1].state == "cancelled"
    assert settings.job_state == "CANCELLED"
    assert "cancelled" in settings.job_message and "earlier model is kept" in settings.job_message
    assert settings.model_text == earlier and earlier["shapegen_model_id"] == earlier_id
    assert {t.name for t in bpy.data.texts} == texts_before
    assert {o.name for o in bpy.data.objects} == objects_before
    assert not bpy.ops.shapegen.fit_cancel.poll() and bpy.ops.shapegen.fit.poll()


def test_a_killed_worker_becomes_a_one_line_report_and_the_scene_is_intact(extension, jobs):
    add_vase_collection(extension)
    settings = bpy.context.scene.shapegen
    manager = addon_module(extension, "shapegen_addon.jobs").MANAGER
    objects_before = {o.name for o in bpy.data.objects}
    assert bpy.ops.shapegen.fit(extra_settings=fast_fit_json()) == {"FINISHED"}
    _pump(jobs, lambda s: s is not None and s.fraction > 0.0)
    temporary = Path(manager.job.temporary_folder)
    os.kill(manager.job._process.pid, signal.SIGKILL)  # from outside, as the out-of-memory killer would
    statuses, _ = _pump(jobs, lambda s: s is not None and s.finished, timeout=30)
    assert statuses[-1].state == "failed"
    assert settings.job_state == "FAILED" and "\n" not in settings.job_message
    assert "the fit worker was killed by signal 9 (SIGKILL) during '" in settings.job_message
    assert "out of memory" in settings.job_message and "fewer parallel jobs" in settings.job_message
    assert "no model was made" in settings.job_message
    assert settings.model_text is None and len(bpy.data.texts) == 0
    assert {o.name for o in bpy.data.objects} == objects_before
    assert not temporary.exists()  # the worker's temporary folder (its spill store) went with it


def test_a_killed_registration_worker_names_its_shape(extension, jobs, monkeypatch):
    """A worker of the fit's registration pool killed (the test hook makes it SIGKILL itself
    on one shape): the job's message names the shape, the signal and fewer jobs."""
    pool = addon_module(extension, "core.correspond.pool")
    add_vase_collection(extension, n=3)
    settings = bpy.context.scene.shapegen
    victim = sorted(o.name for o in settings.source_collection.objects)[1]
    monkeypatch.setenv(pool.KILL_ON_SHAPE_VARIABLE, victim)  # inherited by the job's worker and its pool
    objects_before = {o.name for o in bpy.data.objects}
    assert bpy.ops.shapegen.fit(extra_settings=fast_fit_json(jobs=2)) == {"FINISHED"}
    statuses, _ = _pump(jobs, lambda s: s is not None and s.finished, timeout=120)
    assert statuses[-1].state == "failed" and settings.job_state == "FAILED"
    message = settings.job_message
    assert f"{victim}: the worker process working on it was killed by signal 9 (SIGKILL)" in message, message
    assert "out of memory" in message and "this run used 2" in message and "\n" not in message
    assert settings.model_text is None and {o.name for o in bpy.data.objects} == objects_before


def test_a_failing_fit_reports_the_workers_reason(extension, jobs):
    add_vase_collection(extension)
    settings = bpy.context.scene.shapegen
    settings.fit.latent_dim = 9  # more latent dimensions than the 6 shapes allow: the core refuses
    with pytest.raises(RuntimeError, match="latent dimension 9 must be smaller than the number of shapes"):
        bpy.ops.shapegen.fit(extra_settings=fast_fit_json(), wait=True)
    assert settings.job_state == "FAILED" and settings.model_text is None


def test_fit_refuses_bad_input_before_starting_a_worker(extension, jobs):
    manager = addon_module(extension, "shapegen_addon.jobs").MANAGER
    with pytest.raises(RuntimeError, match="Choose a training collection first"):
        bpy.ops.shapegen.fit()
    collection = add_vase_collection(extension, n=2)
    bpy.data.objects.remove(collection.objects[0])
    with pytest.raises(RuntimeError, match="has 1 mesh object"):
        bpy.ops.shapegen.fit()
    add_vase_collection(extension, n=3, name="more vases")
    with pytest.raises(RuntimeError, match="not a JSON object"):
        bpy.ops.shapegen.fit(extra_settings="[1, 2]")
    with pytest.raises(RuntimeError, match="Invalid fit settings.*unknown model"):
        bpy.ops.shapegen.fit(extra_settings='{"model": "nope"}')
    with pytest.raises(RuntimeError, match="Invalid fit settings"):
        bpy.ops.shapegen.fit(extra_settings='{"correspondence": {"no_such_option": 1}}')
    with pytest.raises(RuntimeError, match=r"Invalid fit settings: prepare\.n_landmarks must be at least 4, got 2"):
        bpy.ops.shapegen.fit(extra_settings='{"prepare": {"n_landmarks": 2}}')  # nested over the panel's
    with pytest.raises(RuntimeError, match="Invalid fit settings: jobs must be at least 1, got 0"):
        bpy.ops.shapegen.fit(extra_settings='{"jobs": 0}')  # a run option, checked as the core checks it
    with pytest.raises(RuntimeError, match="Invalid fit settings: FitSettings has no option 'seed'"):
        bpy.ops.shapegen.fit(extra_settings='{"seed": 2}')  # Prepare's options nest under "prepare"
    with pytest.raises(RuntimeError, match="No collection named 'missing'"):
        bpy.ops.shapegen.fit(collection_name="missing")
    assert not manager.running and bpy.context.scene.shapegen.job_state == "IDLE"


def test_the_polling_function_the_readme_names_exists(extension, jobs):
    """Scripts (timers never fire there) poll through the function the user guide names."""
    readme = (Path(__file__).resolve().parents[2] / "docs" / "user-guide.md").read_text()
    paths = re.findall(r"`(bl_ext\.user_default\.shapegen\.[\w.]+)\(\)`", readme)
    assert paths
    for path in paths:
        module, _, name = path.rpartition(".")
        poll = getattr(importlib.import_module(module), name)
        status = poll()  # nothing runs: the last status (or None), and no error
        assert status is None or status.finished
    assert any(p.endswith("shapegen_addon.fitting.poll_fit") for p in paths)  # the documented path stays


def test_cancel_without_a_job_explains_itself():
    with pytest.raises(RuntimeError, match="No background job is running"):
        bpy.ops.shapegen.fit_cancel()


def test_load_and_export_model_round_trip(extension, model_files, tmp_path):
    load_model("gplvm", model_files)
    text = bpy.context.scene.shapegen.model_text
    assert text.name == "vases_gplvm.shapegen" and text.use_fake_user
    assert text.as_string().startswith("ShapeGen model 'vases_gplvm'\ngplvm, 2 latent dimensions")
    assert text["shapegen_model_npz"] == model_files["gplvm"].read_bytes()
    out = tmp_path / "exported.npz"
    assert bpy.ops.shapegen.export_model(filepath=str(out)) == {"FINISHED"}
    assert out.read_bytes() == model_files["gplvm"].read_bytes()  # packed byte for byte
    # loading another model replaces the first and removes its now unused Text
    load_model("ppca", model_files)
    assert [t.name for t in bpy.data.texts] == ["vases_ppca.shapegen"]


def test_load_model_errors_are_clear(tmp_path):
    with pytest.raises(RuntimeError, match="no such model file"):
        bpy.ops.shapegen.load_model(filepath=str(tmp_path / "missing.npz"))
    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"not a zip file")
    with pytest.raises(RuntimeError, match="not a readable .npz file"):
        bpy.ops.shapegen.load_model(filepath=str(bad))
    assert bpy.context.scene.shapegen.model_text is None and len(bpy.data.texts) == 0
    with pytest.raises(RuntimeError, match="No fitted model in this scene"):
        bpy.ops.shapegen.export_model(filepath=str(tmp_path / "x.npz"))


def test_job_manager_setup_prepare_and_cancel_before_the_worker_starts(extension, tmp_path):
    """The bpy-free manager: a failing setup is a failed job, a cancel during setup stops
    the worker as soon as it starts, prepare's result reaches on_finish."""
    import threading

    jobs = addon_module(extension, "shapegen_addon.jobs")
    core_jobs = addon_module(extension, "core.app.jobs")
    manager = jobs.JobManager()
    finished = []

    def run(**options):
        job = core_jobs.BackgroundJob("selftest", {"steps": 20, "sleep": 0.05, "output": str(tmp_path / "out")})
        manager.start(job, lambda status, prepared: finished.append((status, prepared)), **options)

    def wait():
        deadline = time.monotonic() + 30
        while manager.running and time.monotonic() < deadline:
            manager.poll()
            time.sleep(0.01)
        assert not manager.running

    def boom():
        raise OSError("disk full")

    run(setup=boom)
    wait()
    assert finished[-1][0].state == "failed" and "disk full" in finished[-1][0].error

    gate = threading.Event()
    run(setup=lambda: gate.wait(10))
    assert manager.running and manager.poll().state == "running"
    manager.cancel()
    gate.set()
    wait()
    assert finished[-1][0].state == "cancelled"

    run(prepare=lambda status: (tmp_path / "out").read_text())
    wait()
    assert finished[-1][0].state == "done" and finished[-1][1] == "ok"


def test_poll_fit_after_a_file_load_says_cancelled(extension, jobs, tmp_path):
    """File › Open stops the running job; a script polling `poll_fit` sees it end."""
    add_vase_collection(extension)
    poll_fit = addon_module(extension, "shapegen_addon.fitting").poll_fit
    blend = tmp_path / "other.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(blend), copy=True)
    slow = json.dumps({"jobs": 1, "correspondence": {"alpha_steps": 5, "max_iterations": 40, "groupwise_rounds": 2}})
    assert bpy.ops.shapegen.fit(extra_settings=slow) == {"FINISHED"}
    _pump(jobs, lambda s: s is not None and s.fraction > 0.0, poll=poll_fit)
    bpy.ops.wm.open_mainfile(filepath=str(blend))
    status = poll_fit()
    assert status.finished and status.state == "cancelled"
    assert status.stage == "cancelled: a new file was loaded"
    assert not jobs.MANAGER.running and bpy.context.scene.shapegen.job_state == "IDLE"


def test_a_fit_whose_collection_was_deleted_installs_nothing(extension, jobs):
    collection = add_vase_collection(extension)
    settings = bpy.context.scene.shapegen
    settings.fit.model = "ppca"
    assert bpy.ops.shapegen.fit(extra_settings=fast_fit_json()) == {"FINISHED"}
    bpy.data.collections.remove(collection)
    statuses, _ = _pump(jobs, lambda s: s is not None and s.finished)
    assert statuses[-1].state == "done"  # the worker finished; its model is refused, as Prepare refuses
    assert settings.job_state == "FAILED" and "'vases' was deleted" in settings.job_message
    assert settings.model_text is None and len(bpy.data.texts) == 0


def test_ppca_on_two_shapes_says_what_to_do_in_the_panels_words(extension, jobs):
    add_vase_collection(extension, n=2)
    settings = bpy.context.scene.shapegen
    settings.fit.model, settings.fit.latent_dim = "ppca", 0
    with pytest.raises(RuntimeError, match=r"add training shapes or choose another Model \(gplvm or bgplvm\)"):
        bpy.ops.shapegen.fit(extra_settings=fast_fit_json(), wait=True)
    assert "shrinkage" not in settings.job_message


def test_installing_a_model_never_encodes_on_the_main_thread(extension, model_files, monkeypatch):
    """The worker encodes the training shapes and the model file keeps them: a fit's
    install, Load Model, Explore, Snap and Latent Map read them (no encode, which took
    1.8-2.8 s on the main thread for a Bayesian GP-LVM of 20 shapes)."""
    models = addon_module(extension, "core.models")
    fitting = addon_module(extension, "shapegen_addon.fitting")
    store = addon_module(extension, "shapegen_addon.store")
    encoded = []

    def refuse(model, *_args, **_kwargs):
        encoded.append(type(model).__name__)
        raise AssertionError("encoded on the main thread")

    for kind in ("ppca", "gplvm", "bgplvm"):
        monkeypatch.setattr(models.MODEL_TYPES[kind], "encode", refuse)
    scene = bpy.context.scene
    for kind, path in model_files.items():
        loaded = store.read_model_file(path)  # Fit's helper thread
        model = fitting.install_model(scene, path, f"vases {kind}", loaded)
        assert len(scene.shapegen.latents) == model.latent_dim  # sliders built without encoding
        load_model(kind, model_files)
        assert bpy.ops.shapegen.explore() == {"FINISHED"}
        assert bpy.ops.shapegen.explore_snap() == {"FINISHED"}
        assert bpy.ops.shapegen.latent_map(size=64) == {"FINISHED"}
    assert encoded == []
