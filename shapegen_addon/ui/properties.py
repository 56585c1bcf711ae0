"""Scene-level settings of the ShapeGen panel (`scene.shapegen`).

Everything the sidebar shows lives here and is saved with the .blend: data and fit
settings, the fitted model (a pointer to the Text datablock that holds it, see ../store.py),
the last job's outcome, the latent sliders of the live object and the generate options.
The running job's progress itself is runtime state (jobs.MANAGER), mirrored into
`job_state` / `job_fraction` / `job_stage` so the panel and scripts can read it.
"""

from __future__ import annotations

import sys
from dataclasses import fields

import bpy
from bpy.props import (BoolProperty, CollectionProperty, EnumProperty, FloatProperty, IntProperty,
                       PointerProperty, StringProperty)

from ...core.app.fit_settings import FitSettings
from ...core.app.shape_model import PATH_SHAPES
from ...core.models.latent_units import SLIDER_LIMIT
from ..latent import on_slider_changed
from ..prepared import PREPARE_SETTINGS

#: the core's defaults, the one source of every default below: Blender and `shapegen` agree
CORE_DEFAULTS = FitSettings()

#: each panel setting that is a core option: (group of `scene.shapegen`, property) → the
#: option's dotted path in FitSettings. Its default and limits are the core's (`core_option`);
#: Shapes Differ in Pose shows `data_term.initialisation` as Auto / On / Off, Latent
#: Dimension shows None as 0 (Blender has no empty number)
CORE_OPTIONS = {
    **{("prepare", name): f"prepare.{name}" for name in ("n_landmarks", "up_axis", "align", "scale", "centre", "seed")},
    ("correspondence", "stiffness"): "correspondence.stiffness.alpha_end",
    ("correspondence", "matching"): "correspondence.data_term.matching",
    ("correspondence", "differ_in_pose"): "correspondence.data_term.initialisation",
    ("fit", "model"): "model",
    ("fit", "latent_dim"): "latent_dim",
    ("fit", "mesh_stiffness"): "deform.final_alpha",
    ("generate", "sample_template"): "mesh_template",
}
#: the panel settings the core has no option for, and why
BLENDER_ONLY = {
    ("prepare", "preview_spacing"): "where new objects go in the scene",
    ("prepare", "use_base_mesh"): "which mesh of an object Prepare reads (modifiers applied or not)",
    ("generate", "sample_count"): "how many objects Sample adds (`shapegen sample -n` has no default)",
    ("generate", "interpolate_a"): "an object of the scene",
    ("generate", "interpolate_b"): "an object of the scene",
    ("generate", "interpolate_steps"): "in-between objects, ends not counted (`shapegen interpolate -n` counts them)",
    ("generate", "interpolate_mode"): "objects or a shape-key animation",
    ("generate", "interpolate_frames"): "animation frames",
    ("explore", "seed"): "the next Randomise draw's seed, one more after each",
    ("explore", "map_size"): "pixels of the latent map picture",
    ("explore", "show_uncertainty"): "a viewport colour attribute",
}


def core_option(path: str, precision: int = 2) -> dict:
    """Blender property keywords of the FitSettings option at dotted `path` (its place in
    CORE_OPTIONS): the core's default, and as `min` the lower limit the core checks
    (`option(minimum=...)`; an exclusive `above` bound becomes the smallest value a field
    of `precision` decimals shows above it, Blender's limits being inclusive)."""
    *parents, name = path.split(".")
    owner = CORE_DEFAULTS
    for parent in parents:
        owner = getattr(owner, parent)
    meta = next(f for f in fields(owner) if f.name == name).metadata
    keywords = {"default": getattr(owner, name)}
    if meta.get("minimum") is not None:
        keywords["min"] = meta["minimum"]
    elif meta.get("above") is not None:
        keywords["min"] = meta["above"] + 10 ** -precision
    return keywords

