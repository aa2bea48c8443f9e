"""Frictionless contact of a surface of the flesh with rigid kinematic objects (IPC barrier).

An object (``Sphere``, ``HalfSpace``) is rigid and moves as prescribed: its pose, an ``AffineMap``
from its own frame to the world like the bone frames, is a control set before each solve (a
trajectory is a sequence of poses), so moving it recompiles nothing. The contact surface is a
tagged set of boundary facets (the skin of the face). Every node of it (vertices, and for P2 the
edge midpoints: each P2 triangle is split into four flat ones) keeps a gap g > 0 to every object;
against a sphere, every flat triangle does (``face_contact.FaceContactPotential``, the default
through ``ContactSettings.faces``).

The energy is the incremental potential contact barrier of Li et al. (2020), the IPC Toolkit's
``ipctk.barrier`` b(g) = -(g - dhat)^2 ln(g / dhat) for g < dhat and 0 beyond, weighted by each
node's share of the rest surface area so that it is a surface pressure that converges with the mesh:

    E_c = stiffness / dhat * sum_i A_i b(g_i),   p(g) = -stiffness b'(g) / dhat  (kPa)

``stiffness`` is thus about the contact pressure at g = dhat / 2 (p = 1.19 stiffness there); the
pressure grows without bound as g -> 0. For a triangle mesh (``rigid_mesh.TriangleMesh``) b(g_i)
is a signed sum of b over the triangles, edges and vertices within dhat of the node, smooth where
the nearest triangle changes. For a sphere and a half-space the gap of a node to an object is
analytic, so the barrier couples each node only with itself: the Hessian is 3x3 blocks
on the diagonal, inside the finite-element sparsity, and symmetric (Cholesky still works). The
continuous collision detection is analytic too: ``step_fraction`` bounds a Newton step so that no
node loses more than ``CCD_KEEP`` of its gap, anywhere along the line-search segment.

Under MPI every rank gathers the positions of all contact nodes (a surface is small next to the
volume), orders them by rest coordinates (so the sums are the same on any number of ranks), and
adds the terms of the nodes it owns. ``ContactPotential`` is the solver's extra energy term
(``QuasistaticSolver(energy_terms=...)``): energy, gradient into the residual, Hessian into the
tangent, step bound next to the inversion guard's.
"""
from collections.abc import Callable
from dataclasses import dataclass
import logging

from mpi4py import MPI
from petsc4py import PETSc
import ipctk
import numpy as np
from dolfinx import fem, geometry

from face_dolfinx.model.bones import AffineMap
from face_dolfinx.physics.rigid_mesh import TriangleMesh

log = logging.getLogger(__name__)

# Along a Newton step or line-search segment no node may lose more than this fraction of its gap
# (IPC's conservative rescaling of the time of impact, 0.8, is the same bound for a plane).
CCD_KEEP = 0.8

# Conservative advancement of the collision-free bound (``advanced_contact``): at most this many
# distance queries per step; a point whose advance fell below ADVANCE_STALL of its time so far is
# at a true contact and stops.
ADVANCE_ROUNDS = 8
ADVANCE_STALL = 0.02

# Relative size of an eigenvalue of a barrier block below which it is round-off.
ROUND_OFF = 1e-10

# Where the push-out predictor puts a node that an object's new pose would overlap: at this
# fraction of dhat from the object, where the barrier pressure is about the stiffness.
PUSH_GAP = 0.5

# kPa: the barrier stiffness for the lips on the teeth, about their contact pressure when the
# orbicularis oris presses them there (docs/contact.md); 10 kPa leaves gaps of a few micrometres
# and Newton crawls.
TEETH_STIFFNESS = 100.0

# mm: the teeth's dhat. The barrier must reach further than a Newton correction's overshoot: a
# lining node outside dhat does not feel the teeth in the linearisation, and each one arriving cuts
# the whole step (the orbicularis oris at 0.1 on the 5K face: 68 Newton iterations in 2 load steps
# at 0.05 mm, 13 in one at 0.5 mm; docs/contact.md). The built-in teeth sit far enough behind the
# lining that the rest state is barrier-free.
TEETH_DHAT = 0.5

# mm: when the jaw moves, the lining nodes this close to a tooth are carried with it
# (``ContactPotential.carry``).
CARRY_REACH = 2.0

# mm: a node whose move is shorter than this has not moved (round-off of positions and displacements).
UNMOVED = 1e-9

# Reference tetrahedron (basix): facet i is opposite vertex i; edge e joins these vertices.
_TET_EDGES = ((2, 3), (1, 3), (1, 2), (0, 3), (0, 2), (0, 1))


def barrier(g: np.ndarray, dhat: float) -> np.ndarray:
    """b(g) of ``ipctk.barrier``, vectorised; 0 for g >= dhat, inf for g <= 0."""
    with np.errstate(divide="ignore", invalid="ignore"):
        value = -(g - dhat) ** 2 * np.log(g / dhat)
    return np.where(g >= dhat, 0.0, np.where(g > 0.0, value, np.inf))


def barrier_derivatives(g: np.ndarray, dhat: float) -> tuple[np.ndarray, np.ndarray]:
    """b'(g) and b''(g) (``ipctk.barrier_first_derivative``, ``..._second_derivative``); NaN for
    g <= 0, where the barrier is undefined."""
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = dhat / g
        first = (dhat - g) * (2.0 * np.log(g / dhat) - ratio + 1.0)
        second = (ratio + 2.0) * ratio - 2.0 * np.log(g / dhat) - 3.0
    inactive = g >= dhat
    return (np.where(inactive, 0.0, np.where(g > 0.0, first, np.nan)),
            np.where(inactive, 0.0, np.where(g > 0.0, second, np.nan)))


def closing_in(now: np.ndarray, moved: np.ndarray, dhat: float) -> bool:
    """Whether gaps going from ``now`` to ``moved`` (an object's move) lose more than a
    collision-free step may (``CCD_KEEP``) and end closer than PUSH_GAP dhat somewhere."""
    return bool(((moved < (1.0 - CCD_KEEP) * now) & (moved < PUSH_GAP * dhat)).any())


def _flattens(solver, start: np.ndarray, end: np.ndarray) -> bool:
    """Whether the straight move from the displacement ``start`` to ``end`` (dof arrays with their
    ghosts) flattens a cell of ``solver``'s inversion guard (False without one; collective)."""
    return solver.inversion_guard is not None and solver.inversion_guard.flattens(start, end)


def surfaces_cross(points_a: np.ndarray, triangles_a: np.ndarray, points_b: np.ndarray,
                   triangles_b: np.ndarray) -> bool:
    """Whether an edge of one triangle surface passes through a triangle of the other (the IPC
    Toolkit's exact intersection test; each surface's own intersections are not sought)."""
    vertices = np.asfortranarray(np.vstack([points_a, points_b]), dtype=np.float64)
    faces = np.asfortranarray(np.vstack([triangles_a, np.asarray(triangles_b) + len(points_a)]), dtype=np.int32)
    mesh = ipctk.CollisionMesh(vertices, np.asfortranarray(ipctk.edges(faces)), faces)
    mesh.can_collide = ipctk.make_vertex_patches_filter(
        np.concatenate([np.zeros(len(points_a), dtype=np.int32), np.ones(len(points_b), dtype=np.int32)]))
    return bool(ipctk.has_intersections(mesh, vertices))


