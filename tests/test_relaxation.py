"""Nonlinear elimination of the contact nodes (face_dolfinx.equilibrium.relaxation) on the small
face's pressed lips and the slab under a sphere: the same equilibrium as Newton without it, no
penetration at any point the relaxation tries, the contact nodes' residual cut with every other dof
held, the residual over the cells around the contact surfaces equal to the whole face's on their
nodes, and the same result on 1 and 2 ranks.
"""
from mpi4py import MPI
from petsc4py import PETSc
import numpy as np
import pytest

import face_dolfinx.equilibrium.solver as solver_module
from face_dolfinx.equilibrium.relaxation import RELAXATION_REDUCTION
from face_dolfinx.model.bones import jaw_pose
from face_dolfinx.model.folder import load_model
from face_dolfinx.physics.problem import FaceProblem
from face_dolfinx.physics.self_contact import LipContactSettings, LipIterates
from test_contact import pressed_slab
from test_self_contact import CLOSED, sphincter


LOOSER = 0.8  # the orbicularis oris let go from 1 to this, the jaw still closed


def pressed_lips(model, relaxation: bool = False) -> FaceProblem:
    """The orbicularis oris at 1 with the jaw closed, from rest, the lips on each other."""
    problem = FaceProblem(model, lip_contact=LipContactSettings(), contact_relaxation=relaxation)
    assert problem.solve(activations=sphincter(model), jaw=jaw_pose(model.jaw, CLOSED)).converged
    return problem


def loosened(pressed: FaceProblem, model, relaxation: bool) -> FaceProblem:
    """From ``pressed``'s equilibrium, the orbicularis oris at LOOSER (a warm start, as a tracked
    frame is), on a problem with or without the relaxation."""
    problem = FaceProblem(model, lip_contact=LipContactSettings(), contact_relaxation=relaxation)
    problem.adopt(pressed.controls, pressed.u.x.array)
    assert problem.solve(activations=sphincter(model, LOOSER), jaw=jaw_pose(model.jaw, CLOSED)).converged
    return problem


@pytest.fixture(scope="module")
def pressed(model):
    return pressed_lips(model)


@pytest.fixture(scope="module")
def relaxed(pressed, model):
    return loosened(pressed, model, True)


def test_from_a_pressed_equilibrium_the_equilibrium_newton_reaches_without_it(pressed, relaxed, model):
    """Pressed lips have more than one equilibrium (from rest, with and without the relaxation,
    two 0.5 mm apart whose energies differ by 0.04 %); from a nearby one, as in tracking, both
    reach the same."""
    plain = loosened(pressed, model, False)
    assert relaxed.solver.relaxation.local_iterations > 0 and plain.solver.relaxation is None
    forces = [problem.lips.nodal_forces(problem.u.x.array) for problem in (relaxed, plain)]
    assert np.abs(forces[0] - forces[1]).max() <= 1e-4 * np.abs(forces[1]).max()
    assert np.abs(relaxed.u.x.array - plain.u.x.array).max() < 1e-6  # mm
    assert relaxed.residual_norm() < 1e-6


def test_no_point_the_relaxation_tries_penetrates(model):
    problem = FaceProblem(model, lip_contact=LipContactSettings(), contact_relaxation=True)
    relaxation, lips = problem.solver.relaxation, problem.lips
    iterates = LipIterates(lips, problem.V)
    tried = []

    def recorded(evaluate):
        def evaluated(x, b, *forms):
            evaluate(x, b, *forms)  # sets the unknown (with ghosts) to x
            tried.append((lips.min_distance(problem.u.x.array), lips.penetration(problem.u.x.array)))
        return evaluated
    relaxation.assemble, relaxation.full_residual = recorded(relaxation.assemble), recorded(relaxation.full_residual)
    problem.solver.snes.setMonitor(iterates)
    assert problem.solve(activations=sphincter(model), jaw=jaw_pose(model.jaw, CLOSED)).converged
    problem.solver.snes.cancelMonitor()
    distances, depths = np.array(tried).T
    assert len(tried) > 10 and distances.min() > 0.0 and depths.max() == 0.0
    assert min(iterates.distances) > 0.0 and max(iterates.depths) == 0.0


