"""Fitting with the teeth: the contact gradient's derivative in the objects' poses
(``ContactPotential.pose_rate_forces``) against central differences for every object kind; the
jaw's sensitivities of the small face with the lips pressed on the lower teeth against central
differences of re-solved equilibria (with the teeth's mixed term, and measurably wrong without it),
the head's too; ``fit --contact``: the lips and the teeth, the lips only on a model without teeth,
recorded in run.json; the paper mode refused with the teeth, by the library and the command alike.
"""
from dataclasses import replace
import logging
from types import SimpleNamespace

from mpi4py import MPI
import numpy as np
import pytest
from dolfinx import fem
from dolfinx import mesh as dmesh

from face_dolfinx.cli.main import main, parse_arguments, tracking_settings
from face_dolfinx.fitting import FitSettings
from face_dolfinx.fitting.formulations import head_combination, make_formulation
from face_dolfinx.model.bones import AffineMap, rotation
from face_dolfinx.physics.contact import TEETH_STIFFNESS, ContactPotential, ContactSettings, HalfSpace, Sphere
from face_dolfinx.physics.problem import FaceProblem
from face_dolfinx.physics.rigid_mesh import TriangleMesh
from face_dolfinx.sensitivities.columns import EquilibriumSensitivity
from face_dolfinx.tracking import Tracker
from slab import slab_model

DHAT = 1.5  # mm: wide, so that many nodes of the slab's top face feel the objects at rest


def box(size):
    """An axis-aligned box [0, size] as 12 outward triangles."""
    corners = np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)], dtype=float) * size
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    return corners, np.array([t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))])


@pytest.fixture(scope="module")
def top_face():
    """The P1 space of the slab and its top face z = 10 (the mesh must outlive the contact: the
    contact surface keeps its communicator)."""
    model = slab_model(cells=(16, 8, 4))
    space = fem.VectorFunctionSpace(model.mesh, ("Lagrange", 1))
    return space, dmesh.locate_entities_boundary(model.mesh, 2, lambda x: np.isclose(x[2], 10.0))


def top_face_contact(top_face, obj, pose):
    """A contact potential of the slab's top face against ``obj`` at ``pose``, and a zero
    displacement."""
    space, facets = top_face
    contact = ContactPotential(space, facets, ContactSettings((obj,), (pose,), dhat=DHAT, stiffness=10.0))
    return contact, np.zeros(space.dofmap.index_map_bs * (space.dofmap.index_map.size_local
                                                         + space.dofmap.index_map.num_ghosts))


# Each kind hovering just above the top face, turned so that gaps, normals and (sphere, the box's
# edges and corners) curvatures vary over the nodes within dhat.
TURN = rotation([0.3, -0.5, 0.8], 0.1)
OBJECTS = {
    "sphere": (Sphere(10.0), AffineMap(TURN, [20.0, 10.0, 20.3])),
    "half-space": (HalfSpace((0.0, 0.0, -1.0)), AffineMap(rotation([0.2, 1.0, 0.1], 0.02), [20.0, 10.0, 10.8])),
    "box": (TriangleMesh(*box((12.0, 8.0, 4.0)), name="box"), AffineMap(TURN, [14.0, 5.0, 9.9])),
}


@pytest.mark.parametrize("kind", OBJECTS)
def test_contact_gradient_rate_in_the_pose_against_differences(top_face, kind):
    obj, pose = OBJECTS[kind]
    contact, displacement = top_face_contact(top_face, obj, pose)
    gaps = contact.gaps(displacement)[0]
    assert gaps.min() > 0.0 and (gaps < DHAT).sum() >= 10, kind
    spin = np.array([0.4, -0.7, 0.5])  # the pose's angular velocity (rad per unit parameter) ...
    velocity = np.array([0.3, 0.2, -0.6])  # ... and its translation's rate (mm per unit)

    def pose_at(h):
        return AffineMap(rotation(spin, h * np.linalg.norm(spin)) @ pose.matrix, pose.translation + h * velocity)

    def forces_at(h):
        contact.set_poses((pose_at(h),))
        return contact.nodal_forces(displacement)

    step = 1e-5
    differences = (forces_at(step) - forces_at(-step)) / (2 * step)
    contact.set_poses((pose,))
    W = np.array([[0.0, -spin[2], spin[1]], [spin[2], 0.0, -spin[0]], [-spin[1], spin[0], 0.0]])
    rate = contact.pose_rate_forces(displacement, [(W @ pose.matrix, velocity)])
    scale = np.abs(differences).max()
    assert scale > 0.0
    assert np.abs(rate - differences).max() < 1e-6 * scale, kind
    assert not contact.pose_rate_forces(displacement, [None]).any()
    # The turn alone: nothing for a sphere turning about its centre, a good part of the rate for
    # the others (so the comparison above sees the turn's terms too).
    turn_only = np.abs(contact.pose_rate_forces(displacement, [(W @ pose.matrix, np.zeros(3))])).max()
    if kind == "sphere":
        assert turn_only < 1e-9 * scale
    else:
        assert turn_only > 0.1 * scale


