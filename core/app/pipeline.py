"""The whole fit: prepare (§3.4, §4.2.1) → correspond (§4.2) → shape model (§5.3), giving
the fitted whole, a `GenerativeShapeModel` (shape_model.py) with the `FitSettings` it was
fitted with (fit_settings.py)."""

from __future__ import annotations

import time
import warnings
from dataclasses import replace

import numpy as np

from ..base.errors import CollectionError
from ..base.progress import CancelCheck, Progress, no_progress, sub_range
from ..correspond import Correspondence, correspond
from ..correspond.posing import apply_pose
from ..meshes.mesh import Mesh
from ..meshes.spill import loaded
from ..models import make_model
from ..models.scaling import ScaleWarning, size_note
from ..preprocess.collection import PreparedCollection, prepare_meshes
from .fit_settings import FitSettings, check_mesh_template
from .shape_model import GenerativeShapeModel

__all__ = ["fit_meshes", "fit_shape_model", "posed_meshes"]


def fit_meshes(meshes_or_prepared, settings: FitSettings = FitSettings(), progress: Progress | None = None,
               should_cancel=None, jobs: int | None = None, scheduler: str | None = None) -> GenerativeShapeModel:
    """The whole fit: prepare (§3.4, §4.2.1) → correspond (§4.2) → shape model (§5.3).

    Given a PreparedCollection, its own recorded settings win over `settings.prepare`
    (the model records how its shapes were really prepared); `settings.prepare` is used
    only for raw meshes or a collection that records none.

    Progress fractions (core/base/progress.py): prepare 0–0.15, correspondence 0.15–0.75,
    model 0.75–1. `should_cancel` (None, a callable or an Event) is polled inside every
    step and between them; a cancel raises errors.Cancelled and nothing is returned.
    `jobs`, `scheduler`: where the registrations run (`RunOptions`, `correspond`): worker
    processes (None: all cores; 1: in this process) or a Dask cluster. They change how long
    the fit takes, not the model.
    """
    cancel = CancelCheck(should_cancel, "fit")
    start = time.perf_counter()
    if isinstance(meshes_or_prepared, PreparedCollection):
        prepared = meshes_or_prepared
        if prepared.settings is not None:
            settings = replace(settings, prepare=prepared.settings)
        check_mesh_template(settings, prepared.names)
    else:
        meshes = list(meshes_or_prepared)
        check_mesh_template(settings, [m.name for m in meshes])
        prepared = prepare_meshes(meshes, settings.prepare, progress=sub_range(progress, 0.0, 0.15, "prepare: "),
                                  should_cancel=cancel)
    cancel()
    _check_variation([s.mesh for s in prepared.shapes])  # before the correspondence's work
    corr = correspond(prepared, settings.correspondence, template=settings.template, jobs=jobs,
                      progress=sub_range(progress, 0.15, 0.75, "correspondence: "), should_cancel=cancel,
                      scheduler=scheduler)
    cancel()
    return fit_shape_model(posed_meshes([s.mesh for s in prepared.shapes], corr), corr, settings,
                           progress=sub_range(progress, 0.75, 1.0), should_cancel=cancel, started=start)


def posed_meshes(meshes: list[Mesh], corr: Correspondence) -> list[Mesh]:
    """Prepared meshes (prepared frame) in the model frame: each shape the correspondence
    posed by its landmarks (core/correspond/posing.py) moved by its pose, the others as
    they are (the same objects). A stored dense mesh (core/meshes/spill.py) stays stored."""
    posed = []
    for mesh, pose, moved in zip(meshes, corr.model_poses, corr.posed):
        if moved:
            with loaded(mesh) as full:
                vertices = apply_pose(pose, full.vertices)
            mesh = mesh.with_vertices(vertices)
        posed.append(mesh)
    return posed


#: largest vertex difference between prepared shapes, as a share of their size, below
#: which they are copies of one mesh
IDENTICAL_SPREAD = 1e-6


def _check_variation(meshes: list[Mesh]) -> None:
    """A collection whose prepared shapes are all copies of one mesh (same faces, same
    vertices in the normalised frame) has no variation to learn: a model would invent
    latent dimensions from registration noise. Refused, saying so."""
    if len(meshes) < 2 or not all(isinstance(m, Mesh) for m in meshes):
        return
    first = meshes[0]
    size = float(np.ptp(first.vertices, axis=0).max())
    for other in meshes[1:]:
        if other.faces.shape != first.faces.shape or other.vertices.shape != first.vertices.shape \
                or not np.array_equal(other.faces, first.faces) \
                or np.abs(other.vertices - first.vertices).max() > IDENTICAL_SPREAD * size:
            return
    names = ", ".join(m.name for m in meshes[:4]) + (", …" if len(meshes) > 4 else "")
    raise CollectionError(f"the {len(meshes)} shapes ({names}) are copies of one mesh after alignment: there is no "
                          "variation to learn; add shapes that differ")


def fit_shape_model(meshes: list[Mesh], corr: Correspondence, settings: FitSettings = FitSettings(),
                    progress: Progress | None = None, should_cancel=None,
                    started: float | None = None) -> GenerativeShapeModel:
    """The shape-model stage (§5.3) on a finished correspondence of `meshes` (model frame:
    prepared meshes moved by the correspondence's poses, `posed_meshes`): fit
    `settings.model` to the landmark matrix, encode the training shapes (saved with the
    model, so nobody encodes them again) and bundle the fitted whole.
    `progress` and `should_cancel` as in core/base/progress.py (cancel is checked at every
    progress step of the model fit); `started` (perf_counter) dates the fit's start."""
    report = progress or no_progress
    cancel = CancelCheck(should_cancel, "fit")
    start = time.perf_counter() if started is None else started

    check_mesh_template(settings, list(corr.names))
    _check_variation(meshes)
    note = size_note(settings.model, len(corr.names))
    if note is not None:  # an N³ fit of many shapes: say so
        warnings.warn(note, ScaleWarning, stacklevel=2)
        report(0.0, note)
    model = make_model(settings.model, settings.latent_dim, settings.prepare.seed)
    model.fit(corr.landmark_matrix(), progress=cancel.before(sub_range(report, 0.0, 0.95, f"{settings.model}: ")))
    cancel()
    report(0.95, "encoding the training shapes")
    latents = model.training_latents(corr.landmark_matrix(),
                                     cancel.before(sub_range(report, 0.95, 1.0, "encoding the training shapes: ")))
    cancel()
    report(1.0, "fitted")
    from .. import __version__

    metadata = {"created": time.strftime("%Y-%m-%dT%H:%M:%S"), "fit_seconds": f"{time.perf_counter() - start:.2f}",
                "n_shapes": str(len(meshes)), "shapegen_version": __version__}
    return GenerativeShapeModel(list(meshes), corr, model, settings=settings, metadata=metadata,
                                training_latents=latents)
