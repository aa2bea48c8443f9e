"""The solver's parts that can be tested alone: the factorisation-reuse policy on scripted Newton
iterations, the PETSc options a solver writes under its prefix, Newton on a tangent whose exact
part is indefinite (a double well), when continuation gives up (a scripted Newton), and the
cells the inversion guard finds a step flattening."""
import math
import re

from mpi4py import MPI
import numpy as np
from petsc4py import PETSc
import pytest
from dolfinx import fem

from face_dolfinx.equilibrium.solver import FactorReusePolicy, InversionGuard, PetscOptionsPrefix, QuasistaticSolver
from face_dolfinx.physics.problem import FaceProblem
from face_dolfinx.sensitivities.columns import EquilibriumSensitivity
from slab import slab_model


def newton(policy, iterations, linear_iterations=None, old_factor_release=None, release=math.inf):
    """Drive ``policy`` as QuasistaticSolver does through Newton iterations given as (residual
    norm, correction size, step cut by the guard[, the energy terms' bound of the step]); with
    energy terms, ``old_factor_release`` gives R . K0^-1 R and every correction releases
    ``release``. Returns, per iteration, whether it kept the factor."""
    kept = []
    policy.start_solve()
    for k, (norm, correction, cut, *bound) in enumerate(iterations):
        policy.record_residual(k, norm)
        keep = policy.keep_factor(k, None if linear_iterations is None else linear_iterations[k], old_factor_release)
        if not keep:
            policy.factorised(in_newton=True)
        kept.append(keep)
        policy.record_correction(correction, cut, *bound, release=release)
    return kept


def test_a_solve_refactorises_until_it_converges_then_finishes_with_its_last_factor():
    policy = FactorReusePolicy()  # refresh_contraction 0.25, converging_correction 0.1 mm
    kept = newton(policy, [
        (1e4, 5.0, False),    # iteration 0: no factor yet
        (1e3, 0.05, False),   # cut 10x, but the correction that led here was 5 mm: refresh
        (1e2, 0.01, False),   # cut 10x after a 0.05 mm correction: keep
        (5e1, 1e-3, False),   # one slow cut (0.5), fast over two (sqrt(0.1 * 0.5) = 0.22): keep
        (2.5e1, 1e-4, False),  # two slow cuts (0.5, 0.5): refresh
    ])
    assert kept == [False, False, True, True, False]
    assert not policy.converging_phase  # the last correction came from a fresh factor
    # A new solve starts with a fresh factor whatever the last one held, ...
    assert newton(policy, [(1e3, 0.01, False)]) == [False]
    # ... and a step the guard had to cut refreshes the factor even when Newton contracts.
    assert newton(policy, [(1e3, 0.01, False), (1e2, 0.01, True), (1e1, 0.01, False)]) == [False, True, False]


def test_converging_phase_is_judged_on_the_step_size():
    policy = FactorReusePolicy()
    newton(policy, [(1e4, 0.05, False), (1e2, 0.01, False)])
    assert policy.converging_phase and policy.correction_size == 0.01


def test_no_converging_correction_means_a_fresh_factor_every_iteration():
    policy = FactorReusePolicy(converging_correction=0.0)
    assert newton(policy, [(1e4, 1e-3, False), (1e2, 1e-5, False), (1.0, 1e-7, False)]) == [False] * 3


def test_reuse_across_solves_keeps_the_factor_while_every_iteration_contracts_enough():
    policy = FactorReusePolicy(across_solves=True, refresh_contraction=0.25)
    # No factor yet: the first iteration assembles one.
    assert newton(policy, [(1e4, 5.0, False), (1e3, 0.5, False), (2e2, 0.1, False), (1e2, 0.01, False)]) \
        == [False, True, True, False]  # cuts 0.1 and 0.2 keep it, 0.5 does not
    assert not policy.used_only_an_old_factor
    # The next solve starts from that factor; one that never refactorises says so.
    assert newton(policy, [(1e2, 0.01, False), (1e1, 1e-3, False)]) == [True, True]
    assert policy.used_only_an_old_factor and not policy.converging_phase
    policy.forget_factor()
    assert newton(policy, [(1e2, 0.01, False)]) == [False]
    # A cut step refreshes here too.
    assert newton(policy, [(1e2, 0.01, True), (1e1, 0.01, False)]) == [True, False]


