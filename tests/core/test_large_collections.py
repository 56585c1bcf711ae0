"""Large collections: Prepare's pose search proposes pairs instead of comparing
every pair and still finds the same nearest shapes, what Prepare holds per shape does not
outgrow the shapes themselves, and correspondence's medoid and leave-one-out flags avoid
their N² and N³ costs with the same answers."""

from __future__ import annotations

import tracemalloc

import numpy as np
import pytest

from shapegen_core.correspond import groupwise, outliers
from shapegen_core.demo_data import make_barrels, make_vases
from shapegen_core.geometry import chamfer_matrix
from shapegen_core.meshes.mesh import Mesh
from shapegen_core.preprocess.neighbours import field_descriptors, probe_grid
from shapegen_core.preprocess.posesearch import PoseSearch
from shapegen_core.preprocess.prepare import prepare_collection
from shapegen_core.preprocess.rotations import AXIS_ROTATIONS


def _mixed(n: int, seed: int) -> list:
    """Vases and barrels in random input poses (yaw, scale, position)."""
    vases = [v.mesh for v in make_vases(n // 2, seed=seed, resolution=(12, 18))]
    return vases + list(make_barrels(n - n // 2, seed=seed))


@pytest.mark.quality
def test_candidate_pairs_find_the_nearest_shapes_of_all_pairs():
    meshes = _mixed(40, seed=1)
    every_pair = PoseSearch.of(meshes, [np.eye(3)] * len(meshes), 300, 0)
    assert every_pair.candidates is None  # 40 shapes: below the threshold, as before
    proposed = PoseSearch(every_pair.samples, exact_shapes=0)
    n = len(meshes)
    computed = proposed.candidates.known.sum() - n
    assert computed < 0.5 * n * (n - 1)  # the point of it: far fewer exact costs up front
    rng = np.random.default_rng(0)
    for j in range(n):
        for pool in (range(n), rng.choice(n, n // 3, replace=False), rng.choice(n, 5, replace=False)):
            assert proposed.nearest(j, pool, 3) == every_pair.nearest(j, pool, 3), (j, list(pool))
    known = proposed.candidates.known
    np.testing.assert_array_equal(proposed.distance[known], every_pair.distance[known])  # the same exact costs
    assert known.sum() < n * n  # and still not every pair


@pytest.mark.quality
def test_nearest_in_pool_settles_in_the_order_of_all_pairs():
    """consensus settles the waiting shape closest to a settled one next: NearestInPool,
    kept up to date as the pool grows and exact only where the order needs it, gives the
    order of the all-pairs matrix's row minima, on the exact and the candidate path."""
    from shapegen_core.preprocess.posesearch import NearestInPool

    meshes = _mixed(40, seed=4)
    every_pair = PoseSearch.of(meshes, [np.eye(3)] * len(meshes), 300, 0)
    proposed = PoseSearch(every_pair.samples, exact_shapes=0)
    n, start = len(meshes), [0, 21]
    expected, pool = [], list(start)
    while len(pool) < n:
        waiting = [r for r in range(n) if r not in pool]
        nearest = every_pair.distance[np.ix_(waiting, pool)].min(axis=1)
        expected.append(waiting[int(np.argmin(nearest))])
        pool.append(expected[-1])
    for search in (every_pair, proposed):
        waiting = NearestInPool(search, start, [r for r in range(n) if r not in start])
        order = []
        for _ in range(n - len(start)):
            order.append(waiting.closest())
            waiting.join(order[-1])
        assert order == expected
    assert proposed.candidates.known.sum() < n * n  # exact costs only where the order needs them


def test_field_descriptor_of_a_turned_shape_is_its_turned_field():
    """d_{RP}(q) = d_P(Rᵀq): the descriptor of a shape in axis rotation R equals the
    upright descriptor of the shape turned by R."""
    meshes = _mixed(2, seed=3)
    search = PoseSearch.of(meshes, [np.eye(3)] * 2, 200, 0)
    probes = probe_grid(5, 1.2)
    r = 7
    turned = PoseSearch([search.samples[0] @ AXIS_ROTATIONS[r].T, search.samples[1]])
    np.testing.assert_allclose(field_descriptors(search.trees[:1], probes)[0, r],
                               field_descriptors(turned.trees[:1], probes)[0, 0], atol=1e-12)


@pytest.mark.parametrize("align", ["pca", "consensus"])
def test_prepare_memory_does_not_grow_faster_than_the_shapes(align):
    """Peak and retained traced memory of Prepare per added shape stay within a few times
    the shape's own arrays (Signatures held 16 quadrature points per face of every shape:
    about 15x the mesh, 23 GB for 1000 vases of 20k vertices)."""
    base = [v.mesh for v in make_vases(3, seed=5, resolution=(30, 40))]

    def measure(n):
        # the same 3 vases, repeated as copies with their own arrays: a stage's transient
        # peak (one shape's voxel grid in Hollows, say) is the largest over the shapes, so
        # new shapes would raise it by their own size, not by what is held for all of them
        meshes = [Mesh(m.vertices.copy(), m.faces.copy(), name=f"{m.name}_{k}")
                  for k in range(n // len(base)) for m in base]
        tracemalloc.start()
        before = tracemalloc.get_traced_memory()[0]
        prepared = prepare_collection(meshes, align=align)
        retained, peak = tracemalloc.get_traced_memory()
        tracemalloc.stop()
        mesh_bytes = np.mean([m.vertices.nbytes + m.faces.nbytes for m in meshes])
        return peak - before, retained - before, mesh_bytes, prepared

    small_peak, small_kept, mesh_bytes, _ = measure(3)
    large_peak, large_kept, _, prepared = measure(6)
    per_shape_peak = (large_peak - small_peak) / 3
    per_shape_kept = (large_kept - small_kept) / 3
    assert per_shape_kept < 1.5 * mesh_bytes  # the prepared mesh itself, nothing else
    assert per_shape_peak < 4.0 * mesh_bytes, (per_shape_peak / mesh_bytes)
    assert len(prepared) == 6


def test_screened_medoid_of_a_large_collection_is_the_medoid(monkeypatch):
    """Above MEDOID_EXACT_SHAPES the medoid is screened against a few reference sets and
    summed over all for a shortlist: here the same set as the sum over every pair. The
    threshold is lowered to 60 sets (the screening is the same code; every pair of 220
    sets cost most of this file's time)."""
    monkeypatch.setattr(groupwise, "MEDOID_EXACT_SHAPES", 60)
    rng = np.random.default_rng(0)
    sets = [rng.normal(size=(60, 3)) * (1 + 0.3 * rng.random()) + rng.normal(size=3) * 0.5
            for _ in range(groupwise.MEDOID_EXACT_SHAPES + 40)]
    expected = int(np.argmin(chamfer_matrix(sets).sum(axis=1)))
    assert groupwise.chamfer_medoid(sets) == expected


def test_held_out_groups_flag_the_shape_leave_one_out_flags(monkeypatch):
    """Above LEAVE_ONE_OUT_SHAPES the reconstruction model leaves out a group: no shape is
    in its own model, and the errors stay those of leaving out one shape (a low-rank
    family of 230 shapes plus one upside down: same median, the same one far above it)."""
    count = outliers.LEAVE_ONE_OUT_SHAPES + 30
    groups = outliers.held_out_groups(count)
    assert sorted(i for g in groups for i in g) == list(range(count)) and len(groups) < count
    rng = np.random.default_rng(1)
    base = rng.normal(size=(40, 3))
    modes = rng.normal(size=(3, 40, 3))
    points = base + np.einsum("nk,kld->nld", rng.normal(size=(count, 3)), modes) \
        + 0.01 * rng.normal(size=(count, 40, 3))
    points[11] = points[11] * np.array([1.0, -1.0, -1.0])
    grouped = outliers.leave_one_out_errors(points, 0.9)
    monkeypatch.setattr(outliers, "LEAVE_ONE_OUT_SHAPES", count)
    alone = outliers.leave_one_out_errors(points, 0.9)
    assert abs(np.median(grouped) / np.median(alone) - 1.0) < 0.1
    assert np.isclose(grouped[11], alone[11], rtol=0.01)
    assert list(np.flatnonzero(grouped > 5 * np.median(grouped))) == [11]
    assert list(np.flatnonzero(alone > 5 * np.median(alone))) == [11]


@pytest.mark.parametrize("exact_shapes", [64, 0])
def test_prepare_cancels_within_its_pose_search(monkeypatch, exact_shapes):
    """Cancel is checked while the pose search compares shapes (every pair, or the
    proposed pairs), not only after it: the search stops at its next report."""
    from shapegen_core.preprocess.collection import PrepareSettings, prepare_meshes
    from shapegen_core.base.errors import Cancelled
    from shapegen_core.preprocess import posesearch

    monkeypatch.setattr(posesearch.PoseSearch.__init__, "__defaults__", (exact_shapes, None))
    compared = []
    original = posesearch.PoseSearch.axis_distance
    monkeypatch.setattr(posesearch.PoseSearch, "axis_distance",
                        lambda self, j, i: compared.append((j, i)) or original(self, j, i))
    messages = []
    meshes = [v.mesh for v in make_vases(10, seed=2, resolution=(12, 16))]
    with pytest.raises(Cancelled):
        prepare_meshes(meshes, PrepareSettings(align="consensus"), progress=lambda f, m: messages.append(m),
                       should_cancel=lambda: any("pose search: comparing" in m for m in messages))
    assert messages and all("pose search" in m for m in messages)
    assert 0 < len(compared) < 45  # stopped before every pair (10 shapes: 45)


#: the start of the first message of each of Prepare's loops over the shapes (align consensus)
PREPARE_LOOPS = ["pose search: sampling shape 1 of", "pose search: comparing shape 1 of", "signatures of shape 1 of",
                 "sampling noise of shape 1 of", "hollows of shape 1 of", "up axes: 1 of", "tops and bottoms: 1 of",
                 "comparing 1 of", "orienting ", "checking the poses: 1 of", "landmarks on "]


@pytest.mark.parametrize("loop", PREPARE_LOOPS)
def test_prepare_reports_and_cancels_in_every_loop_over_the_shapes(loop):
    """Every loop of Prepare over the shapes reports progress per shape (or per shape's
    worth of pairs) and stops at its next report once Cancel is asked (a
    1000-shape Prepare spends minutes in each): cancelled at the loop's first report, the
    last report is that first one."""
    from shapegen_core.preprocess.collection import PrepareSettings, prepare_meshes
    from shapegen_core.base.errors import Cancelled

    messages, fractions = [], []
    meshes = [v.mesh for v in make_vases(5, seed=2, resolution=(12, 16))]

    def progress(fraction, message):
        messages.append(message)
        fractions.append(fraction)

    with pytest.raises(Cancelled):
        prepare_meshes(meshes, PrepareSettings(align="consensus"), progress=progress,
                       should_cancel=lambda: any(m.startswith(loop) for m in messages))
    assert messages[-1].startswith(loop), messages[-3:]
    assert sum(m.startswith(loop) for m in messages) == 1
    assert fractions == sorted(fractions)
