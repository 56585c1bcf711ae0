"""The fitted whole: `GenerativeShapeModel` = correspondence + shape model + meshing.

This is the single artefact passed between the CLI, the tests and Blender, saved as one
versioned `.npz` (format "shapegen.model", `allow_pickle=False`):

* the training shapes' meshes in the normalised frame and their transforms to input
  coordinates (so any result maps back, §3.4);
* the correspondence: landmarks (M, L, 3), the template's k-NN graph (kept for meshing,
  §6.2.2), residuals and outlier flags;
* the shape model's arrays (PPCA / GP-LVM / Bayesian GP-LVM, §5.3), prefixed `model__`;
* settings and metadata.

Generation: `sample_landmarks` → `mesh_from_landmarks` (embedded deformation of a
template training mesh, §6), with the template chosen by name, nearest training shape in
data space, or nearest in latent space (§6.2.5). Meshing uses the linear fast path
(`deform.LinearMeshMap`, cached per template) unless the full relaxation is asked for.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Callable

import numpy as np

from .collection import PreparedCollection, prepare_meshes
from .correspond import Correspondence, CorrespondenceSettings, correspond
from .deform import DeformSettings, EmbeddedDeformer, LinearMeshMap, smooth_curvature_flow
from .errors import Cancelled, ModelFileError, ShapeGenError
from . import meshset
from .mesh import Mesh
from .models import MODEL_TYPES, make_model, model_from_arrays
from .npzfile import ArraySpec, load_npz, save_npz

__all__ = ["FitSettings", "GenerativeShapeModel", "LatentMesher", "MODEL_FILE_FORMAT", "MODEL_FILE_VERSION",
           "TEMPLATE_CHOICES", "fit_meshes", "fit_shape_model"]

MODEL_FILE_FORMAT = "shapegen.model"
MODEL_FILE_VERSION = 1
TEMPLATE_CHOICES = ("nearest-data", "nearest-latent")

#: progress(fraction in [0, 1], stage text)
Progress = Callable[[float, str], None]


class TemplateError(ShapeGenError, ValueError):
    """An unknown template name or choice."""


@dataclass(frozen=True)
class FitSettings:
    """Everything a fit needs besides the meshes (defaults: thesis / method.md)."""

    n_landmarks: int = 800
    up_axis: str = "z"
    align: str = "consensus"
    scale: str = "variance"
    centre: str = "centroid"
    seed: int = 0
    model: str = "bgplvm"
    latent_dim: int | None = None
    template: str | None = None  # correspondence template; None = Chamfer medoid
    jobs: int | None = None  # correspondence worker processes; None = all cores
    correspondence: CorrespondenceSettings = field(default_factory=CorrespondenceSettings)
    deform: DeformSettings = field(default_factory=DeformSettings)

    def __post_init__(self):
        if self.model not in MODEL_TYPES:
            raise ValueError(f"unknown model {self.model!r}; choose from {', '.join(MODEL_TYPES)}")

    @classmethod
    def from_dict(cls, options: dict) -> "FitSettings":
        """FitSettings from plain data (JSON), the stage settings as nested dicts under
        "correspondence" and "deform". Unknown or invalid fields raise TypeError/ValueError."""
        rest = dict(options)
        return cls(correspondence=CorrespondenceSettings(**rest.pop("correspondence", {})),
                   deform=DeformSettings(**rest.pop("deform", {})), **rest)


def _scalar_settings(settings: FitSettings) -> dict[str, str]:
    out = {}
    for f in fields(settings):
        value = getattr(settings, f.name)
        if f.name in ("correspondence", "deform"):
            for sub in fields(value):
                out[f"{f.name}.{sub.name}"] = repr(getattr(value, sub.name))
        else:
            out[f.name] = repr(value)
    return out


class GenerativeShapeModel:
    """A fitted shape class: sample, encode, complete and mesh new shapes."""

    def __init__(self, meshes: list[Mesh], correspondence: Correspondence, model,
                 settings: dict[str, str] | None = None, deform_settings: DeformSettings = DeformSettings(),
                 metadata: dict[str, str] | None = None):
        if len(meshes) != len(correspondence.names):
            raise ShapeGenError(f"{len(meshes)} meshes for {len(correspondence.names)} corresponded shapes")
        self.meshes = meshes
        self.correspondence = correspondence
        self.model = model
        self.settings = dict(settings or {})
        self.deform_settings = deform_settings
        self.metadata = dict(metadata or {})
        self._linear_maps: dict[int, LinearMeshMap] = {}
        self._deformers: dict[int, EmbeddedDeformer] = {}
        self._training_latents: np.ndarray | None = None

    # ------------------------------------------------------------------ basics
    @property
    def names(self) -> list[str]:
        return list(self.correspondence.names)

    @property
    def n_landmarks(self) -> int:
        return self.correspondence.n_landmarks

    @property
    def latent_dim(self) -> int:
        return self.model.latent_dim

    @property
    def model_type(self) -> str:
        return self.model.model_type

    def training_matrix(self) -> np.ndarray:
        """Y: training landmarks, N × 3L (normalised frame)."""
        return self.correspondence.landmark_matrix()

    def training_latents(self) -> np.ndarray:
        if self._training_latents is None:
            self._training_latents = self.model.encode(self.training_matrix())
        return self._training_latents

    def shape_index(self, name: str) -> int:
        try:
            return self.names.index(name)
        except ValueError:
            raise TemplateError(
                f"no training shape named {name!r} (known: {', '.join(self.names[:12])}"
                + (", ..." if len(self.names) > 12 else "") + ")") from None

    # ------------------------------------------------------------------ generation
    def sample(self, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """n sampled landmark sets (n, L, 3), as the model's settings ask, and their latents."""
        flat, latents = self.model.sample_with_latents(n, rng)
        return flat.reshape(n, self.n_landmarks, 3), latents

    def decode(self, latents: np.ndarray) -> np.ndarray:
        flat = self.model.decode(np.atleast_2d(latents))
        return flat.reshape(len(flat), self.n_landmarks, 3)

    def encode(self, landmarks: np.ndarray) -> np.ndarray:
        landmarks = np.asarray(landmarks, dtype=np.float64)
        return self.model.encode(landmarks.reshape(len(landmarks), -1))

    def complete(self, partial: np.ndarray) -> np.ndarray:
        """Complete landmark sets with NaN where missing: (n, L, 3) → (n, L, 3)."""
        partial = np.asarray(partial, dtype=np.float64)
        if partial.ndim == 2:
            partial = partial[None]
        if partial.shape[1:] != (self.n_landmarks, 3):
            raise ShapeGenError(f"partial landmarks must have shape (n, {self.n_landmarks}, 3), got {partial.shape}")
        flat = partial.reshape(len(partial), -1)
        mask = np.isfinite(flat)
        if not mask.any(axis=1).all():
            raise ShapeGenError("a partial shape has no observed landmark at all")
        done = self.model.complete(np.where(mask, flat, 0.0), mask)
        return done.reshape(partial.shape)

    def choose_template(self, landmarks: np.ndarray, template: str | None) -> int:
        """Index of the training shape whose mesh is deformed (§6.2.5)."""
        landmarks = self._check_landmarks(landmarks)
        if template is None:
            template = self.settings.get("default_template") or "nearest-data"
            template = template.strip("'")
        if template == "nearest-data":
            distances = ((self.correspondence.points - landmarks[None]) ** 2).sum(axis=(1, 2))
            return int(np.argmin(distances))
        if template == "nearest-latent":
            z = self.encode(landmarks[None])[0]
            return int(np.argmin(((self.training_latents() - z) ** 2).sum(axis=1)))
        return self.shape_index(template)

    def _check_landmarks(self, landmarks: np.ndarray) -> np.ndarray:
        landmarks = np.asarray(landmarks, dtype=np.float64)
        if landmarks.shape != (self.n_landmarks, 3):
            raise ShapeGenError(f"landmarks must have shape ({self.n_landmarks}, 3) for this model, "
                                f"got {landmarks.shape}")
        if not np.isfinite(landmarks).all():
            bad = int(np.flatnonzero(~np.isfinite(landmarks).all(axis=1))[0])
            raise ShapeGenError(f"landmark {bad} is NaN or infinite")
        return landmarks

    def deformer(self, index: int) -> EmbeddedDeformer:
        if index not in self._deformers:
            self._deformers[index] = EmbeddedDeformer(
                self.meshes[index], self.correspondence.points[index], self.correspondence.edges,
                self.deform_settings)
        return self._deformers[index]

    def linear_map(self, index: int) -> LinearMeshMap:
        """The fast path for template `index` (factorised once, then cached)."""
        if index not in self._linear_maps:
            self._linear_maps[index] = LinearMeshMap(self.deformer(index))
        return self._linear_maps[index]

    def mean_template(self) -> int:
        """Index of the training shape nearest (in data space) to the model's mean shape:
        the natural template for meshes that move through the latent space."""
        mean = np.asarray(self.model.mean_, dtype=np.float64).reshape(self.n_landmarks, 3)
        return self.choose_template(mean, "nearest-data")

    def latent_mesher(self, index: int, dtype=np.float32) -> "LatentMesher":
        """The template `index` mesh as an affine function of the model's decode features
        (the live-slider path; see `LatentMesher`)."""
        return LatentMesher(self, index, dtype)

    def mesh_from_landmarks(self, landmarks: np.ndarray, template: str | None = None,
                            smooth: int = 0, exact: bool = False, name: str = "sample") -> Mesh:
        """Mesh the landmark set (L, 3) by embedded deformation of a template mesh.

        exact=False uses the linear fast path (final α only); exact=True runs the full
        stiffness relaxation (§6.2.3)."""
        landmarks = np.asarray(landmarks, dtype=np.float64)
        index = self.choose_template(landmarks, template)
        deformer = self.deformer(index)
        deformer.check_targets(landmarks)
        if exact:
            mesh = deformer.deform(landmarks, "relax", name=name)
        else:
            mesh = self.meshes[index].with_vertices(self.linear_map(index).vertices(landmarks), name=name)
        if smooth:
            mesh = smooth_curvature_flow(mesh, smooth)
        return mesh

    # ------------------------------------------------------------------ persistence
    def to_arrays(self) -> dict[str, np.ndarray]:
        arrays = {f"corr__{k}": v for k, v in self.correspondence.to_arrays().items()}
        arrays.update({f"model__{k}": v for k, v in self.model.to_arrays().items()})
        arrays.update(meshset.pack([m.vertices for m in self.meshes], [m.faces for m in self.meshes], prefix="mesh_"))
        deform = {f.name: getattr(self.deform_settings, f.name) for f in fields(self.deform_settings)}
        arrays["deform_keys"] = np.asarray(list(deform), dtype=str)
        arrays["deform_values"] = np.asarray(list(deform.values()), dtype=np.float64)
        arrays["settings_keys"] = np.asarray(list(self.settings), dtype=str)
        arrays["settings_values"] = np.asarray(list(self.settings.values()), dtype=str)
        arrays["metadata_keys"] = np.asarray(list(self.metadata), dtype=str)
        arrays["metadata_values"] = np.asarray(list(self.metadata.values()), dtype=str)
        return arrays

    def save(self, path: str | os.PathLike) -> Path:
        return save_npz(path, MODEL_FILE_FORMAT, MODEL_FILE_VERSION, self.to_arrays())

    @classmethod
    def load(cls, path: str | os.PathLike) -> "GenerativeShapeModel":
        spec = {
            **meshset.spec(prefix="mesh_"),
            "deform_keys": ArraySpec("U", ("K",)),
            "deform_values": ArraySpec("f", ("K",)),
            "settings_keys": ArraySpec("U", ("S",)),
            "settings_values": ArraySpec("U", ("S",)),
            "metadata_keys": ArraySpec("U", ("T",)),
            "metadata_values": ArraySpec("U", ("T",)),
        }
        arrays = load_npz(path, MODEL_FILE_FORMAT, MODEL_FILE_VERSION, spec)
        corr_arrays = {k[len("corr__"):]: v for k, v in arrays.items() if k.startswith("corr__")}
        model_arrays = {k[len("model__"):]: v for k, v in arrays.items() if k.startswith("model__")}
        try:
            correspondence = Correspondence.from_arrays(corr_arrays, source=str(path))
            model = model_from_arrays(model_arrays)
        except ModelFileError as exc:
            raise ModelFileError(f"{path}: {exc}") from None
        meshes = meshset.unpack(arrays, correspondence.names, str(path), prefix="mesh_")
        if model.n_features_ != 3 * correspondence.n_landmarks:
            raise ModelFileError(f"{path}: the shape model has {model.n_features_} features, "
                                 f"the correspondence {3 * correspondence.n_landmarks}")
        known = {f.name: f for f in fields(DeformSettings)}
        deform_values = {}
        for key, value in zip(arrays["deform_keys"].tolist(), arrays["deform_values"].tolist()):
            if key not in known:
                raise ModelFileError(f"{path}: unknown deformation setting {key!r}")
            deform_values[key] = int(value) if known[key].type in ("int", int) else float(value)
        return cls(meshes, correspondence, model,
                   settings=dict(zip(arrays["settings_keys"].tolist(), arrays["settings_values"].tolist())),
                   deform_settings=DeformSettings(**deform_values),
                   metadata=dict(zip(arrays["metadata_keys"].tolist(), arrays["metadata_values"].tolist())))


