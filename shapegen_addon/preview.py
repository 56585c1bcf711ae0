"""Scene objects that show ShapeGen data: landmark markers and grid layout.

Landmarks are shown as one mesh of small octahedra (a marker per landmark), so they
render in every engine (Workbench, Cycles, EEVEE) and need no geometry nodes. The
landmark coordinates themselves are kept exactly in a custom property of the shape
object (`shapegen_landmarks`), never reconstructed from the markers.
"""

from __future__ import annotations

import math

import bpy
import numpy as np

from .convert import mesh_data_from_arrays

__all__ = ["marker_mesh_arrays", "add_landmark_markers", "grid_offsets", "landmark_material",
           "LANDMARKS_KEY", "TRANSFORM_KEY", "SOURCE_KEY", "LANDMARK_FACES_KEY", "LANDMARK_BARYCENTRIC_KEY",
           "LANDMARK_RADIUS_KEY"]

LANDMARKS_KEY = "shapegen_landmarks"  # flat float list (L*3), the shape object's local frame
TRANSFORM_KEY = "shapegen_transform"  # 16 floats, row-major: input (world) -> normalised
SOURCE_KEY = "shapegen_source"  # name of the user's original object
LANDMARK_FACES_KEY = "shapegen_landmark_faces"  # loop-triangle index of each landmark
LANDMARK_BARYCENTRIC_KEY = "shapegen_landmark_barycentric"  # flat (L*3) barycentrics in that triangle
LANDMARK_RADIUS_KEY = "shapegen_landmark_radius"  # exclusion radius of the landmark selection

_OCTAHEDRON_VERTICES = np.array(
    [[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], dtype=np.float64
)
_OCTAHEDRON_FACES = np.array(
    [[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4], [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]],
    dtype=np.int64,
)


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


def grid_offsets(count: int, spacing: float) -> np.ndarray:
    """x–y offsets laying `count` shapes out on a near-square grid, rows along -y."""
    columns = max(1, math.ceil(math.sqrt(count)))
    index = np.arange(count)
    return np.stack([(index % columns) * spacing, -(index // columns) * spacing, np.zeros(count)], axis=1)
