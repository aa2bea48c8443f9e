"""The forward model on the small built-in face (about 5K tets).

Robustness (rest to every muscle fully on, and to the widest jaw opening with both condyles at the
end of their tracks, each in one call), the quadratic option, and error messages for bad controls.
(Distributed runs against serial: test_problem.py, on the slab and on this face.)
"""
import math

from mpi4py import MPI
import numpy as np
import pytest

from face_dolfinx.model.bones import jaw_pose
from face_dolfinx.model.folder import ModelError
from face_dolfinx.physics.points import PointEvaluator
from face_dolfinx.physics.problem import FaceProblem


def marker_displacements(problem, model):
    points = np.array(list(model.markers.values()))
    return PointEvaluator(problem.V, points).values(problem.u.x.array)


def smile_activations(model) -> dict:
    """The built-in smile's muscle activations, without its jaw opening."""
    expression = dict(model.expressions["smile"])
    expression.pop("jaw_opening_deg", None)
    return expression


def widest_jaw(model):
    jaw = model.jaw
    return jaw_pose(jaw, math.asin(jaw.max_opening_sine), jaw.track_length, jaw.track_length)


def test_all_muscles_and_widest_jaw_from_rest(model):
    problem = FaceProblem(model)
    report = problem.solve(activations=np.ones(problem.num_muscles))
    assert report.converged and problem.residual_norm() < 1e-5  # mN; the initial residual is ~1e4
    assert np.abs(marker_displacements(problem, model)).max() > 3.0
    problem.u.x.array[:] = 0.0
    problem.solve(activations=np.zeros(problem.num_muscles))
    report = problem.solve(activations=np.ones(problem.num_muscles), jaw=widest_jaw(model))
    assert report.converged and problem.residual_norm() < 1e-5  # mN; the initial residual is ~1e4
    chin = marker_displacements(problem, model)[list(model.markers).index("chin_1")] \
        if "chin_1" in model.markers else marker_displacements(problem, model).max(axis=0)
    assert np.linalg.norm(chin) > 15.0  # the chin really drops with a 25 degree opening


def test_expressions_move_the_expected_regions(model):
    """A smile moves the mouth corners far more than the brows (its orbicularis oculi part
    squints a little); a brow raise moves the brows up."""
    problem = FaceProblem(model)
    names = list(model.markers)
    corners = [names.index(n) for n in names if n.startswith("mouth_corner")]
    brows = [names.index(n) for n in names if n.startswith("brow")]
    problem.solve(activations=model.expressions["smile"])
    smile = marker_displacements(problem, model)
    assert np.linalg.norm(smile[corners], axis=1).min() > 3.0
    assert np.linalg.norm(smile[brows], axis=1).max() < 0.5 * np.linalg.norm(smile[corners], axis=1).min()
    problem.solve(activations=model.expressions["brow_raise"])
    raised = marker_displacements(problem, model)
    assert raised[brows, 1].mean() > 2.0  # y is up


def test_quadratic_displacements_are_softer(model):
    """P2 relieves the volumetric locking of P1 tetrahedra: the same smile moves further."""
    linear, quadratic = FaceProblem(model), FaceProblem(model, degree=2)
    for problem in (linear, quadratic):
        assert problem.solve(activations=model.expressions["smile"]).converged
    p1 = np.abs(marker_displacements(linear, model)).max()
    p2 = np.abs(marker_displacements(quadratic, model)).max()
    assert p2 > 1.05 * p1


def test_bad_controls_name_the_problem(model):
    problem = FaceProblem(model)
    with pytest.raises(ModelError, match="unknown muscle 'zygomaticus_major'"):
        problem.solve(activations={"zygomaticus_major": 0.5})
    with pytest.raises(ValueError, match="frontalis_left=1.2"):
        problem.solve(activations={"frontalis_left": 1.2})
    assert np.array_equal(problem.controls.activations, np.zeros(problem.num_muscles))  # unchanged


def test_inversion_guard_shortens_an_inverting_step_only(model):
    """A step that would flatten cells past the bound is halved until none is; a small step is
    kept whole. Volumes are checked independently of the guard, from the cell vertices."""
    problem = FaceProblem(model)
    guard = problem.solver.inversion_guard
    rest = np.zeros_like(problem.u.x.array)
    coordinates = problem.dof_coordinates
    # Squash towards the centre plane y = mean(y): at full step every cell collapses to J = 0.
    centre = coordinates[:, 1].mean()
    squash = np.zeros_like(coordinates)
    squash[:, 1] = coordinates[:, 1] - centre
    fraction = guard.step_fraction(rest, squash.reshape(-1))
    assert fraction < 1.0
    moved = coordinates - fraction * squash
    cells = guard.vertex_blocks
    volume = np.linalg.det(moved[cells][:, 1:] - moved[cells][:, :1])
    ratio = model.mesh.comm.allreduce((volume / guard.rest_volume).min(), op=MPI.MIN)
    assert ratio >= guard.min_volume_ratio
    assert fraction == 0.5 ** round(-np.log2(fraction))  # a power of one half
    small = 0.01 * squash.reshape(-1)
    assert guard.step_fraction(rest, small) == 1.0


