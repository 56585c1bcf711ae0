"""ShapeGen's Blender layer: converts scene data, calls the core, shows results.

Modules: `properties` (scene settings), `operators` (one per user action), `panels`
(sidebar UI), `convert` (bpy <-> core data), `preview` (landmark markers, layout).
Each exports its classes in `CLASSES`; registration order: properties, operators, panels.
"""

from __future__ import annotations

import bpy

from . import operators, panels, properties

_CLASSES = (*properties.CLASSES, *operators.CLASSES, *panels.CLASSES)


def register():
    for cls in _CLASSES:
        bpy.utils.register_class(cls)
    properties.register_properties()


def unregister():
    properties.unregister_properties()
    for cls in reversed(_CLASSES):
        bpy.utils.unregister_class(cls)