def test_relaxing_cuts_the_contact_nodes_residual_and_holds_every_other_dof(relaxed, model):
    """From the pressed equilibrium with the lower lip's nodes moved 0.01 mm down (off equilibrium
    at the lips and the flesh around them), one relaxation brings the residual of the nodes in
    contact down and leaves every other dof where it was."""
    solver, lips = relaxed.solver, relaxed.lips
    x = relaxed.u.vector.copy()
    moved = x.copy()
    owned = np.isin(lips.surface.owned_nodes, lips.lower_nodes)
    moved.array.reshape(-1, 3)[lips.surface.owned_blocks[owned]] -= 0.01 * lips.up
    contact_dofs = np.zeros(x.getLocalSize(), dtype=bool)
    contact_dofs.reshape(-1, 3)[lips.surface.pushed_blocks(lips.nodal_forces(moved.array_r))] = True
    residual = x.duplicate()

    def residual_norms(state):
        """The residual's norm on the nodes in contact and on every other dof."""
        solver.relaxation.full_residual(state, residual)
        squares = [np.sum(residual.array_r[where] ** 2) for where in (contact_dofs, ~contact_dofs)]
        return [MPI.COMM_WORLD.allreduce(square) ** 0.5 for square in squares]

    contact_before, rest_before = residual_norms(moved)
    relaxed_state = moved.copy()
    solver.relaxation.relax(relaxed_state, np.zeros(0, dtype=np.int32))  # no lip node is held
    contact_after, _ = residual_norms(relaxed_state)
    # It stops once the contact nodes' residual is below RELAXATION_REDUCTION of the rest's.
    assert contact_after <= RELAXATION_REDUCTION * rest_before < contact_before
    assert np.array_equal(relaxed_state.array_r[~contact_dofs], moved.array_r[~contact_dofs])
    assert lips.min_distance(relaxed.u.x.array) > 0.0
    x.copy(relaxed.u.vector)
    relaxed.u.vector.ghostUpdate(addv=PETSc.InsertMode.INSERT, mode=PETSc.ScatterMode.FORWARD)


def test_patch_residual_is_the_residual_on_the_contact_surface(relaxed):
    """The local Newton's residual, assembled over the cells around the contact surfaces only,
    is the whole face's on every node of those surfaces."""
    relaxation, lips = relaxed.solver.relaxation, relaxed.lips
    x = relaxed.u.vector.copy()
    moved = x.copy()
    moved.array.reshape(-1, 3)[lips.surface.owned_blocks] -= 0.01 * lips.up
    full, patch = moved.duplicate(), moved.duplicate()
    relaxation.full_residual(moved, full)
    relaxation.patch_residual(moved, patch)
    rows = (3 * lips.surface.owned_blocks[:, None] + np.arange(3)).reshape(-1)
    scale = MPI.COMM_WORLD.allreduce(np.abs(full.array_r[rows]).max(initial=0.0), op=MPI.MAX)
    assert scale > 1.0  # mN: off equilibrium
    difference = np.abs(patch.array_r[rows] - full.array_r[rows]).max(initial=0.0)
    assert MPI.COMM_WORLD.allreduce(difference, op=MPI.MAX) <= 1e-9 * scale
    x.copy(relaxed.u.vector)
    relaxed.u.vector.ghostUpdate(addv=PETSc.InsertMode.INSERT, mode=PETSc.ScatterMode.FORWARD)


