"""Edits in activation space: in-betweens on the controls' own spaces, exaggeration with clamping,
splicing and retiming, keyframes of one muscle, smoothing; and ``run.py edit``."""
import pathlib

import numpy as np
import pytest
from mpi4py import MPI

from face_dolfinx.animation import Animation, AnimationError, keyframe_curve
from face_dolfinx.animation import editing
from face_dolfinx.cli.main import main
from face_dolfinx.model.bones import AffineMap, rotation, tmj_upper_limits

RNG = np.random.default_rng(7)


def rotation_angle(matrix) -> float:
    """The angle of a rotation, accurate near 0 too (arccos of the trace is not)."""
    axial = np.array([matrix[2, 1] - matrix[1, 2], matrix[0, 2] - matrix[2, 0], matrix[1, 0] - matrix[0, 1]])
    return float(np.arctan2(np.linalg.norm(axial) / 2, (np.trace(matrix) - 1) / 2))


def pose(names, activations, cranium=None, tmj=(0.0, 0.0, 0.0), time=0.0) -> Animation:
    return Animation([time], names, [activations], [cranium or AffineMap()], None, None, [tmj], source="pose")


def take(frames=30, rate=30.0, names=("frontalis_left", "mentalis_left")) -> Animation:
    """A take at ``rate`` Hz: smooth activation curves, a head turn, a jaw opening."""
    t = np.arange(frames) / rate
    activations = np.column_stack([0.5 + 0.4 * np.sin(2 * np.pi * (k + 1) * t) for k in range(len(names))])
    cranium = [AffineMap(rotation([0, 1, 0], 0.3 * s), [2 * s, 0, 0]) for s in t]
    tmj = np.column_stack([0.1 * t, 0.5 * t, 0.2 * t])
    return Animation(t, names, activations, cranium, None, None, tmj, source="take")


def test_in_betweens_end_at_the_inputs_and_are_attainable(model):
    """Endpoints are the two poses exactly; every in-between has activations in [0, 1], a
    cranium rotation that is orthonormal and turned by its share of the angle, and TMJ values
    within the model's bounds (sifakis2005 figure 10)."""
    upper = tmj_upper_limits(model.jaw)
    names = model.muscle_names
    first = pose(names[:3], [1.0, 0.0, 0.4], AffineMap(rotation([1, 0, 0], 0.1), [0, 1, 0]), upper * [1, 0, 1])
    second = pose(names[2:5], [1.0, 1.0, 0.0], AffineMap(rotation([0.3, 1, 0], 2.5), [5, 0, -3]), upper * [0, 1, 0])
    path = editing.between(first, second, frames=9, duration=2.0)
    assert np.allclose(path.times, np.linspace(0, 2, 9))
    start, end = path.frame_controls(0, model), path.frame_controls(8, model)
    for controls, given in ((start, first), (end, second)):
        expected = given.controls_at(0.0, model)
        assert np.array_equal(controls.activations, expected.activations)
        assert controls.cranium.same_as(expected.cranium) and controls.jaw.same_as(expected.jaw)
    relative = second.cranium[0].matrix @ first.cranium[0].matrix.T
    for k in range(9):
        assert np.all((path.activations[k] >= 0) & (path.activations[k] <= 1))
        matrix = path.cranium[k].matrix
        assert np.abs(matrix @ matrix.T - np.eye(3)).max() < 1e-12 and np.linalg.det(matrix) == pytest.approx(1)
        turned = matrix @ first.cranium[0].matrix.T
        assert rotation_angle(turned) == pytest.approx(k / 8 * rotation_angle(relative), abs=1e-9)
        assert np.all(path.tmj[k] >= 0) and np.all(path.tmj[k] <= upper + 1e-15)
    path.check(model)
    # The linear blend of the matrices would not be a rotation half way through this turn.
    blend = 0.5 * (first.cranium[0].matrix + second.cranium[0].matrix)
    assert np.abs(blend @ blend.T - np.eye(3)).max() > 0.1
    with pytest.raises(AnimationError, match="a pose is one frame"):
        editing.between(take(), second, 3, 1.0)


def test_scaling_about_neutral_or_a_pose_clamps(model):
    animation = take()
    doubled = editing.scaled(animation, 2.0)
    assert np.array_equal(doubled.activations, np.clip(2 * animation.activations, 0, 1))
    assert doubled.activations.max() == 1.0 and (2 * animation.activations).max() > 1.5  # clamping did work
    reference = pose(["frontalis_left"], [0.5])
    about = editing.scaled(animation, 3.0, about=reference)
    expected = np.clip(np.column_stack([0.5 + 3 * (animation.activations[:, 0] - 0.5), 3 * animation.activations[:, 1]]),
                       0, 1)
    assert np.allclose(about.activations, expected)
    assert about.activations.min() == 0.0 and about.activations.max() == 1.0
    assert np.allclose(editing.scaled(animation, 0.0, about=reference).activations[:, 0], 0.5)
    assert all(a.same_as(b) for a, b in zip(about.cranium, animation.cranium))  # the head is not scaled
    with pytest.raises(AnimationError, match="0 or more"):
        editing.scaled(animation, -1.0)


