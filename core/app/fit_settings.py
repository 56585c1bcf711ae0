"""`FitSettings`: everything a fit needs besides the meshes (prepare, correspondence, model,
meshing), and how a model file's recorded settings are read, also those of files written
before they were one JSON string."""

from __future__ import annotations

from dataclasses import dataclass

from ..base.errors import ModelFileError, ShapeGenError
from ..base.npzfile import ArraySpec, validate_arrays
from ..base.compat import is_key_value_layout, old_model_settings
from ..base.settings import Settings, SettingsError, option
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


def _check_mesh_template(settings: FitSettings, names: list[str]) -> None:
    """The default meshing template must be a choice or one of the training shapes."""
    if settings.mesh_template not in TEMPLATE_CHOICES and settings.mesh_template not in names:
        raise SettingsError("mesh_template", f"must be {' or '.join(TEMPLATE_CHOICES)} or a training shape's "
                            f"name; no shape is named {settings.mesh_template!r}")


def _load_fit_settings(arrays: dict, path) -> FitSettings:
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
