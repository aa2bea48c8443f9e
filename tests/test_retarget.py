"""Retargeting a take onto another face model (docs/retargeting.md).

- A uniformly scaled and turned copy of the small face, driven by the retargeted controls, moves
  as the scaled and turned copy of the source's motion (quasistatic elasticity has no length
  scale): the head and jaw transfer checked from outside.
- Round trip: a take fitted on the small face (A), retargeted to a differently proportioned subject
  adapted from it (B: the template's skin scaled by diag(1.15, 0.9, 1.05), carried by
  ``subjects.carry_model``), simulated on B and refitted from B's markers gives back the
  activations, jaw and head it was given.
- Different muscle sets map what they share and record what they drop; a target without a jaw, or
  sharing no muscle, is refused with one message; the ``retarget`` command writes the animation
  and its record.
Also under mpirun -n 2.
"""
import dataclasses
import json
import math

from mpi4py import MPI
import numpy as np
import pytest

from conftest import on_rank_0
from face_dolfinx.animation import Animation
from face_dolfinx.animation.retarget import RetargetError, carry_tmj, retarget
from face_dolfinx.capture.synthetic import synthesize_take
from face_dolfinx.fitting import FaceFitter, FitSettings, MarkerSet
from face_dolfinx.model.bones import AffineMap, jaw_pose, rigid_map, rotation, tmj_values
from face_dolfinx.model.folder import load_model, read_model_arrays
from face_dolfinx.physics.problem import FaceProblem
from face_dolfinx.sensitivities.columns import EquilibriumSensitivity, bone_position_derivatives
from face_dolfinx.subjects.adaptation import carry_model
from face_dolfinx.tracking import track

FRAMES = 4
SUBJECT_STRETCH = np.diag([1.15, 0.9, 1.05])   # wider, shorter, deeper than the template
# 1.2 times the size, turned 10 degrees about the vertical and moved: the scaled copy
COPY_SCALE, COPY_TURN, COPY_SHIFT = 1.2, rotation([0.0, 1.0, 0.0], math.radians(10.0)), np.array([5.0, -3.0, 2.0])


def affine_subject(template, matrix, translation, folder, name):
    """The template carried onto its own skin moved by x -> matrix x + translation (written on
    rank 0), loaded on every rank, and as arrays."""
    def write():
        moved = template.points[template.skin_nodes] @ matrix.T + translation
        carry_model(template, moved, name=name)[0].write(folder)
    on_rank_0(write)
    return load_model(folder, MPI.COMM_WORLD), read_model_arrays(folder, check=False)


@pytest.fixture(scope="module")
def subject(template, shared_dir):
    return affine_subject(template, SUBJECT_STRETCH, np.zeros(3), shared_dir / "subject_b", "subject_b")


@pytest.fixture(scope="module")
def scaled_copy(template, shared_dir):
    return affine_subject(template, COPY_SCALE * COPY_TURN, COPY_SHIFT, shared_dir / "scaled", "scaled_copy")


def simulate(model, animation, sites):
    """Markers at ``sites`` (markers, 3) of the model driven by ``animation``, frame after frame."""
    problem = FaceProblem(model)
    markers = MarkerSet(problem, sites)
    positions = []
    for frame in range(animation.n_frames):
        controls = animation.frame_controls(frame, model)
        problem.solve(activations=controls.activations, cranium=controls.cranium, jaw=controls.jaw)
        positions.append(markers.positions(problem.u.x.array, controls.cranium))
    return np.array(positions)


def test_tmj_values_invert_jaw_pose(model):
    for values in ([0.3, 1.0, 2.5], [0.1, 4.0, 0.0], [0.0, 0.0, 0.0], [0.42, 10.0, 10.0]):
        assert tmj_values(model.jaw, jaw_pose(model.jaw, *values)) == pytest.approx(values, abs=1e-12)


