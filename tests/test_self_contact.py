"""Lip self-contact (face_dolfinx.physics.self_contact) on the small face: the lip surfaces found
from the landmarks, the lips closed by the jaw and the orbicularis oris (without contact they pass
through each other, with it no iterate penetrates), the barrier's gradient and Hessian against
finite differences of the total energy through the assembled residual and tangent, the widened
sparsity, the sensitivities with pressed lips against central differences, the same result on 1
and 2 ranks, and bad input.
"""
from dataclasses import replace
import logging
import re

from mpi4py import MPI
from petsc4py import PETSc
import numpy as np
import ipctk
import pytest
import dolfinx.fem.petsc as fem_petsc

from face_dolfinx.capture.synthetic import control_curves, truth_contact_options
from face_dolfinx.model.bones import jaw_pose
from face_dolfinx.model.folder import load_model
from face_dolfinx.physics.points import PointEvaluator
from face_dolfinx.physics.problem import FaceProblem
from face_dolfinx.physics.self_contact import PATTERN_SLIDE, LipContact, LipContactSettings, LipIterates, lip_facets
from face_dolfinx.sensitivities.columns import EquilibriumSensitivity

CLOSED = np.radians(-2.0)  # the jaw 2 degrees beyond its rest (closed) pose
LIP_MARKERS = ("upper_lip_1", "upper_lip_4", "lower_lip_4", "lower_lip_7", "mouth_corner_left")


def sphincter(model, level=1.0):
    return {m.name: level for m in model.muscles if m.name.startswith("orbicularis_oris")}


def pressed_lips(model):
    problem = FaceProblem(model, lip_contact=LipContactSettings())
    report = problem.solve(activations=sphincter(model), jaw=jaw_pose(model.jaw, CLOSED))
    assert report.converged
    return problem


@pytest.fixture(scope="module")
def pressed(model):
    return pressed_lips(model)


def test_lip_surfaces_of_the_small_face(model):
    upper, lower, up = lip_facets(model, LipContactSettings())
    assert up[1] > 0.9  # the upper lip lies above the lower
    problem = FaceProblem(model)
    lips = LipContact(problem.V, upper, lower, up, LipContactSettings(), problem.bone_blocks)
    # The two walls of the mouth slit, 48 triangles each, meet at the corners: 72 nodes, 6 on both.
    assert len(lips.surface.triangles) == 96 and lips.surface.num_nodes == 72
    assert len(lips.upper_nodes) == len(lips.lower_nodes) == 39
    assert lips.min_distance(problem.u.x.array) == pytest.approx(0.4774, abs=1e-4)
    assert lips.penetration(problem.u.x.array) == 0.0


def test_without_contact_the_lips_pass_through_each_other(model):
    problem = FaceProblem(model)
    problem.solve(activations=sphincter(model), jaw=jaw_pose(model.jaw, CLOSED))
    lips = LipContact(problem.V, *lip_facets(model, LipContactSettings()), LipContactSettings(), problem.bone_blocks)
    assert lips.penetration(problem.u.x.array) > 10.0  # mm


def test_no_iterate_penetrates(model):
    problem = FaceProblem(model, lip_contact=LipContactSettings())
    iterates = LipIterates(problem.lips, problem.V)
    norms = []
    problem.solver.snes.setMonitor(iterates)
    problem.solver.snes.setMonitor(lambda snes, iteration, norm: norms.append(norm))
    report = problem.solve(activations=sphincter(model), jaw=jaw_pose(model.jaw, CLOSED))
    problem.solver.snes.cancelMonitor()
    assert report.converged and report.load_steps == 1
    assert len(iterates.distances) > 10 and min(iterates.distances) > 0.0 and max(iterates.depths) == 0.0
    u = problem.u.x.array
    assert 0.0 < problem.lips.min_distance(u) < problem.lips.dhat
    assert problem.lips.pairs(u) > 20
    # Newton stops on its correction (1e-10 mm in its converging phase), which against the pressed
    # lips' stiffness leaves a residual ten orders of magnitude below the first (mN).
    assert problem.residual_norm() < 1e-10 * norms[0]


def test_the_newton_trace_says_which_term_cut_a_step_and_where_the_residual_sits(model, caplog):
    """The Newton trace names the energy term whose collision-free bound cut a correction and gives
    the residual's norm on each contact surface's nodes: a part of the residual, so at most its
    norm (both printed to 4 digits). The split is a reduction over the ranks, traced by rank 0 alone."""
    problem = FaceProblem(model, lip_contact=LipContactSettings())
    with caplog.at_level(logging.DEBUG, logger="face_dolfinx.equilibrium.solver.iterations"):
        report = problem.solve(activations=sphincter(model), jaw=jaw_pose(model.jaw, CLOSED))
    assert report.converged
    if problem.comm.rank != 0:
        return
    lines = [r.getMessage() for r in caplog.records if r.getMessage().startswith("Newton ")]
    assert len(lines) > 10
    for line in lines:
        total, lips = re.match(r"Newton \d+: residual (\S+) mN \(lips (\S+)\)", line).groups()
        assert float(lips) <= float(total) * (1.0 + 1e-3)
    assert any(re.search(r"bound 0\.\d+ \(lips\)", line) for line in lines)


