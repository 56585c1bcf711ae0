"""The prepared-object format: what Prepare writes into the scene, and what Find
Correspondences and Fit read back. Written and read here only.

A prepared collection ("<source> Prepared", keys.PREPARED_KEY) records its source
collection and the Prepare settings it was made with (one JSON string). Each prepared shape object is a
copy of a user's object as Prepare read it (the evaluated mesh, or the base mesh when the
panel asks; keys.MESH_SOURCE_KEY says which) in the normalised frame (object-local), wound
outwards like the core's Mesh, tagged with its source's name, the transform input (world)
-> normalised, its pose report (the turn Prepare applied and why, why its pose looks
wrong), its landmarks and where they lie on the mesh (face and barycentrics, so
correspondence starts from them), plus a child marker object. Find Correspondences adds the
corresponded landmarks and index-coloured markers.
"""

from __future__ import annotations

from dataclasses import fields

import bpy
import numpy as np
from mathutils import Matrix

from ..core.preprocess.collection import PrepareSettings, PreparedCollection, pose_notes
from ..core.preprocess.landmarks import Landmarks
from ..core.preprocess import PreparedShape, ShapeTransform
from ..core.base.settings import SettingsError
from ..core.app.stages import Offered
from .convert import object_to_mesh, object_triangles
from .keys import (CORRESPONDENCE_KEY, CORRESPONDENCE_OUTLIER_KEY, CORRESPONDENCE_TEMPLATE_KEY, FLAG_TURN_KEY,
                   KEEP_POSE_KEY,
                   LANDMARK_BARYCENTRIC_KEY, LANDMARK_FACES_KEY, LANDMARK_RADIUS_KEY, LANDMARKS_KEY, MESH_SOURCE_KEY,
                   POSE_CHANGE_KEY, POSE_OUTLIER_KEY, POSE_ROTATION_KEY, PREPARE_SETTINGS_KEY, PREPARED_KEY,
                   SOURCE_COLLECTION_KEY, SOURCE_KEY, TRANSFORM_KEY, mesh_source)
from .placement import grid_offsets, place, vertex_box
from .preview import add_correspondence_markers, add_landmark_markers, landmark_index_colours, new_collection

__all__ = ["PREPARE_SETTINGS", "build_prepared_collection", "prepared_objects", "prepared_collection_for",
           "recorded_prepare_settings", "to_prepared_collection", "PreparedCopies", "offered_prepared",
           "apply_correspondence",
           "prepared_pose_notes", "turn_flagged_copies", "has_correspondence", "flagged_copies"]

#: the Prepare settings a prepared collection records (Fit reuses it only when they match)
PREPARE_SETTINGS = tuple(f.name for f in fields(PrepareSettings))


