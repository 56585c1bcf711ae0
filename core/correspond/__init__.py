"""Dense landmark correspondence by non-rigid ICP (thesis §4.2, docs/method.md §3).

A template landmark cloud X (L points) is deformed onto every shape of a prepared
collection by one affine transform per landmark (Amberg et al. 2007):

* data term (4.11, 4.15): each template point x_i pulls towards its closest point v_n(i)
  on the target *surface*; each target landmark u_j pulls the template point m(j) closest
  to it, weighted by λ (bidirectional: the template must cover the target, Fig. 4.6);
  optional match weights (§4.2.2): normal compatibility and 1/(1 + d) (4.12–4.13);
* stiffness term (4.16, 4.28): Σ_edges ‖(A_i − A_j) G‖²_F, G = diag(1, 1, 1, γ), over the
  symmetrised k-NN graph of the template landmarks (kept in the output: meshing reuses it);
* the stacked system ‖B A − C‖²_F, B = [α (M⊗G); W X; √λ W' X'] (4.29), is solved through
  its normal equations (BᵀB) A = BᵀC (4.31) with ONE sparse LU factorisation per solve,
  reused for the three coordinate right-hand sides. BᵀB = α² (MᵀM ⊗ G²) + block-diagonal
  4 × 4 data blocks: sparse, 4L × 4L, never dense;
* iterative stiffness relaxation (Alg. 3): for α in a decreasing schedule repeat
  {closest points, solve, move the template points} until the objective changes by less
  than ε (relative), with per-α and total iteration caps;
* final placement: every template point goes to its closest point on the target surface
  (**beyond**: the thesis snapped to the nearest vertex, kept as `snap_to_vertices`);
* groupwise (§4.2.7): register the template to every shape, replace it by the mean
  landmark cloud, register again.

Note on α: the thesis writes E = E_D + α E_s (4.18) but stacks α (M⊗G) into B (4.29),
as Amberg et al. do; we follow the stacked system, i.e. the stiffness energy is weighted
by α². Registration runs in a frame where the template landmarks have zero mean and unit
RMS radius, so the thesis's α values mean the same for any input units.

Everything tunable lives in `CorrespondenceSettings` (thesis defaults, one place).

Modules, one layer each (the geometry they share with meshing is core/geometry):
  settings.py      CorrespondenceSettings and its groups (stiffness, data term, iterations,
                   outliers)
  registration.py  one template → target registration (Alg. 3): `register` of a
                   `RegistrationProblem`
  data_terms.py    the data term's pieces (forward, bidirectional, known pairs `Anchors`),
                   each giving the pulls of the next solve; closest or feature matches
  pool.py          registration tasks in this process or in spawned worker processes, their
                   ICP iterations turned into progress fractions
  groupwise.py     `correspond`: template choice (never an outlier), groupwise rounds
  starting.py      the start, one plug chosen once from the settings (`start_for`: closest,
                   spectral, auto), wrapping start.py
  matching.py      the data term's part in the rounds, one plug chosen once from the settings
                   (`data_term_for`: closest points, or feature matches with their checks)
  functional_map.py  the intrinsic start (**beyond**): a spectral map of the template's
                   landmarks onto a shape (candidates, orientation, ZoomOut)
  start.py         `initialisation = "spectral"`: the starts of a collection and the check
                   against closest points that decides which start each shape keeps
  outliers.py      outlier flags and their reasons (residual, size, leave-one-out
                   reconstruction in a PPCA model of the other shapes)
  posing.py        each intrinsically started shape's rigid pose in the model frame from its
                   landmarks (Procrustes onto the template shape's); Keep Pose shapes kept
  result.py        `Correspondence` and its .npz file
  diagnostics.py   `CorrespondenceDiagnostics`: the optional record of how it came about
"""

from .groupwise import chamfer_medoid, correspond
from .outliers import flag_outliers, leave_one_out_errors
from .data_terms import Anchors
from .registration import Registration, RegistrationProblem, register
from .result import CORRESPONDENCE_FORMAT, CORRESPONDENCE_SPEC, CORRESPONDENCE_VERSION, Correspondence
from .diagnostics import CorrespondenceDiagnostics
from .settings import MATCHING_METHODS, CorrespondenceSettings

__all__ = [
    "CorrespondenceSettings",
    "Correspondence",
    "CorrespondenceDiagnostics",
    "Registration",
    "RegistrationProblem",
    "Anchors",
    "correspond",
    "register",
    "chamfer_medoid",
    "flag_outliers",
    "leave_one_out_errors",
    "MATCHING_METHODS",
    "CORRESPONDENCE_FORMAT",
    "CORRESPONDENCE_SPEC",
    "CORRESPONDENCE_VERSION",
]