def test_non_rigid_pose_rate_is_refused(top_face):
    obj, pose = OBJECTS["box"]
    contact, displacement = top_face_contact(top_face, obj, pose)
    stretch = np.diag([1.0, 0.0, 0.0])  # an affine frame's rate, not a rotation's
    with pytest.raises(ValueError, match="box .* moves non-rigidly .* needs rigid frames"):
        contact.pose_rate_forces(displacement, [(stretch, np.zeros(3))])
    contact.set_poses((AffineMap(1.01 * pose.matrix, pose.translation),))
    with pytest.raises(ValueError, match="moves non-rigidly"):
        contact.pose_rate_forces(displacement, [(np.zeros((3, 3)), np.ones(3))])


# -- the small face with the lips pressed on the teeth ---------------------------------------------
LEVEL = 0.1  # the orbicularis oris: about 30 N of the lips on the teeth (tests/test_teeth.py)
# Central-difference steps: the lower incisors move 2e-3 mm for the opening (rad), a tenth of the
# lining's gaps to the teeth, so the barrier stays in its smooth range.
STEPS = {"jaw_opening": 2e-5, "jaw_slide_right": 2e-5, "jaw_slide_left": 2e-5,
         "head_rotation_x": 2e-5, "head_translation_y": 2e-4}


def largest(values, comm):
    return comm.allreduce(float(np.abs(values).max(initial=0.0)), op=MPI.MAX)


@pytest.fixture(scope="module")
def pressed(model):
    """The small face with the orbicularis oris pressing the lips on the teeth (jaw closed), the
    exact formulation's controls there and the jaw and head columns, factorised once: the jaw's
    with and without the teeth's mixed term."""
    problem = FaceProblem(model, contact=ContactSettings(teeth=True, stiffness=TEETH_STIFFNESS))
    problem.solve(activations={name: LEVEL for name in model.muscle_names if name.startswith("orbicularis_oris")})
    formulation = make_formulation(problem, FitSettings(mode="exact", fit_jaw=True, fit_head=True))
    state = formulation.initial_state()
    state.activations = problem.controls.activations.copy()
    sensitivity = EquilibriumSensitivity(problem)
    sensitivity.factor()
    bones = formulation.jaw_position_derivatives(state)
    columns = dict(with_teeth=sensitivity.boundary_columns(bones, formulation.jaw_teeth_derivatives(state)),
                   without_teeth=sensitivity.boundary_columns(bones),
                   head=head_combination(state.cranium) @ sensitivity.cranium_columns())
    return problem, formulation, state, columns


def differences(problem, state_at, step, guess_column):
    """dX/db by central differences of equilibria at the controls ``state_at(+-step)``, each solved
    from the linear prediction of ``guess_column`` (Newton to 1e-8 mm from there; None: from the
    last equilibrium carried along the change of the cranium frame); the problem is
    put back where it was. Returns the column and the Newton iterations."""
    base, controls = problem.u.x.array.copy(), problem.controls.copy()
    shapes, iterations = [], 0
    for sign in (1.0, -1.0):
        state = state_at(sign * step)
        guess = None if guess_column is None else base + sign * step * guess_column
        report = problem.solve(cranium=state.cranium, jaw=state.jaw, guess=guess)
        assert report.converged
        iterations += report.newton_iterations
        shapes.append(problem.u.x.array.copy())
        problem.adopt(controls, base)
    return (shapes[0] - shapes[1]) / (2 * step), iterations


@pytest.mark.parametrize("index", range(3))
def test_jaw_columns_with_the_lips_on_the_teeth_against_differences(pressed, index):
    """Each TMJ column (every dof) against re-solved equilibria: right with the teeth's mixed term
    (largest error 1e-8 to 5e-8 of the column's largest entry, measured), wrong without it (0.57
    to 0.75: the lining on the lower teeth lags the jaw). The solves start from the prediction
    without the mixed term (3 to 7 Newton iterations each), so they do not start at the answer."""
    problem, formulation, state, columns = pressed
    comm = problem.comm
    assert problem.teeth_contact.contact_nodes(problem.u.x.array) > 10
    name = formulation.jaw_names()[index]

    def state_at(h):
        moved = state.copy()
        moved.tmj = state.tmj + h * np.eye(3)[index]
        moved.jaw = formulation.jaw(moved)
        return moved

    column, _ = differences(problem, state_at, STEPS[name], columns["without_teeth"][index])
    scale = largest(column, comm)
    assert scale > 0.5  # mm per rad or per mm
    assert largest(columns["with_teeth"][index] - column, comm) < 1e-4 * scale, name
    assert largest(columns["without_teeth"][index] - column, comm) > 0.2 * scale, name


