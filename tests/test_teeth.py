"""The teeth (face_dolfinx.model.anatomy.teeth, FaceModel.teeth, ContactSettings(teeth=True)): the
built-in face's teeth are closed and behind the lining, written and read with the model, carried
along to a subject; the lips pressed on them by the orbicularis oris stay outside at every Newton
iterate and rest on them (and go through them without the contact) after one Newton solve of
few iterations, also from a prediction that would enter the teeth or close the jaw onto the lining,
and a prediction that carries the face with the head and its teeth is not cut; a jaw opened and
closed with the teeth on keeps every lining node outside them at every Newton iterate; the same
force on 1 and 2 ranks; bad teeth are refused naming the model file.
"""
import shutil
from dataclasses import replace

from mpi4py import MPI
import numpy as np
import pytest

from conftest import on_rank_0
from face_dolfinx.model.bones import AffineMap, rotation
from face_dolfinx.model.folder import ModelError, load_model
from face_dolfinx.model.surface_file import write_triangle_surface
from face_dolfinx.model.bones import jaw_pose
from face_dolfinx.physics.contact import CCD_KEEP, TEETH_DHAT, TEETH_STIFFNESS, ContactSettings
from face_dolfinx.physics.problem import FaceProblem
from face_dolfinx.physics.rigid_mesh import TriangleMesh
from face_dolfinx.sensitivities.columns import EquilibriumSensitivity

# The orbicularis oris at this level presses the lips on the teeth with about 30 N on the small
# face (docs/contact.md).
LEVEL = 0.1
# Newton iterations of that solve: 18 in one Newton solve; a barrier of dhat 0.05 mm with the teeth
# 0.3 mm behind the lining took 68 in two load steps (docs/contact.md).
PRESS_ITERATIONS = 25
# Newton iterations of the orbicularis oris at 1 with the teeth: 26 in one load step on the small face
# (docs/contact.md); a second load step is allowed.
HARD_PRESS_ITERATIONS = 50
# Newton iterations of the jaw closing after a 10 degree opening: 143 in 5 load steps on the small face.
CLOSING_ITERATIONS = 180


def orbicularis_oris(model, level=LEVEL):
    return {name: level for name in model.muscle_names if name.startswith("orbicularis_oris")}


def lining_gaps(arrays, teeth=None):
    """Gap of every node of the oral lining to each of the teeth (bone -> array), at rest."""
    nodes = np.unique(arrays.facets[arrays.facet_values == arrays.boundary_ids["oral"]])
    return {bone: TriangleMesh(*surface).gaps(arrays.points[nodes], AffineMap())[0]
            for bone, surface in (teeth or arrays.teeth).items()}


def test_builtin_teeth_sit_behind_the_lining(template):
    assert set(template.teeth) == {"cranium", "mandible"}
    for bone, gaps in lining_gaps(template).items():
        # 0.8 mm along the rays; less along the normal where the lining is oblique to them, but
        # more than the barrier's dhat: the rest state is barrier-free.
        assert TEETH_DHAT < gaps.min() < 0.8, bone
        assert (gaps < 1.0).sum() >= 10, bone  # the lips rest on them
    upper, lower = (template.teeth[bone][0] for bone in ("cranium", "mandible"))
    assert upper[:, 1].mean() > lower[:, 1].mean() + 10.0  # the upper teeth above the lower ones
    bone_nodes = np.unique(template.facets[template.facet_values == template.boundary_ids["mandible"]])
    moving = TriangleMesh(*template.teeth["cranium"]).gaps(template.points[bone_nodes], AffineMap())[0]
    assert moving.min() > 5.0  # the mandible's nodes do not come near the upper teeth


def test_teeth_are_written_and_read_with_the_model(template, shared_dir):
    out = shared_dir / "copy"
    on_rank_0(lambda: template.write(out))
    model = load_model(out)
    for bone, (points, triangles) in template.teeth.items():
        read_points, read_triangles = model.teeth[bone]
        assert len(read_triangles) == len(triangles)
        volume = [np.einsum("ij,ij->i", p[t[:, 0]], np.cross(p[t[:, 1]], p[t[:, 2]])).sum()
                  for p, t in ((points, triangles), (read_points, read_triangles))]
        assert volume[1] == pytest.approx(volume[0], rel=1e-12) and volume[0] > 0
        assert np.abs(np.sort(read_points, axis=0) - np.sort(points, axis=0)).max() < 1e-5


