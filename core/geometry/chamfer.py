"""Symmetric Chamfer distance between point sets (nearest neighbours by scipy's cKDTree):

    C(A, B) = (1/|A|) Σ_{a∈A} min_{b∈B} ‖a − b‖²  +  (1/|B|) Σ_{b∈B} min_{a∈A} ‖a − b‖²,

the mean squared nearest-neighbour distance each way, summed. Used to choose the consensus
orientation of a collection (preprocess) and the correspondence template (the medoid).
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
from scipy.spatial import cKDTree

__all__ = ["chamfer_distance", "chamfer_distances", "chamfer_matrix"]


def chamfer_distance(a, b, rotation: np.ndarray | None = None,
                     tree_a: cKDTree | None = None, tree_b: cKDTree | None = None) -> float:
    """C(R A, B) for the points a (n, 3) turned by the rotation R (none by default) and b (m, 3).

    tree_a, tree_b: KD-trees of a (as given, not turned) and of b, built when not passed.
    Passing them compares one set in many rotations without rebuilding either tree: the
    nearest points of b in R A are found as those of Rᵀ b in A (distances are the same)."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    tree_a = cKDTree(a) if tree_a is None else tree_a
    tree_b = cKDTree(b) if tree_b is None else tree_b
    if rotation is None:
        a_to_b, _ = tree_b.query(a)
        b_to_a, _ = tree_a.query(b)
    else:
        a_to_b, _ = tree_b.query(a @ rotation.T)
        b_to_a, _ = tree_a.query(b @ rotation)
    return float(np.mean(a_to_b**2) + np.mean(b_to_a**2))


def chamfer_distances(a: np.ndarray, b: np.ndarray, rotations: np.ndarray, tree_a: cKDTree,
                      tree_b: cKDTree) -> np.ndarray:
    """C(R A, B) for each rotation R of `rotations` (k, 3, 3), (k,): `chamfer_distance` with
    one query of each tree for all the rotations."""
    k = len(rotations)
    a_to_b, _ = tree_b.query(np.einsum("kij,nj->kni", rotations, a).reshape(-1, 3))
    b_to_a, _ = tree_a.query(np.einsum("kji,nj->kni", rotations, b).reshape(-1, 3))
    return (a_to_b ** 2).reshape(k, -1).mean(axis=1) + (b_to_a ** 2).reshape(k, -1).mean(axis=1)


def chamfer_matrix(point_sets: Sequence[np.ndarray]) -> np.ndarray:
    """C between every pair of point sets, (n, n), symmetric with a zero diagonal; each set's
    KD-tree is built once."""
    sets = [np.asarray(s, dtype=np.float64) for s in point_sets]
    trees = [cKDTree(s) for s in sets]
    out = np.zeros((len(sets), len(sets)))
    for i in range(len(sets)):
        for j in range(i + 1, len(sets)):
            out[i, j] = out[j, i] = chamfer_distance(sets[i], sets[j], tree_a=trees[i], tree_b=trees[j])
    return out