@pytest.mark.parametrize("name", ["head_rotation_x", "head_translation_y"])
def test_head_columns_carry_the_teeth_along(pressed, name):
    """The analytic head columns: the face, the teeth on the cranium and those on the mandible
    move as one rigid body with the cranium frame, so the pressed equilibrium moves with it
    (largest error 7e-11 of the column, measured)."""
    problem, formulation, state, columns = pressed
    index = formulation.head_names().index(name)

    def state_at(h):
        step = np.zeros(formulation.num_muscles + formulation.head_size + formulation.jaw_size)
        step[formulation.num_muscles + index] = h
        moved = formulation.retract(state, step)
        moved.jaw = formulation.jaw(moved)
        return moved

    column, _ = differences(problem, state_at, STEPS[name], None)
    scale = largest(column, problem.comm)
    assert scale > 0.5
    assert largest(columns["head"][index] - column, problem.comm) < 1e-4 * scale, name


# -- fit --contact -----------------------------------------------------------------------------------
def fit_record(tracker):
    capture = SimpleNamespace(source=None, n_frames=1)
    return tracker.record(capture, SimpleNamespace(method="landmarks", neutral_frame=0))


def test_fit_contact_holds_the_lips_on_each_other_and_on_the_teeth(model):
    settings = tracking_settings(parse_arguments(["fit", "take.trc", "--contact"])[0])
    tracker = Tracker(model, settings)
    problem = tracker.problem
    assert problem.lips is not None and problem.teeth_contact is not None
    assert problem.teeth_contact.stiffness == TEETH_STIFFNESS
    record = fit_record(tracker)
    assert record["contact"] is True and record["contact_surfaces"] == ["lips", "teeth"]

PAPER_WITH_TEETH = (r"the paper mode \(--mode paper\) cannot fit with the teeth \(--contact on a model with teeth\): "
                    r"its affine cranium and jaw frames would shear them; fit with contact in exact mode")


def test_the_paper_mode_refuses_the_teeth_once_for_the_library_and_the_command(model, builtin_model_path, shared_dir):
    """The paper mode's affine frames cannot carry rigid teeth: the formulation refuses them (a
    fitter of the library meets it), and the fit command meets the same refusal before it writes its
    folder. The lips alone, or the head and jaw held, are no reason to refuse."""
    problem = Tracker(model, tracking_settings(parse_arguments(["fit", "take.trc", "--contact"])[0])).problem
    for fit_head, fit_jaw in ((True, True), (False, True), (True, False)):
        with pytest.raises(ValueError, match=PAPER_WITH_TEETH):
            make_formulation(problem, FitSettings(mode="paper", fit_head=fit_head, fit_jaw=fit_jaw))
    assert make_formulation(problem, FitSettings(mode="paper", fit_head=False, fit_jaw=False)).name == "paper"
    lips_only = Tracker(replace(model, teeth={}),
                        tracking_settings(parse_arguments(["fit", "take.trc", "--contact", "--mode", "paper"])[0]))
    assert lips_only.problem.lips is not None and lips_only.problem.teeth_contact is None
    assert make_formulation(lips_only.problem, lips_only.settings.fit).name == "paper"

    options = ["--model", str(builtin_model_path)]
    take = shared_dir / "paper" / "take.trc"
    assert main(["synth", *options, "--frames", "2", "--out", str(take)]) == 0
    out = shared_dir / "paper" / "fit"
    with pytest.raises(SystemExit, match="face-dolfinx fit: " + PAPER_WITH_TEETH):
        main(["fit", str(take), *options, "--out", str(out), "--contact", "--mode", "paper"])
    assert not out.exists()


def test_fit_contact_on_a_model_without_teeth_keeps_the_lips(model, caplog):
    toothless = replace(model, teeth={})
    tracker = Tracker(toothless, tracking_settings(parse_arguments(["fit", "take.trc", "--contact"])[0]))
    with caplog.at_level(logging.WARNING):
        problem = tracker.problem
    assert problem.lips is not None and problem.teeth_contact is None
    assert fit_record(tracker)["contact_surfaces"] == ["lips"]
    if MPI.COMM_WORLD.rank == 0:
        assert "has no teeth ([teeth] in its model.toml): contact holds the lips on each other only" in caplog.text
    assert fit_record(Tracker(model, tracking_settings(parse_arguments(["fit", "take.trc"])[0])))["contact_surfaces"] == []
