"""Alignment and scaling of a shape collection, every transform recorded (thesis §3.4).

Each shape gets one similarity transform, stored as a 4×4 matrix `M` with
``normalised = M @ [x, 1]`` (``M = [s R | t]``, R a proper rotation, s > 0). Its inverse
is exact, so every later result (landmarks, samples) maps back to each input's own
coordinates: `ShapeTransform.to_input`.

Steps, in order (`prepare_collection`):

1. Up axis: the input axis named by `up_axis` becomes +z.
2. Horizontal PCA (`align="pca"` only): the first principal axis of the x–y spread
   becomes x, sign by the rule "the heavier third moment goes to +x" (skewness of x
   positive). It turns every shape, also shapes whose inputs already agree, and its sign
   is noise for near-symmetric shapes; consensus no longer starts from it.
3. Consensus (`align="consensus"`, default): the given up axis and every shape's pose
   are trusted. A shape is turned only by a file-convention turn (its own up
   is clearly another axis of its file: a quarter turn, or a half turn when its top and
   bottom are clearly the other way round) or about up to line its facing up with the
   collection's, each on evidence that holds over the collection (every shape against
   its ten most similar shapes; a feature that varies across the class, such as a taper,
   decides nothing). A shape that may be upside down, on its side or facing away, but
   not clearly so, is flagged with its reason and a suggested turn
   (`PreparedShape.pose_outlier`, `flag_turn`, in every align mode) and left as given;
   `turn_as_flagged` makes that turn at the user's request. Shapes with `keep_pose` are
   never turned. Each change is reported (`PreparedShape.pose_change`, `pose_rotation`).
   Details in `consensus`.
4. Floor at z = 0 and centring (`centre`: "centroid" of the x–y surface spread,
   "highest" vertex, or "none").
5. Scale (`scale`): "variance" — every shape gets the same total surface variance
   (tr Cov over the surface, exact triangle integrals); "bbox" — the same axis-aligned
   bounding-box volume; "none". The common value is the geometric mean of the
   collection's measures, so units stay those of the inputs.

Moments are exact surface integrals (uniform density over the surface), so neither mesh
resolution nor interior vertices bias them (docs/method.md §1 **beyond**).

Modules: `transform` (ShapeTransform, PreparedShape), `moments` (exact surface moments,
scale measures), `rotations` (up axis, horizontal PCA, axis rotations, turns about z and
their description), `posesearch` (Chamfer costs between posed shapes, rotation search),
`signature` (odd-moment signatures: top/bottom and facing), `symmetry` (which axis is
up by the symmetries the collection's up axes share), `consensus` (step 3 and the
pose flags, its constants in `ConsensusSettings`) and `prepare` (`prepare_collection`).
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
