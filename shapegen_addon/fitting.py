"""The fit job outside its operators: what a Fit hands the worker, what its end does to the
scene, and `poll_fit`, the scripting entry point the README documents.

1. `plan_fit` asks core/app/stages.py which stages run (what Prepare and the scene's model
   offer); `fit_inputs` writes what the worker starts from: the model's correspondence,
   the prepared collection, or the objects' meshes (`gather_meshes` / `save_meshes`, main
   thread, then the job's setup thread) as a "shapegen.meshes" hand-off file.
2. `load_result` (helper thread, no bpy) loads and validates the model the worker wrote.
3. `finish` (main thread, from the job runtime's poll) installs it (`install_model`:
   packed into the .blend, sliders follow), or reports why not; the scene and any earlier
   model stay as they were on cancel or failure.
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable

import bpy
import numpy as np

from ..core.base.errors import ShapeGenError
from ..core.app.jobs import JobStatus
from ..core.meshes.meshset import save_mesh_set
from ..core.app.fit_settings import FitSettings
from ..core.app.stages import Offered, StagePlan, plan_stages, same_shapes
from . import latent, store
from .convert import object_triangles
from .jobs import MANAGER, job_settings, poll_job, report_outcome
from .keys import KEEP_POSE_KEY
from .prepared import offered_prepared

__all__ = ["check_fit_settings", "plan_fit", "fit_inputs", "gather_meshes", "save_meshes", "install_model", "load_result", "finish",
           "poll_fit"]


def poll_fit() -> JobStatus | None:
    """For scripts and `blender --background` (timers never fire there): poll the running
    job once (Fit, Prepare or Find Correspondences) and return its status, or None when no
    job has run. Loop until `status.finished`; the job's end is applied to the scene by
    this call, exactly as the UI timer would (`jobs.poll_job`)."""
    return poll_job()


def plan_fit(scene: bpy.types.Scene, collection, objects, options: dict, evaluated: bool) -> StagePlan:
    """Which stages a Fit of `objects` (the mesh objects of `collection`) with `options`
    (FitSettings as plain data) runs, decided by core.app.stages from what the scene offers:
    Prepare's results for the collection (prepared.offered_prepared) and the correspondence
    of the scene's model, current when its training shapes are exactly the reused prepared
    collection's (core.app.stages.same_shapes)."""
    offered = offered_prepared(collection, objects, evaluated)
    try:
        model = store.get_model(scene)
    except ShapeGenError:  # an unreadable model offers nothing to reuse; the fit replaces it
        model = None
    if model is not None:
        had = model.settings
        offered.append(Offered("correspond", f"the correspondence of model '{store.model_name(scene)}'",
                               prepare=had.prepare, correspondence=had.correspondence, template=had.template,
                               current=lambda prepared: same_shapes(model, prepared.data.core()), data=model))
    return plan_stages(FitSettings.from_dict(options), offered)


def fit_inputs(plan: StagePlan, settings, objects, evaluated: bool, folder: Path) -> tuple[dict, Callable]:
    """The fit task's inputs for `plan` (core/app/worker.py task_fit) and the bpy-free setup that
    writes them into `folder` on the job's helper thread: the scene's model (its
    correspondence is reused), the reused prepared collection, or the objects' meshes."""
    if "correspond" not in plan.run:  # only the model part changed: the worker fits the shape model alone
        data = store.model_bytes(settings.model_text)
        return {"correspondence_of": str(folder / "earlier.npz")}, lambda: (folder / "earlier.npz").write_bytes(data)
    reused = plan.reused_stage("prepare")
    if reused is not None:  # Prepare's result is current: the worker starts at correspondence
        prepared = reused.data.core()
        prepared.settings = plan.settings.prepare
        return {"prepared": str(folder / "prepared.npz")}, lambda: prepared.save(folder / "prepared.npz")
    gathered = gather_meshes(objects, evaluated)
    inputs = {"meshes": str(folder / "meshes.npz"), "keep_pose": [bool(o.get(KEEP_POSE_KEY, False)) for o in objects]}
    return inputs, lambda: save_meshes(gathered, folder / "meshes.npz")


