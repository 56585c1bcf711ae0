"""The sidebar panel: View3D › Sidebar › ShapeGen, one sub-panel per stage:
Data, Correspondence, Model, Generate, Explore. Each stage shows one button and the few
settings an artist changes; the rarely needed ones sit in that stage's Advanced
sub-panel, closed by default. The Data, Correspondence and Model panels show their
background job's progress and Cancel while it runs (the Model panel shows any job, and
the last job's outcome).

Panels only draw: they read `scene.shapegen` (one settings group per section), the
model's summary properties on its Text datablock (no model decoding while drawing) and
the job manager's runtime status.
"""

from __future__ import annotations

import bpy

from ..exclusion import excluded_names, outliers, training_collection
from ..jobs import MANAGER
from ..keys import (KEEP_POSE_KEY, LATENT_DIM_KEY, LIVE_KEY, MATCHING_KEY, MODEL_ID_KEY, MODEL_NAME_KEY, MODEL_TYPE_KEY,
                    PIN_DISTANCE_KEY, PIN_KEY,
                   N_LANDMARKS_KEY, N_SHAPES_KEY, OUTLIERS_KEY, QUALITY_KEY, RESIDUAL_MEDIAN_KEY, TEMPLATE_KEY)
from ..prepared import flagged_copies, prepared_collection_for, prepared_objects, prepared_pose_notes

__all__ = ["CLASSES"]


def _model_text(context):
    return context.scene.shapegen.model_text


class _SubPanel:
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "ShapeGen"
    bl_parent_id = "SHAPEGEN_PT_main"


class SHAPEGEN_PT_main(bpy.types.Panel):
    bl_label = "ShapeGen"
    bl_idname = "SHAPEGEN_PT_main"
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "ShapeGen"

    def draw(self, context):
        self.layout.label(text="Learn shapes from a collection", icon="MESH_MONKEY")


def _draw_progress(layout, settings) -> None:
    """The running job's label, progress bar (percentage and stage) and Cancel."""
    status = MANAGER.last_status
    fraction = status.fraction if status else settings.job_fraction
    stage = (status.stage if status and status.stage else settings.job_stage) or "starting"
    layout.label(text=f"Running: {MANAGER.label}", icon="SORTTIME")
    layout.progress(factor=fraction, type="BAR", text=f"{int(100 * fraction)} %  {stage}")
    layout.operator("shapegen.fit_cancel", icon="CANCEL")


def _draw_outcome(layout, settings) -> None:
    """The last job's message (one job at a time: Prepare, Find Correspondences or Fit)."""
    if settings.job_message:
        icon = {"FAILED": "ERROR", "CANCELLED": "CANCEL", "DONE": "CHECKMARK"}.get(settings.job_state, "INFO")
        layout.label(text=settings.job_message, icon=icon)


def _draw_outliers(layout, context, shown: int = 8) -> bool:
    """The training collection's outliers (the model's and the last Find Correspondences')
    with their reasons and Exclude Outliers and Refit; the objects left out of training
    with Include Excluded. True when it listed outliers."""
    collection = training_collection(context.scene.shapegen.source_collection)
    excluded = excluded_names(collection)
    flagged = [(name, reason) for name, reason in outliers(context.scene, collection) if name not in excluded]
    if flagged:
        box = layout.box()
        box.label(text=f"{len(flagged)} outlier(s):", icon="ERROR")
        for name, reason in flagged[:shown]:
            box.label(text=f"{name}: {reason}")
        if len(flagged) > shown:
            box.label(text=f"... and {len(flagged) - shown} more")
        box.operator("shapegen.exclude_outliers", icon="X")
    if excluded:
        box = layout.box()
        box.label(text=f"Left out of training: {', '.join(excluded)}", icon="HIDE_ON")
        box.operator("shapegen.include_excluded", icon="ADD")
    return bool(flagged)


class SHAPEGEN_PT_data(_SubPanel, bpy.types.Panel):
    bl_label = "Data"
    bl_idname = "SHAPEGEN_PT_data"

    def draw(self, context):
        layout = self.layout
        settings = context.scene.shapegen
        layout.operator("shapegen.import_collection", icon="IMPORT")
        layout.prop(settings, "source_collection")
        layout.prop(settings.prepare, "up_axis")
        _draw_prepare(layout, context)


def _draw_prepare(layout, context) -> None:
    """Prepare: Keep Pose for the active object, the button, its progress and the poses it
    turned or flagged."""
    settings = context.scene.shapegen
    active = context.active_object
    if active is not None and active.type == "MESH":
        layout.operator("shapegen.toggle_keep_pose", text=f"Keep Pose: {active.name}", icon="PINNED",
                        depress=bool(active.get(KEEP_POSE_KEY, False)))
    row = layout.row(align=True)
    row.operator("shapegen.prepare", icon="PIVOT_BOUNDBOX")
    row.prop(settings.prepare, "use_base_mesh", toggle=True, icon="MODIFIER_OFF")
    if MANAGER.task == "prepare":
        _draw_progress(layout, settings)
    prepared = prepared_collection_for(settings.source_collection)
    _draw_pose_notes(layout, prepared)
    flagged = flagged_copies(prepared)
    if flagged:
        layout.operator("shapegen.turn_flagged", text=f"Turn Flagged ({len(flagged)})", icon="FILE_REFRESH")