def test_bad_teeth_are_refused(template, shared_dir):
    folder = shared_dir / "bad"
    points, triangles = template.teeth["mandible"]

    def damaged(text=None, surface=None, teeth=template.teeth):
        if MPI.COMM_WORLD.rank == 0:
            shutil.rmtree(folder, ignore_errors=True)
            replace(template, teeth=teeth).write(folder)
            if surface is not None:
                write_triangle_surface(folder / "teeth_mandible.ply", *surface)
            if text is not None:
                toml = folder / "model.toml"
                toml.write_text(toml.read_text().replace('mandible = "teeth_mandible.ply"', text))
        MPI.COMM_WORLD.barrier()

    damaged(surface=(points, triangles[1:]))
    with pytest.raises(ModelError, match=r"model.toml: \[teeth\] mandible = 'teeth_mandible.ply': .*not a closed surface"):
        load_model(folder)
    damaged(text='mandible = "gone.ply"')
    with pytest.raises(ModelError, match=r"model.toml: \[teeth\] mandible = 'gone.ply': no such file"):
        load_model(folder)
    damaged(text='maxilla = "teeth_mandible.ply"')
    with pytest.raises(ModelError, match=r"model.toml: \[teeth\]: unknown bone 'maxilla'"):
        load_model(folder)
    # Lower teeth moved 1 mm forward: into the lining of the lower lip.
    damaged(surface=(points + [0.0, 0.0, 1.0], triangles))
    model = load_model(folder)
    with pytest.raises(ValueError, match=r"bad \(\[teeth\] of its model.toml\): the triangle surface teeth on the "
                                         r"mandible .* starts inside the oral"):
        FaceProblem(model, contact=ContactSettings(teeth=True))
    # 0.5 mm forward: outside, but closer than dhat.
    damaged(surface=(points + [0.0, 0.0, 0.5], triangles))
    with pytest.raises(ValueError, match=r"teeth on the mandible .* comes within .* mm of .* nodes of the oral at "
                                         r"rest; it must leave more than 0.5 mm"):
        FaceProblem(load_model(folder), contact=ContactSettings(teeth=True))
    damaged(teeth={})
    with pytest.raises(ValueError, match=r"model .*bad has no teeth \(\[teeth\] in its model.toml"):
        FaceProblem(load_model(folder), contact=ContactSettings(teeth=True))


@pytest.fixture(scope="module")
def pressed(model):
    """The small face with the orbicularis oris on, jaw closed, teeth contact on; the smallest gap
    to the teeth over all Newton iterates."""
    problem = FaceProblem(model, contact=ContactSettings(teeth=True, stiffness=TEETH_STIFFNESS))
    gaps = []
    problem.solver.snes.setMonitor(lambda snes, it, norm: gaps.append(
        problem.teeth_contact.min_gap(snes.getSolution().array_r)))
    report = problem.solve(activations=orbicularis_oris(model))
    problem.solver.snes.cancelMonitor()
    return problem, report, gaps


def test_lips_pressed_on_the_teeth(pressed):
    problem, report, gaps = pressed
    teeth = problem.teeth_contact
    assert report.converged and len(gaps) > 3
    assert report.load_steps == 1 and report.newton_iterations <= PRESS_ITERATIONS
    assert min(gaps) > 0.0  # no node inside the teeth at any Newton iterate
    assert teeth.contact_nodes(problem.u.x.array) > 0
    forces = teeth.nodal_forces(problem.u.x.array)
    assert np.linalg.norm(forces, axis=1).sum() > 1000.0  # mN pressing on the teeth
    assert problem.residual_norm() < 1e-6


def test_terms_of_the_nodes_that_moved_are_those_of_a_fresh_call(pressed):
    """A state that moved only some lining nodes (the relaxation's local steps) recomputes only
    their barrier terms: every node's force and Hessian block are those of a fresh call, to the
    bit, and the energy to round-off."""
    from petsc4py import PETSc
    problem = pressed[0]
    teeth = problem.teeth_contact
    none = np.zeros(0, dtype=np.int32)
    first = problem.u.vector.getOwnershipRange()[0]
    rows = (first + 3 * teeth.surface.owned_blocks[:, None] + np.arange(3)).reshape(-1).astype(PETSc.IntType)

    def evaluate(x):
        matrix = problem.solver.tangent.duplicate()
        matrix.zeroEntries()
        teeth.add_hessian(x, matrix, none)
        return teeth.nodal_forces(x.array_r), matrix.getValues(rows, rows), teeth.energy(x)

    x = problem.u.vector.copy()
    pushed = teeth.surface.owned_blocks[np.linalg.norm(teeth.nodal_forces(x.array_r), axis=1)[
        teeth.surface.owned_nodes] > 0.0]
    moved = pushed[::2]  # half the pushed nodes move, the rest stays
    assert MPI.COMM_WORLD.allreduce(len(moved)) > 0
    x.array.reshape(-1, 3)[moved] += 1e-3 * np.random.default_rng(3).standard_normal((len(moved), 3))
    x.ghostUpdate(addv=PETSc.InsertMode.INSERT, mode=PETSc.ScatterMode.FORWARD)
    incremental = evaluate(x)
    elsewhere = x.copy()  # every node moved: the next call at x computes all terms afresh
    elsewhere.shift(1e-6)
    elsewhere.ghostUpdate(addv=PETSc.InsertMode.INSERT, mode=PETSc.ScatterMode.FORWARD)
    evaluate(elsewhere)
    fresh = evaluate(x)
    assert np.array_equal(incremental[0], fresh[0]) and np.array_equal(incremental[1], fresh[1])
    assert incremental[2] == pytest.approx(fresh[2], rel=1e-12)


