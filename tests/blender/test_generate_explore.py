"""Sample, Explore (live sliders), Interpolate, PPCA modes as shape keys, latent map —
driven through the installed extension on small fitted models."""

from __future__ import annotations

import addon_utils
import bpy
import numpy as np
import pytest
from conftest import add_vase_collection, addon_module, load_model, vertices

MODEL_TYPES = ("ppca", "gplvm", "bgplvm")


@pytest.fixture
def store(extension):
    return addon_module(extension, "shapegen_addon.store")


def _model(store):
    return store.get_model(bpy.context.scene)


# ------------------------------------------------------------------------------ sample
def test_sample_inserts_tagged_objects_on_a_grid(extension, model_files, store):
    load_model("bgplvm", model_files)
    settings = bpy.context.scene.shapegen
    settings.prepare.seed = 7
    before = {o.name: vertices(o).copy() for o in bpy.data.objects}
    assert bpy.ops.shapegen.sample(count=4) == {"FINISHED"}
    collection = bpy.data.collections["ShapeGen Samples"]
    samples = sorted(collection.objects, key=lambda o: o["shapegen_seed"])
    assert [o["shapegen_seed"] for o in samples] == [7, 8, 9, 10]
    model = _model(store)
    for obj in samples:
        assert obj["shapegen_model"] == "vases_bgplvm"
        assert obj["shapegen_model_id"] == settings.model_text["shapegen_model_id"]
        assert obj["shapegen_template"] in model.names
        z = np.asarray(obj["shapegen_latent"])
        assert z.shape == (2,)
        # the tags reproduce the object: same seed → same latent → same mesh
        _, latents = model.sample(1, np.random.default_rng(obj["shapegen_seed"]))
        np.testing.assert_allclose(z, latents[0])
        expected = model.mesh_from_landmarks(model.decode(z)[0], template=obj["shapegen_template"])
        np.testing.assert_allclose(vertices(obj), expected.vertices, atol=1e-5)
    locations = np.array([o.location[:] for o in samples])
    assert len({tuple(np.round(p, 6)) for p in locations}) == 4  # a grid: no two on one spot
    # the effect is confined to new objects in the new collection (undo removes exactly these)
    assert {o.name for o in bpy.data.objects} == set(before) | {o.name for o in samples}
    for name, co in before.items():
        np.testing.assert_array_equal(vertices(bpy.data.objects[name]), co)
    # sampling again appends further along the grid
    assert bpy.ops.shapegen.sample(count=2, seed=100) == {"FINISHED"}
    assert len(collection.objects) == 6
    assert len({tuple(np.round(o.location[:], 6)) for o in collection.objects}) == 6


def test_generate_and_explore_operators_are_undoable():
    # headless bpy has no window, so ed.undo cannot run (its poll fails); these operators
    # declare UNDO so Blender records a step for each in the UI
    for name in ("sample", "interpolate", "modes_to_shape_keys", "explore", "explore_randomise",
                 "explore_reset", "explore_snap", "explore_bake", "load_model"):
        assert "UNDO" in getattr(bpy.types, f"SHAPEGEN_OT_{name}").bl_options, name