def test_a_step_shortened_by_a_contact_bound_is_judged_by_its_length():
    """A collision-free bound that lets a correction go a fraction t of the way: the residual of
    the quadratic model falls by t, so the factor is kept when it fell by 1 - t (1 - 0.25)."""
    policy = FactorReusePolicy(across_solves=True, refresh_contraction=0.25)
    steps = [(1e4, 1.0, False, 0.2), (8.5e3, 1.0, False, 0.2), (7.7e3, 1.0, False), (1e3, 1.0, False)]
    # 0.85 after a fifth of a step: kept; 0.906 after another fifth: refreshed; the full step's
    # 0.13 keeps the new factor.
    assert newton(policy, steps) == [False, True, False, True]
    # Without the bound the same 0.85 refreshes the factor.
    assert newton(policy, [(1e4, 1.0, False), (8.5e3, 1.0, False)]) == [True, False]


def test_an_old_factor_whose_bounded_steps_crawl_is_refreshed():
    """Corrections that a contact bound lets go a twentieth of the way, each cutting the residual
    by 0.94 (better than the 0.96 a step of that length achieves, so each alone keeps the factor):
    after six such corrections of the old factor in a row it is refreshed, and the count starts
    again after it; a faster cut in between (0.85) starts it again too. Without the rule the factor
    is kept throughout."""
    def crawl(cuts):
        norms = np.cumprod([1e4] + cuts)
        return [(norm, 1.0, False, 0.05) for norm in norms]
    steps = crawl([0.94] * 14)
    policy = FactorReusePolicy(across_solves=True, refresh_contraction=0.25)
    # Iteration 0 factorises and its factor is kept once; the old factor's corrections of
    # iterations 1-6 crawl, so iteration 7 refactorises; again at 14.
    assert newton(policy, steps) == [False, True] + [True] * 5 + [False] + [True] * 6 + [False]
    interrupted = crawl([0.94] * 4 + [0.85] + [0.94] * 6)
    assert newton(FactorReusePolicy(across_solves=True, refresh_contraction=0.25), interrupted) == \
        [False] + [True] * 10 + [False]
    never = FactorReusePolicy(across_solves=True, refresh_contraction=0.25, crawl_refresh_iterations=None)
    assert newton(never, steps) == [False] + [True] * 14


def test_reuse_across_solves_keeps_a_fresh_factor_for_one_more_iteration():
    """A fresh tangent whose correction cut the residual slowly (a contact barrier settling) is
    kept for the next iteration; a slow cut from the older factor then refreshes it."""
    policy = FactorReusePolicy(across_solves=True, refresh_contraction=0.25)
    steps = [(1e4, 1.0, False), (8e3, 1.0, False), (7e3, 1.0, False), (6e3, 1.0, False), (5e3, 1.0, True),
             (4e3, 1.0, False)]
    # 0.8 after a fresh factor: kept; 0.875 after the kept one: refreshed; 0.86 after the fresh one:
    # kept; 0.83 after the kept one: refreshed; that fresh factor's step, cut by the guard: refreshed.
    assert newton(policy, steps) == [False, True, False, True, False, False]


def test_a_lifting_solve_keeps_a_fresh_factor_whose_correction_the_guard_cut_for_one_more_iteration():
    """In a solve that lifts held nodes far to their Dirichlet values (``QuasistaticSolver.newton(lifting=True)``:
    a contact object's push-out or carry) a fresh factor whose correction the inversion guard cut is
    kept for the next iteration, and a cut correction from the kept factor refreshes it; elsewhere
    every cut correction refreshes the factor."""
    steps = [(1e4, 1.0, True), (8e3, 1.0, True), (7e3, 1.0, True), (6e3, 1.0, True)]
    lifting = FactorReusePolicy(across_solves=True, refresh_contraction=0.25)
    lifting.keeps_cut_fresh_factor = True
    assert newton(lifting, steps) == [False, True, False, True]
    assert newton(FactorReusePolicy(across_solves=True, refresh_contraction=0.25), steps) == [False] * 4


