"""`FitSettings`: everything a fit needs besides the meshes (prepare, correspondence, model,
meshing), and how a model file's recorded settings are read, also those of files written
before they were one JSON string. `RunOptions`: how a run is scheduled (worker processes,
a Dask cluster), which changes how long it takes but not what it makes, so no file
records it."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, fields

from ..base.errors import ModelFileError, ShapeGenError
from ..base.npzfile import ArraySpec, validate_arrays
from ..base.compat import RUN_OPTIONS_REMOVED, is_key_value_layout, old_model_settings
from ..base.settings import Settings, SettingsError, option
from ..correspond import CorrespondenceSettings
from ..generate.deform import DeformSettings
from ..models import MODEL_TYPES
from ..preprocess.collection import PrepareSettings

__all__ = ["FitSettings", "RunOptions", "split_run_options", "TemplateError", "TEMPLATE_CHOICES", "load_fit_settings",
           "check_mesh_template"]


TEMPLATE_CHOICES = ("nearest-data", "nearest-latent")


class TemplateError(ShapeGenError, ValueError):
    """An unknown template name or choice."""


@dataclass(frozen=True)
class FitSettings(Settings):
    """Everything a fit needs besides the meshes (defaults: thesis / docs/method.md): what
    the model is, recorded in its file. How the run is scheduled is not here (`RunOptions`)."""

    #: run options that model files recorded among these settings (core/base/compat.py);
    #: not annotated: a class attribute, not a field
    FIELDS_REMOVED = RUN_OPTIONS_REMOVED

    prepare: PrepareSettings = option(default_factory=PrepareSettings,
                                      help="alignment, scaling and landmarks; prepare.seed also seeds the model")
    model: str = option("bgplvm", "shape model", flag="--model", choices=tuple(MODEL_TYPES))
    latent_dim: int | None = option(None, "latent dimension (default: 80 % variance rule)", flag="--latent-dim",
                                    minimum=1)
    template: str | None = option(None, "correspondence template shape (default: the Chamfer medoid)",
                                  flag="--template")
    mesh_template: str = option("nearest-data", "template mesh of generated shapes when none is asked for: "
                                "nearest-data, nearest-latent or a training shape's name", flag="--mesh-template")
    correspondence: CorrespondenceSettings = option(default_factory=CorrespondenceSettings,
                                                    help="the correspondence engine (§4.2)")
    deform: DeformSettings = option(default_factory=DeformSettings, help="meshing by embedded deformation (§6)")

    def __post_init__(self):
        super().__post_init__()
        if not self.mesh_template:
            raise SettingsError("mesh_template", f"must be {' or '.join(TEMPLATE_CHOICES)} or a training shape's name")


@dataclass(frozen=True)
class RunOptions(Settings):
    """How a run is scheduled: the same settings make the same correspondence and model with
    any of these, so they are options of the run (the command line, a job's arguments, the
    add-on's Extra Settings) and never recorded in a file, nor compared when an earlier
    result is reused (core/app/stages.py)."""

    jobs: int | None = option(None, "worker processes reading files and registering shapes (default: all cores)",
                              flag="--jobs", minimum=1)
    scheduler: str | None = option(None, "run the per-shape registrations on Dask: tcp://host:8786 or local:N "
                                   "(needs Dask: pip install \"dask[distributed]\")", flag="--scheduler")


#: the names of the run options
RUN_OPTIONS = tuple(f.name for f in fields(RunOptions))


def split_run_options(data: Mapping) -> tuple[RunOptions, dict]:
    """(the `RunOptions` named at the top level of plain data, the rest of it): for option
    dicts that give both, such as the add-on's Extra Settings ({"jobs": 1, "prepare": ...}).
    An invalid run option raises SettingsError naming it."""
    run = RunOptions.from_dict({name: value for name, value in data.items() if name in RUN_OPTIONS})
    return run, {name: value for name, value in data.items() if name not in RUN_OPTIONS}


def check_mesh_template(settings: FitSettings, names: list[str]) -> None:
    """The default meshing template must be a choice or one of the training shapes."""
    if settings.mesh_template not in TEMPLATE_CHOICES and settings.mesh_template not in names:
        raise SettingsError("mesh_template", f"must be {' or '.join(TEMPLATE_CHOICES)} or a training shape's "
                            f"name; no shape is named {settings.mesh_template!r}")


def load_fit_settings(arrays: dict, path) -> FitSettings:
    """The FitSettings a model file records (one JSON string, or the key/value arrays of
    files written before, `compat.old_model_settings`); invalid settings are a
    ModelFileError naming the file."""
    try:
        if not is_key_value_layout(arrays):
            validate_arrays(arrays, {"settings": ArraySpec("U", ())}, str(path))
            return FitSettings.from_json(str(arrays["settings"]), recorded=True)
        return FitSettings.from_dict(old_model_settings(arrays, str(path)), recorded=True)
    except SettingsError as exc:
        raise ModelFileError(f"{path}: recorded settings are invalid: {exc}") from None
