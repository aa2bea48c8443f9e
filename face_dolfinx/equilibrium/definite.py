"""Newton's tangent of the flesh made positive semidefinite cell by cell.

The flesh's exact tangent is indefinite wherever a cell is squeezed far from rest: the volumetric
term's kappa ln J d(F^-T)/dF and the isochoric factors' curvature turn negative as J falls, and an
active fiber stretched past the peak of its force-length curve softens. Near the lining that the incisors
press, such cells make the assembled tangent nearly singular (MUMPS zero pivots) and Newton's
corrections huge (tens to hundreds of millimetres), which the inversion guard then cuts.

Teran et al. 2005 ("Robust quasistatic finite elements and flesh simulation", the solver of
Sifakis et al. 2005) make each element's stiffness definite. Here, per cell, the stress derivative
H = dP/dF (a symmetric 9 x 9 matrix, constant on a P1 cell) that has an eigenvalue below
``-tolerance`` times its Frobenius norm has its negative eigenvalues clamped to zero, and Newton's
tangent adds the cell's change  int grad(v) : (H+ - H) : grad(du) dx. The residual is untouched,
so the equilibrium is too; only the path to it changes. Cells whose curvature is only slightly
negative (the geometric stiffness of a prestressed cell, which its neighbours outweigh) keep their
exact stiffness: on the test slab a threshold of 0.02 instead of 0.05 doubled Newton's iterations.
"""
import logging
import time

import numpy as np
import ufl
from dolfinx import fem
from petsc4py import PETSc

log = logging.getLogger(__name__)

# A cell's stiffness is corrected where dP/dF has an eigenvalue below -NEGATIVE_CURVATURE times
# its Frobenius norm.
NEGATIVE_CURVATURE = 0.05
# Cells whose dP/dF is evaluated and checked at once (the 81 values of 20K cells take 13 MB).
CHUNK = 20000


class DefiniteFleshTangent:
    """The change to the flesh's tangent that makes each cell's stress derivative positive
    semidefinite where it is clearly indefinite (a Newton correction, as the contact terms'
    projected Hessians are: ``QuasistaticSolver`` adds it to Newton's tangent only).

    ``first_piola``: P(F) of the flesh (UFL) at ``F``, a ``ufl.variable`` of ``unknown``, the
    displacement (P1 on affine tetrahedra: the stress derivative is constant on each cell).
    """

    exact_near_solution = True

    def __init__(self, first_piola, F, unknown: fem.Function, tolerance: float = NEGATIVE_CURVATURE):
        space = unknown.function_space
        mesh = space.mesh
        if space.ufl_element().degree() != 1 or mesh.topology.cell_name() != "tetrahedron":
            raise ValueError("a definite flesh tangent needs P1 displacements on tetrahedra "
                             "(one stress derivative per cell)")
        self.tolerance = tolerance
        self.comm = mesh.comm
        stiffness = ufl.diff(first_piola(F), F)
        pairs = [(i, j) for i in range(3) for j in range(3)]  # (component, direction) of P and of F
        flat = ufl.as_matrix([[stiffness[i, j, k, m] for k, m in pairs] for i, j in pairs])
        self._stiffness = fem.Expression(flat, np.full((1, 3), 0.25))
        owned = mesh.topology.index_map(3).size_local
        self._cells = np.arange(owned, dtype=np.int32)  # each cell's correction is added by its owner
        self._blocks = space.dofmap.list.array.reshape(-1, 4)[:owned]
        self._block_coordinates = space.tabulate_dof_coordinates()
        self.corrected_cells = 0  # cells whose stiffness the last correction changed, all ranks
        self.corrected_tangents = 0  # tangents the correction changed

    def cell_stiffness(self, cells: np.ndarray) -> np.ndarray:
        """dP/dF of the given owned cells at the unknown, symmetrised: (cells, 9, 9)."""
        H = self._stiffness.eval(cells).reshape(-1, 9, 9)
        return 0.5 * (H + H.transpose(0, 2, 1))

    def cell_corrections(self) -> tuple[np.ndarray, np.ndarray]:
        """The owned cells whose dP/dF is clearly indefinite and, for each, H+ - H (its negative
        eigenvalues clamped to zero): (cells, (cells, 9, 9))."""
        corrected, stiffness = [], []
        for start in range(0, self._cells.size, CHUNK):
            cells = self._cells[start:start + CHUNK]
            H = self.cell_stiffness(cells)
            clear = clearly_indefinite(H, self.tolerance) & np.isfinite(H).all(axis=(1, 2))
            corrected.append(cells[clear])
            stiffness.append(H[clear])
        cells = np.concatenate(corrected) if corrected else np.zeros(0, np.int32)
        values, vectors = np.linalg.eigh(np.concatenate(stiffness) if stiffness else np.zeros((0, 9, 9)))
        return cells, -np.einsum("cik,ck,cjk->cij", vectors, np.minimum(values, 0.0), vectors)

    def add_newton_correction(self, x: PETSc.Vec, A: PETSc.Mat, constrained: np.ndarray) -> bool:
        """A += int grad(v) : D : grad(du) over the corrected cells at the unknown (which is ``x``),
        rows and columns of the ``constrained`` local dofs left out; False if no cell on any rank
        needed it (A untouched)."""
        began = time.perf_counter()
        cells, D = self.cell_corrections()
        self.corrected_cells = self.comm.allreduce(cells.size)
        if self.comm.rank == 0:
            log.debug("flesh tangent made definite in %d cells (%.2f s)", self.corrected_cells,
                      time.perf_counter() - began)
        if self.corrected_cells == 0:
            return False
        blocks = self._blocks[cells]
        stiffness = element_stiffness(self._block_coordinates[blocks], D)
        dofs = (3 * blocks[:, :, None] + np.arange(3)).reshape(-1, 12).astype(PETSc.IntType)
        held = np.isin(dofs, constrained)
        stiffness[held[:, :, None] | held[:, None, :]] = 0.0
        for rows, matrix in zip(dofs, stiffness):  # local dofs, through the matrix's local-to-global map
            A.setValuesLocal(rows, rows, matrix, addv=PETSc.InsertMode.ADD_VALUES)
        A.assemble()
        self.corrected_tangents += 1
        return True