def test_orbicularis_oris_at_one_rests_on_the_teeth(model):
    """The orbicularis oris at 1 presses the lips on the teeth with some 190 N: Newton converges
    (26 iterations in one load step measured on the small face; continuation gave up at 0.988 of
    the load with the nearest triangle's distance as the gap, docs/contact.md), no lining node is
    inside the teeth at any Newton iterate."""
    problem = FaceProblem(model, contact=ContactSettings(teeth=True, stiffness=TEETH_STIFFNESS))
    teeth = problem.teeth_contact
    gaps = []
    problem.solver.snes.setMonitor(lambda snes, it, norm: gaps.append(teeth.min_gap(snes.getSolution().array_r)))
    report = problem.solve(activations=orbicularis_oris(model, 1.0))
    problem.solver.snes.cancelMonitor()
    assert report.converged and report.load_steps <= 2 and report.newton_iterations <= HARD_PRESS_ITERATIONS
    assert min(gaps) > 0.0
    assert np.linalg.norm(teeth.nodal_forces(problem.u.x.array), axis=1).sum() > 1e5  # mN
    assert problem.residual_norm() < 1e-6


def test_newton_tangent_projects_the_barrier_blocks(pressed):
    """With the lips pressed on the teeth, Newton's barrier Hessian is every node's exact 3 x 3
    block projected onto the positive semidefinite ones: each block is PSD, differs from the exact
    one by a PSD matrix and equals it where the exact one is PSD."""
    from petsc4py import PETSc
    problem = pressed[0]
    teeth = problem.teeth_contact
    x = problem.u.vector
    matrices = [problem.solver.tangent.duplicate() for _ in range(2)]
    for matrix in matrices:
        matrix.zeroEntries()
        teeth.add_hessian(x, matrix, np.zeros(0, dtype=np.int32))
    projected = teeth.add_newton_correction(x, matrices[1], np.zeros(0, dtype=np.int32))
    first = x.getOwnershipRange()[0]
    negative = 0
    for block in teeth.surface.owned_blocks:
        rows = (first + 3 * block + np.arange(3)).astype(PETSc.IntType)
        exact, newton = (m.getValues(rows, rows) for m in matrices)
        values = np.linalg.eigvalsh(exact)
        scale = max(np.abs(values).max(), 1e-300)
        assert np.linalg.eigvalsh(newton).min() >= -1e-9 * scale
        assert np.linalg.eigvalsh(newton - exact).min() >= -1e-9 * scale
        if values.min() >= -1e-10 * scale:  # positive semidefinite up to round-off: kept
            assert np.abs(newton - exact).max() <= 1e-12 * scale
        else:
            negative += 1
    assert projected == (MPI.COMM_WORLD.allreduce(negative, op=MPI.SUM) > 0)


def test_an_approximate_jacobian_may_take_newtons_projected_factor(model):
    """Newton's last factor, its barrier blocks projected, is not the exact tangent: exact
    sensitivities factorise anew, an approximate Jacobian (``reuse_within``) takes it. Its columns
    lie close to the exact ones: the projection changes a few lining nodes' tangential stiffness."""
    problem = FaceProblem(model, contact=ContactSettings(teeth=True, stiffness=TEETH_STIFFNESS))
    problem.solve(activations=orbicularis_oris(model))
    solver, sensitivity = problem.solver, EquilibriumSensitivity(problem)
    assert not solver.factor_is_exact and solver.factor_distance() == np.inf
    distance = solver.factor_distance(exact=False)
    assert distance < 0.3
    factorizations = solver.factorizations
    assert sensitivity.factor(reuse_within=0.3) == distance and solver.factorizations == factorizations
    approximate = sensitivity.activation_columns()
    assert sensitivity.factor() == 0.0 and solver.factor_is_exact and solver.factorizations == factorizations + 1
    exact = sensitivity.activation_columns()
    owned = problem.V.dofmap.index_map.size_local * 3
    difference, size = (MPI.COMM_WORLD.allreduce(np.sum(a[:, :owned] ** 2), op=MPI.SUM)
                        for a in (approximate - exact, exact))
    assert np.sqrt(difference / size) < 0.01  # 0.0023 on the 5K face


