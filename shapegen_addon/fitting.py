"""Fit in the background: collection → worker process → model packed into the .blend.

Flow:
1. `SHAPEGEN_OT_fit` (main thread) reads the collection's mesh objects' triangles
   (convert.object_triangles, world coordinates); a helper thread writes them as a
   "shapegen.meshes" .npz in a temporary folder, then starts the core's "fit" task in a worker process (core/worker.py,
   which never imports bpy) through `jobs.MANAGER`. Nothing in the scene changes yet.
2. `poll_fit()` polls the job (never blocks) and mirrors progress into
   `scene.shapegen.job_fraction` / `job_stage`. With a window a `bpy.app.timers` function
   calls it every 0.1 s and redraws the sidebar; headless (timers never fire) the caller
   loops over `poll_fit()` itself, or runs the operator with `wait=True`.
3. When the job ends, `_finish` runs on the main thread: on success the model file is
   loaded, packed into the .blend (store.py) and becomes the scene's model; on failure or
   cancel only `job_state` / `job_message` change, so the scene and any earlier model stay
   as they were, and the message says why.

Also here: Cancel, Load Model (.npz from the CLI or an export), Export Model.
"""

from __future__ import annotations

import json
import tempfile
import time
from pathlib import Path

import bpy
import numpy as np
from bpy.props import BoolProperty, StringProperty

from ..core.errors import ShapeGenError
from ..core.jobs import BackgroundJob, JobStatus
from ..core.meshset import save_mesh_set
from . import latent, store
from .convert import object_triangles
from .jobs import MANAGER
from .prepared import PREPARE_SETTINGS, prepare_options, reusable_prepared, to_prepared_collection

__all__ = ["CLASSES", "poll_fit", "fit_settings_dict", "unregister_timer"]

POLL_INTERVAL = 0.1


# ------------------------------------------------------------------------------ settings
def _merge(base: dict, extra: dict) -> dict:
    out = dict(base)
    for key, value in extra.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = _merge(out[key], value)
        else:
            out[key] = value
    return out


def fit_settings_dict(settings, extra: dict | None = None) -> dict:
    """The worker's FitSettings fields (JSON) from the panel's settings plus `extra`."""
    options = {
        **prepare_options(settings),
        "model": settings.fit_model, "latent_dim": settings.latent_dim or None,
        "correspondence": {"alpha_end": settings.stiffness, "alpha_start": max(100.0, settings.stiffness)},
        "deform": {"final_alpha": settings.mesh_stiffness, "start_alpha": max(100.0, settings.mesh_stiffness)},
    }
    return _merge(options, extra or {})


def _check_settings(options: dict) -> None:
    """Build FitSettings here too, so a bad setting is reported before a worker starts."""
    from ..core.pipeline import FitSettings

    try:
        FitSettings.from_dict(options)
    except (TypeError, ValueError) as exc:
        raise ShapeGenError(f"Invalid fit settings: {exc}") from None


def gather_meshes(objects) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """(name, vertices, triangles) of each object, world coordinates: bulk reads only
    (convert.object_triangles, ~4 ms per 100k vertices). The core's mesh validation runs
    in the worker, whose error names the object."""
    return [(o.name, *object_triangles(o)[:2]) for o in objects]


def save_meshes(meshes: list[tuple[str, np.ndarray, np.ndarray]], path: Path) -> Path:
    """Write `gather_meshes` output as a "shapegen.meshes" file (core.meshset). No bpy: runs
    on the job's setup thread. Uncompressed: it is a throwaway hand-off; compressing
    6 × 100k-vertex meshes took 1.5 s, this ~0.1 s."""
    return save_mesh_set(path, [name for name, _, _ in meshes], [v for _, v, _ in meshes],
                         [f for _, _, f in meshes], compress=False)


# ------------------------------------------------------------------------------ polling
def job_scene() -> bpy.types.Scene | None:
    """The scene the running (or last) job of `MANAGER` belongs to, if it still exists."""
    return bpy.data.scenes.get(MANAGER.payload.get("scene", ""))


def job_settings(status: JobStatus, job: str):
    """The ShapeGen settings of the ended job's scene, or None (and a console line naming
    `job`) when the user deleted that scene meanwhile."""
    scene = job_scene()
    if scene is None:
        print(f"ShapeGen: {job} ended ({status.state}) but its scene is gone")
        return None
    return scene.shapegen


