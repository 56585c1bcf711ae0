"""Alignment and scaling of a shape collection, every transform recorded (thesis §3.4).

Each shape gets one similarity transform, stored as a 4×4 matrix `M` with
``normalised = M @ [x, 1]`` (``M = [s R | t]``, R a proper rotation, s > 0). Its inverse
is exact, so every later result (landmarks, samples) maps back to each input's own
coordinates: `ShapeTransform.to_input`.

Steps, in order (`prepare_collection`):

1. Up axis: the input axis named by `up_axis` becomes +z.
2. Horizontal PCA (`align="pca"`): the first principal axis of the x–y spread becomes x,
   sign by the rule "the heavier third moment goes to +x" (skewness of x positive).
3. Consensus (`align="consensus"`, default): the orientation of every shape is made to
   agree with the collection. Each shape has 24 candidate poses: any of its six axis
   directions turned up, the horizontal PCA (and sign rule) redone in that upright frame,
   then a quarter turn k·90° about z; candidate 0 is its step-2 pose. Each shape keeps
   the candidate with the smallest symmetric Chamfer distance to a reference shape (the
   medoid); then the majority decides: if most shapes had to leave their own pose to
   match the reference, the reference was the odd one out and is replaced by a member of
   that majority (see `consensus`). This fixes shapes whose file uses another
   up axis, and shapes that are upside down or facing backwards, which a per-shape sign
   rule cannot decide (a vase's third moment flips with small details), while the
   orientation most input files agree on is kept.
4. Floor at z = 0 and centring (`centre`: "centroid" of the x–y surface spread,
   "highest" vertex, or "none").
5. Scale (`scale`): "variance" — every shape gets the same total surface variance
   (tr Cov over the surface, exact triangle integrals); "bbox" — the same axis-aligned
   bounding-box volume; "none". The common value is the geometric mean of the
   collection's measures, so units stay those of the inputs.

Moments are exact surface integrals (uniform density over the surface), so neither mesh
resolution nor interior vertices bias them (method.md §1 **beyond**).

Modules: `transform` (ShapeTransform, PreparedShape), `moments` (exact surface moments,
scale measures), `rotations` (up axis, horizontal PCA, the 24 candidate poses),
`consensus` (step 3 in named steps, its constants in `ConsensusSettings`) and `prepare`
(`prepare_collection`).
"""

from .consensus import ConsensusSettings
from .moments import SCALE_MODES, scale_measure, surface_moments, third_central_moment
from .prepare import ALIGN_MODES, CENTRE_MODES, prepare_collection
from .rotations import UP_AXES
from .transform import PreparedShape, ShapeTransform

__all__ = [
    "ShapeTransform",
    "PreparedShape",
    "prepare_collection",
    "surface_moments",
    "third_central_moment",
    "scale_measure",
    "ConsensusSettings",
    "UP_AXES",
    "ALIGN_MODES",
    "SCALE_MODES",
    "CENTRE_MODES",
]
