"""ShapeGen core: a plain numpy/scipy library (never imports bpy).

Installed as the package `shapegen_core`; inside the Blender extension the same files are
the sub-package `.core`. Modules use relative imports only so both work.

Stages (thesis sections in brackets): mesh/io -> preprocess (§3.4) -> landmarks (§4.2.1)
-> correspond (§4.2) -> models (§5) -> deform (§6). See docs in each module.
"""

__version__ = "0.1.0"