def _bone_dofs(problem):
    """The owned local dofs of the bone-attached nodes."""
    dofs = (3 * problem.bone_blocks[:, None] + np.arange(3)).reshape(-1)
    return dofs[dofs < problem.u.vector.getLocalSize()]


def _free_direction(problem, seed):
    """A random direction of the free dofs (zero on the bones)."""
    v = problem.u.vector.duplicate()
    rng = np.random.default_rng(seed + 7 * problem.comm.rank)
    v.array[:] = rng.standard_normal(v.getLocalSize())
    v.array[_bone_dofs(problem)] = 0.0
    return v


def _residual(problem, x):
    """The total residual (flesh and lips) at ``x``, without Dirichlet rows set."""
    problem.u.vector.array[:] = x.array_r
    problem.u.x.scatter_forward()
    b = problem.u.vector.duplicate()
    b.set(0.0)
    fem_petsc.assemble_vector(b, problem.solver.residual_form)
    b.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
    problem.lips.add_gradient(problem.u.vector, b)
    return b


def _energy_gradient_matrix(problem, lips, x, add):
    """The lips' energy and gradient at ``x``, and the matrix ``add`` (one of their methods
    ``add_hessian``, ``add_newton_correction``) adds to a zero copy of the tangent, nothing held."""
    b = x.duplicate()
    b.set(0.0)
    lips.add_gradient(x, b)
    A = problem.solver.tangent.duplicate()
    A.zeroEntries()
    add(x, A, np.zeros(0, dtype=np.int32))
    A.assemble()
    return lips.energy(x), b, A


def _lower_lip_blocks(lips) -> np.ndarray:
    """This rank's owned dof blocks of the nodes on the lower lip only (not its corners)."""
    lower = np.isin(lips.surface.owned_nodes, np.setdiff1d(lips.lower_nodes, lips.upper_nodes))
    return lips.surface.owned_blocks[lower]


def test_newton_tangent_leaves_out_the_wider_barrier_on_pairs_that_parted(pressed):
    """The lower lip moved 0.2 mm off the pressed upper (beyond dhat, within the wider reach):
    Newton's model there, after one at the pressed lips, carries no wider barrier (nor any pair
    within dhat); after a model with the lip 0.4 mm off it carries it whole, as with
    ``reach_on_parting_pairs``."""
    lips, u = pressed.lips, pressed.u.vector

    def lowered(distance):
        x = u.copy()
        x.array.reshape(-1, 3)[_lower_lip_blocks(lips)] -= distance * lips.up
        return x

    def model_after(first, then, parting_too):
        lips.reach_on_parting_pairs = parting_too
        try:
            _energy_gradient_matrix(pressed, lips, first, lips.add_newton_correction)
            return _energy_gradient_matrix(pressed, lips, then, lips.add_newton_correction)[2].norm()
        finally:
            lips.reach_on_parting_pairs = False

    apart = lowered(0.2)
    assert lips.pairs(apart.array_r) == 0 < lips.pairs(u.array_r)
    whole = model_after(u, apart, True)
    assert whole > 0.0
    assert model_after(u, apart, False) == 0.0
    assert model_after(lowered(0.4), apart, False) == pytest.approx(whole, rel=1e-12)