UP_AXIS_ITEMS = [
    ("z", "Z", "The input's +Z points up (Blender's convention)"),
    ("y", "Y", "The input's +Y points up (most OBJ/OFF files)"),
    ("x", "X", "The input's +X points up"),
    ("-z", "-Z", "The input's -Z points up"),
    ("-y", "-Y", "The input's -Y points up"),
    ("-x", "-X", "The input's -X points up"),
]
ALIGN_ITEMS = [
    ("consensus", "Collection", "Keep each shape's pose; turn a shape only when the whole collection clearly "
                                "says it lies on another axis or faces another way"),
    ("pca", "Own Axes", "Turn every shape to its own longest horizontal spread (ignores the other shapes)"),
    ("none", "None", "Never turn: only set on the floor, centre and scale"),
]
SCALE_ITEMS = [
    ("variance", "Equal Spread", "Scale every shape to the same overall spread of its surface"),
    ("bbox", "Equal Box Volume", "Scale every shape to the same bounding-box volume"),
    ("none", "None", "Keep each shape's size (the model then learns size too)"),
]
CENTRE_ITEMS = [
    ("centroid", "Centre of Surface", "Put the middle of each shape's surface over the origin"),
    ("highest", "Highest Point", "Put each shape's highest point over the origin (e.g. teapots, whose spouts "
                                 "and handles pull the middle sideways)"),
    ("none", "None", "Keep each shape where it is horizontally"),
]
MATCHING_ITEMS = [
    ("closest", "Closest Points", "Each landmark slides to the nearest part of the surface that faces its way "
                                  "(recommended)"),
    ("features", "Features", "Experimental: landmarks also match by which way the surface faces and by height "
                             "between a shape's bellies and necks. Better on vases, less compact models on "
                             "other classes; falls back to Closest Points where it fits badly"),
]
#: Shapes Differ in Pose: the item numbers keep .blend files of the checkbox it was reading
#: as before (Blender stores an enum by its number: off 0, on 1); Auto is new
POSE_ITEMS = [
    ("AUTO", "Auto", "The collection decides: the intrinsic start where its shapes differ in pose more than in "
                     "proportion (recommended)", 2),
    ("ON", "On", "Every shape starts from a map along its surface (animals, people, hands)", 1),
    ("OFF", "Off", "Every shape starts from the template as it is (vases, mugs, cars)", 0),
]
#: the core's `data_term.initialisation` of each item and back
INITIALISATION_OF = {"AUTO": "auto", "ON": "spectral", "OFF": "closest"}
POSE_ITEM_OF = {value: key for key, value in INITIALISATION_OF.items()}


MODEL_ITEMS = [
    ("ppca", "PPCA", "Linear and fast; its modes can become ordinary shape keys"),
    ("gplvm", "GP-LVM", "Non-linear: follows curved variation (slower)"),
    ("bgplvm", "Bayesian GP-LVM", "Non-linear and picks how many sliders it needs (recommended)"),
]
JOB_STATE_ITEMS = [
    ("IDLE", "Idle", "No background job has run"),
    ("RUNNING", "Running", "A job (Prepare, Find Correspondences or Fit) runs in the background"),
    ("DONE", "Done", "The last job finished; its result is in the scene"),
    ("FAILED", "Failed", "The last job failed; the scene (and any earlier model) is as it was"),
    ("CANCELLED", "Cancelled", "The last job was cancelled; the scene (and any earlier model) is as it was"),
]
TEMPLATE_ITEMS = [
    ("nearest-data", "Nearest Shape", "Build each new shape from the training object it most resembles"),
    ("nearest-latent", "Nearest on the Sliders", "Build each new shape from the training object nearest to it "
                                                 "on the sliders"),
]
INTERPOLATION_ITEMS = [
    ("OBJECTS", "Objects", "K in-between objects in a row"),
    ("SHAPE_KEYS", "Shape Key Animation", "One object morphing over frames (shape keys)"),
]


def _on_latent_changed(self, context):
    on_slider_changed(self.id_data)


class ShapeGenLatent(bpy.types.PropertyGroup):
    """One latent dimension of the live object: z_k = centre + value × scale, where centre
    and scale are the training latents' mean and standard deviation in that dimension."""

    value: FloatProperty(
        name="Value", default=0.0, soft_min=-SLIDER_LIMIT, soft_max=SLIDER_LIMIT, precision=3,
        description=f"Move to change the shape; ±{SLIDER_LIMIT:g} reaches every training shape",
        update=_on_latent_changed,
    )
    centre: FloatProperty(name="Centre", default=0.0, options={"HIDDEN"})
    scale: FloatProperty(name="Scale", default=1.0, options={"HIDDEN"})


class ShapeGenPrepareSettings(bpy.types.PropertyGroup):
    """The Data panel's settings (`scene.shapegen.prepare`): how Prepare reads, aligns,
    scales and landmarks the collection, and the gap between the objects it lays out."""

    n_landmarks: IntProperty(
        name="Landmarks", **core_option("prepare.n_landmarks"),
        soft_max=5000,  # the drag range only: the core sets no upper limit, a typed value may exceed it
        description="Points placed on every shape to compare them. More follow finer detail and take longer",
    )
    up_axis: EnumProperty(name="Up Axis", items=UP_AXIS_ITEMS, **core_option("prepare.up_axis"),
                          description="Which axis points up in your objects (Z in Blender; Y in many OBJ files)")
    align: EnumProperty(name="Align", items=ALIGN_ITEMS, **core_option("prepare.align"),
                        description="How Prepare turns the shapes to face alike")
    scale: EnumProperty(name="Scale", items=SCALE_ITEMS, **core_option("prepare.scale"),
                        description="How Prepare makes the shapes one size")
    centre: EnumProperty(name="Centre", items=CENTRE_ITEMS, **core_option("prepare.centre"),
                         description="Which point of each shape Prepare puts over the origin")
    seed: IntProperty(name="Seed", **core_option("prepare.seed"),
                      description="Change it for different random landmarks and samples; the same seed gives "
                                  "the same result")
    preview_spacing: FloatProperty(name="Spacing", default=1.5, min=0.0,
                                   description="Gap between the prepared shapes and between new shapes, in shape sizes")
    use_base_mesh: BoolProperty(
        name="Base Mesh", default=False,
        description="Read each object without its modifiers (off: as the viewport shows it, modifiers applied)",
    )

    def options(self) -> dict:
        """Options of the core's prepare_meshes (the settings a prepared collection records)."""
        return {name: getattr(self, name) for name in PREPARE_SETTINGS}