# ------------------------------------------------------------------------------ write
def build_prepared_collection(scene: bpy.types.Scene, source: bpy.types.Collection, objects,
                              prepared: PreparedCollection, preview_spacing: float, world_meshes,
                              evaluated: bool) -> bpy.types.Collection:
    """A new "<source> Prepared" collection: copies of `objects` in the normalised frame
    (object-local), laid out on a grid beside the scene's objects (placement.place), each
    tagged with its transform, pose report, landmarks and mesh source, plus landmark markers.
    `world_meshes` are the objects' meshes as Prepare read them (convert.world_mesh_copy,
    world coordinates, evaluated or not); they become the copies' data. The user's objects
    are not modified."""
    boxes = [vertex_box(s.mesh.vertices) for s in prepared.shapes]
    size = max(float(np.ptp(box, axis=0).max()) for box in boxes)
    locations = place(scene, boxes, grid_offsets(len(prepared), preview_spacing * size))
    target = new_collection(scene, f"{source.name} Prepared")
    target[PREPARED_KEY] = True
    target[SOURCE_COLLECTION_KEY] = source.name
    if prepared.settings is not None:
        target[PREPARE_SETTINGS_KEY] = prepared.settings.to_json()
    for obj, data, shape, landmarks, location in zip(objects, world_meshes, prepared.shapes, prepared.landmarks,
                                                     locations):
        data.name = f"{obj.name} prepared"
        data.transform(Matrix(shape.transform.matrix.tolist()))  # world (input) → normalised frame (object-local)
        copy = bpy.data.objects.new(f"{obj.name} prepared", data)
        copy.location = location
        copy[SOURCE_KEY] = obj.name
        copy[MESH_SOURCE_KEY] = mesh_source(evaluated)
        copy[TRANSFORM_KEY] = shape.transform.matrix.ravel().tolist()
        copy[KEEP_POSE_KEY] = bool(obj.get(KEEP_POSE_KEY, False))  # as Prepare was told
        copy[POSE_CHANGE_KEY] = shape.pose_change
        copy[POSE_ROTATION_KEY] = np.asarray(shape.pose_rotation).ravel().tolist()
        copy[POSE_OUTLIER_KEY] = shape.pose_outlier
        if shape.flag_turn is not None:
            copy[FLAG_TURN_KEY] = np.asarray(shape.flag_turn).ravel().tolist()
        copy[LANDMARKS_KEY] = landmarks.points.ravel().tolist()
        # where each landmark lies on the (loop-triangulated) mesh, for correspondence
        copy[LANDMARK_FACES_KEY] = landmarks.face_index.tolist()
        copy[LANDMARK_BARYCENTRIC_KEY] = landmarks.barycentric.ravel().tolist()
        copy[LANDMARK_RADIUS_KEY] = float(landmarks.radius)
        target.objects.link(copy)
        add_landmark_markers(copy, landmarks.points, 0.25 * landmarks.radius, target)
    return target


def apply_correspondence(collection: bpy.types.Collection, result) -> None:
    """Tag every prepared object of `collection` with its corresponded landmarks (a core
    `Correspondence`, object-local), why it is an outlier ("" when it fits) and
    index-coloured markers; its Prepare landmark markers are hidden."""
    objects = {o.get(SOURCE_KEY, o.name): o for o in prepared_objects(collection)}
    colours = landmark_index_colours(result.template_points)
    radius = 0.006 * float(np.linalg.norm(np.ptp(result.template_points, axis=0)))
    for name, points, outlier, reason in zip(result.names, result.points, result.outliers, result.outlier_reasons):
        obj = objects.get(name)
        if obj is None:
            continue
        obj[CORRESPONDENCE_KEY] = points.ravel().tolist()
        obj[CORRESPONDENCE_OUTLIER_KEY] = (reason or "outlier") if outlier else ""
        add_correspondence_markers(obj, points, colours, radius)
        landmark_markers = bpy.data.objects.get(f"{obj.name} landmarks")
        if landmark_markers is not None:
            landmark_markers.hide_viewport = True
            landmark_markers.hide_render = True
    collection[CORRESPONDENCE_TEMPLATE_KEY] = result.template_name


# ------------------------------------------------------------------------------ read
def prepared_objects(collection: bpy.types.Collection) -> list[bpy.types.Object]:
    """The shape objects Prepare made (they carry landmarks and a transform), by name."""
    return sorted((o for o in collection.objects if LANDMARKS_KEY in o and TRANSFORM_KEY in o),
                  key=lambda o: o.name)


def prepared_collection_for(collection: bpy.types.Collection | None) -> bpy.types.Collection | None:
    """`collection` if it is a prepared one, else its newest "<name> Prepared" sibling
    (the last by name, as Fit offers them; None when there is none)."""
    if collection is None:
        return None
    if collection.get(PREPARED_KEY):
        return collection
    siblings = [c for c in bpy.data.collections
                if c.get(PREPARED_KEY) and c.get(SOURCE_COLLECTION_KEY) == collection.name]
    return max(siblings, key=lambda c: c.name, default=None)


def recorded_prepare_settings(collection: bpy.types.Collection) -> PrepareSettings | None:
    """The Prepare settings a prepared collection records (None: none recorded, e.g. by
    the per-setting keys of collections prepared before they were one JSON string, or
    unreadable)."""
    text = collection.get(PREPARE_SETTINGS_KEY)
    try:
        return None if text is None else PrepareSettings.from_json(text, recorded=True)
    except SettingsError:
        return None