def clearly_indefinite(H: np.ndarray, tolerance: float) -> np.ndarray:
    """Whether each symmetric matrix of ``H`` (n, m, m) has an eigenvalue below -tolerance times its
    Frobenius norm: exactly where H + tolerance |H|_F I has a non-positive pivot in its LDL^T
    factorisation, done for all n at once (twice as fast as their eigenvalues)."""
    n, m, _ = H.shape
    A = np.ascontiguousarray(H.transpose(1, 2, 0))
    A[np.arange(m), np.arange(m)] += tolerance * np.sqrt((A * A).sum(axis=(0, 1)))
    failed = np.zeros(n, bool)
    for k in range(m):
        pivot = A[k, k]
        failed |= ~(pivot > 0.0)
        column = A[k + 1:, k] * np.where(failed, 0.0, 1.0 / np.where(failed, 1.0, pivot))
        A[k + 1:, k + 1:] -= column[:, None, :] * A[k, k + 1:][None, :, :]
    return failed


def element_stiffness(corners: np.ndarray, D: np.ndarray) -> np.ndarray:
    """int grad(v) : D : grad(du) on P1 tetrahedra with ``corners`` (n, 4, 3) and a constant D
    (n, 9, 9) over (i j), (k l) of grad's (component, direction): (n, 12, 12) over (node, component)."""
    edges = corners[:, 1:] - corners[:, :1]
    inverse = np.linalg.inv(edges)  # columns: the gradients of the barycentric coordinates 1-3
    gradients = np.concatenate([-inverse.sum(axis=2, keepdims=True), inverse], axis=2).transpose(0, 2, 1)
    volume = np.abs(np.linalg.det(edges)) / 6.0
    K = np.einsum("c,caj,cijkl,cbl->caibk", volume, gradients, D.reshape(-1, 3, 3, 3, 3), gradients)
    return K.reshape(-1, 12, 12)
