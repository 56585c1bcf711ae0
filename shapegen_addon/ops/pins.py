"""Explore's pins: Add Pin and Clear Pins (the pins themselves and the live object's
response to them are `pins.py`'s). Both change the scene, so both are undo steps."""

from __future__ import annotations

import bpy
from bpy.props import IntProperty

from .. import pins
from ..keys import PIN_KEY
from .explore import NeedsLive, run_and_report

__all__ = ["CLASSES"]


class SHAPEGEN_OT_pin_add(NeedsLive, bpy.types.Operator):
    """Pin a point of the live object: an Empty at its landmark nearest the 3D cursor (or the
    landmark given); move the pin and the whole shape follows as far as the model allows"""

    bl_idname = "shapegen.pin_add"
    bl_label = "Add Pin"
    bl_options = {"REGISTER", "UNDO"}

    landmark: IntProperty(name="Landmark", default=-1, min=-1,
                          description="Landmark to pin (-1: the one nearest the 3D cursor)")

    def execute(self, context):
        def work():
            pin = pins.add_pin(context.scene, self.landmark)
            return f"'{pin.name}' pins landmark {pin[PIN_KEY]}: move it to reshape the live object"

        return run_and_report(self, work)


class SHAPEGEN_OT_pins_clear(NeedsLive, bpy.types.Operator):
    """Remove every pin; the live object goes back to its shape before the first pin"""

    bl_idname = "shapegen.pins_clear"
    bl_label = "Clear Pins"
    bl_options = {"REGISTER", "UNDO"}

    def execute(self, context):
        def work():
            return f"Removed {pins.clear_pins(context.scene)} pin(s)"

        return run_and_report(self, work)


CLASSES = (SHAPEGEN_OT_pin_add, SHAPEGEN_OT_pins_clear)
