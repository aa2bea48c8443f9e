"""Newton's tangent of the flesh made definite cell by cell (``equilibrium.definite``): a squeezed
cell's stress derivative has its clearly negative curvature clamped, a cell at rest keeps its own,
and Newton on that tangent finds the equilibrium of the exact one (the residual is untouched)."""
from mpi4py import MPI
import numpy as np
from petsc4py import PETSc
import pytest

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
    H = flesh.cell_stiffness()
    assert np.array_equal(cells, np.arange(len(H)))  # a 70 % squeeze bends every cell's energy the wrong way ...
    exact, corrected = np.linalg.eigvalsh(H), np.linalg.eigvalsh(H + D)
    scale = np.linalg.norm(H, axis=(1, 2))
    assert (exact[:, 0] < -0.05 * scale).all()
    assert (corrected[:, 0] > -1e-10 * scale).all()  # ... which the correction clamps, ...
    # ... leaving the positive curvature as it was.
    np.testing.assert_allclose(corrected[:, -1], exact[:, -1], rtol=1e-10)


@pytest.mark.skipif(MPI.COMM_WORLD.size > 1, reason="the dense spectrum of the whole tangent, on one rank")
def test_the_assembled_tangent_of_a_squeezed_slab_turns_definite():
    problem = FaceProblem(slab_model((4, 2, 2)), definite_tangent=True)
    squeeze(problem, 0.3)
    solver = problem.solver
    exact = solver.tangent.duplicate()
    solver.assemble_tangent(exact)
    corrected = exact.duplicate(copy=True)
    constrained = (problem.bone_blocks * 3 + np.arange(3)[:, None]).reshape(-1)
    assert solver.flesh_correction.add_newton_correction(problem.u.vector, corrected, constrained)
    free = np.setdiff1d(np.arange(problem.u.vector.getSize()), constrained)

    def spectrum(A):
        dense = A.convert(PETSc.Mat.Type.DENSE).getDenseArray()
        return np.linalg.eigvalsh(dense[np.ix_(free, free)])

    before, after = spectrum(exact), spectrum(corrected)
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
