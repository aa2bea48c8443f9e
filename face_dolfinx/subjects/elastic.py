"""The template carried onto a subject by a pseudo-elastic solve with the skin prescribed.

Once the template's skin has been registered onto the subject, every other node of the flesh
mesh (the bone attachment surfaces, the muscles' cells, the inner mouth) follows as the
equilibrium of a compressible neo-Hookean body whose skin nodes are moved onto the registered
skin (Dirichlet conditions). Unlike a map of free space (an RBF warp), an elastic body resists
being turned inside out: the energy grows without bound as a cell flattens, and the project's
own Newton solver (``equilibrium.solver.QuasistaticSolver``) with its inversion guard and its
continuation walks the skin there in steps. A homogeneous (affine) skin motion gives the same
affine motion inside, exactly: a subject that is a stretched template stays one.

The material is fictitious: only its shape matters. A Poisson ratio of 0.3 lets the flesh
thicken or thin where the registered skin moves towards or away from the bones (a nearly
incompressible one would push the bone surfaces instead).

The solve is serial: it runs on whichever process calls it (``MPI.COMM_SELF``); the subject
command runs it on rank 0, as all of subject adaptation, which is a one-off step on arrays.
"""
from __future__ import annotations

from dataclasses import dataclass

from mpi4py import MPI
import numpy as np
import ufl
from dolfinx import fem
from dolfinx import mesh as dolfinx_mesh

import forms
from face_dolfinx.equilibrium.solver import InversionGuard, QuasistaticSolver

SHEAR_MODULUS = 1.0      # arbitrary units: only the ratio to the bulk modulus shapes the result
POISSON_RATIO = 0.3
QUADRATURE_DEGREE = 1    # P1 displacement: the forms are constant per cell
OPTIONS_PREFIX = "subject_"
# Newton stops once a correction moves no node by more than this (mm): far below what a subject
# model can resolve.
STEP_TOLERANCE_MM = 1e-7


@dataclass
class CarryReport:
    """How the pseudo-elastic solve went."""

    newton_iterations: int
    load_steps: int
    seconds: float


class PseudoElasticCarry:
    """The template's flesh mesh as a pseudo-elastic body on this process alone.

    ``points`` (n, 3) and ``cells`` (m, 4) are the template's file arrays; ``prescribed`` the file
    nodes whose displacement is given (the skin). ``solve(displacement)`` returns the new
    positions of all file nodes.
    """

    def __init__(self, points: np.ndarray, cells: np.ndarray, prescribed: np.ndarray, *,
                 poisson_ratio: float = POISSON_RATIO):
        domain = ufl.Mesh(ufl.VectorElement("Lagrange", ufl.tetrahedron, 1))
        self.mesh = dolfinx_mesh.create_mesh(MPI.COMM_SELF, np.asarray(cells, dtype=np.int64),
                                             np.asarray(points, dtype=np.float64), domain)
        self.V = fem.VectorFunctionSpace(self.mesh, ("CG", 1))
        self.u = fem.Function(self.V, name="carry_displacement")
        # Dof blocks and geometry nodes of a cell follow the same reference vertex order; the
        # geometry keeps each node's index in the input arrays.
        blocks = self.V.dofmap.list.array.reshape(-1, 4)
        nodes = self.mesh.geometry.dofmap.array.reshape(-1, 4)
        self.file_node = np.empty(self.V.dofmap.index_map.size_local, dtype=np.int64)
        self.file_node[blocks] = np.asarray(self.mesh.geometry.input_global_indices, dtype=np.int64)[nodes]
        block_of_node = np.full(len(points), -1, dtype=np.int64)
        block_of_node[self.file_node] = np.arange(len(self.file_node))
        self.block_of_node = block_of_node
        self.prescribed_blocks = block_of_node[np.asarray(prescribed)]  # in the order of ``prescribed``
        self.skin_displacement = fem.Function(self.V, name="prescribed_displacement")
        self.target = np.zeros_like(self.skin_displacement.x.array)

        mu = SHEAR_MODULUS
        kappa = 2.0 * mu * (1.0 + poisson_ratio) / (3.0 * (1.0 - 2.0 * poisson_ratio))
        isochoric, volumetric = forms.MooneyRivlin(0.5 * mu, 0.0), forms.LogVolumetric(kappa)
        F = forms.deformation_gradient(self.u)
        dx = ufl.dx(domain=self.mesh, metadata={"quadrature_degree": QUADRATURE_DEGREE})
        energy = (isochoric.strain_energy(F) + volumetric.strain_energy(F)) * dx
        v = ufl.TestFunction(self.V)
        residual = ufl.inner(isochoric.first_piola(F) + volumetric.first_piola(F), ufl.grad(v)) * dx
        bcs = [fem.dirichletbc(self.skin_displacement, np.sort(self.prescribed_blocks).astype(np.int32))]
        # Far from rest the tangent of a compressible body may be indefinite: factorise with pivoting.
        self.solver = QuasistaticSolver(residual, self.u, bcs, tangent="symmetric", energy=energy,
                                        options_prefix=OPTIONS_PREFIX, inversion_guard=InversionGuard(self.V),
                                        step_tolerance=STEP_TOLERANCE_MM)

    def solve(self, displacement: np.ndarray) -> tuple[np.ndarray, CarryReport]:
        """New positions (n, 3) of every file node, the prescribed nodes moved by
        ``displacement`` (len(prescribed), 3), in the order of ``prescribed``.
        EquilibriumError if no equilibrium can be reached."""
        target = self.target.reshape(-1, 3)
        target[:] = 0.0
        target[self.prescribed_blocks] = np.asarray(displacement, dtype=np.float64)

        def set_load(t: float) -> None:
            self.skin_displacement.x.array[:] = t * self.target

        self.u.x.array[:] = 0.0
        set_load(0.0)
        report = self.solver.solve_continuation(set_load)
        positions = np.empty((len(self.file_node), 3))
        rest = self.V.tabulate_dof_coordinates()[:, :3]
        positions[self.file_node] = rest + self.u.x.array.reshape(-1, 3)
        return positions, CarryReport(report.newton_iterations, report.load_steps, report.seconds)


def deformation_gradients(rest: np.ndarray, moved: np.ndarray, cells: np.ndarray) -> np.ndarray:
    """The (constant) deformation gradient (m, 3, 3) of each P1 tet from ``rest`` to ``moved``."""
    rest_edges = (rest[cells[:, 1:]] - rest[cells[:, :1]]).transpose(0, 2, 1)
    moved_edges = (moved[cells[:, 1:]] - moved[cells[:, :1]]).transpose(0, 2, 1)
    return moved_edges @ np.linalg.inv(rest_edges)