def poll_fit() -> JobStatus | None:
    """Poll the running job once (main thread; never blocks on the worker). Mirrors the
    progress into the scene; the job's own callback applies the result when it has ended.
    Returns the status (None when no job ever ran in this process). Any job of
    `jobs.MANAGER` (a fit, or another section's) is polled the same way."""
    if not MANAGER.running:
        return MANAGER.last_status
    scene = job_scene()
    status = MANAGER.poll()
    if status is not None and not status.finished and scene is not None:
        settings = scene.shapegen
        settings.job_fraction = min(max(status.fraction, 0.0), 1.0)
        settings.job_stage = status.stage
    return status


def install_model(scene: bpy.types.Scene, path: str | Path, name: str, loaded=None):
    """The model file at `path` becomes the scene's model (store.store_fitted_model: packed
    into the .blend) and the latent sliders (and any live object) follow it."""
    model = store.store_fitted_model(scene, path, name, loaded)
    latent.model_changed(scene, model)
    return model


def _load_result(status: JobStatus):
    """prepare step of the fit job (helper thread, no bpy): load and validate the model."""
    if status.state != "done":
        return None
    return store.read_model_file(status.output)


def _finish(status: JobStatus, loaded) -> None:
    """on_finish of the fit job: called once, on the main thread, from poll_fit, with
    `_load_result`'s return value (or the exception it raised)."""
    payload = MANAGER.payload
    settings = job_settings(status, f"the fit of '{payload.get('name')}'")
    if settings is None:
        return
    seconds = time.monotonic() - MANAGER.started_at
    if status.state == "done":
        try:
            if isinstance(loaded, Exception):
                raise loaded
            model = install_model(settings.id_data, status.output, payload["name"], loaded)
        except (ShapeGenError, OSError) as exc:
            settings.job_state = "FAILED"
            settings.job_message = f"Fit finished but its model could not be loaded: {exc}"
        else:
            settings.job_state = "DONE"
            settings.job_fraction = 1.0
            settings.job_stage = "fitted"
            settings.job_message = (f"Fitted {model.model_type} to {len(model.names)} shapes of "
                                    f"'{payload['name']}': {model.latent_dim} latent dimensions, "
                                    f"{model.n_landmarks} landmarks ({seconds:.1f} s"
                                    + (f", reusing '{payload['reused']}')" if payload.get("reused") else ")"))
    elif status.state == "cancelled":
        settings.job_state = "CANCELLED"
        settings.job_message = "Fit cancelled; " + ("the earlier model is kept" if settings.model_text
                                                      else "no model was made")
    else:
        settings.job_state = "FAILED"
        settings.job_message = f"Fit failed: {status.error or 'unknown error'}; " + (
            "the earlier model is kept" if settings.model_text else "no model was made")
    level = "INFO" if settings.job_state == "DONE" else "ERROR" if settings.job_state == "FAILED" else "WARNING"
    print(f"ShapeGen: {settings.job_message}")
    _notify(settings.job_message, level)


def _notify(message: str, level: str) -> None:
    """A popup in the UI (a timer has no operator to report through)."""
    if bpy.app.background:
        return
    try:
        wm = bpy.context.window_manager
        icon = {"INFO": "INFO", "WARNING": "CANCEL", "ERROR": "ERROR"}[level]
        wm.popup_menu(lambda menu, _ctx: menu.layout.label(text=message), title="ShapeGen", icon=icon)
    except Exception as exc:  # no window to show it in: the panel still shows job_message
        print(f"ShapeGen: could not show a popup ({exc})")


def _redraw() -> None:
    wm = bpy.context.window_manager
    for window in getattr(wm, "windows", []):
        for area in window.screen.areas:
            if area.type == "VIEW_3D":
                area.tag_redraw()


def _timer() -> float | None:
    try:
        poll_fit()
    except Exception as exc:  # never let the timer die silently with a job still running
        print(f"ShapeGen: polling the fit failed: {exc}")
    _redraw()
    return POLL_INTERVAL if MANAGER.running else None


def start_polling() -> None:
    """Poll `jobs.MANAGER` from a timer while a job runs (UI only: timers never fire in
    background mode, where callers loop over `poll_fit()` themselves)."""
    if not bpy.app.background and not bpy.app.timers.is_registered(_timer):
        bpy.app.timers.register(_timer, first_interval=POLL_INTERVAL)