def test_with_energy_terms_a_slow_residual_cut_keeps_a_factor_whose_energy_norm_contracts():
    """Pressed lips hold most of the residual's norm and little of its energy: where the residual
    norm fell too slowly after a correction from the old factor, that factor is kept if the energy
    norm of the residual by it, R . K0^-1 R (a solve, asked for only then), fell by the expected
    ratio squared since its last correction, or if its correction would release less than the
    energy tolerance (the solve stops after it); a negative one (no descent) refreshes it."""
    policy = FactorReusePolicy(across_solves=True, refresh_contraction=0.25)
    asked = []
    policy.start_solve()

    def iteration(k, norm, release_by_old_factor, release_tolerance=0.0):
        """Newton iteration k at residual ``norm``: whether it kept the factor."""
        policy.record_residual(k, norm)

        def old_factor_release():
            asked.append(k)
            return release_by_old_factor
        keep = policy.keep_factor(k, None, old_factor_release, release_tolerance)
        if not keep:
            policy.factorised(in_newton=True)
        return keep

    kept = [iteration(0, 1e4, None)]  # no factor yet
    policy.record_correction(1.0, release=1000.0)
    kept.append(iteration(1, 8e3, None))  # a fresh factor serves one more iteration whatever its cut
    policy.record_correction(1.0, release=400.0)
    kept.append(iteration(2, 7e3, 20.0))  # residual x0.875, energy norm x0.22 (20 <= 0.25^2 400): kept
    policy.record_correction(1.0, release=20.0)
    kept.append(iteration(3, 6.5e3, 10.0, release_tolerance=6.0))  # x0.71 in energy, but releases 5 < 6
    policy.record_correction(1.0, release=10.0)
    kept.append(iteration(4, 6e3, 8.0))  # x0.89 in energy: refreshed
    policy.record_correction(1.0, release=8.0)
    kept.append(iteration(5, 1e3, 1e3))  # the residual cut 6-fold: kept without asking
    policy.record_correction(1.0, release=1.0)
    kept.append(iteration(6, 9e2, -1e-3))  # an old factor whose correction climbs the energy: refreshed
    assert kept == [False, True, True, True, False, True, False]
    assert asked == [2, 3, 4, 6]
    # Without the old factor's release (no energy terms) the residual norm alone decides.
    plain = FactorReusePolicy(across_solves=True, refresh_contraction=0.25)
    assert newton(plain, [(1e4, 1.0, False), (8e3, 1.0, False), (7e3, 1.0, False)]) == [False, True, False]


def test_where_the_solver_relaxes_the_contact_nodes_instead_a_slow_fall_keeps_the_factor():
    """``relaxes_instead`` is asked only where the residual's slow fall alone would refresh the
    factor (not at a solve's start, not after a fast cut, not after a cut step); where it says the
    solver relaxes the contact nodes instead, the factor is kept and counts as old."""
    policy = FactorReusePolicy(across_solves=True, refresh_contraction=0.25)
    asked, answers = [], iter([False, True])

    def relaxes_instead():
        asked.append(k)
        return next(answers)

    steps = [(1e4, 1.0, False), (8e3, 1.0, False), (7e3, 1.0, False), (1e3, 1.0, True), (9e2, 1.0, False),
             (8e2, 1.0, False), (7e2, 1.0, False)]
    kept = []
    policy.start_solve()
    for k, (norm, correction, cut) in enumerate(steps):
        policy.record_residual(k, norm)
        keep = policy.keep_factor(k, None, relaxes_instead=relaxes_instead)
        if not keep:
            policy.factorised(in_newton=True)
        kept.append(keep)
        policy.record_correction(correction, cut)
    # 0: no factor; 1: a fresh factor's next iteration; 2: x0.875 from the old one, the solver does
    # not relax: refreshed; 3: x0.14, kept without asking, its step cut; 4: slow (x0.9) after that cut:
    # refreshed without asking; 5: the fresh factor's next iteration; 6: slow, the solver relaxes: kept.
    assert kept == [False, True, False, True, False, True, True]
    assert asked == [2, 6]
    assert not policy.fresh_factor


