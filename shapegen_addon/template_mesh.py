"""Generated objects on a copy of their template's own mesh.

Every mesh the core generates has the vertices of one training shape (its template), in
that shape's order as the core read it. The template's object in the scene (the training
collection's object named like the model's shape) is copied, read the way the model read
it (the evaluated mesh, or the base mesh when its prepared copy records so), and only the
vertex positions of the copy are replaced: quads, n-gons, UV maps, materials and their
slots, smooth/flat shading, sharp edges and vertex groups stay the artist's. Custom
normals are dropped (they belong to the old positions) and so are the copy's shape keys.

The core welds coincident vertices and may re-wind faces on reading (core/meshes/intake.py); the
report's `vertex_map` takes each Blender vertex to its core vertex, and the polygons the
core re-wound, or all of them for a mirrored object (negative determinant world matrix),
are reversed in the copy so its normals point outward in the model's frame.

When the template's object is missing (deleted, renamed, edited so that it no longer
reads as the model's shape, or a model loaded from a file), `find_template` returns None
and says why; callers fall back to the core's triangle mesh and report it.
"""

from __future__ import annotations

from dataclasses import dataclass

import bpy
import numpy as np

from ..core.base.errors import MeshError
from . import store
from .convert import (evaluated_depsgraph, mesh_copy, mesh_data_from_arrays, read_object, reverse_polygons,
                      winding_to_reverse)
from .keys import MESH_SOURCE_KEY, SOURCE_KEY, mesh_source
from .prepared import prepared_collection_for, prepared_objects

__all__ = ["Template", "find_template", "TemplateMeshes"]


@dataclass(frozen=True)
class Template:
    """A training shape's object in the scene, read as the model read it."""

    obj: bpy.types.Object
    evaluated: bool  # the model was built from its evaluated mesh (else its base mesh)
    vertex_map: np.ndarray | None  # (V_blender,) core vertex of each Blender vertex; None: the identity
    mirrored: bool  # read through a mirroring world matrix: every polygon is reversed in the copy
    reversed_polygons: np.ndarray  # polygons the core re-wound (`convert.read_object`), reversed too

    def positions(self, vertices: np.ndarray) -> np.ndarray:
        """Core vertex positions (V, 3) as the copy's vertices, flat float32 (3 V_blender,)."""
        vertices = np.asarray(vertices, dtype=np.float32).reshape(-1, 3)
        if self.vertex_map is not None:
            vertices = vertices[self.vertex_map]
        return np.ascontiguousarray(vertices.ravel())

    def mesh(self, name: str, vertices: np.ndarray, depsgraph) -> bpy.types.Mesh:
        """A copy of the template's mesh with `vertices` (core order) as its positions."""
        data = mesh_copy(self.obj, self.evaluated, depsgraph)
        data.name = name
        if data.shape_keys is not None:
            holder = bpy.data.objects.new(name, data)
            holder.shape_key_clear()
            bpy.data.objects.remove(holder)
        if "custom_normal" in data.attributes:
            data.attributes.remove(data.attributes["custom_normal"])
        reverse_polygons(data, winding_to_reverse(len(data.polygons), self.mirrored, self.reversed_polygons))
        data.attributes["position"].data.foreach_set("vector", self.positions(vertices))
        data.update()
        return data


def _training_object(scene: bpy.types.Scene, name: str) -> tuple[bpy.types.Object | None, str]:
    collection = bpy.data.collections.get(store.model_name(scene))
    if collection is None:
        return None, f"no collection '{store.model_name(scene)}' (the model's training collection) in this file"
    obj = collection.all_objects.get(name)
    if obj is None or obj.type != "MESH":
        return None, f"no mesh object '{name}' in collection '{collection.name}'"
    return obj, ""


def _recorded_evaluated(scene: bpy.types.Scene, obj: bpy.types.Object) -> bool:
    """How the model read `obj`: its prepared copy's mesh source, else the panel's Base Mesh."""
    prepared = prepared_collection_for(bpy.data.collections.get(store.model_name(scene)))
    for copy in prepared_objects(prepared) if prepared is not None else ():
        if copy.get(SOURCE_KEY) == obj.name and MESH_SOURCE_KEY in copy:
            return copy[MESH_SOURCE_KEY] == mesh_source(True)
    return not scene.shapegen.prepare.use_base_mesh


def find_template(scene: bpy.types.Scene, model, index: int) -> tuple[Template | None, str]:
    """The scene object of the model's training shape `index`, read as the model read it
    (its recorded mesh source first, then the other), or (None, why not)."""
    name = model.names[index]
    obj, why = _training_object(scene, name)
    if obj is None:
        return None, why
    expected = model.meshes[index]
    first = _recorded_evaluated(scene, obj)
    depsgraph = evaluated_depsgraph(scene)
    for evaluated in (first, not first):
        try:
            reading = read_object(obj, evaluated=evaluated, depsgraph=depsgraph)
        except MeshError:
            continue
        mesh = reading.mesh
        if mesh.n_vertices == expected.n_vertices and mesh.n_faces == expected.n_faces:
            vertex_map = mesh.report.vertex_map
            return Template(obj, evaluated, None if vertex_map is None else np.asarray(vertex_map),
                            mesh.report.mirrored, reading.reversed_polygons), ""
    return None, (f"'{name}' has changed since the fit ({expected.n_vertices} vertices and {expected.n_faces} "
                  "triangles in the model)")


class TemplateMeshes:
    """Mesh datablocks of one operator's generated shapes: template copies where the
    template's object is found (looked up once per template), else the core's triangle
    mesh; `note` says which templates fell back and why (empty when none did)."""

    def __init__(self, scene: bpy.types.Scene, model):
        self.scene, self.model = scene, model
        self._found: dict[int, Template | None] = {}
        self._missing: dict[str, str] = {}

    def template(self, index: int) -> Template | None:
        if index not in self._found:
            found, why = find_template(self.scene, self.model, index)
            self._found[index] = found
            if found is None:
                self._missing[self.model.names[index]] = why
        return self._found[index]

    def mesh(self, name: str, index: int, vertices: np.ndarray) -> bpy.types.Mesh:
        """A new mesh datablock of template `index` with `vertices` (core order)."""
        found = self.template(index)
        if found is None:
            return mesh_data_from_arrays(name, vertices, self.model.meshes[index].faces)
        return found.mesh(name, vertices, evaluated_depsgraph(self.scene))

    def new_object(self, name: str, index: int, vertices: np.ndarray) -> bpy.types.Object:
        """A new object (not linked) on `mesh(name, index, vertices)`; its vertex groups are
        the mesh's (a mesh holds their names and weights)."""
        return bpy.data.objects.new(name, self.mesh(name, index, vertices))

    def positions(self, index: int, vertices: np.ndarray) -> np.ndarray:
        """`vertices` (core order) as flat float32 positions of template `index`'s objects
        (for shape keys)."""
        found = self.template(index)
        if found is None:
            return np.ascontiguousarray(np.asarray(vertices, dtype=np.float32).ravel())
        return found.positions(vertices)

    @property
    def note(self) -> str:
        if not self._missing:
            return ""
        reasons = "; ".join(f"'{name}': {why}" for name, why in self._missing.items())
        return f" Template object not found, so a plain triangle mesh (no UVs or materials) was made: {reasons}"