class ShapeGenCorrespondenceSettings(bpy.types.PropertyGroup):
    """The Correspondence panel's settings (`scene.shapegen.correspondence`)."""

    stiffness: FloatProperty(
        name="Stiffness", **core_option("correspondence.stiffness.alpha_end"),
        soft_max=CORE_DEFAULTS.correspondence.stiffness.alpha_start,  # drag up to where the schedule starts
        description="How stiffly the landmarks move when matched to each shape: higher keeps them evenly "
                    "spread, lower follows each shape's details closely (5 suits vases and mugs, 10 cars)",
    )
    matching: EnumProperty(name="Matches", items=MATCHING_ITEMS, **core_option("correspondence.data_term.matching"),
                           description="What each landmark is matched to on every shape")
    differ_in_pose: EnumProperty(
        name="Shapes Differ in Pose", items=POSE_ITEMS,
        default=POSE_ITEM_OF[CORE_DEFAULTS.correspondence.data_term.initialisation],
        description="Animals, people, hands: shapes that bend at joints. On: each shape's landmarks start where "
                    "a map along its surface puts them, which a moved limb does not change (slower; where that map "
                    "cannot be trusted the shape starts as usual and its message says so). Auto: the collection "
                    "decides, and the messages say which start it chose and why",
    )

    def options(self) -> dict:
        """CorrespondenceSettings options by their flat names (`CorrespondenceSettings.FIELDS_MOVED`
        reads them into its groups): the stiffness schedule ends at `stiffness` and starts where
        the core's does, or at `stiffness` when that is higher (the core's check: the first α is
        at least the last); `matching`; `initialisation` from Shapes Differ in Pose
        (Auto / On: spectral / Off: closest)."""
        start = max(CORE_DEFAULTS.correspondence.stiffness.alpha_start, self.stiffness)
        return {"alpha_end": self.stiffness, "alpha_start": start, "matching": self.matching,
                "initialisation": INITIALISATION_OF[self.differ_in_pose]}


class ShapeGenFitSettings(bpy.types.PropertyGroup):
    """The Model panel's settings (`scene.shapegen.fit`): the shape model and its meshing."""

    model: EnumProperty(name="Model", items=MODEL_ITEMS, **core_option("model"),
                        description="The kind of model that learns the shapes")
    latent_dim: IntProperty(
        name="Latent Dimension", default=CORE_DEFAULTS.latent_dim or 0,
        min=0,  # 0 shows the core's None (the 80 % rule); every other value is at least the core's minimum, 1
        soft_max=20,  # the drag range only: the core's limit is the collection's
        description="How many ways the shapes may vary (one slider each). 0: as many as the collection needs",
    )
    mesh_stiffness: FloatProperty(
        name="Meshing Stiffness", **core_option("deform.final_alpha"),
        soft_max=CORE_DEFAULTS.deform.start_alpha,  # drag up to where the meshing schedule starts
        description="How stiffly new shapes are bent out of a training object: higher keeps its surface smooth "
                    "and unbroken, lower follows the new shape more closely",
    )


class ShapeGenGenerateSettings(bpy.types.PropertyGroup):
    """The Generate panel's settings (`scene.shapegen.generate`): samples and in-betweens."""

    sample_count: IntProperty(name="Count", default=6, min=1, soft_max=100, description="How many new shapes to make")
    sample_template: EnumProperty(name="Template", items=TEMPLATE_ITEMS, **core_option("mesh_template"),
                                  description="Which training object a new shape's mesh is made from")
    interpolate_a: PointerProperty(name="From", type=bpy.types.Object,
                                   description="The first shape: a training object or a ShapeGen sample")
    interpolate_b: PointerProperty(name="To", type=bpy.types.Object,
                                   description="The last shape: a training object or a ShapeGen sample")
    interpolate_steps: IntProperty(name="Steps", default=PATH_SHAPES - 2, min=1, soft_max=50,
                                   description="How many shapes in between")
    interpolate_mode: EnumProperty(name="Output", items=INTERPOLATION_ITEMS, default="OBJECTS",
                                   description="Separate objects, or one object animated with shape keys")
    interpolate_frames: IntProperty(name="Frames per Step", default=10, min=1, soft_max=100,
                                    description="Animation frames from one in-between shape to the next")