def test_a_correction_cut_short_by_a_contact_bound_refreshes_the_old_factor_whatever_its_energy_norm():
    """The old factor's correction that a collision-free bound cut below ``judged_step_bound`` of its
    length (pairs that came close since the factor was made, whose barrier it does not hold) refreshes
    it even where the residual's energy norm fell as a step of that length should; above that bound
    the energy norm still keeps it."""
    def kept_after(bound, energy_norm, judged_step_bound):
        """Whether iteration 2, after a correction from the old factor cut to ``bound`` (the
        residual norm 0.1 % lower, less than such a step achieves), keeps the factor whose
        energy norm of the residual went from 1000 to ``energy_norm``."""
        policy = FactorReusePolicy(across_solves=True, refresh_contraction=0.25, judged_step_bound=judged_step_bound)
        steps = [(norm, 1.0, False, bound) for norm in (1e4, 9.5e3, 9.49e3)]
        return newton(policy, steps, old_factor_release=lambda: energy_norm, release=1000.0)[-1]

    # A step of 0.01 of the way cuts the energy norm to (1 - 0.01 x 0.75)^2 = 0.985 of it: 980 is
    # as expected.
    assert kept_after(0.01, 980.0, judged_step_bound=0.0)
    assert not kept_after(0.01, 980.0, judged_step_bound=0.2)
    # 0.3 of the way: (1 - 0.3 x 0.75)^2 = 0.6.
    assert kept_after(0.3, 500.0, judged_step_bound=0.2)
    assert not kept_after(0.3, 700.0, judged_step_bound=0.2)


def test_krylov_on_the_old_factor_refreshes_when_a_linear_solve_slows():
    policy = FactorReusePolicy(across_solves=True, krylov_refresh_iterations=8)
    steps = [(1e4, 1.0, False), (9e3, 1.0, False), (8e3, 1.0, False), (7e3, 1.0, False)]
    # Residual contractions of 0.875-0.9 keep the factor as long as the linear solves are quick.
    assert newton(policy, steps, linear_iterations=[0, 8, 9, 3]) == [False, True, False, True]


def test_krylov_on_the_old_factor_refreshes_when_newton_stalls():
    policy = FactorReusePolicy(across_solves=True, krylov_refresh_iterations=8)
    steps = [(1e4, 1.0, False), (5e3, 1.0, False), (4.9e3, 1.0, False), (4.85e3, 1.0, False), (1e3, 1.0, False)]
    # Quick linear solves, but the residual falls by 0.98-0.99 per iteration: a fresh factor.
    assert newton(policy, steps, linear_iterations=[0, 2, 2, 2, 2]) == [False, True, True, False, True]


def test_a_solver_writes_its_options_under_its_prefix_and_the_user_wins():
    database, prefix = PETSc.Options(), "unit_options_"
    database[prefix + "snes_max_it"] = 3  # the user's, as from the command line
    try:
        first = PetscOptionsPrefix(prefix)
        first.replace({"snes_max_it": 25, "snes_rtol": 1e-6, "snes_linesearch_type": "cp"})
        assert database.getInt(prefix + "snes_max_it") == 3
        assert database.getReal(prefix + "snes_rtol") == 1e-6
        # The next solver under this prefix: what the first wrote and it does not want is gone,
        # its own values replace the first's, and the user's option stays.
        PetscOptionsPrefix(prefix).replace({"snes_max_it": 10, "snes_linesearch_type": "bt"})
        assert not database.hasName(prefix + "snes_rtol")
        assert database.getString(prefix + "snes_linesearch_type") == "bt"
        assert database.getInt(prefix + "snes_max_it") == 3
        # An option a solver wrote and the user changed since is the user's from then on.
        database[prefix + "snes_linesearch_type"] = "basic"
        PetscOptionsPrefix(prefix).replace({"snes_linesearch_type": "cp"})
        assert database.getString(prefix + "snes_linesearch_type") == "basic"
        PetscOptionsPrefix(prefix).replace({})
        assert database.getString(prefix + "snes_linesearch_type") == "basic"
        assert database.getInt(prefix + "snes_max_it") == 3
    finally:
        for name in ("snes_max_it", "snes_linesearch_type"):
            database.delValue(prefix + name)