def test_a_node_inside_the_teeth_fails_the_factorisation_not_the_process(pressed):
    """A state with a lining node inside the teeth has no finite barrier block there: Newton's
    projection leaves that block to the tangent instead of raising numpy's LinAlgError (which
    ended a fit from within PETSc's tangent callback)."""
    problem = pressed[0]
    teeth = problem.teeth_contact
    x = problem.u.vector.copy()
    gaps = teeth.gaps(x.array_r)
    obj, node = np.unravel_index(np.argmin(gaps), gaps.shape)
    normal = teeth.objects[obj].gaps(teeth.positions(x.array_r)[[node]], teeth.poses[obj])[1][0]
    owned = np.flatnonzero(teeth.surface.owned_nodes == node)
    if owned.size:  # the rank that owns the node pushes it 0.1 mm inside
        block = teeth.surface.owned_blocks[owned[0]]
        x.array[3 * block:3 * block + 3] -= (gaps[obj, node] + 0.1) * normal
    assert teeth.min_gap(x.array_r) < 0.0
    matrix = problem.solver.tangent.duplicate()
    matrix.zeroEntries()
    teeth.add_hessian(x, matrix, np.zeros(0, dtype=np.int32))
    teeth.add_newton_correction(x, matrix, np.zeros(0, dtype=np.int32))


def test_a_prediction_into_the_teeth_is_pulled_back(model, pressed, caplog):
    """A Gauss-Newton prediction that would put lining nodes inside the teeth (here the pressed
    state's motion from rest, tripled) starts Newton only as far along it as the teeth allow:
    Newton from it converges (without the pull-back it failed and continuation from the last
    equilibrium took over), no node inside at any iterate, the same equilibrium."""
    equilibrium = pressed[0].u.x.array
    problem = FaceProblem(model, contact=ContactSettings(teeth=True, stiffness=TEETH_STIFFNESS))
    teeth = problem.teeth_contact
    guess = 3.0 * equilibrium
    assert teeth.gaps(guess).min() < 0.0
    assert teeth.admissible_fraction(problem.u.x.array, guess) < 1.0
    gaps = []
    problem.solver.snes.setMonitor(lambda snes, it, norm: gaps.append(teeth.min_gap(snes.getSolution().array_r)))
    with caplog.at_level("INFO", logger="face_dolfinx.physics.problem"):
        report = problem.solve(activations=orbicularis_oris(model), guess=guess)
    assert report.converged and report.load_steps == 1
    assert "Newton from the predicted shape failed" not in caplog.text
    assert min(gaps) > 0.0
    assert problem.comm.allreduce(np.abs(problem.u.x.array - equilibrium).max(initial=0.0), op=MPI.MAX) < 1e-3


def test_a_prediction_that_moves_the_jaw_moves_the_teeth_with_the_bones(model):
    """A Gauss-Newton prediction that closes the jaw onto the lining (here the opened, pressed
    equilibrium with its bone nodes put at the closed jaw's frames): the teeth move to the
    prediction's jaw in a solve that holds the bones where the prediction put them (a solve that
    held them at the opened frames pulled the mandible back under the closed teeth and pressed the
    lining into them: a node inside, Newton's barrier blocks without a finite value, the fit ended),
    and Newton converges with no lining node inside at any iterate."""
    problem = FaceProblem(model, contact=ContactSettings(teeth=True, stiffness=TEETH_STIFFNESS))
    teeth = problem.teeth_contact
    problem.solve(activations=orbicularis_oris(model), jaw=jaw_pose(model.jaw, np.radians(3.0)))
    closed = jaw_pose(model.jaw, 0.0)
    guess = problem.u.x.array.copy()
    blocks = problem.bone_blocks
    guess.reshape(-1, 3)[blocks] = (problem.bone_positions(problem.controls.cranium, closed)
                                    - problem.dof_coordinates[blocks])
    starts, gaps = [], []
    newton = problem.solver.newton

    def recorded_newton(**options):
        starts.append(problem.solver.bc_error())
        return newton(**options)

    problem.solver.newton = recorded_newton
    problem.solver.snes.setMonitor(lambda snes, it, norm: gaps.append(teeth.min_gap(snes.getSolution().array_r)))
    report = problem.solve(jaw=closed, guess=guess)
    problem.solver.snes.cancelMonitor()
    del problem.solver.newton
    assert report.converged and min(gaps) > 0.0
    assert len(starts) >= 2  # the teeth's move was a solve of its own (``ContactPotential.move_to``)
    motion = np.abs(guess - problem.u.x.array).max()
    assert starts[0] < 1e-3 * motion  # ... which started with the bones where the prediction put them
    assert problem.residual_norm() < 1e-6