def test_gradient_and_hessian_against_differences_of_the_energy(pressed):
    """Along a random direction of the free dofs: the lips' dE . v against central differences of
    their energy, and K v (the solver's tangent, flesh and lips) against central differences of
    the total residual."""
    lips, u = pressed.lips, pressed.u.vector.copy()
    assert lips.pairs(pressed.u.x.array) > 20
    v = _free_direction(pressed, 1)
    # Steps well inside the smallest gap: the barrier stays smooth along them.
    v.scale(0.02 * lips.min_distance(pressed.u.x.array) / v.norm(PETSc.NormType.NORM_INFINITY))

    def at(h):
        x = u.copy()
        x.axpy(h, v)
        pressed.u.vector.array[:] = x.array_r
        pressed.u.x.scatter_forward()
        return x

    # The lips' energy and gradient (the total gradient vanishes at the equilibrium).
    gradient = u.duplicate()
    gradient.set(0.0)
    lips.add_gradient(u, gradient)
    assert abs(gradient.dot(v)) > 1e-6 * gradient.norm() * v.norm()
    for h in (1.0, 0.5):
        fd = (lips.energy(at(h)) - lips.energy(at(-h))) / (2 * h)
        assert fd == pytest.approx(gradient.dot(v), rel=1e-4 * h ** 2)
    at(0.0)
    pressed.solver.assemble_tangent(pressed.solver.tangent)
    Kv = u.duplicate()
    pressed.solver.tangent.mult(v, Kv)
    h = 0.5
    fd = _residual(pressed, at(h))
    fd.axpy(-1.0, _residual(pressed, at(-h)))
    fd.scale(1.0 / (2 * h))
    # The bones' rows of K are the identity's: compare the free rows.
    for vector in (fd, Kv):
        vector.array[_bone_dofs(pressed)] = 0.0
    difference = fd.copy()
    difference.axpy(-1.0, Kv)
    assert difference.norm() <= 1e-5 * Kv.norm()
    # The lips' share of K v is large: the check sees the barrier's Hessian.
    A = pressed.solver.tangent.duplicate()
    A.zeroEntries()
    lips.add_hessian(u, A, np.zeros(0, dtype=np.int32))
    Hv = u.duplicate()
    A.mult(v, Hv)
    assert Hv.norm() > 0.1 * Kv.norm()
    assert A.isSymmetric(1e-8 * A.norm())
    at(0.0)


def test_a_state_seen_again_gives_what_a_fresh_lip_contact_gives(pressed, model):
    """The lips keep the collision set of the last state they saw: energy, gradient, Hessian and
    step bound at two states in turn, and back, equal those of a new ``LipContact`` exactly."""
    settings = LipContactSettings()
    lips = pressed.lips
    u = pressed.u.vector.copy()
    step = _free_direction(pressed, 3)
    step.scale(0.5 * lips.min_distance(pressed.u.x.array) / step.norm(PETSc.NormType.NORM_INFINITY))
    moved = u.copy()
    moved.axpy(0.2, step)

    def terms(contact, x):
        energy, b, A = _energy_gradient_matrix(pressed, contact, x, contact.add_hessian)
        return energy, b.array.copy(), A.norm(), contact.step_fraction(x, step, 1.0)

    # The IPC Toolkit's threaded sums and candidate lists differ in their last bits and order from
    # call to call: one thread, from a state whose collision set the solve did not build.
    threads = ipctk.get_num_threads()
    ipctk.set_num_threads(1)
    try:
        for x in (moved, u, moved):
            fresh = LipContact(pressed.V, *lip_facets(model, settings), settings, pressed.bone_blocks)
            kept, new = terms(lips, x), terms(fresh, x)
            assert kept[0] == new[0] and np.array_equal(kept[1], new[1]) and kept[2:] == new[2:]
        assert terms(lips, moved)[0] != terms(lips, u)[0]
    finally:
        ipctk.set_num_threads(threads)


def test_the_tangents_sparsity_holds_the_lip_pairs(pressed):
    """Every entry of the pressed lips' Hessian lies in the pattern set up at rest (no new nonzero,
    so MUMPS keeps its analysis), which widens the finite-element pattern by pairs of an upper and a
    lower lip node only, within the lips' slide plus two lip edges."""
    lips = pressed.lips
    rest, edges = lips.surface.rest, lips.mesh.edges
    assert lips.pattern_radius == pytest.approx(
        PATTERN_SLIDE + 2 * np.linalg.norm(rest[edges[:, 0]] - rest[edges[:, 1]], axis=1).max())
    node = {block: k for k, block in enumerate(lips.global_blocks)}
    pairs = np.array([[node[a], node[b]] for a, b in lips.coupled_blocks()])
    upper = np.isin(pairs, lips.upper_nodes)
    lower = np.isin(pairs, lips.lower_nodes)
    assert ((upper[:, 0] & lower[:, 1]) | (lower[:, 0] & upper[:, 1])).all()
    assert np.linalg.norm(rest[pairs[:, 0]] - rest[pairs[:, 1]], axis=1).max() <= lips.pattern_radius
    # The pressed primitives lay at least the lips' rest distance apart at rest, and within the slide
    # the pattern leaves room for.
    rest_distance = lips.min_distance(np.zeros_like(pressed.u.x.array))
    assert lips.slide(np.zeros_like(pressed.u.x.array)) == 0.0
    assert rest_distance <= lips.slide(pressed.u.x.array) <= PATTERN_SLIDE
    before = pressed.solver.tangent.getInfo()["nz_allocated"]
    pressed.solver.assemble_tangent(pressed.solver.tangent)
    info = pressed.solver.tangent.getInfo()
    assert info["nz_allocated"] == before and info["mallocs"] == 0


