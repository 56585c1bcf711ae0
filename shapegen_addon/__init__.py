"""ShapeGen's Blender layer: converts scene data, calls the core, shows results.

* `ops/` — one operator module per panel section, each exporting `CLASSES`: `data`
  (Import Training Collection, Prepare), `correspondence` (Find Correspondences), `fit`
  (Fit, Load / Export Model), `cancel` (Cancel the running job), `generate` (Sample,
  Interpolate, Modes to Shape Keys), `explore` (Explore, Randomise, Reset, Snap, Bake,
  Latent Map).
* `ui/` — `properties` (`scene.shapegen`: settings, job state, sliders) and `panels`
  (View3D › Sidebar › ShapeGen).
* `jobs/` — background jobs: the bpy-free manager, the runtime shared by Prepare, Find
  Correspondences and Fit (polling, reporting the outcome), the operator mixin.
* helpers: `keys` (every `shapegen_*` key of the .blend), `prepared` (the prepared-object
  format), `latent` (sliders, live object, latent tags), `store` (the model packed in a
  Text datablock), `handlers` (file load), `convert` (bpy <-> core data), `placement`
  (where new objects go: beside the scene's objects), `preview` (collections, markers),
  `picture` (numpy drawing of the latent map).
"""

from __future__ import annotations

import bpy

from . import handlers, latent, ops
from .jobs import MANAGER, unregister_timer
from .ui import panels, properties

_CLASSES = (*properties.CLASSES, *ops.CLASSES, *panels.CLASSES)


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
