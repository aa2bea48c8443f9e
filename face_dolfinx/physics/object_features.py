"""A triangle-mesh object's vertices and edges kept off the skin: an instrument's tip or a blade's
edge between the skin's nodes (IPC barriers on point-triangle, point-edge, point-point and
mollified edge-edge distances).

``ContactPotential`` keeps every skin *node* outside a triangle-mesh object; a part of the object
sharper than the skin's triangles (an instrument's tip, a blade's edge, a corner of a mask) can
still pass through a skin face between the nodes, which no node's gap sees. Two polyhedral
surfaces first touch vertex to face or edge to edge (IPC's pairs), so ``ObjectFeatureContact`` adds
the barriers of the object's vertices and edges against the skin:

- every vertex v of the object, weighted by its rest area A_v (a third of the object's triangles
  around it), gets the barrier of its distance to the skin as the mirror image of the nodes'
  smooth barrier: the sum over the skin's features within dhat of it, the closed triangles and
  nodes with sign +1 and the edges with sign -1 (``TriangleMesh.barrier_terms``' construction,
  docs/contact.md "A smooth barrier"),

      E_v = stiffness / dhat * sum_v A_v [ sum_T b(d(v, T)) - sum_e b(d(v, e)) + sum_n b(|v - x_n|) ],

  which, where the skin within dhat of v is one disc, is b(distance from v to the skin);
- every pair of an object edge a and a skin edge e within dhat gets IPC's mollified edge-edge
  barrier, weighted by the object edge's rest area A_a (a third of its two triangles),

      E_e = stiffness / dhat * sum_(a, e) A_a m(a, e) b(d(a, e)),

  m the IPC Toolkit's mollifier (``ipctk.edge_edge_mollifier``), which takes the term smoothly to
  zero as the edges turn parallel, where the distance between them is not differentiable.

Each term is C1 in the skin's nodes. Its gradient and Hessian come from the IPC Toolkit's squared
distances (``ipctk.point_triangle_distance``, its point-edge, point-point and edge-edge siblings,
with their derivatives) through the square root and the barrier, and are written into the 9 x 9
block of a skin triangle that holds the skin feature (inside the finite-element sparsity). Newton
takes the blocks projected onto the positive semidefinite ones until it is near the solution, then
the exact ones (``exact_near_solution``, as the lips do: projected throughout, the distance's
curvature as a skin face turns with its corners is lost and Newton converged linearly). The skin's
nodes keep their own barrier against the object's surface, so a face of the object resting flat
on the skin is held by the nodes' and the vertices' barriers together.

Collision-free steps: the object stands still during a solve while the skin moves; each (vertex,
skin triangle) and (object edge, skin edge) pair whose skin feature moves by more than CCD_KEEP
of their distance is tested by the IPC Toolkit's additive CCD with the minimum distance
(1 - CCD_KEEP) of that distance, so no Newton iterate puts a vertex or an edge of the object
through the skin.

Moving the object (``push_out``): after the nodes' push-out, the straight path of each vertex and
each edge from the old pose to the new one is tested against the skin's triangles and edges with
the minimum distance PUSH_GAP * dhat (or (1 - CCD_KEEP) of the pair's distance, if it rests
closer): a vertex's path exactly (``path_contacts``), an edge's by the additive CCD. A skin
triangle or edge that a path reaches at the time t moves with the rest of the path, (1 - t) of its
move plus PUSH_GAP * dhat further, the dent the object makes, round after round until no path
reaches the skin. The dented nodes are held in the solve that spreads the
dent into the flesh (``move_to``), as the pushed nodes are.

Under MPI every rank holds all nodes and triangles of the contact surface (gathered by
``ContactSurface``), computes the same terms and adds the rows of the nodes it owns.
"""
from dataclasses import dataclass

import ipctk
import numpy as np
from scipy.spatial import cKDTree

