"""ShapeGen core: a plain numpy/scipy library (never imports bpy).

Installed as the package `shapegen_core`; inside the Blender extension the same files are
the sub-package `.core`. Modules use relative imports only so both work.

One folder a layer (docs/architecture.md draws them): base/, geometry/, meshes/, models/,
preprocess/ (§3.4, landmarks §4.2.1), generate/ (§6), evaluation/, correspond/ (§4.2),
demo_data/ (the demo's procedural classes) and app/ (the fit, the `shapegen` command, jobs).
A module imports only from its own folder and the folders below it. See docs in each module.
"""

__version__ = "0.1.0"
