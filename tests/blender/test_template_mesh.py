"""Generated objects keep their template's mesh: quads, n-gons, UV maps, materials, smooth
flags, sharp edges and vertex groups, with only the positions replaced."""

from __future__ import annotations

import bmesh
import bpy
import numpy as np
import pytest
from conftest import addon_module, fast_fit_json, vertices

N_AROUND = 16
N_RINGS = 8


@pytest.fixture
def jobs(extension):
    module = addon_module(extension, "shapegen_addon.jobs")
    yield module
    module.MANAGER.kill()


def add_vessel(collection, name: str, rng, seam: bool = False, inside_out: bool = False) -> bpy.types.Object:
    """A vessel of quads with n-gon caps, two UV maps, two materials (body, caps), smooth
    sides and flat caps, a sharp top rim and a "rim" vertex group. `seam`: the side's first
    column of vertices is repeated at the end (coincident vertices the core welds);
    `inside_out`: every face wound inwards (the core turns them) and custom normals set."""
    height = rng.uniform(1.5, 2.5)
    bulge, phase = rng.uniform(0.1, 0.5), rng.uniform(0.0, 1.0)
    editable = bmesh.new()
    count = N_AROUND + 1 if seam else N_AROUND
    rings = []
    for i in range(N_RINGS):
        t = i / (N_RINGS - 1)
        radius = 0.6 + bulge * np.sin(np.pi * (t + phase))
        angles = 2 * np.pi * np.arange(count) / N_AROUND
        rings.append([editable.verts.new((radius * np.cos(a), radius * np.sin(a), height * t)) for a in angles])
    for low, high in zip(rings, rings[1:]):
        for k in range(N_AROUND):
            nxt = k + 1 if seam else (k + 1) % N_AROUND
            editable.faces.new((low[k], low[nxt], high[nxt], high[k]))
    editable.faces.new(list(reversed(rings[0][:N_AROUND])))
    editable.faces.new(rings[-1][:N_AROUND])
    if inside_out:
        bmesh.ops.reverse_faces(editable, faces=editable.faces[:])
    mesh = bpy.data.meshes.new(name)
    editable.to_mesh(mesh)
    editable.free()
    caps = np.array([p.loop_total > 4 for p in mesh.polygons])
    for layer_name, values in (("UVMap", None), ("Detail", rng.uniform(size=(len(mesh.loops), 2)))):
        layer = mesh.uv_layers.new(name=layer_name)
        if values is None:
            co = vertices_of(mesh)[[loop.vertex_index for loop in mesh.loops]]
            values = np.stack([np.arctan2(co[:, 1], co[:, 0]), co[:, 2]], axis=1)
        layer.data.foreach_set("uv", values.astype(np.float32).ravel())
    for material in ("Body", "Cap"):
        mesh.materials.append(bpy.data.materials.get(material) or bpy.data.materials.new(material))
    mesh.polygons.foreach_set("material_index", caps.astype(np.int32))
    mesh.polygons.foreach_set("use_smooth", ~caps)
    top = vertices_of(mesh)[:, 2] > height - 1e-6
    mesh.edges.foreach_set("use_edge_sharp", np.array([top[e.vertices[0]] and top[e.vertices[1]] for e in mesh.edges]))
    if inside_out:
        mesh.normals_split_custom_set_from_vertices([(0.0, 0.0, 1.0)] * len(mesh.vertices))
    obj = bpy.data.objects.new(name, mesh)
    obj.vertex_groups.new(name="rim").add([int(i) for i in np.flatnonzero(top)], 1.0, "REPLACE")
    obj.location = rng.uniform(-3, 3, size=3)
    collection.objects.link(obj)
    return obj


def vertices_of(mesh) -> np.ndarray:
    co = np.empty(len(mesh.vertices) * 3)
    mesh.vertices.foreach_get("co", co)
    return co.reshape(-1, 3)


def signature(obj) -> dict:
    """Everything a generated object keeps of its template (positions excepted). Corners
    are listed per polygon as sorted (vertex, UVs) pairs, so a reversed winding compares
    equal."""
    mesh = obj.data
    corners = []
    for polygon in mesh.polygons:
        loops = range(polygon.loop_start, polygon.loop_start + polygon.loop_total)
        corners.append(sorted((mesh.loops[i].vertex_index,
                               tuple(round(v, 5) for layer in mesh.uv_layers for v in layer.data[i].uv))
                              for i in loops))
    group = obj.vertex_groups.get("rim")
    return {
        "sizes": [p.loop_total for p in mesh.polygons],
        "uv_layers": [layer.name for layer in mesh.uv_layers],
        "corners": corners,
        "materials": [m.name for m in mesh.materials],
        "material_index": [p.material_index for p in mesh.polygons],
        "smooth": [p.use_smooth for p in mesh.polygons],
        "sharp": sorted(tuple(sorted(e.vertices)) for e in mesh.edges if e.use_edge_sharp),
        "groups": [g.name for g in obj.vertex_groups],
        "weights": [[g.weight for g in v.groups if g.group == group.index] for v in mesh.vertices] if group else None,
    }