# ------------------------------------------------------------------------------ explore
@pytest.mark.parametrize("kind", MODEL_TYPES)
def test_sliders_remesh_the_live_object_for_every_model_type(extension, model_files, store, kind):
    load_model(kind, model_files)
    scene = bpy.context.scene
    settings = scene.shapegen
    assert bpy.ops.shapegen.explore() == {"FINISHED"}
    live = settings.live_object
    assert live is not None and live["shapegen_live"] == settings.model_text["shapegen_model_id"]
    assert len(settings.latents) == 2
    model = _model(store)
    template = live["shapegen_template"]
    mean = vertices(live).copy()

    settings.latents[0].value = 1.5  # a slider drag: the update callback re-meshes
    moved = vertices(live).copy()
    assert np.abs(moved - mean).max() > 1e-3
    latent = addon_module(extension, "shapegen_addon.latent")
    z = latent.current_latent(scene)
    np.testing.assert_allclose(live["shapegen_latent"], z)
    # the fast path equals the core's own meshing of decode(z) on the same template
    expected = model.mesh_from_landmarks(model.decode(z)[0], template=template).vertices
    np.testing.assert_allclose(moved, expected, atol=1e-4 * np.ptp(expected))

    assert bpy.ops.shapegen.explore_randomise() == {"FINISHED"}
    assert np.abs(vertices(live) - moved).max() > 1e-4
    assert settings.explore.seed == 1
    assert bpy.ops.shapegen.explore_reset() == {"FINISHED"}
    np.testing.assert_allclose(vertices(live), mean, atol=1e-6)
    settings.latents[1].value = -0.4
    assert bpy.ops.shapegen.explore_snap() == {"FINISHED"}
    training = model.training_latents()
    snapped = latent.current_latent(scene)
    assert np.min(np.abs(training - snapped).max(axis=1)) < 1e-5  # sliders are float32

    assert bpy.ops.shapegen.explore_bake() == {"FINISHED"}
    assert settings.live_object is None
    baked = bpy.data.objects[f"vases_{kind} baked"]
    assert "shapegen_live" not in baked and "shapegen_latent" in baked
    frozen = vertices(baked).copy()
    settings.latents[0].value = -2.0  # no longer driven
    np.testing.assert_array_equal(vertices(baked), frozen)
    # explore again: a new live object, the baked one stays
    assert bpy.ops.shapegen.explore() == {"FINISHED"}
    assert settings.live_object != baked


def test_explore_follows_a_new_model(extension, model_files):
    load_model("ppca", model_files)
    bpy.ops.shapegen.explore()
    live = bpy.context.scene.shapegen.live_object
    load_model("bgplvm", model_files)
    assert bpy.context.scene.shapegen.live_object == live
    assert live["shapegen_live"] == bpy.context.scene.shapegen.model_text["shapegen_model_id"]
    before = vertices(live).copy()
    bpy.context.scene.shapegen.latents[1].value = 2.0
    assert np.abs(vertices(live) - before).max() > 1e-4


# ------------------------------------------------------------------------------ interpolate
def test_interpolate_between_training_shapes_makes_in_between_objects(extension, model_files, store):
    load_model("gplvm", model_files)
    add_vase_collection(extension)
    settings = bpy.context.scene.shapegen
    settings.generate.interpolate_a = bpy.data.objects["vase_000"]
    settings.generate.interpolate_b = bpy.data.objects["vase_004"]
    assert bpy.ops.shapegen.interpolate(steps=3, mode="OBJECTS") == {"FINISHED"}
    made = sorted(bpy.data.collections["ShapeGen Interpolation"].objects, key=lambda o: o["shapegen_interpolation"])
    assert [round(o["shapegen_interpolation"], 3) for o in made] == [0.25, 0.5, 0.75]
    model = _model(store)
    z_a, z_b = model.training_latents()[[model.names.index("vase_000"), model.names.index("vase_004")]]
    np.testing.assert_allclose(made[1]["shapegen_latent"], 0.5 * (z_a + z_b))
    assert len({len(o.data.vertices) for o in made}) == 1  # one template for the whole path
    assert not np.allclose(vertices(made[0]), vertices(made[2]))

    # a sample (latent from its tag) to a training shape, as a shape-key animation
    bpy.ops.shapegen.sample(count=1, seed=3)
    sample = bpy.data.collections["ShapeGen Samples"].objects[0]
    settings.generate.interpolate_frames = 5
    assert bpy.ops.shapegen.interpolate(object_a=sample.name, object_b="vase_004", steps=2,
                                        mode="SHAPE_KEYS") == {"FINISHED"}
    morph = bpy.data.objects[f"{sample.name} to vase_004 morph"]
    keys = morph.data.shape_keys.key_blocks
    assert len(keys) == 1 + 3  # basis + 2 in-between + the end shape
    start = bpy.context.scene.frame_start
    shapes = []
    for frame in (start, start + 5, start + 15, start + 20):
        bpy.context.scene.frame_set(frame)
        shapes.append(vertices(morph, evaluated=True).copy())
    np.testing.assert_allclose(shapes[0], vertices(morph), atol=1e-5)  # frame 1: the start shape
    np.testing.assert_allclose(shapes[1], np.array([k.co[:] for k in keys[1].data]), atol=1e-5)
    np.testing.assert_allclose(shapes[2], np.array([k.co[:] for k in keys[3].data]), atol=1e-5)  # end
    np.testing.assert_allclose(shapes[3], shapes[2], atol=1e-5)  # holds after the end
    assert np.abs(shapes[0] - shapes[2]).max() > 1e-3