def test_scaled_copy_moves_as_the_scaled_copy_of_the_motion(model, template, scaled_copy):
    copy, copy_arrays = scaled_copy
    activations = np.zeros(len(template.muscles))
    for name, value in model.expressions["smile"].items():
        if name != "jaw_opening_deg":
            activations[model.muscle_index(name)] = value
    head = rigid_map(rotation([1.0, 0.3, 0.0], math.radians(5.0)), np.array([0.0, -40.0, 10.0]),
                     np.array([1.5, -2.0, 0.5]))
    motion = Animation([0.0], model.muscle_names, [activations], [head], None, tmj=[[0.15, 2.0, 3.0]])
    moved, record = retarget(motion, template, copy_arrays)
    assert record["head"]["scale"] == pytest.approx(COPY_SCALE, rel=1e-12)
    assert np.allclose(record["head"]["rotation"], COPY_TURN, atol=1e-12)
    assert moved.tmj[0] == pytest.approx([0.15, 2.0 * COPY_SCALE, 3.0 * COPY_SCALE], rel=1e-12)
    assert moved.cranium[0].matrix == pytest.approx(COPY_TURN @ head.matrix @ COPY_TURN.T, abs=1e-12)
    sites = np.array(list(model.markers.values()))
    source = simulate(model, motion, sites)
    target = simulate(copy, moved, sites @ (COPY_SCALE * COPY_TURN).T + COPY_SHIFT)
    expected = source @ (COPY_SCALE * COPY_TURN).T + COPY_SHIFT
    motion_size = np.abs(source - sites).max()
    assert motion_size > 5.0  # mm: head, jaw and smile move the markers
    assert np.abs(target - expected).max() <= 1e-6 * COPY_SCALE * motion_size


def test_round_trip_through_a_differently_proportioned_subject(model, template, subject):
    subject_model, subject_arrays = subject
    sites = np.array(list(model.markers.values()))
    problem = FaceProblem(model)
    capture, _ = synthesize_take(problem, MarkerSet(problem, sites), model, "speech", n_frames=FRAMES,
                                 noise=0.3, seed=5)
    fitted = track(FaceFitter(problem, MarkerSet(problem, sites), FitSettings()), capture.positions)
    motion = Animation(capture.times, model.muscle_names, [r.activations for r in fitted], [r.cranium for r in fitted],
                       None, tmj=[r.jaw_tmj for r in fitted])
    moved, record = retarget(motion, template, subject_arrays)
    assert record["muscles"]["dropped"] == {} and record["muscles"]["held_at_rest"] == []
    assert np.array_equal(moved.activations, motion.activations)
    subject_sites = np.array(list(subject_model.markers.values()))
    markers = simulate(subject_model, moved, subject_sites)
    settings = FitSettings(max_gn_steps=8, relative_decrease=0.0)
    refit_problem = FaceProblem(subject_model)
    refit_markers = MarkerSet(refit_problem, subject_sites)
    fitter = FaceFitter(refit_problem, refit_markers, settings)
    for frame in range(FRAMES):
        result = fitter.fit_frame(markers[frame], frame=frame)
        # Gauss-Newton stops once the marker RMS error is below marker_tolerance. To first order a
        # marker residual r moves the least-squares controls by at most |r| / sigma_min(J), J the
        # markers' Jacobian in all controls (activations, TMJ values, head rotation and translation)
        # at the fitted state: the activations the round trip must give back, to that bound.
        assert result.flag == "" and result.rms_error <= settings.marker_tolerance
        bound = math.sqrt(len(subject_sites)) * settings.marker_tolerance / smallest_singular_value(
            refit_problem, refit_markers)
        assert bound < 0.01  # says something: measured 1.2e-3, with errors of 1e-7 to 2e-6
        assert np.abs(result.activations - moved.activations[frame]).max() <= bound
        assert np.abs(result.jaw_tmj - moved.tmj[frame]).max() <= bound
        assert np.abs(result.cranium.matrix - moved.cranium[frame].matrix).max() <= bound


