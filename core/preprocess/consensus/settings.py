"""The constants of the consensus orientation (`ConsensusSettings`), grouped by the
evidence they weigh: the Chamfer-cost votes, which end is up, facing, the odd-moment
signature, the axis symmetry, hollows and the files' floor."""

from __future__ import annotations

from dataclasses import dataclass, field



@dataclass(frozen=True)
class CostSettings:
    """The Chamfer-cost votes of steps 1-3: how many surface samples, how many references
    each shape asks, and how many of them must ask for a turn, by how much."""

    #: surface samples per shape for the Chamfer costs
    points: int = 600
    #: shapes each shape is compared with for a turn of its up, its ends or its facing
    #: (all others in a smaller collection)
    references: int = 10
    #: share of the references that must ask for a turn of up, ends or facing
    agreement: float = 0.8
    #: cost ratio (its pose / the turned pose) a reference's vote for a turn needs
    margin: float = 1.5
    #: shapes clearly stood on the other common convention's up line (by these votes or
    #: their symmetry) that show a collection mixes the two file conventions
    convention_files: int = 2
    #: the share of the shapes stood on a side (by these votes or their symmetry) that must
    #: stand on the other convention's up line for that: a collection's files may also lie
    #: on their sides (PSB Cup: 5 of 20), and hand turns fall on either side line alike
    convention_share: float = 0.75


@dataclass(frozen=True)
class EndSettings:
    """Which end is up by the costs (step 2, and the end of a shape stood on another axis
    in step 1)."""

    #: median cost ratio a turn-over by the costs alone needs (and that tells the ends of
    #: a shape stood on another axis apart)
    flip_margin: float = 3.0
    #: ... or with the odd moments agreeing (as strongly, over the collection) this one
    flip_support: float = 2.0


@dataclass(frozen=True)
class FacingSettings:
    """Turns about up (step 3) and the nearest shapes of the pose check (step 4)."""

    #: nearest settled shapes a shape's facing is compared with (step 3), and its fit
    #: measured against (step 4)
    neighbours: int = 3
    #: grid step of the turn about z, degrees
    yaw_step: float = 15.0
    #: relative cost within which an exact axis rotation beats a refined turn
    snap: float = 0.03
    #: relative Chamfer cost increase a turn by the facing signature may cost at most
    tolerance: float = 0.1
    #: facing difference (degrees) above which a shape is turned about z
    angle: float = 30.0
    #: share of the facing votes at or below which the collection shares no input facing
    shared_facing: float = 0.4
    #: facing difference (degrees) above which a shape is turned when no facing is shared
    unshared_angle: float = 0.5
    #: share of the Chamfer votes at or below which the collection shares no input pose
    shared_pose: float = 0.4
    #: cost ratio above which a shape is turned about up when no input pose is shared
    unshared_margin: float = 1.1


@dataclass(frozen=True)
class SignatureSettings:
    """The exact odd-moment signatures (`signature.Signatures`) of top and bottom (step 2)
    and of facing (step 3)."""

    #: Legendre polynomials in height in the facing signature
    order: int = 5
    #: signature coherence above which facings are compared, and below whose negative a
    #: reference's top and bottom oppose a shape's (0..1)
    coherence: float = 0.5


@dataclass(frozen=True)
class SymmetrySettings:
    """Which axis is up by the symmetries the collection's up axes share
    (`symmetry.AxisSymmetry`, step 1)."""

    #: shapes needed for the symmetry test of a stand on another axis
    shapes: int = 5
    #: lowest spread (log units) of a symmetry feature in the up profile
    spread: float = 0.3
    #: score difference (its up − another axis) above which that axis has the collection's
    #: up symmetry clearly more than its up
    gap: float = 0.4
    #: ... and the factor by which the other axis must score better
    ratio: float = 1.3


@dataclass(frozen=True)
class HollowSettings:
    """Top and bottom by which way a shape's hollows open (`hollow.Hollows`, step 2)."""

    #: voxel grid cells along a shape's longest side for its hollows
    grid: int = 40
    #: up component of a hollow's opening vector above which it tells top from bottom
    opening: float = 0.1
    #: cost ratio (turned over / its pose) up to which a hollow turns a shape over
    cost: float = 1.5
    #: share of the telling hollows that must open the same way for it to be the collection's
    agreement: float = 0.6


@dataclass(frozen=True)
class FloorSettings:
    """The floor the collection's files share (`floors.FileFloors`, steps 1 and 2)."""

    #: a shape's lowest point within this many times the median size (RMS radius) of the
    #: upright shapes' shared floor rests on it
    tolerance: float = 0.15
    #: lowest points within this many times the median size of each other (at least three
    #: and a third of the upright shapes) make a floor where fewer than half rest on one
    exact: float = 0.02


@dataclass(frozen=True)
class ConsensusSettings:
    """The constants of the consensus orientation (module docstring), by subsystem. Plain
    constants of the method: not a user option, never saved in a file."""

    costs: CostSettings = field(default_factory=CostSettings)
    ends: EndSettings = field(default_factory=EndSettings)
    facing: FacingSettings = field(default_factory=FacingSettings)
    signature: SignatureSettings = field(default_factory=SignatureSettings)
    symmetry: SymmetrySettings = field(default_factory=SymmetrySettings)
    hollows: HollowSettings = field(default_factory=HollowSettings)
    floor: FloorSettings = field(default_factory=FloorSettings)
    #: a shape fitting its nearest shapes this many times worse than the median is flagged
    outlier_factor: float = 3.0