def test_interpolate_errors_are_clear(extension, model_files):
    with pytest.raises(RuntimeError, match="No fitted model"):
        bpy.ops.shapegen.interpolate()
    load_model("ppca", model_files)
    with pytest.raises(RuntimeError, match="Choose the 'From' object first"):
        bpy.ops.shapegen.interpolate()
    stranger = bpy.data.objects.new("stranger", bpy.data.meshes.new("stranger"))
    bpy.context.scene.collection.objects.link(stranger)
    add_vase_collection(extension)
    with pytest.raises(RuntimeError, match="'stranger' has no latent vector"):
        bpy.ops.shapegen.interpolate(object_a="stranger", object_b="vase_001")
    with pytest.raises(RuntimeError, match="same object"):
        bpy.ops.shapegen.interpolate(object_a="vase_001", object_b="vase_001")
    with pytest.raises(RuntimeError, match="No object named 'nope'"):
        bpy.ops.shapegen.interpolate(object_a="nope", object_b="vase_001")


# ------------------------------------------------------------------------------ modes
def test_ppca_modes_are_native_shape_keys_that_work_without_the_addon(extension, model_files, store):
    load_model("ppca", model_files)
    assert bpy.ops.shapegen.modes_to_shape_keys() == {"FINISHED"}
    obj = bpy.data.objects["vases_ppca modes"]
    keys = obj.data.shape_keys.key_blocks
    assert [k.name for k in keys] == ["Mean", "Mode 1", "Mode 2"]
    assert all(k.slider_min == -3.0 and k.slider_max == 3.0 for k in keys[1:])  # ±3 standard deviations
    assert addon_module(extension, "core.models.ppca").MODE_RANGE == 3.0  # the core's range, not the add-on's
    model = _model(store)
    mesher = model.latent_mesher(model.mean_template(), dtype=np.float64)
    basis = np.array([v.co[:] for v in keys[0].data])
    mode_1 = np.array([v.co[:] for v in keys[1].data]) - basis
    np.testing.assert_allclose(mode_1, mesher.basis[0].reshape(-1, 3), atol=1e-5)
    # z = (1.5, 0) through the model equals the mesh with Mode 1 at 1.5
    expected = mesher.vertices(np.array([1.5, 0.0]))

    addon_utils.disable(extension, default_set=True)
    try:
        assert not hasattr(bpy.types.Scene, "shapegen")
        keys = bpy.data.objects["vases_ppca modes"].data.shape_keys.key_blocks
        keys["Mode 1"].value = 1.5
        np.testing.assert_allclose(vertices(bpy.data.objects["vases_ppca modes"], evaluated=True), expected,
                                   atol=1e-5)
    finally:
        addon_utils.enable(extension, default_set=True)


