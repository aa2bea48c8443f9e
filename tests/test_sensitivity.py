"""Every column of the marker Jacobian J = W dX/dc against central differences of full solves.

The slab stands in for the face: activations, the 12 affine numbers of the jaw frame, the 3 TMJ
degrees of freedom and the 12 of the cranium frame, at a deformed, articulated state. Relative
error per column <= 1e-5 (the issue's bound), serial and under mpirun -n 2.
"""
from types import SimpleNamespace

from mpi4py import MPI
import numpy as np
import pytest

from face_dolfinx.model.bones import AffineMap, jaw_pose, rigid_map, rotation
from face_dolfinx.physics.points import PointEvaluator
from face_dolfinx.physics.problem import FaceProblem
from face_dolfinx.sensitivities.columns import EquilibriumSensitivity, bone_position_derivatives
from slab import slab_model

MARKERS = np.array([[8.0, 4.0, 10.0], [20.0, 10.0, 10.0], [31.0, 15.0, 10.0], [15.0, 20.0, 6.0],
                    [25.0, 0.0, 3.0], [36.0, 9.0, 10.0]])
SLAB_JAW = slab_model(comm=MPI.COMM_SELF).jaw
ACTIVATIONS = np.array([0.6, 0.3, 0.8])
CRANIUM = rigid_map(rotation([0.3, 1.0, 0.2], 0.4), [0, 10, 5], [2.0, -1.0, 3.0])
TMJ = np.array([0.15, 1.0, 2.0])  # opening angle (rad), right and left slides (mm)


def affine_from(params):
    return AffineMap(params[:9].reshape(3, 3), params[9:])


def affine_params(a: AffineMap):
    return np.concatenate([a.matrix.reshape(-1), a.translation])


@pytest.fixture(scope="module")
def slab():
    problem = FaceProblem(slab_model())
    return SimpleNamespace(problem=problem, sensitivity=EquilibriumSensitivity(problem),
                           markers=PointEvaluator(problem.V, MARKERS), jaw=jaw_pose(SLAB_JAW, *TMJ))


@pytest.fixture
def setup(slab):
    """The slab at the deformed, articulated state with the tangent of that state factored,
    whatever an earlier test left (each test passes alone and in any order)."""
    slab.problem.solve(activations=ACTIVATIONS, cranium=CRANIUM, jaw=slab.jaw)
    slab.sensitivity.factor()
    return slab


def marker_positions(s, **controls):
    s.problem.solve(**controls)
    return MARKERS + s.markers.values(s.problem.u.x.array)


def check_columns(s, analytic, positions_at, params, step):
    """Compare marker Jacobian columns with central differences of the nonlinear solve."""
    base = s.problem.u.x.array.copy()
    for i in range(len(params)):
        bump = np.zeros_like(params)
        bump[i] = step
        plus = positions_at(params + bump)
        minus = positions_at(params - bump)
        s.problem.u.x.array[:] = base
        fd = (plus - minus) / (2 * step)
        scale = max(np.abs(fd).max(), 1e-3)
        assert np.abs(analytic[i] - fd).max() <= 1e-5 * scale, f"column {i}"
    positions_at(params)  # back to the base state


def test_activation_columns(setup):
    s = setup
    columns = s.markers.values_many(s.sensitivity.activation_columns())
    check_columns(s, columns, lambda a: marker_positions(s, activations=np.clip(a, 0, 1)),
                  ACTIVATIONS, 1e-4)


def test_jaw_affine_columns(setup):
    s = setup
    params = affine_params(s.jaw)
    pose = lambda p: (CRANIUM, affine_from(p))  # noqa: E731
    derivatives = bone_position_derivatives(s.problem, pose, params, step=1.0)
    columns = s.markers.values_many(s.sensitivity.boundary_columns(derivatives))
    check_columns(s, columns, lambda p: marker_positions(s, jaw=affine_from(p)), params, 1e-5)


def test_jaw_tmj_columns(setup):
    s = setup
    pose = lambda p: (CRANIUM, jaw_pose(SLAB_JAW, *p))  # noqa: E731
    derivatives = bone_position_derivatives(s.problem, pose, TMJ, step=1e-6)
    columns = s.markers.values_many(s.sensitivity.boundary_columns(derivatives))
    check_columns(s, columns, lambda p: marker_positions(s, jaw=jaw_pose(SLAB_JAW, *p)), TMJ, 1e-5)


