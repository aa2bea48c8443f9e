"""FaceProblem on a small muscle slab: derivatives, linearity in activations, robustness, MPI
(distributed against serial on the small built-in face too).

Finite-difference checks: the residual is the derivative of the energy, the tangent is the
derivative of the residual, and the active force f_i is exactly R(a) - R(a + e_i) because the
energy is linear in each activation (sifakis2005 eq. 1).
"""
from mpi4py import MPI
from petsc4py import PETSc
import numpy as np
import pytest
from dolfinx import fem
import dolfinx.fem.petsc as fem_petsc

from face_dolfinx.model.bones import AffineMap, jaw_pose, rigid_map, rotation
from face_dolfinx.model.folder import load_model
from face_dolfinx.physics.points import PointEvaluator
from face_dolfinx.physics.problem import BLEND_WIDTHS, Controls, FaceProblem
from slab import slab_model


@pytest.fixture(scope="module")
def problem():
    return FaceProblem(slab_model())


def random_displacement(problem, scale, seed):
    rng = np.random.default_rng(seed)
    X = problem.V.tabulate_dof_coordinates()[:, :3]
    # A smooth field (so no element inverts) with a random direction and phase.
    k = rng.normal(size=3) * 0.1
    amplitude = rng.normal(size=3) * scale
    values = amplitude[None, :] * np.sin(X @ k + rng.uniform(0, 6))[:, None]
    return values.reshape(-1)


def assemble(form):
    vec = fem_petsc.assemble_vector(form)
    vec.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
    return vec


def test_residual_is_energy_derivative_and_tangent_is_residual_derivative(problem):
    p = problem
    p.set_controls(Controls(np.array([0.7, 0.3, 1.0]), AffineMap(), AffineMap()))
    p.u.x.array[:] = random_displacement(p, 1.5, seed=1)
    direction = fem.Function(p.V)
    direction.x.array[:] = random_displacement(p, 1.0, seed=2)
    base = p.u.x.array.copy()

    def energy_at(h):
        p.u.x.array[:] = base + h * direction.x.array
        return p.energy()

    residual = assemble(p.solver.residual_form)
    p.u.x.array[:] = base
    derivative = residual.dot(direction.vector)
    h = 1e-4
    fd = (energy_at(h) - energy_at(-h)) / (2 * h)
    assert fd == pytest.approx(derivative, rel=1e-7)

    p.u.x.array[:] = base
    K = fem_petsc.assemble_matrix(p.solver.jacobian_form)
    K.assemble()
    K_dir = K.createVecLeft()
    K.mult(direction.vector, K_dir)

    def residual_at(h):
        p.u.x.array[:] = base + h * direction.x.array
        return assemble(p.solver.residual_form)

    fd_vec = residual_at(h) - residual_at(-h)
    fd_vec.scale(1 / (2 * h))
    fd_vec.axpy(-1.0, K_dir)
    assert fd_vec.norm() <= 1e-6 * K_dir.norm()
    p.u.x.array[:] = 0.0


@pytest.mark.parametrize("muscle", [0, 1, 2])
def test_active_force_is_exact_activation_derivative(problem, muscle):
    p = problem
    p.u.x.array[:] = random_displacement(p, 1.0, seed=3)
    activations = np.array([0.2, 0.5, 0.1])
    p.set_controls(Controls(activations, AffineMap(), AffineMap()))
    r0 = assemble(p.solver.residual_form)
    bumped = activations.copy()
    bumped[muscle] += 0.5
    p.set_controls(Controls(bumped, AffineMap(), AffineMap()))
    r1 = assemble(p.solver.residual_form)
    f_i = p.active_force(muscle)
    # Dirichlet rows are zero in f_i; compare on the free rows only.
    fem_petsc.set_bc(r0, p.bcs, scale=0.0)
    fem_petsc.set_bc(r1, p.bcs, scale=0.0)
    r0.axpy(-1.0, r1)
    r0.scale(1 / 0.5)  # (R(a) - R(a + h e_i)) / h = f_i exactly
    assert f_i.norm() > 1.0
    r0.axpy(-1.0, f_i)
    assert r0.norm() <= 1e-10 * f_i.norm()
    p.reset_to_rest()


