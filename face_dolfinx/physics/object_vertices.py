"""A triangle-mesh object's vertices kept off the skin's triangles: an instrument's tip between the
skin's nodes (IPC barrier on point-triangle, point-edge and point-point distances).

``ContactPotential`` keeps every skin *node* outside a triangle-mesh object; an object's vertex
sharper than the skin's triangles (an instrument's tip, a corner of a mask) can still pass through
a skin face between the nodes, which no node's gap sees. ``ObjectVertexContact`` adds the mirror
image of the nodal barrier: every vertex v of a triangle-mesh object, weighted by its rest area
A_v (its share of the object's surface), gets the barrier of its distance to the skin, as the sum
over the skin's features within dhat of it, the closed triangles and vertices with sign +1 and the
edges with sign -1 (``TriangleMesh.barrier_terms``' construction, docs/contact.md "A smooth
barrier"):

    E_v = stiffness / dhat * sum_v A_v [ sum_T b(d(v, T)) - sum_e b(d(v, e)) + sum_n b(|v - x_n|) ].

Where the skin within dhat of v is one disc, as on every smooth piece of it, the sum is
b(distance from v to the skin); each term is C1 in the skin's nodes (the distance to a closed
convex feature is C1 off it), so the sum is. A term's gradient and Hessian in the feature's nodes
(a triangle's three, an edge's two, a node) come from the IPC Toolkit's squared distances
(``ipctk.point_triangle_distance`` and its point-edge and point-point siblings) through the
square root; each is written into the 9 x 9 block of a skin triangle holding the feature, inside
the finite-element sparsity, and Newton's tangent projects each block onto the positive
semidefinite ones as for a sphere's triangles (``FaceContactPotential``). The skin's nodes keep
their own barrier against the object's surface, so a face of the object resting flat on the skin
is held by both (the nodes' and the object's vertices' pressures add).

Collision-free steps: the object's vertices stand still during a solve while the skin's triangles
move, each pair (v, T) whose triangle's corners move by more than CCD_KEEP of their distance is
tested by the IPC Toolkit's additive CCD with the minimum distance (1 - CCD_KEEP) d(v, T): no
vertex comes closer to any skin triangle than that, so none crosses the skin at any Newton
iterate.

Moving the object (``push_out``): after the nodes' push-out, each vertex's straight path from its
old pose to its new one is tested against the skin's triangles by the same CCD with the minimum
distance PUSH_GAP * dhat (or (1 - CCD_KEEP) of the pair's distance, if it already rests closer);
a triangle the tip reaches is moved with the rest of the tip's path (plus PUSH_GAP * dhat), the
dent the tip makes, round after round until no path reaches a triangle; the dented nodes are held
in the solve that spreads the dent into the flesh, as the pushed nodes are (``move_to``).

Not paired: the object's *edges* against the skin's edges. An edge sharper than the skin's
triangles (a blade's) whose vertices stay outside the skin can still cut through a skin face
between nodes (docs/contact.md, "Limits").

Under MPI every rank holds all nodes and triangles of the contact surface (gathered by
``ContactSurface``), computes the same terms and adds the rows of the nodes it owns.
"""
import ipctk
import numpy as np
from scipy.spatial import cKDTree

from face_dolfinx.alignment.surface import closest_points
from face_dolfinx.physics.contact import CCD_KEEP, PUSH_GAP, ContactPotential, Sphere, barrier, barrier_derivatives
from face_dolfinx.physics.face_contact import (NARROW_PHASE, PUSH_ROUNDS, FaceContactPotential,
                                               distance_derivatives)
from face_dolfinx.physics.rigid_mesh import TriangleMesh

# The corners of a triangle that each feature of it holds: the face, its edges (ab, bc, ca), its
# corners.
_TRIANGLE_EDGES = ((0, 1), (1, 2), (2, 0))


