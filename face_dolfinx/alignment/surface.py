"""Exact closest points on a triangulated skin, and markers embedded in it (sifakis2005 section 5).

In the rest pose each marker is attached to the skin triangle closest to it, by the barycentric
coordinates of its closest point. A marker that does not lie on the skin (a marker's centre sits a
millimetre or two above it) keeps its offset vector, so that

    position(X) = sum_k w_k X[v_k] + offset

for any skin vertex positions X: the paper subtracts the offset from the marker data, which is the
same objective. Stacked over markers this is X^L = W X + offsets with W sparse (``matrix``).

Everything works on plain arrays, points (N, 3) and triangles (M, 3) of vertex ids, so nothing
here depends on the mesh library.

Closest-point search: a k-d tree holds one proxy point per triangle (its centroid; a triangle much
larger than is typical is split into congruent sub-triangles, one proxy each) and R, the radius of
the largest ball about a proxy that its (sub-)triangle fits in. A triangle is then at least
|q - p| - R from a query q, for each of its proxies p. Round 1: the exact distances (Ericson,
Real-Time Collision Detection, 5.1.5) to the triangles of the k proxies nearest q give a best
distance d; every other proxy is at least as far as the k-th, at d_k, so if d <= d_k - R the
answer is proven. Round 2, for the rest: any triangle closer than d has a proxy within d + R of q,
so the triangles of all proxies in that ball are compared, which proves the answer. Near the skin
round 1 nearly always suffices; far from it the ball holds more and more nearly equidistant
triangles, and a query costs more.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree

# Proxies per query in the first round: enough on a skin of roughly even triangles.
INITIAL_CANDIDATES = 16
# (query, candidate) pairs evaluated at once: bounds the temporaries to some tens of MB.
WORK_BUDGET = 100_000
# A triangle whose area is below this fraction of its longest edge squared is treated as its three
# edges: its region tests would depend on rounding, and it has no normal.
DEGENERATE_AREA_RATIO = 1e-12
# Closest-point regions of a point against a triangle (a, b, c) (``closest_points``).
FACE, EDGE_AB, EDGE_BC, EDGE_CA, VERTEX_A, VERTEX_B, VERTEX_C = range(7)


class SkinSurface:
    """A triangle surface (the skin) with exact closest-point queries and normals.

    ``points`` (N, 3) may contain vertices that no triangle uses (e.g. every mesh node); they are
    ignored by the queries and get a zero vertex normal.
    """

    def __init__(self, points, triangles):
        points = np.array(points, dtype=np.float64)
        if points.ndim != 2 or points.shape[1] != 3:
            raise ValueError(f"points must have shape (n, 3), not {points.shape}")
        if not np.all(np.isfinite(points)):
            raise ValueError("points must be finite")
        triangles = np.asarray(triangles)
        if triangles.ndim != 2 or triangles.shape[1] != 3 or len(triangles) == 0:
            raise ValueError(f"triangles must have shape (m, 3) with m >= 1, not {triangles.shape}")
        if not np.issubdtype(triangles.dtype, np.integer):
            raise ValueError(f"triangles must hold integer vertex ids, not {triangles.dtype}")
        triangles = triangles.astype(np.int64)
        if triangles.min() < 0 or triangles.max() >= len(points):
            raise ValueError(f"triangle vertex ids must lie in [0, {len(points)})")
        points.flags.writeable = False
        triangles.flags.writeable = False
        self.points = points
        self.triangles = triangles

        self._a, self._b, self._c = (points[triangles[:, k]] for k in range(3))
        cross = np.cross(self._b - self._a, self._c - self._a)
        twice_area = np.linalg.norm(cross, axis=1)
        longest_edge_squared = np.max(
            [np.sum((self._b - self._a) ** 2, axis=1), np.sum((self._c - self._b) ** 2, axis=1),
             np.sum((self._a - self._c) ** 2, axis=1)], axis=0)
        self.degenerate = twice_area <= DEGENERATE_AREA_RATIO * longest_edge_squared
        self.areas = 0.5 * twice_area
        # Unit normals by the right-hand rule on the vertex order; zero for degenerate triangles.
        self.triangle_normals = np.zeros_like(cross)
        self.triangle_normals[~self.degenerate] = (cross[~self.degenerate]
                                                   / twice_area[~self.degenerate, None])
        # The cross product's length is twice the area, so summing it weights by area.
        summed = np.zeros_like(points)
        for corner in range(3):
            np.add.at(summed, triangles[:, corner], cross)
        length = np.linalg.norm(summed, axis=1)
        self.vertex_normals = np.divide(summed, length[:, None], out=np.zeros_like(summed),
                                        where=length[:, None] > 0)

        proxies, self._proxy_triangle, self._proxy_radius = covering_points(self._a, self._b, self._c)
        self._tree = cKDTree(proxies)

    def closest(self, query):
        """Exact closest skin points of ``query`` (n, 3).

        Returns (triangle index (n,), barycentric coordinates (n, 3) on that triangle's vertices in
        its vertex order, closest point (n, 3), distance (n,)). Where several triangles are equally
        close (the closest point is on a shared edge or vertex), one of them is returned.
        """
        query = np.asarray(query, dtype=np.float64)
        if query.ndim != 2 or query.shape[1] != 3:
            raise ValueError(f"query points must have shape (n, 3), not {query.shape}")
        if not np.all(np.isfinite(query)):
            bad = np.flatnonzero(~np.all(np.isfinite(query), axis=1))
            raise ValueError(f"query points must be finite; rows {bad[:10]} are not")
        n = len(query)
        triangle = np.empty(n, dtype=np.int64)
        barycentric = np.empty((n, 3))
        point = np.empty((n, 3))
        distance = np.empty(n)
        if n == 0:
            return triangle, barycentric, point, distance

        def settle(batch, proxies_per_query):
            """Keep, for each query of ``batch``, the nearest of the triangles of its proxies."""
            owner = np.repeat(np.arange(len(batch)), [len(found) for found in proxies_per_query])
            candidates = self._proxy_triangle[np.concatenate(proxies_per_query).astype(np.int64)]
            cand_bary, cand_point, cand_distance = self._closest_on_triangles(query[batch][owner], candidates)
            # Sorted by query, then distance: each query's first entry is its nearest candidate.
            order = np.lexsort((cand_distance, owner))
            best = order[np.searchsorted(owner[order], np.arange(len(batch)))]
            triangle[batch], barycentric[batch] = candidates[best], cand_bary[best]
            point[batch], distance[batch] = cand_point[best], cand_distance[best]

        # Round 1: the k nearest proxies; proven where nothing unseen can be closer than the best.
        k = min(INITIAL_CANDIDATES, self._tree.n)
        unproven = []
        for chunk in np.array_split(np.arange(n), max(1, -(-n * k // WORK_BUDGET))):
            proxy_distance, proxy = self._tree.query(query[chunk], k)
            proxy_distance, proxy = proxy_distance.reshape(len(chunk), k), proxy.reshape(len(chunk), k)
            settle(chunk, proxy)
            if k < self._tree.n:
                unproven.append(chunk[distance[chunk] > proxy_distance[:, -1] - self._proxy_radius])
        # Round 2: any triangle closer than the best so far has a proxy within best + R: take them all.
        unproven = np.concatenate(unproven) if unproven else np.empty(0, dtype=np.int64)
        if unproven.size:
            counts = self._tree.query_ball_point(query[unproven], distance[unproven] + self._proxy_radius,
                                                 return_length=True)
            batch_of = (np.cumsum(counts) - 1) // WORK_BUDGET  # consecutive queries, ~WORK_BUDGET pairs each
            for batch_id in np.unique(batch_of):
                batch = unproven[batch_of == batch_id]
                settle(batch, self._tree.query_ball_point(query[batch], distance[batch] + self._proxy_radius))
        return triangle, barycentric, point, distance

    def embed(self, query, names=None) -> MarkerEmbedding:
        """Attach each query point to its closest skin triangle, keeping its offset from the skin."""
        query = np.asarray(query, dtype=np.float64)
        triangle, barycentric, _, _ = self.closest(query)
        vertices = self.triangles[triangle]
        # The offset is taken from the same weighted sum positions() evaluates, so that the round
        # trip reproduces the query to rounding.
        on_skin = np.einsum("nk,nkd->nd", barycentric, self.points[vertices])
        return MarkerEmbedding(vertices, barycentric, query - on_skin,
                               None if names is None else tuple(names))

    def _closest_on_triangles(self, p, triangle):
        """Closest points of p (P, 3) on triangles ``triangle`` (P,): barycentric, point, distance."""
        a, b, c = self._a[triangle], self._b[triangle], self._c[triangle]
        point, barycentric, _ = closest_points(p, a, b, c)
        degenerate = self.degenerate[triangle]
        if np.any(degenerate):
            corners = (a[degenerate], b[degenerate], c[degenerate])
            barycentric[degenerate] = _closest_on_edges(p[degenerate], *corners)
            point[degenerate] = sum(barycentric[degenerate, k:k + 1] * corners[k] for k in range(3))
        return barycentric, point, np.linalg.norm(p - point, axis=1)


@dataclass(frozen=True, eq=False)
class MarkerEmbedding:
    """Markers attached to a triangle surface: position(X) = sum_k weights[:, k] X[triangles[:, k]] + offsets.

    ``triangles`` (n, 3) are vertex ids into the surface's points, ``weights`` (n, 3) barycentric
    coordinates (non-negative, summing to one) and ``offsets`` (n, 3) the constant vectors from
    the skin point to the marker, in the frame the vertex positions are given in. ``names``
    optionally names the markers, in row order.
    """

    triangles: np.ndarray
    weights: np.ndarray
    offsets: np.ndarray
    names: tuple[str, ...] | None = None

    def __len__(self):
        return len(self.triangles)

    def positions(self, vertex_positions) -> np.ndarray:
        """Marker positions (n, 3) for surface vertex positions (N, 3) (e.g. a deformed skin)."""
        vertex_positions = np.asarray(vertex_positions, dtype=np.float64)
        return np.einsum("nk,nkd->nd", self.weights, vertex_positions[self.triangles]) + self.offsets

    def matrix(self, n_vertices: int) -> sp.csr_matrix:
        """W, shape (3n, 3N), with ``W @ X.ravel() + offsets.ravel() == positions(X).ravel()``.

        It acts on flattened (N, 3) vertex positions, xyz interleaved per vertex (the layout of a
        blocked vector field's dofs), and maps them to the markers' positions likewise.
        """
        if self.triangles.size and self.triangles.max() >= n_vertices:
            raise ValueError(f"the embedding uses vertex {self.triangles.max()}, but n_vertices is {n_vertices}")
        n = len(self)
        marker = np.repeat(np.arange(n), 3)  # marker of each (marker, corner) entry
        vertex = self.triangles.ravel()
        weight = self.weights.ravel()
        rows = (3 * marker[:, None] + np.arange(3)).ravel()
        cols = (3 * vertex[:, None] + np.arange(3)).ravel()
        return sp.csr_matrix((np.repeat(weight, 3), (rows, cols)), shape=(3 * n, 3 * n_vertices))


def covering_points(a, b, c):
    """Proxy points covering the triangles abc (all (M, 3)), their triangle ids, and R: every point
    of a triangle lies within R of one of its proxies.

    A triangle is covered by the ball about its centroid through its farthest vertex. A triangle
    whose ball is over twice the median is split into s x s congruent sub-triangles (each a copy
    scaled by 1/s, so with a ball s times smaller), one proxy per sub-triangle. R then stays near
    the typical triangle size however unevenly the skin is meshed, and so does the candidate count.
    """
    centroid = (a + b + c) / 3.0
    radius = np.sqrt(np.max([np.sum((v - centroid) ** 2, axis=1) for v in (a, b, c)], axis=0))
    typical = 2.0 * np.median(radius)
    splits = np.ones(len(a), dtype=np.int64)
    if typical > 0:
        splits = np.maximum(1, np.ceil(radius / typical - 1e-9)).astype(np.int64)
    proxies, owners, largest = [], [], 0.0
    for s in np.unique(splits):
        members = np.flatnonzero(splits == s)
        weights = _subtriangle_centroids(s)  # (s*s, 3) barycentric
        proxies.append((np.einsum("jk,tkd->tjd", weights, np.stack([a[members], b[members], c[members]], axis=1))
                        ).reshape(-1, 3))
        owners.append(np.repeat(members, len(weights)))
        largest = max(largest, radius[members].max() / s)
    proxies = np.concatenate(proxies)
    # A margin far above the rounding of the distances the proof compares keeps it sound.
    margin = 1e-9 * largest + 1e-12 * np.abs(proxies).max()
    return proxies, np.concatenate(owners), largest + margin


def _subtriangle_centroids(s):
    """Barycentric coordinates of the centroids of the s*s sub-triangles of a regular s-subdivision."""
    upward = [(3 * i + 1, 3 * j + 1) for i in range(s) for j in range(s - i)]        # i + j <= s-1
    downward = [(3 * i + 2, 3 * j + 2) for i in range(s - 1) for j in range(s - 1 - i)]  # i + j <= s-2
    ij = np.array(upward + downward, dtype=np.float64) / (3 * s)
    return np.column_stack([1.0 - ij.sum(axis=1), ij])


def closest_points(p, a, b, c):
    """Closest points of p on triangles abc, all (P, 3), by Ericson's Voronoi-region tests
    (Real-Time Collision Detection, 5.1.5): the closest points (P, 3), their barycentric
    coordinates (P, 3) on (a, b, c) and their regions (P,): FACE, EDGE_AB, EDGE_BC, EDGE_CA,
    VERTEX_A, VERTEX_B or VERTEX_C.

    The tests run in Ericson's order (vertex a, vertex b, edge ab, vertex c, edge ca, edge bc, else
    the face); the first that holds decides. A vertex region's coordinates are exactly one and
    zeros, an edge region's opposite coordinate exactly zero. For a non-degenerate triangle no
    division is by zero: an edge region's denominator is that edge's squared length, and the
    face's is positive when all three of va, vb, vc are.
    """
    ab, ac = b - a, c - a
    ap, bp, cp = p - a, p - b, p - c
    d1, d2 = _dot(ab, ap), _dot(ac, ap)
    d3, d4 = _dot(ab, bp), _dot(ac, bp)
    d5, d6 = _dot(ab, cp), _dot(ac, cp)
    vc = d1 * d4 - d3 * d2
    vb = d5 * d2 - d1 * d6
    va = d3 * d6 - d5 * d4

    regions = [
        (d1 <= 0) & (d2 <= 0),                               # vertex a
        (d3 >= 0) & (d4 <= d3),                              # vertex b
        (vc <= 0) & (d1 >= 0) & (d3 <= 0),                   # edge ab
        (d6 >= 0) & (d5 <= d6),                              # vertex c
        (vb <= 0) & (d2 >= 0) & (d6 <= 0),                   # edge ca
        (va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0),         # edge bc
    ]
    # Along-edge parameters, evaluated everywhere but used only inside their regions.
    with np.errstate(divide="ignore", invalid="ignore"):
        t_ab = d1 / (d1 - d3)
        t_ac = d2 / (d2 - d6)
        t_bc = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        total = va + vb + vc
        v_face, w_face = vb / total, vc / total
    zero, one = np.zeros_like(d1), np.ones_like(d1)
    v = np.select(regions, [zero, one, t_ab, zero, zero, 1 - t_bc], default=v_face)
    w = np.select(regions, [zero, zero, zero, one, t_ac, t_bc], default=w_face)
    region = np.select(regions, [VERTEX_A, VERTEX_B, EDGE_AB, VERTEX_C, EDGE_CA, EDGE_BC], default=FACE)
    barycentric = np.column_stack([1 - v - w, v, w])
    point = barycentric[:, :1] * a + barycentric[:, 1:2] * b + barycentric[:, 2:] * c
    return point, barycentric, region


def _closest_on_edges(p, a, b, c):
    """Barycentric coordinates of the closest points of p on the three edges of triangles abc."""
    best_distance = np.full(len(p), np.inf)
    barycentric = np.zeros((len(p), 3))
    for start, end, i, j in ((a, b, 0, 1), (b, c, 1, 2), (c, a, 2, 0)):
        edge = end - start
        length_squared = _dot(edge, edge)
        t = np.divide(_dot(p - start, edge), length_squared, out=np.zeros(len(p)),
                      where=length_squared > 0)
        t = np.clip(t, 0.0, 1.0)
        d = np.linalg.norm(p - (start + t[:, None] * edge), axis=1)
        closer = d < best_distance
        best_distance[closer] = d[closer]
        barycentric[closer] = 0.0
        barycentric[closer, i] = 1 - t[closer]
        barycentric[closer, j] = t[closer]
    return barycentric


def _dot(u, v):
    return np.einsum("ij,ij->i", u, v)
