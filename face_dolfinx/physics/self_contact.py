"""Frictionless self-contact of the lips: upper lip against lower lip (IPC barrier, IPC Toolkit).

The lip surfaces are the skin facets that line the mouth slit: those near the segment between the
mouth corners whose outward normal faces the other lip (``lip_facets``; a model designates them by
its ``skin`` tag and the landmarks ``mouth_corner_left``, ``mouth_corner_right``,
``upper_lip_center`` and ``lower_lip_center``, docs/model_format.md). Their nodes and flat
triangles (``contact.ContactSurface``, gathered on every rank in rest-coordinate order) form one
``ipctk.CollisionMesh``. Every point-triangle and edge-edge pair of it closer than ``dhat`` (and not
sharing a vertex) carries the IPC barrier (Li et al. 2020), zero beyond dhat and unbounded as the
distance goes to 0, weighted by the IPC Toolkit's rest areas of its primitives
(``ipctk.BarrierPotential(dhat, stiffness, use_physical_barrier=True)`` with area weighting), so
that it acts as a contact pressure that converges with the mesh; ``stiffness`` scales it (the
pressures it gives are measured by ``nodal_pressure``; docs/contact.md). Its gradient goes into the residual and its
exact Hessian into the tangent, which stays the symmetric Hessian of one total energy: MUMPS
Cholesky and the sensitivities dX/dc (one solve per control with the same factor) see the contact
with no change. Newton's own tangent, while it is far from the solution, has each pair's Hessian
projected onto the positive semidefinite ones (``add_newton_correction``, IPC's practice): the
exact one turns indefinite along the pressed lips' sliding. That tangent also carries a barrier of
wider reach (``newton_reach``, 10 dhat by default) on the pairs across the lips, not on those beyond
dhat that have parted since its last model (``reach_on_parting_pairs``): a model that sees
only the pairs within dhat lets a correction bring together pairs it does not see, and the step
bound then cuts it short; with the wider barrier Newton sees them coming (from rest, 13-14
factorisations on the 404K face where it took 17-18, half the Newton iterations on the 20K face;
docs/performance.md). The energy, the residual and the solution are the narrow barrier's alone.

A pair couples nodes of the two lips that share no element, outside the finite-element sparsity.
``coupled_blocks`` lists the pairs of an upper and a lower lip node within ``pattern_radius`` of
each other at rest; the solver adds them to the tangent's pattern once at set-up
(``equilibrium.solver``, ``widened_tangent``). The default radius holds every pair a barrier pair
can couple while the lips slide up to ``PATTERN_SLIDE`` on each other: its primitives then lie at
most that far apart at rest, and each of its nodes at most one lip edge from its primitive's
nearest point. Room costs every factorisation fill: on the 404K face every pair of lip nodes
within 15 mm of each other makes 32 % more flops than the tangent without lip contact, the default
room 12 % (docs/contact.md, "The tangent's pattern"). A pair found beyond it (lips sliding
further) is still added: the matrix accepts the new entry and MUMPS analyses the changed pattern
again at the next factorisation.

Continuous collision detection (``ipctk.compute_collision_free_stepsize``) bounds every Newton
step so that no point of the line-search segment lets two lip primitives come closer than
(1 - CCD_KEEP) of their smallest distance now: no iterate ever penetrates.

Under MPI every rank gathers all lip nodes (a few hundred) and computes the same pairs; each adds
the gradient and Hessian rows of the nodes it owns (columns anywhere). The energy and the step
bound are reduced (min) over the ranks so that every rank takes the same step.

The collision set (broad and narrow phase) is built once per state: the energy, gradient, Hessian
and step bound at the same lip positions (an exact compare with the last ones) share it.
"""
from dataclasses import dataclass

import ipctk
from mpi4py import MPI
from petsc4py import PETSc
import numpy as np
import scipy.sparse
import scipy.spatial
from dolfinx import fem

from face_dolfinx.alignment.surface import closest_points
from face_dolfinx.physics.contact import ContactSurface

# No point of a Newton step's line-search segment may bring two lip primitives closer than
# (1 - CCD_KEEP) of their smallest distance now (IPC's conservative rescaling).
CCD_KEEP = 0.8

# The narrow phase of the step bound: additive CCD (Li et al. 2021), some thousand times faster than
# ipctk's default tight-inclusion CCD with a minimum distance on the 5K face's pressed lips, for
# the same step fractions (benchmarks/lip_ccd.py, docs/contact.md).
NARROW_PHASE = ipctk.AdditiveCCD()

# Halvings of a collision-free bound whose end still has the lips intersecting, before it is 0.
INTERSECTION_HALVINGS = 30

# Newton iterations a solve with lip contact may take before continuation takes over.
LIP_NEWTON_ITERATIONS = 100