def test_reset_to_rest_is_the_rest_equilibrium_without_a_solve():
    p = FaceProblem(slab_model())
    p.solve(activations=[0.5, 0.2, 0.8], jaw=rigid_map(rotation([0, 1, 0], 0.3), [40, 10, 5], [0, 0, 0]))
    factorizations = p.solver.factorizations
    p.reset_to_rest()
    assert p.controls.same_as(Controls(np.zeros(3), AffineMap(), AffineMap())) and not p.u.x.array.any()
    assert p.residual_norm() < 1e-12 and p.solver.bc_error() == 0.0
    assert p.solver.factorizations == factorizations


def test_equilibrium_all_muscles_and_large_jaw_motion_converge():
    p = FaceProblem(slab_model())
    report = p.solve(activations=[1.0, 1.0, 1.0])
    assert report.converged and p.residual_norm() < 1e-6
    contracted = p.u.x.array.copy()
    assert np.abs(contracted).max() > 1.0  # the muscles visibly contract the slab
    # A 70 degree turn of the far end pushes elements through inversion in one step.
    report = p.solve(jaw=rigid_map(rotation([0, 1, 0], 1.2), [40, 10, 5], [0, 0, -10]))
    assert report.converged and p.residual_norm() < 1e-6
    assert p.solver.bc_error() < 1e-8
    # Back to rest: the equilibrium is unique there, so the path does not matter.
    report = p.solve(activations=[0.0, 0.0, 0.0], jaw=AffineMap())
    assert np.abs(p.u.x.array).max() < 1e-6


def test_more_line_search_iterations_change_the_path_not_the_equilibrium():
    """fit --fast gives the critical-point line search 3 secant iterations per Newton step: more
    residual evaluations, the same equilibrium. Fewer than one is refused."""
    activations = [1.0, 0.5, 0.8]
    one, three = FaceProblem(slab_model()), FaceProblem(slab_model(), line_search_iterations=3)
    for p in (one, three):
        assert p.solve(activations=activations).converged
    assert three.solver.residual_evaluations > one.solver.residual_evaluations
    assert three.u.vector.norm() == pytest.approx(one.u.vector.norm(), rel=1e-10)
    assert three.energy() == pytest.approx(one.energy(), rel=1e-10)
    with pytest.raises(ValueError, match="line_search_iterations = 0"):
        FaceProblem(slab_model(), line_search_iterations=0)


def test_rigid_head_motion_is_exact_and_cheap():
    """A cranium motion moves everything rigidly: the predictor makes it a zero-iteration solve."""
    p = FaceProblem(slab_model())
    p.solve(activations=[0.5, 0.2, 0.8])
    X = p.V.tabulate_dof_coordinates()[:, :3]
    before = X + p.u.x.array.reshape(-1, 3)
    head = rigid_map(rotation([0.2, 1, 0.1], 0.6), [0, 10, 5], [3, -2, 1])
    report = p.solve(cranium=head)
    after = X + p.u.x.array.reshape(-1, 3)
    assert report.newton_iterations <= 1
    assert np.abs(after - head.apply(before)).max() < 1e-8


def test_a_prediction_that_flattens_a_few_cells_is_cut_short_around_them_only():
    """A Gauss-Newton prediction can be huge on a few nodes (where the tangent is nearly
    singular): here the next equilibrium with one inner node moved 40 mm through its neighbours.
    Newton starts from the prediction beyond the widest blend around that node's cells, from
    less than an eighth of the way at that node, with no cell flattened, and reaches the
    equilibrium; cut short as a whole (``bound_prediction_locally`` off) it starts a sixteenth of
    the way everywhere."""
    p = FaceProblem(slab_model())
    p.solve(activations=[0.2, 0.1, 0.3])
    start, start_controls = p.u.x.array.copy(), p.controls.copy()
    p.solve(activations=[0.8, 0.6, 0.9])
    target = p.u.x.array.copy()
    distance = np.linalg.norm(p.dof_coordinates - [20.0, 10.0, 5.0], axis=1)
    guess = target.copy()
    guess.reshape(-1, 3)[distance < 1e-8, 0] += 40.0
    newton, starts = p.solver.newton, []

    def recorded(**options):
        starts.append(p.u.x.array.copy())
        return newton(**options)

    p.solver.newton = recorded
    comm = MPI.COMM_WORLD
    for local in (True, False):
        p.adopt(start_controls, start)
        p.bound_prediction_locally = local
        report = p.solve(activations=[0.8, 0.6, 0.9], guess=guess)
        assert report.converged and report.load_steps == 1
        assert np.abs(p.u.x.array - target).max() < 1e-4
        assert p.solver.inversion_guard.min_ratio(starts[-1]) >= p.solver.inversion_guard.min_volume_ratio
        way = np.linalg.norm((starts[-1] - start).reshape(-1, 3), axis=1) / np.linalg.norm(
            (guess - start).reshape(-1, 3), axis=1).clip(1e-12)
        far = distance > np.sqrt(3 * 5.0 ** 2) + max(BLEND_WIDTHS)
        assert comm.allreduce(float(way[distance < 1e-8].max(initial=0.0)), op=MPI.MAX) < 0.125
        if local:
            assert comm.allreduce(float(np.abs(starts[-1] - guess).reshape(-1, 3)[far].max(initial=0.0)),
                                  op=MPI.MAX) < 1e-12
        else:
            assert comm.allreduce(float(way[far].max(initial=0.0)), op=MPI.MAX) <= 0.0625 + 1e-12


