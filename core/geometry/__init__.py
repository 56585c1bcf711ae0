"""Geometry shared by correspondence and meshing.

Surface queries (closest points on a triangle mesh), the affine graph of per-node
3x4 affines with its k-NN stiffness term and sparse solver (thesis §4.2 and §6.2), and
Chamfer distances between point sets. Nothing here knows about collections, files or
shape models.
"""