from face_dolfinx.alignment.surface import closest_points
from face_dolfinx.physics.contact import CCD_KEEP, PUSH_GAP, ContactPotential, Sphere
from face_dolfinx.physics.face_contact import NARROW_PHASE, PUSH_ROUNDS, FaceContactPotential, distance_from_squared
from face_dolfinx.physics.rigid_mesh import TriangleMesh

# Bisections of a vertex path's first contact (``path_contacts``): the time to 2^-50 of the path.
PATH_BISECTIONS = 50

# The features of a skin triangle as masks of its corners: the face, its edges ab, bc, ca, its
# corners a, b, c.
FEATURE_MASKS = np.array([7, 3, 6, 5, 1, 2, 4])


def surface_areas(obj: TriangleMesh) -> tuple[np.ndarray, np.ndarray]:
    """Each vertex's and each edge's share of a triangle mesh's area: a third of every triangle on
    it."""
    corners = obj.corners
    third = np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1) / 6.0
    vertex = np.bincount(obj.triangles.reshape(-1), np.repeat(third, 3), minlength=len(obj.points))
    edge = np.bincount(obj.triangle_edges.reshape(-1), np.repeat(third, 3), minlength=len(obj.edges))
    return vertex, edge


def barrier_of_squared_distance(squared: float, gradient: np.ndarray, hessian: np.ndarray, dhat: float,
                                mollifier=None) -> tuple[float, np.ndarray, np.ndarray]:
    """phi = m b(d), d = sqrt(s), with its gradient and Hessian, from the squared distance s and
    its derivatives (and the mollifier m with its derivatives, or none: m = 1)."""
    d, d_gradient, d_hessian = distance_from_squared(squared, gradient, hessian)
    b, b1, b2 = ipctk.barrier(d, dhat), ipctk.barrier_first_derivative(d, dhat), ipctk.barrier_second_derivative(d, dhat)
    value, phi_gradient = b, b1 * d_gradient
    phi_hessian = b2 * np.outer(d_gradient, d_gradient) + b1 * d_hessian
    if mollifier is not None:
        m, m_gradient, m_hessian = mollifier
        cross = b1 * np.outer(m_gradient, d_gradient)
        value, phi_gradient = m * b, b * m_gradient + m * phi_gradient
        phi_hessian = b * m_hessian + cross + cross.T + m * phi_hessian
    return value, phi_gradient, phi_hessian


def path_contacts(start: np.ndarray, end: np.ndarray, corners: np.ndarray, clearance: np.ndarray) -> np.ndarray:
    """The first time t in [0, 1] at which each point moving straight from ``start`` to ``end`` (m, 3)
    comes within ``clearance`` (m,) of its standing triangle ``corners`` (m, 3, 3); inf where it
    does not. The distance from a point moving on a line to a convex set is convex in the time, so
    its minimum over the path is found by golden-section search and the first crossing by
    bisection before it: exact to 2^-PATH_BISECTIONS of the path. (The additive CCD of the step
    bounds reported the apex of a probe moved from 10 mm to 1 mm off the 5K face's cheek as
    reaching a skin triangle at 0.997 of its path, its distance never below 1 mm, and dented the
    skin for nothing; tight inclusion with a minimum distance took seconds per move on the test
    slab.)"""
    def distance(t):
        points = start + t[:, None] * (end - start)
        nearest = closest_points(points, corners[:, 0], corners[:, 1], corners[:, 2])[0]
        return np.linalg.norm(points - nearest, axis=1)

    if not len(start):
        return np.zeros(0)
    low, high = np.zeros(len(start)), np.ones(len(start))
    ratio = (np.sqrt(5.0) - 1.0) / 2.0
    a, b = high - ratio * (high - low), low + ratio * (high - low)
    at_a, at_b = distance(a), distance(b)
    for _ in range(PATH_BISECTIONS):
        # The kept inner point is the new interval's other golden point (ratio^2 = 1 - ratio): one
        # distance per round.
        left = at_a < at_b
        high, low = np.where(left, b, high), np.where(left, low, a)
        new = np.where(left, high - ratio * (high - low), low + ratio * (high - low))
        at_new = distance(new)
        a, at_a, b, at_b = (np.where(left, new, b), np.where(left, at_new, at_b),
                            np.where(left, a, new), np.where(left, at_a, at_new))
    lowest = 0.5 * (low + high)
    hits = np.minimum(distance(lowest), distance(np.ones(len(start)))) < clearance
    # The distance falls from t = 0 to ``lowest``: bisect for where it reaches the clearance.
    low, high = np.zeros(len(start)), lowest
    for _ in range(PATH_BISECTIONS):
        middle = 0.5 * (low + high)
        reached = distance(middle) < clearance
        high, low = np.where(reached, middle, high), np.where(reached, low, middle)
    return np.where(hits, low, np.inf)