def test_bad_activations_are_rejected_with_names(problem):
    with pytest.raises(ValueError, match="across=1.5"):
        problem.activation_vector([0.0, 1.5, 0.2])
    with pytest.raises(ValueError, match="long=-0.1"):
        problem.activation_vector({"long": -0.1})
    with pytest.raises(KeyError, match="unknown muscle 'zygo'"):
        problem.activation_vector({"zygo": 0.5})
    with pytest.raises(ValueError, match="expected 3 activations"):
        problem.activation_vector([0.5, 0.5])


@pytest.mark.parametrize("body", ["slab", "face"])
def test_distributed_solution_matches_serial(body, request):
    """Same equilibrium on all ranks of COMM_WORLD as on one rank (COMM_SELF): displacements at
    probe points (the face's markers) to 1e-8 of the largest, and the same norm."""
    if body == "slab":
        def build(comm):
            return slab_model(comm=comm)
        controls = dict(activations=[0.9, 0.4, 0.7],
                        jaw=rigid_map(rotation([1, 0, 0], 0.3), [40, 10, 5], [0, 2, 0]))
        probes = np.array([[10.0, 5.0, 5.0], [25.0, 12.0, 3.0], [33.0, 18.0, 9.0]])
    else:
        path = request.getfixturevalue("builtin_model_path")

        def build(comm):
            return load_model(path, comm)
        model = build(MPI.COMM_SELF)
        controls = dict(activations=model.expressions["pucker"], jaw=jaw_pose(model.jaw, 0.15, 1.0, 2.0))
        probes = np.array(list(model.markers.values()))
    world, alone = (FaceProblem(build(comm)) for comm in (MPI.COMM_WORLD, MPI.COMM_SELF))
    for problem in (world, alone):
        assert problem.solve(**controls).converged
    a, b = (PointEvaluator(problem.V, probes).values(problem.u.x.array) for problem in (world, alone))
    assert np.abs(a - b).max() <= 1e-8 * np.abs(b).max()
    assert world.u.vector.norm() == pytest.approx(alone.u.vector.norm(), rel=1e-8)


def test_bone_frames_are_interpolated_along_their_motion():
    """Continuation half way through a turn: the frame has turned by half the angle about the
    same axis and is still rigid (the linear blend of the 12 numbers shrinks it by cos(theta/2))."""
    axis, centre = np.array([0.3, 1.0, -0.2]), np.array([40.0, 10.0, 5.0])
    shift = 1.5 * axis  # a screw: turn about an axis through centre and slide along it
    start = rigid_map(rotation(axis, 0.2), centre, [0, 0, 0])
    end = rigid_map(rotation(axis, 1.4), centre, shift)
    half = start.geodesic(end, 0.5)
    assert np.allclose(half.matrix, rotation(axis, 0.8), atol=1e-12)
    assert np.allclose(half.apply(centre), centre + 0.5 * shift, atol=1e-10)
    blended = start.interpolate(end, 0.5)
    assert abs(np.linalg.svd(blended.matrix, compute_uv=False).min() - np.cos(0.6)) < 1e-12
    assert start.geodesic(end, 0.0) is start and start.geodesic(end, 1.0) is end