def test_a_prediction_cut_short_while_the_jaw_closes_starts_with_the_teeth_at_the_target(model, caplog):
    """A Gauss-Newton prediction that the teeth cut short (here twice the way from the jaw opened 1
    degree to the orbicularis oris at 1 with the jaw 0.5 degrees beyond closed, a fifth of it
    admissible) while the jaw closes: the teeth go to the target's poses, pushing the lining out,
    before Newton takes the bones there. Left at the cut prediction's poses until Newton started,
    they overran a lining node (a NaN residual) and the solve fell back on continuation from the
    last equilibrium (3 load steps, 145 Newton iterations; 29 and one load step so)."""
    settings = ContactSettings(teeth=True, stiffness=TEETH_STIFFNESS)
    closing = jaw_pose(model.jaw, np.radians(-0.5))
    problem, target = FaceProblem(model, contact=settings), FaceProblem(model, contact=settings)
    problem.solve(jaw=jaw_pose(model.jaw, np.radians(1.0)))
    target.solve(activations=orbicularis_oris(model, 1.0), jaw=closing)
    start = problem.u.x.array.copy()
    guess = start + 2.0 * (target.u.x.array - start)
    guess.reshape(-1, 3)[problem.bone_blocks] = target.u.x.array.reshape(-1, 3)[problem.bone_blocks]
    assert problem.teeth_contact.admissible_fraction(start, guess) < 0.5
    gaps = []
    problem.solver.snes.setMonitor(lambda snes, it, norm: gaps.append(
        problem.teeth_contact.min_gap(snes.getSolution().array_r)))
    with caplog.at_level("INFO", logger="face_dolfinx.physics.problem"):
        report = problem.solve(activations=orbicularis_oris(model, 1.0), jaw=closing, guess=guess)
    problem.solver.snes.cancelMonitor()
    assert report.converged and report.load_steps == 1
    assert "Newton from the predicted shape failed" not in caplog.text
    assert min(gaps) > 0.0


def test_a_prediction_that_moves_the_head_with_its_teeth_is_taken_whole(model, pressed, caplog):
    """A Gauss-Newton prediction that carries the pressed face rigidly with the cranium (2 degrees
    about a tilted axis and 1 mm): the lining moves with the teeth it rests on. The teeth's bound on
    each node's path relative to its teeth (``relative_fraction``) leaves it whole where a bound
    against the teeth standing still cuts it, and Newton from it has nothing left to do."""
    problem = FaceProblem(model, contact=ContactSettings(teeth=True, stiffness=TEETH_STIFFNESS))
    problem.u.x.array[:] = pressed[0].u.x.array
    problem.set_controls(pressed[0].controls)
    teeth = problem.teeth_contact
    turn = AffineMap(rotation(np.array([1.0, 0.3, 0.2]), np.radians(2.0)), np.array([0.0, 0.6, 0.8]))
    X = problem.dof_coordinates
    start = problem.u.x.array.copy()
    guess = (turn.apply(X + start.reshape(-1, 3)) - X).reshape(-1)
    cranium = turn.compose(problem.controls.cranium)
    assert teeth.admissible_fraction(start, guess) < 1.0
    assert teeth.relative_fraction(start, guess, problem.teeth_poses(replace(problem.controls, cranium=cranium))) == 1.0
    with caplog.at_level("DEBUG", logger="face_dolfinx.physics.problem"):
        report = problem.solve(cranium=cranium, guess=guess)
    assert report.converged and report.load_steps == 1 and report.newton_iterations <= 1
    assert "prediction pulled back" not in caplog.text
    assert problem.comm.allreduce(np.abs(problem.u.x.array - guess).max(initial=0.0), op=MPI.MAX) < 1e-6