def to_prepared_collection(objects) -> PreparedCollection:
    """Core data of prepared objects: their (normalised) meshes, transforms, landmarks and
    Keep Pose (as Prepare was told: the correspondence does not pose those by their landmarks)."""
    shapes, landmarks = [], []
    for obj in objects:
        mesh = object_to_mesh(obj, world=False, evaluated=False)
        mesh = mesh.with_vertices(mesh.vertices, name=obj.get(SOURCE_KEY, obj.name))
        points = np.asarray(obj[LANDMARKS_KEY], dtype=np.float64).reshape(-1, 3)
        faces = np.asarray(obj.get(LANDMARK_FACES_KEY, []), dtype=np.int64)
        bary = np.asarray(obj.get(LANDMARK_BARYCENTRIC_KEY, []), dtype=np.float64).reshape(-1, 3)
        if len(faces) != len(points) or (len(faces) and faces.max() >= mesh.n_faces):
            # older Prepare results (or an edited mesh): put each landmark on its nearest face again
            from ..core.geometry import TargetSurface

            placed = TargetSurface(mesh.vertices, mesh.faces).closest(points)
            faces, bary = placed.face_index, placed.barycentric
        transform = ShapeTransform.from_matrix(np.asarray(obj[TRANSFORM_KEY], dtype=np.float64).reshape(4, 4))
        change = str(obj.get(POSE_CHANGE_KEY, ""))
        rotation = np.asarray(obj.get(POSE_ROTATION_KEY, np.eye(3).ravel().tolist()), dtype=np.float64).reshape(3, 3)
        turn = obj.get(FLAG_TURN_KEY)
        turn = None if turn is None else np.asarray(turn, dtype=np.float64).reshape(3, 3)
        shapes.append(PreparedShape(mesh, transform, bool(change), rotation, change,
                                    str(obj.get(POSE_OUTLIER_KEY, "")), turn, bool(obj.get(KEEP_POSE_KEY, False))))
        landmarks.append(Landmarks(points, faces, bary, float(obj.get(LANDMARK_RADIUS_KEY, 0.0))))
    return PreparedCollection(shapes, landmarks)


def flagged_copies(collection: bpy.types.Collection | None) -> list[bpy.types.Object]:
    """The prepared copies of `collection` whose pose flag suggests a turn (Turn Flagged)."""
    return [] if collection is None else [o for o in prepared_objects(collection) if FLAG_TURN_KEY in o]


def prepared_pose_notes(objects) -> list[str]:
    """What Prepare did to the poses of prepared `objects` (core.preprocess.collection.pose_notes,
    named after their source objects): "name: turned ..." and "name: pose looks wrong: ..."."""
    return pose_notes([o.get(SOURCE_KEY, o.name) for o in objects], [o.get(POSE_CHANGE_KEY, "") for o in objects],
                      [o.get(POSE_OUTLIER_KEY, "") for o in objects])


class PreparedCopies:
    """A "<name> Prepared" collection and its copies of a fit's objects (in the objects'
    order; None when it has no copy of some), with their core data read once."""

    def __init__(self, collection: bpy.types.Collection, copies: list | None):
        self.collection = collection
        self.copies = copies
        self._core: PreparedCollection | None = None

    def core(self) -> PreparedCollection:
        """The copies as a core PreparedCollection (`to_prepared_collection`), read once."""
        if self._core is None:
            self._core = to_prepared_collection(self.copies)
        return self._core