def test_cranium_columns_along_rigid_motions(setup):
    """The analytic cranium columns hold along rotations (the paper's assumption): compare the
    directional derivative along a rotation generator and along translations."""
    s = setup
    columns = s.markers.values_many(s.sensitivity.cranium_columns())
    generator = np.array([[0.0, -0.3, 0.5], [0.3, 0.0, -0.2], [-0.5, 0.2, 0.0]])
    direction = np.concatenate([(generator @ CRANIUM.matrix).reshape(-1), [0.4, -1.0, 0.7]])
    analytic = np.tensordot(direction, columns, axes=1)

    def positions(h):
        moved = AffineMap(rotation_from_generator(generator, h) @ CRANIUM.matrix,
                          CRANIUM.translation + h * np.array([0.4, -1.0, 0.7]))
        return marker_positions(s, cranium=moved)

    h = 1e-5
    fd = (positions(h) - positions(-h)) / (2 * h)
    positions(0.0)
    assert np.abs(analytic - fd).max() <= 1e-5 * np.abs(fd).max()


def rotation_from_generator(generator, h):
    axis = np.array([generator[2, 1], generator[0, 2], generator[1, 0]])
    angle = np.linalg.norm(axis) * h
    return rotation(axis, angle) if angle else np.eye(3)


def test_columns_need_the_tangent_of_the_current_state(setup):
    """After a solve the factor belongs to an earlier iterate (or, with factorisation reuse, an
    earlier state): the sensitivities refuse it instead of returning those of another state."""
    s = setup
    s.sensitivity.activation_columns()  # the factor of this state
    s.problem.solve(activations=0.5 * ACTIVATIONS)
    with pytest.raises(RuntimeError, match="call factor"):
        s.sensitivity.activation_columns()
    s.sensitivity.factor()
    assert s.sensitivity.activation_columns().shape[0] == s.problem.num_muscles


def test_a_nearby_factor_serves_approximate_columns_without_factorising():
    """``factor(reuse_within=d)`` keeps the factor of a state at most d mm away (of the same
    controls): no factorisation, and columns within a few per cent of the exact ones but not
    equal to them. A farther state makes the columns refuse; a change of controls forces a new
    factorisation whatever d."""
    problem = FaceProblem(slab_model())
    problem.solve(activations=ACTIVATIONS, cranium=CRANIUM, jaw=jaw_pose(SLAB_JAW, *TMJ))
    sensitivity = EquilibriumSensitivity(problem)
    solver = problem.solver
    assert sensitivity.factor() == 0.0 and solver.factor_distance() == 0.0
    equilibrium = problem.u.x.array.copy()
    # A smooth displacement of at most 0.05 mm stands in for the distance to Newton's last factor.
    x = problem.dof_coordinates
    problem.u.x.array[:] = equilibrium + (0.05 * np.sin(x[:, 0] / 7.0)[:, None] * [1.0, 0.5, 0.0]).reshape(-1)
    distance = solver.factor_distance()
    assert 0.01 < distance <= 0.05
    factorizations = solver.factorizations
    assert sensitivity.factor(reuse_within=0.1) == pytest.approx(distance)
    assert solver.factorizations == factorizations
    approximate = sensitivity.activation_columns()
    # Too far: a fresh factor of this state (Newton's tangent, without energy terms the exact one).
    sensitivity.factor(reuse_within=0.001, newton_tangent=True)
    assert solver.factorizations == factorizations + 1 and solver.factor_distance() == 0.0
    exact = sensitivity.activation_columns()
    owned = problem.V.dofmap.index_map.size_local * 3
    difference, size = (MPI.COMM_WORLD.allreduce(np.sum(a[:, :owned] ** 2, axis=1), op=MPI.SUM)
                        for a in (approximate - exact, exact))
    relative = np.sqrt(difference / size)
    assert np.all(relative > 1e-6) and np.all(relative < 0.05)

    problem.u.x.array[:] += 1.0  # 1 mm from the factor's state, beyond what factor() accepted
    with pytest.raises(RuntimeError, match="call factor"):
        sensitivity.activation_columns()
    problem.u.x.array[:] = equilibrium
    problem.solve(activations=0.9 * ACTIVATIONS)
    problem.adopt(problem.controls.copy(), equilibrium)  # the same controls: the factor still counts
    assert np.isfinite(solver.factor_distance())
    controls = problem.controls.copy()
    controls.activations = ACTIVATIONS.copy()
    problem.adopt(controls, equilibrium)
    assert solver.factor_distance() == np.inf
    assert sensitivity.factor(reuse_within=1e9) == 0.0
    assert solver.factorizations > factorizations + 1
