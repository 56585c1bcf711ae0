"""The sidebar panels draw without errors in every state (no model, model + live object,
a running job). Headless Blender never draws, so each panel's draw() runs against a
recording layout that checks every property, operator and icon it names exists."""

from __future__ import annotations

import dataclasses
import json
import time

import bpy
import pytest
from conftest import FAST_FIT, add_vase_collection, addon_module, load_model

STAGES = ("SHAPEGEN_PT_main", "SHAPEGEN_PT_data", "SHAPEGEN_PT_correspondence", "SHAPEGEN_PT_model",
          "SHAPEGEN_PT_generate", "SHAPEGEN_PT_explore")
ADVANCED = ("SHAPEGEN_PT_data_advanced", "SHAPEGEN_PT_correspondence_advanced", "SHAPEGEN_PT_model_advanced",
            "SHAPEGEN_PT_generate_advanced")
PANELS = STAGES + ADVANCED
#: research and rarely needed settings: only in a stage's Advanced sub-panel
RARELY_NEEDED = ("prepare.n_landmarks", "prepare.align", "prepare.scale", "prepare.centre", "prepare.seed",
                 "prepare.preview_spacing", "correspondence.stiffness", "correspondence.matching",
                 "fit.mesh_stiffness", "generate.sample_template")
ICONS = set(bpy.types.UILayout.bl_rna.functions["label"].parameters["icon"].enum_items.keys())


class RecordingLayout:
    def __init__(self, calls: list, qualified: bool = False):
        self.calls = calls
        self.qualified = qualified  # props recorded as "group.name" (scene.shapegen.<group>)
        self.enabled = True
        self.active = True

    def _icon(self, icon):
        assert icon in ICONS, f"unknown icon {icon!r}"

    def prop(self, data, name, **options):
        assert name in data.bl_rna.properties, f"{type(data).__name__} has no property {name!r}"
        self._icon(options.get("icon", "NONE"))
        group = data.path_from_id().split(".")[-1]
        self.calls.append(("prop", f"{group}.{name}" if self.qualified else name))

    def operator(self, idname, **options):
        category, name = idname.split(".")
        assert hasattr(bpy.types, f"{category.upper()}_OT_{name}"), f"no operator {idname}"
        self._icon(options.get("icon", "NONE"))
        self.calls.append(("operator", idname))

    def label(self, text="", icon="NONE", **options):
        self._icon(icon)
        self.calls.append(("label", text))

    def progress(self, factor=0.0, type="BAR", text=""):
        assert 0.0 <= factor <= 1.0
        self.calls.append(("progress", text))

    def template_icon(self, icon_value=0, scale=1.0):
        self.calls.append(("icon", icon_value))

    def separator(self, **options):
        pass

    def column(self, **options):
        return RecordingLayout(self.calls, self.qualified)

    row = box = column


class Context:
    def __init__(self):
        self.scene = bpy.context.scene
        self.space_data = None
        self.active_object = bpy.context.view_layer.objects.active


def _draw_all(panels=PANELS, qualified: bool = False) -> list:
    calls = []
    for name in panels:
        panel = getattr(bpy.types, name)
        fake = type("Fake", (), {"layout": RecordingLayout(calls, qualified), "properties": getattr(panel, "properties", ())})
        panel.draw(fake(), Context())
    return calls


def test_panels_draw_without_a_model():
    calls = _draw_all()
    assert ("operator", "shapegen.fit") in calls and ("label", "No fitted model") in calls


def test_panels_draw_with_a_model_a_live_object_and_a_map(model_files):
    load_model("ppca", model_files)
    bpy.ops.shapegen.explore()
    bpy.ops.shapegen.latent_map(size=64)
    calls = _draw_all()
    sliders = [c for c in calls if c == ("prop", "value")]
    assert len(sliders) == 2
    assert ("label", "Matches: closest points") in calls  # the model's data term (Correspondence.matching_summary)
    for idname in ("shapegen.explore_randomise", "shapegen.explore_snap", "shapegen.explore_bake",
                   "shapegen.sample", "shapegen.interpolate", "shapegen.modes_to_shape_keys"):
        assert ("operator", idname) in calls