def test_a_user_face_option_overrides_the_problem_default():
    """-face_snes_max_it given by the user (here after other solvers of this process wrote their
    own value) beats the solver's default (25) and a FaceProblem's petsc_options; the FaceProblem
    built after the user's option is gone gets the default back."""
    FaceProblem(slab_model())
    database = PETSc.Options()
    database["face_snes_max_it"] = 7
    try:
        problem = FaceProblem(slab_model(), petsc_options={"snes_max_it": 40})
        assert problem.solver.iteration_limit == 7
        assert database.getInt("face_snes_max_it") == 7
    finally:
        database.delValue("face_snes_max_it")
    assert FaceProblem(slab_model()).solver.iteration_limit == 25


def test_a_converging_phase_finishes_past_the_iteration_limit():
    """The iteration limit (snes_max_it) stops a Newton whose corrections still come from fresh
    factors; one in its converging phase (a kept factor contracting the residual) goes on to its
    step test. The slab's three muscles at 1: fresh factors up to the 4th iterate, the kept one's
    corrections from there."""
    from face_dolfinx.equilibrium.solver import CONVERGING_PHASE_ITERATIONS
    phases = {}
    for limit in (25, 5, 3):
        problem = FaceProblem(slab_model(), petsc_options={"snes_max_it": limit})
        policy = problem.solver.reuse_policy
        phases[limit] = []
        problem.solver.snes.setMonitor(lambda snes, it, norm: phases[limit].append(policy.converging_phase))
        report = problem.solve(activations=[1.0, 1.0, 1.0])
        assert report.converged
        if limit == 25:
            free = report.newton_iterations
            assert report.load_steps == 1 and phases[25][4:] == [True] * (free - 3) and not any(phases[25][:4])
            assert free - 5 < CONVERGING_PHASE_ITERATIONS
        elif limit == 5:
            assert report.load_steps == 1 and report.newton_iterations == free > limit
        else:
            assert report.load_steps > 1  # Newton stopped at 3: the continuation took over


def test_the_tangent_structure_is_explicit():
    problem = FaceProblem(slab_model())
    assert problem.solver.tangent_structure == "spd"
    assert problem.solver.tangent.isSymmetricKnown() == (True, True)
    with pytest.raises(ValueError, match="tangent = 'cholesky'"):
        QuasistaticSolver(problem.solver.residual_form, problem.u, problem.bcs, tangent="cholesky")


def test_a_factorisation_that_meets_a_zero_pivot_is_made_again_with_pivoting():
    """The tangent for the sensitivities with an exact zero pivot: a bone node's x and y rows
    (decoupled identity rows) turned into [[0, 1], [1, 0]], which the factorisation without
    pivoting cannot take and the one with pivoting can. The factor is made again with pivoting and
    gives the columns of the untouched tangent (the sensitivities' right-hand sides vanish on the
    bone dofs; a solve on the failed factor raises MUMPS's error -3)."""
    problem = FaceProblem(slab_model())
    problem.solve(activations={"across": 0.5})
    solver, sensitivity = problem.solver, EquilibriumSensitivity(problem)
    sensitivity.factor()
    expected = sensitivity.activation_columns()
    start = problem.V.dofmap.index_map.local_range[0]
    owned = problem.bone_blocks[problem.bone_blocks < problem.V.dofmap.index_map.size_local]
    assemble = solver.assemble_tangent

    def with_a_zero_pivot(A):
        assemble(A)
        if len(owned):
            rows = 3 * (start + owned[0]) + np.arange(2, dtype=PETSc.IntType)
            A.setValues(rows, rows, [[0.0, 1.0], [1.0, 0.0]], addv=PETSc.InsertMode.INSERT_VALUES)
        A.assemble()

    assert MPI.COMM_WORLD.allreduce(len(owned), op=MPI.SUM) > 0
    solver.assemble_tangent = with_a_zero_pivot
    solver.controls_changed()  # the factor is made again
    assert sensitivity.factor() == 0.0
    assert np.abs(sensitivity.activation_columns() - expected).max() <= 1e-8 * np.abs(expected).max()
    assert solver.pivoting


