"""The per-shape work of refinement (refine.py), in this process or spread over worker
processes: every shape's closest-point structure, its landmarks on the surface, the moves
back onto it and its spread term live with one shard for the whole refinement, so a
step sends only landmark arrays (the surfaces are built once, in the process that uses
them). The registration pool (pool.py) cannot do this: its tasks go to whichever worker
is free, so state kept between iterations would have to travel with every task.

A shard answers `propose(step)` (the landmarks moved by `step`, mapped back onto their
surfaces, with what the objective needs: face and smooth normals, the normals'
Jacobians and the spread term) and `accept()` (make the last proposal current).
"""

from __future__ import annotations

import multiprocessing
import os
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from ..base.child_process import exit_with_parent
from ..geometry import TargetSurface
from ..meshes.mesh import Mesh
from .objective import LandmarkState, SpreadTerm, spread_sigma

__all__ = ["ShapeShard", "Shards", "ShardAnswer", "interpolated_normals"]

#: a moved landmark may map onto faces whose normal is at most 90° from its old face's
MIN_NORMAL_COS = 0.0


def interpolated_normals(triangles: np.ndarray, corner_normals: np.ndarray, barycentric: np.ndarray
                         ) -> tuple[np.ndarray, np.ndarray]:
    """Smooth normals n = ñ / |ñ|, ñ = Σ_k b_k n_k (Phong), at points with barycentrics b on
    triangles (n, 3, 3) with corner normals (n, 3, 3), and their Jacobians ∂n/∂x (n, 3, 3)
    for x moving along the triangle: with e1 = b − a, e2 = c − a and G their Gram matrix,
    (dv, dw) = G⁻¹ (e1 · dx, e2 · dx), dñ = (n_b − n_a) dv + (n_c − n_a) dw, and
    dn = (I − n nᵀ) dñ / |ñ| (a move off the plane changes nothing)."""
    raw = np.einsum("nk,nkd->nd", barycentric, corner_normals)
    length = np.maximum(np.linalg.norm(raw, axis=1), np.finfo(float).tiny)
    normals = raw / length[:, None]
    edges = np.stack([triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0]], axis=1)  # (n, 2, 3)
    gram = np.einsum("nid,njd->nij", edges, edges)
    determinant = gram[:, 0, 0] * gram[:, 1, 1] - gram[:, 0, 1] ** 2
    safe = np.where(np.abs(determinant) > 0, determinant, 1.0)
    inverse = np.stack([np.stack([gram[:, 1, 1], -gram[:, 0, 1]], 1), np.stack([-gram[:, 0, 1], gram[:, 0, 0]], 1)],
                       1) / safe[:, None, None]
    inverse[np.abs(determinant) == 0] = 0.0  # a degenerate face: its normal does not move
    turn = np.stack([corner_normals[:, 1] - corner_normals[:, 0], corner_normals[:, 2] - corner_normals[:, 0]],
                    axis=2)  # (n, 3, 2)
    projector = np.eye(3) - normals[:, :, None] * normals[:, None, :]
    return normals, projector @ (turn @ inverse @ edges) / length[:, None, None]


@dataclass(frozen=True)
class ShardAnswer:
    """A shard's landmarks (proposed or current) as the objective sees them."""

    state: LandmarkState
    spread: np.ndarray  # (n,) S_m
    spread_gradient: np.ndarray  # (n, L, 3)


class ShapeShard:
    """Some shapes' surfaces (built once), their landmarks and the moves onto them."""

    def __init__(self, meshes: Sequence[Mesh], points, face_index, barycentric, sigma: float):
        self.surfaces = [TargetSurface(mesh.vertices, mesh.faces) for mesh in meshes]
        n_landmarks = np.shape(points)[1]
        self.spacing = np.array([np.sqrt(mesh.area() / n_landmarks) for mesh in meshes])
        # candidate faces kept with a slack of one landmark spacing: a step moves a landmark by
        # at most `refinement.max_move` spacings, so most queries reuse them
        self.trackers = [surface.tracker(margin) for surface, margin in zip(self.surfaces, self.spacing)]
        self.vertex_normals = [mesh.vertex_normals() for mesh in meshes]
        self.current = (np.array(points, dtype=np.float64), np.array(face_index, dtype=np.int64),
                        np.array(barycentric, dtype=np.float64))
        self.proposal = self.current
        state = self.state(*self.current)
        self.spread_term = SpreadTerm(state.points, state.face_normals,
                                      [spread_sigma(mesh.area(), n_landmarks, sigma) for mesh in meshes])

    def state(self, points, face_index, barycentric) -> LandmarkState:
        smooth = [interpolated_normals(s.triangles[f], v[s.faces[f]], b)
                  for s, v, f, b in zip(self.surfaces, self.vertex_normals, face_index, barycentric)]
        face_normals = np.stack([s.face_normals[f] for s, f in zip(self.surfaces, face_index)])
        return LandmarkState(points, face_normals, np.stack([n for n, _ in smooth]), np.stack([j for _, j in smooth]))

    def answer(self, where) -> ShardAnswer:
        state = self.state(*where)
        return ShardAnswer(state, *self.spread_term.evaluate(state.points, state.face_normals))

    def propose(self, step: np.ndarray | None) -> ShardAnswer:
        """The landmarks moved by `step` (n, L, 3) and mapped back onto their surfaces (each
        to the closest point with a compatible normal; a landmark without one stays put).
        None: the current landmarks."""
        if step is None:
            self.proposal = self.current
            return self.answer(self.current)
        points, faces, barys = (a.copy() for a in self.current)
        normals = np.stack([s.face_normals[f] for s, f in zip(self.surfaces, faces)])
        for m, tracker in enumerate(self.trackers):
            found = tracker.closest(self.current[0][m] + step[m], normals[m], MIN_NORMAL_COS)
            ok = np.isfinite(found.distance)
            points[m, ok], faces[m, ok], barys[m, ok] = found.points[ok], found.face_index[ok], found.barycentric[ok]
        self.proposal = (points, faces, barys)
        return self.answer(self.proposal)

    def accept(self) -> None:
        self.current = self.proposal