def no_job_running(operator_class) -> bool:
    """Operator poll part shared by Prepare, Find Correspondences and Fit: one background
    job at a time; says which one runs and how far it is."""
    if not MANAGER.running:
        return True
    status = MANAGER.last_status
    percent = int(100 * status.fraction) if status else 0
    operator_class.poll_message_set(f"A job is already running ({MANAGER.label}, {percent} %): "
                                    "wait for it or cancel it")
    return False


def chosen_collection(operator, name: str, settings):
    """The collection an operator works on: the one named `name`, else the panel's chosen
    training collection. None (reported on `operator`) when there is none."""
    collection = bpy.data.collections.get(name) if name else settings.source_collection
    if collection is None:
        operator.report({"ERROR"}, f"No collection named '{name}'" if name else "Choose a training collection first")
    return collection


def parse_extra_settings(text: str) -> dict:
    """The operators' "Extra Settings" JSON: an object, or empty. ValueError otherwise."""
    extra = json.loads(text) if text.strip() else {}
    if not isinstance(extra, dict):
        raise ValueError("not a JSON object")
    return extra


def run_worker_job(operator, settings, prefix: str, start, *, wait: bool, started: str) -> set[str]:
    """The shared tail of the operators that run core work in a worker (Fit, Find
    Correspondences): `start(folder)` writes the job's inputs into a fresh temporary folder
    and starts it on `MANAGER`; if that fails the folder is removed and the error reported.
    Then the job state is mirrored into `settings`, and the operator either blocks until
    the job has ended (`wait`: scripts and background mode, where timers never fire) or
    leaves it to the UI timer."""
    folder = Path(tempfile.mkdtemp(prefix=prefix))
    try:
        start(folder)
    except (ShapeGenError, OSError) as exc:
        import shutil

        shutil.rmtree(folder, ignore_errors=True)
        operator.report({"ERROR"}, str(exc))
        return {"CANCELLED"}
    settings.job_state = "RUNNING"
    settings.job_fraction = 0.0
    settings.job_stage = "starting"
    settings.job_message = ""
    if wait:
        status = MANAGER.last_status
        while MANAGER.running:
            status = poll_fit()
            time.sleep(0.05)
        if status is None or status.state != "done" or settings.job_state != "DONE":
            operator.report({"ERROR"}, settings.job_message)
            return {"CANCELLED"}
        operator.report({"INFO"}, settings.job_message)
        return {"FINISHED"}
    start_polling()
    operator.report({"INFO"}, started)
    return {"FINISHED"}


def unregister_timer() -> None:
    if bpy.app.timers.is_registered(_timer):
        bpy.app.timers.unregister(_timer)


# ------------------------------------------------------------------------------ operators
class SHAPEGEN_OT_fit(bpy.types.Operator):
    """Fit a generative shape model to the chosen collection in a background process
    (Blender stays usable; progress and Cancel in the Model panel)"""

    bl_idname = "shapegen.fit"
    bl_label = "Fit"
    bl_options = {"REGISTER"}

    collection_name: StringProperty(name="Collection", default="",
                                    description="Collection to fit (empty: the panel's chosen collection)")
    extra_settings: StringProperty(
        name="Extra Settings", default="",
        description='More FitSettings fields as JSON, e.g. {"jobs": 1, "correspondence": {"max_iterations": 10}}',
    )
    wait: BoolProperty(name="Wait", default=False, options={"SKIP_SAVE"},
                       description="Block until the fit ends (scripts and background mode)")

    @classmethod
    def poll(cls, context):
        if not no_job_running(cls):
            return False
        if context.scene.shapegen.source_collection is None:
            cls.poll_message_set("Choose a training collection first (Data panel)")
            return False
        return True

    def execute(self, context):
        scene = context.scene
        settings = scene.shapegen
        collection = chosen_collection(self, self.collection_name, settings)
        if collection is None:
            return {"CANCELLED"}
        objects = sorted((o for o in collection.all_objects if o.type == "MESH"), key=lambda o: o.name)
        if len(objects) < 2:
            self.report({"ERROR"}, f"Collection '{collection.name}' has {len(objects)} mesh object(s); "
                        "a shape model needs at least 2")
            return {"CANCELLED"}
        try:
            extra = parse_extra_settings(self.extra_settings)
        except ValueError as exc:
            self.report({"ERROR"}, f"Extra settings are not a JSON object: {exc}")
            return {"CANCELLED"}
        options = fit_settings_dict(settings, extra)
        reuse = reusable_prepared(collection, objects, options)

        def start(folder: Path) -> None:
            _check_settings(options)
            payload = {"scene": scene.name, "name": collection.name}
            if reuse is not None:  # Prepare's result is current: the worker starts at correspondence
                prepared = to_prepared_collection(reuse[1])
                prepared.settings = {k: options[k] for k in PREPARE_SETTINGS}
                inputs, payload["reused"] = {"prepared": str(folder / "prepared.npz")}, reuse[0].name
                setup = lambda: prepared.save(folder / "prepared.npz")  # noqa: E731
            else:
                gathered = gather_meshes(objects)
                inputs = {"meshes": str(folder / "meshes.npz")}
                setup = lambda: save_meshes(gathered, folder / "meshes.npz")  # noqa: E731
            job = BackgroundJob("fit", {**inputs, "settings": options, "output": str(folder / "model.npz")})
            MANAGER.start(job, _finish, label=f"fit '{collection.name}'", folder=folder,
                          payload=payload, prepare=_load_result, setup=setup)

        return run_worker_job(self, settings, "shapegen-fit-", start, wait=self.wait,
                              started=f"Fitting {len(objects)} shapes of '{collection.name}' in the background")


