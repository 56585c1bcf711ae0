"""Correspondence section: "Find Correspondences" on a prepared collection (thesis §4.2).

The prepared shapes (from Prepare) are written to a temporary `.npz` and corresponded in
a background worker (core task "correspond", the same job manager as Fit: one job at a
time, progress in the panel, Cancel). The result is applied on the main thread: every
prepared object gets its corresponded landmarks (`shapegen_correspondence`, object-local
= normalised frame) and a child marker object whose colours encode the LANDMARK INDEX the
same way on every shape (colour of landmark i = position of template landmark i in the
template's bounding box, as RGB), so a user can judge correspondence by eye (thesis
Fig. 4.2–4.4): the same colour should sit on the same part of every shape.
"""

from __future__ import annotations

from pathlib import Path

import bpy
import numpy as np
from bpy.props import BoolProperty, StringProperty

from ..core.collection import PreparedCollection
from ..core.jobs import BackgroundJob, JobStatus
from ..core.landmarks import Landmarks
from ..core.preprocess import PreparedShape, ShapeTransform
from .convert import mesh_data_from_arrays, object_to_mesh
from .fitting import job_settings, no_job_running, parse_extra_settings, run_worker_job
from .jobs import MANAGER
from .preview import (LANDMARK_BARYCENTRIC_KEY, LANDMARK_FACES_KEY, LANDMARK_RADIUS_KEY, LANDMARKS_KEY,
                      TRANSFORM_KEY, marker_mesh_arrays)

__all__ = ["CLASSES", "prepared_objects", "landmark_index_colours"]

CORRESPONDENCE_KEY = "shapegen_correspondence"  # flat (L*3) corresponded landmarks, object-local
COLOUR_ATTRIBUTE = "landmark_index_colour"


def prepared_objects(collection: bpy.types.Collection) -> list[bpy.types.Object]:
    """The shape objects Prepare made (they carry landmarks and a transform), by name."""
    return sorted((o for o in collection.objects if LANDMARKS_KEY in o and TRANSFORM_KEY in o),
                  key=lambda o: o.name)


def prepared_collection_of(context) -> bpy.types.Collection | None:
    """The chosen collection if it is a prepared one, else its "<name> Prepared" sibling."""
    chosen = context.scene.shapegen.source_collection
    if chosen is None:
        return None
    if chosen.get("shapegen_prepared"):
        return chosen
    for collection in bpy.data.collections:
        if collection.get("shapegen_prepared") and collection.get("shapegen_source_collection") == chosen.name:
            return collection
    return None


def to_prepared_collection(objects) -> PreparedCollection:
    """Core data of prepared objects: their (normalised) meshes, transforms, landmarks."""
    shapes, landmarks = [], []
    for obj in objects:
        mesh = object_to_mesh(obj, world=False)
        mesh = mesh.with_vertices(mesh.vertices, name=obj.get("shapegen_source", obj.name))
        points = np.asarray(obj[LANDMARKS_KEY], dtype=np.float64).reshape(-1, 3)
        faces = np.asarray(obj.get(LANDMARK_FACES_KEY, []), dtype=np.int64)
        bary = np.asarray(obj.get(LANDMARK_BARYCENTRIC_KEY, []), dtype=np.float64).reshape(-1, 3)
        if len(faces) != len(points) or (len(faces) and faces.max() >= mesh.n_faces):
            # older Prepare results (or an edited mesh): put each landmark on its nearest face again
            from ..core.correspond import TargetSurface

            placed = TargetSurface(mesh.vertices, mesh.faces).closest(points)
            faces, bary = placed.face_index, placed.barycentric
        transform = ShapeTransform.from_matrix(np.asarray(obj[TRANSFORM_KEY], dtype=np.float64).reshape(4, 4))
        shapes.append(PreparedShape(mesh, transform))
        landmarks.append(Landmarks(points, faces, bary, float(obj.get(LANDMARK_RADIUS_KEY, 0.0))))
    return PreparedCollection(shapes, landmarks)


def landmark_index_colours(template_points: np.ndarray) -> np.ndarray:
    """RGBA per landmark index: the template landmark's position in its bounding box."""
    lo, hi = template_points.min(axis=0), template_points.max(axis=0)
    rgb = (template_points - lo) / np.maximum(hi - lo, 1e-12)
    return np.hstack([0.1 + 0.85 * rgb, np.ones((len(rgb), 1))]).astype(np.float32)


def add_correspondence_markers(parent: bpy.types.Object, points: np.ndarray, colours: np.ndarray,
                               radius: float) -> bpy.types.Object:
    """A child of `parent` with one octahedron per landmark, coloured by landmark index."""
    name = f"{parent.name} correspondence"
    old = bpy.data.objects.get(name)
    if old is not None:
        bpy.data.objects.remove(old)
    vertices, faces = marker_mesh_arrays(points, radius)
    data = mesh_data_from_arrays(name, vertices, faces)
    attribute = data.color_attributes.new(COLOUR_ATTRIBUTE, "FLOAT_COLOR", "POINT")
    attribute.data.foreach_set("color", np.repeat(colours, 6, axis=0).ravel())
    data.color_attributes.active_color = attribute
    markers = bpy.data.objects.new(name, data)
    markers.parent = parent
    markers.hide_select = True
    for collection in parent.users_collection:
        collection.objects.link(markers)
    return markers