# How far the lips may slide on each other (mm, at rest) before a barrier pair couples nodes outside
# the tangent's pattern (``coupled_blocks``): the built-in face's bilabial take slides them up to
# 1.7 mm (docs/contact.md, "The tangent's pattern").
PATTERN_SLIDE = 3.0

# A lip node's sides (``LipContact._sides``), and where each kind of ipctk pair's vertex ids
# (``vertex_ids``: the first primitive's, then the second's, -1 for none) pass to its second primitive.
_UPPER, _LOWER = 1, 2
_FIRST_PRIMITIVE = {"vv_collisions": 1, "ev_collisions": 1, "ee_collisions": 2, "fv_collisions": 1}

# Rounds of ``LipContact.pushed_along``: each gives the nodes of every pair of lip primitives that a
# move would bring too close the longest move among them.
PUSH_ALONG_ROUNDS = 8

# The landmarks that place the mouth.
LIP_LANDMARKS = ("mouth_corner_left", "mouth_corner_right", "upper_lip_center", "lower_lip_center")


@dataclass
class LipContactSettings:
    """The lips' barrier: activation distance ``dhat`` (mm) and ``stiffness`` (the barrier's
    scale: a stiffer barrier holds the lips further apart under the same pressure); how far from
    the mouth-corner segment a facet of the slit may lie (``depth``, mm) and how squarely it must
    face the other lip (``facing``: cosine of the angle between its normal and the direction
    between the lips); ``pattern_radius`` (mm): pairs of an upper and a lower lip node this close at
    rest get room in the tangent's sparsity (None: ``PATTERN_SLIDE`` plus twice the lips' longest
    edge; docs/contact.md); ``newton_reach`` (mm): the reach of the barrier that Newton's tangent
    alone carries across the lips while it is far from the solution (``add_newton_correction``; at
    most dhat: none)."""

    dhat: float = 0.05
    stiffness: float = 10.0
    depth: float = 15.0
    facing: float = 0.7
    pattern_radius: float | None = None
    newton_reach: float = 0.5
    where: str = "the lip contact settings"  # named in error messages (a file, an option)