def signed_volume(obj) -> float:
    """Enclosed volume of the object's mesh, positive when its normals point outwards."""
    mesh = obj.data
    mesh.calc_loop_triangles()
    tris = np.array([t.vertices[:] for t in mesh.loop_triangles])
    co = vertices_of(mesh)[tris]
    return float(np.einsum("ij,ij->i", co[:, 0], np.cross(co[:, 1], co[:, 2])).sum() / 6.0)


def add_vessels(name: str = "vessels") -> dict:
    """Six vessels (0 mirrored, 1 and 4 with a welded seam, 5 inside out with custom
    normals) in a new collection, chosen for a PPCA fit."""
    collection = bpy.data.collections.new(name)
    bpy.context.scene.collection.children.link(collection)
    rng = np.random.default_rng(3)
    objects = [add_vessel(collection, f"vessel {i}", rng, seam=i in (1, 4), inside_out=i == 5) for i in range(6)]
    objects[0].scale = (-1.0, 1.0, 1.0)
    settings = bpy.context.scene.shapegen
    settings.source_collection = collection
    settings.prepare.n_landmarks = 100
    settings.fit.latent_dim = 2
    settings.fit.model = "ppca"
    return {o.name: o for o in objects}


def fit() -> None:
    settings = bpy.context.scene.shapegen
    assert bpy.ops.shapegen.fit(wait=True, extra_settings=fast_fit_json()) == {"FINISHED"}
    assert settings.model_text is not None, settings.job_message


@pytest.fixture
def vessels(extension, jobs):
    """`add_vessels`, fitted in the scene."""
    found = add_vessels()
    fit()
    return found


def _expected(intake, template, flat_core_vertices) -> np.ndarray:
    """Core vertex positions as the template copy's vertices (through the weld map)."""
    world = vertices_of(template.data) @ np.array(template.matrix_world)[:3, :3].T
    _, vertex_map = intake.weld_vertices(world)
    return np.asarray(flat_core_vertices).reshape(-1, 3)[vertex_map]


def test_every_generated_object_keeps_the_template_mesh(extension, vessels, capfd):
    intake = addon_module(extension, "core.meshes.intake")
    scene = bpy.context.scene
    store = addon_module(extension, "shapegen_addon.store")
    model = store.get_model(scene)
    made = []

    def check(obj, expected=None):
        template = vessels[obj["shapegen_template"]]
        assert signature(obj) == signature(template), obj.name
        assert "custom_normal" not in obj.data.attributes
        assert not np.allclose(vertices(obj), vertices(template), atol=1e-4)  # only positions differ
        if expected is not None:
            np.testing.assert_allclose(vertices(obj), _expected(intake, template, expected), atol=1e-4)
        assert signed_volume(obj) > 0, f"{obj.name}: normals point inwards"
        made.append(obj)

    # samples: the core's mesh, on a copy of the template's
    assert bpy.ops.shapegen.sample(count=3, seed=5) == {"FINISHED"}
    for obj in bpy.data.collections["ShapeGen Samples"].objects:
        z = np.asarray(obj["shapegen_latent"])
        mesh = model.mesh_from_landmarks(model.decode(z)[0], template=obj["shapegen_template"])
        check(obj, mesh.vertices)

    # the live object on every template (the mirrored one included), re-meshed by a slider; then baked
    for name in vessels:
        assert bpy.ops.shapegen.explore(template=name) == {"FINISHED"}
        live = scene.shapegen.live_object
        scene.shapegen.latents[0].value = 1.5
        mesher = model.latent_mesher(model.shape_index(name), dtype=np.float64)
        check(live, mesher.flat_vertices(np.asarray(live["shapegen_latent"])))
    assert bpy.ops.shapegen.explore_bake() == {"FINISHED"}
    baked = made[-1]
    assert "shapegen_vertex_map" not in baked and baked.name.endswith("baked")
    check(baked)

    # in-between objects, then one object with a shape-key animation
    settings = scene.shapegen
    assert bpy.ops.shapegen.interpolate(object_a="vessel 0", object_b="vessel 4", steps=2,
                                        mode="OBJECTS") == {"FINISHED"}
    for obj in bpy.data.collections["ShapeGen Interpolation"].objects:
        check(obj)
    assert bpy.ops.shapegen.interpolate(object_a="vessel 1", object_b="vessel 2", steps=2,
                                        mode="SHAPE_KEYS") == {"FINISHED"}
    morph = bpy.data.objects["vessel 1 to vessel 2 morph"]
    check(morph)
    keys = morph.data.shape_keys.key_blocks
    index = model.shape_index(morph["shapegen_template"])
    z_b = model.training_latents()[model.shape_index("vessel 2")]
    last = np.empty(len(morph.data.vertices) * 3)
    keys[-1].data.foreach_get("co", last)
    mesher = model.latent_mesher(index, dtype=np.float64)
    np.testing.assert_allclose(last.reshape(-1, 3), _expected(intake, vessels[morph["shapegen_template"]],
                                                              mesher.flat_vertices(z_b)), atol=1e-4)

    # PPCA modes as shape keys
    assert bpy.ops.shapegen.modes_to_shape_keys() == {"FINISHED"}
    modes = bpy.data.objects[f"{store.model_name(scene)} modes"]
    check(modes)
    assert [k.name for k in modes.data.shape_keys.key_blocks] == ["Mean", "Mode 1", "Mode 2"]
    assert "Template object not found" not in capfd.readouterr().out
    assert settings.live_object is None


