"""Where a surface point lies between the turning lines of its region (**beyond** the
thesis; a feature of `matching="features"`, features.py).

A turning line is where the surface turns from facing down to facing up (n_z = 0 with +z
up after Prepare): the belly and the neck of a vase, a shoulder, the equator of a sphere.
The saturated up-feature of features.py tells which side of such a line a point is on;
it pulls only the points lying between the template's line and the target's, which pile
up just beyond it (docs/history.md, Correspondence: feature matches). This module gives every
point a position along its region instead, so points on both sides of a line are pulled
in proportion:

    g(x) = d_low(x) / (d_low(x) + d_high(x))     (a region between two turning lines)
    g(x) = d(x) / max_region d                   (a region with one turning line)

with d the length of the shortest path within the region (on a k-nearest-neighbour graph of
the points) from a turning line, "low" and "high" the region's lines of lowest and highest
mean height. A path's length counts the height it climbs or falls plus `LENGTH_SHARE` of its
length (|Δz| + 0.1 ‖Δx‖ per edge), so along a wall g is the point's height between the
lines, not its arc length (a wall that slopes between belly and neck put its arc-length
middle below its height middle, by a different amount on every vase). The line lies where
the up-component of the normal crosses zero between two neighbouring points (interpolated
along their edge), not at the points beside it, which lie up to half a spacing inside the
region by an amount that differs per shape. (Both choices removed an S-shaped bias of g
against the true height fraction; figures in docs/history.md, Correspondence: feature matches.) A line
often comes in pieces (on a wide belly whose normals are nearly horizontal over a band,
the sign change breaks into arcs): pieces at about the same height are one line
(`SAME_LINE`), since taking only the lowest piece would measure g around the shape from
one arc. A region is a connected part of the surface facing one way (up or
down); graph edges between points whose normals differ by more than `max_angle` are cut,
so the two faces of a thin wall, and a crease such as a vase's rim or base, are not
joined. g lies in [0, 1]: 0 on the lower (or only) line. A region without a turning line
gets 0.5. g is invariant to scale and position. It depends on how densely the surface is
sampled through the graph's approximation of path lengths: on a vase's dense
surface samples its rank correlation with the true position along a wall is 0.99 or more
(tests/core/test_turning.py), on 300 of its landmarks it fell to 0.12-0.54 along some
walls, so correspondence compares g computed on each shape's landmarks and dense samples
(features.py), never on a sparse template alone.
"""

from __future__ import annotations

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components, dijkstra
from scipy.spatial import cKDTree

__all__ = ["position_between_turning_lines", "facing_regions", "positions_and_regions"]

#: g of points in regions without a turning line (and of isolated points)
NO_LINE = 0.5
#: graph edges join points whose normals differ by at most this (degrees)
MAX_ANGLE = 60.0
#: a path's length is the height it climbs or falls plus this share of its length
LENGTH_SHARE = 0.1
#: pieces of turning line whose mean heights differ by at most this share of their
#: region's height are one line (`_turning_lines`)
SAME_LINE = 0.1


def position_between_turning_lines(points: np.ndarray, normals: np.ndarray, neighbours: int = 8,
                                   max_angle: float = MAX_ANGLE, min_line_share: float = 0.02) -> np.ndarray:
    """g (module docstring) of every point, (n,), from points (n, 3) and their normals (n, 3).

    neighbours: k of the graph. max_angle: edges between points whose normals differ by more
    (degrees) are cut. min_line_share: a turning line needs at least this share of its
    region's line points (and 3 points); smaller pieces are noise of a near-vertical wall."""
    return positions_and_regions(points, normals, neighbours, max_angle, min_line_share)[0]


