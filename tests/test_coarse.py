"""Coarse start (nested iteration): transfer exactness, the same equilibrium, fewer iterations."""
from mpi4py import MPI
import numpy as np
import pytest

from face_dolfinx.model.bones import rigid_map, rotation
from face_dolfinx.equilibrium.coarse import CoarseStart, locate_in_cells
from face_dolfinx.physics.problem import FaceProblem
from slab import slab_model


def test_located_weights_reproduce_linear_fields_inside_and_outside():
    """Barycentric weights interpolate a linear field exactly in the host cell and extend it
    exactly outside; the distance outside is minus the smallest weight."""
    points = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1]])
    cells = np.array([[0, 1, 2, 3], [1, 2, 3, 4]])
    targets = np.array([[0.1, 0.2, 0.3], [0.6, 0.6, 0.6], [-0.5, 0.2, 0.2]])
    host, weights, outside = locate_in_cells(points, cells, targets)
    assert np.array_equal(host[0], cells[0]) and np.array_equal(host[1], cells[1])
    assert outside[0] == 0.0 and outside[1] == 0.0 and outside[2] == pytest.approx(0.5)
    field = points @ np.array([[1.0, 2, 3], [0, -1, 4], [2, 0.5, 0]]) + np.array([1.0, -2, 0.5])
    expected = targets @ np.array([[1.0, 2, 3], [0, -1, 4], [2, 0.5, 0]]) + np.array([1.0, -2, 0.5])
    assert np.allclose(np.einsum("ij,ijk->ik", weights, field[host]), expected, atol=1e-12)


def test_coarse_start_transfers_a_linear_field_exactly():
    coarse, fine = FaceProblem(slab_model((4, 2, 2))), FaceProblem(slab_model((8, 4, 2)))
    start = CoarseStart(coarse, fine)
    gradient = np.array([[0.01, 0.02, 0.0], [0.0, -0.01, 0.03], [0.02, 0.0, 0.01]])
    coarse.u.x.array[:] = (coarse.dof_coordinates @ gradient.T).reshape(-1)
    assert np.allclose(start.guess(), (fine.dof_coordinates @ gradient.T).reshape(-1), atol=1e-12)


def by_position(problem) -> np.ndarray:
    """The displacement of every dof of all ranks, ordered by position (two meshes of the same
    box can be partitioned differently)."""
    owned = problem.V.dofmap.index_map.size_local
    points = np.concatenate(MPI.COMM_WORLD.allgather(problem.dof_coordinates[:owned]))
    values = np.concatenate(MPI.COMM_WORLD.allgather(problem.u.x.array.reshape(-1, 3)[:owned]))
    return values[np.lexsort(np.round(points, 6).T)]  # rounded: coordinates differ by round-off


def test_coarse_start_reaches_the_fine_equilibrium_in_fewer_newton_iterations():
    # A 70 degree turn of the far end: from rest Newton inverts elements and needs continuation.
    controls = dict(activations=[1.0, 0.6, 0.8],
                    jaw=rigid_map(rotation([0, 1, 0], 1.2), [40, 10, 5], [0, 0, -10]))
    reference = FaceProblem(slab_model((16, 8, 4)))
    from_rest = reference.solve(**controls)
    fine = FaceProblem(slab_model((16, 8, 4)))
    started = CoarseStart(FaceProblem(slab_model((8, 4, 2))), fine).solve(**controls)
    assert started.converged and fine.residual_norm() < 1e-6
    assert np.abs(by_position(fine) - by_position(reference)).max() < 1e-6
    assert started.newton_iterations < from_rest.newton_iterations


def test_coarse_model_of_another_face_is_rejected():
    coarse = FaceProblem(slab_model((4, 2, 2)))
    other = slab_model((4, 2, 2))
    other.muscles = other.muscles[:2]
    with pytest.raises(ValueError, match="different muscles"):
        CoarseStart(coarse, FaceProblem(other))
    with pytest.raises(ValueError, match="P1"):
        CoarseStart(FaceProblem(slab_model((4, 2, 2)), degree=2), coarse)


def test_activations_alone_are_solved_on_the_fine_model_directly():
    coarse, fine = FaceProblem(slab_model((4, 2, 2))), FaceProblem(slab_model((8, 4, 2)))
    report = CoarseStart(coarse, fine).solve(activations=[0.5, 0.2, 0.8])
    assert report.converged and fine.residual_norm() < 1e-6
    assert np.all(coarse.u.x.array == 0.0)  # the coarse model was not asked
