"""One operator per user action. Operators convert Blender data, call the core, and turn
the result back into scene data; they hold no algorithm.

Data section:
* `SHAPEGEN_OT_import_collection` — a folder of mesh files → a new collection of mesh
  objects named after the files (Blender's own importers; OFF through the core reader).
* `SHAPEGEN_OT_prepare` — align, scale and landmark a collection (core.collection,
  thesis §3.4 / §4.2.1) into a new "<name> Prepared" collection; the user's objects are
  never modified.
"""

from __future__ import annotations

from pathlib import Path

import bpy
import numpy as np
from bpy.props import StringProperty
from mathutils import Matrix

from ..core.errors import ShapeGenError
from .convert import import_mesh_file, object_to_mesh
from .preview import (LANDMARK_BARYCENTRIC_KEY, LANDMARK_FACES_KEY, LANDMARK_RADIUS_KEY, LANDMARKS_KEY,
                      SOURCE_KEY, TRANSFORM_KEY, add_landmark_markers, grid_offsets)

__all__ = ["CLASSES"]

PREPARED_KEY = "shapegen_prepared"  # collection property: marks a prepared collection


def _unique_collection_name(base: str) -> str:
    if base not in bpy.data.collections:
        return base
    index = 1
    while f"{base}.{index:03d}" in bpy.data.collections:
        index += 1
    return f"{base}.{index:03d}"


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
        from ..core.io import list_mesh_files

        folder = Path(bpy.path.abspath(self.directory))
        try:
            files = list_mesh_files(folder)
        except ShapeGenError as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        if not files:
            self.report({"ERROR"}, f"{folder}: no mesh files found (.obj, .ply, .stl, .off, .glb, .gltf)")
            return {"CANCELLED"}

        collection = bpy.data.collections.new(_unique_collection_name(folder.name or "Training"))
        context.scene.collection.children.link(collection)
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


class SHAPEGEN_OT_prepare(bpy.types.Operator):
    """Align, scale and landmark the chosen collection into a new "Prepared" collection (originals untouched)"""

    bl_idname = "shapegen.prepare"
    bl_label = "Prepare"
    bl_options = {"REGISTER", "UNDO"}

    collection_name: StringProperty(
        name="Collection", default="",
        description="Collection to prepare (empty: the panel's chosen collection)",
    )

    @classmethod
    def poll(cls, context):
        settings = context.scene.shapegen
        if settings.source_collection is None:
            cls.poll_message_set("Choose a training collection first")
            return False
        return True

    def execute(self, context):
        from ..core.collection import prepare_meshes

        settings = context.scene.shapegen
        source = (bpy.data.collections.get(self.collection_name) if self.collection_name
                  else settings.source_collection)
        if source is None:
            self.report({"ERROR"}, f"No collection named '{self.collection_name}'")
            return {"CANCELLED"}
        objects = sorted(source.all_objects, key=lambda o: o.name)
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

        # 1. everything that can fail happens before the scene is touched
        wm = context.window_manager
        wm.progress_begin(0, 100)
        try:
            meshes = [object_to_mesh(o) for o in mesh_objects]
            prepared = prepare_meshes(
                meshes, n_landmarks=settings.n_landmarks, up_axis=settings.up_axis,
                align=settings.align, scale=settings.scale, centre=settings.centre,
                seed=settings.seed, progress=lambda f, msg: wm.progress_update(int(100 * f)),
            )
        except ShapeGenError as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        finally:
            wm.progress_end()
        for mesh in meshes:
            if mesh.report.summary() != "clean":
                self.report({"INFO"}, f"{mesh.name}: {mesh.report.summary()}")

        # 2. build the new collection: copies in the normalised frame, laid out on a grid
        target = bpy.data.collections.new(_unique_collection_name(f"{source.name} Prepared"))
        context.scene.collection.children.link(target)
        target[PREPARED_KEY] = True
        target["shapegen_source_collection"] = source.name
        for key, value in prepared.settings.items():
            target[f"shapegen_{key}"] = value
        size = max(float(np.ptp(s.mesh.vertices, axis=0).max()) for s in prepared.shapes)
        offsets = grid_offsets(len(prepared), settings.preview_spacing * size)
        for obj, shape, landmarks, offset in zip(mesh_objects, prepared.shapes, prepared.landmarks, offsets):
            data = obj.data.copy()
            data.name = f"{obj.name} prepared"
            data.transform(obj.matrix_world)  # input coordinates = the original's world frame
            data.transform(Matrix(shape.transform.matrix.tolist()))  # → normalised frame (object-local)
            copy = bpy.data.objects.new(f"{obj.name} prepared", data)
            copy.location = offset
            copy[SOURCE_KEY] = obj.name
            copy[TRANSFORM_KEY] = shape.transform.matrix.ravel().tolist()
            copy[LANDMARKS_KEY] = landmarks.points.ravel().tolist()
            # where each landmark lies on the (loop-triangulated) mesh, for correspondence
            copy[LANDMARK_FACES_KEY] = landmarks.face_index.tolist()
            copy[LANDMARK_BARYCENTRIC_KEY] = landmarks.barycentric.ravel().tolist()
            copy[LANDMARK_RADIUS_KEY] = float(landmarks.radius)
            target.objects.link(copy)
            add_landmark_markers(copy, landmarks.points, 0.25 * landmarks.radius, target)
        counts = [len(l) for l in prepared.landmarks]
        turned = sum(s.orientation_changed for s in prepared.shapes)
        self.report({"INFO"}, f"Prepared {len(prepared)} shapes into '{target.name}': "
                    f"{min(counts)}-{max(counts)} landmarks each, {turned} re-oriented by consensus")
        return {"FINISHED"}


CLASSES = (SHAPEGEN_OT_import_collection, SHAPEGEN_OT_prepare)