def positions_and_regions(points: np.ndarray, normals: np.ndarray, neighbours: int = 8,
                          max_angle: float = MAX_ANGLE, min_line_share: float = 0.02
                          ) -> tuple[np.ndarray, np.ndarray]:
    """`position_between_turning_lines` and `facing_regions` of the same points from one
    graph: (g (n,), region labels (n,))."""
    points = np.asarray(points, dtype=np.float64)
    count = len(points)
    position = np.full(count, NO_LINE)
    if min(neighbours, count - 1) < 1:
        return position, np.arange(count)
    unit, graph, region, (i, j, d, same_side, length) = _facing_graph(points, normals, neighbours, max_angle)
    on_line = np.zeros(count, dtype=bool)
    on_line[i[~same_side]] = on_line[j[~same_side]] = True
    faces_up = unit[:, 2] > 0
    start = _distance_to_crossing(unit[:, 2], i[~same_side], j[~same_side], length[~same_side])
    line = _line_pieces(points, on_line, faces_up, 3 * float(np.median(d)) if len(d) else 0.0)
    low_lines, high_lines, one_line, two_lines = [], [], [], []
    for members in _groups(region):
        extent = float(np.ptp(points[members, 2]))
        ends = _turning_lines(members[on_line[members]], line, points, min_line_share, extent)
        if not ends:
            continue
        low_lines.append(ends[0])
        if len(ends) == 1:
            one_line.append(members)
        else:
            two_lines.append(members)
            high_lines.append(ends[-1])
    if not low_lines:
        return position, region
    # regions are separate components of the graph, so one search serves all their lines
    low = _distance_from(graph, np.concatenate(low_lines), start)
    for members in one_line:
        reach = low[members]
        reached = np.isfinite(reach)
        if reached.any() and reach[reached].max() > 0:
            position[members[reached]] = reach[reached] / reach[reached].max()
    if two_lines:
        high = _distance_from(graph, np.concatenate(high_lines), start)
        for members in two_lines:
            lo, hi = low[members], high[members]
            reached = np.isfinite(lo) & np.isfinite(hi) & (lo + hi > 0)
            position[members[reached]] = lo[reached] / (lo[reached] + hi[reached])
    return position, region


def facing_regions(points: np.ndarray, normals: np.ndarray, neighbours: int = 8,
                   max_angle: float = MAX_ANGLE) -> np.ndarray:
    """(n,) a label per point: its region, a connected part of the surface facing one way
    (up or down), bounded by turning lines and by creases (graph edges between points whose
    normals differ by more than `max_angle` degrees are cut): the regions whose positions
    `position_between_turning_lines` measures. Labels are arbitrary integers; an isolated
    point is a region of its own."""
    points = np.asarray(points, dtype=np.float64)
    if min(neighbours, len(points) - 1) < 1:
        return np.arange(len(points))
    return _facing_graph(points, normals, neighbours, max_angle)[2]


def _facing_graph(points: np.ndarray, normals: np.ndarray, neighbours: int, max_angle: float):
    """The k-nearest-neighbour graph of the module docstring: (unit normals, the graph of
    edges between points facing the same way with their path lengths, the region label of
    every point, and the kept edges (i, j, their lengths d, whether they join points facing
    the same way, their path lengths)). Needs at least 2 points."""
    unit = np.asarray(normals, dtype=np.float64)
    unit = unit / np.maximum(np.linalg.norm(unit, axis=1, keepdims=True), 1e-300)
    count = len(points)
    k = min(neighbours, count - 1)
    distance, nearest = cKDTree(points).query(points, k + 1)
    i, j, d = np.repeat(np.arange(count), k), nearest[:, 1:].ravel(), distance[:, 1:].ravel()
    keep = np.einsum("ij,ij->i", unit[i], unit[j]) >= np.cos(np.radians(max_angle))
    i, j, d = i[keep], j[keep], d[keep]
    faces_up = unit[:, 2] > 0
    same_side = faces_up[i] == faces_up[j]
    length = np.abs(points[i, 2] - points[j, 2]) + LENGTH_SHARE * d
    graph = coo_matrix((length[same_side], (i[same_side], j[same_side])), shape=(count, count)).tocsr()
    graph = graph.maximum(graph.T)
    _, region = connected_components(graph, directed=False)
    return unit, graph, region, (i, j, d, same_side, length)