def test_the_wider_reach_is_in_newtons_tangent_only(pressed, model):
    """``LipContactSettings.newton_reach``: the barrier of wider reach across the lips changes
    Newton's tangent alone, by a symmetric positive semidefinite matrix between upper and lower lip
    nodes inside the tangent's pattern; the energy, the gradient, the Hessian and the equilibria
    are those without it."""
    settings = LipContactSettings()
    assert settings.newton_reach > settings.dhat
    narrow = LipContact(pressed.V, *lip_facets(model, settings), replace(settings, newton_reach=0.0),
                        pressed.bone_blocks)
    wide, u = pressed.lips, pressed.u.vector
    # (Equal up to the last bits of the IPC Toolkit's threaded sums.)
    energies, gradients, hessians = zip(*(_energy_gradient_matrix(pressed, lips, u, lips.add_hessian)
                                          for lips in (wide, narrow)))
    assert energies[0] == pytest.approx(energies[1], rel=1e-12)
    gradients[0].axpy(-1.0, gradients[1])
    assert gradients[0].norm() <= 1e-12 * gradients[1].norm()
    difference = hessians[0].copy()
    difference.axpy(-1.0, hessians[1])
    assert difference.norm() <= 1e-12 * hessians[1].norm()
    # Newton's corrections: the wider reach adds pairs the narrow barrier does not have yet.
    corrections = [_energy_gradient_matrix(pressed, lips, u, lips.add_newton_correction)[2] for lips in (wide, narrow)]
    assert corrections[0].getInfo()["mallocs"] == 0  # no entry outside the tangent's pattern
    added = corrections[0].copy()
    added.axpy(-1.0, corrections[1])
    assert added.norm() > 1e-3 * corrections[1].norm()
    assert added.isSymmetric(1e-10 * added.norm())
    rng = np.random.default_rng(11 + pressed.comm.rank)
    v, Dv = u.duplicate(), u.duplicate()
    for _ in range(5):
        v.array[:] = rng.standard_normal(v.getLocalSize())
        added.mult(v, Dv)
        assert v.dot(Dv) >= -1e-10 * added.norm() * v.norm() ** 2
    # Its rows are the lip nodes' only, and it couples each lip with the other: a load on one lip's
    # nodes alone meets rows of the other's.
    for nodes, others in ((wide.upper_nodes, wide.lower_nodes), (wide.lower_nodes, wide.upper_nodes)):
        only, rest = np.setdiff1d(nodes, others), np.setdiff1d(others, nodes)
        v.set(0.0)
        mine = np.isin(wide.surface.owned_nodes, only)
        v.array.reshape(-1, 3)[wide.surface.owned_blocks[mine]] = rng.standard_normal((mine.sum(), 3))
        added.mult(v, Dv)
        lip_rows = np.zeros(u.getLocalSize() // 3, dtype=bool)
        lip_rows[wide.surface.owned_blocks] = True
        assert np.abs(Dv.array.reshape(-1, 3)[~lip_rows]).max(initial=0.0) == 0.0
        on_others = np.isin(wide.surface.owned_nodes, rest)
        other_rows = np.abs(Dv.array.reshape(-1, 3)[wide.surface.owned_blocks[on_others]]).max(initial=0.0)
        assert pressed.comm.allreduce(other_rows, op=MPI.MAX) > 0.0
    # The same equilibria: a solve without it, started at the equilibrium found with it, stays
    # there. (From rest the two Newton paths may end at different equilibria of the pressed lips:
    # 0.16 mm apart on the small face.)
    without = FaceProblem(model, lip_contact=replace(settings, newton_reach=0.0))
    assert without.solve(activations=sphincter(model), jaw=jaw_pose(model.jaw, CLOSED),
                         guess=pressed.u.x.array.copy()).converged
    gap = np.abs(without.u.x.array - pressed.u.x.array).max()
    assert pressed.comm.allreduce(gap, op=MPI.MAX) <= 1e-6 * pressed.comm.allreduce(
        np.abs(pressed.u.x.array).max(), op=MPI.MAX)


def test_held_lip_nodes_keep_the_identitys_rows_and_columns(pressed):
    """Lip nodes held by a Dirichlet condition (the teeth carry the lining's nodes along when the
    jaw moves, some of them lip nodes) get no barrier entries in their rows or columns, in the
    Hessian and in Newton's correction: the tangent's rows and columns of held dofs stay the
    identity's. The free lip nodes keep theirs."""
    lips, u = pressed.lips, pressed.u.vector
    forces = lips.nodal_forces(pressed.u.x.array)
    touching = np.flatnonzero(np.linalg.norm(forces, axis=1) > 0.0)
    assert touching.size > 10
    held = touching[::2]
    blocks = lips.surface.local_blocks[np.isin(lips.surface.local_nodes, held)]
    dofs = (3 * blocks[:, None] + np.arange(3)).reshape(-1)
    constrained = dofs[dofs < u.getLocalSize()].astype(np.int32)
    on_held, on_free = u.duplicate(), u.duplicate()
    rng = np.random.default_rng(5 + pressed.comm.rank)
    for vector, nodes in ((on_held, held), (on_free, np.setdiff1d(touching, held))):
        vector.set(0.0)
        mine = np.isin(lips.surface.owned_nodes, nodes)
        vector.array.reshape(-1, 3)[lips.surface.owned_blocks[mine]] = rng.standard_normal((mine.sum(), 3))

    def columns_and_rows(constrained):
        out = []
        for add in (lips.add_hessian, lips.add_newton_correction):
            A = pressed.solver.tangent.duplicate()
            A.zeroEntries()
            add(u, A, constrained)
            A.assemble()
            y = u.duplicate()
            A.mult(on_held, y)
            out.append(y.norm())  # the held columns
            A.multTranspose(on_held, y)
            out.append(y.norm())  # the held rows
            A.mult(on_free, y)
            out.append(y.norm())  # the free columns
        return np.array(out)

    unheld, held_out = columns_and_rows(np.zeros(0, dtype=np.int32)), columns_and_rows(constrained)
    assert (unheld > 0.0).all()  # the barrier couples the held nodes when nothing holds them
    assert held_out[[0, 1, 3, 4]].max() == 0.0
    assert (held_out[[2, 5]] > 0.0).all()


def test_a_lower_lip_pushed_into_the_upper_pushes_it_along(pressed):
    """The lower lip's pressed nodes pushed 0.3 mm up (as the closing teeth push the lining out of
    their way) would pass through the upper lip: ``pushed_along`` moves the nodes of the pairs
    that would pass each other along with the pushed ones (the upper lip's among them), and the
    lips then pass each other nowhere on the way; the pushed nodes keep their move."""
    lips, start = pressed.lips, pressed.u.x.array
    x = lips.positions(start)
    touching = np.flatnonzero(np.linalg.norm(lips.nodal_forces(start), axis=1) > 0.0)
    lower_only = np.setdiff1d(lips.lower_nodes, lips.upper_nodes)
    pushed = np.intersect1d(touching, lower_only)
    assert pushed.size > 5
    moved = x.copy()
    moved[pushed] += 0.3 * lips.up
    end = lips.surface.placed(start, moved, pushed)
    assert lips.admissible_fraction(start, end) < 0.5

    mended = lips.pushed_along(start, end)
    assert mended is not None and lips.admissible_fraction(start, mended) == 1.0
    assert not lips.intersects(mended)
    y = lips.positions(mended)
    move = y - x
    assert np.allclose(move[pushed], 0.3 * lips.up)
    along = np.flatnonzero(np.linalg.norm(move, axis=1) > 0.0)
    others = np.setdiff1d(along, pushed)
    assert np.isin(others, lips.upper_nodes).any()
    assert np.allclose(move[others], 0.3 * lips.up)  # the move of a pushed node
    # ... a move the lips already allow is returned as it is
    assert lips.pushed_along(start, mended) is mended


def test_activation_columns_with_pressed_lips(pressed, model):
    """dX/da by the solver's factor (the lips' Hessian included) against central differences, at
    lips pressed by the orbicularis oris at 0.9 with the depressor anguli oris at 0.2."""
    activations = pressed.activation_vector({**sphincter(model, 0.9), "depressor_anguli_oris_left": 0.2})
    assert pressed.solve(activations=activations).converged
    assert pressed.lips.pairs(pressed.u.x.array) > 20
    base, controls = pressed.u.x.array.copy(), pressed.controls.copy()
    markers = PointEvaluator(pressed.V, np.array([model.markers[name] for name in LIP_MARKERS]))
    sensitivity = EquilibriumSensitivity(pressed)
    sensitivity.factor()
    columns = markers.values_many(sensitivity.activation_columns())
    step = 1e-4
    for name in ("orbicularis_oris_upper_left", "depressor_anguli_oris_left"):
        muscle = model.muscle_index(name)
        bump = np.zeros_like(activations)
        bump[muscle] = step
        pressed.solve(activations=activations + bump)
        plus = markers.values(pressed.u.x.array)
        pressed.solve(activations=activations - bump)
        minus = markers.values(pressed.u.x.array)
        fd = (plus - minus) / (2 * step)
        assert np.abs(columns[muscle] - fd).max() <= 1e-3 * np.abs(fd).max(), name
        pressed.adopt(controls, base)


def test_a_fresh_approximate_jacobian_factorises_newtons_tangent(pressed, model):
    """Where no factor of these controls lies close enough, an approximate Jacobian (``reuse_within``
    > 0 with ``newton_tangent``, as ``fit --fast`` asks) factorises Newton's tangent at the pressed
    lips, their pair Hessians projected and their barrier of wider reach in it: not the exact
    tangent (exact sensitivities factorise again), kept by the next approximate Jacobian. Its lip
    marker columns lie 16 % from the exact ones (10 % with the projection alone): a Gauss-Newton
    direction, of the same kind as the columns from Newton's last factor."""
    solver, sensitivity = pressed.solver, EquilibriumSensitivity(pressed)
    markers = PointEvaluator(pressed.V, np.array([model.markers[name] for name in LIP_MARKERS]))
    solver.controls_changed()  # no factor holds a tangent of these controls
    factorizations = solver.factorizations
    assert sensitivity.factor(reuse_within=0.3, newton_tangent=True) == 0.0
    assert solver.factorizations == factorizations + 1 and not solver.factor_is_exact
    assert solver.factor_distance(exact=False) == 0.0 and solver.factor_distance() == np.inf
    newton = markers.values_many(sensitivity.activation_columns())
    assert sensitivity.factor(reuse_within=0.3, newton_tangent=True) == 0.0
    assert solver.factorizations == factorizations + 1
    assert sensitivity.factor() == 0.0 and solver.factor_is_exact and solver.factorizations == factorizations + 2
    exact = markers.values_many(sensitivity.activation_columns())
    relative = np.linalg.norm(newton - exact) / np.linalg.norm(exact)
    assert 1e-3 < relative < 0.3


def test_same_result_on_one_rank(builtin_model_path):
    """The distributed solve against the same problem on this rank alone (every rank gathers the
    lips, computes the same pairs and adds the rows it owns)."""
    here = pressed_lips(load_model(builtin_model_path, MPI.COMM_WORLD))
    alone = pressed_lips(load_model(builtin_model_path, MPI.COMM_SELF))
    forces = [problem.lips.nodal_forces(problem.u.x.array) for problem in (here, alone)]
    assert np.abs(forces[0] - forces[1]).max() <= 1e-6 * np.abs(forces[1]).max()
    assert here.lips.min_distance(here.u.x.array) == pytest.approx(alone.lips.min_distance(alone.u.x.array), rel=1e-6)


def test_bad_input_is_refused_before_any_solve(model):
    with pytest.raises(ValueError, match="dhat and the stiffness must be positive"):
        FaceProblem(model, lip_contact=LipContactSettings(dhat=0.0))
    with pytest.raises(ValueError, match="Newton reach"):
        FaceProblem(model, lip_contact=LipContactSettings(newton_reach=-1.0))
    with pytest.raises(ValueError, match="apart at rest"):
        FaceProblem(model, lip_contact=LipContactSettings(dhat=1.0))  # the slit is 0.48 mm at its corners
    landmarks = dict(model.landmarks)
    del landmarks["upper_lip_center"]
    with pytest.raises(ValueError, match="upper_lip_center"):
        lip_facets(replace(model, landmarks=landmarks), LipContactSettings())
    with pytest.raises(ValueError, match="no skin facets lining the mouth slit"):
        lip_facets(model, LipContactSettings(depth=0.01))


def test_fit_of_pressed_lips_with_contact(model):
    """Markers of lips pressed together (the truth solved with contact) fitted with contact: the
    activations are recovered and the fitted lips do not pass each other."""
    from face_dolfinx.fitting import FaceFitter, FitSettings, MarkerSet
    problem = FaceProblem(model, lip_contact=LipContactSettings())
    truth = problem.activation_vector({**sphincter(model, 0.9), "depressor_anguli_oris_left": 0.2})
    assert problem.solve(activations=truth).converged
    assert problem.lips.pairs(problem.u.x.array) > 20
    markers = MarkerSet(problem, np.array(list(model.markers.values())))
    targets = markers.positions(problem.u.x.array, problem.controls.cranium)
    problem.reset_to_rest()
    fitter = FaceFitter(problem, markers, FitSettings(fit_head=False, fit_jaw=False, first_frame_gn_steps=10))
    result = fitter.fit_frame(targets)
    error = np.abs(result.activations - truth).max()
    # Measured: 0.026 mm from 3.5 mm, activation error 0.014, in 6 Gauss-Newton steps.
    assert result.rms_error < 0.05  # mm: a tenth of a capture's noise
    assert error < 0.05
    assert problem.lips.penetration(problem.u.x.array) == 0.0
    assert problem.lips.min_distance(problem.u.x.array) > 0.0


def test_tracking_with_contact_builds_the_lips_into_its_problem(model):
    """``fit --contact``: the tracking setting reaches the problem and the run's record."""
    from face_dolfinx.cli.main import parse_arguments, tracking_settings
    from face_dolfinx.tracking import Tracker
    settings = tracking_settings(parse_arguments(["fit", "take.trc", "--contact"])[0])
    assert settings.contact and settings.record()["contact"] is True
    problem = Tracker(model, settings).problem
    assert problem.lips is not None and problem.lips.settings.where == "--contact"
    assert problem.solver.energy_terms == (problem.teeth_contact, problem.lips)
    # A tracker's problem options take the place of the settings' (a stiffer lip barrier).
    stiffer = Tracker(model, settings, problem_options=dict(lip_contact=LipContactSettings(stiffness=50.0))).problem
    assert stiffer.lips.stiffness == 50.0 and stiffer.teeth_contact is not None


def test_the_jaw_carries_the_lining_but_not_the_lips(model):
    """With the teeth on, a jaw motion carries the lining resting on the teeth along by a Dirichlet
    condition (``ContactPotential.carry``); some lining nodes are lip nodes, which it leaves free
    for the lips' barrier. The bilabial take's lips opening and closing again with the jaw (frames
    5-13 of 60, each solved from the last equilibrium, as the synthetic take's truth is): every
    frame converges from the last equilibrium, and the lips never pass each other. (Carrying lip
    nodes, the lower lip's lining moved rigidly with the teeth into the upper lip: frame 12 failed
    and was solved from rest, 789 Newton iterations in all.)"""
    problem = FaceProblem(model, **truth_contact_options(model, "lips+teeth", where="test"))
    activations, tmj, head = control_curves(model, "bilabial", 60, head_motion=False)
    iterations = []
    for frame in range(5, 14):
        report = problem.solve(activations=activations[frame], cranium=head[frame], jaw=jaw_pose(model.jaw, *tmj[frame]))
        iterations.append(report.newton_iterations)
        assert report.converged
        assert problem.lips.min_distance(problem.u.x.array) > 0.0
    assert max(iterations[-2:]) < 100


def test_lip_nodes_the_teeth_overrun_start_the_carry_outside_them(model, monkeypatch):
    """As the lips close again with the head moving (the bilabial take's frames 19-20, each solved
    from the last equilibrium, as the truth is), the lower teeth's new pose overruns lip nodes that
    ``ContactPotential.carry`` leaves free for the lips' barrier. They start its solve moved out to
    the gap they had: every Newton solve starts with a finite residual and each frame takes one
    load step. (Left where they were, inside the teeth: eight starts without a finite residual and
    frames 19-20 in 2 and 3 load steps.)"""
    problem = FaceProblem(model, **truth_contact_options(model, "lips+teeth", where="test"))
    activations, tmj, head = control_curves(model, "bilabial", 60, head_motion=True)
    finite_starts = []
    newton = problem.solver.newton

    def checked_newton(**options):
        finite_starts.append(bool(np.isfinite(problem.solver.residual_norm())))
        return newton(**options)

    monkeypatch.setattr(problem.solver, "newton", checked_newton)
    for frame in range(21):
        report = problem.solve(activations=activations[frame], cranium=head[frame],
                               jaw=jaw_pose(model.jaw, *tmj[frame]))
        assert report.converged
        if frame >= 19:
            assert report.load_steps == 1
    assert all(finite_starts)
    assert problem.lips.min_distance(problem.u.x.array) > 0.0
    assert problem.teeth_contact.min_gap(problem.u.x.array) > 0.0


@pytest.mark.parametrize("mended", [True, False], ids=["pushed-along", "refused"])
def test_a_push_out_through_the_lips_pushes_the_other_lip_along_or_is_not_solved_from(model, monkeypatch, caplog,
                                                                                       mended):
    """Before Newton starts from a predicted shape the teeth move to their new poses and push the
    lining out of their way (``ContactPotential.move_to``), which knows nothing of the lips: on the
    5K face's bilabial take with the head moving it took pressed lower-lip nodes 0.03 mm through the
    upper lip. The upper lip is pushed along (``LipContact.pushed_along``) and Newton starts from
    there; where that cannot be done (here made so), the start is refused and the solve goes on
    from the last equilibrium, and a load step of the continuation with such a start fails as a
    failed solve would. Here the push-out takes the lower lip 0.05 mm up, once in each case."""
    problem = FaceProblem(model, **truth_contact_options(model, "lips+teeth", where="test"))
    activations, tmj, head = control_curves(model, "bilabial", 60, head_motion=False)

    def frame(k):
        return dict(activations=activations[k], cranium=head[k], jaw=jaw_pose(model.jaw, *tmj[k]))

    for k in (5, 6):
        assert problem.solve(**frame(k)).converged
    lips, teeth = problem.lips, problem.teeth_contact
    assert lips.min_distance(problem.u.x.array) < lips.dhat  # pressed
    push_out = teeth.push_out
    lower = _lower_lip_blocks(lips)

    pushed = []

    def through_the_lips(displacement, poses):
        out, held = push_out(displacement, poses)
        if not pushed:
            out.reshape(-1, 3)[lower] += 0.05 * lips.up
        pushed.append(lips.min_distance(out))
        return out, held

    monkeypatch.setattr(teeth, "push_out", through_the_lips)
    monkeypatch.setattr(teeth, "closes_in", lambda displacement, old_poses, new_poses: True)
    if not mended:
        monkeypatch.setattr(lips, "pushed_along", lambda start, end: None)
    distances = []
    problem.solver.snes.setMonitor(lambda snes, it, norm: distances.append(lips.min_distance(snes.getSolution().array_r)))
    # From a predicted shape (the last equilibrium), then by continuation alone.
    for k, guess in ((7, problem.u.x.array.copy()), (8, None)):
        pushed.clear()
        with caplog.at_level("DEBUG", logger="face_dolfinx.physics.problem"):
            caplog.clear()
            report = problem.solve(guess=guess, **frame(k))
        assert report.converged and pushed[0] == 0.0  # the first push went through the upper lip
        if mended:
            assert "other lip pushed along" in caplog.text and "lips intersect" not in caplog.text
            assert len(pushed) == 1 and report.load_steps == 1  # ... and was solved from, pushed along
        else:
            assert len(pushed) > 1  # ... and was not solved from
        assert lips.min_distance(problem.u.x.array) > 0.0 and lips.penetration(problem.u.x.array) == 0.0
    problem.solver.snes.cancelMonitor()
    if mended:
        assert min(distances) > 0.0  # no Newton iterate with the lips intersecting


def test_the_step_bound_stops_short_of_intersecting_lips(pressed, monkeypatch):
    """The lips' step bound is the IPC Toolkit's collision-free step (CCD), and also stops short
    of an end where the lips intersect: a CCD that let a step through (here one that says every
    step is free) is caught. The step takes the pressed lower lip 0.01 mm up, through the upper lip."""
    lips = pressed.lips
    u = pressed.u.x.array
    end = u.copy()
    end.reshape(-1, 3)[_lower_lip_blocks(lips)] += 0.01 * lips.up
    fraction = lips.admissible_fraction(u, end)
    assert 0.0 < fraction < 1.0
    monkeypatch.setattr(ipctk, "compute_collision_free_stepsize", lambda *args, **kwargs: 1.0)
    missed = lips.admissible_fraction(u, end)
    assert 0.0 < missed < 1.0
    stop = u + missed * (end - u)
    assert lips.min_distance(stop) > 0.0 and lips.min_distance(u + 2.0 * missed * (end - u)) == 0.0


def test_simulate_with_the_contact_solver_options(model, shared_dir, monkeypatch):
    """``simulate --contact --contact-relaxation --newton-energy-tolerance 10``: the options reach
    the problem's solver, whose relaxation works on the lining the teeth push out, and the smile lands
    where the default solver puts it, within what the energy stop leaves; without contact, or with a
    tolerance that is no positive energy, the options are refused before any solve."""
    import json
    import face_dolfinx.physics.problem as problem_module
    from face_dolfinx.cli.main import main
    solvers = []

    class Recorded(problem_module.FaceProblem):
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            solvers.append(self.solver)

    monkeypatch.setattr(problem_module, "FaceProblem", Recorded)
    rows = {}
    for name, options in (("plain", []), ("relaxed", ["--contact-relaxation", "--newton-energy-tolerance", "10"])):
        out = shared_dir / f"smile_{name}"
        assert main(["simulate", "smile", "--model", str(model.path), "--contact", "--out", str(out),
                     "--no-render", *options]) == 0
        rows[name] = json.loads((out / "summary.json").read_text())["expressions"][0]
    plain, relaxed = solvers
    assert plain.contact_relaxation is None and plain.energy_tolerance is None  # relaxed once Newton crawls
    assert relaxed.contact_relaxation is True and relaxed.energy_tolerance == 10.0
    assert relaxed.relaxation.local_iterations > 0
    assert abs(rows["relaxed"]["max_displacement_mm"] - rows["plain"]["max_displacement_mm"]) < 0.01
    for options, message in ((["--contact-relaxation"], "give --contact or --object"),
                             (["--contact", "--newton-energy-tolerance", "0"], "give a positive energy")):
        with pytest.raises(SystemExit, match=message):
            main(["simulate", "smile", "--model", str(model.path), "--out", str(shared_dir / "never"),
                  "--no-render", *options])
    assert not (shared_dir / "never").exists()
