"""The fitted whole: `GenerativeShapeModel` = correspondence + shape model + meshing.

This is the single artefact passed between the CLI, the tests and Blender, saved as one
versioned `.npz` (format "shapegen.model", `allow_pickle=False`):

* the training shapes' meshes in the model frame: the normalised frame, each shape moved
  by its pose from its landmarks where the correspondence posed it (core/correspond/
  posing.py); their transforms to input coordinates are the correspondence's
  `model_transforms` (so any result maps back, §3.4), and, for meshes read from files with
  polygons or UVs, their files' layouts (`layout.FaceLayout`: polygons, UVs per corner;
  arrays `mesh_layout_*`, version 2; version-1 files load without them);
* the correspondence: landmarks (M, L, 3), the template's k-NN graph (kept for meshing,
  §6.2.2), residuals and outlier flags;
* the shape model's arrays (PPCA / GP-LVM / Bayesian GP-LVM, §5.3), prefixed `model__`;
* the fit's settings (`FitSettings`, one JSON string) and metadata;
* optionally the training meshes' part labels (`labels.PartLabels`: `label_names` (P,) and
  `mesh_face_labels`, the part of every face of every mesh in order, -1 for none), read
  beside the files a model is fitted from; files without them load with none;
* what Blender needs at once when a model is installed, computed where the model is
  fitted (the worker), so installing it costs no encoding on Blender's main thread: the
  training shapes' latent vectors `training_latents` (N, Q; the latent map's points, Snap's
  targets) and the sliders' units `latent_centre` / `latent_scale` (core/models/latent_units.py).
  Files written before these arrays existed still load: they are computed on load.

Generation: `sample_landmarks` → `mesh_from_landmarks` (embedded deformation of a
template training mesh, §6), with the template chosen by name, nearest training shape in
data space, or nearest in latent space (§6.2.5). Meshing uses the linear fast path
(`deform.LinearMeshMap`, cached per template) unless the full relaxation is asked for.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from ..base.errors import ModelFileError, ShapeGenError
from ..base.npzfile import ArraySpec, load_npz, save_npz, validate_arrays
from ..correspond import Correspondence
from ..generate.deform import DeformSettings, EmbeddedDeformer, LinearMeshMap, smooth_curvature_flow
from ..meshes import meshset
from ..meshes.labels import PartLabels
from ..meshes.layout import pack_layouts, unpack_layouts
from ..meshes.mesh import Mesh, MeshReport
from ..meshes.spill import full_mesh
from ..models import model_from_arrays
from ..models.latent_units import LatentUnits
from ..preprocess.rotations import up_rotation
from .fit_settings import TEMPLATE_CHOICES, FitSettings, TemplateError, load_fit_settings

__all__ = ["GenerativeShapeModel", "LatentMesher", "PinCompletion", "MODEL_FILE_FORMAT", "MODEL_FILE_VERSION",
           "MODEL_FILE_VERSIONS", "PATH_SHAPES"]


MODEL_FILE_FORMAT = "shapegen.model"


MODEL_FILE_VERSION = 2


#: Versions `GenerativeShapeModel.load` reads (1: before the meshes' face layouts).
MODEL_FILE_VERSIONS = (1, 2)

#: shapes on a path between two latents by default, both ends included: `shapegen morph`
#: writes them all, Blender's Interpolate adds the PATH_SHAPES − 2 between its two objects
PATH_SHAPES = 8


@dataclass(frozen=True)
class PinCompletion:
    """The most probable shape given pinned landmarks (`GenerativeShapeModel.complete_from_pins`).

    landmarks: (L, 3) posterior mean shape (model frame); std: (L,) each landmark's posterior
    standard deviation, the root of the summed variances of its x, y and z (the root mean
    square distance of the landmark from where it is shown); latent: (Q,) the latent point
    of the shape (PPCA: E[z | pins]), the sliders' position."""

    landmarks: np.ndarray
    std: np.ndarray
    latent: np.ndarray

    def distances(self, pins: Mapping[int, np.ndarray]) -> dict[int, float]:
        """How far the shape stays from each pin (landmark index -> distance)."""
        return {int(i): float(np.linalg.norm(self.landmarks[int(i)] - np.asarray(p, dtype=np.float64)))
                for i, p in pins.items()}


