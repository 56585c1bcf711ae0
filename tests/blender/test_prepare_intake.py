"""Prepare reads objects as the artist sees them: the evaluated mesh (an
unapplied Subdivision counts) unless the panel's Base Mesh is on, world coordinates
(parents and rotations included), a mirrored object (scale -1 on x) and a mesh wound
inside out both come out with outward normals; the message and a custom property on each
copy say what was read, and Fit's "is Prepare's result current" check reads the same way.
"""

from __future__ import annotations

import math

import bpy
import numpy as np
import pytest
import trimesh
from conftest import addon_module, reused_prepared, vertices

def _add(convert, collection, name: str, mesh, faces=None):
    data = convert.mesh_data_from_arrays(name, mesh.vertices, mesh.faces if faces is None else faces)
    obj = bpy.data.objects.new(name, data)
    collection.objects.link(obj)
    return obj


@pytest.fixture
def shapes(extension):
    """Seven vases: two plain, one mirrored (scale -1 on x), one wound inside out, one with
    an unapplied level-1 Subdivision, one parented to a turned, scaled empty, one rotated."""
    datasets = addon_module(extension, "core.demo_data")
    add = lambda *args: _add(addon_module(extension, "shapegen_addon.convert"), collection, *args)  # noqa: E731
    vases = [s.mesh for s in datasets.make_vases(7, seed=1, resolution=(10, 14))]
    collection = bpy.data.collections.new("shapes")
    bpy.context.scene.collection.children.link(collection)
    add("plain_a", vases[0])
    add("plain_b", vases[1])
    add("mirrored", vases[2]).scale = (-1.0, 1.0, 1.0)
    add("inverted", vases[3], vases[3].faces[:, ::-1])
    subdivided = add("subdivided", vases[4])
    modifier = subdivided.modifiers.new("Subdivision", "SUBSURF")
    modifier.levels = modifier.render_levels = 1
    parent = bpy.data.objects.new("holder", None)
    bpy.context.scene.collection.objects.link(parent)  # outside the training collection
    parent.location, parent.rotation_euler, parent.scale = (3.0, -1.0, 0.5), (0.0, 0.0, math.radians(30)), (1.5,) * 3
    child = add("parented", vases[5])
    child.parent = parent
    child.location = (0.2, 0.0, 0.0)
    add("rotated", vases[6]).rotation_euler = (0.25, -0.15, math.radians(70))
    settings = bpy.context.scene.shapegen
    settings.source_collection = collection
    settings.prepare.n_landmarks = 60
    return collection


def _triangles(data: bpy.types.Mesh) -> np.ndarray:
    data.calc_loop_triangles()
    tris = np.empty(len(data.loop_triangles) * 3, dtype=np.int64)
    data.loop_triangles.foreach_get("vertices", tris)
    return tris.reshape(-1, 3)


def _world_as_seen(obj) -> np.ndarray:
    """The object's evaluated vertices in world coordinates, read here independently."""
    depsgraph = bpy.context.evaluated_depsgraph_get()
    matrix = np.array(obj.evaluated_get(depsgraph).matrix_world)
    return vertices(obj, evaluated=True) @ matrix[:3, :3].T + matrix[:3, 3]


def _copies() -> dict:
    prepared = bpy.data.collections["shapes Prepared"]
    return {o["shapegen_source"]: o for o in prepared.objects if "shapegen_landmarks" in o}


def test_prepared_copies_are_the_world_shapes_as_seen_with_outward_normals(shapes):
    assert bpy.ops.shapegen.prepare(wait=True) == {"FINISHED"}
    message = bpy.context.scene.shapegen.job_message
    assert "from their meshes as the viewport shows them (modifiers applied)" in message
    assert "mirrored: mirrored (negative scale): winding reversed" in message
    assert "inverted: 1 inside-out part(s) turned outward" in message
    copies = _copies()
    assert sorted(copies) == sorted(o.name for o in shapes.objects)
    for name, copy in copies.items():
        source = shapes.objects[name]
        assert copy["shapegen_mesh_source"] == "evaluated"
        local = vertices(copy)
        tm = trimesh.Trimesh(local, _triangles(copy.data), process=False)
        assert tm.is_watertight and tm.is_winding_consistent, name
        assert tm.volume > 0, name  # outward normals: positive enclosed volume
        # the copy is the source's world shape (parent, rotation, mirror, modifier included)
        # mapped by the recorded transform
        transform = np.asarray(copy["shapegen_transform"]).reshape(4, 4)
        world = _world_as_seen(source)
        assert len(world) == len(local), name
        np.testing.assert_allclose(world @ transform[:3, :3].T + transform[:3, 3], local,
                                   atol=1e-5 * np.ptp(local, axis=0).max(), err_msg=name)
        assert np.linalg.det(transform[:3, :3]) > 0  # Prepare's own transform mirrors nothing
    subdivided = shapes.objects["subdivided"]
    assert len(copies["subdivided"].data.vertices) == len(vertices(subdivided, evaluated=True))
    assert len(vertices(subdivided, evaluated=True)) > 3 * len(subdivided.data.vertices)