def test_a_prediction_that_takes_the_lining_into_the_teeth_moves_it_out(model, pressed, caplog):
    """A Gauss-Newton prediction that carries the lining resting on the teeth into them (here the
    pressed face translated 0.45 mm against the teeth, its nearest lining node 0.28 mm from them):
    the teeth's bound would cut the whole face's prediction short; instead each lining node whose
    path comes too close stops at the teeth's tangent plane where it does and slides on along it
    (``projected_end``; only those nodes move, no further than asked), and Newton starts from the
    prediction taken whole and reaches the pressed equilibrium, no node inside at any iterate."""
    problem = FaceProblem(model, contact=ContactSettings(teeth=True, stiffness=TEETH_STIFFNESS))
    problem.u.x.array[:] = pressed[0].u.x.array
    problem.set_controls(pressed[0].controls)
    teeth = problem.teeth_contact
    start = problem.u.x.array.copy()
    gaps = teeth.gaps(start)
    obj, node = np.unravel_index(np.argmin(gaps), gaps.shape)
    normal = teeth.objects[obj].gaps(teeth.positions(start)[[node]], teeth.poses[obj])[1][0]
    guess = (start.reshape(-1, 3) - 0.45 * normal).reshape(-1)
    assert teeth.gaps(guess).min() < -0.1 and teeth.admissible_fraction(start, guess) < 0.6

    projected = teeth.projected_end(start, guess, teeth.poses, limit=0.5)
    moves = np.linalg.norm(teeth.positions(projected) - teeth.positions(guess), axis=1)
    assert 0.0 < moves.max() <= 0.5
    assert (teeth.gaps(projected) >= 0.5 * (1.0 - CCD_KEEP) * gaps).all()
    changed = np.flatnonzero(np.any(projected.reshape(-1, 3) != guess.reshape(-1, 3), axis=1))
    assert np.isin(changed, teeth.surface.local_blocks_of(moves > 0.0)[0]).all()
    assert teeth.projected_end(start, guess, teeth.poses, limit=0.5 * moves.max()) is None

    iterate_gaps = []
    problem.solver.snes.setMonitor(lambda snes, it, norm: iterate_gaps.append(teeth.min_gap(snes.getSolution().array_r)))
    with caplog.at_level("DEBUG", logger="face_dolfinx.physics.problem"):
        report = problem.solve(guess=guess)
    problem.solver.snes.cancelMonitor()
    assert "lining moved out of the teeth instead" in caplog.text and "prediction pulled back" not in caplog.text
    assert report.converged and report.load_steps == 1 and min(iterate_gaps) > 0.0
    assert problem.comm.allreduce(np.abs(problem.u.x.array - start).max(initial=0.0), op=MPI.MAX) < 1e-3


def test_a_lining_node_from_afar_is_projected_out_of_the_teeth(model, pressed):
    """A lining node 5-8 mm from the teeth whose prediction takes it 0.3 mm into them: its
    clearance ((1 - CCD_KEEP) of its gap, over 1 mm) lies beyond the teeth's dhat, and its
    projected place is checked against that clearance by its true gap (the gap within dhat alone
    is a lower bound there, dhat, which refused the projection), so ``projected_end`` moves it out
    to the teeth's tangent plane at that clearance, by less than the limit, and it alone."""
    problem = FaceProblem(model, contact=ContactSettings(teeth=True, stiffness=TEETH_STIFFNESS))
    problem.u.x.array[:] = pressed[0].u.x.array
    teeth = problem.teeth_contact
    start = problem.u.x.array.copy()
    gaps = teeth.gaps(start)
    nearest = gaps.min(axis=0)
    node = int(np.flatnonzero((nearest > 5.0) & (nearest < 8.0))[0])
    obj = int(np.argmin(gaps[:, node]))
    x = teeth.positions(start)
    normal = teeth.objects[obj].gaps(x[[node]], teeth.poses[obj])[1][0]
    x[node] -= (nearest[node] + 0.3) * normal
    guess = teeth.surface.placed(start, x, np.array([node]))
    assert teeth.gaps(guess)[obj, node] < 0.0
    clearance = (1.0 - CCD_KEEP) * nearest[node]
    assert clearance > 2.0 * TEETH_DHAT

    projected = teeth.projected_end(start, guess, teeth.poses, limit=2.0)
    assert projected is not None
    ends = teeth.positions(projected)
    assert teeth.gaps(projected)[obj, node] >= 0.5 * clearance
    assert 0.0 < np.linalg.norm(ends[node] - x[node]) <= 2.0
    others = np.arange(len(ends)) != node
    assert np.abs(ends[others] - teeth.positions(guess)[others]).max(initial=0.0) == 0.0


