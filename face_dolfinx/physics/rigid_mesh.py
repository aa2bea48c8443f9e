"""A rigid closed triangle surface as a contact object: signed distances, their derivatives and a
conservative collision-free step.

``TriangleMesh`` has the interface of the analytic objects of ``face_dolfinx.physics.contact``
(``gaps``, ``first_contact``, ``describe``, ``surface``): a pose (a rigid ``AffineMap`` from its
own frame to the world) places it, and the gap of a point is its signed distance to the surface,
positive outside. The closest point on the nearest triangle (Ericson's regions: the face, one of
three edges or one of three vertices) gives the distance; the sign is that of the angle-weighted
pseudonormal of the closest feature (Baerentzen & Aanaes 2005), exact for a closed, consistently
oriented surface. The gap's gradient is the unit normal n = (x - p) / |x - p|; its Hessian is 0 in
a face region, (I - n n^T - e e^T) / d next to an edge of direction e and (I - n n^T) / d next to
a vertex: the Hessian of ``ipctk.point_triangle_distance`` of the same pair with the triangle
held fixed (the tests compare them).

Candidate triangles come from a KD-tree of sample points that cover the surface: every point of
a triangle lies within the covering radius h of one of its samples (``covering_points``: a
triangle much larger than is typical is split into congruent sub-triangles, one sample each, so h
stays near the typical triangle size however long the teeth's side-wall triangles are). The
nearest sample, at D, bounds a point's distance d from both sides, D - h <= d <= D, and a triangle
at a distance r has a sample within r + h: the triangles of the samples within D + h hold the
nearest one, a few dozen per point near the surface.

``gaps(points, pose, within=...)`` computes the exact gap, normal and Hessian only of the points
whose lower bound D - h is below ``within``; the others get that lower bound (at least
``within``) and a zero normal and Hessian, so that a call costs in proportion to the points within
reach of the surface. The bound is one of the distance: it bounds the gap of a point outside the
surface, the only points the contact terms evaluate (their states are kept outside every object
by the collision-free steps; ``ContactPotential.gaps`` and ``check_clear`` ask for exact gaps).

A smooth barrier: the gap to the nearest triangle has a gradient that jumps where the nearest
triangle changes across a concave edge or vertex, and the barrier of it with it; a node pressed
onto such an edge sees its force turn by the edge's angle as it crosses. The barrier of a triangle
mesh is instead the sum over its features within dhat of a node, triangles and vertices with
sign +1 and edges with -1, of b(distance to the closed feature) (``barrier_terms``). Each term is C1
in the node's position (the distance to a closed convex set is C1 off it; b is C2 at dhat), so the
sum is. By the layer-cake form b(d) = integral over r in (d, dhat) of -b'(r), the sum is the
integral of -b'(r) times the Euler characteristic of the part of the surface within r of the node
(inclusion-exclusion over the closed triangles that part meets, whose intersections are the edges
and vertices): where that part is one disc, as on every flat or convex piece, the barrier is
b(distance to the surface) exactly; next to a concave edge, where a ball can touch the two
triangles but not their edge, both push (a plain sum over point-triangle pairs counts a node over a
vertex of six triangles six times, which the edges' terms cancel here). Its Hessian per term is
that of the distance to one feature: 0 over a triangle's face, (I - n n^T - e e^T) / d next to an
edge of direction e and (I - n n^T) / d next to a vertex.

``first_contact`` bounds the time at which a point moving along a straight step first comes
within a clearance of the surface, from below: per candidate triangle the larger of the time to
reach the clearance from the triangle's plane (the distance to a triangle is at least that to its
plane) and from the tangent at the start of the distance to the triangle (a convex function of
the time, as the distance from a point moving on a line to a convex set is). A point sliding along
a face, or moving away from a triangle, is not held back by it; the per-node bound gap / step
length alone would hold a node sliding at a gap of 0.01 mm to 1 % of a 1 mm step.
"""
import itertools