def test_the_inversion_guard_names_the_vertices_of_the_cells_a_step_flattens():
    """A step that moves the slab 2 mm and one inner node 30 mm more, through its neighbours: the
    guard cuts it as a whole to an eighth or less (``step_fraction``), and the vertices of the
    cells it flattens (``flattened_blocks``) are that node and nodes of its cells only; the
    translation alone flattens none."""
    V = fem.VectorFunctionSpace(slab_model().mesh, ("CG", 1))
    guard = InversionGuard(V)
    X = V.tabulate_dof_coordinates()[:, :3]
    distance = np.linalg.norm(X - [20.0, 10.0, 5.0], axis=1)
    translation = np.tile([2.0, 0.0, 0.0], (len(X), 1))
    step = translation.copy()
    step[distance < 1e-8, 0] += 30.0
    at_rest = np.zeros(step.size)
    comm = MPI.COMM_WORLD
    assert guard.step_fraction(at_rest, -step.reshape(-1)) <= 0.125
    flattened = guard.flattened_blocks(at_rest, step.reshape(-1))
    assert comm.allreduce(bool(np.any(distance[flattened] < 1e-8)), op=MPI.LOR)
    assert comm.allreduce(float(distance[flattened].max(initial=0.0)), op=MPI.MAX) < np.sqrt(3 * 5.0 ** 2) + 1e-8
    assert comm.allreduce(len(guard.flattened_blocks(at_rest, translation.reshape(-1)))) == 0


def test_a_factor_is_not_reused_under_other_dirichlet_conditions():
    """Reuse across solves: the nodes of the slab's middle get a condition of their own, a little
    displaced (as a contact object holds the lining it carries). The factor of the last tangent
    has the flesh's rows for them, not the identity, so its corrections would move them off their
    values (the slab's Newton recovers with fresh factors). The factor counts as one of other
    conditions while the condition is added and after it is removed, and Newton reaches the held
    values."""
    from dolfinx import fem
    problem = FaceProblem(slab_model(), reuse_factorization=True)
    problem.solve(activations={"across": 0.5})
    solver = problem.solver
    middle = np.flatnonzero(np.abs(problem.dof_coordinates[:, 0] - 20.0) < 3.0).astype(np.int32)
    values = fem.Function(problem.V)
    values.x.array[:] = problem.u.x.array
    values.x.array.reshape(-1, 3)[middle, 2] += 0.5  # mm up
    held = fem.dirichletbc(values, middle)
    solver.factorize()
    assert solver.factor_distance() == 0.0
    solver.bcs.append(held)
    try:
        assert solver.factor_distance() == np.inf
        converged, _, reason = solver.newton()
        assert converged, reason
        assert solver.bc_error() < 1e-10
    finally:
        solver.bcs.remove(held)
    assert solver.factor_distance() == np.inf


def linear_block():
    """A 10 mm cube of 4 x 4 x 4 x 6 P1 tetrahedra, linear elastic (small strain, mu 10 kPa,
    lambda 10 kPa): its space, unknown, energy and residual."""
    import ufl
    from dolfinx import mesh as dmesh
    domain = dmesh.create_box(MPI.COMM_WORLD, [np.zeros(3), np.full(3, 10.0)], [4, 4, 4],
                              dmesh.CellType.tetrahedron)
    V = fem.VectorFunctionSpace(domain, ("Lagrange", 1))
    u = fem.Function(V)
    eps = ufl.sym(ufl.grad(u))
    dx = ufl.dx(metadata={"quadrature_degree": 2})
    energy = (10.0 * ufl.inner(eps, eps) + 5.0 * ufl.tr(eps) ** 2) * dx
    return V, u, energy, ufl.derivative(energy, u, ufl.TestFunction(V))


