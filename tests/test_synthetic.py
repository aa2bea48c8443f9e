"""Synthetic takes (face_dolfinx.capture.synthetic): the truth is the face solved at the true
controls, the noise has the RMS asked for, outliers and gaps appear as many as asked, and a
seed gives the same take again (another seed another one)."""
import numpy as np
import pytest

from face_dolfinx.capture.synthetic import (SCENARIOS, control_curves, load_truth, save_truth,
                                            synthesize_take)
from face_dolfinx.fitting.fitter import MarkerSet
from face_dolfinx.model.bones import jaw_pose
from face_dolfinx.physics.problem import FaceProblem

FRAMES, NOISE, OUTLIERS, OUTLIER_SIZE, GAPS = 3, 0.5, 2, 10.0, 2


@pytest.fixture(scope="module")
def face(model):
    problem = FaceProblem(model)
    return problem, MarkerSet(problem, np.array(list(model.markers.values())), names=list(model.markers))


def take(face, model, seed, **options):
    problem, markers = face
    settings = dict(n_frames=FRAMES, noise=NOISE, outliers=OUTLIERS, outlier_size=OUTLIER_SIZE, gaps=GAPS)
    return synthesize_take(problem, markers, model, "speech", seed=seed, **{**settings, **options})


@pytest.fixture(scope="module")
def seeded(face, model):
    return take(face, model, seed=5)


def test_truth_is_the_face_at_the_true_controls(face, model, seeded):
    problem, markers = face
    capture, truth = seeded
    activations, tmj, head = control_curves(model, "speech", FRAMES, seed=5)
    assert np.array_equal(truth.activations, activations) and np.array_equal(truth.tmj, tmj)
    assert all(a.same_as(b) for a, b in zip(truth.head, head))
    assert capture.marker_names == list(model.markers) and capture.frame_rate == 60.0
    problem.solve(activations=np.zeros(problem.num_muscles))  # from rest, not from the take's last frame
    frame = FRAMES - 1
    problem.solve(activations=activations[frame], cranium=head[frame], jaw=jaw_pose(model.jaw, *tmj[frame]))
    np.testing.assert_allclose(markers.positions(problem.u.x.array, head[frame]), truth.clean_positions[frame],
                               atol=1e-6)
    assert np.abs(np.diff(truth.clean_positions, axis=0)).max() > 1.0  # the take moves


def test_noise_outliers_and_gaps_as_asked(seeded):
    capture, truth = seeded
    deviation = capture.positions - truth.clean_positions
    gap = ~capture.present
    assert np.isnan(capture.positions[gap]).all() and np.isfinite(capture.positions[~gap]).all()
    # Each gap hides a marker for 2 frames (a tenth of the take, at least 2); two may overlap.
    assert 2 <= gap.sum() <= 2 * GAPS and len(set(np.argwhere(gap)[:, 1])) <= GAPS
    size = np.linalg.norm(deviation, axis=2)
    jumped = size > 5.0
    # Each outlier moves a marker by 10 mm for up to 3 frames (plus its noise), unless a gap hides it.
    assert 1 <= jumped.sum() <= 3 * OUTLIERS and len(set(np.argwhere(jumped)[:, 1])) <= OUTLIERS
    assert np.all(np.abs(size[jumped] - OUTLIER_SIZE) < 5 * NOISE)
    plain = ~gap & ~jumped
    rms = np.sqrt(np.mean(size[plain] ** 2))
    assert rms == pytest.approx(NOISE, rel=0.12)  # 230-odd samples: the RMS to about 5 %
    assert abs(deviation[plain].mean()) < 0.1  # no bias
    # Per-coordinate sigma = noise / sqrt(3), so every direction gets its share.
    np.testing.assert_allclose(deviation[plain].std(axis=0), NOISE / np.sqrt(3), rtol=0.2)


def test_a_seed_gives_the_same_take_and_another_seed_another(face, model):
    """The same noise, outliers and gaps bit for bit (the solves, warm-started from wherever the
    face was, agree to the Newton tolerance); another seed draws others. One frame of the take."""
    first, first_truth = take(face, model, seed=5, frames=range(1))
    again, again_truth = take(face, model, seed=5, frames=range(1))
    other, other_truth = take(face, model, seed=6, frames=range(1))
    np.testing.assert_allclose(again_truth.clean_positions, first_truth.clean_positions, atol=1e-6)
    noise = [capture.positions - truth.clean_positions
             for capture, truth in ((first, first_truth), (again, again_truth), (other, other_truth))]
    np.testing.assert_allclose(noise[1], noise[0], rtol=0, atol=1e-9)
    assert np.array_equal(np.isnan(noise[1]), np.isnan(noise[0]))
    assert np.nanmax(np.abs(noise[2] - noise[0])) > 1.0
    assert not np.array_equal(other_truth.activations, first_truth.activations)  # speech's random phases


def test_noise_free_take_is_its_truth(face, model):
    capture, truth = take(face, model, seed=1, noise=0.0, outliers=0, gaps=0, frames=range(1))
    assert np.array_equal(capture.positions, truth.clean_positions)


def test_head_motion_is_a_small_rigid_drift_or_none(model):
    _, _, still = control_curves(model, "speech", 5, head_motion=False)
    assert all(h.same_as(still[0]) for h in still) and np.array_equal(still[0].matrix, np.eye(3))
    _, _, moving = control_curves(model, "speech", 5)
    for head in moving:
        np.testing.assert_allclose(head.matrix @ head.matrix.T, np.eye(3), atol=1e-14)
        assert np.linalg.norm(head.translation) < 5.0 and np.trace(head.matrix) > 3 - 0.02  # < 8 degrees
    assert np.linalg.norm(moving[-1].translation - moving[0].translation) > 1.0


def test_truth_file_round_trip(seeded, model, tmp_path):
    _, truth = seeded
    save_truth(tmp_path / "take.truth.npz", truth, model.muscle_names)
    read = load_truth(tmp_path / "take.truth.npz")
    for name in ("activations", "tmj", "clean_positions"):
        assert np.array_equal(getattr(read, name), getattr(truth, name)), name
    assert all(a.same_as(b) for a, b in zip(read.head, truth.head))


def test_unknown_scenario():
    with pytest.raises(ValueError, match="unknown scenario 'yawn'; choose from " + ", ".join(SCENARIOS)):
        control_curves(None, "yawn", 10)
