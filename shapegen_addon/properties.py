"""Scene-level settings of the ShapeGen panel (`scene.shapegen`)."""

from __future__ import annotations

import bpy
from bpy.props import EnumProperty, FloatProperty, IntProperty, PointerProperty, StringProperty

from ..core.landmarks import DEFAULT_LANDMARKS

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
    last_import_directory: StringProperty(name="Last Folder", subtype="DIR_PATH")


CLASSES = (ShapeGenSettings,)


def register_properties():
    bpy.types.Scene.shapegen = PointerProperty(type=ShapeGenSettings)


def unregister_properties():
    del bpy.types.Scene.shapegen
