"""Skin triangles, not only skin nodes, kept out of rigid spheres (IPC barrier on point-triangle
distances).

``ContactPotential`` keeps every *node* of the contact surface outside the objects; between the
nodes a flat triangle of edge l hangs into a sphere of radius R by up to about l^2 / (8 R) (0.4 mm
on the 20K face against R = 15 mm, docs/contact.md). ``FaceContactPotential`` gives every flat
triangle T of the contact surface (four per P2 facet) the gap to a sphere

    g_T = dist(c, T) - R,

c the sphere's centre: the distance from the centre to the nearest point of T, so g_T > 0 exactly
when no point of T is inside the sphere. The barrier is that of ``ContactPotential`` summed over
the triangles, each weighted by its rest area A_T (the nodal barrier lumps the same areas to the
nodes):

    E_c = stiffness / dhat * sum_T A_T b(g_T).

The nearest point q = sum_i w_i x_i (barycentric w; in the face, on an edge or at a vertex) gives
dg_T/dx_i = w_i n, n = (q - c) / |q - c|: the force of a triangle goes to its three nodes by the
barycentric weights of its nearest point. The distance is C1 in the vertices; its Hessian (per
region) is that of the IPC Toolkit's squared point-triangle distance
(``ipctk.point_triangle_distance_hessian``) taken through the square root. A triangle couples its
three nodes, which share a cell: the 9 x 9 blocks lie inside the finite-element sparsity. Newton's
tangent gets each triangle's block projected onto the positive semidefinite ones
(``add_newton_correction``, IPC's practice); the Hessian proper (``add_hessian``) stays exact for
the sensitivities.

Collision-free steps: a triangle with gap g_T and vertex moves m_i cannot come closer than
g_T - max_i |m_i| (the distance is 1-Lipschitz in the vertices), so only triangles with
max |m_i| > CCD_KEEP g_T are tested, each by the IPC Toolkit's additive CCD of the fixed centre
against the moving triangle with the minimum distance R + (1 - CCD_KEEP) g_T.

Only spheres need this. A half-space is convex: a triangle whose vertices are outside it is
outside, and the nodal barrier is already exact for it. A triangle-mesh object keeps the nodal
barrier, and its vertices and edges keep off the skin by ``object_features.ObjectFeatureContact``.
Under MPI every rank holds all nodes and triangles of the contact surface (gathered, in
rest-coordinate order by ``ContactSurface``), computes the same triangle terms and adds the rows
of the nodes it owns (columns anywhere): the same result on any number of ranks.
"""
import ipctk
from petsc4py import PETSc
import numpy as np

from face_dolfinx.alignment.surface import closest_points
from face_dolfinx.physics.contact import (CCD_KEEP, PUSH_GAP, ROUND_OFF, ContactPotential, Sphere, closing_in,
                                          barrier, barrier_derivatives)

# The narrow phase of the triangles' step bound (the centre fixed, the triangle moving); its own
# conservative rescaling (0.9 of the time of impact) comes on top of the CCD_KEEP clearance.
NARROW_PHASE = ipctk.AdditiveCCD()

# Newton iterations a solve with the triangle barrier may take before continuation takes over: a
# sphere pressed 1 mm further into the 5K face's smiling cheek settles in 21-41 (collision-limited
# steps while the triangles close from dhat to their contact gap, then Newton's convergence); with
# PETSc's 25 a failed Newton solve and continuation made 86-152 of them.
FACE_NEWTON_ITERATIONS = 60

# Rounds of ``push_out``'s radial push of the triangles that a sphere's new pose would overlap.
PUSH_ROUNDS = 50