import numpy as np
from scipy.spatial import cKDTree

from face_dolfinx.alignment.surface import (EDGE_AB, EDGE_BC, EDGE_CA, FACE, VERTEX_A, VERTEX_B, VERTEX_C,
                                            closest_points, covering_points)
from face_dolfinx.model.bones import AffineMap
from face_dolfinx.model.surface_file import check_closed_surface, read_triangle_surface

_EDGE_ENDS = {EDGE_AB: (0, 1), EDGE_BC: (1, 2), EDGE_CA: (2, 0)}


class TriangleMesh:
    """A rigid closed triangle surface (points and outward triangles in its own frame) as a
    contact object (module docstring). ``name`` is used in messages (e.g. its file)."""

    def __init__(self, points: np.ndarray, triangles: np.ndarray, name: str = "triangle mesh"):
        self.name = name
        self.points, self.triangles = check_closed_surface(points, triangles, name)
        corners = self.corners = self.points[self.triangles]
        normal = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
        self.normals = normal / np.linalg.norm(normal, axis=1)[:, None]
        self.pseudonormals = self._pseudonormals()
        # The surface's edges (each once, as vertex pairs) and each triangle's three (ab, bc, ca).
        directed = np.concatenate([self.triangles[:, [0, 1]], self.triangles[:, [1, 2]], self.triangles[:, [2, 0]]])
        self.edges, index = np.unique(np.sort(directed, axis=1), axis=0, return_inverse=True)
        self.triangle_edges = index.reshape(3, -1).T
        samples, self.sample_triangles, self.covering_radius = covering_points(corners[:, 0], corners[:, 1],
                                                                              corners[:, 2])
        self.sample_tree = cKDTree(samples)

    @classmethod
    def read(cls, path) -> "TriangleMesh":
        return cls(*read_triangle_surface(path), name=str(path))

    def _pseudonormals(self) -> np.ndarray:
        """(triangles, 7, 3): the normal of each closest-point region (module docstring)."""
        t = self.triangles
        out = np.empty((len(t), 7, 3))
        out[:, FACE] = self.normals
        # Edges: the sum of the normals of the two triangles that share them.
        directed = np.concatenate([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]])
        key = np.sort(directed, axis=1)
        _, edge = np.unique(key, axis=0, return_inverse=True)
        edge = edge.reshape(-1)
        edge_sum = np.zeros((edge.max() + 1, 3))
        np.add.at(edge_sum, edge, np.tile(self.normals, (3, 1)))
        for k, region in enumerate((EDGE_AB, EDGE_BC, EDGE_CA)):
            out[:, region] = edge_sum[edge[k * len(t):(k + 1) * len(t)]]
        # Vertices: the normals of their triangles weighted by the angles there.
        vertex_sum = np.zeros((len(self.points), 3))
        for k in range(3):
            here = self.corners[:, k]
            u = self.corners[:, (k + 1) % 3] - here
            v = self.corners[:, (k + 2) % 3] - here
            cosine = np.einsum("ij,ij->i", u, v) / (np.linalg.norm(u, axis=1) * np.linalg.norm(v, axis=1))
            np.add.at(vertex_sum, t[:, k], np.arccos(np.clip(cosine, -1.0, 1.0))[:, None] * self.normals)
        for k, region in enumerate((VERTEX_A, VERTEX_B, VERTEX_C)):
            out[:, region] = vertex_sum[t[:, k]]
        return out

    # -- distances -----------------------------------------------------------------------------
    def candidate_pairs(self, points: np.ndarray, radii: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(point, triangle) index pairs, each once, of every triangle that may come within
        ``radii`` of each point: the triangles of the samples within radii + h."""
        lists = self.sample_tree.query_ball_point(points, radii + self.covering_radius)
        counts = np.fromiter(map(len, lists), dtype=np.int64, count=len(lists))
        samples = np.fromiter(itertools.chain.from_iterable(lists), dtype=np.int64, count=int(counts.sum()))
        key = np.unique(np.repeat(np.arange(len(points)), counts) * len(self.triangles) + self.sample_triangles[samples])
        return key // len(self.triangles), key % len(self.triangles)

    def distance_bounds(self, points: np.ndarray, within=np.inf) -> tuple[np.ndarray, np.ndarray]:
        """In the object's frame: a lower and an upper bound of each point's distance to the
        surface, D - h and D (module docstring). A point whose nearest sample lies beyond the
        largest of ``within`` (a number or one per point) plus h, surely farther than that, gets
        that largest ``within`` and inf: the tree's search stops there."""
        reach = float(np.max(within, initial=0.0))
        upper = self.sample_tree.query(points, distance_upper_bound=reach + self.covering_radius)[0]
        lower = upper - self.covering_radius
        lower[~np.isfinite(upper)] = reach
        return lower, upper

    def local_distances(self, points: np.ndarray, within=np.inf, chunk: int = 4096):
        """In the object's frame: signed gap, unit normal and gap Hessian (k, 3, 3) of each point
        whose distance may be below ``within`` (a number or one per point); a lower bound of the
        distance, at least ``within``, and zeros for the others (module docstring)."""
        n = len(points)
        lower, upper = self.distance_bounds(points, within)
        gap, normal, hessian = lower, np.zeros((n, 3)), np.zeros((n, 3, 3))
        near = np.flatnonzero(lower < within)
        for start in range(0, len(near), chunk):
            part = near[start:start + chunk]
            gap[part], normal[part], hessian[part] = self._distances(points[part], upper[part])
        return gap, normal, hessian

    def _distances(self, points: np.ndarray, upper: np.ndarray):
        # The nearest triangle is no farther than the nearest sample.
        which, tri = self.candidate_pairs(points, upper)
        distance, offset, region = self._pair_offsets(points[which], tri)
        first = self._nearest(which, distance, len(points))
        d, offset, reg, t = distance[first], offset[first], region[first], tri[first]
        sign = self._signs(offset, t, reg)
        unit = self._units(d, offset, t, reg)
        with np.errstate(divide="ignore"):
            scale = np.where(d > 0.0, sign / d, 0.0)
        return sign * d, sign[:, None] * unit, scale[:, None, None] * self._projections(unit, t, reg)

    def _pair_offsets(self, p: np.ndarray, tri: np.ndarray):
        """Distance, offset x - closest point and closest-point region of each (point, triangle) pair."""
        corners = self.corners[tri]
        closest, _, region = closest_points(p, corners[:, 0], corners[:, 1], corners[:, 2])
        offset = p - closest
        return np.linalg.norm(offset, axis=1), offset, region

    @staticmethod
    def _nearest(which: np.ndarray, distance: np.ndarray, count: int) -> np.ndarray:
        """The pair of least distance of each of ``count`` points (every point has a pair)."""
        order = np.lexsort((distance, which))
        return order[np.searchsorted(which[order], np.arange(count))]

    def _signs(self, offset: np.ndarray, tri: np.ndarray, region: np.ndarray) -> np.ndarray:
        """+1 outside, -1 inside: the side of the closest feature's pseudonormal."""
        return np.where(np.einsum("ij,ij->i", offset, self.pseudonormals[tri, region]) < 0.0, -1.0, 1.0)

    def _units(self, d: np.ndarray, offset: np.ndarray, tri: np.ndarray, region: np.ndarray) -> np.ndarray:
        """(x - p) / |x - p|, or the feature's pseudonormal for a point on the surface."""
        pseudo = self.pseudonormals[tri, region]
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(d[:, None] > 0.0, offset / d[:, None], pseudo / np.linalg.norm(pseudo, axis=1)[:, None])

    def _projections(self, unit: np.ndarray, tri: np.ndarray, region: np.ndarray) -> np.ndarray:
        """d times the Hessian of the distance to the closed triangle: the projection off the
        closest feature and the normal (0 over the face)."""
        projection = np.eye(3) - unit[:, :, None] * unit[:, None, :]
        edge = np.isin(region, list(_EDGE_ENDS))
        if edge.any():
            ends = np.array([_EDGE_ENDS[r] for r in region[edge]])
            tangent = self.corners[tri[edge], ends[:, 1]] - self.corners[tri[edge], ends[:, 0]]
            tangent /= np.linalg.norm(tangent, axis=1)[:, None]
            projection[edge] -= tangent[:, :, None] * tangent[:, None, :]
        projection[region == FACE] = 0.0
        return projection

    def local_features(self, points: np.ndarray, within: float):
        """In the object's frame: the barrier's terms of the points within ``within`` of the
        surface (module docstring, "a smooth barrier"): one per (point, triangle), (point, edge)
        and (point, vertex) pair closer than ``within``, as the point's index, the term's sign (+1
        for triangles and vertices, -1 for edges), the distance to the feature (signed by the
        point's side of the surface), and its unit gradient and (k, 3, 3) Hessian. A point inside
        the surface gets only its nearest triangle, with a negative distance."""
        empty = (np.zeros(0, dtype=np.int64), np.zeros(0), np.zeros(0), np.zeros((0, 3)), np.zeros((0, 3, 3)))
        lower, upper = self.distance_bounds(points, within)
        near = np.flatnonzero(lower < within)
        if not near.size:
            return empty
        # Candidates: every triangle within ``within``, and the nearest one (no farther than D).
        which, tri = self.candidate_pairs(points[near], np.maximum(upper[near], within))
        p = points[near]
        distance, offset, region = self._pair_offsets(p[which], tri)
        first = self._nearest(which, distance, len(near))
        side = self._signs(offset[first], tri[first], region[first])
        outside = side[which] > 0.0
        # Triangles: the distance to the closed triangle.
        face = (distance < within) & outside
        face[first[side < 0.0]] = True
        unit = self._units(distance[face], offset[face], tri[face], region[face])
        terms = [(which[face], np.ones(int(face.sum())), distance[face] * side[which[face]],
                  side[which[face], None] * unit, self._projections(unit, tri[face], region[face]))]
        # Edges and vertices of the candidate triangles (an edge or a vertex within reach belongs
        # to a triangle within reach), each once per point; outside points only.
        nodes, tri = which[outside], tri[outside]
        for sign, ids, count in ((-1.0, self.triangle_edges[tri], len(self.edges)),
                                 (1.0, self.triangles[tri], len(self.points))):
            key = np.unique(np.repeat(nodes, 3) * count + ids.reshape(-1))
            node, feature = key // count, key % count
            if sign < 0.0:
                a, b = self.points[self.edges[feature, 0]], self.points[self.edges[feature, 1]]
                along = b - a
                t = np.clip(np.einsum("ij,ij->i", p[node] - a, along) / np.einsum("ij,ij->i", along, along), 0.0, 1.0)
                offset = p[node] - (a + t[:, None] * along)
            else:
                offset = p[node] - self.points[feature]
            d = np.linalg.norm(offset, axis=1)
            close = d < within
            node, offset, d = node[close], offset[close], d[close]
            unit = offset / d[:, None]
            projection = np.eye(3) - unit[:, :, None] * unit[:, None, :]
            if sign < 0.0:
                # Off the segment's interior the distance is to an end point, as to a vertex.
                inner = ((t[close] > 0.0) & (t[close] < 1.0))
                e = along[close][inner] / np.linalg.norm(along[close][inner], axis=1)[:, None]
                projection[inner] -= e[:, :, None] * e[:, None, :]
            terms.append((node, np.full(len(node), sign), d, unit, projection))
        node, sign, d, unit, projection = (np.concatenate(parts) for parts in zip(*terms))
        with np.errstate(divide="ignore"):
            scale = np.where(d != 0.0, 1.0 / d, 0.0)
        return near[node], sign, d, unit, scale[:, None, None] * projection

    def barrier_terms(self, points: np.ndarray, pose: AffineMap, within: float):
        """``local_features`` of points in the world at ``pose`` (rigid): (point index, sign,
        distance, unit gradient, Hessian) of every (point, feature) pair closer than ``within``."""
        rotation = pose.matrix
        local = (points - pose.translation) @ rotation
        which, sign, distance, unit, hessian = self.local_features(local, within)
        return which, sign, distance, unit @ rotation.T, np.einsum("ij,kjl,ml->kim", rotation, hessian, rotation)

    def gaps(self, points: np.ndarray, pose: AffineMap, within=np.inf) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Signed gap of each point (world) to the surface at ``pose`` (rigid), the unit outward
        normal there, and the gap's Hessian (k, 3, 3); for the points that are surely farther than
        ``within`` (a number or one per point) a lower bound of the distance, at least ``within``,
        and zeros (module docstring)."""
        rotation = pose.matrix
        local = (points - pose.translation) @ rotation
        gap, normal, hessian = self.local_distances(local, within)
        return gap, normal @ rotation.T, np.einsum("ij,kjl,ml->kim", rotation, hessian, rotation)

    def first_contact(self, points: np.ndarray, steps: np.ndarray, pose: AffineMap,
                      clearance: np.ndarray) -> np.ndarray:
        """For each point, a time t > 0 no later than the first at which points + t steps comes
        within ``clearance`` of the surface (inf if never; module docstring)."""
        rotation = pose.matrix
        local = (points - pose.translation) @ rotation
        moves = steps @ rotation
        length = np.linalg.norm(moves, axis=1)
        # No point comes within the clearance before it has moved its distance less the clearance.
        lower = self.distance_bounds(local, length + clearance)[0]
        with np.errstate(divide="ignore", invalid="ignore"):
            t = np.where(length > 0.0, (lower - clearance) / length, np.inf)
        reachable = np.flatnonzero(t < 1.0)
        if not reachable.size:
            return t
        which, tri = self.candidate_pairs(local[reachable], length[reachable] + clearance[reachable])
        p, s, c = local[reachable][which], moves[reachable][which], clearance[reachable][which]
        corners = self.corners[tri]
        closest = closest_points(p, corners[:, 0], corners[:, 1], corners[:, 2])[0]
        n = self.normals[tri]
        height, approach = np.einsum("ij,ij->i", p - corners[:, 0], n), -np.einsum("ij,ij->i", s, n)
        distance = np.linalg.norm(p - closest, axis=1)
        # The distance of a point moving on a line to a convex set (the triangle) is convex in t:
        # it stays above its tangent at t = 0, whose slope is the step along the pair's normal.
        closing = -np.einsum("ij,ij->i", p - closest, s) / np.maximum(distance, 1e-300)
        with np.errstate(divide="ignore", invalid="ignore"):
            by_plane = np.where(height <= c, 0.0, np.where(approach > 0.0, (height - c) / approach, np.inf))
            by_tangent = np.where(closing > 0.0, (distance - c) / closing, np.inf)
        pair = np.maximum(by_plane, np.maximum(by_tangent, 0.0))
        refined = np.full(len(reachable), np.inf)
        np.minimum.at(refined, which, pair)
        # Triangles beyond the candidates are not reached before t = 1 (nor before the bound t).
        t[reachable] = np.minimum(refined, np.maximum(t[reachable], 1.0))
        return t

    def describe(self) -> str:
        return f"triangle surface {self.name} ({len(self.triangles)} triangles)"

    def surface(self) -> tuple[np.ndarray, np.ndarray]:
        """Points and triangles in the object's frame, for output."""
        return self.points, self.triangles