class SHAPEGEN_OT_fit_cancel(bpy.types.Operator):
    """Stop the running background job (Prepare, Find Correspondences or Fit); the scene and
    any earlier model stay as they are"""

    bl_idname = "shapegen.fit_cancel"
    bl_label = "Cancel"
    bl_options = {"REGISTER"}

    @classmethod
    def poll(cls, context):
        if not MANAGER.running:
            cls.poll_message_set("No background job is running")
            return False
        return True

    def execute(self, context):
        MANAGER.cancel()
        scene = job_scene()
        if scene is not None:
            scene.shapegen.job_stage = "cancelling"
        self.report({"INFO"}, f"Cancelling {MANAGER.label}")
        return {"FINISHED"}


class SHAPEGEN_OT_load_model(bpy.types.Operator):
    """Load a fitted model file (.npz from `shapegen fit` or Export Model) into this scene;
    it is packed into the .blend"""

    bl_idname = "shapegen.load_model"
    bl_label = "Load Model"
    bl_options = {"REGISTER", "UNDO"}

    filepath: StringProperty(name="File", subtype="FILE_PATH")
    filter_glob: StringProperty(default="*.npz", options={"HIDDEN"})

    @classmethod
    def poll(cls, context):
        if MANAGER.running:
            cls.poll_message_set("A fit is running: wait for it or cancel it")
            return False
        return True

    def invoke(self, context, event):
        context.window_manager.fileselect_add(self)
        return {"RUNNING_MODAL"}

    def execute(self, context):
        path = Path(bpy.path.abspath(self.filepath))
        if not path.is_file():
            self.report({"ERROR"}, f"{path}: no such model file")
            return {"CANCELLED"}
        try:
            model = install_model(context.scene, path, path.stem)
        except ShapeGenError as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        self.report({"INFO"}, f"Loaded {model.model_type} model '{path.stem}': {len(model.names)} shapes, "
                    f"{model.latent_dim} latent dimensions")
        return {"FINISHED"}


class SHAPEGEN_OT_export_model(store.NeedsModel, bpy.types.Operator):
    """Write the scene's packed model to a .npz file (for the `shapegen` command line)"""

    bl_idname = "shapegen.export_model"
    bl_label = "Export Model"
    bl_options = {"REGISTER"}

    filepath: StringProperty(name="File", subtype="FILE_PATH")
    filter_glob: StringProperty(default="*.npz", options={"HIDDEN"})

    def invoke(self, context, event):
        if not self.filepath:
            self.filepath = f"{bpy.path.clean_name(store.model_name(context.scene))}.npz"
        context.window_manager.fileselect_add(self)
        return {"RUNNING_MODAL"}

    def execute(self, context):
        if not self.filepath:
            self.report({"ERROR"}, "No file path given")
            return {"CANCELLED"}
        path = Path(bpy.path.abspath(self.filepath))
        try:
            path.write_bytes(store.model_bytes(context.scene.shapegen.model_text))
        except (OSError, ShapeGenError) as exc:
            self.report({"ERROR"}, f"{path}: {exc}")
            return {"CANCELLED"}
        self.report({"INFO"}, f"Wrote {path}")
        return {"FINISHED"}


CLASSES = (SHAPEGEN_OT_fit, SHAPEGEN_OT_fit_cancel, SHAPEGEN_OT_load_model, SHAPEGEN_OT_export_model)