# ------------------------------------------------------------------------------ job
def _load(status: JobStatus):
    if status.state != "done":
        return None
    from ..core.correspond import Correspondence

    return Correspondence.load(status.output)


def _finish(status: JobStatus, result) -> None:
    settings = job_settings(status, f"finding correspondences in '{MANAGER.payload.get('collection')}'")
    if settings is None:
        return
    collection = bpy.data.collections.get(MANAGER.payload.get("collection", ""))
    if status.state != "done" or isinstance(result, Exception) or collection is None:
        settings.job_state = "CANCELLED" if status.state == "cancelled" else "FAILED"
        reason = (str(result) if isinstance(result, Exception) else status.error
                  or ("the prepared collection is gone" if collection is None else status.state))
        settings.job_message = f"Find Correspondences {status.state}: {reason}; nothing was changed"
        print(f"ShapeGen: {settings.job_message}")
        return
    objects = {o.get("shapegen_source", o.name): o for o in prepared_objects(collection)}
    colours = landmark_index_colours(result.template_points)
    radius = 0.006 * float(np.linalg.norm(np.ptp(result.template_points, axis=0)))
    for name, points, outlier in zip(result.names, result.points, result.outliers):
        obj = objects.get(name)
        if obj is None:
            continue
        obj[CORRESPONDENCE_KEY] = points.ravel().tolist()
        obj["shapegen_correspondence_outlier"] = bool(outlier)
        add_correspondence_markers(obj, points, colours, radius)
        landmark_markers = bpy.data.objects.get(f"{obj.name} landmarks")
        if landmark_markers is not None:
            landmark_markers.hide_viewport = True
            landmark_markers.hide_render = True
    collection["shapegen_correspondence_template"] = result.template_name
    outliers = [n for n, o in zip(result.names, result.outliers) if o]
    settings.job_state = "DONE"
    settings.job_fraction = 1.0
    settings.job_stage = "corresponded"
    settings.job_message = (f"Corresponded {len(result.names)} shapes x {result.n_landmarks} landmarks "
                            f"(template {result.template_name}); "
                            + (f"outliers: {', '.join(outliers)}" if outliers else "no outliers"))
    print(f"ShapeGen: {settings.job_message}")


class SHAPEGEN_OT_find_correspondences(bpy.types.Operator):
    """Find dense corresponding landmarks across the prepared collection (non-rigid ICP, in the background)"""

    bl_idname = "shapegen.find_correspondences"
    bl_label = "Find Correspondences"
    bl_options = {"REGISTER"}

    wait: BoolProperty(name="Wait", default=False, options={"SKIP_SAVE"},
                       description="Block until the job ends (scripts and background mode)")
    extra_settings: StringProperty(
        name="Extra Settings", default="",
        description='More CorrespondenceSettings fields as JSON, e.g. {"groupwise_rounds": 0}',
    )

    @classmethod
    def poll(cls, context):
        if not no_job_running(cls):
            return False
        if prepared_collection_of(context) is None:
            cls.poll_message_set("Prepare the chosen collection first (Data panel)")
            return False
        return True

    def execute(self, context):
        collection = prepared_collection_of(context)
        objects = prepared_objects(collection)
        if len(objects) < 2:
            self.report({"ERROR"}, f"'{collection.name}' has {len(objects)} prepared shape(s); need at least 2")
            return {"CANCELLED"}
        settings = context.scene.shapegen
        options = {"alpha_end": settings.stiffness, "alpha_start": max(100.0, settings.stiffness)}
        try:
            options.update(parse_extra_settings(self.extra_settings))
            from ..core.correspond import CorrespondenceSettings

            CorrespondenceSettings(**options)  # a bad setting is reported before a worker starts
        except (TypeError, ValueError) as exc:
            self.report({"ERROR"}, f"Invalid correspondence settings: {exc}")
            return {"CANCELLED"}
        def start(folder: Path) -> None:
            to_prepared_collection(objects).save(folder / "prepared.npz")
            job = BackgroundJob("correspond", {"prepared": str(folder / "prepared.npz"), "settings": options,
                                               "output": str(folder / "correspondence.npz")})
            MANAGER.start(job, _finish, label=f"correspond '{collection.name}'", folder=folder,
                          payload={"scene": context.scene.name, "collection": collection.name}, prepare=_load)

        return run_worker_job(self, settings, "shapegen-correspond-", start, wait=self.wait,
                              started=f"Finding correspondences across {len(objects)} shapes in the background")


CLASSES = (SHAPEGEN_OT_find_correspondences,)