class _AdvancedPanel(_SubPanel):
    """A stage's rarely needed settings, closed until opened."""

    bl_label = "Advanced"
    bl_options = {"DEFAULT_CLOSED"}
    properties: tuple[str, ...] = ()  # "group.name" paths in scene.shapegen

    def draw(self, context):
        column = self.layout.column(align=True)
        for path in self.properties:
            group, name = path.split(".")
            column.prop(getattr(context.scene.shapegen, group), name)


class SHAPEGEN_PT_data_advanced(_AdvancedPanel, bpy.types.Panel):
    bl_idname = "SHAPEGEN_PT_data_advanced"
    bl_parent_id = "SHAPEGEN_PT_data"
    properties = ("prepare.n_landmarks", "prepare.align", "prepare.scale", "prepare.centre", "prepare.seed",
                  "prepare.preview_spacing")


def _draw_pose_notes(layout, collection, shown: int = 8) -> None:
    """The prepared shapes Prepare turned or whose pose looks wrong, with the reasons
    (the first `shown` lines, then how many more)."""
    if collection is None:
        return
    notes = prepared_pose_notes(prepared_objects(collection))
    if not notes:
        return
    box = layout.box()
    box.label(text=f"Poses in '{collection.name}':", icon="ORIENTATION_GIMBAL")
    for line in notes[:shown]:
        box.label(text=line, icon="ERROR" if ": pose looks wrong: " in line else "LOOP_BACK")
    if len(notes) > shown:
        box.label(text=f"... and {len(notes) - shown} more")


class SHAPEGEN_PT_correspondence(_SubPanel, bpy.types.Panel):
    bl_label = "Correspondence"
    bl_idname = "SHAPEGEN_PT_correspondence"

    def draw(self, context):
        layout = self.layout
        settings = context.scene.shapegen
        layout.prop(settings.correspondence, "differ_in_pose")
        layout.label(text="Optional: Fit finds them too", icon="INFO")
        layout.operator("shapegen.find_correspondences", icon="STICKY_UVS_LOC")
        if MANAGER.task == "correspond":
            _draw_progress(layout, settings)
        layout.label(text="Colours show the landmark index: same colour, same part", icon="INFO")
        listed = _draw_outliers(layout, context)
        text = _model_text(context)
        if text is None:
            layout.label(text="No model yet: Fit corresponds the landmarks again", icon="INFO")
            return
        box = layout.box()
        box.label(text=f"{text.get(N_LANDMARKS_KEY, '?')} landmarks on "
                       f"{text.get(N_SHAPES_KEY, '?')} shapes", icon="STICKY_UVS_LOC")
        box.label(text=f"Template: {text.get(TEMPLATE_KEY, '?')}")
        median = text.get(RESIDUAL_MEDIAN_KEY)
        if median is not None:
            box.label(text=f"Median residual: {100 * median:.2f} % of the diagonal")
        matching = text.get(MATCHING_KEY)
        if matching is not None:
            box.label(text=f"Matches: {matching}")
        model_outliers = [str(line) for line in text.get(OUTLIERS_KEY, [])]
        if model_outliers and not listed:  # outliers of a model fitted to another collection
            box.label(text=f"{len(model_outliers)} outlier(s) in the model:", icon="ERROR")
            for line in model_outliers[:8]:
                box.label(text=line)
        elif not model_outliers:
            box.label(text="No outliers", icon="CHECKMARK")


class SHAPEGEN_PT_correspondence_advanced(_AdvancedPanel, bpy.types.Panel):
    bl_idname = "SHAPEGEN_PT_correspondence_advanced"
    bl_parent_id = "SHAPEGEN_PT_correspondence"
    properties = ("correspondence.stiffness", "correspondence.matching")


class SHAPEGEN_PT_model(_SubPanel, bpy.types.Panel):
    bl_label = "Model"
    bl_idname = "SHAPEGEN_PT_model"

    def draw(self, context):
        layout = self.layout
        settings = context.scene.shapegen
        column = layout.column(align=True)
        column.prop(settings.fit, "model")
        column.prop(settings.fit, "latent_dim")
        if not MANAGER.running:
            layout.operator("shapegen.fit", icon="PLAY")
        else:
            _draw_progress(layout, settings)
        _draw_outcome(layout, settings)
        text = _model_text(context)
        box = layout.box()
        if text is None:
            box.label(text="No fitted model", icon="INFO")
        else:
            box.label(text=str(text.get(MODEL_NAME_KEY, text.name)), icon="OUTLINER_OB_POINTCLOUD")
            box.label(text=f"{text.get(MODEL_TYPE_KEY, '?')}, {text.get(LATENT_DIM_KEY, '?')} "
                           f"latent dimensions, {text.get(N_SHAPES_KEY, '?')} shapes")
            box.label(text=f"Stored in the .blend: Text '{text.name}'")
        row = layout.row(align=True)
        row.operator("shapegen.load_model", icon="FILE_FOLDER")
        row.operator("shapegen.export_model", icon="EXPORT")