def test_a_mirrored_template_gives_outward_normals(extension, vessels):
    assert vessels["vessel 0"].matrix_world.determinant() < 0
    assert bpy.ops.shapegen.explore(template="vessel 0") == {"FINISHED"}
    live = bpy.context.scene.shapegen.live_object
    assert live["shapegen_template"] == "vessel 0"
    assert signed_volume(live) > 0
    assert signed_volume(vessels["vessel 1"]) > 0  # the vessels are wound outwards themselves


def test_a_template_wound_inwards_gives_outward_normals_and_no_custom_normals(extension, vessels):
    template = vessels["vessel 5"]
    assert signed_volume(template) < 0 and "custom_normal" in template.data.attributes
    assert bpy.ops.shapegen.explore(template="vessel 5") == {"FINISHED"}
    live = bpy.context.scene.shapegen.live_object
    assert signed_volume(live) > 0
    assert "custom_normal" not in live.data.attributes
    assert signature(live) == signature(template)


def test_a_missing_template_falls_back_to_a_triangle_mesh_and_says_so(extension, vessels, capfd):
    store = addon_module(extension, "shapegen_addon.store")
    model = store.get_model(bpy.context.scene)
    capfd.readouterr()
    bpy.data.objects.remove(vessels.pop("vessel 3"))
    assert bpy.ops.shapegen.explore(template="vessel 3") == {"FINISHED"}
    live = bpy.context.scene.shapegen.live_object
    assert {p.loop_total for p in live.data.polygons} == {3}
    assert len(live.data.vertices) == model.meshes[model.shape_index("vessel 3")].n_vertices
    assert "Template object not found" in capfd.readouterr().out + capfd.readouterr().err
    # an edited template (another vertex count) falls back too; the others keep their mesh
    edited = vessels["vessel 2"]
    edited.data.vertices.add(1)
    edited.data.update()
    assert bpy.ops.shapegen.explore(template="vessel 2") == {"FINISHED"}
    assert {p.loop_total for p in bpy.context.scene.shapegen.live_object.data.polygons} == {3}
    assert "has changed since the fit" in capfd.readouterr().out
    assert bpy.ops.shapegen.explore(template="vessel 5") == {"FINISHED"}
    assert signature(bpy.context.scene.shapegen.live_object) == signature(vessels["vessel 5"])