def vertex_areas(points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Each vertex's share of a triangle surface's area (a third of every triangle around it)."""
    corners = points[triangles]
    area = 0.5 * np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1)
    return np.bincount(triangles.reshape(-1), np.repeat(area / 3.0, 3), minlength=len(points))


def squared_to_distance(squared: float, gradient: np.ndarray, hessian: np.ndarray):
    """The distance d = sqrt(s) with its gradient and Hessian from those of s."""
    distance = np.sqrt(squared)
    return (distance, gradient / (2.0 * distance),
            hessian / (2.0 * distance) - np.outer(gradient, gradient) / (4.0 * distance ** 3))


def segment_distances(points: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distance of each point to the segment ab (all (m, 3))."""
    edge = b - a
    t = np.clip(np.einsum("ij,ij->i", points - a, edge) / np.einsum("ij,ij->i", edge, edge), 0.0, 1.0)
    return np.linalg.norm(points - a - t[:, None] * edge, axis=1)


class ObjectVertexContact(FaceContactPotential):
    """``FaceContactPotential`` whose triangle-mesh objects also keep their vertices off the contact
    surface's triangles (module docstring); spheres act on the triangles and every object on the
    nodes as there."""

    # Newton takes the projected blocks only until it is near the solution, as for the lips
    # (``LipContact``): the projection drops the curvature of the distance to a skin face that
    # turns with its corners, and Newton's convergence turned linear (the tip pressed 1.5 mm into
    # the test slab: a residual falling 0.83-fold per iteration until the 60 allowed ran out).
    exact_near_solution = True

    def __init__(self, space, facets, settings):
        super().__init__(space, facets, settings)
        self.by_vertices = tuple(isinstance(obj, TriangleMesh) for obj in self.objects)
        self.object_vertex_areas = tuple(vertex_areas(obj.points, obj.triangles) if isinstance(obj, TriangleMesh)
                                         else None for obj in self.objects)
        self._last_vertex_terms = None  # (positions, poses, ignored, terms) of the last ``vertex_terms``

    # -- the vertices' features ----------------------------------------------------------------
    def _candidates(self, x: np.ndarray, points: np.ndarray, reach) -> tuple[np.ndarray, np.ndarray]:
        """(vertex, triangle) pairs of the free triangles of the surface at ``x`` that may lie within
        ``reach`` of the object's ``points`` (a number, or one per triangle): the vertices within
        that plus the triangle's radius of its centroid."""
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

    def vertex_gaps(self, displacement: np.ndarray, within: float, poses=None) -> list:
        """Per triangle-mesh object (in their order among the objects): each vertex's distance to
        the nearest free triangle of the contact surface (mm), ``within`` where none lies closer than
        that."""
        x = self.positions(displacement)
        poses = self.poses if poses is None else poses
        out = []
        for obj, pose, by_vertices in zip(self.objects, poses, self.by_vertices):
            if not by_vertices:
                continue
            points = pose.apply(obj.points)
            vertex, triangle = self._candidates(x, points, within)
            corners = x[self.surface.triangles[triangle]]
            distance = np.linalg.norm(points[vertex] - closest_points(points[vertex], corners[:, 0], corners[:, 1],
                                                                      corners[:, 2])[0], axis=1)
            gap = np.full(len(points), float(within))
            np.minimum.at(gap, vertex, distance)
            out.append(gap)
        return out

    def vertex_terms(self, displacement: np.ndarray) -> list:
        """Per triangle-mesh object: its barrier's terms (module docstring), each a (vertex,
        feature) pair within dhat: the skin triangle holding the feature (m,), the weight (the
        vertex's area times the feature's sign), the distance, its gradient in the triangle's
        corners (m, 3, 3; zero rows for corners off the feature) and Hessian (m, 9, 9), the
        Hessian's block mixing the corners with the vertex (m, 9, 3), and the vertex (m,). The
        gradient, Hessian, Newton correction and pose rates of one state share them."""
        x = self.positions(displacement)
        last = self._last_vertex_terms
        if last is not None and last[1] is self.poses and last[2] is self.ignored and np.array_equal(last[0], x):
            return last[3]
        triangles = self.surface.triangles
        terms = []
        for obj, pose, areas in zip(self.objects, self.poses, self.object_vertex_areas):
            if areas is None:
                continue
            points = pose.apply(obj.points)
            vertex, triangle = self._candidates(x, points, self.dhat)
            corners = x[triangles[triangle]]
            distance = np.linalg.norm(points[vertex] - closest_points(points[vertex], corners[:, 0], corners[:, 1],
                                                                      corners[:, 2])[0], axis=1)
            near = distance < self.dhat
            vertex, triangle = vertex[near], triangle[near]
            # Each (vertex, skin feature) once: every feature of the near triangles (a mask of the
            # triangle's corners on it: 7 the face, 3 / 6 / 5 an edge, 1 / 2 / 4 a corner), an edge or
            # corner that two near triangles share kept with the first of them.
            masks = np.array([7, 3, 6, 5, 1, 2, 4])
            vertex, host, mask = (np.repeat(vertex, len(masks)), np.repeat(triangle, len(masks)),
                                  np.tile(masks, len(vertex)))
            on = ((mask[:, None] >> np.arange(3)) & 1).astype(bool)
            feature = np.sort(np.where(on, triangles[host], -1), axis=1)
            _, first = np.unique(np.column_stack([vertex, feature]), axis=0, return_index=True)
            vertex, host, mask, on = vertex[first], host[first], mask[first], on[first]
            sign = np.where(on.sum(axis=1) == 2, -1.0, 1.0)
            terms.append(self._feature_derivatives(x, points, vertex, host, mask, sign * areas[vertex]))
        self._last_vertex_terms = (x, self.poses, self.ignored, terms)
        return terms

    def _feature_derivatives(self, x, points, vertex, host, mask, weight) -> tuple:
        """The terms of ``vertex_terms`` for the (vertex, feature) pairs given by the host triangle
        and the mask of its corners on the feature (7: the face), those within dhat kept."""
        count = len(vertex)
        distance = np.full(count, np.inf)
        gradients = np.zeros((count, 3, 3))
        hessians = np.zeros((count, 9, 9))
        mixed = np.zeros((count, 9, 3))
        corners = x[self.surface.triangles[host]]
        for k in range(count):
            slots = [s for s in range(3) if mask[k] >> s & 1]
            p, c = points[vertex[k]], corners[k]
            if len(slots) == 3:
                distance[k] = np.sqrt(ipctk.point_triangle_distance(p, *c))
                if distance[k] >= self.dhat:
                    continue
                gradient, hessian = distance_derivatives(p, c)
            elif len(slots) == 2:
                a, b = c[slots]
                distance[k], gradient, hessian = squared_to_distance(
                    ipctk.point_edge_distance(p, a, b), ipctk.point_edge_distance_gradient(p, a, b),
                    ipctk.point_edge_distance_hessian(p, a, b))
            else:
                q = c[slots[0]]
                distance[k], gradient, hessian = squared_to_distance(
                    ipctk.point_point_distance(p, q), ipctk.point_point_distance_gradient(p, q),
                    ipctk.point_point_distance_hessian(p, q))
            if distance[k] >= self.dhat:
                continue
            dofs = np.concatenate([3 * s + np.arange(3) for s in slots])
            gradients[k].reshape(-1)[dofs] = gradient[3:]
            hessians[k][np.ix_(dofs, dofs)] = hessian[3:, 3:]
            mixed[k][dofs] = hessian[3:, :3]
        keep = distance < self.dhat
        return host[keep], weight[keep], distance[keep], gradients[keep], hessians[keep], mixed[keep], vertex[keep]

    # -- the solver's energy-term interface ---------------------------------------------------
    def energy(self, x) -> float:
        scale = self.stiffness / self.dhat
        vertices = sum(scale * (weight * barrier(gap, self.dhat)).sum()
                       for _, weight, gap, _, _, _, _ in self.vertex_terms(x.array_r))
        return super().energy(x) + float(vertices)

    def nodal_forces(self, displacement: np.ndarray) -> np.ndarray:
        gradient = super().nodal_forces(displacement)
        scale = self.stiffness / self.dhat
        for host, weight, gap, gradients, _, _, _ in self.vertex_terms(displacement):
            first, _ = barrier_derivatives(gap, self.dhat)
            np.add.at(gradient, self.surface.triangles[host], (scale * weight * first)[:, None, None] * gradients)
        return gradient

    def triangle_blocks(self, displacement: np.ndarray) -> list:
        """The spheres' triangle blocks and the objects' vertices' (in the triangles that hold their
        features)."""
        blocks = super().triangle_blocks(displacement)
        scale = self.stiffness / self.dhat
        for host, weight, gap, gradients, hessians, _, _ in self.vertex_terms(displacement):
            first, second = barrier_derivatives(gap, self.dhat)
            flat = gradients.reshape(-1, 9)
            local = second[:, None, None] * flat[:, :, None] * flat[:, None, :] + first[:, None, None] * hessians
            blocks.append((host, scale * weight[:, None, None] * local))
        return blocks

    def contact_vertices(self, displacement: np.ndarray) -> int:
        """Number of (object, vertex) pairs within dhat of the contact surface."""
        return int(sum((gap < self.dhat).sum() for gap in self.vertex_gaps(displacement, within=self.dhat)))

    # -- collision-free steps ------------------------------------------------------------------
    def admissible_fraction(self, start: np.ndarray, end: np.ndarray) -> float:
        """The spheres' and nodes' bound, and no point of the straight path from the displacement
        ``start`` to ``end`` brings a skin triangle closer to an object's vertex than (1 - CCD_KEEP)
        of their distance now."""
        fraction = super().admissible_fraction(start, end)
        x0, x1 = self.positions(start), self.positions(end)
        triangles = self.surface.triangles
        move = np.linalg.norm(x1 - x0, axis=1)[triangles].max(axis=1)
        for obj, pose, by_vertices in zip(self.objects, self.poses, self.by_vertices):
            if not by_vertices or not move.max(initial=0.0) > 0.0:
                continue
            points = pose.apply(obj.points)
            vertex, triangle = self._candidates(x0, points, move.max() / CCD_KEEP)
            corners = x0[triangles[triangle]]
            distance = np.linalg.norm(points[vertex] - closest_points(points[vertex], corners[:, 0], corners[:, 1],
                                                                      corners[:, 2])[0], axis=1)
            # A pair whose triangle moves by less than CCD_KEEP of its distance keeps the rest.
            tested = move[triangle] > CCD_KEEP * distance
            for v, t, d in zip(vertex[tested], triangle[tested], distance[tested]):
                p = points[v]
                hit, toi = NARROW_PHASE.point_triangle_ccd(p, *x0[triangles[t]], p, *x1[triangles[t]],
                                                           min_distance=(1.0 - CCD_KEEP) * d, tmax=fraction)
                if hit:
                    fraction = min(fraction, toi)
        return fraction

    # -- moving the objects ------------------------------------------------------------------
    def _path_contacts(self, x: np.ndarray, old, new, obj) -> list:
        """The (vertex, triangle, time) of each object vertex whose straight path from its place at
        the pose ``old`` to that at ``new`` comes within PUSH_GAP * dhat (or (1 - CCD_KEEP) of their
        distance at the start, if closer) of a free triangle of the surface at ``x``, the first such
        triangle of each vertex."""
        start, end = old.apply(obj.points), new.apply(obj.points)
        path = np.linalg.norm(end - start, axis=1)
        moving = np.flatnonzero(path > 0.0)
        if not moving.size:
            return []
        target = PUSH_GAP * self.dhat
        # Every point of the path lies within half its length of its middle.
        middle = 0.5 * (start + end)
        vertex, triangle = self._candidates(x, middle[moving], 0.5 * path[moving].max() + target)
        vertex = moving[vertex]
        corners = x[self.surface.triangles[triangle]]
        distance = np.linalg.norm(start[vertex] - closest_points(start[vertex], corners[:, 0], corners[:, 1],
                                                                 corners[:, 2])[0], axis=1)
        first = {}
        for v, t, d, c in zip(vertex, triangle, distance, corners):
            hit, toi = NARROW_PHASE.point_triangle_ccd(start[v], *c, end[v], *c,
                                                       min_distance=min(target, (1.0 - CCD_KEEP) * d),
                                                       tmax=first.get(v, (None, 1.0))[1])
            if hit:
                first[v] = (t, toi)
        return [(v, t, toi) for v, (t, toi) in first.items()]

    def closes_in(self, displacement: np.ndarray, old_poses, new_poses) -> bool:
        """The nodes' and spheres' test, and whether an object vertex's path to its new pose reaches
        a skin triangle (``_path_contacts``)."""
        if super().closes_in(displacement, old_poses, new_poses):
            return True
        x = self.positions(displacement)
        return any(by_vertices and self._path_contacts(x, old, new, obj)
                   for obj, old, new, by_vertices in zip(self.objects, old_poses, new_poses, self.by_vertices))

    def push_out(self, displacement: np.ndarray, poses) -> tuple[np.ndarray, np.ndarray]:
        """The nodes' and spheres' push-out, then the dent of each object vertex's path (module
        docstring): a triangle it reaches at the time t of its path is moved by (1 - t) of the
        vertex's move plus PUSH_GAP * dhat along it, round after round (PUSH_ROUNDS) until no path
        reaches a triangle; the moved nodes join the held ones."""
        out, held = super().push_out(displacement, poses)
        x = self.positions(out)
        moved = np.zeros(len(x), dtype=bool)
        target = PUSH_GAP * self.dhat
        for obj, old, new, by_vertices in zip(self.objects, self.poses, poses, self.by_vertices):
            if not by_vertices:
                continue
            step = new.apply(obj.points) - old.apply(obj.points)
            for _ in range(PUSH_ROUNDS):
                contacts = self._path_contacts(x, old, new, obj)
                if not contacts:
                    break
                shift = np.zeros_like(x)
                for v, t, toi in contacts:
                    length = np.linalg.norm(step[v])
                    dent = (1.0 - toi) * step[v] + target * step[v] / length
                    nodes = self.surface.triangles[t]
                    # A node that two paths dent goes as far as the deeper one takes it.
                    deeper = np.linalg.norm(dent) > np.linalg.norm(shift[nodes], axis=1)
                    shift[nodes[deeper]] = dent
                touched = np.linalg.norm(shift, axis=1) > 0.0
                x[touched] += shift[touched]
                moved |= touched
            else:
                raise RuntimeError(f"{self.settings.where}: the {obj.describe()} at {new.translation.round(3).tolist()}: "
                                   f"its vertices' paths could not be cleared of the skin's triangles in {PUSH_ROUNDS} "
                                   "rounds")
        if not moved.any():
            return out, held
        values = out.reshape(-1, 3)
        values[self.surface.owned_blocks] = (x - self.surface.rest)[self.surface.owned_nodes]
        return out, np.union1d(held, np.flatnonzero(moved))

    # -- derivatives in the objects' poses ------------------------------------------------------
    def pose_rate_forces(self, displacement: np.ndarray, rates) -> np.ndarray:
        """The nodes' and spheres' rates, and the vertices': a vertex p of an object moving at
        (dM, dt) moves at v = W (p - t) + dt (W = dM M^T), so a term's force s w b'(d) dd/dx changes
        at s w [b'' (dd/dp . v) dd/dx + b' d2d/dx dp v], dd/dp = -(sum of dd/dx_i) (the distance
        depends on the corners relative to the vertex)."""
        out = super().pose_rate_forces(displacement, rates)
        scale = self.stiffness / self.dhat
        mesh_rates = [(pose, rate) for pose, rate, by_vertices in zip(self.poses, rates, self.by_vertices) if by_vertices]
        for (pose, rate), (host, weight, gap, gradients, _, mixed, vertex), obj in zip(
                mesh_rates, self.vertex_terms(displacement), [o for o, b in zip(self.objects, self.by_vertices) if b]):
            if rate is None:
                continue
            dM, dt = np.asarray(rate[0], dtype=float).reshape(3, 3), np.asarray(rate[1], dtype=float).reshape(3)
            W = dM @ pose.matrix.T
            velocity = (pose.apply(obj.points)[vertex] - pose.translation) @ W.T + dt
            first, second = barrier_derivatives(gap, self.dhat)
            distance_rate = -np.einsum("kij,kj->k", gradients, velocity)
            change = ((second * distance_rate)[:, None, None] * gradients
                      + first[:, None, None] * np.einsum("kij,kj->ki", mixed, velocity).reshape(-1, 3, 3))
            np.add.at(out, self.surface.triangles[host], (scale * weight)[:, None, None] * change)
        return out


def contact_potential(space, facets, settings) -> ContactPotential:
    """The contact term of ``settings``: with its ``faces`` option on, ``ObjectVertexContact`` when
    one of its objects is a triangle mesh, ``FaceContactPotential`` when one is a sphere; else the
    nodal ``ContactPotential``."""
    if settings.faces and any(isinstance(obj, TriangleMesh) for obj in settings.objects):
        return ObjectVertexContact(space, facets, settings)
    if settings.faces and any(isinstance(obj, Sphere) for obj in settings.objects):
        return FaceContactPotential(space, facets, settings)
    return ContactPotential(space, facets, settings)
