"""Where new objects go: beside the work already in the scene, never on top of it.

Every operator that adds objects (Prepare's grid, Sample's grid, Interpolate's row or morph
object, Explore's live object, Modes to Shape Keys) asks `place` for their locations. The
layout (a near-square grid or a row, `spacing` apart) starts at the 3D cursor; when its
bounding box, grown by a margin of half a shape, overlaps the world-space bounding box of a
visible object with geometry (evaluated: modifiers included), the layout moves along +x to
the nearest position clear of all of them. Bake leaves the live object where Explore put it.
"""

from __future__ import annotations

import math

import bpy
import numpy as np

__all__ = ["grid_offsets", "vertex_box", "union_box", "occupied_boxes", "clear_shift", "place", "place_one", "MARGIN"]

#: gap between a new layout and what is there, in units of the layout's largest shape side
MARGIN = 0.5

#: object types whose bounding box is geometry (cameras, lights and empties take no room)
_GEOMETRY_TYPES = frozenset({"MESH", "CURVE", "SURFACE", "META", "FONT", "CURVES", "POINTCLOUD", "VOLUME",
                             "GREASEPENCIL", "GPENCIL"})


def grid_offsets(count: int, spacing: float, columns: int | None = None) -> np.ndarray:
    """x–y offsets laying `count` shapes out `spacing` apart, `columns` per row (default a
    near-square grid; `columns=count` is one row along +x), rows along -y."""
    columns = columns or max(1, math.ceil(math.sqrt(count)))
    index = np.arange(count)
    return np.stack([(index % columns) * spacing, -(index // columns) * spacing, np.zeros(count)], axis=1)


def vertex_box(vertices: np.ndarray) -> np.ndarray:
    """(2, 3) [min corner, max corner] of points (n, 3)."""
    vertices = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    return np.stack([vertices.min(axis=0), vertices.max(axis=0)])


def union_box(boxes) -> np.ndarray:
    """(2, 3) box around every (2, 3) box of `boxes`."""
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 2, 3)
    return np.stack([boxes[:, 0].min(axis=0), boxes[:, 1].max(axis=0)])


def _view_layer(scene: bpy.types.Scene) -> bpy.types.ViewLayer:
    context_layer = getattr(bpy.context, "view_layer", None)
    if context_layer is not None and getattr(bpy.context, "scene", None) == scene:
        return context_layer
    return scene.view_layers[0]


def occupied_boxes(scene: bpy.types.Scene) -> np.ndarray:
    """(k, 2, 3) world-space bounding boxes of the scene's visible objects with geometry, from
    their evaluated bounding boxes (`bound_box` corners × `matrix_world`)."""
    view_layer = _view_layer(scene)
    depsgraph = view_layer.depsgraph
    depsgraph.update()
    boxes = []
    for obj in scene.objects:
        if obj.type not in _GEOMETRY_TYPES or not obj.visible_get(view_layer=view_layer):
            continue
        evaluated = obj.evaluated_get(depsgraph)
        corners = np.array([tuple(corner) for corner in evaluated.bound_box], dtype=np.float64)
        matrix = np.array(evaluated.matrix_world, dtype=np.float64)
        boxes.append(vertex_box(corners @ matrix[:3, :3].T + matrix[:3, 3]))
    return np.array(boxes, dtype=np.float64).reshape(-1, 2, 3)


def _overlaps(box: np.ndarray, others: np.ndarray) -> np.ndarray:
    """Which of `others` (k, 2, 3) overlap `box` (2, 3) with positive volume."""
    return np.all((others[:, 0] < box[1]) & (others[:, 1] > box[0]), axis=1)


def clear_shift(box: np.ndarray, occupied: np.ndarray) -> float:
    """The smallest shift s >= 0 along +x after which `box` (2, 3) overlaps none of
    `occupied` (k, 2, 3): 0, or a shift that puts the box's -x side on an occupied box's +x
    side (the largest of them clears every box)."""
    candidates = np.concatenate([[0.0], occupied[:, 1, 0] - box[0, 0]])
    shifts = np.sort(candidates[candidates >= 0.0])
    for shift in shifts[:-1]:
        if not _overlaps(box + np.array([shift, 0.0, 0.0]), occupied).any():
            return float(shift)
    return float(shifts[-1])  # past every occupied box's +x side


def place(scene: bpy.types.Scene, boxes, offsets: np.ndarray) -> np.ndarray:
    """World locations (n, 3) for n new objects whose local bounding boxes are `boxes`
    (n, 2, 3), laid out by `offsets` (n, 3, e.g. `grid_offsets`): the 3D cursor plus the
    offsets, moved along +x until the layout, grown by `MARGIN` shape sides, is clear of every
    visible object already in the scene. Call it before linking the new objects."""
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 2, 3)
    offsets = np.asarray(offsets, dtype=np.float64).reshape(-1, 3)
    origin = np.array(scene.cursor.location, dtype=np.float64)
    layout = union_box(boxes + offsets[:, None, :]) + origin
    margin = MARGIN * float(np.max(boxes[:, 1] - boxes[:, 0]))
    grown = layout + np.array([[-margin], [margin]])
    shift = clear_shift(grown, occupied_boxes(scene))
    return origin + offsets + np.array([shift, 0.0, 0.0])


def place_one(scene: bpy.types.Scene, box) -> np.ndarray:
    """World location (3,) of one new object with local bounding box `box` (2, 3) (`place`)."""
    return place(scene, [box], np.zeros((1, 3)))[0]