def advanced_contact(obj, pose, points: np.ndarray, steps: np.ndarray, clearance: np.ndarray,
                     bound: np.ndarray) -> np.ndarray:
    """A first-contact time ``bound`` (a lower bound per point of when points + t steps comes
    within ``clearance`` of ``obj``) pushed towards the true one by conservative advancement: the
    signed distance changes no faster than the point moves, so from a time t at which the point
    is g away the clearance is not reached before t + (g - clearance) / |step|. Each round is one
    distance query of the points still short of t = 1; ADVANCE_ROUNDS of them. A node sliding
    along a triangle surface keeps its distance, which a bound from planes and tangents (a
    triangle mesh's ``first_contact``) does not see: measured on the teeth, bounds of 0.2-0.3 for
    sliding lining nodes that never came within the clearance over the whole step."""
    t = np.minimum(bound, 1.0)
    speed = np.linalg.norm(steps, axis=1)
    pending = np.flatnonzero((t < 1.0) & (speed > 0.0))
    for _ in range(ADVANCE_ROUNDS):
        if not pending.size:
            break
        # A lower bound of the gap (the cut-off) advances less, never too far.
        remaining = (1.0 - t[pending]) * speed[pending] + clearance[pending]
        gap = obj.gaps(points[pending] + t[pending, None] * steps[pending], pose, within=remaining)[0]
        gain = (gap - clearance[pending]) / speed[pending]
        t[pending] = np.minimum(t[pending] + np.maximum(gain, 0.0), 1.0)
        # Done: at t = 1, or stuck at the clearance (a true contact within the step).
        pending = pending[(t[pending] < 1.0) & (gain > ADVANCE_STALL * t[pending])]
    return np.where(t >= 1.0, np.maximum(bound, 1.0), t)