@dataclass
class _ObjectFeatures:
    """A triangle-mesh object's areas and its collision mesh joined with the skin's (skin nodes and
    edges first), whose broad phase pairs only the object's edges with the skin's."""

    vertex_areas: np.ndarray
    edge_areas: np.ndarray
    edges: np.ndarray  # object vertex pairs, in the joined mesh after the skin's edges
    mesh: ipctk.CollisionMesh


class ObjectFeatureContact(FaceContactPotential):
    """``FaceContactPotential`` whose triangle-mesh objects also keep their vertices and edges off
    the contact surface (module docstring); spheres act on the triangles and every object on the
    nodes as there."""

    def __init__(self, space, facets, settings):
        super().__init__(space, facets, settings)
        triangles = self.surface.triangles
        directed = np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]])
        self.skin_edges, first = np.unique(np.sort(directed, axis=1), axis=0, return_index=True)
        # The triangle holding each skin edge and the edge's corners there.
        self.skin_edge_host = first % len(triangles)
        slot = first // len(triangles)
        ends = np.array([[0, 1], [1, 2], [2, 0]])[slot]
        swapped = triangles[self.skin_edge_host, ends[:, 0]] != self.skin_edges[:, 0]
        self.skin_edge_slots = np.where(swapped[:, None], ends[:, ::-1], ends)
        self.features = tuple(self._object_features(obj) if isinstance(obj, TriangleMesh) else None
                              for obj in self.objects)
        self._last_object_terms = None  # (positions, poses, ignored, terms) of the last ``object_terms``

    def _object_features(self, obj: TriangleMesh) -> _ObjectFeatures:
        vertex_areas, edge_areas = surface_areas(obj)
        count = self.surface.num_nodes
        vertices = np.asfortranarray(np.vstack([self.surface.rest, obj.points]))
        faces = np.asfortranarray(np.vstack([self.surface.triangles, obj.triangles + count]), dtype=np.int32)
        edges = np.asfortranarray(np.vstack([self.skin_edges, obj.edges + count]), dtype=np.int32)
        mesh = ipctk.CollisionMesh(vertices, edges, faces)
        mesh.can_collide = ipctk.make_vertex_patches_filter(
            np.concatenate([np.zeros(count, dtype=np.int32), np.ones(len(obj.points), dtype=np.int32)]))
        return _ObjectFeatures(vertex_areas, edge_areas, obj.edges, mesh)

    # -- candidate pairs -----------------------------------------------------------------------
    def _vertex_candidates(self, x: np.ndarray, points: np.ndarray, reach: float) -> tuple[np.ndarray, np.ndarray]:
        """(vertex, triangle) pairs of the object's ``points`` and the free triangles of the surface
        at ``x`` that may lie within ``reach``: the vertices within that plus the triangle's radius
        of its centroid."""
        free = np.flatnonzero(self.free_triangles())
        if not free.size or not len(points):
            return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
        corners = x[self.surface.triangles[free]]
        centroids = corners.mean(axis=1)
        radius = np.linalg.norm(corners - centroids[:, None], axis=2).max(axis=1)
        lists = cKDTree(points).query_ball_point(centroids, radius + reach)
        counts = np.fromiter((len(item) for item in lists), dtype=np.int64, count=len(lists))
        vertices = np.fromiter((i for item in lists for i in item), dtype=np.int64, count=int(counts.sum()))
        return vertices, np.repeat(free, counts)

    def _vertex_distances(self, x, points, vertex, triangle) -> np.ndarray:
        corners = x[self.surface.triangles[triangle]]
        nearest = closest_points(points[vertex], corners[:, 0], corners[:, 1], corners[:, 2])[0]
        return np.linalg.norm(points[vertex] - nearest, axis=1)

    def _edge_candidates(self, features: _ObjectFeatures, x0, points0, x1=None, points1=None,
                         inflation: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """(object edge, skin edge) pairs whose boxes (of the straight paths from ``x0``, ``points0``
        to ``x1``, ``points1``, if given) come within ``inflation`` (the IPC Toolkit's broad phase),
        skin edges with a left-out node dropped."""
        candidates = ipctk.Candidates()
        start = np.asfortranarray(np.vstack([x0, points0]))
        if x1 is None:
            candidates.build(features.mesh, start, inflation)
        else:
            candidates.build(features.mesh, start, np.asfortranarray(np.vstack([x1, points1])), inflation)
        count = len(self.skin_edges)
        pairs = np.array([(c.edge0_id, c.edge1_id) for c in candidates.ee_candidates], dtype=np.int64).reshape(-1, 2)
        pairs.sort(axis=1)  # the skin's edges come first in the joined mesh
        pairs = pairs[(pairs[:, 0] < count) & (pairs[:, 1] >= count)]
        skin, edge = pairs[:, 0], pairs[:, 1] - count
        keep = ~self.ignored[self.skin_edges[skin]].any(axis=1)
        return edge[keep], skin[keep]

    # -- the terms -----------------------------------------------------------------------------
    def object_terms(self, displacement: np.ndarray) -> list:
        """Per triangle-mesh object (in their order among the objects): its barrier's terms
        (module docstring), each a (vertex, skin feature) or (object edge, skin edge) pair within
        dhat: the skin triangle holding the skin feature (m,), the weight (the object feature's
        area, times the sign of a vertex's feature), phi = m b(d) (m = 1 for a vertex), its
        gradient in the triangle's corners (m, 3, 3; zero rows for corners off the feature) and
        Hessian (m, 9, 9), the Hessian's block mixing the corners with the object feature's
        vertices (m, 9, 6; a vertex's in the first three columns) and those vertices (m, 2; a
        vertex's second is -1). The energy, gradient, Hessian, Newton correction and pose rates
        of one state share them."""
        x = self.positions(displacement)
        last = self._last_object_terms
        if last is not None and last[1] is self.poses and last[2] is self.ignored and np.array_equal(last[0], x):
            return last[3]
        terms = [self._terms_of(x, obj, pose, features)
                 for obj, pose, features in zip(self.objects, self.poses, self.features) if features is not None]
        self._last_object_terms = (x, self.poses, self.ignored, terms)
        return terms

    def _terms_of(self, x: np.ndarray, obj: TriangleMesh, pose, features: _ObjectFeatures) -> tuple:
        points = pose.apply(obj.points)
        triangles = self.surface.triangles
        rows = []  # (host, weight, value, gradient, hessian, mixed, object vertices)
        # The vertices: each (vertex, skin feature) once, every feature of the triangles within
        # dhat of it, an edge or corner that two such triangles share kept with the first of them.
        vertex, triangle = self._vertex_candidates(x, points, self.dhat)
        near = self._vertex_distances(x, points, vertex, triangle) < self.dhat
        vertex, host = np.repeat(vertex[near], len(FEATURE_MASKS)), np.repeat(triangle[near], len(FEATURE_MASKS))
        mask = np.tile(FEATURE_MASKS, int(near.sum()))
        on = ((mask[:, None] >> np.arange(3)) & 1).astype(bool)
        _, first = np.unique(np.column_stack([vertex, np.sort(np.where(on, triangles[host], -1), axis=1)]), axis=0,
                             return_index=True)
        for v, t, slots in zip(vertex[first], host[first], on[first]):
            p, c = points[v], x[triangles[t]][slots]
            if len(c) == 3:
                squared = (ipctk.point_triangle_distance(p, *c), ipctk.point_triangle_distance_gradient(p, *c),
                           ipctk.point_triangle_distance_hessian(p, *c))
            elif len(c) == 2:
                squared = (ipctk.point_edge_distance(p, *c), ipctk.point_edge_distance_gradient(p, *c),
                           ipctk.point_edge_distance_hessian(p, *c))
            else:
                squared = (ipctk.point_point_distance(p, *c), ipctk.point_point_distance_gradient(p, *c),
                           ipctk.point_point_distance_hessian(p, *c))
            if squared[0] >= self.dhat ** 2:
                continue
            sign = -1.0 if len(c) == 2 else 1.0
            rows.append(self._row(t, np.flatnonzero(slots), sign * features.vertex_areas[v], (v, -1), 3,
                                  barrier_of_squared_distance(*squared, self.dhat)))
        # The edges.
        for a, e in zip(*self._edge_candidates(features, x, points, inflation=self.dhat)):
            ea0, ea1 = points[features.edges[a]]
            eb0, eb1 = x[self.skin_edges[e]]
            squared = ipctk.edge_edge_distance(ea0, ea1, eb0, eb1)
            if squared >= self.dhat ** 2:
                continue
            rest = np.vstack([obj.points[features.edges[a]], self.surface.rest[self.skin_edges[e]]])
            eps_x = ipctk.edge_edge_mollifier_threshold(*rest)
            mollifier = (ipctk.edge_edge_mollifier(ea0, ea1, eb0, eb1, eps_x),
                         ipctk.edge_edge_mollifier_gradient(ea0, ea1, eb0, eb1, eps_x),
                         ipctk.edge_edge_mollifier_hessian(ea0, ea1, eb0, eb1, eps_x))
            if mollifier[0] == 0.0:
                continue
            term = barrier_of_squared_distance(squared, ipctk.edge_edge_distance_gradient(ea0, ea1, eb0, eb1),
                                               ipctk.edge_edge_distance_hessian(ea0, ea1, eb0, eb1), self.dhat,
                                               mollifier)
            rows.append(self._row(self.skin_edge_host[e], self.skin_edge_slots[e], features.edge_areas[a],
                                  tuple(features.edges[a]), 6, term))
        if not rows:
            return (np.zeros(0, dtype=np.int64), np.zeros(0), np.zeros(0), np.zeros((0, 3, 3)), np.zeros((0, 9, 9)),
                    np.zeros((0, 9, 6)), np.zeros((0, 2), dtype=np.int64))
        return tuple(np.array(column) for column in zip(*rows))

    @staticmethod
    def _row(host: int, slots: np.ndarray, weight: float, object_vertices: tuple, size: int, term) -> tuple:
        """One term of ``object_terms`` from phi and its derivatives in (the object feature's
        ``size`` coordinates, then the skin feature's nodes in the corners ``slots`` of ``host``)."""
        value, gradient, hessian = term
        dofs = (3 * np.asarray(slots)[:, None] + np.arange(3)).reshape(-1)
        corner_gradient, corner_hessian, mixed = np.zeros(9), np.zeros((9, 9)), np.zeros((9, 6))
        corner_gradient[dofs] = gradient[size:]
        corner_hessian[np.ix_(dofs, dofs)] = hessian[size:, size:]
        mixed[dofs, :size] = hessian[size:, :size]
        return host, weight, value, corner_gradient.reshape(3, 3), corner_hessian, mixed, object_vertices

    # -- the solver's energy-term interface ---------------------------------------------------
    def energy(self, x) -> float:
        scale = self.stiffness / self.dhat
        objects = sum(scale * (weight * value).sum() for _, weight, value, *_ in self.object_terms(x.array_r))
        return super().energy(x) + float(objects)

    def nodal_forces(self, displacement: np.ndarray) -> np.ndarray:
        gradient = super().nodal_forces(displacement)
        scale = self.stiffness / self.dhat
        for host, weight, _, gradients, *_ in self.object_terms(displacement):
            np.add.at(gradient, self.surface.triangles[host], (scale * weight)[:, None, None] * gradients)
        return gradient

    def triangle_blocks(self, displacement: np.ndarray) -> list:
        """The spheres' triangle blocks and the objects' features' (in the triangles that hold the
        skin features)."""
        blocks = super().triangle_blocks(displacement)
        scale = self.stiffness / self.dhat
        for host, weight, _, _, hessians, *_ in self.object_terms(displacement):
            blocks.append((host, (scale * weight)[:, None, None] * hessians))
        return blocks

    # -- diagnostics ---------------------------------------------------------------------------
    def vertex_gaps(self, displacement: np.ndarray, within: float, poses=None) -> list:
        """Per triangle-mesh object: each vertex's distance to the nearest free triangle of the
        contact surface (mm), ``within`` where none lies closer than that."""
        x = self.positions(displacement)
        poses = self.poses if poses is None else poses
        out = []
        for obj, pose, features in zip(self.objects, poses, self.features):
            if features is None:
                continue
            points = pose.apply(obj.points)
            vertex, triangle = self._vertex_candidates(x, points, within)
            gap = np.full(len(points), float(within))
            np.minimum.at(gap, vertex, self._vertex_distances(x, points, vertex, triangle))
            out.append(gap)
        return out

    def edge_gaps(self, displacement: np.ndarray, within: float) -> list:
        """Per triangle-mesh object: each edge's distance to the nearest skin edge (mm), ``within``
        where none lies closer than that."""
        x = self.positions(displacement)
        out = []
        for obj, pose, features in zip(self.objects, self.poses, self.features):
            if features is None:
                continue
            points = pose.apply(obj.points)
            gap = np.full(len(features.edges), float(within))
            for a, e in zip(*self._edge_candidates(features, x, points, inflation=within)):
                squared = ipctk.edge_edge_distance(*points[features.edges[a]], *x[self.skin_edges[e]])
                gap[a] = min(gap[a], np.sqrt(squared))
            out.append(gap)
        return out

    def contact_features(self, displacement: np.ndarray) -> tuple[int, int]:
        """Numbers of object vertices and of object edges within dhat of the contact surface."""
        vertices = sum(int((gap < self.dhat).sum()) for gap in self.vertex_gaps(displacement, within=self.dhat))
        edges = sum(int((gap < self.dhat).sum()) for gap in self.edge_gaps(displacement, within=self.dhat))
        return vertices, edges

    # -- collision-free steps ------------------------------------------------------------------
    def admissible_fraction(self, start: np.ndarray, end: np.ndarray) -> float:
        """The spheres' and nodes' bound, and no point of the straight path from the displacement
        ``start`` to ``end`` brings a skin triangle closer to an object's vertex, or a skin edge
        to an object's edge, than (1 - CCD_KEEP) of their distance now."""
        fraction = super().admissible_fraction(start, end)
        x0, x1 = self.positions(start), self.positions(end)
        node_move = np.linalg.norm(x1 - x0, axis=1)
        if not node_move.max(initial=0.0) > 0.0:
            return fraction
        triangles = self.surface.triangles
        move = node_move[triangles].max(axis=1)
        for obj, pose, features in zip(self.objects, self.poses, self.features):
            if features is None:
                continue
            points = pose.apply(obj.points)
            vertex, triangle = self._vertex_candidates(x0, points, move.max() / CCD_KEEP)
            distance = self._vertex_distances(x0, points, vertex, triangle)
            # A pair whose skin feature moves by less than CCD_KEEP of its distance keeps the rest.
            tested = move[triangle] > CCD_KEEP * distance
            for v, t, d in zip(vertex[tested], triangle[tested], distance[tested]):
                p = points[v]
                hit, toi = NARROW_PHASE.point_triangle_ccd(p, *x0[triangles[t]], p, *x1[triangles[t]],
                                                           min_distance=(1.0 - CCD_KEEP) * d, tmax=fraction)
                if hit:
                    fraction = min(fraction, toi)
            for a, e in zip(*self._edge_candidates(features, x0, points, x1, points)):
                ea = points[features.edges[a]]
                nodes = self.skin_edges[e]
                d = np.sqrt(ipctk.edge_edge_distance(*ea, *x0[nodes]))
                if node_move[nodes].max() > CCD_KEEP * d:
                    hit, toi = NARROW_PHASE.edge_edge_ccd(*ea, *x0[nodes], *ea, *x1[nodes],
                                                          min_distance=(1.0 - CCD_KEEP) * d, tmax=fraction)
                    if hit:
                        fraction = min(fraction, toi)
        return fraction

    # -- moving the objects ------------------------------------------------------------------
    def _path_contacts(self, x: np.ndarray, old, new, obj: TriangleMesh, features: _ObjectFeatures) -> list:
        """Where the object's move from the pose ``old`` to ``new`` reaches the surface at ``x``
        (standing still): (skin nodes, time, the object feature's step) of each vertex's first
        free triangle and each edge's first skin edge that its straight path comes within
        PUSH_GAP * dhat of (or (1 - CCD_KEEP) of their distance at the start, if closer)."""
        start, end = old.apply(obj.points), new.apply(obj.points)
        path = np.linalg.norm(end - start, axis=1)
        if not path.max(initial=0.0) > 0.0:
            return []
        target = PUSH_GAP * self.dhat
        triangles = self.surface.triangles
        contacts = []
        # Every point of a vertex's path lies within half its length of its middle.
        vertex, triangle = self._vertex_candidates(x, 0.5 * (start + end), 0.5 * path.max() + target)
        distance = self._vertex_distances(x, start, vertex, triangle)
        times = path_contacts(start[vertex], end[vertex], x[triangles[triangle]],
                              np.minimum(target, (1.0 - CCD_KEEP) * distance))
        first = {}
        for v, t, toi in zip(vertex, triangle, times):
            if np.isfinite(toi) and toi < first.get(v, (None, np.inf))[1]:
                first[v] = (t, toi)
        contacts += [(triangles[t], toi, end[v] - start[v]) for v, (t, toi) in first.items()]
        first = {}
        for a, e in zip(*self._edge_candidates(features, x, start, x, end, inflation=target)):
            ends, nodes = features.edges[a], self.skin_edges[e]
            d = np.sqrt(ipctk.edge_edge_distance(*start[ends], *x[nodes]))
            hit, toi = NARROW_PHASE.edge_edge_ccd(*start[ends], *x[nodes], *end[ends], *x[nodes],
                                                  min_distance=min(target, (1.0 - CCD_KEEP) * d),
                                                  tmax=first.get(a, (None, 1.0))[1])
            if hit:
                first[a] = (e, toi)
        contacts += [(self.skin_edges[e], toi, (end - start)[features.edges[a]].mean(axis=0))
                     for a, (e, toi) in first.items()]
        return contacts

    def closes_in(self, displacement: np.ndarray, old_poses, new_poses) -> bool:
        """The nodes' and spheres' test, and whether a path of an object's vertex or edge to its
        new pose reaches the skin (``_path_contacts``)."""
        if super().closes_in(displacement, old_poses, new_poses):
            return True
        x = self.positions(displacement)
        return any(features is not None and self._path_contacts(x, old, new, obj, features)
                   for obj, old, new, features in zip(self.objects, old_poses, new_poses, self.features))

    def push_out(self, displacement: np.ndarray, poses) -> tuple[np.ndarray, np.ndarray]:
        """The nodes' and spheres' push-out, then the dent of the object's move (module docstring):
        the skin feature that a vertex's or edge's path reaches at the time t of its path moves by
        (1 - t) of the feature's step plus PUSH_GAP * dhat along it, round after round
        (PUSH_ROUNDS) until no path reaches the skin; the moved nodes join the held ones."""
        out, held = super().push_out(displacement, poses)
        x = self.positions(out)
        moved = np.zeros(len(x), dtype=bool)
        target = PUSH_GAP * self.dhat
        for obj, old, new, features in zip(self.objects, self.poses, poses, self.features):
            if features is None:
                continue
            for _ in range(PUSH_ROUNDS):
                contacts = self._path_contacts(x, old, new, obj, features)
                if not contacts:
                    break
                shift = np.zeros_like(x)
                for nodes, toi, step in contacts:
                    dent = (1.0 - toi) * step + target * step / np.linalg.norm(step)
                    # A node that two paths dent goes as far as the deeper one takes it.
                    deeper = np.linalg.norm(dent) > np.linalg.norm(shift[nodes], axis=1)
                    shift[nodes[deeper]] = dent
                touched = np.linalg.norm(shift, axis=1) > 0.0
                x[touched] += shift[touched]
                moved |= touched
            else:
                raise RuntimeError(f"{self.settings.where}: the {obj.describe()} at {new.translation.round(3).tolist()}: "
                                   f"the paths of its vertices and edges could not be cleared of the skin in "
                                   f"{PUSH_ROUNDS} rounds")
        return self.with_moved_nodes(out, held, x, moved)

    # -- derivatives in the objects' poses ------------------------------------------------------
    def pose_rate_forces(self, displacement: np.ndarray, rates) -> np.ndarray:
        """The nodes' and spheres' rates, and the object features': a vertex p of an object moving
        at (dM, dt) moves at v = W (p - t) + dt (W = dM M^T), so a term's force s w dphi/dx changes
        at s w d2phi/dx dy . v over the feature's vertices y."""
        out = super().pose_rate_forces(displacement, rates)
        scale = self.stiffness / self.dhat
        meshes = [(obj, pose, rate) for obj, pose, rate, features in zip(self.objects, self.poses, rates, self.features)
                  if features is not None]
        for (obj, pose, rate), (host, weight, _, _, _, mixed, ends) in zip(meshes, self.object_terms(displacement)):
            if rate is None or not len(host):
                continue
            dM, dt = np.asarray(rate[0], dtype=float).reshape(3, 3), np.asarray(rate[1], dtype=float).reshape(3)
            velocity = (pose.apply(obj.points) - pose.translation) @ (dM @ pose.matrix.T).T + dt
            # A vertex's term has no second vertex: its mixed block's last columns are zero.
            feature_velocity = np.concatenate([velocity[ends[:, 0]], velocity[np.maximum(ends[:, 1], 0)]], axis=1)
            change = np.einsum("kij,kj->ki", mixed, feature_velocity).reshape(-1, 3, 3)
            np.add.at(out, self.surface.triangles[host], (scale * weight)[:, None, None] * change)
        return out


def contact_potential(space, facets, settings) -> ContactPotential:
    """The contact term of ``settings``: with its ``faces`` option on, ``ObjectFeatureContact`` when
    one of its objects is a triangle mesh, ``FaceContactPotential`` when one is a sphere; else the
    nodal ``ContactPotential``."""
    if settings.faces and any(isinstance(obj, TriangleMesh) for obj in settings.objects):
        return ObjectFeatureContact(space, facets, settings)
    if settings.faces and any(isinstance(obj, Sphere) for obj in settings.objects):
        return FaceContactPotential(space, facets, settings)
    return ContactPotential(space, facets, settings)
