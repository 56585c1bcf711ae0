"""Which way a shape's hollows open: the inside/outside-aware evidence for top and bottom
that surface samples cannot give (a mug open at the top and closed at the bottom, whose
walls taper either way: upside down, its outside looks like an upright mug of the
opposite taper, and Chamfer costs and odd surface moments cannot tell them apart).

On a voxel grid over the shape (centred, unit total variance, base pose; `grid` cells
along its longest side): the surface's cells (dense surface samples, dilated by one cell),
the solid = those cells with every enclosed region filled, the hull = cells whose centre
lies inside the convex hull of the vertices. Hollows = hull cells outside the solid (the
inside of an open cup or vase, the gap under a goblet's bowl, the eye of a handle); each
connected hollow opens where it meets the hull's boundary (its mouth cells, next to a
cell outside the hull), towards the mean outward normal n_k of the hull facets there.
The opening vector is

    o = Σ_k V_k n̄_k / V_hull

(V_k the hollow's volume): an upright mug about (0, 0, 0.5), upside down (0, 0, −0.5), on
its side horizontal; a closed barrel 0; a goblet's bowl opens up and the gap under it
sideways (its hull's slanted side: slightly down), net up. A turn R of the shape turns o
to R o. Calibration (bench/orientation.py sets): the vertical component of upright
procedural vases 0.24–0.54, Blender mugs 0.41–0.57 (upside down −0.45 to −0.56),
PSB cups 0.04–0.53 (all upright, the martini glass 0.04), PSB vases 0.00–0.14, fish and
airplanes |o_z| ≤ 0.04 (their hollows open sideways), closed barrels ≤ 0.005.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
from scipy import ndimage
from scipy.spatial import ConvexHull, Delaunay, QhullError

from ..meshes.mesh import Mesh
from ..base.progress import Progress, no_progress
from .moments import surface_moments

__all__ = ["Hollows", "opening_vector"]

#: surface samples per grid cell along the longest side squared (dense enough that the
#: dilated sample cells close every wall)
SAMPLES_PER_CELL = 25


def opening_vector(mesh: Mesh, rotation: np.ndarray, grid: int, seed: int) -> np.ndarray:
    """o of `mesh` turned by `rotation` (module docstring), (3,)."""
    _, mean, cov = surface_moments(mesh)
    scale = np.sqrt(np.trace(cov))
    vertices = (mesh.vertices[mesh.used_vertices()] - mean) @ rotation.T / scale
    points = (mesh.sample_surface(SAMPLES_PER_CELL * grid * grid, np.random.default_rng(seed)).points
              - mean) @ rotation.T / scale
    low, high = vertices.min(axis=0), vertices.max(axis=0)
    cell = float((high - low).max()) / grid
    if cell <= 0:
        return np.zeros(3)
    low = low - 2.0 * cell
    shape = tuple(int(s) for s in np.ceil((high - low) / cell).astype(int) + 3)
    surface = np.zeros(shape, dtype=bool)
    index = np.clip(np.floor((points - low) / cell).astype(int), 0, np.array(shape) - 1)
    surface[tuple(index.T)] = True
    solid = ndimage.binary_fill_holes(ndimage.binary_dilation(surface))
    try:
        hull = ConvexHull(vertices)
        inside_test = Delaunay(vertices[hull.vertices])
    except QhullError:  # flat or degenerate: no volume, no hollow
        return np.zeros(3)
    centres = low + (np.indices(shape).reshape(3, -1).T + 0.5) * cell
    inside = (inside_test.find_simplex(centres) >= 0).reshape(shape)
    hull_cells = int(inside.sum())
    hollow = inside & ~solid
    if hull_cells == 0 or not hollow.any():
        return np.zeros(3)
    labels, count = ndimage.label(hollow)
    volumes = np.bincount(labels.ravel(), minlength=count + 1)
    mouth = hollow & ndimage.binary_dilation(~inside)
    mouth_labels = labels[mouth]
    mouth_centres = centres[mouth.ravel()]
    # the outward normal of the hull facet nearest each mouth cell (the one it is least inside)
    facets = hull.equations
    nearest = np.argmax(mouth_centres @ facets[:, :3].T + facets[:, 3], axis=1)
    normals = facets[nearest, :3]
    opening = np.zeros(3)
    for k in np.unique(mouth_labels):
        opening += volumes[k] * normals[mouth_labels == k].mean(axis=0)
    return opening / hull_cells


class Hollows:
    """The opening vector of every shape of a collection in its base pose, and the test
    that one shape opens the other way up from reference shapes."""

    def __init__(self, openings: Sequence[np.ndarray]):
        self.openings = [np.asarray(o, dtype=np.float64) for o in openings]

    @classmethod
    def of(cls, meshes: Sequence[Mesh], base: Sequence[np.ndarray], grid: int, seed: int,
           progress: Progress | None = None) -> "Hollows":
        """Opening vectors of the meshes turned by their base rotations (samples: seed + i),
        `progress` per shape."""
        report, openings = progress or no_progress, []
        for i, (mesh, rotation) in enumerate(zip(meshes, base)):
            openings.append(opening_vector(mesh, rotation, grid, seed + i))
            report((i + 1) / len(meshes), f"hollows of shape {i + 1} of {len(meshes)}")
        return cls(openings)

    def vertical(self, j: int, rotation: np.ndarray) -> float:
        """The up component of shape j's opening vector when turned by `rotation`."""
        return float(rotation[2] @ self.openings[j])

    def upside_down(self, j: int, rotation: np.ndarray, references: Sequence[tuple[int, np.ndarray]],
                    floor: float) -> tuple[float, float] | None:
        """(its up component, the references' median) when shape j, turned by `rotation`,
        opens the other way up from every reference, each of them and shape j by more
        than `floor`; else None."""
        own = self.vertical(j, rotation)
        theirs = np.array([self.vertical(i, r) for i, r in references])
        if len(theirs) == 0 or abs(own) <= floor or np.any(np.abs(theirs) <= floor):
            return None
        if np.all(np.sign(theirs) == -np.sign(own)):
            return own, float(np.median(theirs))
        return None