class LatentMesher:
    """Mesh vertices of one template as a direct function of a latent vector z.

    Every model decodes as decode(z) = mean_ + features(z) @ basis (`decode_features`,
    `decode_basis`) and the fast mesher is affine in the landmarks (`LinearMeshMap`), so

        vertices(z) = vertices(mean_) + features(z) @ linear_part(basis)

    exactly (for this template). The mesh-sized basis (K × 3V) is computed once; each new
    z then costs one small feature evaluation and one (K × 3V) product. Results are flat
    (3V,) arrays in `dtype` (float32 by default: what Blender stores), ready for a bulk
    vertex write.
    """

    def __init__(self, shape_model: GenerativeShapeModel, index: int, dtype=np.float32):
        linear = shape_model.linear_map(index)
        model = shape_model.model
        n_landmarks = shape_model.n_landmarks
        self.template_index = int(index)
        self.template_name = shape_model.names[index]
        self.latent_dim = shape_model.latent_dim
        self.n_vertices = shape_model.meshes[index].n_vertices
        self.offset = np.ascontiguousarray(
            linear.vertices(np.asarray(model.mean_, dtype=np.float64).reshape(n_landmarks, 3)).ravel(), dtype=dtype)
        basis = np.asarray(model.decode_basis(), dtype=np.float64).reshape(-1, n_landmarks, 3)
        self.basis = np.ascontiguousarray(linear.linear_part(basis).reshape(len(basis), -1), dtype=dtype)
        self._features = model.decode_features

    def flat_vertices(self, z: np.ndarray) -> np.ndarray:
        """(3V,) vertex coordinates for one latent vector z (Q,)."""
        features = np.asarray(self._features(np.asarray(z, dtype=np.float64).reshape(1, -1))[0], dtype=self.basis.dtype)
        return self.offset + features @ self.basis

    def vertices(self, z: np.ndarray) -> np.ndarray:
        """(V, 3) vertex coordinates for one latent vector z (Q,)."""
        return self.flat_vertices(z).reshape(-1, 3)