def smallest_singular_value(problem, markers) -> float:
    """sigma_min of d(markers)/d(controls) at the problem's equilibrium: activations, TMJ values
    (rad, mm) and a rotation vector (rad) and translation (mm) of the head after its frame."""
    sensitivity = EquilibriumSensitivity(problem)
    sensitivity.factor()
    controls = problem.controls
    tmj = tmj_values(problem.model.jaw, controls.jaw)

    def jaw_pose_of(values):
        return controls.cranium, jaw_pose(problem.model.jaw, *values)

    def head_pose_of(values):
        turn = rotation(values[:3], np.linalg.norm(values[:3])) if np.any(values[:3]) else np.eye(3)
        return rigid_map(turn, np.zeros(3), values[3:]).compose(controls.cranium), controls.jaw
    columns = [sensitivity.activation_columns(),
               sensitivity.boundary_columns(bone_position_derivatives(problem, jaw_pose_of, tmj, 1e-6)),
               sensitivity.boundary_columns(bone_position_derivatives(problem, head_pose_of, np.zeros(6), 1e-6))]
    jacobian = markers.evaluator.values_many(np.concatenate(columns)).reshape(-1, 3 * len(markers.reference))
    return float(np.linalg.svd(jacobian, compute_uv=False).min())


def test_different_muscle_sets_map_what_they_share(model, template):
    kept = template.muscles[2:]
    renamed = dataclasses.replace(template.muscles[2], name="procerus")
    target = dataclasses.replace(template, muscles=kept + [renamed])
    activations = np.linspace(0.0, 0.6, len(template.muscles))[None, :]
    motion = Animation([0.0], model.muscle_names, activations, [AffineMap()], None, tmj=np.zeros((1, 3)))
    moved, record = retarget(motion, template, target)
    record = record["muscles"]
    assert record["mapped"] == [m.name for m in kept]
    assert record["dropped"] == {m.name: pytest.approx(a) for m, a in zip(template.muscles[:2], activations[0, :2])}
    assert record["held_at_rest"] == ["procerus"]
    assert moved.muscle_names == tuple(m.name for m in kept)  # procerus: not named, so at rest
    assert np.array_equal(moved.activations[0], activations[0, 2:])


def test_jaw_is_clamped_to_the_targets_bounds(template):
    small = dataclasses.replace(template.jaw, max_opening_sine=0.2, track_length=5.0)
    # slides as fractions of the track (10 mm on the source): only a slide beyond the source's own
    # track (a paper-mode fit's, held there by a penalty) leaves the target's
    tmj = np.array([[0.3, 4.0, 12.0], [0.1, 2.0, 1.0]])
    carried, record = carry_tmj(tmj, template.jaw, small)
    assert carried == pytest.approx(np.array([[math.asin(0.2), 2.0, 5.0], [0.1, 1.0, 0.5]]))
    assert record["clamped_frames"] == dict(opening=1, slide_right=0, slide_left=1)


def test_jaw_given_by_frames_carries_its_tmj_values(model, template, subject):
    """A paper-mode fit gives the jaw as frames: their TMJ values (``bones.tmj_values``) carry over."""
    tmj = np.array([[0.2, 1.0, 3.0], [0.05, 0.0, 0.0]])
    frames = Animation([0.0, 0.1], model.muscle_names, np.zeros((2, len(template.muscles))), [AffineMap()] * 2,
                       [jaw_pose(template.jaw, *values) for values in tmj])
    values = Animation([0.0, 0.1], model.muscle_names, np.zeros((2, len(template.muscles))), [AffineMap()] * 2,
                       None, tmj=tmj)
    subject_arrays = subject[1]
    assert retarget(frames, template, subject_arrays)[0].tmj == pytest.approx(
        retarget(values, template, subject_arrays)[0].tmj, abs=1e-12)


def test_bad_targets_are_refused_with_one_message(model, template):
    moving_jaw = Animation([0.0], model.muscle_names, np.zeros((1, len(template.muscles))), [AffineMap()], None,
                           tmj=[[0.2, 0.0, 0.0]])
    values = template.facet_values.copy()
    values[values == template.boundary_ids["mandible"]] = template.boundary_ids["free"]
    jawless = dataclasses.replace(template, facet_values=values)
    with pytest.raises(RetargetError, match=r"has no jaw \(no facets tagged mandible\).*opening up to 11.5 deg"):
        retarget(moving_jaw, template, jawless)
    still_jaw = dataclasses.replace(moving_jaw, tmj=np.zeros((1, 3)))
    assert retarget(still_jaw, template, jawless)[1]["muscles"]["dropped"] == {}
    strangers = dataclasses.replace(template, muscles=[dataclasses.replace(m, name=f"other_{m.name}")
                                                       for m in template.muscles])
    with pytest.raises(RetargetError, match="shares no muscle with the animation"):
        retarget(still_jaw, template, strangers)
    values[values == template.boundary_ids["oral"]] = template.boundary_ids["free"]
    puffing = dataclasses.replace(still_jaw, pressure=np.array([2.0]))
    with pytest.raises(RetargetError, match=r"no oral surface .*\(up to 2 kPa\)"):
        retarget(puffing, template, dataclasses.replace(template, facet_values=values))


