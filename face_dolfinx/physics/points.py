"""Evaluating Lagrange fields at fixed material points, as one sparse matrix per rank.

Markers, landmarks and skin vertices sit at fixed points of the reference configuration, so the
value of any displacement-like field there is a fixed linear map of its dofs: W u. Each point is
claimed by exactly one rank (the lowest rank owning a cell that contains it); a rank's W holds the
basis function values of that cell, and results are summed over ranks. On a skin facet this is
the paper's barycentric embedding (P1) and its quadratic analogue (P2).
"""
from mpi4py import MPI
import numpy as np
import basix
import scipy.sparse as sp
from dolfinx import fem, geometry


class PointEvaluator:
    """W with ``values(u) = W u`` at ``points`` (n, 3) for blocked (vector) or scalar fields."""

    def __init__(self, space: fem.FunctionSpace, points: np.ndarray):
        domain = space.mesh
        comm = domain.comm
        points = np.ascontiguousarray(np.asarray(points, dtype=np.float64).reshape(-1, 3))
        self.num_points = len(points)
        tdim = domain.topology.dim
        owned_cells = domain.topology.index_map(tdim).size_local
        tree = geometry.BoundingBoxTree(domain, tdim)
        colliding = geometry.compute_colliding_cells(
            domain, geometry.compute_collisions(tree, points), points)
        cell_of_point = np.full(self.num_points, -1, dtype=np.int64)
        for i in range(self.num_points):
            cells = colliding.links(i)
            cells = cells[cells < owned_cells]
            if len(cells):
                cell_of_point[i] = cells[0]
        # The lowest rank that owns a containing cell takes the point.
        claim = np.where(cell_of_point >= 0, comm.rank, comm.size).astype(np.int64)
        winner = np.empty_like(claim)
        comm.Allreduce(claim, winner, op=MPI.MIN)
        missing = np.flatnonzero(winner == comm.size)
        if missing.size:
            raise ValueError(f"{missing.size} point(s) lie outside the mesh, e.g. {points[missing[0]]}")
        mine = np.flatnonzero(winner == comm.rank)

        degree = space.ufl_element().degree()
        element = basix.create_element(basix.ElementFamily.P, basix.CellType.tetrahedron, degree,
                                       basix.LagrangeVariant.gll_warped)
        x = domain.geometry.x
        geometry_dofs = domain.geometry.dofmap
        rows, cols, vals = [], [], []
        for i in mine:
            cell = cell_of_point[i]
            vertices = x[geometry_dofs.links(cell)[:4]]
            jacobian = (vertices[1:] - vertices[0]).T
            reference = np.linalg.solve(jacobian, points[i] - vertices[0])
            basis = element.tabulate(0, reference.reshape(1, 3))[0, 0, :, 0]
            dofs = space.dofmap.cell_dofs(cell)
            rows.extend([i] * len(dofs))
            cols.extend(dofs)
            vals.extend(basis)
        num_blocks = space.dofmap.index_map.size_local + space.dofmap.index_map.num_ghosts
        self.comm = comm
        self.matrix = sp.csr_matrix((vals, (rows, cols)), shape=(self.num_points, num_blocks))
        self.block_size = space.dofmap.index_map_bs

    def values(self, array: np.ndarray) -> np.ndarray:
        """Field values (n, block size) at the points from a local dof array (owned + ghost)."""
        local = self.matrix @ np.asarray(array).reshape(-1, self.block_size)
        total = np.zeros(local.shape)
        self.comm.Allreduce(np.ascontiguousarray(local), total, op=MPI.SUM)
        return total

    def values_many(self, arrays: np.ndarray) -> np.ndarray:
        """Values of several fields at once: ``arrays`` (k, local dofs) -> (k, n, block size)."""
        k = len(arrays)
        stacked = np.asarray(arrays).reshape(k, -1, self.block_size).transpose(1, 0, 2).reshape(
            -1, k * self.block_size)
        local = np.ascontiguousarray(
            (self.matrix @ stacked).reshape(self.num_points, k, self.block_size).transpose(1, 0, 2))
        total = np.zeros(local.shape)
        self.comm.Allreduce(np.ascontiguousarray(local), total, op=MPI.SUM)
        return total