def _serve(connection, meshes, points, face_index, barycentric, sigma) -> None:
    """A worker process: one `ShapeShard`, answering (command, argument) messages."""
    exit_with_parent()
    try:
        shard = ShapeShard(meshes, points, face_index, barycentric, sigma)
    except Exception as exc:  # noqa: BLE001 - reported to the parent, which raises it
        connection.send(("error", exc))
        return
    connection.send(("ready", shard.spacing))
    while True:
        command, argument = connection.recv()
        if command == "stop":
            return
        try:
            if command == "propose":
                connection.send(("ok", shard.propose(argument)))
            elif command == "accept":
                shard.accept()
                connection.send(("ok", None))
            elif command == "current":
                connection.send(("ok", shard.current))
        except Exception as exc:  # noqa: BLE001 - reported to the parent, which raises it
            connection.send(("error", exc))


class Shards:
    """All shapes of a refinement in `jobs` shards: jobs = 1 in this process, otherwise in
    spawned worker processes (contiguous blocks of shapes), with OPENBLAS_NUM_THREADS=1
    for them as in pool.py. Every call returns the whole population's arrays."""

    def __init__(self, meshes: Sequence[Mesh], points, face_index, barycentric, sigma: float, jobs: int = 1):
        n = len(meshes)
        jobs = max(1, min(int(jobs), n))
        self.blocks = [block for block in np.array_split(np.arange(n), jobs) if len(block)]
        self.local: ShapeShard | None = None
        self.workers: list = []
        if len(self.blocks) == 1:
            self.local = ShapeShard(meshes, points, face_index, barycentric, sigma)
            self.spacing = self.local.spacing
            return
        context = multiprocessing.get_context("spawn")
        unset = "OPENBLAS_NUM_THREADS" not in os.environ
        if unset:
            os.environ["OPENBLAS_NUM_THREADS"] = "1"
        try:
            for block in self.blocks:
                parent, child = context.Pipe()
                process = context.Process(target=_serve, daemon=True, args=(
                    child, [meshes[i] for i in block], points[block], face_index[block], barycentric[block], sigma))
                process.start()
                self.workers.append((process, parent))
        finally:
            if unset:
                os.environ.pop("OPENBLAS_NUM_THREADS", None)
        try:
            self.spacing = np.concatenate([self._receive(parent) for _, parent in self.workers])
        except BaseException:
            self.close()
            raise

    @staticmethod
    def _receive(connection):
        status, value = connection.recv()
        if status == "error":
            raise value
        return value

    def _all(self, command: str, arguments: list) -> list:
        for (_, connection), argument in zip(self.workers, arguments):
            connection.send((command, argument))
        return [self._receive(connection) for _, connection in self.workers]

    def propose(self, step: np.ndarray | None) -> ShardAnswer:
        if self.local is not None:
            return self.local.propose(step)
        answers = self._all("propose", [None if step is None else step[b] for b in self.blocks])
        join = lambda name: np.concatenate([getattr(a.state, name) for a in answers])  # noqa: E731
        return ShardAnswer(LandmarkState(join("points"), join("face_normals"), join("normals"),
                                         join("normal_jacobians")),
                           np.concatenate([a.spread for a in answers]),
                           np.concatenate([a.spread_gradient for a in answers]))

    def accept(self) -> None:
        if self.local is not None:
            self.local.accept()
        else:
            self._all("accept", [None] * len(self.workers))

    def current(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Points, face indices and barycentrics of the current landmarks."""
        if self.local is not None:
            return self.local.current
        parts = self._all("current", [None] * len(self.workers))
        return tuple(np.concatenate([p[k] for p in parts]) for k in range(3))

    def close(self) -> None:
        for process, connection in self.workers:
            try:
                connection.send(("stop", None))
            except (BrokenPipeError, OSError):
                pass
        for process, connection in self.workers:
            process.join(timeout=5)
            if process.is_alive():
                process.terminate()
            connection.close()
        self.workers = []