def _distance_to_crossing(up: np.ndarray, i: np.ndarray, j: np.ndarray, length: np.ndarray) -> np.ndarray:
    """Per point, the path length to where the turning line crosses its nearest edge to a
    point facing the other way (inf for points with no such edge). Along edge (i, j) the
    up-component is interpolated linearly: it is zero at the fraction up_i / (up_i - up_j)
    of the edge's length from i."""
    distance = np.full(len(up), np.inf)
    change = up[i] - up[j]
    share = np.clip(np.divide(up[i], change, out=np.zeros_like(change), where=change != 0), 0.0, 1.0)
    np.minimum.at(distance, i, share * length)
    np.minimum.at(distance, j, (1.0 - share) * length)
    return distance


def _distance_from(graph, sources: np.ndarray, start: np.ndarray) -> np.ndarray:
    """Shortest path length of every node from the set `sources`, each source starting at
    its own length `start` (a search from one extra node joined to every source by an edge
    of that length; scipy drops edges of length 0, so every start is at least a tiny one)."""
    count = graph.shape[0]
    tiny = 1e-12 * max(float(np.max(graph.data, initial=0.0)), 1e-300)
    entry = coo_matrix((start[sources] + tiny, (np.full(len(sources), count), sources)), shape=(count + 1, count + 1))
    padded = graph.tocoo()
    padded.resize((count + 1, count + 1))
    return dijkstra((padded + entry).tocsr(), directed=True, indices=count)[:count]


def _groups(labels: np.ndarray) -> list[np.ndarray]:
    """Indices of every label's members."""
    order = np.argsort(labels, kind="stable")
    cuts = np.flatnonzero(np.diff(labels[order])) + 1
    return np.split(order, cuts)


def _line_pieces(points: np.ndarray, on_line: np.ndarray, faces_up: np.ndarray, reach: float) -> np.ndarray:
    """A label per point: line points within `reach` of each other on the same side form one
    piece of a turning line (a line's points are not always graph neighbours)."""
    members = np.flatnonzero(on_line)
    pairs = cKDTree(points[members]).query_pairs(reach, output_type="ndarray") if reach > 0 else np.zeros((0, 2), int)
    pairs = pairs[faces_up[members[pairs[:, 0]]] == faces_up[members[pairs[:, 1]]]]
    links = coo_matrix((np.ones(len(pairs)), (members[pairs[:, 0]], members[pairs[:, 1]])),
                       shape=(len(points), len(points)))
    return connected_components(links, directed=False)[1]


def _turning_lines(line_points: np.ndarray, line: np.ndarray, points: np.ndarray, min_share: float,
                   extent: float) -> list[np.ndarray]:
    """A region's turning lines as point sets, the lowest (by mean height) first and the
    highest last (one set when the region has one line; none when it has none).

    A line often comes in pieces (a wide belly whose normals are nearly horizontal over a
    band breaks into arcs), so pieces are grouped by mean height: split at the largest gap
    between consecutive piece heights into a low and a high line when that gap exceeds
    SAME_LINE × the region's height `extent`, else all pieces form one line."""
    if len(line_points) == 0:
        return []
    labels, sizes = np.unique(line[line_points], return_counts=True)
    labels = labels[sizes >= max(3, min_share * len(line_points))]
    if len(labels) == 0:
        return []
    pieces = [line_points[line[line_points] == label] for label in labels]
    heights = np.array([points[piece, 2].mean() for piece in pieces])
    order = np.argsort(heights, kind="stable")
    pieces, heights = [pieces[i] for i in order], heights[order]
    gaps = np.diff(heights)
    if len(gaps) == 0 or gaps.max() <= SAME_LINE * extent:
        return [np.concatenate(pieces)]
    cut = int(np.argmax(gaps)) + 1
    return [np.concatenate(pieces[:cut]), np.concatenate(pieces[cut:])]
