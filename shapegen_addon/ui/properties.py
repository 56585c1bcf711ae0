"""Scene-level settings of the ShapeGen panel (`scene.shapegen`).

Everything the sidebar shows lives here and is saved with the .blend: data and fit
settings, the fitted model (a pointer to the Text datablock that holds it, see ../store.py),
the last job's outcome, the latent sliders of the live object and the generate options.
The running job's progress itself is runtime state (jobs.MANAGER), mirrored into
`job_state` / `job_fraction` / `job_stage` so the panel and scripts can read it.
"""

from __future__ import annotations

import bpy
from bpy.props import (BoolProperty, CollectionProperty, EnumProperty, FloatProperty, IntProperty,
                       PointerProperty, StringProperty)

from ...core.landmarks import DEFAULT_LANDMARKS
from ..latent import on_slider_changed
from ..prepared import PREPARE_SETTINGS

UP_AXIS_ITEMS = [
    ("z", "Z", "The input's +Z points up (Blender's convention)"),
    ("y", "Y", "The input's +Y points up (most OBJ/OFF files)"),
    ("x", "X", "The input's +X points up"),
    ("-z", "-Z", "The input's -Z points up"),
    ("-y", "-Y", "The input's -Y points up"),
    ("-x", "-X", "The input's -X points up"),
]
ALIGN_ITEMS = [
    ("consensus", "Consensus", "Principal axes, then every shape turned to agree with the collection's medoid"),
    ("pca", "PCA", "Principal axis of the horizontal spread on X, sign by third moment"),
    ("none", "None", "Only floor, centre and scale"),
]
SCALE_ITEMS = [
    ("variance", "Equal Variance", "Same total surface variance for every shape"),
    ("bbox", "Equal Box Volume", "Same bounding-box volume for every shape"),
    ("none", "None", "Keep sizes"),
]
CENTRE_ITEMS = [
    ("centroid", "Centroid", "Horizontal centre of the surface at the origin"),
    ("highest", "Highest Point", "Highest vertex above the origin (teapots)"),
    ("none", "None", "Keep the horizontal position"),
]
MATCHING_ITEMS = [
    ("closest", "Closest Points", "Each landmark is pulled to the closest surface point facing its way (the thesis)"),
    ("features", "Features", "Beyond the thesis: to the nearest surface point in position, surface normal and "
                             "height between the turning lines, so bellies and necks line up; lower "
                             "correspondence error on vases, but models fitted on it were less compact on real "
                             "classes. Where it fits more than a tenth of the shapes clearly worse than closest "
                             "points (walls leaning in on some shapes and out on others, as mugs can), the "
                             "collection is matched by closest points; the Correspondence panel says which "
                             "(docs/results.md)"),
]
REFINE_ITEMS = [
    ("none", "None", "Non-rigid ICP's landmarks as they are (the thesis)"),
    ("population", "Population", "Beyond the thesis: landmarks then slide on their surfaces to make the "
                                 "collection's landmark model compact while staying spread"),
]


MODEL_ITEMS = [
    ("ppca", "PPCA", "Probabilistic PCA: linear, fast; its modes can become native shape keys"),
    ("gplvm", "GP-LVM", "Gaussian-process latent variable model: non-linear"),
    ("bgplvm", "Bayesian GP-LVM", "Variational Bayesian GP-LVM: non-linear, picks its dimensions (ARD)"),
]
JOB_STATE_ITEMS = [
    ("IDLE", "Idle", "No background job has run"),
    ("RUNNING", "Running", "A job (Prepare, Find Correspondences or Fit) runs in the background"),
    ("DONE", "Done", "The last job finished; its result is in the scene"),
    ("FAILED", "Failed", "The last job failed; the scene (and any earlier model) is as it was"),
    ("CANCELLED", "Cancelled", "The last job was cancelled; the scene (and any earlier model) is as it was"),
]
TEMPLATE_ITEMS = [
    ("nearest-data", "Nearest Shape", "Deform the training mesh nearest to the sample's landmarks"),
    ("nearest-latent", "Nearest in Latent Space", "Deform the training mesh nearest in latent space"),
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
        name="Value", default=0.0, soft_min=-3.0, soft_max=3.0, precision=3,
        description="Position along this latent dimension, in training standard deviations",
        update=_on_latent_changed,
    )
    centre: FloatProperty(name="Centre", default=0.0, options={"HIDDEN"})
    scale: FloatProperty(name="Scale", default=1.0, options={"HIDDEN"})


