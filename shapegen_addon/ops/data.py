"""Data section. Operators convert Blender data, call the core, and turn the result back
into scene data; they hold no algorithm.

* `SHAPEGEN_OT_import_collection` — a folder of mesh files → a new collection of mesh
  objects named after the files (Blender's own importers; OFF through the core reader).
* `SHAPEGEN_OT_prepare` — align, scale and landmark a collection (core.preprocess.collection,
  thesis §3.4 / §4.2.1) into a new "<name> Prepared" collection; the user's objects are
  never modified. Meshes are read here as the artist sees them (modifiers applied, unless
  the panel's Base Mesh is on; a mirrored object's winding reversed) and cleaned by the
  core's intake (welded, wound outwards); the slow part runs in a worker (core.app.worker
  "prepare") through `jobs.MANAGER`, like Find Correspondences and Fit. Objects flagged
  Keep Pose (keys.KEEP_POSE_KEY) are never turned; the message names the turned and the
  flagged shapes.
* `SHAPEGEN_OT_toggle_keep_pose` — flip the active object's Keep Pose flag.
* `SHAPEGEN_OT_turn_flagged` — turn the prepared copies Prepare flagged (it never turns a
  shape on doubtful evidence) as their flags suggest, in one undo step.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import bpy
from bpy.props import StringProperty

from ...core.preprocess.collection import PrepareSettings
from ...core.base.errors import ShapeGenError
from ...core.app.jobs import BackgroundJob, JobStatus
from ...core.meshes.meshset import save_mesh_set
from ..convert import evaluated_depsgraph, import_mesh_file, read_object, world_mesh_copy
from ..exclusion import training_objects
from ..jobs import MANAGER, JobOperator, job_settings, report_outcome
from ..keys import KEEP_POSE_KEY
from ..prepared import (PREPARE_SETTINGS, build_prepared_collection, flagged_copies, has_correspondence,
                        prepared_collection_for, turn_flagged_copies)
from ..preview import new_collection

__all__ = ["CLASSES"]

class SHAPEGEN_OT_import_collection(bpy.types.Operator):
    """Import every mesh file of a folder into a new collection (one object per file)"""

    bl_idname = "shapegen.import_collection"
    bl_label = "Import Training Collection"
    bl_options = {"REGISTER", "UNDO"}

    directory: StringProperty(name="Folder", subtype="DIR_PATH",
                              description="Folder of .obj, .ply, .stl, .off, .glb or .gltf files")
    filter_folder: bpy.props.BoolProperty(default=True, options={"HIDDEN"})

    def invoke(self, context, event):
        context.window_manager.fileselect_add(self)
        return {"RUNNING_MODAL"}

    def execute(self, context):
        from ...core.meshes.reading import list_mesh_files

        folder = Path(bpy.path.abspath(self.directory))
        try:
            files = list_mesh_files(folder)
        except ShapeGenError as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        if not files:
            self.report({"ERROR"}, f"{folder}: no mesh files found (.obj, .ply, .stl, .off, .glb, .gltf)")
            return {"CANCELLED"}

        collection = new_collection(context.scene, folder.name or "Training")
        imported, failures = [], []
        wm = context.window_manager
        wm.progress_begin(0, len(files))
        try:
            for index, path in enumerate(files):
                try:
                    imported.append(import_mesh_file(path, collection))
                except ShapeGenError as exc:
                    failures.append(str(exc))
                wm.progress_update(index + 1)
        finally:
            wm.progress_end()
        if not imported:
            bpy.data.collections.remove(collection)
            self.report({"ERROR"}, f"{folder}: no file could be imported: " + "; ".join(failures))
            return {"CANCELLED"}
        for message in failures:
            self.report({"WARNING"}, message)
        context.scene.shapegen.source_collection = collection
        context.scene.shapegen.last_import_directory = str(folder)
        self.report({"INFO"}, f"Imported {len(imported)} of {len(files)} file(s) into '{collection.name}'")
        return {"FINISHED"}


# ------------------------------------------------------------------------------ prepare
def _load_prepared(status: JobStatus):
    """prepare step of the job (helper thread, no bpy): load and validate the result."""
    if status.state != "done":
        return None
    from ...core.preprocess.collection import PreparedCollection

    return PreparedCollection.load(status.output)


def _finish_prepare(status: JobStatus, prepared) -> None:
    """on_finish of the prepare job (main thread, once): build the prepared collection, or
    say why not. Nothing is created when the job failed or was cancelled, or when the
    user deleted or edited a source object while it ran."""
    payload = MANAGER.payload
    settings = job_settings(status, f"preparing '{payload.get('source')}'")
    if settings is None:
        return
    source = bpy.data.collections.get(payload.get("source", ""))
    names = payload.get("objects", [])
    objects = [bpy.data.objects.get(name) for name in names]
    failed = status.state != "done" or isinstance(prepared, Exception) or source is None
    world_meshes, changed = [], []
    if not failed:
        changed = [name for name, obj in zip(names, objects) if obj is None or obj.type != "MESH"]
        if not changed:  # each object as read now, as Prepare read it: its vertex count must be the same
            depsgraph = evaluated_depsgraph(settings.id_data)
            world_meshes = [world_mesh_copy(obj, f"{obj.name} prepared", payload["evaluated"], depsgraph, flips)
                            for obj, flips in zip(objects, payload["reversed_polygons"])]
            changed = [name for name, data, count in zip(names, world_meshes, payload["vertex_counts"])
                       if len(data.vertices) != count]
    if failed or changed:
        for data in world_meshes:
            bpy.data.meshes.remove(data)
        reason = (str(prepared) if isinstance(prepared, Exception) else status.error if status.state != "done"
                  else f"collection '{payload.get('source')}' was deleted" if source is None
                  else f"object(s) deleted or edited while preparing: {', '.join(changed)}")
        report_outcome(settings, "CANCELLED" if status.state == "cancelled" else "FAILED",
                       f"Prepare {status.state}: {reason or status.state}; nothing was created")
        return
    target = build_prepared_collection(settings.id_data, source, objects, prepared, settings.prepare.preview_spacing,
                                       world_meshes, payload["evaluated"])
    counts = [len(l) for l in prepared.landmarks]
    for line in prepared.pose_notes():
        print(f"ShapeGen: {line}")
    read = "meshes as the viewport shows them (modifiers applied)" if payload["evaluated"] else \
        "base meshes (modifiers ignored)"
    report_outcome(settings, "DONE", f"Prepared {len(prepared)} shapes into '{target.name}' from their {read}: "
                   f"{min(counts)}-{max(counts)} landmarks each, " + _pose_summary(prepared)
                   + _intake_notes(payload["notes"])
                   + (f"; {payload['triangulated']}" if payload["triangulated"] else ""), "prepared")
    if not bpy.app.background and not payload.get("wait"):
        _push_undo_step("ShapeGen Prepare")  # after the outcome, so the step holds it


def _pose_summary(prepared, shown: int = 4) -> str:
    """'2 turned (A, B), 1 flagged (C)': the shapes whose pose Prepare changed and those
    whose pose looks wrong, the first `shown` of each by name (reasons: the Data panel)."""
    def named(names: list[str]) -> str:
        if not names:
            return ""
        more = f" and {len(names) - shown} more" if len(names) > shown else ""
        return f" ({', '.join(names[:shown])}{more})"

    turned = [s.name for s in prepared.shapes if s.pose_change]
    flagged = [s.name for s in prepared.shapes if s.pose_outlier]
    return f"{len(turned)} turned{named(turned)}, {len(flagged)} flagged{named(flagged)}"


def _intake_changes(meshes) -> dict[str, str]:
    """{object name: what intake changed} for the meshes it changed beyond triangulating
    polygons (Mesh.report.summary without that part: `_triangulation_line` says it once)."""
    notes = {m.name: replace(m.report, polygons_triangulated=0, triangles_from_polygons=0).summary()
             for m in meshes}
    return {name: note for name, note in notes.items() if note != "clean"}


def _triangulation_line(meshes) -> str:
    """One line for the whole Prepare: how many polygons of how many objects were
    triangulated (quads and n-gons are normal input), or "" when none was."""
    split = [m.report for m in meshes if m.report.polygons_triangulated]
    if not split:
        return ""
    return (f"Triangulated {sum(r.polygons_triangulated for r in split)} polygon(s) of {len(split)} object(s) into "
            f"{sum(r.triangles_from_polygons for r in split)} triangles")


def _intake_notes(notes: dict[str, str], shown: int = 4) -> str:
    """'; intake: A: mirrored ...; B: ...' for the objects whose meshes the core changed on
    reading (Mesh.report.summary), the first `shown` of them by name."""
    if not notes:
        return ""
    listed = "; ".join(f"{name}: {note}" for name, note in list(notes.items())[:shown])
    more = f"; and {len(notes) - shown} more (see the Info log)" if len(notes) > shown else ""
    return f"; intake: {listed}{more}"


def _push_undo_step(message: str) -> None:
    """An undo step for a change made after the operator returned (from the job timer,
    which has no window in its context: borrow the first one)."""
    windows = list(getattr(bpy.context.window_manager, "windows", []))
    try:
        if windows:
            with bpy.context.temp_override(window=windows[0], screen=windows[0].screen):
                bpy.ops.ed.undo_push(message=message)
        else:
            bpy.ops.ed.undo_push(message=message)
    except RuntimeError as exc:
        print(f"ShapeGen: no undo step for '{message}' ({exc})")


def _check_prepare_options(options: dict) -> None:
    unknown = sorted(set(options) - set(PREPARE_SETTINGS))
    if unknown:
        raise ValueError(f"unknown option(s) {', '.join(unknown)} (known: {', '.join(PREPARE_SETTINGS)})")
    PrepareSettings.from_dict(options)


class SHAPEGEN_OT_prepare(JobOperator, bpy.types.Operator):
    """Align, scale and landmark the chosen collection into a new "Prepared" collection, in
    the background (originals untouched; progress and Cancel in the panel). Your up axis and
    poses are trusted: a shape is turned only when it clearly lies on another axis of its
    file or faces another way; a doubtful one is flagged and left as it is"""

    bl_idname = "shapegen.prepare"
    bl_label = "Prepare"
    bl_options = {"REGISTER", "UNDO"}
    job_name = "prepare"

    def execute(self, context):
        settings = context.scene.shapegen
        source = self.chosen_collection(context)
        if source is None:
            return {"CANCELLED"}
        objects = training_objects(source)
        mesh_objects = [o for o in objects if o.type == "MESH"]
        skipped = [o.name for o in objects if o.type != "MESH"]
        if skipped:
            self.report({"WARNING"}, f"Skipped {len(skipped)} non-mesh object(s): {', '.join(skipped)}")
        if not mesh_objects:
            self.report({"ERROR"}, f"Collection '{source.name}' has no mesh objects to prepare")
            return {"CANCELLED"}
        if len(mesh_objects) < 2:
            self.report({"ERROR"}, f"Collection '{source.name}' has only one mesh object "
                        f"('{mesh_objects[0].name}'); a shape model needs at least 2")
            return {"CANCELLED"}

        # 1. read and clean here (bulk reads, fast): a bad object is named at once and
        #    the scene is never touched; the slow part (alignment, landmarks) runs in a worker
        evaluated = not settings.prepare.use_base_mesh
        depsgraph = context.evaluated_depsgraph_get()
        try:
            readings = [read_object(o, evaluated=evaluated, depsgraph=depsgraph) for o in mesh_objects]
        except ShapeGenError as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        meshes = [r.mesh for r in readings]
        notes = _intake_changes(meshes)
        for name, note in notes.items():
            self.report({"INFO"}, f"{name}: {note}")
        triangulated = _triangulation_line(meshes)
        if triangulated:
            self.report({"INFO"}, triangulated)
        checked = self.job_options(settings.prepare_options(), _check_prepare_options)
        if checked is None:
            return {"CANCELLED"}
        options, run = checked
        payload = {"scene": context.scene.name, "source": source.name, "objects": [o.name for o in mesh_objects],
                   "vertex_counts": [r.n_vertices for r in readings], "evaluated": evaluated,
                   "reversed_polygons": [r.reversed_polygons for r in readings], "notes": notes,
                   "triangulated": triangulated, "wait": self.wait}
        keep_pose = [bool(o.get(KEEP_POSE_KEY, False)) for o in mesh_objects]

        # 2. the worker; `_finish_prepare` builds the collection on the main thread
        def start(folder: Path) -> None:
            mesh_file = folder / "meshes.npz"
            job = BackgroundJob("prepare", {"meshes": str(mesh_file), "settings": options, "keep_pose": keep_pose,
                                            **run, "output": str(folder / "prepared.npz")})
            MANAGER.start(job, _finish_prepare, label=f"prepare '{source.name}'", folder=folder, payload=payload,
                          prepare=_load_prepared,
                          setup=lambda: save_mesh_set(mesh_file, [m.name for m in meshes], [m.vertices for m in meshes],
                                                      [m.faces for m in meshes], compress=False))

        return self.run_job(context, start, started=f"Preparing {len(meshes)} shapes of '{source.name}' in the background")


class SHAPEGEN_OT_toggle_keep_pose(bpy.types.Operator):
    """Keep the active object's pose when preparing (never turned beyond the Up Axis; still
    flagged when its pose looks wrong), or let consensus turn it again"""

    bl_idname = "shapegen.toggle_keep_pose"
    bl_label = "Keep Pose"
    bl_options = {"REGISTER", "UNDO"}

    @classmethod
    def poll(cls, context):
        return context.active_object is not None and context.active_object.type == "MESH"

    def execute(self, context):
        obj = context.active_object
        obj[KEEP_POSE_KEY] = not obj.get(KEEP_POSE_KEY, False)
        self.report({"INFO"}, f"'{obj.name}': pose {'kept' if obj[KEEP_POSE_KEY] else 'left to consensus'} "
                              "when preparing")
        return {"FINISHED"}


class SHAPEGEN_OT_turn_flagged(bpy.types.Operator):
    """Turn the prepared shapes whose pose Prepare doubted (upside down, on a side) as the
    flag suggests. Your own objects are not changed"""

    bl_idname = "shapegen.turn_flagged"
    bl_label = "Turn Flagged"
    bl_options = {"REGISTER", "UNDO"}

    @classmethod
    def poll(cls, context):
        return bool(flagged_copies(prepared_collection_for(context.scene.shapegen.source_collection)))

    def execute(self, context):
        collection = prepared_collection_for(context.scene.shapegen.source_collection)
        if has_correspondence(collection):
            self.report({"ERROR"}, f"'{collection.name}' already has correspondences: Prepare again, then Turn "
                                   "Flagged before Find Correspondences")
            return {"CANCELLED"}
        try:
            turned = turn_flagged_copies(collection)
        except ShapeGenError as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        self.report({"INFO"}, f"Turned {len(turned)} flagged shape(s) of '{collection.name}': {', '.join(turned)}")
        return {"FINISHED"}


CLASSES = (SHAPEGEN_OT_import_collection, SHAPEGEN_OT_prepare, SHAPEGEN_OT_toggle_keep_pose,
           SHAPEGEN_OT_turn_flagged)