def lip_facets(model, settings: LipContactSettings) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Local indices of the upper and lower lip facets of ``model`` (see the module docstring) and
    the unit direction from the lower lip to the upper.
    ValueError naming the model if a landmark or the skin tag is missing or no facet qualifies."""
    missing = [name for name in LIP_LANDMARKS if name not in model.landmarks]
    if missing or "skin" not in model.boundary_ids:
        what = f"the landmarks {', '.join(missing)}" if missing else "facets tagged 'skin'"
        raise ValueError(f"{settings.where}: model {model.path} has no {what}, which place the lips "
                         "(docs/model_format.md)")
    mesh = model.mesh
    tdim = mesh.topology.dim
    for dims in ((tdim - 1, 0), (tdim - 1, tdim), (tdim, 0)):
        mesh.topology.create_connectivity(*dims)
    facet_vertices = mesh.topology.connectivity(tdim - 1, 0)
    facet_cells = mesh.topology.connectivity(tdim - 1, tdim)
    cell_vertices = mesh.topology.connectivity(tdim, 0)
    x = mesh.geometry.x
    # Geometry nodes of the vertices (P1 geometry: the same numbering only by chance, so mapped).
    vertex_node = np.empty(mesh.topology.index_map(0).size_local + mesh.topology.index_map(0).num_ghosts, dtype=np.int64)
    vertex_node[cell_vertices.array.reshape(-1, 4)] = mesh.geometry.dofmap.array.reshape(len(cell_vertices), -1)[:, :4]
    landmarks = model.landmarks
    left, right = (np.asarray(landmarks[k], dtype=float) for k in LIP_LANDMARKS[:2])
    up = np.asarray(landmarks["upper_lip_center"], dtype=float) - np.asarray(landmarks["lower_lip_center"], dtype=float)
    up /= np.linalg.norm(up)
    axis = right - left
    upper, lower = [], []
    for facet in model.facet_tags.find(model.boundary_ids["skin"]):
        corners = vertex_node[facet_vertices.links(facet)]
        cell = facet_cells.links(facet)[0]
        opposite = np.setdiff1d(vertex_node[cell_vertices.links(cell)], corners)[0]
        p = x[corners]
        normal = np.cross(p[1] - p[0], p[2] - p[0])
        normal /= np.linalg.norm(normal)
        if normal @ (p[0] - x[opposite]) < 0.0:
            normal = -normal
        centre = p.mean(axis=0)
        t = np.clip((centre - left) @ axis / (axis @ axis), 0.0, 1.0)
        if np.linalg.norm(centre - left - t * axis) > settings.depth:
            continue
        if normal @ up <= -settings.facing:
            upper.append(facet)
        elif normal @ up >= settings.facing:
            lower.append(facet)
    upper, lower = np.array(upper, dtype=np.int32), np.array(lower, dtype=np.int32)
    comm = mesh.comm
    if comm.allreduce(len(upper), op=MPI.SUM) == 0 or comm.allreduce(len(lower), op=MPI.SUM) == 0:
        raise ValueError(f"{settings.where}: model {model.path} has no skin facets lining the mouth slit "
                         f"within {settings.depth:g} mm of its corners facing the other lip")
    return upper, lower, up


class LipContact:
    """The barrier energy of the lips against each other, as an extra energy term of the
    equilibrium solver (module docstring). ``upper``, ``lower``, ``up``: ``lip_facets``;
    ``constrained_blocks``: the local blocks a bone holds (refused on the lips)."""

    # Newton takes the projected pair Hessians (``add_newton_correction``) only until it is near the
    # solution (``QuasistaticSolver``): the projection drops curvature the solution has and turns
    # Newton's quadratic convergence linear. The orbicularis oris at 1 with the jaw closed, 5K
    # face, from rest: 238 Newton iterations in 2 load steps projected throughout, 74 in 1 this way,
    # 75 with the exact Hessian always (docs/contact.md, "Newton with pressed lips").
    exact_near_solution = True
    label = "lips"  # names the term in the Newton trace
    # A Newton solve whose corrections this bound cuts again and again, the residual on the contact
    # nodes, relaxes them (QuasistaticSolver, CRAWL_CUTS): the lips peeling apart, an edge-edge
    # pair at the front setting every bound (docs/performance.md, "The lips' opening").
    relax_on_crawl = True
    # And one whose residual falls slowly on the lips' nodes (QuasistaticSolver,
    # SLOW_FALL_CONTACT_SHARE): the lips letting go of each other. The 5K face's pressed lips let go:
    # 2-6 factorisations instead of 3-20; the 20K face, frames 6-14 and 16-24 of the bilabial take
    # with the head moving: 13 and 11 in the warm frames instead of 16 and 12; at 404K the opening 10
    # instead of 16-22, the second closure 10-14 instead of 8 (docs/performance.md, "The lips' slow
    # fall").
    relax_on_slow_fall = True
    # False: the wider barrier leaves out the pairs beyond dhat that have parted since the last
    # Newton model (``_drop_parting``).
    reach_on_parting_pairs = False

    def __init__(self, space: fem.FunctionSpace, upper: np.ndarray, lower: np.ndarray, up: np.ndarray,
                 settings: LipContactSettings, constrained_blocks: np.ndarray):
        if not settings.dhat > 0.0 or not settings.stiffness > 0.0:
            raise ValueError(f"{settings.where}: dhat and the stiffness must be positive "
                             f"(got {settings.dhat:g} mm, {settings.stiffness:g} kPa)")
        if not np.isfinite(settings.newton_reach) or settings.newton_reach < 0.0:
            raise ValueError(f"{settings.where}: the lips' Newton reach must be a distance of 0 mm or more "
                             f"(got {settings.newton_reach!r})")
        self.settings = settings
        self.up = np.asarray(up, dtype=float)
        self.dhat, self.stiffness = settings.dhat, settings.stiffness
        self.surface = ContactSurface(space, np.concatenate([upper, lower]))
        self.comm = self.surface.comm
        index_map = space.dofmap.index_map
        # Global block (node) index of every lip node, and whether a bone holds it.
        owned_global = index_map.local_to_global(self.surface.owned_blocks)
        self.global_blocks = np.empty(self.surface.num_nodes, dtype=np.int64)
        self.global_blocks[np.concatenate(self.comm.allgather(self.surface.owned_nodes))] = \
            np.concatenate(self.comm.allgather(owned_global))
        if self._flagged(constrained_blocks).size:
            raise ValueError(f"{settings.where}: some lip nodes are held by a bone; the lip surfaces must be "
                             "free flesh (shrink the lips' depth)")
        dim = space.mesh.topology.dim - 1
        self.upper_nodes = self._flagged(fem.locate_dofs_topological(space, dim, upper))
        self.lower_nodes = self._flagged(fem.locate_dofs_topological(space, dim, lower))
        faces = np.ascontiguousarray(self.surface.triangles, dtype=np.int32)
        edges = ipctk.edges(faces)
        self.mesh = ipctk.CollisionMesh(np.asfortranarray(self.surface.rest), np.asfortranarray(edges),
                                        np.asfortranarray(faces))
        self.potential = ipctk.BarrierPotential(self.dhat, self.stiffness, True)
        self.newton_potential = (ipctk.BarrierPotential(settings.newton_reach, self.stiffness, True)
                                 if settings.newton_reach > self.dhat else None)
        # Which lips each node lies on (the mouth corners' on both), and a last entry on both for
        # ipctk's vertex id -1 (no vertex), for ``_across``.
        self._sides = np.full(self.surface.num_nodes + 1, _UPPER | _LOWER, dtype=np.int8)
        self._sides[:-1] = 0
        self._sides[self.upper_nodes] |= _UPPER
        self._sides[self.lower_nodes] |= _LOWER
        self._last = None  # the last state's collisions (``_state``)
        self._wide_reference = None  # the lip nodes at the last Newton model (``_drop_parting``)
        # The cells near the lips (vertex blocks, rest corners, global vertex blocks), for
        # ``penetration``.
        cells = space.mesh.topology.index_map(3).size_local
        blocks = space.dofmap.list.array.reshape(-1, space.dofmap.dof_layout.num_dofs)[:cells, :4]
        rest_corners = space.tabulate_dof_coordinates()[:, :3][blocks]
        centre, reach = self.surface.rest.mean(axis=0), np.ptp(self.surface.rest, axis=0).max()
        near = np.linalg.norm(rest_corners.mean(axis=1) - centre, axis=1) < reach
        self._cell_blocks, self._cell_rest = blocks[near], rest_corners[near]
        self._cell_globals = index_map.local_to_global(blocks[near].reshape(-1)).reshape(-1, 4)
        # Each lip's nodes off the other lip, with the other lip's triangles.
        self._opposite = [(np.setdiff1d(nodes, others),
                           self.surface.triangles[np.isin(self.surface.triangles, others).all(axis=1)])
                          for nodes, others in ((self.upper_nodes, self.lower_nodes),
                                                (self.lower_nodes, self.upper_nodes))]
        rest_distance = self.min_distance(np.zeros(3 * (space.dofmap.index_map.size_local + index_map.num_ghosts)))
        if not rest_distance > self.dhat:
            raise ValueError(f"{settings.where}: the lips are {rest_distance:.3g} mm apart at rest, not more than "
                             f"dhat = {self.dhat:g} mm: give a smaller dhat")

    def _flagged(self, blocks: np.ndarray) -> np.ndarray:
        """Lip node indices (every rank) of the local blocks ``blocks`` of any rank."""
        return np.flatnonzero(self.surface.flagged(blocks))

    # -- geometry ----------------------------------------------------------------------------
    def positions(self, displacement: np.ndarray) -> np.ndarray:
        """(lip nodes, 3) current positions (every rank; the owned part of ``displacement`` read)."""
        return np.asfortranarray(self.surface.rest + self.surface.gather(displacement))

    def _state(self, vertices: np.ndarray) -> "_LipState":
        """The broad and narrow phase at ``vertices``: the same state as the last call's (an exact
        compare) reuses its results, so that the energy, gradient, Hessian and step bound of one
        Newton iterate build the collision set once."""
        if self._last is None or not np.array_equal(vertices, self._last.vertices):
            self._last = _LipState(self.mesh, vertices.copy(order="F"), self.dhat)
        return self._last

    def _collisions(self, vertices: np.ndarray) -> ipctk.NormalCollisions:
        return self._state(vertices).collisions

    def min_distance(self, displacement: np.ndarray, reach: float = np.inf) -> float:
        """Smallest distance between lip primitives that share no vertex (mm; 0 once they
        intersect), or ``reach`` if none is closer than that."""
        return self._min_distance_at(self.positions(displacement), reach)

    def intersects(self, displacement: np.ndarray) -> bool:
        """Whether any two lip triangles intersect at ``displacement`` (the same on every rank)."""
        return self._state(self.positions(displacement)).intersects

    def _min_distance_at(self, vertices: np.ndarray, reach: float) -> float:
        state = self._state(vertices)
        if state.intersects:
            return 0.0
        reach = min(reach, ipctk.world_bbox_diagonal_length(vertices))
        if reach == self.dhat:
            # The pairs within dhat are the barrier's collision set (its area weights do not
            # change the distances).
            collisions = state.collisions
        else:
            # Every pair closer than a search radius is in its set, so the first radius that finds
            # one finds the nearest: growing it from dhat spares building the lips' all-pairs set
            # (on the 404K face a sixth of a closing solve's time).
            radius = min(self.dhat, reach)
            while True:
                collisions = ipctk.NormalCollisions()
                collisions.build(self.mesh, vertices, radius)
                if len(collisions) or radius >= reach:
                    break
                radius = min(4.0 * radius, reach)
        # ipctk's distances are squared.
        return float(np.sqrt(collisions.compute_minimum_distance(self.mesh, vertices))) if len(collisions) else reach

    def pairs(self, displacement: np.ndarray) -> int:
        """Number of barrier pairs (point-triangle, edge-edge, ...) within dhat."""
        return len(self._collisions(self.positions(displacement)))

    def slide(self, displacement: np.ndarray) -> float:
        """Largest distance at rest between the two primitives of a barrier pair at ``displacement``
        (mm; 0 without pairs): how far the pressed lips have slid on each other, their rest gap
        included (``PATTERN_SLIDE``)."""
        state = self._state(self.positions(displacement))
        rest, edges, faces = np.asfortranarray(self.surface.rest), self.mesh.edges, self.mesh.faces
        # ipctk's distances are squared.
        return max((float(np.sqrt(pair.compute_distance(pair.dof(rest, edges, faces)))) for pair in state.collisions),
                   default=0.0)

    def nodal_forces(self, displacement: np.ndarray) -> np.ndarray:
        """(lip nodes, 3) dE_s/dx: the contact force each lip node exerts (mN)."""
        vertices = self.positions(displacement)
        return self.potential.gradient(self._collisions(vertices), self.mesh, vertices).reshape(-1, 3)

    def nodal_pressure(self, displacement: np.ndarray) -> np.ndarray:
        """|contact force| / lumped rest area per lip node (kPa)."""
        return np.linalg.norm(self.nodal_forces(displacement), axis=1) / self.surface.areas

    def penetration(self, displacement: np.ndarray) -> float:
        """Deepest lip node inside the flesh of the other lip (mm, 0 if none; every rank): a node
        inside a cell it is no vertex of, by its distance to the other lip's surface. (A lip that
        passes a slit's width through the other leaves the surfaces disjoint again, so the test
        is by the cells.) ``displacement``: a local dof array with its ghosts."""
        x = self.positions(displacement)
        corners = self._cell_rest + displacement.reshape(-1, 3)[self._cell_blocks]
        deepest = 0.0
        if len(corners):
            # A cell holds only points within its farthest corner of its centroid: each node is
            # tested against the cells that near (on the 404K face the test of every node against
            # every cell near the lips took most of a closing solve's time).
            centroids = corners.mean(axis=1)
            reach = np.linalg.norm(corners - centroids[:, None, :], axis=2).max()
            tree = scipy.spatial.cKDTree(centroids)
            for free, triangles in self._opposite:
                for node, near in zip(free, tree.query_ball_point(x[free], reach)):
                    near = np.asarray(near, dtype=np.int64)
                    inside = (_contains(corners[near], x[node])
                              & ~(self._cell_globals[near] == self.global_blocks[node]).any(axis=1))
                    if inside.any():
                        deepest = max(deepest, _distance_to_triangles(x[node], x[triangles]))
        return self.comm.allreduce(deepest, op=MPI.MAX)

    # -- sparsity ----------------------------------------------------------------------------
    def coupled_blocks(self) -> np.ndarray:
        """(pairs, 2) global block indices of the upper and lower lip nodes within
        ``pattern_radius`` of each other at rest, both orders: entries the tangent's sparsity must hold."""
        rest = self.surface.rest
        upper, lower = self.upper_nodes, self.lower_nodes
        distance = np.linalg.norm(rest[upper, None, :] - rest[None, lower, :], axis=2)
        i, j = np.nonzero(distance <= self.pattern_radius)
        pairs = np.column_stack([self.global_blocks[upper[i]], self.global_blocks[lower[j]]])
        return np.concatenate([pairs, pairs[:, ::-1]])

    @property
    def pattern_radius(self) -> float:
        """The settings' ``pattern_radius``, or by default ``PATTERN_SLIDE`` plus twice the longest
        edge of the lip surfaces (mm)."""
        if self.settings.pattern_radius is not None:
            return self.settings.pattern_radius
        rest, edges = self.surface.rest, self.mesh.edges
        return PATTERN_SLIDE + 2.0 * float(np.linalg.norm(rest[edges[:, 0]] - rest[edges[:, 1]], axis=1).max())

    # -- the solver's energy-term interface ---------------------------------------------------
    def energy(self, x: PETSc.Vec) -> float:
        """E_s at the displacement ``x`` (the same on every rank; inf once the lips intersect)."""
        vertices = self.positions(x.array_r)
        state = self._state(vertices)
        value = np.inf if state.intersects else float(self.potential(state.collisions, self.mesh, vertices))
        return self.comm.allreduce(value, op=MPI.MAX)

    def add_gradient(self, x: PETSc.Vec, b: PETSc.Vec) -> None:
        """b += dE_s/du on this rank's dofs."""
        gradient = self.nodal_forces(x.array_r)[self.surface.owned_nodes]
        b.array.reshape(-1, 3)[self.surface.owned_blocks] += gradient

    def add_hessian(self, x: PETSc.Vec, A: PETSc.Mat, constrained: np.ndarray) -> None:
        """A += d2E_s/du2 on this rank's rows (assembled), the rows and columns of the Dirichlet
        dofs ``constrained`` (owned local dofs, on any rank) left alone: no bone holds a lip node
        (checked at set-up), but an object's move holds the skin nodes it pushes out for one
        solve (``ContactPotential.move_to``), lip nodes too where it presses on the lips."""
        free = self.surface.free(constrained, x.getLocalSize())
        state = self._state(self.positions(x.array_r))
        if len(state.collisions):
            self._add_matrix(state.hessian(self.potential), A, free)
        A.assemble()

    def add_newton_correction(self, x: PETSc.Vec, A: PETSc.Mat, constrained: np.ndarray) -> bool:
        """A += the change that makes ``add_hessian``'s matrix Newton's: each pair's Hessian
        projected onto the positive semidefinite ones (IPC's practice, ``PSDProjectionMethod.CLAMP``).
        The exact Hessian of a pair b'' grad d grad d^T + b' hess d has the negative part b' hess d
        (b' < 0), of size |b'| / d, which grows without bound as the pressed lips close in: the
        tangent then turns indefinite along the lips' sliding, and Newton's corrections there point
        nowhere useful. Plus the projected Hessian of the barrier of wider reach across the lips
        (``newton_reach``). Returns whether the matrix changed (the same on every rank)."""
        return self._add_newton_model(x, A, constrained, wide=True)

    def add_projection(self, x: PETSc.Vec, A: PETSc.Mat, constrained: np.ndarray) -> bool:
        """``add_newton_correction`` without the barrier of wider reach: the projection alone, for
        a Newton that iterates the lip nodes to their own equilibrium (``relaxation``), which the
        wider barrier's curvature would slow."""
        return self._add_newton_model(x, A, constrained, wide=False)

    def _add_newton_model(self, x: PETSc.Vec, A: PETSc.Mat, constrained: np.ndarray, wide: bool) -> bool:
        free = self.surface.free(constrained, x.getLocalSize())
        vertices = self.positions(x.array_r)
        state = self._state(vertices)
        change = None
        if len(state.collisions):
            change = (state.hessian(self.potential, projected=True) - state.hessian(self.potential)).tocsc()
        if wide and self.newton_potential is not None:
            wide = ipctk.NormalCollisions()
            wide.use_area_weighting = True
            wide.build(self.mesh, vertices, self.newton_potential.dhat)
            self._across(wide)
            self._drop_parting(wide, vertices)
            if len(wide):
                wide = self.newton_potential.hessian(wide, self.mesh, vertices,
                                                     project_hessian_to_psd=ipctk.PSDProjectionMethod.CLAMP).tocsc()
                change = wide if change is None else change + wide
        if change is not None:
            change.eliminate_zeros()
        # The ranks may differ in the last bits of ipctk's threaded sums: they agree on the answer
        # (and assemble together) by the reduction.
        changed = self.comm.allreduce(change is not None and change.nnz > 0, op=MPI.LOR)
        if changed:
            if change is not None:
                self._add_matrix(change, A, free)
            A.assemble()
        return changed

    def _drop_parting(self, collisions: ipctk.NormalCollisions, vertices: np.ndarray) -> None:
        """Drop from the wider barrier's ``collisions`` the pairs beyond dhat that have parted since
        the last Newton model: the wider barrier is there for pairs coming together; on lips letting
        go of each other it is a stiffness against their parting that the energy does not have,
        and Newton's corrections fall short of the opening. (The 20K face, frames 6-14 and 16-24 of
        the bilabial take with the head moving: 15 and 13 factorisations in the warm frames against
        16 and 12, with the slow fall on the lips' nodes 12 and 11 against 13 and 11.)"""
        reference, self._wide_reference = self._wide_reference, vertices.copy(order="F")
        if reference is None or self.reach_on_parting_pairs:
            return
        edges, faces = self.mesh.edges, self.mesh.faces
        for kind in _FIRST_PRIMITIVE:
            pairs = getattr(collisions, kind)
            if pairs:
                # ipctk's distances are squared.
                setattr(collisions, kind, [
                    pair for pair in pairs
                    if (now := pair.compute_distance(vertices, edges, faces)) <= self.dhat ** 2
                    or now <= pair.compute_distance(reference, edges, faces)])

    def _across(self, collisions: ipctk.NormalCollisions) -> None:
        """Drop from ``collisions`` the pairs of two primitives of one lip: the tangent's pattern
        holds room for pairs across the lips only (``coupled_blocks``)."""
        edges, faces = self.mesh.edges, self.mesh.faces
        for kind, first in _FIRST_PRIMITIVE.items():
            pairs = getattr(collisions, kind)
            if not pairs:
                continue
            sides = self._sides[np.array([pair.vertex_ids(edges, faces) for pair in pairs])]
            # A primitive lies on the lips all its vertices lie on.
            one = np.bitwise_and.reduce(sides[:, :first], axis=1)
            other = np.bitwise_and.reduce(sides[:, first:], axis=1)
            across = (((one & _UPPER) > 0) & ((other & _LOWER) > 0)) | (((one & _LOWER) > 0) & ((other & _UPPER) > 0))
            setattr(collisions, kind, [pair for pair, keep in zip(pairs, across) if keep])

    def _add_matrix(self, matrix, A: PETSc.Mat, free: np.ndarray) -> None:
        """A += the lip nodes' (3 nodes, 3 nodes) ``matrix`` (scipy sparse) on this rank's rows,
        only between the ``free`` dofs (lip nodes, 3)."""
        keep = scipy.sparse.diags(free.reshape(-1).astype(float))
        owned_rows = (3 * self.surface.owned_nodes[:, None] + np.arange(3)).reshape(-1)
        global_dof = (3 * self.global_blocks[:, None] + np.arange(3)).reshape(-1).astype(PETSc.IntType)
        local = (keep @ matrix @ keep).tocsr()[owned_rows]
        local.eliminate_zeros()
        if local.nnz:
            # All rows in one call (PETSc loops over them): a Python loop over the rows cost
            # more than the Hessian itself.
            A.setValuesIJV(local.indptr.astype(PETSc.IntType), global_dof[local.indices], local.data,
                           addv=PETSc.InsertMode.ADD_VALUES, rowmap=global_dof[owned_rows])

    def step_fraction(self, x: PETSc.Vec, step: PETSc.Vec, largest: float) -> float:
        """Largest t in (0, 1] such that no point of x - s t largest step, s in [0, 1], brings two
        lip primitives closer than (1 - CCD_KEEP) of their smallest distance now."""
        return self.admissible_fraction(x.array_r, x.array_r - largest * step.array_r)

    def admissible_fraction(self, start: np.ndarray, end: np.ndarray) -> float:
        """The same bound for the straight path from the displacement ``start`` to ``end`` (dof
        arrays, owned part read); the same on every rank."""
        v0, v1 = self.positions(start), self.positions(end)
        distance = self._min_distance_at(v0, self.dhat)
        # Every point of a primitive moves at most as far as its farthest vertex: two that close in
        # by less than CCD_KEEP of the smallest distance cannot come closer than the bound.
        # (The ranks may differ in the last bits of ipctk's threaded reductions: they agree by the
        # reduction, whichever branch each took.)
        fraction = 1.0
        if 2.0 * np.linalg.norm(v1 - v0, axis=1).max(initial=0.0) > CCD_KEEP * distance:
            fraction = float(ipctk.compute_collision_free_stepsize(self.mesh, v0, v1, (1.0 - CCD_KEEP) * distance,
                                                                    narrow_phase_ccd=NARROW_PHASE))
            # The bound also stops short of an end where the lips intersect: the relaxation of
            # pressed lips on 2 ranks was once seen to try such a point within the CCD's bound,
            # and from there every later bound let it be (docs/contact.md, "A missed crossing").
            if distance > 0.0:
                for _ in range(INTERSECTION_HALVINGS):
                    if not ipctk.has_intersections(self.mesh, v0 + fraction * (v1 - v0)):
                        break
                    fraction *= 0.5
                else:
                    fraction = 0.0
        return self.comm.allreduce(fraction, op=MPI.MIN)

    def pushed_along(self, start: np.ndarray, end: np.ndarray) -> np.ndarray | None:
        """``end``, a move of some lip nodes from the displacement ``start`` (dof arrays with their
        ghosts) that would let the lips pass each other (``admissible_fraction`` below 1), with the
        lips pushed along one another: round after round, the nodes of every pair of primitives
        that the move brings closer than the bound allows (each pair found by the IPC Toolkit's
        continuous collision detection) all take the longest move among them, until no pair is
        left; None if PUSH_ALONG_ROUNDS rounds do not get there. A lower lip node that the teeth
        closing overrun is pushed out of their way into the upper lip pressed on it: left there,
        the solve had no finite residual; with the upper lip moved too, the pair keeps its gap
        (collective; rank 0 decides, the same on every rank)."""
        v0 = self.positions(start)
        move = self.positions(end) - v0
        pushed = end
        for _ in range(PUSH_ALONG_ROUNDS):
            if self.admissible_fraction(start, pushed) == 1.0:
                return pushed
            taken, move = self.comm.bcast(self._pushed_together(v0, move) if self.comm.rank == 0 else None, root=0)
            if not taken.size:
                return None
            pushed = self.surface.placed(pushed, v0 + move, taken)
        return pushed if self.admissible_fraction(start, pushed) == 1.0 else None

    def _pushed_together(self, v0: np.ndarray, move: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The lip nodes whose ``move`` (nodes, 3) becomes the longest one among the nodes of a pair
        of primitives that the moves from ``v0`` bring closer than ``admissible_fraction`` allows
        (and whose move that changes), and the moves so changed."""
        separation = (1.0 - CCD_KEEP) * self._min_distance_at(v0, self.dhat)
        v0, v1 = np.asfortranarray(v0), np.asfortranarray(v0 + move)
        candidates = ipctk.Candidates()
        candidates.build(self.mesh, v0, v1, separation)
        edges, faces = self.mesh.edges, self.mesh.faces
        length = np.linalg.norm(move, axis=1)
        longest, source = length.copy(), np.arange(len(move))
        for kind in ("vv_candidates", "ev_candidates", "ee_candidates", "fv_candidates"):
            for candidate in getattr(candidates, kind):
                hit, toi = candidate.ccd(candidate.dof(v0, edges, faces), candidate.dof(v1, edges, faces),
                                         separation, 1.0, NARROW_PHASE)
                if not hit or toi >= 1.0:
                    continue
                nodes = np.asarray(candidate.vertex_ids(edges, faces))
                nodes = nodes[nodes >= 0]
                leader = nodes[np.argmax(length[nodes])]
                follow = nodes[length[leader] > longest[nodes]]
                longest[follow], source[follow] = length[leader], leader
        taken = np.flatnonzero(source != np.arange(len(move)))
        return taken, move[source]


class LipIterates:
    """A SNES monitor (``solver.snes.setMonitor(LipIterates(lips, space))``) that records at every
    Newton iterate the lips' smallest distance (``distances``) and their deepest penetration
    (``depths``, ``LipContact.penetration``), both in mm."""

    def __init__(self, lips: LipContact, space: fem.FunctionSpace):
        self.lips = lips
        self.distances, self.depths = [], []
        self.iterate = fem.Function(space)  # the iterate with its ghosts, for the cells' corners
        self.owned = space.dofmap.index_map.size_local * space.dofmap.index_map_bs

    def __call__(self, snes, iteration: int, norm: float) -> None:
        self.iterate.x.array[:self.owned] = snes.getSolution().array_r
        self.iterate.x.scatter_forward()
        self.distances.append(self.lips.min_distance(self.iterate.x.array))
        self.depths.append(self.lips.penetration(self.iterate.x.array))


class _LipState:
    """The lips' collision queries at one set of vertex positions, each computed on first use."""

    def __init__(self, mesh: ipctk.CollisionMesh, vertices: np.ndarray, dhat: float):
        self.mesh, self.vertices, self.dhat = mesh, vertices, dhat
        self._collisions, self._intersects = None, None
        self._hessians = {}

    def hessian(self, potential: ipctk.BarrierPotential, projected: bool = False):
        """The barrier's Hessian (scipy sparse; ``projected``: each pair's onto the positive
        semidefinite ones): the tangent's and Newton's correction at one iterate share the exact one."""
        if projected not in self._hessians:
            method = ipctk.PSDProjectionMethod.CLAMP if projected else ipctk.PSDProjectionMethod.NONE
            self._hessians[projected] = potential.hessian(self.collisions, self.mesh, self.vertices,
                                                          project_hessian_to_psd=method)
        return self._hessians[projected]

    @property
    def collisions(self) -> ipctk.NormalCollisions:
        """The barrier's pairs within dhat, with the IPC Toolkit's area weights."""
        if self._collisions is None:
            self._collisions = ipctk.NormalCollisions()
            self._collisions.use_area_weighting = True
            self._collisions.build(self.mesh, self.vertices, self.dhat)
        return self._collisions

    @property
    def intersects(self) -> bool:
        """Whether any two lip triangles intersect."""
        if self._intersects is None:
            self._intersects = bool(ipctk.has_intersections(self.mesh, self.vertices))
        return self._intersects


def _contains(corners: np.ndarray, point: np.ndarray) -> np.ndarray:
    """Which tetrahedra (cells, 4, 3) contain ``point`` (barycentric coordinates all >= 0)."""
    edges = corners[:, 1:] - corners[:, :1]
    offset = point - corners[:, 0]
    with np.errstate(all="ignore"):
        weights = np.linalg.solve(np.transpose(edges, (0, 2, 1)), offset[:, :, None])[:, :, 0]
    return (weights >= 0.0).all(axis=1) & (weights.sum(axis=1) <= 1.0)


def _distance_to_triangles(point: np.ndarray, triangles: np.ndarray) -> float:
    """Distance of ``point`` to the nearest of the triangles (k, 3, 3)."""
    points = np.broadcast_to(point, (len(triangles), 3))
    closest = closest_points(points, triangles[:, 0], triangles[:, 1], triangles[:, 2])[0]
    return float(np.linalg.norm(points - closest, axis=1).min())