def fit_meshes(meshes_or_prepared, settings: FitSettings = FitSettings(), progress: Progress | None = None,
               should_cancel: Callable[[], bool] | None = None) -> GenerativeShapeModel:
    """The whole fit: prepare (§3.4, §4.2.1) → correspond (§4.2) → shape model (§5.3).

    Progress fractions: prepare 0–0.15, correspondence 0.15–0.75, model 0.75–1.
    `should_cancel` is polled between steps and inside correspondence; a cancel raises
    errors.Cancelled and nothing is returned.
    """
    report = progress or (lambda fraction, stage: None)
    cancelled = should_cancel or (lambda: False)
    start = time.perf_counter()

    def check():
        if cancelled():
            raise Cancelled("fit cancelled")

    if isinstance(meshes_or_prepared, PreparedCollection):
        prepared = meshes_or_prepared
    else:
        prepared = prepare_meshes(
            meshes_or_prepared, n_landmarks=settings.n_landmarks, up_axis=settings.up_axis,
            align=settings.align, scale=settings.scale, centre=settings.centre, seed=settings.seed,
            progress=lambda f, msg: report(0.15 * f, f"prepare: {msg}"))
    check()
    n_shapes = len(prepared)
    done = {"count": 0, "round": 0}

    def correspondence_progress(shape: str, stage: str, iteration: int) -> None:
        if stage == "registered":
            done["count"] += 1
        elif stage == "mean template":
            done["round"] = iteration
        rounds = settings.correspondence.groupwise_rounds + 1
        fraction = min(1.0, done["count"] / (n_shapes * rounds))
        report(0.15 + 0.6 * fraction, f"correspondence: {stage} {shape}")

    corr = correspond(prepared, settings.correspondence, template=settings.template, jobs=settings.jobs,
                      progress=correspondence_progress, should_cancel=cancelled)
    check()
    return fit_shape_model([s.mesh for s in prepared.shapes], corr, settings, progress=report,
                           should_cancel=cancelled, span=(0.75, 1.0), started=start)