class GenerativeShapeModel:
    """A fitted shape class: sample, encode, complete and mesh new shapes. In the run that
    fitted it, a dense training mesh may still be a `spill.StoredMesh` (kept on disk for
    the run): loaded when it is meshed from, streamed into the file by `save`."""

    def __init__(self, meshes: list[Mesh], correspondence: Correspondence, model,
                 settings: FitSettings = FitSettings(), metadata: dict[str, str] | None = None,
                 training_latents: np.ndarray | None = None, latent_units: LatentUnits | None = None,
                 part_labels: PartLabels | None = None):
        if len(meshes) != len(correspondence.names):
            raise ShapeGenError(f"{len(meshes)} meshes for {len(correspondence.names)} corresponded shapes")
        if part_labels is not None and len(part_labels.parts) != len(meshes):
            raise ShapeGenError(f"part labels of {len(part_labels.parts)} meshes for {len(meshes)} meshes")
        #: the training meshes' part labels (core/meshes/labels.py), None when the files had none;
        #: a sample's faces have the parts of its template's
        self.part_labels = part_labels
        self.meshes = meshes
        self.correspondence = correspondence
        self.model = model
        self.settings = settings
        self.metadata = dict(metadata or {})
        self._linear_maps: dict[tuple[int, float], LinearMeshMap] = {}
        self._deformers: dict[tuple[int, float], EmbeddedDeformer] = {}
        self._training_latents = training_latents
        self._latent_units = latent_units
        self._training_points: np.ndarray | None = None

    # ------------------------------------------------------------------ basics
    @property
    def names(self) -> list[str]:
        return list(self.correspondence.names)

    @property
    def file_axes(self) -> np.ndarray:
        """3 × 3, rows: the model frame's x, y, z in the coordinates of the files it was
        fitted from (the inverse of Prepare's up rotation, §3.1): `vertices @ file_axes`
        turns a Z-up mesh of the model into the files' axis convention (Y up for files read
        with `--up y`), which is how written samples leave the CLI."""
        return up_rotation(self.settings.prepare.up_axis)

    @property
    def deform_settings(self) -> DeformSettings:
        return self.settings.deform

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
        """Y: training landmarks, N × 3L (model frame)."""
        return self.correspondence.landmark_matrix()

    @property
    def training_points(self) -> np.ndarray:
        """(N, L, 3) the training landmarks in the model frame, on `meshes` (the
        correspondence's `model_points`, computed once)."""
        if self._training_points is None:
            self._training_points = self.correspondence.model_points()
        return self._training_points

    def training_latents(self) -> np.ndarray:
        """The training shapes' latent vectors (N, Q): encoded once (a search per shape for
        the GP-LVMs), then kept and saved with the model."""
        if self._training_latents is None:
            self._training_latents = self.model.encode(self.training_matrix())
        return self._training_latents

    def latent_units(self) -> LatentUnits:
        """The sliders' units (core/models/latent_units.py) from the training latents."""
        if self._latent_units is None:
            self._latent_units = LatentUnits.from_training(self.training_latents())
        return self._latent_units

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

    def complete_from_pins(self, pins: Mapping[int, np.ndarray], start: np.ndarray | None = None) -> PinCompletion:
        """The most probable shape given pinned landmarks {landmark index: position (3,) in
        the model frame}: §5.5.3's completion made soft, each pin a noisy observation under
        the model's noise, so a pin the class cannot reach is followed only as far as the
        model allows (`ShapeModel.posterior`: PPCA's exact conditional Gaussian; the GP-LVMs'
        MAP latent point, searched from `start` (Q,) when given, e.g. the live object's).
        Returns the shape, each landmark's posterior standard deviation and the latent."""
        if not pins:
            raise ShapeGenError("no pins: pin at least one landmark")
        y = np.zeros((self.n_landmarks, 3))
        mask = np.zeros((self.n_landmarks, 3), dtype=bool)
        for index, position in pins.items():
            if isinstance(index, bool) or not isinstance(index, (int, np.integer)) \
                    or not 0 <= int(index) < self.n_landmarks:
                raise ShapeGenError(f"pin landmark {index!r} is not a landmark index of this model "
                                    f"(0 to {self.n_landmarks - 1})")
            position = np.asarray(position, dtype=np.float64)
            if position.shape != (3,) or not np.isfinite(position).all():
                raise ShapeGenError(f"pin of landmark {index}: position must be 3 finite numbers, got "
                                    f"{np.asarray(position).tolist()}")
            y[int(index)], mask[int(index)] = position, True
        found = self.model.posterior(y.ravel(), mask.ravel(), start=start)
        std = np.sqrt(np.maximum(found.variance, 0.0).reshape(self.n_landmarks, 3).sum(axis=1))
        return PinCompletion(found.mean.reshape(self.n_landmarks, 3), std, np.asarray(found.latent, dtype=np.float64))

    def vertex_std(self, landmark_std: np.ndarray, index: int, stiffness: float | None = None) -> np.ndarray:
        """Per-vertex standard deviation (V,) of template `index`'s mesh from the landmarks'
        (L,): carried to the vertices by the weights that carry the landmarks' positions in
        meshing (`LinearMeshMap.linear_part`, §6.2), so a vertex shows the uncertainty of
        the landmarks that move it; clipped at 0 (the weights may be slightly negative)."""
        landmark_std = np.asarray(landmark_std, dtype=np.float64)
        if landmark_std.shape != (self.n_landmarks,):
            raise ShapeGenError(f"landmark std must have shape ({self.n_landmarks},), got {landmark_std.shape}")
        directions = np.zeros((1, self.n_landmarks, 3))
        directions[0, :, 0] = landmark_std
        return np.maximum(self.linear_map(index, stiffness).linear_part(directions)[0, :, 0], 0.0)

    def choose_template(self, landmarks: np.ndarray, template: str | None) -> int:
        """Index of the training shape whose mesh is deformed (§6.2.5). nearest-data and
        nearest-latent choose among the shapes the correspondence did not flag as outliers
        (among all when it flagged every one); a name is used as given."""
        return int(self.template_order(landmarks, template)[0])

    def path_template(self, latent_a: np.ndarray, latent_b: np.ndarray, template: str | None) -> int:
        """Index of the one template mesh of a path between two latents (a morph, Blender's
        Interpolate): chosen (`choose_template`) for the shape at the path's midpoint, so every
        step is the same mesh and moves only as its landmarks do. A template chosen per step
        would switch mid-path: the mesh would jump and change its vertex count (§6.2.5)."""
        midpoint = self.decode(0.5 * (np.asarray(latent_a, dtype=np.float64) + np.asarray(latent_b, dtype=np.float64)))
        return self.choose_template(midpoint[0], template)

    @staticmethod
    def latent_path(latent_a: np.ndarray, latent_b: np.ndarray, count: int = PATH_SHAPES
                    ) -> tuple[np.ndarray, np.ndarray]:
        """`count` evenly spaced points of the straight latent line from `latent_a` to
        `latent_b`, both ends included (a morph, Blender's Interpolate): (weights (count,)
        from 0 to 1, latents (count, d))."""
        if count < 2:
            raise ShapeGenError(f"a path needs at least 2 shapes (both ends), got {count}")
        weights = np.linspace(0.0, 1.0, count)
        latent_a, latent_b = np.asarray(latent_a, dtype=np.float64), np.asarray(latent_b, dtype=np.float64)
        return weights, (1 - weights[:, None]) * latent_a + weights[:, None] * latent_b

    def template_order(self, landmarks: np.ndarray, template: str | None) -> np.ndarray:
        """The templates for a landmark set, best first: a named template alone, else the
        candidates (`template_candidates`) nearest first, in data space (nearest-data) or
        latent space (nearest-latent). The gated sampler (core/generate/sampling.py) tries the next
        ones when a mesh fails the quality gate."""
        landmarks = self._check_landmarks(landmarks)
        if template is None:
            template = self.settings.mesh_template
        if template not in TEMPLATE_CHOICES:
            return np.array([self.shape_index(template)])
        candidates = self.template_candidates()
        if template == "nearest-data":
            distances = ((self.training_points[candidates] - landmarks[None]) ** 2).sum(axis=(1, 2))
        else:
            z = self.encode(landmarks[None])[0]
            distances = ((self.training_latents()[candidates] - z) ** 2).sum(axis=1)
        return candidates[np.argsort(distances, kind="stable")]

    def template_candidates(self) -> np.ndarray:
        """Indices of the training shapes that may serve as a mesh template: those not
        flagged as correspondence outliers (all of them when every shape is flagged)."""
        fits = np.flatnonzero(~np.asarray(self.correspondence.outliers, dtype=bool))
        return fits if len(fits) else np.arange(len(self.names))

    def _check_landmarks(self, landmarks: np.ndarray) -> np.ndarray:
        landmarks = np.asarray(landmarks, dtype=np.float64)
        if landmarks.shape != (self.n_landmarks, 3):
            raise ShapeGenError(f"landmarks must have shape ({self.n_landmarks}, 3) for this model, "
                                f"got {landmarks.shape}")
        if not np.isfinite(landmarks).all():
            bad = int(np.flatnonzero(~np.isfinite(landmarks).all(axis=1))[0])
            raise ShapeGenError(f"landmark {bad} is NaN or infinite")
        return landmarks

    def deformer(self, index: int, stiffness: float | None = None) -> EmbeddedDeformer:
        """The embedded deformation of template `index` at final α `stiffness` (default:
        the model's deform settings), cached."""
        alpha = self.deform_settings.final_alpha if stiffness is None else float(stiffness)
        key = (int(index), alpha)
        if key not in self._deformers:
            self._deformers[key] = EmbeddedDeformer(
                full_mesh(self.meshes[index]), self.training_points[index], self.correspondence.edges,
                replace(self.deform_settings, final_alpha=alpha))
        return self._deformers[key]

    def linear_map(self, index: int, stiffness: float | None = None) -> LinearMeshMap:
        """The fast path for template `index` at final α `stiffness` (default: the model's),
        factorised once, then cached."""
        alpha = self.deform_settings.final_alpha if stiffness is None else float(stiffness)
        key = (int(index), alpha)
        if key not in self._linear_maps:
            self._linear_maps[key] = LinearMeshMap(self.deformer(index, alpha))
        return self._linear_maps[key]

    def mean_template(self) -> int:
        """Index of the training shape nearest (in data space) to the model's mean shape,
        outliers skipped: the natural template for meshes that move through the latent space."""
        mean = np.asarray(self.model.mean_, dtype=np.float64).reshape(self.n_landmarks, 3)
        return self.choose_template(mean, "nearest-data")

    def latent_mesher(self, index: int, dtype=np.float32) -> "LatentMesher":
        """The template `index` mesh as an affine function of the model's decode features
        (the live-slider path; see `LatentMesher`)."""
        return LatentMesher(self, index, dtype)

    def mesh_from_landmarks(self, landmarks: np.ndarray, template: str | None = None,
                            smooth: int = 0, exact: bool = False, name: str = "sample",
                            stiffness: float | None = None) -> Mesh:
        """Mesh the landmark set (L, 3) by embedded deformation of a template mesh.

        exact=False uses the linear fast path (final α only); exact=True runs the full
        stiffness relaxation (§6.2.3). `stiffness` replaces the final α of the model's
        deform settings (the gated sampler's stiffer re-mesh, core/generate/sampling.py)."""
        landmarks = np.asarray(landmarks, dtype=np.float64)
        index = self.choose_template(landmarks, template)
        deformer = self.deformer(index, stiffness)
        deformer.check_targets(landmarks)
        if exact:
            mesh = deformer.deform(landmarks, "relax", name=name)
        else:
            mesh = full_mesh(self.meshes[index]).with_vertices(self.linear_map(index, stiffness).vertices(landmarks),
                                                              name=name)
        if smooth:
            mesh = smooth_curvature_flow(mesh, smooth)
        return mesh

    # ------------------------------------------------------------------ persistence
    def to_arrays(self, lazy: bool = False) -> dict[str, np.ndarray]:
        """The model file's arrays (`lazy`: the meshes as `npzfile.Concatenation`s)."""
        arrays = {f"corr__{k}": v for k, v in self.correspondence.to_arrays().items()}
        arrays.update({f"model__{k}": v for k, v in self.model.to_arrays().items()})
        arrays.update(meshset.pack([m.vertices for m in self.meshes], [m.faces for m in self.meshes], prefix="mesh_",
                                   lazy=lazy))
        arrays.update(pack_layouts([m.report.layout for m in self.meshes], prefix="mesh_"))
        arrays["settings"] = np.asarray(self.settings.to_json())
        arrays["metadata_keys"] = np.asarray(list(self.metadata), dtype=str)
        arrays["metadata_values"] = np.asarray(list(self.metadata.values()), dtype=str)
        if self.part_labels is not None:
            arrays["label_names"] = np.asarray(self.part_labels.names, dtype=str)
            arrays["mesh_face_labels"] = np.concatenate(self.part_labels.parts).astype(np.int32)
        units = self.latent_units()
        arrays["training_latents"] = self.training_latents()
        arrays["latent_centre"], arrays["latent_scale"] = units.centre, units.scale
        return arrays

    def save(self, path: str | os.PathLike) -> Path:
        """The model file: the training meshes streamed in uncompressed (float64 vertices,
        int32 faces: a million-vertex mesh took seconds to deflate), the rest compressed."""
        return save_npz(path, MODEL_FILE_FORMAT, MODEL_FILE_VERSION, self.to_arrays(lazy=True),
                        stored=meshset.stored("mesh_"))

    @classmethod
    def load(cls, path: str | os.PathLike) -> "GenerativeShapeModel":
        spec = {
            **meshset.spec(prefix="mesh_"),
            "metadata_keys": ArraySpec("U", ("T",)),
            "metadata_values": ArraySpec("U", ("T",)),
        }
        arrays = load_npz(path, MODEL_FILE_FORMAT, MODEL_FILE_VERSIONS, spec)
        corr_arrays = {k[len("corr__"):]: v for k, v in arrays.items() if k.startswith("corr__")}
        model_arrays = {k[len("model__"):]: v for k, v in arrays.items() if k.startswith("model__")}
        try:
            correspondence = Correspondence.from_arrays(corr_arrays, source=str(path))
            model = model_from_arrays(model_arrays)
        except ModelFileError as exc:
            raise ModelFileError(f"{path}: {exc}") from None
        meshes = _with_layouts(meshset.unpack(arrays, correspondence.names, str(path), prefix="mesh_"),
                               unpack_layouts(arrays, len(correspondence.names), str(path), prefix="mesh_"), path)
        if model.n_features_ != 3 * correspondence.n_landmarks:
            raise ModelFileError(f"{path}: the shape model has {model.n_features_} features, "
                                 f"the correspondence {3 * correspondence.n_landmarks}")
        loaded = cls(meshes, correspondence, model, settings=load_fit_settings(arrays, path),
                     metadata=dict(zip(arrays["metadata_keys"].tolist(), arrays["metadata_values"].tolist())),
                     **_load_latents(arrays, path, len(meshes), model.latent_dim),
                     part_labels=_load_part_labels(arrays, path, [len(m.faces) for m in meshes]))
        loaded.latent_units()  # a file from before the arrays existed: computed now, on load
        return loaded