def test_base_mesh_option_reads_the_cage_and_says_so(shapes):
    bpy.context.scene.shapegen.prepare.use_base_mesh = True
    assert bpy.ops.shapegen.prepare(wait=True) == {"FINISHED"}
    assert "from their base meshes (modifiers ignored)" in bpy.context.scene.shapegen.job_message
    copies = _copies()
    assert {c["shapegen_mesh_source"] for c in copies.values()} == {"base"}
    subdivided = shapes.objects["subdivided"]
    assert len(copies["subdivided"].data.vertices) == len(subdivided.data.vertices)
    for name, copy in copies.items():
        assert trimesh.Trimesh(vertices(copy), _triangles(copy.data), process=False).volume > 0, name


def test_fit_reads_like_prepare_and_a_modifier_change_makes_prepare_stale(extension, shapes):
    fitting = addon_module(extension, "shapegen_addon.fitting")
    settings = bpy.context.scene.shapegen
    assert bpy.ops.shapegen.prepare(wait=True) == {"FINISHED"}
    objects = sorted(shapes.objects, key=lambda o: o.name)
    options = settings.fit_options()
    assert reused_prepared(extension, shapes, objects, options, evaluated=True) is not None
    assert reused_prepared(extension, shapes, objects, options, evaluated=False) is None  # read otherwise

    gathered = {name: (v, f) for name, v, f, _ in fitting.gather_meshes(objects, evaluated=True)}
    subdivided = shapes.objects["subdivided"]
    assert len(gathered["subdivided"][0]) == len(vertices(subdivided, evaluated=True))
    assert len(fitting.gather_meshes([subdivided], evaluated=False)[0][1]) == len(subdivided.data.vertices)
    for name, (world, faces) in gathered.items():  # world coordinates, mirrored winding reversed
        np.testing.assert_allclose(world, _world_as_seen(shapes.objects[name]), atol=1e-5)
        volume = trimesh.Trimesh(world, faces, process=False).volume
        assert volume > 0 or name == "inverted", name  # the core's intake turns "inverted" in the worker

    subdivided.modifiers["Subdivision"].levels = 2  # what the viewport shows changed: stale
    assert reused_prepared(extension, shapes, objects, options, evaluated=True) is None
    subdivided.modifiers["Subdivision"].levels = 1
    assert reused_prepared(extension, shapes, objects, options, evaluated=True) is not None
    displace = subdivided.modifiers.new("Displace", "DISPLACE")  # same vertex count, other shape
    displace.strength = 0.05
    assert reused_prepared(extension, shapes, objects, options, evaluated=True) is None


def test_objects_of_a_scene_the_context_does_not_show_are_read_evaluated(extension, shapes):
    """Prepare's end is applied from the job timer, whose context may show another scene
    (or none): the prepared copies are read through that job scene's own depsgraph."""
    convert = addon_module(extension, "shapegen_addon.convert")
    other = bpy.data.scenes.new("other")
    obj = shapes.objects["subdivided"].copy()
    other.collection.objects.link(obj)
    obj.modifiers["Subdivision"].levels = 2
    obj.scale = (-1.0, 1.0, 1.0)
    depsgraph = convert.evaluated_depsgraph(other)
    assert depsgraph.scene == other
    read = convert.object_triangles(obj, depsgraph=depsgraph)
    assert len(read.vertices) > len(vertices(shapes.objects["subdivided"], evaluated=True))  # level 2, not 1
    assert read.mirrored
    copy = convert.world_mesh_copy(obj, "copy", depsgraph=depsgraph)
    assert len(copy.vertices) == len(read.vertices)
    local = np.empty(len(copy.vertices) * 3)
    copy.vertices.foreach_get("co", local)
    assert trimesh.Trimesh(local.reshape(-1, 3), _triangles(copy), process=False).volume > 0


def _double_sided_cad_scene(path, rng) -> None:
    """A CAD-like file: a sphere and a small label box, every face twice (the
    copy wound the other way), each triangle on its own vertices with its own UVs (OBJ or
    glTF binary by the suffix)."""
    body = trimesh.creation.icosphere(2)
    label = trimesh.creation.box(extents=(0.1, 0.1, 0.02))
    vertices = np.concatenate([body.vertices, label.vertices + [0, 0, 1.1]])
    faces = np.concatenate([body.faces, label.faces + len(body.vertices)])
    faces = np.concatenate([faces, faces[:, [0, 2, 1]]])
    corners = vertices[faces.ravel()]
    uv = rng.random((len(corners), 2))
    if path.suffix == ".glb":
        soup = trimesh.Trimesh(corners, np.arange(len(corners)).reshape(-1, 3), process=False,
                               visual=trimesh.visual.TextureVisuals(uv=uv))
        path.write_bytes(soup.export(file_type="glb"))
        return
    lines = [f"v {x!r} {y!r} {z!r}" for x, y, z in corners.tolist()]
    lines += [f"vt {u:.6f} {v:.6f}" for u, v in uv]
    lines += [f"f {3 * i + 1}/{3 * i + 1} {3 * i + 2}/{3 * i + 2} {3 * i + 3}/{3 * i + 3}" for i in range(len(faces))]
    path.write_text("\n".join(lines) + "\n")