def check_fit_settings(options: dict) -> None:
    """Refuse bad settings before a worker starts (a ShapeGenError names the option)."""
    FitSettings.from_dict(options)


def gather_meshes(objects, evaluated: bool = True) -> list[tuple[str, np.ndarray, np.ndarray, np.ndarray]]:
    """(name, vertices, triangles, the polygon of each triangle) of each object, world coordinates, read as Prepare reads
    them (`evaluated`: modifiers applied, else the base mesh; a mirrored object's winding
    reversed): bulk reads only (convert.object_triangles, ~4 ms per 100k vertices). The
    core's intake (welding, winding, validation) runs in the worker, whose error names the
    object."""
    depsgraph = bpy.context.evaluated_depsgraph_get()
    read = [object_triangles(o, evaluated=evaluated, depsgraph=depsgraph) for o in objects]
    return [(o.name, r.vertices, r.triangles, r.triangle_polygon) for o, r in zip(objects, read)]


def save_meshes(meshes: list[tuple[str, np.ndarray, np.ndarray, np.ndarray]], path: Path) -> Path:
    """Write `gather_meshes` output as a "shapegen.meshes" file (core.meshes.meshset). No bpy: runs
    on the job's setup thread. Uncompressed: it is a throwaway hand-off; compressing
    6 × 100k-vertex meshes took 1.5 s, this ~0.1 s."""
    return save_mesh_set(path, [m[0] for m in meshes], [m[1] for m in meshes], [m[2] for m in meshes],
                         compress=False, face_polygons=[m[3] for m in meshes])


def install_model(scene: bpy.types.Scene, path: str | Path, name: str, loaded=None):
    """The model file at `path` becomes the scene's model (store.store_fitted_model: packed
    into the .blend) and the latent sliders (and any live object) follow it."""
    model = store.store_fitted_model(scene, path, name, loaded)
    latent.model_changed(scene, model)
    return model


def load_result(status: JobStatus):
    """prepare step of the fit job (helper thread, no bpy): load and validate the model."""
    if status.state != "done":
        return None
    return store.read_model_file(status.output)


def finish(status: JobStatus, loaded) -> None:
    """on_finish of the fit job: called once, on the main thread, from the job runtime's
    poll, with `load_result`'s return value (or the exception it raised)."""
    payload = MANAGER.payload
    settings = job_settings(status, f"the fit of '{payload.get('name')}'")
    if settings is None:
        return
    kept = "the earlier model is kept" if settings.model_text else "no model was made"
    if status.state == "cancelled":
        report_outcome(settings, "CANCELLED", f"Fit cancelled; {kept}")
        return
    if status.state != "done":
        report_outcome(settings, "FAILED", f"Fit failed: {status.error or 'unknown error'}; {kept}")
        return
    if bpy.data.collections.get(payload["name"]) is None:  # as Prepare refuses: its shapes are gone
        report_outcome(settings, "FAILED", f"Fit finished but collection '{payload['name']}' was deleted "
                       f"meanwhile; {kept}")
        return
    try:
        if isinstance(loaded, Exception):
            raise loaded
        model = install_model(settings.id_data, status.output, payload["name"], loaded)
    except (ShapeGenError, OSError) as exc:
        report_outcome(settings, "FAILED", f"Fit finished but its model could not be loaded: {exc}")
        return
    reused = f", reusing {payload['reused']}" if payload.get("reused") else ""
    report_outcome(settings, "DONE", f"Fitted {model.model_type} to {len(model.names)} shapes of '{payload['name']}': "
                   f"{model.latent_dim} latent dimensions, {model.n_landmarks} landmarks "
                   f"({MANAGER.elapsed:.1f} s{reused})", "fitted")
