"""Geometry shared by correspondence and meshing.

Surface queries (closest points on a triangle mesh), the affine graph of per-node
3x4 affines with its k-NN stiffness term and sparse solver (thesis §4.2 and §6.2), and
Chamfer distances between point sets, and the Laplace–Beltrami spectrum of a mesh
(spectral.py, imported from there). Nothing here knows about collections, files or
shape models.
"""

from .affine_graph import (AffineSolver, apply_affines, compose_affines, data_blocks, identity_affines, knn_graph,
                           registration_frame, stiffness_energy, stiffness_matrix, transform_normals)
from .alike import nearest_facing_alike
from .chamfer import chamfer_distance, chamfer_matrix
from .surface import SurfacePoints, TargetSurface, closest_points_on_triangles

__all__ = [
    "AffineSolver",
    "SurfacePoints",
    "TargetSurface",
    "apply_affines",
    "chamfer_distance",
    "chamfer_matrix",
    "closest_points_on_triangles",
    "compose_affines",
    "data_blocks",
    "identity_affines",
    "knn_graph",
    "nearest_facing_alike",
    "registration_frame",
    "stiffness_energy",
    "stiffness_matrix",
    "transform_normals",
]