class DoubleWell:
    """An energy term on one node's z displacement w: a/4 (w^2 - c^2)^2 - f w, a double well whose
    curvature a c^2 at w = 0 exceeds the block's stiffness at the node, so that the total energy
    has its minima in the wells and a maximum along w near w = 0. Its exact Hessian a (3 w^2 - c^2) is negative there; Newton's tangent
    takes it only near the solution (``exact_near_solution``, as the lips' barrier) and the
    clamped one, max(0, ...), before."""

    exact_near_solution = True
    label = "double well"

    def __init__(self, space, point, a=50.0, c=1.0, f=0.1):
        coordinates = space.tabulate_dof_coordinates()
        owned = space.dofmap.index_map.size_local
        near = np.flatnonzero(np.linalg.norm(coordinates[:owned] - point, axis=1) < 1e-9)
        self.comm = space.mesh.comm
        self.local_dof = 3 * int(near[0]) + 2 if len(near) else None  # z of the node, on its owner
        self.global_dof = (int(space.dofmap.index_map.local_to_global(near[:1].astype(np.int32))[0]) * 3 + 2
                           if len(near) else None)
        self.a, self.c, self.f = a, c, f

    def w(self, x):
        return x.array_r[self.local_dof] if self.local_dof is not None else 0.0

    def energy(self, x):
        w = self.w(x)
        mine = self.a / 4 * (w * w - self.c ** 2) ** 2 - self.f * w if self.local_dof is not None else 0.0
        return self.comm.allreduce(mine)

    def add_gradient(self, x, b):
        if self.local_dof is not None:
            w = self.w(x)
            b.array[self.local_dof] += self.a * w * (w * w - self.c ** 2) - self.f

    def _add(self, A, value):
        if self.local_dof is not None:
            A.setValue(self.global_dof, self.global_dof, value, addv=PETSc.InsertMode.ADD_VALUES)
        A.assemble()

    def add_hessian(self, x, A, constrained):
        w = self.w(x)
        self._add(A, self.a * (3 * w * w - self.c ** 2) if self.local_dof is not None else 0.0)

    def add_newton_correction(self, x, A, constrained):
        w = self.w(x)
        exact = self.a * (3 * w * w - self.c ** 2) if self.local_dof is not None else 0.0
        self._add(A, max(0.0, exact) - exact)
        return True

    def step_fraction(self, x, step, largest):
        return 1.0


def test_newton_does_not_climb_to_a_maximum_on_an_exact_indefinite_tangent():
    """A block clamped at x = 0 with a double well on the z displacement of its far corner
    (``DoubleWell``). From rest the clamped tangent's first correction is small and taken whole,
    so Newton is near and the next tangent takes the exact Hessian, indefinite there: its
    correction climbs the energy towards the maximum near w = 0, where Newton would converge
    (a residual of zero at a maximum of the energy: w = -0.0028 mm before the refusal). Such a
    correction is refused and solved again with the clamped tangent: Newton ends in a well, at a
    minimum (w = 0.848 mm: the block's stiffness at the node, about 14 mN/mm, pulls the well in
    from c = 1 mm)."""
    V, u, energy, residual = linear_block()
    clamped = fem.locate_dofs_geometrical(V, lambda x: np.isclose(x[0], 0.0))
    zero = fem.Function(V)
    well = DoubleWell(V, np.array([10.0, 10.0, 10.0]))
    solver = QuasistaticSolver(residual, u, [fem.dirichletbc(zero, clamped)], tangent="symmetric",
                               energy=energy, energy_terms=(well,), step_tolerance=1e-10)
    converged, _, reason = solver.newton()
    assert converged, reason
    w = MPI.COMM_WORLD.allreduce(well.w(u.vector) if well.local_dof is not None else 0.0)
    # At the maximum |w| is below a micrometre-scale f / (a c^2); the wells lie beyond c / sqrt(3),
    # where the double well's curvature turns positive.
    assert abs(w) > well.c / np.sqrt(3.0), w
    assert solver.refused_exact_tangents > 0


