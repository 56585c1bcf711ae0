"""Where a collection's files put their floor: file-convention evidence for Prepare's
consensus orientation (thesis §3.4; `consensus` steps 1 and 2).

Files of one source usually share a placement convention along their up axis: scans and
statues stand on z = 0, the objects of a Blender scene rest on one ground plane or table.
When most upright shapes of a collection have their lowest point at one height (the
floor), a shape whose lowest point lies on that floor as given rests where its author
put it: its pose is the author's, even when the other
shapes fit it better turned (a rearing cat, a sitting dog among standing ones). Such a
shape is flagged, never turned onto a side or over. A file re-saved a quarter or half
turn about its origin has its old floor on a side and its lowest point elsewhere, so the
costs restore it, and the floor backs them: it rests on the floor only once turned back
(`lands`). Where nothing rests on one floor, the floor tells nothing and the costs decide
alone. Files all centred in one box (each file's middle at its origin, as PSB's are)
share a "floor" only by the normalisation: their lowest points meet at minus half their
common height. That is no ground plane, and a shape turned about the centre lands on it
whenever another of its extents matches, so there the floor is not used at all and the
costs decide alone (`FileFloors.shared`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ..meshes.mesh import Mesh
from .moments import surface_moments

__all__ = ["FileFloors", "Floor"]


@dataclass(frozen=True)
class Floor:
    """A floor shared by a collection's files: its height along the given up and the
    distance (file units) within which a lowest point lies on it."""

    level: float
    reach: float


class FileFloors:
    """Each shape's surface points as given (base frame: the given up along z, file units
    and origin) and its size (RMS radius of its surface)."""

    def __init__(self, points: Sequence[np.ndarray], sizes: Sequence[float]):
        self.points = [np.asarray(p, dtype=np.float64) for p in points]
        self.sizes = np.asarray(sizes, dtype=np.float64)

    @classmethod
    def of(cls, meshes: Sequence[Mesh], up: np.ndarray) -> "FileFloors":
        """From the meshes as given, `up` the rotation taking the given up axis to z
        (only vertices of faces count: a stray vertex is no surface)."""
        points, sizes = [], []
        for mesh in meshes:
            points.append(mesh.vertices[mesh.used_vertices()] @ up.T)
            _, _, cov = surface_moments(mesh)
            sizes.append(np.sqrt(np.trace(cov)))
        return cls(points, sizes)

    def lowest(self, j: int, turn: np.ndarray | None = None) -> float:
        """Shape j's lowest height as given, or after `turn` (about its file's origin)."""
        direction = np.array([0.0, 0.0, 1.0]) if turn is None else np.asarray(turn)[2]
        return float((self.points[j] @ direction).min())

    def shared(self, members: Sequence[int], tolerance: float, exact: float = 0.0) -> Floor | None:
        """The floor the `members` (the upright shapes) share: more than half of at least
        three have their lowest point within `tolerance` × their median size of the
        median lowest point (a majority, so that a third of the files saved turned over
        and a shape that jumps leave it standing). Where fewer than half do (a third of a
        small class saved in another convention and one shape jumping), at least three
        and a third of them with their lowest points within `exact` × their median size of
        each other share one: random heights do not meet that closely. None: no shared
        floor, or one only the files' centring makes (`_centred`)."""
        members = list(members)
        if len(members) < 3:
            return None
        lows = np.array([self.lowest(j) for j in members])
        size = float(np.median(self.sizes[members]))
        floor = Floor(float(np.median(lows)), tolerance * size)
        if np.mean(np.abs(lows - floor.level) <= floor.reach) <= 0.5:
            floor = _exact_floor(lows, size, tolerance, exact)
        if floor is None or self._centred(members, floor):
            return None
        return floor

    def middle(self, j: int) -> float:
        """Height of the middle of shape j's extent along up, as given."""
        heights = self.points[j][:, 2]
        return float((heights.min() + heights.max()) / 2.0)

    def _centred(self, members: Sequence[int], floor: Floor) -> bool:
        """Whether the members' lowest points meet only because their files are centred in
        one box: most have the middle of their extent at their file's origin height while
        the floor lies below it. Such a "floor" is where the normalisation put half of the
        shape's height, not a ground plane: a shape turned about the centre lands on it
        whenever another extent of it happens to match, so it tells nothing of how the
        file was saved (a flat airplane turned a quarter turn lands on the upright
        airplanes' "floor" by chance)."""
        middles = np.array([self.middle(j) for j in members])
        return bool(np.mean(np.abs(middles) <= floor.reach) > 0.5 and abs(floor.level) > floor.reach)

    def keeps(self, j: int, floor: Floor | None) -> bool:
        """Whether the floor tells that shape j is posed as its author put it: it rests on
        the shared floor as given (a mug laid on its side on the ground plane by hand
        rests there as given; whether it would after a turn about its origin says
        nothing of that)."""
        return floor is not None and self._rests(j, None, floor)

    def lands(self, j: int, turn: np.ndarray, floor: Floor | None) -> bool:
        """Whether the floor tells that shape j's file was saved turned: it rests on the
        shared floor only after `turn` (about its file's origin, as a re-saved file turns)."""
        return floor is not None and not self._rests(j, None, floor) and self._rests(j, turn, floor)

    def _rests(self, j: int, turn: np.ndarray | None, floor: Floor) -> bool:
        return abs(self.lowest(j, turn) - floor.level) <= floor.reach


def _exact_floor(lows: np.ndarray, size: float, tolerance: float, exact: float) -> Floor | None:
    """The height most `lows` meet at within `exact` × `size` of each other, when at least
    three and a third of them do (its reach the usual `tolerance` × `size`); else None."""
    if exact <= 0.0:
        return None
    meets = np.abs(lows[:, None] - lows[None, :]) <= exact * size
    counts = meets.sum(axis=1)
    best = int(np.argmax(counts))
    if counts[best] < max(3.0, len(lows) / 3.0):
        return None
    return Floor(float(np.median(lows[meets[best]])), tolerance * size)