def triangle_distances(centre: np.ndarray, corners: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Distance of ``centre`` to each triangle (corners (m, 3, 3)), the nearest points' barycentric
    coordinates (m, 3) and the unit vectors from the centre to them (m, 3)."""
    count = len(corners)
    nearest, weights, _ = closest_points(np.broadcast_to(centre, (count, 3)), corners[:, 0], corners[:, 1],
                                         corners[:, 2])
    offset = nearest - centre
    distance = np.linalg.norm(offset, axis=1)
    return distance, weights, offset / np.maximum(distance, 1e-300)[:, None]


def distance_from_squared(squared: float, gradient: np.ndarray, hessian: np.ndarray):
    """The distance d = sqrt(s) with its gradient and Hessian from those of the squared distance s:
    grad d = grad s / (2 d), hess d = hess s / (2 d) - grad s grad s^T / (4 d^3)."""
    distance = np.sqrt(squared)
    return (distance, gradient / (2.0 * distance),
            hessian / (2.0 * distance) - np.outer(gradient, gradient) / (4.0 * distance ** 3))


def distance_derivatives(centre: np.ndarray, corners: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Gradient (12,) and Hessian (12, 12) of the distance from a point to a triangle, in the
    point's coordinates and then the three corners' (the IPC Toolkit's squared distance,
    ``distance_from_squared``)."""
    a, b, c = corners
    return distance_from_squared(ipctk.point_triangle_distance(centre, a, b, c),
                                 ipctk.point_triangle_distance_gradient(centre, a, b, c),
                                 ipctk.point_triangle_distance_hessian(centre, a, b, c))[1:]


class FaceContactPotential(ContactPotential):
    """``ContactPotential`` whose spheres act on the contact surface's triangles (module docstring);
    its other objects keep the nodal barrier."""

    def __init__(self, space, facets, settings):
        super().__init__(space, facets, settings)
        self.by_faces = tuple(isinstance(obj, Sphere) for obj in self.objects)
        self.node_barrier = tuple(not faces for faces in self.by_faces)
        surface = self.surface
        rest = surface.rest[surface.triangles]
        self.triangle_areas = 0.5 * np.linalg.norm(np.cross(rest[:, 1] - rest[:, 0], rest[:, 2] - rest[:, 0]), axis=1)
        owned_global = space.dofmap.index_map.local_to_global(surface.owned_blocks)
        self.global_blocks = np.empty(surface.num_nodes, dtype=np.int64)
        self.global_blocks[np.concatenate(surface.comm.allgather(surface.owned_nodes))] = \
            np.concatenate(surface.comm.allgather(owned_global))
        self.owned = np.zeros(surface.num_nodes, dtype=bool)
        self.owned[surface.owned_nodes] = True
        self.last_face_terms = None  # (positions, poses, ignored, terms) of the last ``face_terms``

    # -- the triangles' gaps and derivatives ----------------------------------------------------
    def free_triangles(self) -> np.ndarray:
        """Triangles with no ignored node (a node held by a bone leaves its triangles out, as the
        nodal barrier leaves the node out)."""
        return ~self.ignored[self.surface.triangles].any(axis=1)

    def triangle_gaps(self, displacement: np.ndarray, poses=None) -> np.ndarray:
        """(spheres, triangles) gap of every triangle to every sphere (mm, negative: a point of the
        triangle inside), in the order of the spheres among the objects; inf for triangles left out."""
        x = self.positions(displacement)
        poses = self.poses if poses is None else poses
        free = self.free_triangles()
        gaps = []
        for obj, pose, faces in zip(self.objects, poses, self.by_faces):
            if faces:
                gap = triangle_distances(pose.translation, x[self.surface.triangles])[0] - obj.radius
                gaps.append(np.where(free, gap, np.inf))
        return np.array(gaps).reshape(-1, len(self.surface.triangles))

    def contact_triangles(self, displacement: np.ndarray) -> int:
        """Number of (sphere, triangle) pairs within dhat."""
        return int((self.triangle_gaps(displacement) < self.dhat).sum())

    def face_terms(self, displacement: np.ndarray) -> list:
        """Per sphere: the triangles within dhat, their gaps, the gaps' gradients (m, 3, 3) and
        Hessians (m, 9, 9) in the triangles' corners, and the Hessians' blocks mixing the corners
        with the centre (m, 9, 3). The gradient, Hessian, Newton correction and pose rates of one
        state share them."""
        x = self.positions(displacement)
        last = self.last_face_terms
        if last is not None and last[1] is self.poses and last[2] is self.ignored and np.array_equal(last[0], x):
            return last[3]
        terms = []
        free = self.free_triangles()
        for obj, pose, faces in zip(self.objects, self.poses, self.by_faces):
            if not faces:
                continue
            centre = pose.translation
            corners = x[self.surface.triangles]
            distance = triangle_distances(centre, corners)[0]
            active = np.flatnonzero((distance - obj.radius < self.dhat) & free)
            gradients = np.zeros((len(active), 3, 3))
            hessians = np.zeros((len(active), 9, 9))
            mixed = np.zeros((len(active), 9, 3))
            for k, triangle in enumerate(active):
                gradient, hessian = distance_derivatives(centre, corners[triangle])
                gradients[k] = gradient[3:].reshape(3, 3)
                hessians[k] = hessian[3:, 3:]
                mixed[k] = hessian[3:, :3]
            terms.append((active, distance[active] - obj.radius, gradients, hessians, mixed))
        self.last_face_terms = (x, self.poses, self.ignored, terms)
        return terms

    def triangle_blocks(self, displacement: np.ndarray) -> list:
        """Per sphere: the active triangles and d2E_c/dx2 of each (m, 9, 9), in its corners."""
        scale = self.stiffness / self.dhat
        blocks = []
        for active, gap, gradients, hessians, _ in self.face_terms(displacement):
            first, second = barrier_derivatives(gap, self.dhat)
            flat = gradients.reshape(-1, 9)
            local = second[:, None, None] * flat[:, :, None] * flat[:, None, :] + first[:, None, None] * hessians
            blocks.append((active, scale * self.triangle_areas[active][:, None, None] * local))
        return blocks

    # -- the solver's energy-term interface ---------------------------------------------------
    def energy(self, x: PETSc.Vec) -> float:
        scale = self.stiffness / self.dhat
        faces = sum(scale * (self.triangle_areas[active] * barrier(gap, self.dhat)).sum()
                    for active, gap, _, _, _ in self.face_terms(x.array_r))
        return super().energy(x) + float(faces)

    def nodal_forces(self, displacement: np.ndarray) -> np.ndarray:
        gradient = super().nodal_forces(displacement)
        scale = self.stiffness / self.dhat
        for active, gap, gradients, _, _ in self.face_terms(displacement):
            first, _ = barrier_derivatives(gap, self.dhat)
            np.add.at(gradient, self.surface.triangles[active],
                      (scale * self.triangle_areas[active] * first)[:, None, None] * gradients)
        return gradient

    def face_pressure(self, displacement: np.ndarray) -> np.ndarray:
        """(nodes,) contact pressure (kPa): each triangle's barrier pressure -stiffness b'(g_T) / dhat
        (its force over its rest area), averaged over the triangles around a node weighted by their
        areas. A pressure field for plots; ``nodal_forces`` over the nodes' areas is the other."""
        pressure = np.zeros(self.surface.num_nodes)
        for active, gap, _, _, _ in self.face_terms(displacement):
            first, _ = barrier_derivatives(gap, self.dhat)
            share = -self.stiffness / self.dhat * first * self.triangle_areas[active] / 3.0
            np.add.at(pressure, self.surface.triangles[active], share[:, None])
        return pressure / self.surface.areas

    def add_hessian(self, x: PETSc.Vec, A: PETSc.Mat, constrained: np.ndarray) -> None:
        super().add_hessian(x, A, constrained)
        self.add_triangle_blocks(self.triangle_blocks(x.array_r), x, A, constrained)

    def add_newton_correction(self, x: PETSc.Vec, A: PETSc.Mat, constrained: np.ndarray) -> bool:
        """The nodal correction and every triangle's block projected onto the positive
        semidefinite ones (its negative eigenvalues set to 0). The same answer on every rank."""
        changed = super().add_newton_correction(x, A, constrained)
        corrections = []
        for active, blocks in self.triangle_blocks(x.array_r):
            values, vectors = np.linalg.eigh(np.where(np.isfinite(blocks), blocks, 0.0))  # as the nodes'
            negative = values.min(axis=1, initial=0.0) < -ROUND_OFF * np.abs(values).max(axis=1, initial=0.0)
            change = np.einsum("nij,nj,nkj->nik", vectors[negative], np.maximum(-values[negative], 0.0), vectors[negative])
            corrections.append((active[negative], change))
        if not any(len(active) for active, _ in corrections):
            return changed
        self.add_triangle_blocks(corrections, x, A, constrained)
        return True

    def add_triangle_blocks(self, blocks: list, x: PETSc.Vec, A: PETSc.Mat, constrained: np.ndarray) -> None:
        """A += per sphere the (m, 9, 9) blocks of the triangles ``active``, the rows of this rank's
        nodes, the rows and columns of ``constrained`` (owned local dofs, on any rank) left alone;
        A assembled."""
        free = self.surface.free(constrained, x.getLocalSize())
        for active, values in blocks:
            for triangle, block in zip(self.surface.triangles[active], values):
                dofs = (3 * self.global_blocks[triangle][:, None] + np.arange(3)).reshape(-1)
                keep = free[triangle].reshape(-1)
                columns = dofs[keep].astype(PETSc.IntType)
                for corner in np.flatnonzero(self.owned[triangle]):
                    rows = slice(3 * corner, 3 * corner + 3)
                    kept_rows = keep[rows]
                    if kept_rows.any():
                        # C order: petsc4py reads the buffer row by row (a boolean column index
                        # leaves numpy's result in Fortran order).
                        values = np.ascontiguousarray(block[rows][np.ix_(kept_rows, keep)])
                        A.setValues(dofs[rows][kept_rows].astype(PETSc.IntType), columns, values,
                                    addv=PETSc.InsertMode.ADD_VALUES)
        A.assemble()

    def admissible_fraction(self, start: np.ndarray, end: np.ndarray) -> float:
        """The nodal bound, and no point of the straight path from the displacement ``start`` to
        ``end`` brings a triangle closer to a sphere than (1 - CCD_KEEP) of its gap now."""
        fraction = super().admissible_fraction(start, end)
        points = self.positions(start)
        moves = self.positions(end) - points
        triangles = self.surface.triangles
        reach = np.linalg.norm(moves, axis=1)[triangles].max(axis=1) / CCD_KEEP
        for gaps, (obj, pose) in zip(self.triangle_gaps(start),
                                     [(o, p) for o, p, f in zip(self.objects, self.poses, self.by_faces) if f]):
            centre = pose.translation
            for triangle, gap in zip(triangles[gaps < reach], gaps[gaps < reach]):
                start, end = points[triangle], points[triangle] + moves[triangle]
                hit, toi = NARROW_PHASE.point_triangle_ccd(centre, *start, centre, *end,
                                                           min_distance=obj.radius + (1.0 - CCD_KEEP) * gap,
                                                           tmax=fraction)
                if hit:
                    fraction = min(fraction, toi)
        return fraction

    def check_clear(self, displacement: np.ndarray, margin: float = 0.0) -> None:
        super().check_clear(displacement, margin)
        spheres = [(obj, pose) for obj, pose, faces in zip(self.objects, self.poses, self.by_faces) if faces]
        for (obj, pose), gap in zip(spheres, self.triangle_gaps(displacement)):
            if gap.min(initial=np.inf) <= 0.0:
                raise ValueError(f"{self.settings.where}: the {obj.describe()} at {pose.translation.round(3).tolist()} "
                                 f"cuts {int((gap <= 0.0).sum())} triangles of the {self.settings.surface} "
                                 f"(deepest {-gap.min():.3g} mm inside) though no node is inside: place it outside")
            if gap.min(initial=np.inf) <= margin:
                raise ValueError(f"{self.settings.where}: the {obj.describe()} comes within {gap.min():.3g} mm of "
                                 f"{int((gap <= margin).sum())} triangles of the {self.settings.surface} at rest; it "
                                 f"must leave more than {margin:g} mm")

    # -- moving the objects ------------------------------------------------------------------
    def closes_in(self, displacement: np.ndarray, old_poses, new_poses) -> bool:
        """The nodes' test, and the same for the skin triangles against the spheres."""
        if super().closes_in(displacement, old_poses, new_poses):
            return True
        return closing_in(self.triangle_gaps(displacement, old_poses), self.triangle_gaps(displacement, new_poses),
                          self.dhat)

    def push_out(self, displacement: np.ndarray, poses) -> tuple[np.ndarray, np.ndarray]:
        """The nodal push-out, then the corners of every triangle that a sphere at its new pose
        would leave closer than PUSH_GAP * dhat moved radially out by the triangle's shortfall to
        twice that, round after round (PUSH_ROUNDS) until no triangle is that close; the moved
        nodes join the held ones."""
        out, held = super().push_out(displacement, poses)
        x = self.positions(out)
        moved = np.zeros(len(x), dtype=bool)
        target = PUSH_GAP * self.dhat
        triangles = self.surface.triangles
        free = self.free_triangles()
        for obj, pose, faces in zip(self.objects, poses, self.by_faces):
            if not faces:
                continue
            centre = pose.translation
            for _ in range(PUSH_ROUNDS):
                gap = triangle_distances(centre, x[triangles])[0] - obj.radius
                close = free & (gap < target)
                if not close.any():
                    break
                shortfall = np.zeros(len(x))
                # Aimed at twice the target: a triangle's gap approaches the aim only geometrically.
                np.maximum.at(shortfall, triangles[close], (2.0 * target - gap[close])[:, None])
                nodes = np.flatnonzero(shortfall > 0.0)
                radial = x[nodes] - centre
                x[nodes] += (shortfall[nodes] / np.linalg.norm(radial, axis=1))[:, None] * radial
                moved[nodes] = True
            else:
                raise RuntimeError(f"{self.settings.where}: the {obj.describe()} at "
                                   f"{pose.translation.round(3).tolist()}: the skin's triangles could not be pushed "
                                   f"clear of it in {PUSH_ROUNDS} rounds")
        return self.with_moved_nodes(out, held, x, moved)

    def with_moved_nodes(self, out: np.ndarray, held: np.ndarray, x: np.ndarray,
                         moved: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """A push-out's displacement ``out`` with the ``moved`` nodes at their positions in ``x``
        (this rank's owned part written) and the held nodes with them."""
        if not moved.any():
            return out, held
        values = out.reshape(-1, 3)
        values[self.surface.owned_blocks] = (x - self.surface.rest)[self.surface.owned_nodes]
        return out, np.union1d(held, np.flatnonzero(moved))

    # -- derivatives in the objects' poses ------------------------------------------------------
    def pose_rate_forces(self, displacement: np.ndarray, rates) -> np.ndarray:
        """The nodal rates and the triangles': a sphere moves only with its centre's velocity dt
        (a rotation about the centre changes no gap), so a triangle's force s A_T b'(g_T) dg_T/dx
        changes at s A_T [b'' (dg_T/dc . dt) dg_T/dx + b' d2g_T/dx dc dt]."""
        out = super().pose_rate_forces(displacement, rates)
        scale = self.stiffness / self.dhat
        sphere_rates = [rate for rate, faces in zip(rates, self.by_faces) if faces]
        for rate, (active, gap, gradients, _, mixed) in zip(sphere_rates, self.face_terms(displacement)):
            if rate is None:
                continue
            dt = np.asarray(rate[1], dtype=float).reshape(3)
            first, second = barrier_derivatives(gap, self.dhat)
            # dg/dc = -(sum_i dg/dx_i): the distance depends on the corners relative to the centre.
            gap_rate = -np.einsum("kij,j->k", gradients, dt)
            change = (second * gap_rate)[:, None, None] * gradients + first[:, None, None] * (mixed @ dt).reshape(-1, 3, 3)
            np.add.at(out, self.surface.triangles[active], (scale * self.triangle_areas[active])[:, None, None] * change)
        return out


def smoothed_pressure(points: np.ndarray, forces: np.ndarray, areas: np.ndarray, radius: float) -> np.ndarray:
    """(nodes,) contact pressure (kPa) resolved at the length ``radius`` (mm): the nodal contact
    forces' magnitudes (mN) and the nodes' areas (mm^2) summed with the hat weights
    max(0, 1 - |x_i - x_j| / radius) around each node, force over area. Nodes without force
    nearby get 0. A barrier's nodal pressure |f_i| / A_i scatters from node to node where the
    contact patch spans a few skin edges (each node's share depends on where it sits against the
    object); with ``radius`` about one skin edge this shows the pressure that the mesh resolves."""
    from scipy.spatial import cKDTree
    magnitude = np.linalg.norm(forces, axis=1)
    loaded = np.flatnonzero(magnitude > 0.0)
    pressure = np.zeros(len(points))
    if not loaded.size:
        return pressure
    tree = cKDTree(points)
    near = np.unique(np.concatenate(tree.query_ball_point(points[loaded], radius)))
    for node, neighbours in zip(near, tree.query_ball_point(points[near], radius)):
        weights = np.maximum(1.0 - np.linalg.norm(points[neighbours] - points[node], axis=1) / radius, 0.0)
        pressure[node] = weights @ magnitude[neighbours] / (weights @ areas[neighbours])
    return pressure