def test_model_panel_shows_progress_and_cancel_while_a_job_runs(extension, tmp_path):
    jobs = addon_module(extension, "shapegen_addon.jobs")
    core_jobs = addon_module(extension, "core.app.jobs")
    job = core_jobs.BackgroundJob("selftest", {"steps": 50, "sleep": 0.1, "output": str(tmp_path / "out")})
    jobs.MANAGER.start(job, lambda status, prepared: None, label="selftest")
    try:
        calls = _draw_all()
    finally:
        jobs.MANAGER.kill()
    assert any(kind == "progress" for kind, _ in calls)
    assert ("operator", "shapegen.fit_cancel") in calls and ("operator", "shapegen.fit") not in calls


def test_correspondence_panel_shows_its_jobs_stage_and_percentage(extension):
    jobs = addon_module(extension, "shapegen_addon.jobs")
    add_vase_collection(extension)
    assert bpy.ops.shapegen.prepare(wait=True) == {"FINISHED"}
    assert not any(kind == "progress" for kind, _ in _draw_all(["SHAPEGEN_PT_correspondence"]))
    calls, status = [], None
    try:
        extra = json.dumps(FAST_FIT["correspondence"])
        assert bpy.ops.shapegen.find_correspondences(extra_settings=extra) == {"FINISHED"}
        deadline = time.monotonic() + 60
        while jobs.MANAGER.running and time.monotonic() < deadline:
            status = jobs.poll_job()
            if 0.0 < status.fraction < 1.0 and status.stage:  # a shape is registered, more run
                calls = _draw_all(["SHAPEGEN_PT_correspondence"])
                break
            time.sleep(0.02)
    finally:
        jobs.MANAGER.kill()
    progress = [text for kind, text in calls if kind == "progress"]
    assert progress == [f"{int(100 * status.fraction)} %  {status.stage}"]
    assert ("operator", "shapegen.fit_cancel") in calls


@pytest.mark.parametrize("name", ["fit", "fit_cancel", "load_model", "export_model", "sample", "interpolate",
                                  "modes_to_shape_keys", "explore", "explore_randomise", "explore_reset",
                                  "explore_snap", "explore_bake", "latent_map"])
def test_every_operator_has_a_description(name):
    cls = getattr(bpy.types, f"SHAPEGEN_OT_{name}")
    assert cls.bl_idname == f"shapegen.{name}" and (cls.__doc__ or "").strip()


def test_rarely_needed_settings_sit_in_closed_advanced_sub_panels():
    shown = {name for kind, name in _draw_all(STAGES, qualified=True) if kind == "prop"}
    assert not shown & set(RARELY_NEEDED), sorted(shown & set(RARELY_NEEDED))
    advanced = {name for kind, name in _draw_all(ADVANCED, qualified=True) if kind == "prop"}
    assert set(RARELY_NEEDED) <= advanced
    for name in ADVANCED:
        assert "DEFAULT_CLOSED" in getattr(bpy.types, name).bl_options


def test_tooltips_speak_to_artists_not_programmers():
    settings = bpy.types.Scene.bl_rna.properties["shapegen"].fixed_type
    groups = [p.fixed_type for p in settings.properties if p.type == "POINTER" and
              p.fixed_type.identifier.startswith("ShapeGen")]
    assert len(groups) == 5  # prepare, correspondence, fit, generate, explore
    texts = []
    for prop in [p for rna in (settings, *groups) for p in rna.properties]:
        texts.append(prop.description)
        if prop.type == "ENUM":
            texts += [item.description for item in prop.enum_items]
    for text in texts:
        assert "Settings." not in text and "core." not in text and "thesis" not in text, text