def _with_layouts(meshes: list[Mesh], layouts: list, path) -> list[Mesh]:
    """The meshes carrying their files' layouts (report.layout), each checked against its mesh."""
    found = []
    for mesh, layout in zip(meshes, layouts):
        if layout is not None:
            if layout.vertex_map.max() >= mesh.n_vertices:
                raise ModelFileError(f"{path}: the face layout of mesh {mesh.name!r} refers to a vertex "
                                     "it does not have")
            mesh = Mesh(mesh.vertices, mesh.faces, name=mesh.name, report=MeshReport(layout=layout))
        found.append(mesh)
    return found


def _load_part_labels(arrays: dict, path, n_faces: list[int]) -> PartLabels | None:
    """The training meshes' part labels a model file records (None when it has none:
    fitted without labels, or written before they were saved)."""
    if "label_names" not in arrays and "mesh_face_labels" not in arrays:
        return None
    validate_arrays(arrays, {"label_names": ArraySpec("U", ("P",)),
                             "mesh_face_labels": ArraySpec("i", (int(sum(n_faces)),))}, str(path))
    parts = arrays["mesh_face_labels"].astype(np.int64)
    if parts.size and (parts.min() < -1 or parts.max() >= len(arrays["label_names"])):
        raise ModelFileError(f"{path}: array 'mesh_face_labels' names a part the model does not have")
    return PartLabels(tuple(arrays["label_names"].tolist()), tuple(np.split(parts, np.cumsum(n_faces)[:-1])))


def _load_latents(arrays: dict, path, n_shapes: int, latent_dim: int) -> dict:
    """training_latents and latent_units as a model file records them ({} when it does not:
    files written before they were saved)."""
    if "training_latents" not in arrays:
        return {}
    spec = {"training_latents": ArraySpec("f", (n_shapes, latent_dim)),
            "latent_centre": ArraySpec("f", (latent_dim,)), "latent_scale": ArraySpec("f", (latent_dim,))}
    validate_arrays(arrays, spec, str(path))
    if not np.all(arrays["latent_scale"] > 0):
        raise ModelFileError(f"{path}: array 'latent_scale' must be positive")
    return {"training_latents": arrays["training_latents"],
            "latent_units": LatentUnits(arrays["latent_centre"], arrays["latent_scale"])}


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
