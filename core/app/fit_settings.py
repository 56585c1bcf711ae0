"""`FitSettings`: everything a fit needs besides the meshes (prepare, correspondence, model,
meshing), and how a model file's recorded settings are read, also those of files written
before they were one JSON string."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, fields

from ..base.errors import ModelFileError, ShapeGenError
from ..base.npzfile import ArraySpec, validate_arrays
from ..base.settings import Settings, SettingsError, legacy_settings, option
from ..correspond import CorrespondenceSettings
from ..generate.deform import DeformSettings
from ..models import MODEL_TYPES
from ..preprocess.collection import PrepareSettings

__all__ = ["FitSettings", "TemplateError", "TEMPLATE_CHOICES"]


TEMPLATE_CHOICES = ("nearest-data", "nearest-latent")


class TemplateError(ShapeGenError, ValueError):
    """An unknown template name or choice."""


@dataclass(frozen=True)
class FitSettings(Settings):
    """Everything a fit needs besides the meshes (defaults: thesis / docs/method.md)."""

    prepare: PrepareSettings = option(default_factory=PrepareSettings,
                                      help="alignment, scaling and landmarks; prepare.seed also seeds the model")
    model: str = option("bgplvm", "shape model", flag="--model", choices=tuple(MODEL_TYPES))
    latent_dim: int | None = option(None, "latent dimension (default: 80 % variance rule)", flag="--latent-dim",
                                    minimum=1)
    template: str | None = option(None, "correspondence template shape (default: the Chamfer medoid)",
                                  flag="--template")
    jobs: int | None = option(None, "worker processes reading files and registering shapes (default: all cores)",
                              flag="--jobs", minimum=1)
    scheduler: str | None = option(None, "run the per-shape registrations on Dask: tcp://host:8786 or local:N "
                                   "(needs Dask: pip install \"dask[distributed]\")", flag="--scheduler")
    mesh_template: str = option("nearest-data", "template mesh of generated shapes when none is asked for: "
                                "nearest-data, nearest-latent or a training shape's name", flag="--mesh-template")
    correspondence: CorrespondenceSettings = option(default_factory=CorrespondenceSettings,
                                                    help="the correspondence engine (§4.2)")
    deform: DeformSettings = option(default_factory=DeformSettings, help="meshing by embedded deformation (§6)")

    def __post_init__(self):
        super().__post_init__()
        if not self.mesh_template:
            raise SettingsError("mesh_template", f"must be {' or '.join(TEMPLATE_CHOICES)} or a training shape's name")


def _nest_prepare(data: Mapping) -> dict:
    """`data` with Prepare options given flat at the top level (n_landmarks, up_axis, ...;
    as the key/value settings of model files before issue 11 hold them) moved under
    "prepare"."""
    names = {f.name for f in fields(PrepareSettings)}
    nested = {key: value for key, value in data.items() if key not in names}
    nested["prepare"] = {key: value for key, value in data.items() if key in names}
    return nested


def _check_mesh_template(settings: FitSettings, names: list[str]) -> None:
    """The default meshing template must be a choice or one of the training shapes."""
    if settings.mesh_template not in TEMPLATE_CHOICES and settings.mesh_template not in names:
        raise SettingsError("mesh_template", f"must be {' or '.join(TEMPLATE_CHOICES)} or a training shape's "
                            f"name; no shape is named {settings.mesh_template!r}")


#: Model files before issue 11: settings as repr strings by (dotted) key, deformation
#: settings as numbers by key.
_LEGACY_SETTINGS_SPEC = {
    "settings_keys": ArraySpec("U", ("S",)),
    "settings_values": ArraySpec("U", ("S",)),
    "deform_keys": ArraySpec("U", ("K",)),
    "deform_values": ArraySpec("f", ("K",)),
}


def _load_fit_settings(arrays: dict, path) -> FitSettings:
    """The FitSettings a model file records (one JSON string, or the key/value arrays of
    files written before); invalid settings are a ModelFileError naming the file."""
    try:
        if "settings" in arrays or "settings_keys" not in arrays:
            validate_arrays(arrays, {"settings": ArraySpec("U", ())}, str(path))
            return FitSettings.from_json(str(arrays["settings"]), recorded=True)
        validate_arrays(arrays, _LEGACY_SETTINGS_SPEC, str(path))
        options = _nest_prepare(legacy_settings(arrays["settings_keys"].tolist(), arrays["settings_values"].tolist()))
        defaults = DeformSettings()
        options["deform"] = {key: type(getattr(defaults, key, 0.0))(value)
                             for key, value in zip(arrays["deform_keys"].tolist(), arrays["deform_values"].tolist())}
        return FitSettings.from_dict(options, recorded=True)
    except SettingsError as exc:
        raise ModelFileError(f"{path}: recorded settings are invalid: {exc}") from None