class ShapeGenExploreSettings(bpy.types.PropertyGroup):
    """The Explore panel's settings (`scene.shapegen.explore`)."""

    seed: IntProperty(name="Seed", default=0, min=0, description="Change it for another random shape")
    map_size: IntProperty(name="Map Size", default=256, min=64, max=2048,
                          description="Size of the latent map picture, in pixels")
    show_uncertainty: BoolProperty(name="Show Uncertainty", default=False,
                                   description="While pins shape the live object, colour it by how unsure the "
                                   "model is of each point (attribute 'shapegen_std': white = least sure)")


class ShapeGenSettings(bpy.types.PropertyGroup):
    """The panel's settings, one group per panel section (prepare, correspondence, fit,
    generate, explore), beside the chosen collection, the fitted model, the last job and
    the live object's sliders. Every default that the core also has is read from the core's
    settings (`CORE_DEFAULTS`), so Blender and `shapegen` start from the same values."""

    source_collection: PointerProperty(
        name="Collection", type=bpy.types.Collection,
        description="The collection of example objects to learn from, all of one kind (vases, mugs, cars, ...)",
    )
    last_import_directory: StringProperty(name="Last Folder", subtype="DIR_PATH")
    prepare: PointerProperty(type=ShapeGenPrepareSettings)
    correspondence: PointerProperty(type=ShapeGenCorrespondenceSettings)
    fit: PointerProperty(type=ShapeGenFitSettings)
    generate: PointerProperty(type=ShapeGenGenerateSettings)
    explore: PointerProperty(type=ShapeGenExploreSettings)

    # --- the fitted model (packed in a Text datablock, see store.py) and the last job
    model_text: PointerProperty(
        name="Model", type=bpy.types.Text,
        description="The text block that keeps the fitted model inside this .blend file",
    )
    job_state: EnumProperty(name="Job State", items=JOB_STATE_ITEMS, default="IDLE")
    job_fraction: FloatProperty(name="Progress", default=0.0, min=0.0, max=1.0, subtype="FACTOR")
    job_stage: StringProperty(name="Stage")
    job_message: StringProperty(name="Message", description="What the last job did, or why it stopped")

    # --- the live object and its sliders (Explore)
    latents: CollectionProperty(type=ShapeGenLatent)
    live_object: PointerProperty(name="Live Object", type=bpy.types.Object)

    # --- the panel's settings as the core's options (the worker tasks' JSON)
    def prepare_options(self) -> dict:
        """Options of the core's prepare_meshes (the settings a prepared collection records)."""
        return self.prepare.options()

    def correspondence_options(self) -> dict:
        """CorrespondenceSettings fields (ShapeGenCorrespondenceSettings.options)."""
        return self.correspondence.options()

    def fit_options(self) -> dict:
        """FitSettings as plain data (`FitSettings.as_dict()`-shaped): Prepare's options
        nested under "prepare", the model's, correspondence and meshing stiffness (its
        schedule starting where the core's does, or at the stiffness when that is higher)."""
        fit = self.fit
        return {
            "prepare": self.prepare_options(),
            "model": fit.model, "latent_dim": fit.latent_dim or None,
            "correspondence": self.correspondence_options(),
            "deform": {"final_alpha": fit.mesh_stiffness,
                       "start_alpha": max(CORE_DEFAULTS.deform.start_alpha, fit.mesh_stiffness)},
        }


#: the groups before the settings that point to them (Blender registers them in this order)
CLASSES = (ShapeGenLatent, ShapeGenPrepareSettings, ShapeGenCorrespondenceSettings, ShapeGenFitSettings,
           ShapeGenGenerateSettings, ShapeGenExploreSettings, ShapeGenSettings)

# Blender 4.2 never lets go of a PropertyGroup class, even after unregister_class, and
# Blender-as-a-module shuts down only when Python frees the `bpy` module at exit. Through
# their methods and update callbacks these classes hold this module's globals, and with
# them `bpy`; Python clears the globals of the modules still alive at exit, but this one has
# died by then (its package is cleared first), so `bpy` outlived Python and the process
# crashed at exit (SIGSEGV). The classes hold the module itself, so it lives until Python
# clears its globals. (Blender 5.0 frees unregistered classes.)
for _cls in CLASSES:
    _cls._module = sys.modules[__name__]
del _cls


def register_properties():
    bpy.types.Scene.shapegen = PointerProperty(type=ShapeGenSettings)


def unregister_properties():
    del bpy.types.Scene.shapegen