@pytest.mark.parametrize("suffix", ["obj", "glb"])
def test_a_double_sided_cad_file_reads_alike_through_blenders_importer_and_the_core(extension, tmp_path, suffix):
    """Blender's OBJ and glTF importers keep the soup's vertices; read as Prepare reads the
    object, it is the same one surface as the core's reader makes of the file: the same
    faces, twins, parts and one-line message."""
    convert = addon_module(extension, "shapegen_addon.convert")
    reading = addon_module(extension, "core.meshes.reading")
    path = tmp_path / f"cad.{suffix}"
    _double_sided_cad_scene(path, np.random.default_rng(0))
    from_file = reading.read_mesh(path)
    importer = bpy.ops.wm.obj_import if suffix == "obj" else bpy.ops.import_scene.gltf
    assert importer(filepath=str(path)) == {"FINISHED"}
    obj = next(o for o in bpy.context.selected_objects if o.type == "MESH")  # glTF adds an empty too
    from_blender = convert.read_object(obj).mesh
    assert from_blender.n_faces == from_file.n_faces == 320 + 12
    assert from_blender.report.twin_faces_dropped == from_file.report.twin_faces_dropped == 332
    assert from_blender.report.separate_parts == from_file.report.separate_parts == 2
    assert from_blender.report.summary() == from_file.report.summary()
    assert from_blender.is_closed() and from_file.is_closed()


def test_double_sided_quads_and_a_wall_between_cells_read_alike_through_blenders_importer(extension, tmp_path):
    """Two cells of a box and the wall between them, every quad twice (the back listed from
    its last corner, so its triangles are cut along the other diagonal): Blender's OBJ
    importer and the core's reader both make the same closed surface of the outside, the
    wall left out. The core's reader reads the backs as twins (20 triangles; the wall's two
    sides, 4, are counted as internal); Blender's importer keeps one polygon per vertex set
    on its own, so the object has no backs and a one-sided wall."""
    convert = addon_module(extension, "shapegen_addon.convert")
    reading = addon_module(extension, "core.meshes.reading")
    at = lambda x, y, z: 4 * x + 2 * y + z + 1  # noqa: E731  (OBJ numbers vertices from 1)
    quads = [[at(0, 0, 0), at(0, 0, 1), at(0, 1, 1), at(0, 1, 0)], [at(2, 0, 0), at(2, 1, 0), at(2, 1, 1), at(2, 0, 1)],
             [at(1, 0, 0), at(1, 1, 0), at(1, 1, 1), at(1, 0, 1)]]  # two ends and the wall
    for x in (0, 1):
        quads += [[at(x, 0, 0), at(x + 1, 0, 0), at(x + 1, 0, 1), at(x, 0, 1)],
                  [at(x, 1, 0), at(x, 1, 1), at(x + 1, 1, 1), at(x + 1, 1, 0)],
                  [at(x, 0, 0), at(x, 1, 0), at(x + 1, 1, 0), at(x + 1, 0, 0)],
                  [at(x, 0, 1), at(x + 1, 0, 1), at(x + 1, 1, 1), at(x, 1, 1)]]
    quads += [q[::-1] for q in quads]
    lines = [f"v {x} {y} {z}" for x in (0, 1, 2) for y in (0, 1) for z in (0, 1)]
    path = tmp_path / "cells.obj"
    path.write_text("\n".join(lines + ["f " + " ".join(map(str, q)) for q in quads]) + "\n")
    from_file = reading.read_mesh(path)
    assert bpy.ops.wm.obj_import(filepath=str(path)) == {"FINISHED"}
    from_blender = convert.read_object(bpy.context.selected_objects[0], world=False).mesh
    for mesh in (from_file, from_blender):
        assert mesh.n_faces == 20 and mesh.is_closed()
        assert trimesh.Trimesh(mesh.vertices, mesh.faces, process=False).volume == pytest.approx(2.0)
    np.testing.assert_array_equal(from_blender.vertices, from_file.vertices)
    assert from_blender.face_areas().sum() == pytest.approx(from_file.face_areas().sum()) == pytest.approx(10.0)
    assert (from_file.report.twin_faces_dropped, from_file.report.internal_faces_dropped) == (20, 4)
    assert (from_blender.report.twin_faces_dropped, from_blender.report.internal_faces_dropped) == (0, 2)
    assert "internal face(s)" in from_blender.report.summary()