def test_factorisation_reuse_gives_the_same_equilibrium_with_fewer_factorisations(model):
    expression = smile_activations(model)
    shapes, counts = [], []
    for reuse in (False, True):
        problem = FaceProblem(model, reuse_factorization=reuse)
        first = problem.solve(activations=expression)
        # A nearby second state, as the next frame of a take: the old factor serves it.
        nearby = {name: 0.9 * value for name, value in expression.items()}
        second = problem.solve(activations=nearby)
        assert first.converged and second.converged
        shapes.append(problem.u.x.array.copy())
        counts.append((problem.solver.factorizations, first.newton_iterations + second.newton_iterations))
    difference = np.linalg.norm(shapes[1] - shapes[0]) / np.linalg.norm(shapes[0])
    assert model.mesh.comm.allreduce(difference, op=MPI.MAX) < 1e-8
    fresh_factorizations, fresh_newton = counts[0]
    reused_factorizations, _ = counts[1]
    # One per Newton iteration until Newton converges (CONVERGING_CORRECTION), then none ...
    assert fresh_factorizations < fresh_newton
    plain = FaceProblem(model)
    plain.solver.reuse_policy.converging_correction = 0.0  # ... or one per iteration throughout
    report = plain.solve(activations=expression)
    assert plain.solver.factorizations == report.newton_iterations
    # Reuse across solves: fewer still, and under half of full Newton's one per iteration.
    assert reused_factorizations < fresh_factorizations
    assert reused_factorizations < fresh_newton / 2


def test_krylov_on_the_old_factor_gives_the_same_equilibrium_without_refactorising(model):
    """GMRES on the matrix-free tangent, preconditioned by the last factor: the equilibrium of
    the next, nearby state to 1e-8 as with full Newton, from the old factor alone (under mpirun
    the matrix-free products evaluate the residual into vectors without ghosts)."""
    expression = smile_activations(model)
    nearby = {name: 0.9 * value for name, value in expression.items()}
    reference = FaceProblem(model)
    reference.solve(activations=nearby)
    problem = FaceProblem(model, reuse_factorization=True, krylov_on_old_factor=True)
    assert problem.solve(activations=expression).converged
    factorizations, iterations = problem.solver.factorizations, problem.solver.linear_iterations
    report = problem.solve(activations=nearby)
    assert report.converged and report.load_steps == 1
    assert problem.solver.factorizations == factorizations
    assert problem.solver.linear_iterations - iterations > report.newton_iterations  # GMRES did work
    difference = np.linalg.norm(problem.u.x.array - reference.u.x.array) / np.linalg.norm(reference.u.x.array)
    assert model.mesh.comm.allreduce(difference, op=MPI.MAX) < 1e-8
    with pytest.raises(ValueError, match="needs reuse_factorization"):
        FaceProblem(model, krylov_on_old_factor=True)


def test_newton_tolerance_bounds_the_last_correction(model):
    """A looser Newton tolerance (mm) saves iterations and leaves the shape within it."""
    expression = smile_activations(model)
    tight, loose = FaceProblem(model), FaceProblem(model, newton_tolerance=1e-4)
    tight_report, loose_report = tight.solve(activations=expression), loose.solve(activations=expression)
    assert loose_report.converged and loose_report.newton_iterations < tight_report.newton_iterations
    assert 0.0 < model.mesh.comm.allreduce(np.abs(loose.u.x.array - tight.u.x.array).max(), op=MPI.MAX) < 1e-4


def test_newton_from_an_equilibrium_stops_on_the_step_tolerance(model):
    """A residual tolerance below the round-off floor can never be met; Newton started at a
    converged state then stops once its correction is below the step tolerance instead of
    stalling to the iteration limit (which raised mid-take when a line search's best point was
    re-solved)."""
    problem = FaceProblem(model, petsc_options=dict(snes_atol=1e-30, snes_rtol=1e-30))
    expression = smile_activations(model)
    assert problem.solve(activations=expression).converged
    converged, iterations, reason = problem.solver.newton()
    assert converged and iterations <= 2 and "SNORM" in reason


def test_adopt_takes_a_solved_state_without_solving(model):
    problem = FaceProblem(model)
    expression = smile_activations(model)
    problem.solve(activations=expression)
    smile, controls = problem.u.x.array.copy(), problem.controls.copy()
    problem.solve(activations=np.zeros(problem.num_muscles))
    factorizations = problem.solver.factorizations
    problem.adopt(controls, smile)
    assert problem.solver.factorizations == factorizations
    assert np.array_equal(problem.u.x.array, smile)
    assert np.array_equal(problem.controls.activations, controls.activations)
    assert problem.residual_norm() < 1e-6  # the smile's own activations are back in the forms
