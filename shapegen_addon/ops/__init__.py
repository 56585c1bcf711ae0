"""Operators, one module per panel section, each exporting its `CLASSES` (registration order)."""

from . import cancel, correspondence, data, explore, fit, generate, outliers

CLASSES = (*data.CLASSES, *correspondence.CLASSES, *outliers.CLASSES, *fit.CLASSES, *cancel.CLASSES,
           *generate.CLASSES, *explore.CLASSES)

__all__ = ["CLASSES"]