def test_a_cut_prediction_keeps_the_heads_whole_motion(model, pressed):
    """A Gauss-Newton prediction that turns the head (2 degrees about a tilted axis and 1 mm) and
    carries the lining into the teeth far enough to be cut short (the pressed shape's displacement
    from rest tripled, turned with the head; the teeth cut it to 0.15): the equilibrium is first
    carried rigidly with the head's whole change, teeth included, and the bounds cut only the rest.
    Newton then starts with the cranium's nodes at the target's frame (1e-14 mm off; 9 Newton
    iterations, 4 factorisations); with the head's motion in the cut prediction (``carry_head``
    off) they started 3.1 mm off, of 3.7 mm of motion, left to the lifting of Newton's first step,
    and the teeth's move to their poses took a solve of its own (21 iterations, 10 factorisations
    in all)."""
    turn = AffineMap(rotation(np.array([1.0, 0.3, 0.2]), np.radians(2.0)), np.array([0.0, 0.6, 0.8]))
    starts = {}
    for carry in (True, False):
        problem = FaceProblem(model, contact=ContactSettings(teeth=True, stiffness=TEETH_STIFFNESS))
        problem.carry_head = carry
        problem.u.x.array[:] = pressed[0].u.x.array
        problem.set_controls(pressed[0].controls)
        X = problem.dof_coordinates
        start = problem.u.x.array.copy()
        guess = (turn.apply(X + 3.0 * start.reshape(-1, 3)) - X).reshape(-1)
        cranium = turn.compose(problem.controls.cranium)
        newton, errors = problem.solver.newton, []

        def recorded_newton(**options):
            errors.append(problem.solver.bc_error())
            return newton(**options)

        problem.solver.newton = recorded_newton
        gaps = []
        problem.solver.snes.setMonitor(lambda snes, it, norm: gaps.append(
            problem.teeth_contact.min_gap(snes.getSolution().array_r)))
        report = problem.solve(cranium=cranium, guess=guess)
        problem.solver.snes.cancelMonitor()
        assert report.converged and min(gaps) > 0.0
        starts[carry] = errors[-1]  # the last solve is Newton's own
    motion = np.abs(turn.apply(X) - X).max()
    assert starts[True] < 1e-9 * motion < starts[False] and starts[False] > 0.5 * motion


def test_a_slow_fall_on_the_teeth_relaxes_the_contact_nodes_instead_of_refactorising(model, pressed, caplog):
    """With the factor kept across solves, the default ``contact_relaxation`` (None) starts the
    relaxation of the contact nodes where the residual's slow fall would refresh the factor while
    the teeth's contact nodes hold SLOW_FALL_CONTACT_SHARE of the residual's square, and keeps the
    factor there: the orbicularis oris raised by half from the lips pressed on the teeth (a warm
    start). It reaches the equilibrium Newton reaches without it, with fewer factorisations (3
    against 9), no Newton iterate with a lining node inside the teeth."""
    start, _, _ = pressed
    solved = {}
    for relaxation in (None, False):
        problem = FaceProblem(model, contact=ContactSettings(teeth=True, stiffness=TEETH_STIFFNESS),
                              reuse_factorization=True, contact_relaxation=relaxation)
        problem.adopt(start.controls, start.u.x.array)
        gaps = []
        problem.solver.snes.setMonitor(lambda snes, it, norm: gaps.append(
            problem.teeth_contact.min_gap(snes.getSolution().array_r)))
        with caplog.at_level("DEBUG", logger="face_dolfinx.equilibrium.solver"):
            assert problem.solve(activations=orbicularis_oris(model, 1.5 * LEVEL)).converged
        problem.solver.snes.cancelMonitor()
        started = any("the factor kept" in record.getMessage() for record in caplog.records)
        caplog.clear()
        solved[relaxation] = problem, MPI.COMM_WORLD.bcast(started), min(gaps)
    (relaxed, started, closest), (plain, plain_started, _) = solved[None], solved[False]
    assert started and not plain_started and relaxed.solver.relaxation.local_iterations > 0
    assert relaxed.solver.factorizations < plain.solver.factorizations
    assert np.abs(relaxed.u.x.array - plain.u.x.array).max() < 1e-4  # mm
    assert closest > 0.0