def offered_prepared(collection, objects, evaluated: bool = True) -> list[Offered]:
    """Every Prepare result of `collection` (newest name first) as a found stage output for
    core.app.stages: the Prepare settings it records, and, as its `current` check, whether it
    has a copy of each of `objects` (the mesh objects of `collection`, sorted by name) read
    the same way (`evaluated`: modifiers applied, or the base mesh) and none has changed
    since: every copy equals its source as read now, in world coordinates, under its stored
    transform (bulk reads, well under 1 ms per 100k vertices), so editing a modifier makes
    the copies stale. `data`: its `PreparedCopies`."""
    found = sorted((c for c in bpy.data.collections
                    if c.get(PREPARED_KEY) and c.get(SOURCE_COLLECTION_KEY) == collection.name),
                   key=lambda c: c.name, reverse=True)
    depsgraph = bpy.context.evaluated_depsgraph_get()
    offered = []
    for prepared in found:
        copies = {o.get(SOURCE_KEY): o for o in prepared_objects(prepared)}
        ordered = [copies[o.name] for o in objects] if set(copies) == {o.name for o in objects} else None
        current = (lambda _, ordered=ordered: ordered is not None and all(
            _unchanged(source, copy, evaluated, depsgraph) for source, copy in zip(objects, ordered)))
        offered.append(Offered("prepare", f"'{prepared.name}'", prepare=recorded_prepare_settings(prepared),
                               current=current, data=PreparedCopies(prepared, ordered)))
    return offered


def turn_flagged_copies(collection: bpy.types.Collection) -> list[str]:
    """Turn the prepared copies of `collection` whose pose flag suggests a turn, as the
    core turns them (`PreparedCollection.turn_flagged`): each copy's mesh and its landmark
    markers are moved by the same exact similarity (topology, UVs and materials kept),
    its transform, pose report and landmarks updated, its flag cleared. Returns the source
    names turned. The user's own objects are not touched."""
    copies = prepared_objects(collection)
    flagged = [o for o in copies if FLAG_TURN_KEY in o]
    if not flagged:
        return []
    before = to_prepared_collection(flagged)
    settings = recorded_prepare_settings(collection)
    before.settings = settings
    after = before.turn_flagged()
    for copy, old, new, marks in zip(flagged, before.shapes, after.shapes, after.landmarks):
        step = Matrix((new.transform.matrix @ np.linalg.inv(old.transform.matrix)).tolist())
        copy.data.transform(step)
        for child in copy.children:  # its landmark markers, in the copy's frame
            if child.type == "MESH":
                child.data.transform(step)
        copy.data.update()
        copy[TRANSFORM_KEY] = new.transform.matrix.ravel().tolist()
        copy[POSE_CHANGE_KEY] = new.pose_change
        copy[POSE_ROTATION_KEY] = np.asarray(new.pose_rotation).ravel().tolist()
        copy[POSE_OUTLIER_KEY] = ""
        del copy[FLAG_TURN_KEY]
        copy[LANDMARKS_KEY] = marks.points.ravel().tolist()
    return [o.get(SOURCE_KEY, o.name) for o in flagged]


def has_correspondence(collection: bpy.types.Collection) -> bool:
    """Whether Find Correspondences ran on the prepared `collection`."""
    return any(CORRESPONDENCE_KEY in o for o in prepared_objects(collection))


def _unchanged(source, copy, evaluated: bool, depsgraph) -> bool:
    """True when the prepared `copy` was read like `evaluated` says, with the Keep Pose flag
    `source` has now, and still equals `source` (read the same way) mapped by its stored
    transform. Copies from before the mesh source was recorded read the base mesh."""
    if copy.get(MESH_SOURCE_KEY, mesh_source(False)) != mesh_source(evaluated):
        return False
    if bool(copy.get(KEEP_POSE_KEY, False)) != bool(source.get(KEEP_POSE_KEY, False)):
        return False
    world = object_triangles(source, world=True, evaluated=evaluated, depsgraph=depsgraph)
    local = object_triangles(copy, world=False, evaluated=False)
    if len(world.vertices) != len(local.vertices) or len(world.triangles) != len(local.triangles):
        return False
    matrix = np.asarray(copy[TRANSFORM_KEY], dtype=np.float64).reshape(4, 4)
    mapped = world.vertices @ matrix[:3, :3].T + matrix[:3, 3]
    size = max(float(np.ptp(local.vertices, axis=0).max()), 1e-12)
    return bool(np.abs(mapped - local.vertices).max() <= 1e-5 * size)
