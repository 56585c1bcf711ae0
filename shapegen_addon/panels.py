"""The sidebar panel: View3D › Sidebar › ShapeGen, one sub-panel per stage."""

from __future__ import annotations

import bpy

__all__ = ["CLASSES"]


class SHAPEGEN_PT_main(bpy.types.Panel):
    bl_label = "ShapeGen"
    bl_idname = "SHAPEGEN_PT_main"
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "ShapeGen"

    def draw(self, context):
        self.layout.label(text="Learn shapes from a collection", icon="MESH_MONKEY")


class SHAPEGEN_PT_data(bpy.types.Panel):
    bl_label = "Data"
    bl_idname = "SHAPEGEN_PT_data"
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "ShapeGen"
    bl_parent_id = "SHAPEGEN_PT_main"

    def draw(self, context):
        layout = self.layout
        settings = context.scene.shapegen
        layout.operator("shapegen.import_collection", icon="IMPORT")
        layout.prop(settings, "source_collection")
        column = layout.column(align=True)
        column.prop(settings, "n_landmarks")
        column.prop(settings, "up_axis")
        column.prop(settings, "align")
        column.prop(settings, "scale")
        column.prop(settings, "centre")
        column.prop(settings, "seed")
        column.prop(settings, "preview_spacing")
        layout.operator("shapegen.prepare", icon="PIVOT_BOUNDBOX")


CLASSES = (SHAPEGEN_PT_main, SHAPEGEN_PT_data)
