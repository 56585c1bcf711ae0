"""Explore: one live object driven by a slider per latent dimension, and the latent map.

Operators: Explore (create / reset the live object), Randomise, Reset, Snap to Nearest
Training Shape, Bake (the live object becomes an ordinary mesh), Latent Map (an image).
The sliders and the live object themselves are `latent.py`'s.
"""

from __future__ import annotations

import bpy
import numpy as np
from bpy.props import IntProperty, StringProperty

from ...core.base.errors import ShapeGenError
from .. import store
from ..keys import MAP_BOUNDS_KEY, MAP_DIMS_KEY, MODEL_ID_KEY, QUALITY_KEY, TEMPLATE_KEY
from ..latent import (bake_live, create_live, current_latent, live_object, reset_sliders, set_latent, set_values,
                     slider_units, tagged_latents)
from ..picture import latent_map_pixels

__all__ = ["CLASSES"]

MAP_NAME = "ShapeGen Latent Map"


# ------------------------------------------------------------------------------ operators
class NeedsLive(store.NeedsModel):
    """Operator mixin: a model and its live object (Explore) must exist."""

    @classmethod
    def poll(cls, context):
        if not super().poll(context):
            return False
        if live_object(context.scene) is None:
            cls.poll_message_set("No live object: press Explore first")
            return False
        return True


def run_and_report(operator, function) -> set[str]:
    """Run `function` (returns a message); a live shape that now fails the quality gate
    (latent.py keeps its reasons in keys.QUALITY_KEY) turns the report into a warning."""
    try:
        message = function()
    except ShapeGenError as exc:
        operator.report({"ERROR"}, str(exc))
        return {"CANCELLED"}
    live = live_object(bpy.context.scene)
    warning = str(live.get(QUALITY_KEY, "")) if live is not None else ""
    if warning:
        operator.report({"WARNING"}, f"{message + '. ' if message else ''}This shape fails the quality gate: {warning}")
    elif message:
        operator.report({"INFO"}, message)
    return {"FINISHED"}


class SHAPEGEN_OT_explore(store.NeedsModel, bpy.types.Operator):
    """Make the live object, a shape you change with the sliders below (or rebuild it)"""

    bl_idname = "shapegen.explore"
    bl_label = "Explore"
    bl_options = {"REGISTER", "UNDO"}

    template: StringProperty(name="Template", default="",
                             description="Training shape to deform (empty: the one nearest the mean shape)")

    def execute(self, context):
        def work():
            model = store.require_model(context.scene)
            obj, note = create_live(context.scene, model, self.template)
            return f"'{obj.name}': {model.latent_dim} sliders on template '{obj[TEMPLATE_KEY]}'.{note}"

        return run_and_report(self, work)


class SHAPEGEN_OT_explore_randomise(NeedsLive, bpy.types.Operator):
    """Set the sliders to a random plausible shape (within ±3 on every slider)"""

    bl_idname = "shapegen.explore_randomise"
    bl_label = "Randomise"
    bl_options = {"REGISTER", "UNDO"}

    def execute(self, context):
        def work():
            scene = context.scene
            model = store.require_model(scene)
            seed = scene.shapegen.explore.seed
            units = slider_units(scene)
            drawn = units.random(model.model.sample_latents, np.random.default_rng(seed))
            set_values(scene, drawn.values)
            scene.shapegen.explore.seed = seed + 1
            limit = f"±{units.limit:g}"
            if drawn.clipped:
                return f"Random shape (seed {seed}): no draw within {limit} in {drawn.redraws + 1}, clipped to {limit}"
            return f"Random shape (seed {seed}{f', {drawn.redraws} redrawn beyond {limit}' if drawn.redraws else ''})"

        return run_and_report(self, work)


class SHAPEGEN_OT_explore_reset(NeedsLive, bpy.types.Operator):
    """Move every slider back to the middle: the collection's average shape"""

    bl_idname = "shapegen.explore_reset"
    bl_label = "Reset"
    bl_options = {"REGISTER", "UNDO"}

    def execute(self, context):
        def work():
            reset_sliders(context.scene)
            return ""

        return run_and_report(self, work)


class SHAPEGEN_OT_explore_snap(NeedsLive, bpy.types.Operator):
    """Move the sliders to the training shape nearest to the live shape"""

    bl_idname = "shapegen.explore_snap"
    bl_label = "Snap to Nearest Training Shape"
    bl_options = {"REGISTER", "UNDO"}

    def execute(self, context):
        def work():
            scene = context.scene
            model = store.require_model(scene)
            units = slider_units(scene)
            training = model.training_latents()
            distances = ((units.to_values(training) - units.to_values(current_latent(scene))) ** 2).sum(axis=1)
            index = int(np.argmin(distances))
            set_latent(scene, training[index])
            return f"Snapped to '{model.names[index]}'"

        return run_and_report(self, work)


class SHAPEGEN_OT_explore_bake(NeedsLive, bpy.types.Operator):
    """Turn the live object into an ordinary mesh (no longer driven by the sliders)"""

    bl_idname = "shapegen.explore_bake"
    bl_label = "Bake"
    bl_options = {"REGISTER", "UNDO"}

    def execute(self, context):
        def work():
            obj = bake_live(context.scene)
            warning = obj.get(QUALITY_KEY, "")
            return f"Baked '{obj.name}'" + (f" (it fails the quality gate: {warning})" if warning else "")

        return run_and_report(self, work)


class SHAPEGEN_OT_latent_map(store.NeedsModel, bpy.types.Operator):
    """Draw a map of where the shapes lie on the first two sliders (image "ShapeGen Latent
    Map"): training shapes blue, outliers red, ShapeGen samples green, the live object white"""

    bl_idname = "shapegen.latent_map"
    bl_label = "Latent Map"
    bl_options = {"REGISTER"}

    size: IntProperty(name="Size", default=0, min=0, max=4096, description="Pixels (0: the panel's Map Size)")

    def execute(self, context):
        def work():
            scene = context.scene
            model = store.require_model(scene)
            size = self.size or scene.shapegen.explore.map_size
            live = live_object(scene)
            picture = latent_map_pixels(
                model.training_latents(), model.correspondence.outliers, size,
                samples=tagged_latents(scene, model),
                live=current_latent(scene) if live is not None else None)
            image = bpy.data.images.get(MAP_NAME)
            if image is not None and tuple(image.size) != (size, size):
                bpy.data.images.remove(image)
                image = None
            if image is None:
                image = bpy.data.images.new(MAP_NAME, size, size, alpha=True)
            image.pixels.foreach_set(picture.pixels.ravel())
            image.update()
            try:
                image.pack()  # keep the pixels with the .blend
            except RuntimeError:
                pass
            image[MAP_DIMS_KEY] = list(picture.dims)
            image[MAP_BOUNDS_KEY] = list(picture.bounds)
            image[MODEL_ID_KEY] = store.model_id(scene)
            n_out = int(np.sum(model.correspondence.outliers))
            axes = ", ".join(f"z{d + 1}" for d in picture.dims if d >= 0)
            return (f"Latent map of {len(model.names)} shapes ({n_out} outlier(s)) on {axes}: "
                    f"image '{image.name}'")

        return run_and_report(self, work)


CLASSES = (SHAPEGEN_OT_explore, SHAPEGEN_OT_explore_randomise, SHAPEGEN_OT_explore_reset,
           SHAPEGEN_OT_explore_snap, SHAPEGEN_OT_explore_bake, SHAPEGEN_OT_latent_map)