def test_segments_retime_and_splice():
    animation = take(frames=31, rate=10.0)  # 0 .. 3 s
    part = editing.segment(animation, 1.0, 2.0, speed=2.0)
    assert np.allclose(part.times, np.arange(11) / 20)
    assert np.array_equal(part.activations, animation.activations[10:21])
    slow = editing.segment(animation, 0.0, 1.0, speed=0.5, frame_rate=10.0)  # 1 s of take over 2 s
    assert np.allclose(slow.times, np.arange(21) / 10)
    assert np.allclose(slow.activations[2], animation.activations[1]) and np.allclose(slow.tmj[20], animation.tmj[10])
    assert np.allclose(slow.activations[1], 0.5 * (animation.activations[0] + animation.activations[1]))
    spliced = editing.splice([part, slow], transition=0.2)
    # part ends at 0.5 s; the seam is 0.2 s at part's 0.05 s spacing: 3 in-betweens, then slow from 0.7 s.
    assert np.allclose(spliced.times, np.concatenate([np.arange(11) / 20, 0.5 + np.array([0.05, 0.1, 0.15]),
                                                      0.7 + np.arange(21) / 10]))
    middle = spliced.activations[11 + 1]  # half way across the seam
    assert np.allclose(middle, 0.5 * (part.activations[-1] + slow.activations[0]))
    assert np.all(np.diff(spliced.times) > 0)
    joined = editing.splice([part, part])  # default seam: one frame
    assert np.allclose(joined.times, np.arange(22) / 20)
    with pytest.raises(AnimationError, match="within the animation's"):
        editing.segment(animation, 2.0, 4.0)
    with pytest.raises(AnimationError, match="speed"):
        editing.segment(animation, speed=0.0)


def test_keyframes_of_one_muscle_blend_in_and_out():
    animation = take(frames=61, rate=20.0)  # 0 .. 3 s
    t = animation.times
    edited = editing.with_keyframes(animation, "mentalis_left", [1.0, 1.5, 2.0], [0.9, 0.2, 0.9], blend=0.25,
                                    interpolation="linear")
    curve, original = edited.activation("mentalis_left"), animation.activation("mentalis_left")
    inside = (t >= 1.0) & (t <= 2.0)
    assert np.allclose(curve[inside], np.interp(t[inside], [1.0, 1.5, 2.0], [0.9, 0.2, 0.9]))
    outside = (t <= 0.75) | (t >= 2.25)
    assert np.array_equal(curve[outside], original[outside])
    ramp = (t > 0.75) & (t < 1.0)  # in between the original and the keys' value
    low, high = np.minimum(original[ramp], 0.9), np.maximum(original[ramp], 0.9)
    assert np.all((curve[ramp] >= low - 1e-12) & (curve[ramp] <= high + 1e-12))
    assert np.array_equal(edited.activation("frontalis_left"), animation.activation("frontalis_left"))
    added = editing.with_keyframes(animation, "risorius_left", [1.0], [0.6], blend=0.0)
    assert added.muscle_names[-1] == "risorius_left"
    assert np.array_equal(added.activation("risorius_left"), np.where(t == 1.0, 0.6, 0.0))
    with pytest.raises(AnimationError, match=r"\[0, 1\]"):
        editing.with_keyframes(animation, "mentalis_left", [1.0], [1.2])


@pytest.mark.parametrize("method", ["gaussian", "savgol"])
def test_smoothing_reduces_roughness_and_clamps(method):
    clean = take(frames=120, rate=60.0)
    noisy_values = np.clip(clean.activations + RNG.normal(0, 0.08, clean.activations.shape), 0, 1)
    noisy_tmj = np.clip(clean.tmj + RNG.normal(0, 0.01, clean.tmj.shape), 0, None)
    noisy = Animation(clean.times, clean.muscle_names, noisy_values, clean.cranium, None, None, noisy_tmj)
    smooth = editing.smoothed(noisy, 0.03, method)
    for k in range(2):
        before, after = (editing.roughness(a.activations[:, k], a.times) for a in (noisy, smooth))
        assert after < 0.2 * before, (before, after)
        # closer to the clean curve than the noisy one was (Savitzky-Golay's end windows extrapolate
        # the noise: it gains less than the Gaussian there)
        assert (np.abs(smooth.activations[:, k] - clean.activations[:, k]).mean()
                < 0.8 * np.abs(noisy.activations[:, k] - clean.activations[:, k]).mean())
    assert smooth.activations.min() >= 0 and smooth.activations.max() <= 1
    assert np.all(smooth.tmj >= noisy.tmj.min(axis=0)) and np.all(smooth.tmj <= noisy.tmj.max(axis=0))
    for frame in smooth.cranium:
        assert np.abs(frame.matrix @ frame.matrix.T - np.eye(3)).max() < 1e-12
    uneven = editing.segment(noisy, 0.0, 0.5)
    uneven = Animation(np.sqrt(uneven.times), uneven.muscle_names, uneven.activations, uneven.cranium, None,
                       None, uneven.tmj)
    if method == "savgol":
        with pytest.raises(AnimationError, match="evenly spaced"):
            editing.smoothed(uneven, 0.03, method)