def test_retarget_command_carries_a_fit_that_simulate_plays(builtin_model_path, subject, shared_dir):
    """synth and fit on the small face, retarget the fit folder onto subject B, play it there."""
    from face_dolfinx.cli.main import main
    from face_dolfinx.results.folder import FitFolder
    subject_model, subject_arrays = subject
    folder = shared_dir / "command"
    take, fit, animation = folder / "take.trc", folder / "fit", folder / "on_b.csv"
    model = ["--model", str(builtin_model_path)]
    assert main(["synth", *model, "--frames", "3", "--noise", "0.2", "--out", str(take)]) == 0
    assert main(["fit", str(take), *model, "--out", str(fit)]) == 0
    assert main(["retarget", str(fit), "--model", str(subject_model.path), "--out", str(animation)]) == 0
    record = json.loads((folder / "on_b.retarget.json").read_text())
    assert record["source_model"] == str(builtin_model_path) and record["frames"] == 3
    assert record["head"]["scale"] == pytest.approx(np.linalg.det(SUBJECT_STRETCH) ** (1 / 3), rel=0.05)
    played = Animation.read(animation)
    expected, _ = retarget(Animation.read(fit), read_model_arrays(builtin_model_path, check=False), subject_arrays)
    assert np.array_equal(played.activations, expected.activations) and np.array_equal(played.tmj, expected.tmj)
    assert main(["simulate", *["--model", str(subject_model.path)], "--animation", str(animation),
                 "--out", str(folder / "sim"), "--no-render"]) == 0
    frames = FitFolder(folder / "sim").finished_frames()
    assert sorted(frames) == [0, 1, 2]
    for frame, result in frames.items():
        controls = played.frame_controls(frame, subject_model)
        assert np.array_equal(result.activations, controls.activations)
        assert result.cranium.same_as(controls.cranium)
    with pytest.raises(SystemExit, match="exists; pass --overwrite"):
        main(["retarget", str(fit), "--model", str(subject_model.path), "--out", str(animation)])


@pytest.mark.parametrize("change, message", [
    ("jawless", r"has no jaw \(no facets tagged mandible\)"),
    ("strangers", "shares no muscle"),
])
def test_retarget_command_refuses_bad_targets_writing_nothing(builtin_model_path, template, shared_dir,
                                                              change, message):
    from face_dolfinx.cli.main import main
    folder = shared_dir / "refused" / change
    values = template.facet_values.copy()
    if change == "jawless":
        values[values == template.boundary_ids["mandible"]] = template.boundary_ids["free"]
    muscles = [dataclasses.replace(m, name=f"other_{m.name}") if change == "strangers" else m
               for m in template.muscles]
    expressions = {} if change == "strangers" else template.expressions  # they name the muscles
    on_rank_0(lambda: dataclasses.replace(template, facet_values=values, muscles=muscles,
                                          expressions=expressions).write(folder / "target"))
    take = shared_dir / "refused" / "jaw.csv"
    names = ",".join(template.muscles[i].name for i in (0, 1))
    on_rank_0(lambda: take.write_text(f"time_s,{names},jaw_opening_deg\n0,0.1,0.2,0\n0.1,0.3,0.4,8\n"))
    out = folder / "never.csv"
    with pytest.raises(SystemExit, match=message):
        main(["retarget", str(take), "--source-model", str(builtin_model_path), "--model", str(folder / "target"),
              "--out", str(out)])
    assert not out.exists() and not (folder / "never.retarget.json").exists()
    with pytest.raises(SystemExit, match="does not name the model it was made for; give --source-model"):
        main(["retarget", str(take), "--model", str(folder / "target"), "--out", str(out)])