class SHAPEGEN_PT_model_advanced(_AdvancedPanel, bpy.types.Panel):
    bl_idname = "SHAPEGEN_PT_model_advanced"
    bl_parent_id = "SHAPEGEN_PT_model"
    properties = ("fit.mesh_stiffness",)


class SHAPEGEN_PT_generate(_SubPanel, bpy.types.Panel):
    bl_label = "Generate"
    bl_idname = "SHAPEGEN_PT_generate"

    def draw(self, context):
        layout = self.layout
        settings = context.scene.shapegen
        column = layout.column(align=True)
        column.prop(settings.generate, "sample_count")
        layout.operator("shapegen.sample", icon="MOD_ARRAY")
        layout.separator()
        column = layout.column(align=True)
        column.prop(settings.generate, "interpolate_a")
        column.prop(settings.generate, "interpolate_b")
        column.prop(settings.generate, "interpolate_steps")
        column.prop(settings.generate, "interpolate_mode")
        if settings.generate.interpolate_mode == "SHAPE_KEYS":
            column.prop(settings.generate, "interpolate_frames")
        layout.operator("shapegen.interpolate", icon="IPO_LINEAR")
        layout.separator()
        row = layout.row()
        text = _model_text(context)
        row.enabled = text is not None and text.get(MODEL_TYPE_KEY) == "ppca"
        row.operator("shapegen.modes_to_shape_keys", icon="SHAPEKEY_DATA")


class SHAPEGEN_PT_generate_advanced(_AdvancedPanel, bpy.types.Panel):
    bl_idname = "SHAPEGEN_PT_generate_advanced"
    bl_parent_id = "SHAPEGEN_PT_generate"
    properties = ("generate.sample_template", "prepare.seed")


class SHAPEGEN_PT_explore(_SubPanel, bpy.types.Panel):
    bl_label = "Explore"
    bl_idname = "SHAPEGEN_PT_explore"

    def draw(self, context):
        layout = self.layout
        settings = context.scene.shapegen
        layout.operator("shapegen.explore", icon="HIDE_OFF")
        live = settings.live_object
        if live is not None and LIVE_KEY in live:
            column = layout.column(align=True)
            for item in settings.latents:
                column.prop(item, "value", text=item.name, slider=True)
            warning = str(live.get(QUALITY_KEY, ""))
            if warning:  # latent.py keeps the quality gate's reasons on the live object
                box = layout.box()
                box.label(text="This shape fails the quality gate:", icon="ERROR")
                for reason in warning.split("; "):
                    box.label(text=reason)
            row = layout.row(align=True)
            row.operator("shapegen.explore_randomise", icon="FILE_REFRESH")
            row.prop(settings.explore, "seed", text="")
            row = layout.row(align=True)
            row.operator("shapegen.explore_reset", icon="LOOP_BACK")
            row.operator("shapegen.explore_snap", text="Snap", icon="SNAP_ON")
            layout.operator("shapegen.explore_bake", icon="CHECKMARK")
            box = layout.box()  # pins: the live object takes the most probable shape given them (pins.py)
            row = box.row(align=True)
            row.operator("shapegen.pin_add", icon="PINNED")
            row.operator("shapegen.pins_clear", icon="X")
            box.prop(settings.explore, "show_uncertainty")
            key = live.get(MODEL_ID_KEY)
            for pin in context.scene.objects:
                if PIN_KEY in pin and pin.get(MODEL_ID_KEY) == key:
                    box.label(text=f"{pin.name}: {float(pin.get(PIN_DISTANCE_KEY, 0.0)):.4g} from the shape")
        layout.separator()
        row = layout.row(align=True)
        row.prop(settings.explore, "map_size")
        row.operator("shapegen.latent_map", icon="IMAGE_DATA")
        image = bpy.data.images.get("ShapeGen Latent Map")
        if image is not None:
            preview = image.preview_ensure()
            if preview is not None:
                layout.template_icon(icon_value=preview.icon_id, scale=8.0)
            layout.label(text=f"Image '{image.name}': open it in an Image Editor", icon="IMAGE")


# parents before their children (Blender registers a sub-panel after its parent)
CLASSES = (SHAPEGEN_PT_main, SHAPEGEN_PT_data, SHAPEGEN_PT_data_advanced, SHAPEGEN_PT_correspondence,
           SHAPEGEN_PT_correspondence_advanced, SHAPEGEN_PT_model, SHAPEGEN_PT_model_advanced,
           SHAPEGEN_PT_generate, SHAPEGEN_PT_generate_advanced, SHAPEGEN_PT_explore)
