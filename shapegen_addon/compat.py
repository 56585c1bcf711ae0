"""Reading .blend files saved by earlier versions of the add-on: panel settings saved before
they were grouped by panel section.

The core's own older files (settings moved, removed or added since) are read by
core/base/compat.py; its tables name the core's options. These are the panel's property
names on `scene.shapegen` (Blender stores a .blend's values by them), which the core has no
table of: many are Blender-only or named for the panel (fit_model, mesh_stiffness,
explore_seed). They are written in the same form as the core's `FIELDS_MOVED`: the flat
name of before → its dotted place now.
"""

from __future__ import annotations

__all__ = ["FLAT_NAMES", "regroup_flat_settings"]

#: where each panel setting lived in files saved before the settings were grouped by panel
#: section: old name on `scene.shapegen` → "group.name"
FLAT_NAMES = {
    **{name: f"prepare.{name}" for name in ("n_landmarks", "up_axis", "align", "scale", "centre", "seed",
                                            "preview_spacing", "use_base_mesh")},
    **{name: f"correspondence.{name}" for name in ("stiffness", "matching", "differ_in_pose")},
    "fit_model": "fit.model", "latent_dim": "fit.latent_dim", "mesh_stiffness": "fit.mesh_stiffness",
    **{name: f"generate.{name}" for name in ("sample_count", "sample_template", "interpolate_a", "interpolate_b",
                                             "interpolate_steps", "interpolate_mode", "interpolate_frames")},
    "explore_seed": "explore.seed", "map_size": "explore.map_size",
}


def regroup_flat_settings(settings) -> list[str]:
    """Move the panel settings a .blend saved before they were grouped (Blender keeps them
    as plain ID properties of `scene.shapegen`, a ShapeGenSettings: enums as item numbers,
    booleans as 0/1) into their groups, so an artist's settings survive the update. Returns
    the old names moved (Blender clamps a value out of range); one of the wrong type is
    dropped, its name followed by "?"."""
    moved = []
    for old, place in FLAT_NAMES.items():
        if old not in settings.keys():
            continue
        group, name = place.split(".")
        value, target = settings[old], getattr(settings, group)
        kind = target.bl_rna.properties[name]
        if kind.type == "ENUM":
            value = next((item.identifier for item in kind.enum_items if item.value == value), value)
        try:
            setattr(target, name, bool(value) if kind.type == "BOOLEAN" else value)
            moved.append(old)
        except (TypeError, ValueError):
            moved.append(f"{old}?")
        del settings[old]
    return moved
