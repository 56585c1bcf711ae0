"""Operators, one module per panel section (pins: Explore's pins), each exporting its `CLASSES` (registration order)."""

from . import cancel, correspondence, data, explore, fit, generate, outliers, pins

CLASSES = (*data.CLASSES, *correspondence.CLASSES, *outliers.CLASSES, *fit.CLASSES, *cancel.CLASSES,
           *generate.CLASSES, *explore.CLASSES, *pins.CLASSES)

__all__ = ["CLASSES"]
