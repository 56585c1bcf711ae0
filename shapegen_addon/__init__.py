"""ShapeGen's Blender layer: converts scene data, calls the core, shows results.

Modules exporting classes (`CLASSES`), registered in this order:
`properties` (scene settings), `operators` (Data: import, prepare), `correspondence`
(Find Correspondences on a prepared collection, landmark-index colours), `fitting` (Fit in a
worker process, Cancel, Load / Export Model), `generate` (Sample, Interpolate, Modes to
Shape Keys), `explore` (live object sliders, Randomise, Reset, Snap, Bake, Latent Map),
`panels` (sidebar UI).
Helpers: `convert` (bpy <-> core data), `preview` (landmark markers, layout), `store`
(the model packed in the .blend, load_post restore), `jobs` (bpy-free job manager),
`picture` (numpy drawing of the latent map).
"""

from __future__ import annotations

import bpy

from . import correspondence, explore, fitting, generate, handlers, latent, operators, panels, properties
from .jobs import MANAGER, unregister_timer

_CLASSES = (*properties.CLASSES, *operators.CLASSES, *correspondence.CLASSES, *fitting.CLASSES,
            *generate.CLASSES, *explore.CLASSES, *panels.CLASSES)


def register():
    for cls in _CLASSES:
        bpy.utils.register_class(cls)
    properties.register_properties()
    handlers.register_handlers()


def unregister():
    unregister_timer()
    MANAGER.kill()
    handlers.unregister_handlers()
    latent.forget_cache()
    properties.unregister_properties()
    for cls in reversed(_CLASSES):
        bpy.utils.unregister_class(cls)