class ShapeGenSettings(bpy.types.PropertyGroup):
    source_collection: PointerProperty(
        name="Collection", type=bpy.types.Collection,
        description="Training collection of mesh objects (one shape class)",
    )
    n_landmarks: IntProperty(
        name="Landmarks", default=DEFAULT_LANDMARKS, min=16, max=5000,
        description="Landmarks per shape (thesis: 700-800)",
    )
    up_axis: EnumProperty(name="Up Axis", items=UP_AXIS_ITEMS, default="z",
                          description="Which axis of the inputs points up")
    align: EnumProperty(name="Align", items=ALIGN_ITEMS, default="consensus")
    scale: EnumProperty(name="Scale", items=SCALE_ITEMS, default="variance")
    centre: EnumProperty(name="Centre", items=CENTRE_ITEMS, default="centroid")
    seed: IntProperty(name="Seed", default=0, min=0, description="Random seed (results are deterministic)")
    preview_spacing: FloatProperty(name="Spacing", default=1.5, min=0.0,
                                   description="Grid spacing of prepared shapes, in shape sizes")
    use_base_mesh: BoolProperty(
        name="Base Mesh", default=False,
        description="Read each object's own mesh, ignoring its modifiers (default: the mesh as the viewport "
                    "shows it, modifiers applied). Prepare and Fit read the same way",
    )
    last_import_directory: StringProperty(name="Last Folder", subtype="DIR_PATH")

    # --- fit (Correspondence + Model sub-panels)
    stiffness: FloatProperty(
        name="Stiffness", default=5.0, min=0.01, soft_max=100.0,
        description="Final stiffness of the correspondence (thesis: 5 vases and teapots, 10 cars; feature "
                    "matches end at 0.4 of it); higher keeps the template's shape, lower follows each shape closely",
    )
    matching: EnumProperty(name="Matches", items=MATCHING_ITEMS, default="closest",
                           description="What non-rigid ICP pulls each landmark to (CorrespondenceSettings.matching)")
    refine: EnumProperty(name="Refine", items=REFINE_ITEMS, default="none",
                         description="Groupwise refinement after non-rigid ICP (CorrespondenceSettings.refine)")
    mesh_stiffness: FloatProperty(
        name="Meshing Stiffness", default=2.0, min=0.01, soft_max=100.0,
        description="Stiffness of the embedded deformation that meshes generated landmarks: low follows "
                    "the landmarks closely, high keeps the template's mesh quality (2: under 0.1 % "
                    "flipped triangles on PSB airplanes)",
    )
    fit_model: EnumProperty(name="Model", items=MODEL_ITEMS, default="bgplvm")
    latent_dim: IntProperty(
        name="Latent Dimension", default=0, min=0, soft_max=20,
        description="Dimensions of the latent space (0: automatic, 80 % of the variance)",
    )

    # --- the fitted model (packed in a Text datablock, see store.py) and the last job
    model_text: PointerProperty(
        name="Model", type=bpy.types.Text,
        description="Text datablock holding the fitted model (the model .npz byte for byte, in its custom "
                    "property 'shapegen_model_npz')",
    )
    job_state: EnumProperty(name="Job State", items=JOB_STATE_ITEMS, default="IDLE")
    job_fraction: FloatProperty(name="Progress", default=0.0, min=0.0, max=1.0, subtype="FACTOR")
    job_stage: StringProperty(name="Stage")
    job_message: StringProperty(name="Message", description="Outcome of the last job (why it failed, ...)")

    # --- generate
    sample_count: IntProperty(name="Count", default=6, min=1, soft_max=100, description="Shapes to sample")
    sample_template: EnumProperty(name="Template", items=TEMPLATE_ITEMS, default="nearest-data")
    interpolate_a: PointerProperty(name="From", type=bpy.types.Object,
                                   description="First shape (a training shape or a ShapeGen sample)")
    interpolate_b: PointerProperty(name="To", type=bpy.types.Object,
                                   description="Second shape (a training shape or a ShapeGen sample)")
    interpolate_steps: IntProperty(name="Steps", default=5, min=1, soft_max=50,
                                   description="In-between shapes")
    interpolate_mode: EnumProperty(name="Output", items=INTERPOLATION_ITEMS, default="OBJECTS")
    interpolate_frames: IntProperty(name="Frames per Step", default=10, min=1, soft_max=100)

    # --- explore
    latents: CollectionProperty(type=ShapeGenLatent)
    live_object: PointerProperty(name="Live Object", type=bpy.types.Object)
    explore_seed: IntProperty(name="Seed", default=0, min=0, description="Seed of the next Randomise")
    map_size: IntProperty(name="Map Size", default=256, min=64, max=2048, description="Latent map size in pixels")

    # --- the panel's settings as the core's options (the worker tasks' JSON)
    def prepare_options(self) -> dict:
        """Options of the core's prepare_meshes (the settings a prepared collection records)."""
        return {name: getattr(self, name) for name in PREPARE_SETTINGS}

    def correspondence_options(self) -> dict:
        """CorrespondenceSettings fields: the stiffness schedule ends at `stiffness`; `matching`, `refine`."""
        return {"alpha_end": self.stiffness, "alpha_start": max(100.0, self.stiffness), "matching": self.matching,
                "refine": self.refine}

    def fit_options(self) -> dict:
        """FitSettings as plain data (`FitSettings.as_dict()`-shaped): Prepare's options
        nested under "prepare", the model's, correspondence and meshing stiffness."""
        return {
            "prepare": self.prepare_options(),
            "model": self.fit_model, "latent_dim": self.latent_dim or None,
            "correspondence": self.correspondence_options(),
            "deform": {"final_alpha": self.mesh_stiffness, "start_alpha": max(100.0, self.mesh_stiffness)},
        }


CLASSES = (ShapeGenLatent, ShapeGenSettings)


def register_properties():
    bpy.types.Scene.shapegen = PointerProperty(type=ShapeGenSettings)


def unregister_properties():
    del bpy.types.Scene.shapegen