@pytest.mark.parametrize("base", [False, True])
def test_the_copy_is_the_mesh_the_fit_read(extension, jobs, base):
    """With modifiers applied (the default) a generated object is a copy of the evaluated
    mesh; with Base Mesh, of the object's own data without its shape keys. The prepared
    copies record which, so changing the panel's choice after the fit changes nothing."""
    vessels = add_vessels()
    for obj in vessels.values():
        obj.modifiers.new("subdivide", "SUBSURF").levels = 1
        obj.shape_key_add(name="Basis")
        obj.shape_key_add(name="Taller").data[0].co.z += 0.1
    settings = bpy.context.scene.shapegen
    settings.prepare.use_base_mesh = base
    assert bpy.ops.shapegen.prepare(wait=True) == {"FINISHED"}
    fit()
    assert "reusing" in settings.job_message
    settings.prepare.use_base_mesh = not base
    assert bpy.ops.shapegen.sample(count=2, seed=1) == {"FINISHED"}
    depsgraph = bpy.context.evaluated_depsgraph_get()
    for obj in bpy.data.collections["ShapeGen Samples"].objects:
        template = vessels[obj["shapegen_template"]]
        if base:
            assert len(obj.data.polygons) == len(template.data.polygons)
        else:
            evaluated = template.evaluated_get(depsgraph).data
            assert len(obj.data.polygons) == len(evaluated.polygons) > len(template.data.polygons)
            assert [layer.name for layer in obj.data.uv_layers] == ["UVMap", "Detail"]
        assert obj.data.shape_keys is None
        assert [m.name for m in obj.data.materials] == ["Body", "Cap"]
        assert signed_volume(obj) > 0


def test_the_live_object_on_a_welded_template_keeps_updating_after_reopening(extension, vessels, tmp_path):
    scene = bpy.context.scene
    assert bpy.ops.shapegen.explore(template="vessel 1") == {"FINISHED"}
    assert "shapegen_vertex_map" in scene.shapegen.live_object  # vessel 1's seam was welded
    blend = tmp_path / "vessels.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(blend))
    bpy.ops.wm.open_mainfile(filepath=str(blend))
    scene = bpy.context.scene
    live = scene.shapegen.live_object
    before = vertices(live).copy()
    scene.shapegen.latents[1].value = -2.0
    moved = vertices(live)
    assert not np.allclose(before, moved)
    store = addon_module(extension, "shapegen_addon.store")
    model = store.get_model(scene)
    mesher = model.latent_mesher(model.shape_index("vessel 1"), dtype=np.float64)
    intake = addon_module(extension, "core.meshes.intake")
    z = np.asarray(live["shapegen_latent"])
    expected = _expected(intake, bpy.data.objects["vessel 1"], mesher.flat_vertices(z))
    np.testing.assert_allclose(moved, expected, atol=1e-4)


def make_double_sided(obj, inside_out: bool = False) -> int:
    """Every polygon of `obj` repeated on its own copies of the vertices and wound the other
    way (the back of a CAD sheet), the copies after the originals; `inside_out`: the front
    wound inwards first. Returns the number of front polygons."""
    editable = bmesh.new()
    editable.from_mesh(obj.data)
    front = editable.faces[:]
    if inside_out:
        bmesh.ops.reverse_faces(editable, faces=front)
    copied = bmesh.ops.duplicate(editable, geom=editable.verts[:] + editable.edges[:] + front)
    bmesh.ops.reverse_faces(editable, faces=[g for g in copied["geom"] if isinstance(g, bmesh.types.BMFace)])
    editable.to_mesh(obj.data)
    editable.free()
    return len(front)


def side_volumes(obj, n_front: int) -> tuple[float, float]:
    """Signed volumes enclosed by the front polygons and by their backs."""
    mesh = obj.data
    mesh.calc_loop_triangles()
    tris = np.array([t.vertices[:] for t in mesh.loop_triangles])
    polygon = np.array([t.polygon_index for t in mesh.loop_triangles])
    co = vertices_of(mesh)[tris]
    volume = np.einsum("ij,ij->i", co[:, 0], np.cross(co[:, 1], co[:, 2])) / 6.0
    return float(volume[polygon < n_front].sum()), float(volume[polygon >= n_front].sum())


def test_a_double_sided_template_keeps_its_two_sides_facing_apart(extension, jobs):
    """Double-sided vessels (one wound inwards): the core reads each as one surface, and the
    live object on every template keeps both sides as the object had them, the front facing
    out and the back in (CAD files come double-sided)."""
    found = add_vessels("sheets")
    fronts = {name: make_double_sided(obj, inside_out=name == "vessel 2") for name, obj in found.items()}
    fit()
    read_object = addon_module(extension, "shapegen_addon.convert").read_object
    for name, obj in found.items():
        mesh = read_object(obj).mesh
        assert mesh.report.twin_faces_dropped == mesh.n_faces and mesh.is_closed()  # the back of every face
        assert "double-sided" in mesh.report.summary() and "no outside" not in mesh.report.summary()
        assert bpy.ops.shapegen.explore(template=name) == {"FINISHED"}
        front, back = side_volumes(bpy.context.scene.shapegen.live_object, fronts[name])
        assert front > 0 and back == pytest.approx(-front, rel=2e-2), name  # caps: cut differently per side