@dataclass(frozen=True)
class Sphere:
    """A rigid ball of ``radius`` (mm), centred at the origin of its frame."""

    radius: float

    def __post_init__(self):
        if not self.radius > 0.0:
            raise ValueError(f"sphere radius {self.radius:g} mm: give a positive radius")

    def gaps(self, points: np.ndarray, pose: AffineMap, within=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Signed gap of each point to the surface, the outward unit normal there, and 1 / the
        distance to the centre (the gap's Hessian is (I - n n^T) times that). Exact for every
        point: ``within`` (the cut-off of ``TriangleMesh.gaps``) is ignored."""
        offset = points - pose.translation
        distance = np.linalg.norm(offset, axis=1)
        inverse = 1.0 / np.maximum(distance, 1e-300)
        return distance - self.radius, offset * inverse[:, None], inverse

    def first_contact(self, points: np.ndarray, steps: np.ndarray, pose: AffineMap,
                      clearance: np.ndarray) -> np.ndarray:
        """For each point, the smallest t > 0 at which points + t steps comes within ``clearance``
        of the sphere (inf if never)."""
        q = points - pose.translation
        r = self.radius + clearance
        a = np.einsum("ij,ij->i", steps, steps)
        b = np.einsum("ij,ij->i", q, steps)
        c = np.einsum("ij,ij->i", q, q) - r * r
        discriminant = b * b - a * c
        with np.errstate(divide="ignore", invalid="ignore"):
            # The smaller root of a t^2 + 2 b t + c = 0, written to avoid cancellation.
            t = c / (-b + np.sqrt(np.maximum(discriminant, 0.0)))
        hits = (discriminant >= 0.0) & (b < 0.0) & (a > 0.0)
        return np.where(hits & (t > 0.0), t, np.inf)

    def describe(self) -> str:
        return f"sphere of radius {self.radius:g} mm"

    def surface(self, refinements: int = 2) -> tuple[np.ndarray, np.ndarray]:
        """Points and triangles of an icosphere on the sphere (in its frame), for output."""
        t = (1.0 + 5.0 ** 0.5) / 2.0
        points = np.array([[-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0], [0, -1, t], [0, 1, t],
                           [0, -1, -t], [0, 1, -t], [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1]], dtype=float)
        triangles = np.array([[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4],
                              [11, 10, 2], [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8],
                              [3, 8, 9], [4, 9, 5], [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1]])
        for _ in range(refinements):
            edges = np.sort(np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]]), axis=1)
            unique, index = np.unique(edges, axis=0, return_inverse=True)
            mid = len(points) + index.reshape(3, -1)
            points = np.vstack([points, 0.5 * (points[unique[:, 0]] + points[unique[:, 1]])])
            a, b, c = triangles.T
            triangles = np.vstack([np.c_[a, mid[0], mid[2]], np.c_[b, mid[1], mid[0]],
                                   np.c_[c, mid[2], mid[1]], np.c_[mid[0], mid[1], mid[2]]])
        points *= self.radius / np.linalg.norm(points, axis=1)[:, None]
        return points, triangles


@dataclass(frozen=True)
class HalfSpace:
    """The rigid half-space below the plane through the origin of its frame with outward unit
    ``normal`` (in its frame): n . x <= 0 is solid."""

    normal: tuple = (0.0, 0.0, 1.0)

    def world_normal(self, pose: AffineMap) -> np.ndarray:
        n = pose.matrix @ np.asarray(self.normal, dtype=float)
        return n / np.linalg.norm(n)

    def gaps(self, points: np.ndarray, pose: AffineMap, within=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Signed gap, normal and zero curvature of each point; exact, ``within`` is ignored."""
        n = self.world_normal(pose)
        gap = (points - pose.translation) @ n
        return gap, np.broadcast_to(n, points.shape), np.zeros(len(points))

    def first_contact(self, points, steps, pose, clearance) -> np.ndarray:
        n = self.world_normal(pose)
        approach = -(steps @ n)
        with np.errstate(divide="ignore", invalid="ignore"):
            t = ((points - pose.translation) @ n - clearance) / approach
        return np.where(approach > 0.0, np.maximum(t, 0.0), np.inf)

    def describe(self) -> str:
        return f"half-space with normal {tuple(float(v) for v in self.normal)}"


def read_path(path) -> list[AffineMap]:
    """Poses of an object over time from a text file: one line per pose with the x y z (mm, model
    frame) of the object's origin, separated by spaces or commas; ``#`` starts a comment. One clear
    error naming the file and line for anything else."""
    poses = []
    try:
        lines = open(path).read().splitlines()
    except OSError as error:
        raise ValueError(f"{path}: cannot read the object's path ({error.strerror})") from None
    for number, line in enumerate(lines, start=1):
        text = line.split("#", 1)[0].replace(",", " ").split()
        if not text:
            continue
        try:
            values = np.array([float(v) for v in text])
        except ValueError:
            values = np.array([np.nan])
        if values.shape != (3,) or not np.isfinite(values).all():
            raise ValueError(f"{path}, line {number}: expected the three coordinates x y z (mm) of a pose, "
                             f"got {line.strip()!r}")
        poses.append(AffineMap(np.eye(3), values))
    if not poses:
        raise ValueError(f"{path}: no poses (one line of x y z per pose)")
    return poses


@dataclass
class ContactSettings:
    """What the flesh may touch: rigid ``objects`` at their rest ``poses`` (identity if not given),
    the barrier's activation distance ``dhat`` (mm) and ``stiffness`` (kPa, about the contact
    pressure at g = dhat / 2), and the tagged boundary ``surface`` that touches them. With
    ``teeth``, the model's teeth (``FaceModel.teeth``, each moving with its bone frame) touch the
    facets tagged ``teeth_surface`` (the lining of the lips and cheeks) with the same stiffness and
    their own activation distance ``teeth_dhat`` (mm). With ``faces`` the spheres keep the
    surface's triangles out, not only its nodes (``face_contact.FaceContactPotential``), and the
    triangle meshes keep their vertices and edges off the surface (``object_features.ObjectFeatureContact``)."""

    objects: tuple = ()
    poses: tuple = ()
    dhat: float = 0.05
    stiffness: float = 10.0
    surface: str = "skin"
    where: str = "the contact settings"  # named in error messages (a file, an option)
    teeth: bool = False
    teeth_surface: str = "oral"
    teeth_dhat: float = TEETH_DHAT
    faces: bool = True

    def rest_poses(self) -> tuple:
        return tuple(self.poses) if self.poses else tuple(AffineMap() for _ in self.objects)


class ContactSurface:
    """The nodes of a set of boundary facets, gathered on every rank in rest-coordinate order,
    with their flat triangles and lumped rest areas, and the nodes each rank owns."""

    def __init__(self, space: fem.FunctionSpace, facets: np.ndarray):
        mesh = space.mesh
        self.comm = mesh.comm
        tdim = mesh.topology.dim
        mesh.topology.create_connectivity(tdim - 1, tdim)
        mesh.topology.create_connectivity(tdim, tdim - 1)
        facet_cells, cell_facets = mesh.topology.connectivity(tdim - 1, tdim), mesh.topology.connectivity(tdim, tdim - 1)
        layout = space.dofmap.dof_layout
        vertex_dof = [layout.entity_dofs(0, v)[0] for v in range(4)]
        edge_dof = {frozenset(e): layout.entity_dofs(1, i)[0] for i, e in enumerate(_TET_EDGES)
                    if len(layout.entity_dofs(1, i))}
        index_map = space.dofmap.index_map
        local_triangles = []
        for facet in np.asarray(facets, dtype=np.int32):
            cell = facet_cells.links(facet)[0]
            opposite = int(np.flatnonzero(cell_facets.links(cell) == facet)[0])
            blocks = space.dofmap.cell_dofs(cell)
            a, b, c = (v for v in range(4) if v != opposite)
            if edge_dof:  # P2: four flat triangles through the edge midpoints
                ab, bc, ca = (edge_dof[frozenset(e)] for e in ((a, b), (b, c), (c, a)))
                A, B, C = vertex_dof[a], vertex_dof[b], vertex_dof[c]
                for tri in ((A, ab, ca), (B, bc, ab), (C, ca, bc), (ab, bc, ca)):
                    local_triangles.append(blocks[list(tri)])
            else:
                local_triangles.append(blocks[[vertex_dof[a], vertex_dof[b], vertex_dof[c]]])
        local_triangles = np.array(local_triangles, dtype=np.int32).reshape(-1, 3)
        global_triangles = index_map.local_to_global(local_triangles.reshape(-1)).reshape(-1, 3)
        coordinates = space.tabulate_dof_coordinates()[:, :3]
        # A node of a facet may be owned by a rank that does not hold the facet (a ghost on the
        # facet's rank): every rank contributes the nodes it owns among all ranks' facets.
        surface_global = np.unique(np.concatenate(self.comm.allgather(np.unique(global_triangles))))
        first, last = index_map.local_range
        owned_global = surface_global[(surface_global >= first) & (surface_global < last)]
        owned = (owned_global - first).astype(np.int32)

        # Every rank: all triangles and all owned nodes with their rest coordinates.
        all_triangles = np.concatenate(self.comm.allgather(global_triangles))
        node_global = np.concatenate(self.comm.allgather(owned_global))
        node_rest = np.concatenate(self.comm.allgather(coordinates[owned]))
        order = np.lexsort(node_rest.T[::-1])
        node_global, self.rest = node_global[order], node_rest[order]
        lookup = np.argsort(node_global)
        def surface_index(g):
            return lookup[np.searchsorted(node_global[lookup], g)]
        triangles = surface_index(all_triangles)
        # A facet seen by two ranks (a ghost) is counted once.
        self.triangles = np.unique(np.sort(triangles, axis=1), axis=0)
        edges1 = self.rest[self.triangles[:, 1]] - self.rest[self.triangles[:, 0]]
        edges2 = self.rest[self.triangles[:, 2]] - self.rest[self.triangles[:, 0]]
        area = 0.5 * np.linalg.norm(np.cross(edges1, edges2), axis=1)
        self.areas = np.bincount(self.triangles.reshape(-1), np.repeat(area / 3.0, 3), minlength=len(self.rest))
        self.num_nodes = len(self.rest)
        self.owned_blocks = owned  # local block indices of this rank's nodes ...
        self.owned_nodes = surface_index(owned_global)  # ... and their surface indices
        self._counts = np.array(self.comm.allgather(3 * len(owned)))
        self._gathered_nodes = np.concatenate(self.comm.allgather(self.owned_nodes))
        # Owned and ghost nodes (a Dirichlet condition on nodes must hold on every rank that sees them).
        self.local_blocks = np.unique(local_triangles)
        self.local_nodes = surface_index(index_map.local_to_global(self.local_blocks))

    def free(self, constrained: np.ndarray, local_size: int) -> np.ndarray:
        """(num_nodes, 3): whether each dof of the surface's nodes is free of the Dirichlet
        conditions ``constrained`` (owned local dofs, of any rank; collective)."""
        flags = np.zeros(local_size)
        flags[constrained] = 1.0
        return self.gather(flags) < 0.5

    def flagged(self, blocks: np.ndarray) -> np.ndarray:
        """(num_nodes,) whether each node is one of the local dof blocks ``blocks`` (owned or
        ghost) of some rank (collective)."""
        mine = np.zeros(self.num_nodes)
        mine[self.local_nodes[np.isin(self.local_blocks, blocks)]] = 1.0
        self.comm.Allreduce(MPI.IN_PLACE, mine, op=MPI.MAX)
        return mine > 0.0

    def pushed_blocks(self, forces: np.ndarray) -> np.ndarray:
        """Local blocks of this rank's nodes whose (num_nodes, 3) ``forces`` are not zero."""
        return self.owned_blocks[np.any(forces[self.owned_nodes] != 0.0, axis=1)]

    def local_blocks_of(self, chosen: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The local dof blocks on this rank (owned, or ghosts of its facets; each once) of the
        surface nodes flagged in ``chosen`` (num_nodes,), and those nodes' surface indices. (A node
        may be owned by a rank that holds none of its facets: ``local_blocks`` alone misses it
        there.)"""
        blocks, first = np.unique(np.concatenate([self.owned_blocks, self.local_blocks]), return_index=True)
        nodes = np.concatenate([self.owned_nodes, self.local_nodes])[first]
        keep = chosen[nodes]
        return blocks[keep], nodes[keep]

    def placed(self, displacement: np.ndarray, positions: np.ndarray, nodes: np.ndarray) -> np.ndarray:
        """A copy of the local dof array ``displacement`` (ghosts included) with the surface nodes
        ``nodes`` (surface indices, the same on every rank) put at ``positions`` (num_nodes, 3):
        on every rank that owns them or sees them as ghosts."""
        out = displacement.copy()
        chosen = np.zeros(self.num_nodes, dtype=bool)
        chosen[nodes] = True
        blocks, surface_nodes = self.local_blocks_of(chosen)
        out.reshape(-1, 3)[blocks] = (positions - self.rest)[surface_nodes]
        return out

    def gather(self, values: np.ndarray) -> np.ndarray:
        """(num_nodes, 3) of a blocked dof array (owned part at least), from every rank."""
        mine = np.ascontiguousarray(values.reshape(-1, 3)[self.owned_blocks]).reshape(-1)
        received = np.empty(int(self._counts.sum()))
        self.comm.Allgatherv(mine, [received, self._counts])
        out = np.empty((self.num_nodes, 3))
        out[self._gathered_nodes] = received.reshape(-1, 3)
        return out


class ContactPotential:
    """The barrier energy of a contact surface against rigid objects at given poses, as an extra
    energy term of the equilibrium solver (see the module docstring). Poses: ``set_poses``."""

    # A Newton solve whose residual falls slowly with the residual on this surface's nodes relaxes
    # them instead of refactorising (QuasistaticSolver, ``_relaxes_instead``): the lining settling
    # on the teeth (docs/performance.md, "Settling on the teeth").
    relax_on_slow_fall = True
    # Newton takes the projected blocks until it is near the solution, then the exact ones: projected
    # throughout, the lining pressed on the teeth converged linearly (the residual falling about 4x
    # per iteration with fresh factors).
    exact_near_solution = True

    def __init__(self, space: fem.FunctionSpace, facets: np.ndarray, settings: ContactSettings, label: str = "objects"):
        if not settings.dhat > 0.0 or not settings.stiffness > 0.0:
            raise ValueError(f"{settings.where}: dhat and the stiffness must be positive "
                             f"(got {settings.dhat:g} mm, {settings.stiffness:g} kPa)")
        self.settings = settings
        self.label = label  # names the term in the Newton trace
        self.space = space
        self.objects = tuple(settings.objects)
        self.dhat, self.stiffness = settings.dhat, settings.stiffness
        self.surface = ContactSurface(space, facets)
        if self.surface.comm.allreduce(len(facets), op=MPI.SUM) == 0:
            raise ValueError(f"{settings.where}: the contact surface {settings.surface!r} has no facets")
        self.poses = settings.rest_poses()
        self.ignored = np.zeros(self.surface.num_nodes, dtype=bool)
        self.node_barrier = tuple(True for _ in self.objects)  # per object: its barrier acts on the nodes
        self._last_terms = None  # (positions, poses, ignored, terms) of the last ``_terms``
        if len(self.poses) != len(self.objects):
            raise ValueError(f"{settings.where}: {len(self.objects)} objects but {len(self.poses)} poses")

    def ignore(self, blocks: np.ndarray) -> None:
        """Leave the nodes of these local dof blocks out of the contact (collective): nodes held by a
        bone, which the barrier cannot push and whose prescribed path it must not cut short."""
        self.ignored = self.surface.flagged(np.asarray(blocks))

    def set_poses(self, poses) -> None:
        poses = tuple(poses)
        if len(poses) != len(self.objects):
            raise ValueError(f"{len(poses)} object poses for {len(self.objects)} objects")
        self.poses = poses

    # -- geometry ----------------------------------------------------------------------------
    def positions(self, displacement: np.ndarray) -> np.ndarray:
        """Current positions of all contact nodes (every rank)."""
        return self.surface.rest + self.surface.gather(displacement)

    def gaps(self, displacement: np.ndarray, poses=None, within=np.inf) -> np.ndarray:
        """(objects, nodes) signed gaps; negative inside an object. With ``within`` (mm), exact
        only for the nodes closer than that, a lower bound above it for the others (the objects'
        cut-off)."""
        x = self.positions(displacement)
        poses = self.poses if poses is None else poses
        gaps = np.array([obj.gaps(x, pose, within=within)[0]
                         for obj, pose in zip(self.objects, poses)]).reshape(-1, len(x))
        gaps[:, self.ignored] = np.inf
        return gaps

    def min_gap(self, displacement: np.ndarray) -> float:
        """Smallest gap of any node to any object (mm; negative: penetration)."""
        gaps = self.gaps(displacement)
        return float(gaps.min()) if gaps.size else np.inf

    def check_clear(self, displacement: np.ndarray, margin: float = 0.0) -> None:
        """A clear error if an object at its pose overlaps the surface or touches it (gap <= 0),
        or comes within ``margin`` of it."""
        for obj, pose, gap in zip(self.objects, self.poses, self.gaps(displacement)):
            if gap.min() <= 0.0:
                raise ValueError(f"{self.settings.where}: the {obj.describe()} at {pose.translation.round(3).tolist()} "
                                 f"starts inside the {self.settings.surface} ({int((gap <= 0).sum())} "
                                 f"nodes, deepest {-gap.min():.3g} mm): place it outside")
            if gap.min() <= margin:
                raise ValueError(f"{self.settings.where}: the {obj.describe()} comes within {gap.min():.3g} mm of "
                                 f"{int((gap <= margin).sum())} nodes of the {self.settings.surface} at rest; it must "
                                 f"leave more than {margin:g} mm")
        self._check_outside_flesh(displacement)

    def _check_outside_flesh(self, displacement: np.ndarray) -> None:
        """In the rest configuration (``displacement`` zero on every rank; a deformed state is not
        checked): a clear error if a point of an object (a triangle mesh's vertex, a sphere's
        centre) lies in a cell of the flesh, or a triangle mesh's surface crosses the contact
        surface's triangles. Either is an object inside the face with no surface node inside it:
        smaller than the surface's triangles, or through them between their nodes (an instrument's
        tip), which the barrier of the nodes would take as a start outside."""
        comm = self.surface.comm
        if comm.allreduce(bool(np.any(displacement != 0.0)), op=MPI.LOR):
            return
        mesh = self.space.mesh
        tdim = mesh.topology.dim
        owned_cells = mesh.topology.index_map(tdim).size_local
        tree = geometry.BoundingBoxTree(mesh, tdim)
        for obj, pose in zip(self.objects, self.poses):
            if isinstance(obj, TriangleMesh):
                points = np.ascontiguousarray(pose.apply(obj.points), dtype=np.float64)
            elif isinstance(obj, Sphere):
                points = pose.translation.reshape(1, 3).astype(np.float64)
            else:
                continue  # a half-space holds every point beyond its plane: the nodes' gaps decide
            cells = geometry.compute_colliding_cells(mesh, geometry.compute_collisions(tree, points), points)
            mine = np.array([(cells.links(i) < owned_cells).any() for i in range(len(points))], dtype=np.int32)
            anywhere = np.zeros_like(mine)
            comm.Allreduce(mine, anywhere, op=MPI.MAX)
            inside = np.flatnonzero(anywhere)
            where = f"{self.settings.where}: the {obj.describe()} at {pose.translation.round(3).tolist()}"
            if inside.size:
                what = "its centre lies" if len(points) == 1 else f"{inside.size} of its {len(points)} vertices lie"
                raise ValueError(f"{where}: {what} inside the flesh (e.g. {points[inside[0]].round(3).tolist()}) "
                                 f"though no node of the {self.settings.surface} is inside it: place it outside")
            if isinstance(obj, TriangleMesh) and surfaces_cross(self.positions(displacement), self.surface.triangles,
                                                                points, obj.triangles):
                raise ValueError(f"{where} crosses the triangles of the {self.settings.surface} between their "
                                 "nodes (no node inside it): place it outside")

    def contact_nodes(self, displacement: np.ndarray) -> int:
        """Number of (object, node) pairs within dhat."""
        return int((self.gaps(displacement) < self.dhat).sum())

    # -- the solver's energy-term interface ---------------------------------------------------
    def _terms(self, displacement: np.ndarray) -> list:
        """Per object: the barrier's terms, each of a node (a node may have several), with its
        weight (the node's area, times the term's sign), the node's position, the gap, its normal
        and its Hessian (3 x 3 d2g/dx2). An analytic object has one term per node within dhat, a
        triangle mesh one per (node, triangle), (node, edge) and (node, vertex) pair within dhat
        (``TriangleMesh.barrier_terms``, docs/contact.md "A smooth barrier"). The gradient, the
        Hessian, Newton's correction and the pose rates of one state share them: the same
        positions, poses and ignored nodes as the last call's reuse its result, and a state that
        moved only some nodes (the relaxation's local steps) recomputes only theirs (a node's terms
        depend on its position alone; each node's come whole from one computation, in the same
        order, so its force and Hessian block are those of a fresh call to the bit)."""
        x = self.positions(displacement)
        last = self._last_terms
        if last is None or last[1] is not self.poses or last[2] is not self.ignored:
            terms = self._node_terms(x, np.arange(len(x)))
        else:
            moved = np.flatnonzero((last[0] != x).any(axis=1))
            if not moved.size:
                return last[3]
            terms = self._node_terms(x, moved)
            if moved.size < len(x):
                terms = [tuple(np.concatenate([a[~np.isin(old[0], moved)], b]) for a, b in zip(old, new))
                         for old, new in zip(last[3], terms)]
        self._last_terms = (x, self.poses, self.ignored, terms)
        return terms

    def _node_terms(self, x: np.ndarray, nodes: np.ndarray) -> list:
        """``_terms`` of the contact nodes ``nodes`` (indices into x, the positions of all)."""
        terms = []
        points = x[nodes]
        for obj, pose, by_nodes in zip(self.objects, self.poses, self.node_barrier):
            if not by_nodes:  # a subclass's barrier takes the object
                terms.append((np.zeros(0, dtype=int), np.zeros(0), np.zeros((0, 3)), np.zeros(0), np.zeros((0, 3)),
                              np.zeros((0, 3, 3))))
                continue
            if isinstance(obj, TriangleMesh):
                which, sign, gap, normal, gap_hessian = obj.barrier_terms(points, pose, within=self.dhat)
                active = nodes[which]
                kept = ~self.ignored[active]
                active = active[kept]
                terms.append((active, sign[kept] * self.surface.areas[active], x[active], gap[kept], normal[kept],
                              gap_hessian[kept]))
                continue
            # Nodes surely beyond dhat get a lower bound of their gap (>= dhat): inactive either way.
            gap, normal, curvature = obj.gaps(points, pose, within=self.dhat)
            near = np.flatnonzero((gap < self.dhat) & ~self.ignored[nodes])
            active = nodes[near]
            normal, curvature = normal[near], curvature[near]
            # d2g/dx2 = c (I - n n^T) for a sphere (a scalar curvature c per node), given whole by
            # a triangle mesh.
            gap_hessian = (curvature if curvature.ndim == 3 else
                           curvature[:, None, None] * (np.eye(3) - normal[:, :, None] * normal[:, None, :]))
            terms.append((active, self.surface.areas[active], x[active], gap[near], normal, gap_hessian))
        return terms

    def energy(self, x: PETSc.Vec) -> float:
        """E_c at the displacement ``x`` (the same on every rank; inf if a node is inside)."""
        scale = self.stiffness / self.dhat
        return float(sum(scale * (weight * barrier(gap, self.dhat)).sum()
                         for _, weight, _, gap, _, _ in self._terms(x.array_r)))

    def nodal_forces(self, displacement: np.ndarray) -> np.ndarray:
        """(nodes, 3) dE_c/dx at every contact node (the force on the objects; NaN if inside)."""
        gradient = np.zeros((self.surface.num_nodes, 3))
        scale = self.stiffness / self.dhat
        for active, weight, _, gap, normal, _ in self._terms(displacement):
            first, _ = barrier_derivatives(gap, self.dhat)
            np.add.at(gradient, active, (scale * weight * first)[:, None] * normal)
        return gradient

    def add_gradient(self, x: PETSc.Vec, b: PETSc.Vec) -> None:
        """b += dE_c/du on this rank's dofs."""
        gradient = self.nodal_forces(x.array_r)[self.surface.owned_nodes]
        values = b.array.reshape(-1, 3)
        values[self.surface.owned_blocks] += gradient

    def add_hessian(self, x: PETSc.Vec, A: PETSc.Mat, constrained: np.ndarray) -> None:
        """A += d2E_c/du2 on this rank's rows (assembled); the rows and columns of ``constrained``
        (owned local dofs, a Dirichlet condition's) are left alone."""
        self._add_blocks(self._hessian_blocks(x), x, A, constrained)

    def add_newton_correction(self, x: PETSc.Vec, A: PETSc.Mat, constrained: np.ndarray) -> bool:
        """A += the change that makes ``add_hessian``'s blocks those of Newton's tangent away from
        the solution (``exact_near_solution``): every node's 3 x 3 block projected onto the positive
        semidefinite ones (its negative eigenvalues set to 0; IPC's practice). Next to an edge or a
        vertex of a triangle mesh the exact block
        b'' n n^T + b' d2g/dx2 has the negative part b' (I - n n^T - e e^T) / d (b' < 0), which
        grows as the gap closes (down to -1.1e4 mN/mm while the lips settled on the 5K face's
        teeth): the projected tangent keeps every correction a descent direction. Returns whether
        a block changed (the same on every rank; A is untouched otherwise)."""
        blocks = self._hessian_blocks(x)
        # A node at or inside an object has no finite block (nor residual): the tangent keeps its
        # NaN for Newton to fail on, rather than numpy raising from within PETSc's callback.
        values, vectors = np.linalg.eigh(np.where(np.isfinite(blocks), blocks, 0.0))
        # Blocks over a face (b'' n n^T) have two zero eigenvalues that come out as round-off.
        negative = values.min(axis=1) < -ROUND_OFF * np.abs(values).max(axis=1)
        if not negative.any():
            return False
        change = np.zeros_like(blocks)
        change[negative] = np.einsum("nij,nj,nkj->nik", vectors[negative], np.maximum(-values[negative], 0.0),
                                     vectors[negative])
        self._add_blocks(change, x, A, constrained)
        return True

    def _hessian_blocks(self, x: PETSc.Vec) -> np.ndarray:
        """(nodes, 3, 3): d2E_c/dx2 of every contact node (the same on every rank)."""
        blocks = np.zeros((self.surface.num_nodes, 3, 3))
        scale = self.stiffness / self.dhat
        for active, weight, _, gap, normal, gap_hessian in self._terms(x.array_r):
            first, second = barrier_derivatives(gap, self.dhat)
            # d2b/dx2 = b'' n n^T + b' d2g/dx2
            local = second[:, None, None] * normal[:, :, None] * normal[:, None, :] + first[:, None, None] * gap_hessian
            np.add.at(blocks, active, scale * weight[:, None, None] * local)
        return blocks

    def _add_blocks(self, blocks: np.ndarray, x: PETSc.Vec, A: PETSc.Mat, constrained: np.ndarray) -> None:
        """A += the (nodes, 3, 3) ``blocks`` on the diagonal, this rank's rows, the rows and columns
        of ``constrained`` left alone; A assembled."""
        owned = self.surface.owned_nodes
        touched = np.flatnonzero(np.abs(blocks[owned]).sum(axis=(1, 2)) > 0.0)
        free = np.ones(x.getLocalSize(), dtype=bool)
        free[constrained] = False
        first_row = x.getOwnershipRange()[0]
        for k in touched:
            local_dofs = 3 * self.surface.owned_blocks[k] + np.arange(3)
            keep = free[local_dofs]
            if keep.any():
                rows = (first_row + local_dofs[keep]).astype(PETSc.IntType)
                A.setValues(rows, rows, blocks[owned[k]][np.ix_(keep, keep)], addv=PETSc.InsertMode.ADD_VALUES)
        A.assemble()

    def step_fraction(self, x: PETSc.Vec, step: PETSc.Vec, largest: float) -> float:
        """Largest t in (0, 1] such that no point of x - s t largest step, s in [0, 1], brings a
        node closer to an object than (1 - CCD_KEEP) of its gap now."""
        return self.admissible_fraction(x.array_r, x.array_r - largest * step.array_r)

    def admissible_fraction(self, start: np.ndarray, end: np.ndarray) -> float:
        """The same bound for the straight path from the displacement ``start`` to ``end`` (dof
        arrays, owned part read), the objects at their present poses; the same on every rank."""
        return self.relative_fraction(start, end, self.poses)

    def relative_fraction(self, start: np.ndarray, end: np.ndarray, end_poses) -> float:
        """``admissible_fraction`` of a path on which the objects move too, from their present poses
        to ``end_poses`` (the teeth with their bones along a Gauss-Newton prediction): each node's
        path relative to each object, straight in the object's frame from its place at the start
        to its place at the end. Checked against objects standing still, the lining that moves
        with the jaw along the teeth ran into their old place: predictions cut to 0.2-0.3 of
        their length on the 20K face's jaw motions, with the lips apart."""
        points, ends = self.positions(start), self.positions(end)
        kept = ~self.ignored
        if all(end_pose is pose for pose, end_pose in zip(self.poses, end_poses)):
            # A node that stays where it is keeps its gaps to objects that stay too: the relaxation's
            # local steps move a few hundred of the lining's 2 204 nodes on the 404K face.
            kept &= (points != ends).any(axis=1)
        times = self._first_contacts(points[kept], ends[kept], end_poses)
        return min([1.0] + [float(t.min(initial=np.inf)) for *_, t in times])

    def _first_contacts(self, points: np.ndarray, ends: np.ndarray, end_poses):
        """Per object: the object, its present pose, the map from the frame of its pose in
        ``end_poses`` to that of its present one, the moves of ``points`` (world, at the start) to
        ``ends`` (at the end) relative to the object, their clearances ((1 - CCD_KEEP) of their
        gaps at the start) and the first times they come that close (1 or more: not on the way)."""
        for obj, pose, end_pose in zip(self.objects, self.poses, end_poses):
            to_start = pose.compose(end_pose.inverse())
            moves = (ends if end_pose is pose else to_start.apply(ends)) - points
            # A node farther than its move / CCD_KEEP cannot lose CCD_KEEP of its gap: a lower bound
            # of its gap will do. Its clearance is then smaller than (1 - CCD_KEEP) gap but still
            # positive, a collision-free bound, and its first contact lies beyond t = 1 with either
            # clearance.
            reach = np.linalg.norm(moves, axis=1) / CCD_KEEP
            clearance = (1.0 - CCD_KEEP) * obj.gaps(points, pose, within=reach)[0]
            yield obj, pose, to_start, moves, clearance, advanced_contact(
                obj, pose, points, moves, clearance, obj.first_contact(points, moves, pose, clearance))

    def projected_end(self, start: np.ndarray, end: np.ndarray, end_poses, limit: float) -> np.ndarray | None:
        """``end`` (a displacement, the objects then at ``end_poses``) with every node whose straight
        path relative to an object (as in ``relative_fraction``) comes closer to it than
        (1 - CCD_KEEP) of its gap at ``start`` (the objects at their present poses) stopped at the
        object's tangent plane where it first came that close, free to slide along it: its
        place at the end moved along that plane's normal until it lies on it (local dof array,
        ghosts included; the same on every rank). None if a node would move farther than
        ``limit`` (mm), or still ends closer than half that clearance (a curved surface), to that
        object or another."""
        kept = np.flatnonzero(~self.ignored)
        x = self.positions(end)
        x0, x1 = self.positions(start)[kept], x[kept]
        clearances = []
        moved = np.zeros(len(kept), dtype=bool)
        # Each object sees the nodes as the ones before it left them (their ends moved out of it).
        for obj, pose, to_start, moves, clearance, t in self._first_contacts(x0, x1, end_poses):
            clearances.append(clearance)
            hit = np.flatnonzero(t < 1.0)
            if not hit.size:
                continue
            contact = x0[hit] + t[hit, None] * moves[hit]
            normal = obj.gaps(contact, pose, within=clearance[hit] + self.dhat)[1]
            ends = x0[hit] + moves[hit]
            push = np.maximum(np.einsum("ij,ij->i", contact - ends, normal), 0.0)
            if push.max(initial=0.0) > limit:
                log.debug("lining not projected out of an object: %d nodes, one by %.3g mm (limit %g)", hit.size,
                          push.max(), limit)
                return None
            x1[hit] = to_start.inverse().apply(ends + push[:, None] * normal)
            moved[hit] = True
        if not moved.any():
            return end.copy()
        chosen = np.flatnonzero(moved)
        for obj, end_pose, clearance in zip(self.objects, end_poses, clearances):
            # (Within dhat only, a farther node's gap is a lower bound, dhat: not to be compared with
            # a clearance beyond 2 dhat.)
            gap = obj.gaps(x1[chosen], end_pose, within=max(self.dhat, clearance[chosen].max()))[0]
            if (gap < 0.5 * clearance[chosen]).any():
                log.debug("lining not projected out of an object: a projected node still ends too close")
                return None
        x[kept[chosen]] = x1[chosen]
        return self.surface.placed(end, x, kept[chosen])

    # -- moving the objects ------------------------------------------------------------------
    def closes_in(self, displacement: np.ndarray, old_poses, new_poses) -> bool:
        """Whether moving the objects from ``old_poses`` to ``new_poses`` takes more of some node's
        gap than a collision-free step may (``CCD_KEEP``) and leaves it closer than PUSH_GAP dhat (a
        node inside counts): a start that the barrier alone cannot take, which ``move_to`` makes.
        The same on every rank."""
        x = self.positions(displacement)
        near = PUSH_GAP * self.dhat
        for obj, old, new in zip(self.objects, old_poses, new_poses):
            # Only the nodes the new pose leaves closer than that can count: their gaps now are
            # needed, no other node's (every node's exact gaps at both poses took 0.23 s on the 404K
            # face, this 0.02 s).
            moved = obj.gaps(x, new, within=near)[0]
            moved[self.ignored] = np.inf
            close = np.flatnonzero(moved < near)
            if close.size and closing_in(obj.gaps(x[close], old)[0], moved[close], self.dhat):
                return True
        return False

    def push_out(self, displacement: np.ndarray, poses) -> tuple[np.ndarray, np.ndarray]:
        """The displacement with every node that the objects at ``poses`` would leave closer than
        PUSH_GAP * dhat moved out along the object's normal to that gap (a start that overlaps no
        object; local dof array, owned part changed, ghosts need an update), and the nodes to hold
        while the flesh follows: those and every node within the objects' move of them (the flesh
        a dent displaces bulges up around it, into the object's way)."""
        out = displacement.copy()
        x = self.positions(displacement)
        held = np.zeros(len(x), dtype=bool)
        target = PUSH_GAP * self.dhat
        for obj, old, new in zip(self.objects, self.poses, poses):
            reach = target + np.linalg.norm(new.compose(old.inverse()).apply(x) - x, axis=1).max(initial=0.0)
            gap, normal, _ = obj.gaps(x, new, within=reach)
            gap[self.ignored] = np.inf
            close = gap < target
            x[close] += (target - gap[close])[:, None] * normal[close]
            held |= gap < reach
        moved = x - self.surface.rest
        values = out.reshape(-1, 3)
        values[self.surface.owned_blocks] = moved[self.surface.owned_nodes]
        return out, np.flatnonzero(held)

    def carry(self, poses, solver, reach: float, free_blocks: np.ndarray | None = None,
              mend: Callable[[np.ndarray, np.ndarray], np.ndarray | None] | None = None) -> int:
        """Put the objects at ``poses``, carrying along the surface nodes that rest on them: every
        node within ``reach`` (mm) of an object at its present pose, and every farther one that the
        object at its new pose would leave closer than PUSH_GAP * dhat (the teeth closing onto the
        lining in front of them), is held, for one Newton solve of ``solver``, where the object's
        move from its present pose to its new one takes it, and left out of the barrier meanwhile.
        The held nodes keep their gaps to the object they rest on, the flesh follows them and the
        bones (whose Dirichlet values the solve reaches as well), and the solve that follows
        releases them. A jaw opening with the lining left behind would otherwise drag the lining
        along the teeth in collision-limited steps that also cut the bones' motion short; a node
        the teeth overrun would be inside them. The nodes of the local dof blocks ``free_blocks``
        (of any rank) are never held: the lips' nodes, which the lips' barrier must keep out of
        the other lip (moved rigidly with the lower teeth, the lower lip's lining went through the
        upper lip). Those of them that an object's new pose would leave closer than the gap they
        have now (or PUSH_GAP * dhat) start the solve moved out along its normal to that gap, as
        ``mend(start, end)`` (dof arrays) makes that move admissible (the end it returns, e.g. with
        the other lip pushed along; None: not moved) and it flattens no cell: left where they were,
        lip nodes inside the teeth gave the solve no finite residual (the lips' second closure,
        docs/performance.md).
        Returns the Newton iterations it took."""
        u = solver.unknown
        gaps = self.gaps(u.x.array, within=reach)
        # A node farther than ``reach`` that an object's new pose overruns goes with that object.
        overrun = self.gaps(u.x.array, poses, within=PUSH_GAP * self.dhat) < PUSH_GAP * self.dhat
        carried = (gaps < reach) | overrun
        if free_blocks is not None:
            free = self.surface.flagged(free_blocks)
            carried &= ~free
            overrun_free = overrun & free
            if mend is not None and overrun_free.any():
                moved = self._mended(mend, u.x.array, self._kept_clear(u.x.array, overrun_free, gaps, poses), poses)
                if moved is not None and not _flattens(solver, u.x.array, moved):
                    u.x.array[:] = moved
                else:
                    log.debug("carry: %d free nodes that the new poses overrun not moved out (not admissible)",
                              int(overrun_free.any(axis=0).sum()))
        x = self.positions(u.x.array)
        gaps[~carried] = np.inf
        nearest, held = gaps.argmin(axis=0), carried.any(axis=0)
        target = x.copy()
        for k, (old, new) in enumerate(zip(self.poses, poses)):
            chosen = held & (nearest == k)
            target[chosen] = new.compose(old.inverse()).apply(x[chosen])
        self.set_poses(poses)
        solver.controls_changed()
        if not held.any():
            return 0
        values = fem.Function(u.function_space)
        values.x.array[:] = self.surface.placed(u.x.array, target, np.flatnonzero(held))
        condition = fem.dirichletbc(values, self.surface.local_blocks_of(held)[0])
        solver.bcs.append(condition)
        ignored = self.ignored
        self.ignored = ignored | held
        try:
            return solver.newton(lifting=True)[1]
        finally:
            self.ignored = ignored
            solver.bcs.remove(condition)
            solver.controls_changed()

    def _kept_clear(self, displacement: np.ndarray, nodes: np.ndarray, gaps: np.ndarray, poses) -> np.ndarray:
        """A copy of the dof array ``displacement`` (ghosts included) in which each node flagged in
        ``nodes`` (objects, nodes) that the object at its pose in ``poses`` leaves closer than its
        gap in ``gaps`` (capped at PUSH_GAP * dhat) is moved out along that object's normal to it."""
        x = self.positions(displacement)
        for k, (obj, pose) in enumerate(zip(self.objects, poses)):
            chosen = np.flatnonzero(nodes[k])
            if chosen.size:
                gap, normal, _ = obj.gaps(x[chosen], pose, within=PUSH_GAP * self.dhat)
                wanted = np.minimum(gaps[k, chosen], PUSH_GAP * self.dhat)
                x[chosen] += np.maximum(wanted - gap, 0.0)[:, None] * normal
        return self.surface.placed(displacement, x, np.flatnonzero(nodes.any(axis=0)))

    def _mended(self, mend, start: np.ndarray, end: np.ndarray, poses) -> np.ndarray | None:
        """``mend(start, end)``, unless it is None or puts a node it moves inside an object at
        ``poses`` (collective)."""
        mended = mend(start, end)
        if mended is None:
            return None
        moved = np.linalg.norm(self.positions(mended) - self.positions(start), axis=1) > UNMOVED
        return mended if (self.gaps(mended, poses, within=self.dhat)[:, moved] > 0.0).all() else None

    def move_to(self, poses, solver, mend: Callable[[np.ndarray, np.ndarray], np.ndarray | None] | None = None) -> int:
        """Put the objects at ``poses``, first pushing the surface out of them (``push_out``) and
        carrying the flesh along by a Newton solve of ``solver`` (whose unknown is the displacement)
        with the pushed nodes and their neighbourhood held where they are put: that spreads the dent smoothly into the
        flesh, as the lifting of a bone motion does, where Newton from the bare push-out crawls in
        collision-limited steps while the flesh pulls the dent back node by node. The state it
        leaves overlaps no object; the solve that follows releases the nodes. ``mend(start, end)``
        (dof arrays), if given, takes the push-out's move and returns it admissible (e.g. with the
        other lip pushed along out of the pushed lip's way; None: the push-out as it is). A
        push-out that would flatten a cell of ``solver``'s inversion guard is not put there: the
        solve starts where the surface was, the held nodes out of the barrier, and lifts them to
        their pushed places as it lifts a bone motion (the guard cuts its steps). Put there, the
        teeth's push-out of the lips' lining as the jaw closed on them left no finite residual,
        and the frame went on by continuation (the lips' second closure, docs/performance.md).
        Returns the Newton iterations it took."""
        u = solver.unknown
        before = u.x.array.copy()
        u.x.array[:], nodes = self.push_out(before, poses)
        u.x.scatter_forward()
        mended = self._mended(mend, before, u.x.array, poses) if mend is not None else None
        if mended is not None:
            u.x.array[:] = mended
        self.set_poses(poses)
        solver.controls_changed()
        if not nodes.size:
            return 0
        values = fem.Function(u.function_space)
        values.x.array[:] = u.x.array
        chosen = np.zeros(self.surface.num_nodes, dtype=bool)
        chosen[nodes] = True
        ignored = self.ignored
        lifted = _flattens(solver, before, values.x.array)
        if lifted:
            log.debug("push-out of %d nodes lifted into the flesh: put there, it flattens cells", len(nodes))
            u.x.array[:] = before
            self.ignored = ignored | chosen
        held = fem.dirichletbc(values, self.surface.local_blocks_of(chosen)[0])
        solver.bcs.append(held)
        try:
            return solver.newton(lifting=lifted)[1]
        finally:
            self.ignored = ignored
            solver.bcs.remove(held)
            solver.controls_changed()

    # -- derivatives in the objects' poses ------------------------------------------------------
    def pose_rate_forces(self, displacement: np.ndarray, rates) -> np.ndarray:
        """(nodes, 3) the rate of change of dE_c/dx at every contact node, the nodes held still,
        while the objects move at ``rates``: per object (dM, dt), the derivatives of its pose's
        matrix and translation in one parameter, or None for an object that stays.

        A rigid object (pose M y + t, M a rotation) moves its points with the velocity
        v(x) = W (x - t) + dt, W = dM M^T (skew). Its gap field g(x) = g0(M^T (x - t)) then changes
        at dg = -n . v and its unit normal at dn = W n - H v (H the gap's world Hessian), so the
        nodal gradient s A b'(g) n (s = stiffness / dhat, A the node's area) changes at
        s A [b''(g) dg n + b'(g) dn]. Refuses a pose or a rate that is not rigid."""
        out = np.zeros((self.surface.num_nodes, 3))
        scale = self.stiffness / self.dhat
        identity = np.eye(3)
        for obj, pose, rate, (active, weight, x, gap, n, gap_hessian) in zip(self.objects, self.poses, rates,
                                                                     self._terms(displacement)):
            if rate is None:
                continue
            dM, dt = np.asarray(rate[0], dtype=float).reshape(3, 3), np.asarray(rate[1], dtype=float).reshape(3)
            M = pose.matrix
            W = dM @ M.T
            size = 1.0 + np.abs(dM).max() + np.abs(dt).max()
            if np.abs(M.T @ M - identity).max() > 1e-8 or np.abs(W + W.T).max() > 1e-6 * size:
                raise ValueError(f"{self.settings.where}: the {obj.describe()} moves non-rigidly (an affine "
                                 "bone frame): the contact's derivative in its pose needs rigid frames")
            v = (x - pose.translation) @ W.T + dt
            first, second = barrier_derivatives(gap, self.dhat)
            gap_rate = -np.einsum("ij,ij->i", n, v)
            normal_rate = n @ W.T - np.einsum("kij,kj->ki", gap_hessian, v)
            np.add.at(out, active, (scale * weight)[:, None]
                      * ((second * gap_rate)[:, None] * n + first[:, None] * normal_rate))
        return out

    def add_pose_rate(self, displacement: np.ndarray, rates, b: PETSc.Vec, scale: float = 1.0) -> None:
        """b += scale * ``pose_rate_forces`` on this rank's dofs (collective)."""
        values = b.array.reshape(-1, 3)
        values[self.surface.owned_blocks] += scale * self.pose_rate_forces(displacement, rates)[self.surface.owned_nodes]
