"""Procedural shape classes with a known parametrisation (the demo's default data and the
test/benchmark fixtures with ground-truth correspondence).

Vases (`make_vases`): thick-walled jugs made by revolving a profile around z, with an
elliptical cross-section and a pouring lip. Every surface point has surface coordinates
(s, θ): s ∈ [0, 1] runs along the profile (bottom centre → base rim → outer wall up →
rim → inner wall down → inner floor centre) with the same breakpoints on every shape and
the belly and neck at fixed s along each wall (`_wall_height`); θ is the angle around the
axis measured from the lip. Equal (s, θ) on two vases is
their true correspondence, so correspondence error can be measured exactly
(docs/method.md §5 **beyond**).

Barrels (`make_barrels`): closed barrels nearly symmetric top-to-bottom (a bulging body, a
small knob on the lid, a tap at mid height giving the facing), for orientation tests and
benchmarks: their third moments along the axis are small, so a sign rule is noise there.

Cups (`make_cups`): thick-walled cups without handles whose straight walls lean in on some
and out on others, the geometry that defeats feature matches (core/correspond/features.py).

Mugs (`make_mugs`): mugs with a handle as a second part, walls tapering inward on some and
outward on others, closed at both ends (as an artist models a mug as a solid) or open at
the top; the orientation fixtures where a taper is all that tells top from bottom.

Classes built from parts (`make_handled_mugs`, `make_quadrupeds`; parted.py): each part
the image of a map (u, v) → R³ with its ground truth, as the vases.

Meshes are triangulated differently on purpose: ring and segment counts, ring offsets and
quad diagonals vary per shape. Each shape is also placed in a random input pose (scale,
yaw, translation), so alignment has work to do.

The package stands beside the algorithms, not among them: no other part of the core imports
it; the demo (scripts/demo.py, the add-on's demo data), the tests and the benchmarks do.
"""

from __future__ import annotations

from pathlib import Path

from .parted import PartedShape, make_handled_mugs, make_quadrupeds
from .revolved import make_barrels, make_cups, make_mugs
from .vases import PROFILE_BREAKS, ProceduralShape, VaseParameters, make_vases, vase_surface

__all__ = ["VaseParameters", "ProceduralShape", "PartedShape", "make_vases", "make_barrels", "make_cups", "make_mugs",
           "make_handled_mugs", "make_quadrupeds", "vase_surface",
           "write_collection", "PROFILE_BREAKS"]


def write_collection(shapes, folder: str | Path, file_format: str = "obj") -> list[Path]:
    """Write the shapes' meshes into `folder` as `<name>.<format>`; returns the paths."""
    from ..meshes.writing import write_mesh

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    return [write_mesh(s.mesh, folder / f"{s.name}.{file_format}") for s in shapes]
