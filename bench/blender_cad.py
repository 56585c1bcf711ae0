"""A CAD-like collection modelled in Blender: bottles built with bmesh through
bpy headless (the bpy 5.0.1 module) and exported by Blender's own OBJ exporter as large
public CAD collections distribute them; and Blender's Workbench render of mesh files.
Used by bench/cad.py (class "blender:bottles", `--picture`).

One bottle (`bottle_data`), +Z up in its own frame: a single-sheet wall of quads revolved
from a profile (foot, body, shoulder, neck, open mouth) closed underneath by a 32-gon, with
separate parts: a cap (a closed short cylinder on the neck), a label (an open band 4 %
off the body) and, on the first bottle, a bouquet (five small closed flowers above the
mouth). Then made CAD-like in bmesh:

* UVs per corner (cylindrical), cut by splitting every edge: a soup whose UV seams split
  every vertex (`bmesh.ops.split_edges`);
* double-sided: every face repeated on its own vertices with its corners listed
  backwards (from its last corner, as a writer reading a polygon backwards does: a quad's
  back is cut along the other diagonal);
* mixed-up axes: each object turned about its up axis, exported with the exporter's
  default axes (Y up, −Z forward) and its object transform applied.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

N_AROUND = 32


def _revolve(bm, profile: list[tuple[float, float]]) -> list[list]:
    """Rings of N_AROUND vertices at the (radius, height) of `profile`, bridged by quads."""
    angles = 2 * np.pi * np.arange(N_AROUND) / N_AROUND
    rings = [[bm.verts.new((r * np.cos(a), r * np.sin(a), z)) for a in angles] for r, z in profile]
    for low, high in zip(rings, rings[1:]):
        for k in range(N_AROUND):
            bm.faces.new((low[k], low[(k + 1) % N_AROUND], high[(k + 1) % N_AROUND], high[k]))
    return rings


def bottle_data(name: str, rng: np.random.Generator, bouquet: bool):
    """The bmesh of one bottle (module docstring), before it is made CAD-like."""
    import bmesh

    radius, height = rng.uniform(0.8, 1.1), rng.uniform(2.6, 3.6)
    neck, shoulder = rng.uniform(0.22, 0.32) * radius, rng.uniform(0.55, 0.7) * height
    bm = bmesh.new()
    profile = [(0.9 * radius, 0.0), (radius, 0.08 * height), (radius, shoulder), (0.7 * radius, shoulder + 0.08 * height),
               (neck * 1.1, shoulder + 0.18 * height), (neck, 0.92 * height), (neck * 1.15, height)]
    wall = _revolve(bm, profile)
    bm.faces.new(list(reversed(wall[0])))  # the bottom, facing down
    cap = _revolve(bm, [(neck * 1.3, 0.95 * height), (neck * 1.3, 1.04 * height)])
    bm.faces.new(list(reversed(cap[0])))
    bm.faces.new(list(cap[-1]))
    label = 1.04 * radius
    _revolve(bm, [(label, 0.25 * shoulder), (label, 0.5 * shoulder), (label, 0.75 * shoulder)])
    if bouquet:
        for k in range(5):
            angle = 2 * np.pi * k / 5
            centre = (0.35 * radius * np.cos(angle), 0.35 * radius * np.sin(angle), 1.15 * height + 0.1 * k)
            flower = bmesh.ops.create_icosphere(bm, subdivisions=1, radius=0.12 * radius)
            bmesh.ops.translate(bm, verts=flower["verts"], vec=centre)
    bmesh.ops.recalc_face_normals(bm, faces=[f for f in bm.faces if len(f.verts) == 3])  # the closed flowers
    return bm


def cad_object(name: str, rng: np.random.Generator, bouquet: bool):
    """A bottle object made CAD-like (module docstring), linked to the scene."""
    import bmesh
    import bpy

    bm = bottle_data(name, rng, bouquet)
    uv_layer = bm.loops.layers.uv.new("UVMap")
    for face in bm.faces:
        for loop in face.loops:
            x, y, z = loop.vert.co
            loop[uv_layer].uv = ((np.arctan2(y, x) / (2 * np.pi)) % 1.0, z / 4.0)
    bmesh.ops.split_edges(bm, edges=bm.edges[:])  # a soup: every face on its own corners
    for face in list(bm.faces):  # the back of every face on its own corners, its corners listed backwards
        loops = list(face.loops)[::-1]
        back = bm.faces.new([bm.verts.new(loop.vert.co) for loop in loops])
        for corner, loop in zip(back.loops, loops):
            corner[uv_layer].uv = loop[uv_layer].uv
    data = bpy.data.meshes.new(name)
    bm.to_mesh(data)
    bm.free()
    obj = bpy.data.objects.new(name, data)
    obj.rotation_euler = (0.0, 0.0, rng.uniform(0, 2 * np.pi))
    bpy.context.scene.collection.objects.link(obj)
    return obj


def write_bottles(folder: Path, n: int, seed: int = 0) -> list[Path]:
    """`n` CAD-like bottles modelled in Blender, one OBJ file each (Blender's exporter,
    its default axes: Y up), in `folder`."""
    import bpy

    bpy.ops.wm.read_factory_settings(use_empty=True)
    rng = np.random.default_rng(seed)
    objects = [cad_object(f"bottle_{i:02d}", rng, bouquet=i == 0) for i in range(n)]
    bpy.context.view_layer.update()
    paths = []
    for obj in objects:
        for other in objects:
            other.select_set(other is obj)
        path = folder / f"{obj.name}.obj"
        bpy.ops.wm.obj_export(filepath=str(path), export_selected_objects=True, export_uv=True,
                              export_normals=True, export_materials=False)
        paths.append(path)
    return paths


def render_files(rows: list[list[tuple[Path, str]]], path: Path, size: tuple[int, int] = (1600, 900)) -> Path:
    """A Workbench render (studio light, single colour, back faces drawn) of OBJ files
    imported by Blender's own OBJ importer as an artist would, each (file, its up axis
    "Y" or "Z"), one row per list, each object on the ground beside the previous, looked
    at from the front, slightly above."""
    import bpy
    from mathutils import Vector

    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    spacing, widest, tallest = 0.0, 0.0, 0.0
    placed = []
    for r, row in enumerate(rows):
        for c, (file, up) in enumerate(row):
            bpy.ops.wm.obj_import(filepath=str(file), up_axis=up, forward_axis="NEGATIVE_Z" if up == "Y" else "Y")
            obj = bpy.context.selected_objects[0]
            bpy.context.view_layer.update()
            corners = np.array([obj.matrix_world @ Vector(v) for v in obj.bound_box])
            lo, hi = corners.min(axis=0), corners.max(axis=0)
            scale = 1.0 / max(hi[2] - lo[2], 1e-9)  # every object one unit tall
            obj.scale = (scale,) * 3
            obj.location = (-scale * (lo[0] + hi[0]) / 2, -scale * (lo[1] + hi[1]) / 2, -scale * lo[2])
            placed.append((r, c, obj))
            widest = max(widest, scale * (hi[0] - lo[0]), scale * (hi[1] - lo[1]))
    spacing = max(widest, 0.6) * 1.15
    n_columns = max(len(row) for row in rows)
    for r, c, obj in placed:
        obj.location.x += (c - (n_columns - 1) / 2) * spacing
        obj.location.z += (len(rows) - 1 - r) * 1.3
    camera = bpy.data.objects.new("camera", bpy.data.cameras.new("camera"))
    scene.collection.objects.link(camera)
    camera.data.type = "ORTHO"
    camera.data.ortho_scale = max(n_columns * spacing, len(rows) * 1.3 * size[0] / size[1]) * 1.05
    centre = Vector((0.0, 0.0, len(rows) * 1.3 / 2 - 0.15))
    camera.location = centre + Vector((0.0, -10.0, 2.5))
    camera.rotation_euler = (centre - camera.location).to_track_quat("-Z", "Y").to_euler()
    scene.camera = camera
    scene.render.engine = "BLENDER_WORKBENCH"
    scene.display.shading.light = "STUDIO"
    scene.display.shading.color_type = "SINGLE"
    scene.display.shading.show_backface_culling = False
    scene.render.resolution_x, scene.render.resolution_y = size
    scene.render.filepath = str(path)
    bpy.ops.render.render(write_still=True)
    return path