@pytest.fixture(scope="module")
def fit_folder(builtin_model_path, shared_dir):
    model = ["--model", str(builtin_model_path)]
    capture = shared_dir / "take.trc"
    assert main(["synth", *model, "--frames", "3", "--noise", "0.2", "--out", str(capture)]) == 0
    assert main(["fit", str(capture), *model, "--out", str(shared_dir / "fit")]) == 0
    return shared_dir / "fit"


def test_edit_command_writes_what_simulate_plays(builtin_model_path, shared_dir, fit_folder):
    """Each operation of ``run.py edit`` on a fit (and expressions) writes an animation; the
    in-betweens of two expressions are simulated, each an equilibrium of the face."""
    model = ["--model", str(builtin_model_path)]
    out = shared_dir / "edits"
    fit = str(fit_folder)
    commands = {
        "between.csv": ["between", "expression:smile", "expression:jaw_open", "--frames", "3", "--duration", "0.2",
                        *model],
        "scaled.csv": ["scale", fit, "--factor", "1.5", "--about", f"{fit}#0"],
        "spliced.csv": ["splice", f"{fit}@0:0.02x0.5", str(out / "between.csv"), "--transition", "0.05"],
        "keyed.csv": ["keyframes", fit, "--muscle", "mentalis_left", "--keys", "0.01=0.7,0.03=0.2", "--blend", "0"],
        "smoothed.csv": ["smooth", fit, "--time-constant", "0.02"],
    }
    for name, command in commands.items():
        assert main(["edit", *command, "--out", str(out / name)]) == 0
        animation = Animation.read(out / name)
        assert animation.n_frames >= 3, name
    fitted = Animation.read(fit_folder)
    scaled = Animation.read(out / "scaled.csv")
    assert np.allclose(scaled.activations, np.clip(fitted.activations[0] + 1.5 * (fitted.activations
                                                                                   - fitted.activations[0]), 0, 1))
    keyed, original = Animation.read(out / "keyed.csv").activation("mentalis_left"), fitted.activation("mentalis_left")
    assert np.allclose(fitted.times, [0, 1 / 60, 2 / 60])  # frames 0 and 2 outside the keys, 1 between them
    assert keyed[0] == original[0] and keyed[2] == original[2]
    assert keyed[1] == pytest.approx(keyframe_curve([0.01, 0.03], [0.7, 0.2], [1 / 60], "smooth")[0])
    played = shared_dir / "played_between"
    assert main(["simulate", *model, "--animation", str(out / "between.csv"), "--out", str(played)]) == 0
    moved = [np.abs(np.load(played / "frames" / f"{k:06d}.displacement.npy")).max() for k in range(3)]
    assert min(moved) > 0.5
    with pytest.raises(SystemExit, match="already exists"):
        main(["edit", *commands["scaled.csv"], "--out", str(out / "scaled.csv")])


@pytest.mark.parametrize("command, message", [
    (["between", "expression:smile", "expression:frown"], "needs the model"),
    (["scale", "FIT", "--factor", "2", "--about", "FIT#7"], "frame 7 of the 3 frames"),
    (["splice", "FIT@0.1"], "give PATH@START:STOP"),
    (["keyframes", "FIT", "--muscle", "mentalis_left", "--keys", "0.1:0.5"], "give TIME=ACTIVATION pairs"),
    (["smooth", "FIT", "--time-constant", "0"], "must be positive"),
])
def test_edit_command_bad_input(shared_dir, fit_folder, command, message):
    out = shared_dir / "never.csv"
    command = [str(fit_folder) + part[3:] if part.startswith("FIT") else part for part in command]
    with pytest.raises(SystemExit, match=message):
        main(["edit", *command, "--out", str(out)])
    assert not pathlib.Path(out).exists()
    MPI.COMM_WORLD.barrier()