def test_continuation_gives_up_on_a_walk_that_only_creeps():
    """A Newton that converges only for load steps of 1/256 of the way or less (as on the 5K
    bilabial take's hard closure): continuation would reach the target after some 500 solves;
    it gives up once 16 load steps in a row were no longer than 1/128, with the state at the last
    equilibrium. A walk that needs a few small steps and then lengthens them again goes on."""
    from face_dolfinx.equilibrium.solver import CREEP_LOAD_STEPS, EquilibriumError
    problem = FaceProblem(slab_model())
    solver = problem.solver
    reached, trying, solves = [0.0], [0.0], [0]

    def set_controls(t):
        trying[0] = t

    def newton(longest):
        solves[0] += 1
        if trying[0] - reached[0] <= longest(reached[0]) + 1e-15:
            reached[0] = trying[0]
            return True, 1, "converged"
        return False, 1, "diverged"

    solver.newton = lambda: newton(lambda t: 1.0 / 256.0)
    with pytest.raises(EquilibriumError, match="load steps in a row no longer than") as refusal:
        solver.solve_continuation(set_controls)
    assert int(re.search(r"(\d+) load steps in a row", str(refusal.value)).group(1)) >= CREEP_LOAD_STEPS
    assert reached[0] < 0.1 and solves[0] < 60
    # Small steps for a stretch only (a hard bit of the way): the walk goes on to the end.
    reached[0], solves[0] = 0.0, 0
    solver.newton = lambda: newton(lambda t: 1.0 / 256.0 if 0.3 <= t < 0.33 else 1.0)
    report = solver.solve_continuation(set_controls)
    assert report.converged and reached[0] == 1.0


class Wall:
    """An energy term of no energy whose collision-free bound lets a correction that would move a
    dof more than ``reach`` mm go only ``fraction`` of the line search's longest step (a contact
    that long corrections run into). For each bound it records whether the inversion guard would
    have cut that longest step by itself."""

    label = "wall"

    def __init__(self, guard: InversionGuard, fraction: float, reach: float):
        self.guard, self.fraction, self.reach = guard, fraction, reach
        self.guard_would_cut = []

    def energy(self, x):
        return 0.0

    def add_gradient(self, x, b):
        pass

    def add_hessian(self, x, A, constrained):
        pass

    def step_fraction(self, x, step, largest):
        if largest * step.norm(PETSc.NormType.NORM_INFINITY) <= self.reach:
            return 1.0
        ghosted = []
        for vector in (x, step):
            copy = vector.copy()
            copy.ghostUpdate(addv=PETSc.InsertMode.INSERT, mode=PETSc.ScatterMode.FORWARD)
            with copy.localForm() as local:
                ghosted.append(local.array_r.copy())
        self.guard_would_cut.append(self.guard.step_fraction(*ghosted, largest) < largest)
        return self.fraction


def test_corrections_that_a_contact_bound_cuts_shorter_than_the_guard_keep_the_factor():
    """A block clamped at x = 0 whose far face is pushed 6 mm (of 10) towards it, with a ``Wall``
    bounding every correction that would move a dof more than 1.5 mm to a tenth of the line search's
    longest step (two corrections). The first nine corrections' longest steps would invert cells
    (the guard's own fraction below 1), but the wall cuts them far shorter: the guard cut nothing.
    The line search takes each bounded step once (a tenth of the correction, not the two tenths
    the bound allows), which cuts the residual by 0.9, what a step of that length achieves on this
    linear material: Newton keeps its first factor to the end. Counted as guard cuts, they
    refactorised at every such iteration (12 factorisations in 15 iterations), and judged as steps
    of the bound's length, at every other one (8), as in the 404K face's closing frames, where the
    teeth's bound cut corrections to 0.08-0.16 of their length (docs/performance.md)."""
    V, u, energy, residual = linear_block()
    pushed = fem.Function(V)
    pushed.interpolate(lambda x: np.vstack([-0.6 * x[0], np.zeros_like(x[1]), np.zeros_like(x[2])]))
    ends = fem.locate_dofs_geometrical(V, lambda x: np.isclose(x[0], 0.0) | np.isclose(x[0], 10.0))
    guard = InversionGuard(V)
    wall = Wall(guard, fraction=0.1, reach=3.0)
    solver = QuasistaticSolver(residual, u, [fem.dirichletbc(pushed, ends)], tangent="spd", energy=energy,
                               energy_terms=(wall,), inversion_guard=guard,
                               reuse_policy=FactorReusePolicy(across_solves=True), step_tolerance=1e-10)
    cut = []
    solver.snes.setMonitor(lambda snes, it, norm: cut.append(solver.reuse_policy.step_was_cut))
    converged, iterations, reason = solver.newton()
    assert converged, reason
    assert solver.bc_error() < 1e-8
    assert sum(wall.guard_would_cut) >= 2 and len(wall.guard_would_cut) > 10
    assert not any(cut)
    assert solver.factorizations == 1 < iterations
