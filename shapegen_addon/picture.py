"""Pictures drawn with numpy only (no bpy): the 2-D latent map as an RGBA pixel buffer.

Blender images store rows bottom-up, so row 0 of the buffer is the bottom of the picture
and larger latent values are drawn higher up, as in a plot.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["LatentMap", "latent_map_pixels", "map_dimensions", "COLOURS"]

COLOURS = {
    "background": (0.06, 0.06, 0.07, 1.0),
    "axis": (0.25, 0.25, 0.28, 1.0),
    "training": (0.25, 0.6, 1.0, 1.0),
    "outlier": (1.0, 0.22, 0.15, 1.0),
    "sample": (0.3, 0.9, 0.35, 1.0),
    "live": (1.0, 1.0, 1.0, 1.0),
}


@dataclass
class LatentMap:
    pixels: np.ndarray  # (size, size, 4) float32, rows bottom-up
    dims: tuple[int, int]  # latent dimensions on x and y (y = -1: a 1-D model, drawn on a line)
    bounds: tuple[float, float, float, float]  # x0, x1, y0, y1 of the drawn latent window
    training_pixels: np.ndarray  # (N, 2) int (column, row) of every training shape


def map_dimensions(latents: np.ndarray) -> tuple[int, int]:
    """The two latent dimensions with the largest spread of the training latents (in
    index order), or (0, -1) for a one-dimensional latent space."""
    q = latents.shape[1]
    if q == 1:
        return 0, -1
    order = np.argsort(-latents.var(axis=0), kind="stable")[:2]
    first, second = sorted(int(i) for i in order)
    return first, second


def _disc(pixels: np.ndarray, centre: tuple[int, int], radius: float, colour, ring: bool = False) -> None:
    size = pixels.shape[0]
    cx, cy = centre
    r = int(np.ceil(radius)) + 1
    x0, x1, y0, y1 = max(cx - r, 0), min(cx + r + 1, size), max(cy - r, 0), min(cy + r + 1, size)
    if x0 >= x1 or y0 >= y1:
        return
    yy, xx = np.mgrid[y0:y1, x0:x1]
    distance = np.hypot(xx - cx, yy - cy)
    mask = (np.abs(distance - radius) <= 1.0) if ring else (distance <= radius)
    pixels[y0:y1, x0:x1][mask] = colour


def latent_map_pixels(latents: np.ndarray, outliers: np.ndarray, size: int = 256,
                      samples: np.ndarray | None = None, live: np.ndarray | None = None) -> LatentMap:
    """Draw training latents (N, Q) as dots (outliers in red with a ring), optional sample
    latents (green) and the live object's latent (white ring) into a size × size image."""
    latents = np.asarray(latents, dtype=np.float64)
    outliers = np.asarray(outliers, dtype=bool).ravel()
    dims = map_dimensions(latents)

    def project(z: np.ndarray) -> np.ndarray:
        z = np.atleast_2d(z)
        y = z[:, dims[1]] if dims[1] >= 0 else np.zeros(len(z))
        return np.column_stack([z[:, dims[0]], y])

    points = project(latents)
    extra = [points]
    if samples is not None and len(samples):
        extra.append(project(samples))
    if live is not None:
        extra.append(project(live))
    everything = np.vstack(extra)
    lo, hi = everything.min(axis=0), everything.max(axis=0)
    span = np.maximum(hi - lo, 1e-9)
    if dims[1] < 0:
        lo[1], span[1] = -1.0, 2.0
    square = span.max()  # equal scale on both axes: distances in the map are latent distances
    centre = (lo + hi) / 2
    lo, hi = centre - 0.6 * square, centre + 0.6 * square  # 10 % margin each side

    def to_pixel(p: np.ndarray) -> np.ndarray:
        return np.clip(np.round((p - lo) / (hi - lo) * (size - 1)), 0, size - 1).astype(int)

    pixels = np.empty((size, size, 4), dtype=np.float32)
    pixels[:] = COLOURS["background"]
    origin = to_pixel(np.zeros(2))
    if 0 < origin[1] < size - 1:
        pixels[origin[1], :] = COLOURS["axis"]
    if 0 < origin[0] < size - 1:
        pixels[:, origin[0]] = COLOURS["axis"]
    radius = max(2.5, size / 80)
    if samples is not None and len(samples):
        for p in to_pixel(project(samples)):
            _disc(pixels, tuple(p), 0.6 * radius, COLOURS["sample"])
    training_pixels = to_pixel(points)
    for p, bad in zip(training_pixels, outliers):
        _disc(pixels, tuple(p), radius, COLOURS["outlier" if bad else "training"])
        if bad:
            _disc(pixels, tuple(p), 1.8 * radius, COLOURS["outlier"], ring=True)
    if live is not None:
        _disc(pixels, tuple(to_pixel(project(live))[0]), 1.5 * radius, COLOURS["live"], ring=True)
    return LatentMap(pixels, dims, (float(lo[0]), float(hi[0]), float(lo[1]), float(hi[1])), training_pixels)