def test_every_blender_default_is_the_core_and_cli_default(extension):
    """The panel's defaults, as the worker receives them, are the core's default FitSettings,
    which are the `shapegen` defaults too (its options are built from the same classes)."""
    fit_settings = addon_module(extension, "core.app.fit_settings")
    core_settings = addon_module(extension, "core.base.settings")
    scene = bpy.data.scenes.new("fresh defaults")
    try:
        panel = scene.shapegen
        received = core_settings.settings_from_dict(fit_settings.FitSettings, panel.fit_options())
        assert received == fit_settings.FitSettings()
        for item, initialisation in (("ON", "spectral"), ("OFF", "closest"), ("AUTO", "auto")):
            panel.correspondence.differ_in_pose = item  # "Shapes Differ in Pose": Auto / On / Off
            received = core_settings.settings_from_dict(fit_settings.FitSettings, panel.fit_options())
            assert received.correspondence.data_term.initialisation == initialisation
        assert panel.generate.sample_template == fit_settings.FitSettings().mesh_template
        assert panel.fit.mesh_stiffness == fit_settings.FitSettings().deform.final_alpha
        # Interpolate's in-betweens and its two objects are the shapes `shapegen morph` writes
        assert panel.generate.interpolate_steps + 2 == addon_module(extension, "core.app.shape_model").PATH_SHAPES
    finally:
        bpy.data.scenes.remove(scene)
    # every choice the panel offers is one the core knows, and the other way round
    defaults = fit_settings.FitSettings()
    choices = {"prepare.up_axis": (defaults.prepare, "up_axis"), "prepare.align": (defaults.prepare, "align"),
               "prepare.scale": (defaults.prepare, "scale"), "prepare.centre": (defaults.prepare, "centre"),
               "correspondence.matching": (defaults.correspondence.data_term, "matching"),
               "fit.model": (defaults, "model")}
    rna = bpy.types.Scene.bl_rna.properties["shapegen"].fixed_type.properties
    for path, (owner, field_name) in choices.items():
        group, name = path.split(".")
        core_field = next(f for f in dataclasses.fields(owner) if f.name == field_name)
        enum = rna[group].fixed_type.properties[name]
        assert set(enum.enum_items.keys()) == set(core_field.metadata["choices"]), path


def test_each_panel_setting_that_is_a_core_option_has_the_cores_default_and_limits(extension):
    """A panel setting that is a core option (properties.CORE_OPTIONS) takes its default, its
    allowed values and its lower limit from the core's settings field, and sets no upper
    limit the core does not (a soft, drag-only one at most); every other panel setting is
    named Blender-only with a reason, so no setting holds a default of its own unnoticed."""
    properties = addon_module(extension, "shapegen_addon.ui.properties")
    latent_units = addon_module(extension, "core.models.latent_units")
    defaults = addon_module(extension, "core.app.fit_settings").FitSettings()
    rna = bpy.types.Scene.bl_rna.properties["shapegen"].fixed_type.properties
    sections = ("prepare", "correspondence", "fit", "generate", "explore")
    panel = {(section, p.identifier) for section in sections for p in rna[section].fixed_type.properties
             if p.identifier not in ("rna_type", "name")}
    assert panel == set(properties.CORE_OPTIONS) | set(properties.BLENDER_ONLY)
    assert not set(properties.CORE_OPTIONS) & set(properties.BLENDER_ONLY)
    assert all(properties.BLENDER_ONLY.values())  # each says why the core has no such option
    for (section, name), path in properties.CORE_OPTIONS.items():
        prop = rna[section].fixed_type.properties[name]
        *parents, leaf = path.split(".")
        owner = defaults
        for parent in parents:
            owner = getattr(owner, parent)
        core, meta = getattr(owner, leaf), next(f for f in dataclasses.fields(owner) if f.name == leaf).metadata
        if prop.type == "ENUM":
            shown = properties.INITIALISATION_OF if name == "differ_in_pose" else {k: k for k in prop.enum_items.keys()}
            assert shown[prop.default] == core, path
            if meta["choices"] is not None:
                assert {shown[k] for k in prop.enum_items.keys()} == set(meta["choices"]), path
            continue
        if name == "latent_dim":  # 0 shows the core's None
            assert (prop.default, core, prop.hard_min, meta["minimum"]) == (0, None, 0, 1)
        else:
            assert prop.default == pytest.approx(core, rel=1e-6), path
            if meta["minimum"] is not None:
                assert prop.hard_min == meta["minimum"], path
            elif meta["above"] is not None:  # inclusive in Blender: the next value the field shows
                assert prop.hard_min == pytest.approx(meta["above"] + 10 ** -prop.precision), path
            else:
                assert prop.hard_min < -1e9, path
        assert prop.hard_max > 1e9, path  # the core sets no upper limit
    value = properties.ShapeGenLatent.bl_rna.properties["value"]
    assert (value.soft_min, value.soft_max) == (-latent_units.SLIDER_LIMIT, latent_units.SLIDER_LIMIT)
