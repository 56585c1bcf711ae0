"""Where ShapeGen's data appears in the scene: collections and landmark markers (placement.py
says where new objects go).

Landmarks are shown as one mesh of small octahedra (a marker per landmark), so they
render in every engine (Workbench, Cycles, EEVEE) and need no geometry nodes. The
landmark coordinates themselves are kept exactly in custom properties of the shape
object (keys.LANDMARKS_KEY, keys.CORRESPONDENCE_KEY), never reconstructed from the markers.
Correspondence markers are coloured by LANDMARK INDEX the same way on every shape
(colour of landmark i = position of template landmark i in the template's bounding box,
as RGB), so a user can judge correspondence by eye (thesis Fig. 4.2–4.4).
"""

from __future__ import annotations

import bpy
import numpy as np

from .convert import mesh_data_from_arrays

__all__ = ["marker_mesh_arrays", "add_landmark_markers", "add_correspondence_markers", "landmark_index_colours",
           "landmark_material", "new_collection", "ensure_collection", "COLOUR_ATTRIBUTE"]

COLOUR_ATTRIBUTE = "landmark_index_colour"

_OCTAHEDRON_VERTICES = np.array(
    [[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], dtype=np.float64
)
_OCTAHEDRON_FACES = np.array(
    [[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4], [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]],
    dtype=np.int64,
)


def new_collection(scene: bpy.types.Scene, base: str) -> bpy.types.Collection:
    """A new collection named `base` (or "base.001", ... when taken), linked to the scene."""
    name, index = base, 0
    while name in bpy.data.collections:
        index += 1
        name = f"{base}.{index:03d}"
    collection = bpy.data.collections.new(name)
    scene.collection.children.link(collection)
    return collection


def ensure_collection(scene: bpy.types.Scene, name: str) -> bpy.types.Collection:
    """The collection `name` linked to the scene (created when missing)."""
    collection = bpy.data.collections.get(name)
    if collection is None:
        collection = bpy.data.collections.new(name)
    if collection.name not in scene.collection.children:
        scene.collection.children.link(collection)
    return collection


def marker_mesh_arrays(points: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """Vertices and faces of one octahedron of `radius` centred on every point."""
    points = np.asarray(points, dtype=np.float64)
    n = len(points)
    vertices = (points[:, None, :] + radius * _OCTAHEDRON_VERTICES[None]).reshape(-1, 3)
    faces = (_OCTAHEDRON_FACES[None] + 6 * np.arange(n)[:, None, None]).reshape(-1, 3)
    return vertices, faces


def landmark_material() -> bpy.types.Material:
    """A shared bright material for landmark markers (viewport and render colour)."""
    name = "ShapeGen Landmark"
    material = bpy.data.materials.get(name)
    if material is None:
        material = bpy.data.materials.new(name)
        material.diffuse_color = (0.95, 0.3, 0.05, 1.0)
    return material


def add_landmark_markers(parent: bpy.types.Object, points: np.ndarray, radius: float,
                         collection: bpy.types.Collection) -> bpy.types.Object:
    """A child object of `parent` showing `points` (in the parent's local frame)."""
    vertices, faces = marker_mesh_arrays(points, radius)
    name = f"{parent.name} landmarks"
    data = mesh_data_from_arrays(name, vertices, faces)
    data.materials.append(landmark_material())
    markers = bpy.data.objects.new(name, data)
    markers.parent = parent
    markers.hide_select = True
    markers.color = (0.95, 0.3, 0.05, 1.0)
    collection.objects.link(markers)
    return markers


def landmark_index_colours(template_points: np.ndarray) -> np.ndarray:
    """RGBA per landmark index: the template landmark's position in its bounding box."""
    lo, hi = template_points.min(axis=0), template_points.max(axis=0)
    rgb = (template_points - lo) / np.maximum(hi - lo, 1e-12)
    return np.hstack([0.1 + 0.85 * rgb, np.ones((len(rgb), 1))]).astype(np.float32)


def add_correspondence_markers(parent: bpy.types.Object, points: np.ndarray, colours: np.ndarray,
                               radius: float) -> bpy.types.Object:
    """A child of `parent` with one octahedron per landmark, coloured by landmark index
    (replaces an earlier one)."""
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