@pytest.mark.parametrize("share, relaxes", [(0.0, True), (1.01, False)])
def test_by_default_the_relaxation_starts_once_newton_crawls_on_the_contact_nodes(model, monkeypatch, share, relaxes):
    """``contact_relaxation=None`` (the default) relaxes the contact nodes from the correction at
    which CRAWL_CUTS corrections in a row were cut by a bound with CRAWL_CONTACT_SHARE of the
    residual's square on the contact nodes: the lips closing from rest, whose corrections the
    lips' bound cuts from the first on, with a share of 0 after the first cut correction, with a
    share above 1 never. Either way no iterate penetrates and the lips end pressed."""
    monkeypatch.setattr(solver_module, "CRAWL_CUTS", 1)
    monkeypatch.setattr(solver_module, "CRAWL_CONTACT_SHARE", share)
    problem = FaceProblem(model, lip_contact=LipContactSettings())
    assert problem.solver.contact_relaxation is None
    iterates = LipIterates(problem.lips, problem.V)
    problem.solver.snes.setMonitor(iterates)
    assert problem.solve(activations=sphincter(model), jaw=jaw_pose(model.jaw, CLOSED)).converged
    problem.solver.snes.cancelMonitor()
    assert (problem.solver.relaxation.local_iterations > 0) == relaxes
    assert min(iterates.distances) > 0.0 and max(iterates.depths) == 0.0
    assert problem.lips.pairs(problem.u.x.array) > 20


def test_a_slow_fall_on_the_lips_relaxes_the_contact_nodes_instead_of_refactorising(pressed, model, caplog):
    """With the factor kept across solves, the lips' nodes count for the residual's slow fall
    (``LipContact.relax_on_slow_fall``): the lips let go of each other from their pressed
    equilibrium (the orbicularis oris off, the jaw opened 6 degrees; a warm start from the factor
    of that equilibrium, as a tracked frame's) with fewer factorisations than with the teeth's
    nodes' share alone (none here, so never relaxing), to the same equilibrium, no iterate
    penetrating."""
    solved = {}
    for lips_count in (True, False):
        problem = FaceProblem(model, lip_contact=LipContactSettings(), reuse_factorization=True)
        problem.lips.relax_on_slow_fall = lips_count
        problem.adopt(pressed.controls, pressed.u.x.array)
        problem.solver.factorize(newton_model=True)
        first = problem.solver.factorizations
        iterates = LipIterates(problem.lips, problem.V)
        problem.solver.snes.setMonitor(iterates)
        with caplog.at_level("DEBUG", logger="face_dolfinx.equilibrium.solver"):
            assert problem.solve(activations=sphincter(model, 0.0), jaw=jaw_pose(model.jaw, np.radians(6.0))).converged
        problem.solver.snes.cancelMonitor()
        started = MPI.COMM_WORLD.bcast(any("the factor kept" in record.getMessage() for record in caplog.records))
        caplog.clear()
        solved[lips_count] = problem, started, problem.solver.factorizations - first
        assert min(iterates.distances) > 0.0 and max(iterates.depths) == 0.0
    (relaxed, started, factorizations), (plain, plain_started, plain_factorizations) = solved[True], solved[False]
    assert started and not plain_started
    assert factorizations < plain_factorizations
    assert np.abs(relaxed.u.x.array - plain.u.x.array).max() < 1e-4  # mm


def test_sphere_pressed_into_the_slab_with_relaxation():
    relaxed, plain = (pressed_slab(depth=1.5, contact_relaxation=flag) for flag in (True, False))
    assert relaxed.solver.relaxation.local_iterations > 0
    forces = [problem.contact.nodal_forces(problem.u.x.array).sum(axis=0) for problem in (relaxed, plain)]
    assert np.abs(forces[0] - forces[1]).max() <= 1e-6 * np.abs(forces[1]).max()
    assert 0.0 < relaxed.contact.min_gap(relaxed.u.x.array) < relaxed.contact.dhat


def test_same_result_on_one_rank(relaxed, builtin_model_path):
    model = load_model(builtin_model_path, MPI.COMM_SELF)
    alone = loosened(pressed_lips(model), model, True)
    forces = [problem.lips.nodal_forces(problem.u.x.array) for problem in (relaxed, alone)]
    assert np.abs(forces[0] - forces[1]).max() <= 1e-4 * np.abs(forces[1]).max()
    assert relaxed.lips.min_distance(relaxed.u.x.array) == pytest.approx(alone.lips.min_distance(alone.u.x.array),
                                                                         rel=1e-4)