def test_same_force_on_one_rank(model, builtin_model_path, pressed):
    problem = pressed[0]
    serial = FaceProblem(load_model(builtin_model_path, MPI.COMM_SELF),
                         contact=ContactSettings(teeth=True, stiffness=TEETH_STIFFNESS))
    serial.solve(activations=orbicularis_oris(model))
    here = problem.teeth_contact.nodal_forces(problem.u.x.array)
    alone = serial.teeth_contact.nodal_forces(serial.u.x.array)
    assert np.abs(here - alone).max() <= 1e-6 * np.abs(alone).max()


def test_without_teeth_the_lips_go_through(model, pressed):
    """The same solve without contact leaves lining nodes inside the teeth: the contact matters."""
    problem = FaceProblem(model)
    problem.solve(activations=orbicularis_oris(model))
    teeth = pressed[0].teeth_contact
    assert teeth.gaps(problem.u.x.array).min() < 0.0


def test_jaw_opened_and_closed_with_the_teeth(model):
    """A 10 degree jaw opening from rest with the teeth on converges in one load step, no lining
    node the barrier holds is inside the teeth at any Newton iterate, and the bone-held ones are
    outside at the end; closing it again converges in bounded iterations, no lining node inside at
    any Newton iterate."""
    problem = FaceProblem(model, contact=ContactSettings(teeth=True, stiffness=TEETH_STIFFNESS))
    teeth = problem.teeth_contact
    gaps = []
    problem.solver.snes.setMonitor(lambda snes, it, norm: gaps.append(teeth.min_gap(snes.getSolution().array_r)))
    report = problem.solve(jaw=jaw_pose(model.jaw, np.radians(10.0)))
    problem.solver.snes.cancelMonitor()
    assert report.converged and report.load_steps == 1 and len(gaps) > 1
    assert min(gaps) > 0.0
    points = teeth.positions(problem.u.x.array)
    assert min(float(obj.gaps(points, pose)[0].min()) for obj, pose in zip(teeth.objects, teeth.poses)) > 0.0
    assert teeth.contact_nodes(problem.u.x.array) > 0  # the lining rests on the teeth
    assert problem.residual_norm() < 1e-6
    # Closed again: the lower teeth carry the lining they would overrun (143 Newton iterations in
    # 5 load steps measured, 219 in 8 carrying only the lining within CARRY_REACH).
    gaps.clear()
    problem.solver.snes.setMonitor(lambda snes, it, norm: gaps.append(teeth.min_gap(snes.getSolution().array_r)))
    report = problem.solve(jaw=jaw_pose(model.jaw, 0.0))
    problem.solver.snes.cancelMonitor()
    assert report.converged and report.newton_iterations <= CLOSING_ITERATIONS
    assert min(gaps) > 0.0
    assert problem.residual_norm() < 1e-6


def test_teeth_carried_to_a_subject(template):
    """carry_model with the skin moved smoothly (a broader, shorter face): the teeth follow the
    lining they rest on and stay clear of it."""
    from face_dolfinx.subjects.adaptation import carry_model
    skin = template.points[template.skin_nodes]
    centre = skin.mean(axis=0)
    bump = np.exp(-np.sum(((skin - centre) / 60.0) ** 2, axis=1))[:, None]
    targets = centre + (skin - centre) * [1.06, 0.95, 1.0] + 2.0 * bump * [0.0, 0.0, 1.0]
    subject, _ = carry_model(template, targets, name="subject")
    before, after = lining_gaps(template), lining_gaps(subject)
    for bone in ("cranium", "mandible"):
        resting = before[bone] < 1.0  # the lining on the teeth
        assert after[bone].min() > TEETH_DHAT, bone
        assert np.abs(after[bone] - before[bone])[resting].max() < 0.05, bone



def test_simulate_with_contact(model, template, shared_dir):
    """run.py simulate --contact: the teeth rows of summary.json; a model without teeth is refused
    naming it, before any solve."""
    import json
    from face_dolfinx.cli.main import main
    out = shared_dir / "smile"
    assert main(["simulate", "smile", "--model", str(model.path), "--contact", "--out", str(out), "--no-render"]) == 0
    row = json.loads((out / "summary.json").read_text())["expressions"][0]
    assert row["expression"] == "smile" and row["teeth"]["min_gap_mm"] > 0.0
    bare = shared_dir / "no_teeth"
    on_rank_0(lambda: replace(template, teeth={}).write(bare))
    with pytest.raises(SystemExit, match=r"model .*no_teeth has no teeth"):
        main(["simulate", "smile", "--model", str(bare), "--contact", "--out", str(shared_dir / "never"), "--no-render"])
    assert not (shared_dir / "never").exists()
