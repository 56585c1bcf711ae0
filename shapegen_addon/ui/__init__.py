"""The sidebar: the scene's settings (`properties`, `scene.shapegen`) and the panels that draw them."""

from . import panels, properties

__all__ = ["panels", "properties"]