def fit_shape_model(meshes: list[Mesh], corr: Correspondence, settings: FitSettings = FitSettings(),
                    progress: Progress | None = None, should_cancel: Callable[[], bool] | None = None,
                    span: tuple[float, float] = (0.0, 1.0), started: float | None = None) -> GenerativeShapeModel:
    """The shape-model stage (§5.3) on a finished correspondence of `meshes` (normalised
    frame): fit `settings.model` to the landmark matrix and bundle the fitted whole.
    Progress is reported within `span`; `started` (perf_counter) dates the fit's start."""
    report = progress or (lambda fraction, stage: None)
    cancelled = should_cancel or (lambda: False)
    start = time.perf_counter() if started is None else started
    low, high = span

    def check():
        if cancelled():
            raise Cancelled("fit cancelled")

    model = make_model(settings.model, settings.latent_dim, settings.seed)
    model.fit(corr.landmark_matrix(),
              progress=lambda f, msg: (check(), report(low + (high - low) * f, f"{settings.model}: {msg}")))
    check()
    report(high, "fitted")
    from . import __version__

    metadata = {"created": time.strftime("%Y-%m-%dT%H:%M:%S"), "fit_seconds": f"{time.perf_counter() - start:.2f}",
                "n_shapes": str(len(meshes)), "shapegen_version": __version__}
    return GenerativeShapeModel(list(meshes), corr, model, settings=_scalar_settings(settings),
                                deform_settings=settings.deform, metadata=metadata)
