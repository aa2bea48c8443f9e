"""Newton's tangent of the flesh made definite cell by cell (``equilibrium.definite``): a squeezed
cell's stress derivative has its clearly negative curvature clamped, a cell at rest keeps its own,
the cells' stiffness is laid out as the assembled tangent's, and Newton on that tangent finds the
equilibrium of the exact one (the residual is untouched)."""
from mpi4py import MPI
import numpy as np
from petsc4py import PETSc
import pytest

from face_dolfinx.equilibrium.definite import element_stiffness
from face_dolfinx.model.bones import rigid_map, rotation
from face_dolfinx.physics.problem import FaceProblem
from slab import slab_model


def squeeze(problem, thickness_ratio):
    """A homogeneous squeeze of the slab across its thickness (z), the bones' dofs included."""
    problem.u.interpolate(lambda x: np.stack([0.0 * x[0], 0.0 * x[1], (thickness_ratio - 1.0) * x[2]]))


def test_a_squeezed_cells_negative_curvature_is_clamped_and_a_cell_at_rest_keeps_its_own():
    problem = FaceProblem(slab_model((4, 2, 2)), definite_tangent=True)
    flesh = problem.solver.flesh_correction
    assert flesh.cell_corrections()[0].size == 0  # at rest every cell's stiffness is its own

    squeeze(problem, 0.3)
    cells, D = flesh.cell_corrections()
    H = flesh.cell_stiffness(cells)
    assert cells.size == problem.mesh.topology.index_map(3).size_local  # a 70 % squeeze bends every cell's energy the wrong way ...
    exact, corrected = np.linalg.eigvalsh(H), np.linalg.eigvalsh(H + D)
    scale = np.linalg.norm(H, axis=(1, 2))
    assert (exact[:, 0] < -0.05 * scale).all()
    assert (corrected[:, 0] > -1e-10 * scale).all()  # ... which the correction clamps, ...
    # ... leaving the positive curvature as it was.
    np.testing.assert_allclose(corrected[:, -1], exact[:, -1], rtol=1e-10)


def bone_dofs(problem):
    """The local dofs the bones hold."""
    return (problem.bone_blocks * 3 + np.arange(3)[:, None]).reshape(-1)


def dense_free_block(problem, A):
    """The tangent's rows and columns of the dofs no bone holds, as a dense array (one rank)."""
    free = np.setdiff1d(np.arange(problem.u.vector.getSize()), bone_dofs(problem))
    return A.convert(PETSc.Mat.Type.DENSE).getDenseArray()[np.ix_(free, free)]


@pytest.mark.skipif(MPI.COMM_WORLD.size > 1, reason="a dense tangent, on one rank")
def test_the_cells_stiffness_from_their_stress_derivatives_is_the_flesh_tangent():
    """With D = dP/dF itself, the element stiffness the correction adds sums to the exact tangent:
    the stress derivative's layout and the cells' gradients are those of the assembled form."""
    problem = FaceProblem(slab_model((4, 2, 2)), definite_tangent=True)
    problem.u.interpolate(lambda x: np.stack([0.02 * x[1] * x[2], 0.01 * x[0] * x[2], -0.4 * x[2]]))
    flesh = problem.solver.flesh_correction
    cells = np.arange(problem.mesh.topology.index_map(3).size_local, dtype=np.int32)
    blocks = problem.V.dofmap.list.array.reshape(-1, 4)[cells]
    elements = element_stiffness(problem.V.tabulate_dof_coordinates()[blocks], flesh.cell_stiffness(cells))
    summed = PETSc.Mat().createAIJ(problem.solver.tangent.getSizes(), comm=MPI.COMM_SELF)
    summed.setUp()
    summed.setOption(PETSc.Mat.Option.NEW_NONZERO_ALLOCATION_ERR, False)
    for dofs, matrix in zip((3 * blocks[:, :, None] + np.arange(3)).reshape(-1, 12).astype(PETSc.IntType), elements):
        summed.setValues(dofs, dofs, matrix, addv=PETSc.InsertMode.ADD_VALUES)
    summed.assemble()
    exact = problem.solver.tangent.duplicate()
    problem.solver.assemble_tangent(exact)
    expected = dense_free_block(problem, exact)
    np.testing.assert_allclose(dense_free_block(problem, summed), expected, atol=1e-10 * np.abs(expected).max())


@pytest.mark.skipif(MPI.COMM_WORLD.size > 1, reason="the dense spectrum of the whole tangent, on one rank")
def test_the_assembled_tangent_of_a_squeezed_slab_turns_definite():
    problem = FaceProblem(slab_model((4, 2, 2)), definite_tangent=True)
    squeeze(problem, 0.3)
    solver = problem.solver
    exact = solver.tangent.duplicate()
    solver.assemble_tangent(exact)
    corrected = exact.duplicate(copy=True)
    assert solver.flesh_correction.add_newton_correction(problem.u.vector, corrected, bone_dofs(problem))
    before, after = (np.linalg.eigvalsh(dense_free_block(problem, A)) for A in (exact, corrected))
    assert before[0] < -1e-3 * before[-1]
    assert after[0] > -1e-10 * after[-1]


def test_newton_on_the_definite_tangent_reaches_the_exact_tangents_equilibrium():
    controls = dict(activations=[1.0, 1.0, 1.0], jaw=rigid_map(rotation([1, 0, 0], 0.8), [40, 10, 5], [0, 4, 0]))
    model = slab_model((8, 4, 2))  # one mesh: under MPI two would be partitioned differently
    solutions, corrected = [], []
    for definite in (False, True):
        problem = FaceProblem(model, definite_tangent=definite)
        problem.solve(**controls)
        solutions.append(problem.u.x.array.copy())
        if definite:
            corrected.append(problem.solver.flesh_correction.corrected_tangents)
    assert corrected[0] > 0  # Newton met cells it had to correct
    np.testing.assert_allclose(solutions[1], solutions[0], atol=1e-7 * np.abs(solutions[0]).max())