def test_modes_need_a_ppca_model(model_files):
    with pytest.raises(RuntimeError, match="No fitted model"):
        bpy.ops.shapegen.modes_to_shape_keys()
    load_model("gplvm", model_files)
    with pytest.raises(RuntimeError, match="need a PPCA model"):
        bpy.ops.shapegen.modes_to_shape_keys()
    assert "ShapeGen Modes" not in bpy.data.collections


# ------------------------------------------------------------------------------ latent map
def test_latent_map_is_an_image_with_training_shapes_marked(extension, model_files, store):
    load_model("bgplvm", model_files)
    bpy.ops.shapegen.sample(count=3)
    assert bpy.ops.shapegen.latent_map(size=128) == {"FINISHED"}
    image = bpy.data.images["ShapeGen Latent Map"]
    assert tuple(image.size) == (128, 128)
    pixels = np.empty(128 * 128 * 4, dtype=np.float32)
    image.pixels.foreach_get(pixels)
    pixels = pixels.reshape(128, 128, 4)
    picture = addon_module(extension, "shapegen_addon.picture")
    model = _model(store)
    drawn = picture.latent_map_pixels(model.training_latents(), model.correspondence.outliers, 128)
    for (column, row), bad in zip(drawn.training_pixels, model.correspondence.outliers):
        colour = picture.COLOURS["outlier" if bad else "training"]
        np.testing.assert_allclose(pixels[row, column], colour, atol=3 / 255)
    green = np.all(np.abs(pixels - picture.COLOURS["sample"]) < 3 / 255, axis=2)  # 8-bit image
    assert green.any()  # the samples are on the map too
    assert image.packed_file is not None  # travels with the .blend


def test_latent_map_marks_outliers_and_handles_one_dimension(extension):
    picture = addon_module(extension, "shapegen_addon.picture")
    rng = np.random.default_rng(0)
    latents = rng.standard_normal((8, 4)) * np.array([0.1, 2.0, 0.2, 1.0])
    outliers = np.zeros(8, dtype=bool)
    outliers[3] = True
    drawn = picture.latent_map_pixels(latents, outliers, 96)
    assert drawn.dims == (1, 3)  # the two dimensions with the largest spread
    column, row = drawn.training_pixels[3]
    np.testing.assert_allclose(drawn.pixels[row, column], picture.COLOURS["outlier"])
    column, row = drawn.training_pixels[0]
    np.testing.assert_allclose(drawn.pixels[row, column], picture.COLOURS["training"])
    flat = picture.latent_map_pixels(latents[:, :1], outliers, 64)
    assert flat.dims == (0, -1) and flat.pixels.shape == (64, 64, 4)


# ------------------------------------------------------------------------------ error paths
@pytest.mark.parametrize("name", ["sample", "explore", "latent_map", "explore_randomise", "explore_reset",
                                  "explore_snap", "explore_bake"])
def test_operators_without_a_model_explain_why(name):
    with pytest.raises(RuntimeError, match="No fitted model in this scene"):
        getattr(bpy.ops.shapegen, name)()


@pytest.mark.parametrize("name", ["explore_randomise", "explore_reset", "explore_snap", "explore_bake"])
def test_explore_operators_without_a_live_object_explain_why(model_files, name):
    load_model("ppca", model_files)
    with pytest.raises(RuntimeError, match="No live object: press Explore first"):
        getattr(bpy.ops.shapegen, name)()


def test_a_damaged_packed_model_is_reported(extension, model_files, store):
    load_model("ppca", model_files)
    text = bpy.context.scene.shapegen.model_text
    text["shapegen_model_npz"] = b"PK\x03\x04 damaged"
    store.forget_cache()
    with pytest.raises(RuntimeError, match="Text 'vases_ppca.shapegen'.*not a readable .npz"):
        bpy.ops.shapegen.sample(count=1)
    del text["shapegen_model_npz"]
    with pytest.raises(RuntimeError, match="holds no packed ShapeGen model"):
        bpy.ops.shapegen.explore()
    assert "ShapeGen Samples" not in bpy.data.collections