def test_continuation_gives_up_only_when_its_step_is_too_small():
    """A walk that needs steps of at most 0.3 of the way fails at steps 1 and 0.5 again and again
    but gets there with max_halvings = 2 (steps down to 0.25); with max_halvings = 1 it stops at
    the last equilibrium and says how far it got."""
    from face_dolfinx.equilibrium.solver import EquilibriumError

    p = FaceProblem(slab_model())
    reached = {"t": 0.0, "load": 0.0}

    def set_controls(t):
        reached["load"] = t

    def newton():
        ok = reached["load"] - reached["t"] <= 0.3
        if ok:
            reached["t"] = reached["load"]
        return ok, 1, "converged" if ok else "DIVERGED_LINE_SEARCH (-6)"

    p.solver.newton = newton
    report = p.solver.solve_continuation(set_controls, max_halvings=2)
    assert report.converged and reached["t"] == 1.0 and report.load_steps == 4
    reached.update(t=0.0, load=0.0)
    with pytest.raises(EquilibriumError, match="beyond 0.0000 .* step of 0.5 of the way failed"):
        p.solver.solve_continuation(set_controls, max_halvings=1)
    assert reached["load"] == 0.0


def test_kept_coefficient_data_follow_the_unknown_and_repack_when_stale(problem):
    """``PackedCoefficients`` (which FaceProblem's solver assembles with) reproduces DOLFINx's
    own packing whenever the unknown changes, and needs ``stale`` when another coefficient does
    (the owner's controls_changed())."""
    from dolfinx.fem.assemble import pack_coefficients
    from face_dolfinx.equilibrium.solver import PackedCoefficients
    form = problem.solver.residual_form
    kept = PackedCoefficients(form, problem.u)
    rng = np.random.default_rng(4)
    saved_u = problem.u.x.array.copy()
    for _ in range(2):  # the first call packs everything, the second refreshes the unknown only
        problem.u.x.array[:] = rng.uniform(-0.1, 0.1, problem.u.x.array.size)
        packed, reference = kept.packed(), pack_coefficients(form)
        assert all(np.array_equal(packed[key], reference[key]) for key in reference)
    activation = problem.slots.activation[0]
    saved_activation = activation.x.array.copy()
    activation.x.array[:] = 0.7
    reference = pack_coefficients(form)
    assert not all(np.array_equal(kept.packed()[key], reference[key]) for key in reference)
    kept.stale = True
    assert all(np.array_equal(kept.packed()[key], reference[key]) for key in reference)
    activation.x.array[:] = saved_activation
    problem.u.x.array[:] = saved_u


@pytest.mark.parametrize("reuse", [False, True])
def test_a_failed_factorisation_is_followed_by_one_with_pivoting(reuse, caplog):
    """A factorisation that fails inside Newton (here: the first tangent made singular) makes
    PETSc skip every later one of the same analysis; the solver resets the preconditioner,
    factorises with pivoting for the rest of that solve and reaches the equilibrium of an unbroken
    problem (with factorisation reuse too, where Newton would otherwise start from the failed
    factor). The next solve factorises without pivoting again, and reaches its equilibrium."""
    activations = np.array([0.6, 0.3, 0.8])
    reference = FaceProblem(slab_model())
    reference.solve(activations=activations)
    problem = FaceProblem(slab_model(), reuse_factorization=reuse)
    solver = problem.solver
    assemble, assembled = solver.assemble_tangent, []

    def singular_first(A):
        assemble(A)
        if not assembled:
            A.zeroEntries()
            A.assemble()
        assembled.append(A)

    solver.assemble_tangent = singular_first
    assert problem.solve(activations=activations).converged
    assert len(assembled) > 1
    assert MPI.COMM_WORLD.rank != 0 or "retrying the Newton solve with pivoting" in caplog.text
    # Each problem has its own distribution under MPI: compare numbering-free quantities.
    assert problem.u.vector.norm() == pytest.approx(reference.u.vector.norm(), rel=1e-10)
    assert problem.energy() == pytest.approx(reference.energy(), rel=1e-10)
    assert solver.pivoting
    assert problem.solve(activations=activations / 2).converged
    reference.solve(activations=activations / 2)
    assert not solver.pivoting
    assert problem.u.vector.norm() == pytest.approx(reference.u.vector.norm(), rel=1e-10)
