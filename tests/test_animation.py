"""Animations as input: the CSV and TOML forms, a fit played back through ``simulate --animation``
(the same frames again), resume, the strength override, and each bad input's one message."""
import json
import pathlib

import numpy as np
import pytest
from mpi4py import MPI

from face_dolfinx.animation import Animation, AnimationError, keyframe_curve
from face_dolfinx.cli.main import main
from face_dolfinx.model.bones import AffineMap, jaw_pose, rotation, tmj_upper_limits
from killed_run import kill_after_frame

NEWTON_TOLERANCE = 1e-8  # mm, the default step tolerance of fit and simulate


def write_on_rank_0(path: pathlib.Path, text: str) -> pathlib.Path:
    """``text`` in ``path``, once every rank is done with whatever was there before."""
    MPI.COMM_WORLD.barrier()
    if MPI.COMM_WORLD.rank == 0:
        path.write_text(text)
    MPI.COMM_WORLD.barrier()
    return path


@pytest.fixture(scope="module")
def fitted(builtin_model_path, shared_dir):
    """A 4-frame synthetic take (0.2 mm noise, head motion), its fit, and the fit played back."""
    model = ["--model", str(builtin_model_path)]
    take = shared_dir / "take.trc"
    assert main(["synth", *model, "--frames", "4", "--noise", "0.2", "--out", str(take)]) == 0
    assert main(["fit", str(take), *model, "--out", str(shared_dir / "fit")]) == 0
    assert main(["simulate", *model, "--animation", str(shared_dir / "fit"), "--out", str(shared_dir / "played")]) == 0
    return model, shared_dir / "fit", shared_dir / "played"


def frame_record(folder: pathlib.Path, frame: int) -> dict:
    return json.loads((folder / "frames" / f"{frame:06d}.json").read_text())


def test_a_played_back_fit_reproduces_its_frames(fitted):
    """Fit folder -> Animation -> simulate: every frame's equilibrium is the fit's to Newton
    tolerance, at the mesh nodes and at the markers, with the same marker errors; the tables of
    controls are the same bytes."""
    _, fit, played = fitted
    for frame in range(4):
        fitted_u, played_u = (np.load(folder / "frames" / f"{frame:06d}.displacement.npy") for folder in (fit, played))
        assert np.abs(fitted_u).max() > 1.0  # the face moved
        assert np.abs(played_u - fitted_u).max() < 10 * NEWTON_TOLERANCE
        a, b = frame_record(fit, frame), frame_record(played, frame)
        assert np.abs(np.array(a["simulated_markers"]) - np.array(b["simulated_markers"])).max() < 10 * NEWTON_TOLERANCE
        assert np.array_equal(np.array(a["captured_markers"], dtype=float), np.array(b["captured_markers"], dtype=float))
        assert b["rms_error"] == pytest.approx(a["rms_error"], abs=10 * NEWTON_TOLERANCE)
    for table in ("activations.csv", "kinematics.csv"):
        assert (fit / table).read_bytes() == (played / table).read_bytes(), table
    for name in ("activations.png", "kinematics.png", "marker_error.png", "face.xdmf", "animation.csv"):
        assert (played / name).is_file(), name
    assert not (played / "IN_PROGRESS").exists()
    # The folder played is an animation too, and the same one.
    again, original = Animation.read(played), Animation.read(fit)
    assert np.array_equal(again.activations, original.activations) and np.array_equal(again.tmj, original.tmj)
    assert Animation.read(played / "animation.csv").csv_text() == original.csv_text()


def test_video_of_a_playback(fitted, shared_dir):
    _, _, played = fitted
    gif = shared_dir / "played.gif"
    assert main(["video", str(played), "--out", str(gif), "--gif"]) == 0
    if MPI.COMM_WORLD.rank == 0:
        import imageio.v2 as imageio
        assert len(imageio.mimread(gif)) == 4


def test_resume_after_stop_gives_the_same_bytes(fitted, shared_dir):
    """Stopped after 2 frames and rerun: frames and tables are the bytes of the uninterrupted
    playback (under MPI, where the parallel factorisation varies at round-off from run to run,
    the same to far below Newton tolerance)."""
    model, fit, played = fitted
    out = shared_dir / "resumed"
    assert main(["simulate", *model, "--animation", str(fit), "--out", str(out), "--stop-after", "2"]) == 0
    assert (out / "IN_PROGRESS").exists() and not (out / "activations.csv").exists()
    assert sorted(p.name for p in (out / "frames").glob("*.json")) == ["000000.json", "000001.json"]
    assert main(["simulate", *model, "--animation", str(fit), "--out", str(out)]) == 0
    assert not (out / "IN_PROGRESS").exists()
    for frame in range(4):
        name = f"frames/{frame:06d}.displacement.npy"
        if MPI.COMM_WORLD.size == 1:
            assert (out / name).read_bytes() == (played / name).read_bytes(), name
        else:
            assert np.abs(np.load(out / name) - np.load(played / name)).max() < 1e-3 * NEWTON_TOLERANCE
    names = ["activations.csv", "kinematics.csv"] + (["marker_errors.csv", "frames.csv"] if MPI.COMM_WORLD.size == 1
                                                     else [])
    for name in names:
        assert (out / name).read_bytes() == (played / name).read_bytes(), name
    # Another animation in the same folder is refused, naming what differs.
    other = write_on_rank_0(shared_dir / "other.toml", "frame_rate = 2\n[muscles.mentalis_left]\n"
                                                       "times = [0, 1]\nvalues = [0, 0.5]\n")
    with pytest.raises(SystemExit, match="animation"):
        main(["simulate", *model, "--animation", str(other), "--out", str(out)])


def test_csv_form_reads_back_exactly_and_hand_written_columns(tmp_path):
    turn = AffineMap(rotation([0.2, 1.0, 0.1], 0.3), [1.0, -2.0, 0.5])
    animation = Animation([0.0, 0.1, 0.25], ["mentalis_left", "risorius_right"],
                          [[0.0, 0.3], [1.0 / 3.0, 1.0], [0.7, 0.0]], [AffineMap(), turn, turn],
                          [AffineMap(), AffineMap(), turn], [0.0, 0.1, -0.2], [[0, 0, 0], [0.1, 1, 2], [0.2, 0, 0]])
    path = animation.write(tmp_path / "a.csv")
    back = Animation.read(path)
    assert back.csv_text() == animation.csv_text()
    assert back.muscle_names == animation.muscle_names and np.array_equal(back.activations, animation.activations)
    assert all(a.same_as(b) for a, b in zip(back.cranium, animation.cranium))
    assert all(a.same_as(b) for a, b in zip(back.jaw, animation.jaw))
    assert np.array_equal(back.pressure, animation.pressure) and np.array_equal(back.tmj, animation.tmj)
    # Head as a rotation vector (degrees) and translation, jaw opening in degrees, a comment line.
    (tmp_path / "h.csv").write_text("# a nod\ntime_s,frontalis_left,head_rx_deg,head_ry_deg,head_rz_deg,head_ty_mm,"
                                    "jaw_opening_deg\n0,0,0,0,0,0,0\n0.5,0.5,10,0,0,2,6\n")
    hand = Animation.read(tmp_path / "h.csv")
    assert np.allclose(hand.cranium[1].matrix, rotation([1, 0, 0], np.radians(10)), atol=1e-15)
    assert np.array_equal(hand.cranium[1].translation, [0, 2, 0])
    assert hand.jaw is None and hand.tmj[1] == pytest.approx([np.radians(6), 0, 0])


def test_toml_keyframes(tmp_path):
    (tmp_path / "k.toml").write_text("""
frame_rate = 10
duration = 1.2
[muscles.zygomaticus_major_left]
times = [0.2, 0.6, 1.0]
values = [0.0, 0.9, 0.3]
[jaw]
times = [0.0, 1.0]
opening_deg = [0.0, 10.0]
slide_left_mm = [0.0, 1.0]
[head]
times = [0.0, 1.0]
rotation_deg = [[0, 0, 0], [0, 30, 0]]
translation_mm = [[0, 0, 0], [4, 0, 0]]
""")
    animation = Animation.read(tmp_path / "k.toml")
    assert np.allclose(animation.times, np.arange(13) / 10)
    curve = animation.activation("zygomaticus_major_left")
    assert curve[[0, 1, 2]] == pytest.approx([0, 0, 0]) and curve[6] == pytest.approx(0.9)
    assert curve[4] == pytest.approx(0.45) and curve[12] == pytest.approx(0.3)  # held after the last key
    assert np.array_equal(animation.activation("mentalis_left"), np.zeros(13))  # unspecified: 0
    assert animation.tmj[5] == pytest.approx([np.radians(5), 0, 0.5])
    half = animation.cranium[5]
    assert np.allclose(half.matrix, rotation([0, 1, 0], np.radians(15)), atol=1e-12)  # on SO(3)
    assert np.allclose(half.translation, [2, 0, 0], atol=1e-12)
    # Smooth: eased in and out of every key, still between the keys' values.
    smooth = keyframe_curve([0.0, 1.0], [0.0, 1.0], np.linspace(0, 1, 101), "smooth")
    assert smooth[50] == pytest.approx(0.5) and smooth[1] < 0.01 and smooth.min() >= 0 and smooth.max() <= 1
    assert np.all(np.diff(smooth) >= 0)


def test_controls_at_maps_muscles_by_name_and_moves_on_proper_spaces(model, tmp_path):
    names = model.muscle_names
    upper = tmj_upper_limits(model.jaw)
    turn = AffineMap(rotation([0, 0, 1], 0.8), [0, 3, 0])
    animation = Animation([0.0, 2.0], [names[5], names[0]], [[0.2, 1.0], [0.6, 0.0]], [AffineMap(), turn], None,
                          None, [[0, 0, 0], upper])
    controls = animation.controls_at(0.5, model)
    assert controls.activations[5] == pytest.approx(0.3) and controls.activations[0] == pytest.approx(0.75)
    assert np.count_nonzero(controls.activations) == 2
    assert np.allclose(controls.cranium.matrix, rotation([0, 0, 1], 0.2), atol=1e-12)
    assert controls.jaw.same_as(jaw_pose(model.jaw, *(0.25 * upper)))
    exact = animation.frame_controls(1, model)
    assert exact.cranium.same_as(turn) and exact.activations[0] == 0.0
    with pytest.raises(AnimationError, match="outside the animation's span"):
        animation.controls_at(2.5, model)


def test_strength_applies_to_an_animation(builtin_model_path, shared_dir):
    """--strength scales the force-length curve of a played animation: one muscle at twice its
    peak stress moves the face more than at its own, and run.json records it."""
    model = ["--model", str(builtin_model_path)]
    animation = write_on_rank_0(shared_dir / "smile.csv", "time_s,zygomaticus_major_left\n0,0\n0.1,0.5\n")
    plain, strong = shared_dir / "plain", shared_dir / "strong"
    assert main(["simulate", *model, "--animation", str(animation), "--out", str(plain)]) == 0
    assert main(["simulate", *model, "--animation", str(animation), "--out", str(strong),
                 "--strength", "zygomaticus_major_left=2"]) == 0
    assert json.loads((strong / "run.json").read_text())["strength"] == {"zygomaticus_major_left": 2.0}
    moved = [np.abs(np.load(folder / "frames" / "000001.displacement.npy")).max() for folder in (plain, strong)]
    assert moved[0] > 0.5 and moved[1] > 1.2 * moved[0]


BAD_CSV = [
    ("time_s,mentalis_left,nose_wiggler\n0,0,0\n", "unknown to the model.*nose_wiggler.*the model's muscles: frontalis_left"),
    ("time_s,mentalis_left\n0,0\n0.1,1.5\n", r"bad\d\.csv:3: activation of mentalis_left is 1.5, outside \[0, 1\]"),
    ("time_s,mentalis_left\n0,0\n0.2,0.1\n0.2,0.2\n", r"bad\d\.csv:4: time 0.2 s is not after the previous row's 0.2 s"),
    ("time_s,mentalis_left\n0,0\n0.1,abc\n", r"bad\d\.csv:3: column mentalis_left: 'abc' is not a number"),
    ("time_s,mentalis_left\n0,0\n0.1\n", r"bad\d\.csv:3: 1 fields, the header \(line 1\) has 2"),
    ("mentalis_left\n0\n", r"bad\d\.csv:1: no time_s column"),
    ("time_s,cranium_M00\n0,1\n", "the cranium needs all of its columns"),
    ("time_s,mentalis_left,\n0,0,0\n", r"bad\d\.csv:1: column 3 has no name"),
]


BAD_TOML = [
    ("frame_rate = 10\n[muscles.mentalis_left]\ntimes = [0, 1]\nvalues = [0, 2]\n",
     r"\[muscles.mentalis_left\].values: activation 2 is outside \[0, 1\]"),
    ("frame_rate = 10\n[muscles.mentalis_left]\ntimes = [0, 1, 0.5]\nvalues = [0, 1, 0]\n",
     r"\[muscles.mentalis_left\].times must increase: 0.5 s follows 1 s"),
    ("frame_rate = 10\n[muscles.mentalis_left]\ntimes = [0, 1]\nvalues = [0]\n", "must be a list of 2 values"),
    ("[muscles.mentalis_left]\ntimes = [0, 1]\nvalues = [0, 1]\n", "no frame_rate"),
    ("frame_rate = 10\nspeed = 2\n", "unknown key"),
    ("frame_rate = 10\n[jaw]\ntimes = [0, 1]\nopening_deg = [0, 80]\n", "outside the model's TMJ bounds"),
    ("frame_rate = [\n", "cannot be read as TOML"),
]


BAD_FILES = [(".csv", index, text, message) for index, (text, message) in enumerate(BAD_CSV)] + \
    [(".toml", index, text, message) for index, (text, message) in enumerate(BAD_TOML)]


@pytest.mark.parametrize("suffix, index, text, message", BAD_FILES)
def test_bad_animation_files_get_one_message_and_leave_nothing(builtin_model_path, shared_dir, suffix, index, text,
                                                               message):
    path = write_on_rank_0(shared_dir / f"bad{index}{suffix}", text)
    out = shared_dir / "never"
    with pytest.raises(SystemExit, match=message):
        main(["simulate", "--model", str(builtin_model_path), "--animation", str(path), "--out", str(out)])
    assert not out.exists()


def test_what_is_not_an_animation(builtin_model_path, shared_dir):
    model = ["--model", str(builtin_model_path)]
    with pytest.raises(SystemExit, match="no such animation file"):
        main(["simulate", *model, "--animation", str(shared_dir / "missing.csv"), "--out", str(shared_dir / "x")])
    with pytest.raises(SystemExit, match="not a fit results folder"):
        main(["simulate", *model, "--animation", str(shared_dir), "--out", str(shared_dir / "x")])
    with pytest.raises(SystemExit, match="--animation plays the animation alone"):
        main(["simulate", "smile", *model, "--animation", str(shared_dir / "smile.csv"), "--out", str(shared_dir / "x")])


def test_the_example_animation_fits_the_built_in_face(model):
    example = Animation.read(pathlib.Path(__file__).resolve().parents[1] / "examples" / "smile_and_nod.toml")
    example.check(model)
    assert example.n_frames == 31 and example.times[-1] == pytest.approx(2.0)
    assert np.array_equal(example.activation("zygomaticus_major_left"),
                          keyframe_curve([0.2, 0.9, 1.6], [0.0, 0.7, 0.1], example.times, "smooth"))
    assert np.all(example.activation("mentalis_left") == 0)


@pytest.mark.skipif(MPI.COMM_WORLD.size > 1, reason="kills a serial subprocess")
def test_resume_after_kill_9_gives_the_same_bytes(builtin_model_path, tmp_path):
    """A playback killed after its second frame and rerun: the same frames and tables as an
    uninterrupted one."""
    model = ["--model", str(builtin_model_path)]
    animation = tmp_path / "keys.toml"
    animation.write_text("frame_rate = 10\n[muscles.zygomaticus_major_left]\ntimes = [0, 1.1]\nvalues = [0, 0.9]\n"
                         "[jaw]\ntimes = [0, 1.1]\nopening_deg = [0, 10]\n")
    whole, killed = tmp_path / "whole", tmp_path / "killed"
    assert main(["simulate", *model, "--animation", str(animation), "--out", str(whole)]) == 0
    kill_after_frame(["simulate", *model, "--animation", str(animation), "--out", str(killed)], killed, 1)
    assert (killed / "IN_PROGRESS").exists() and not (killed / "frames" / "000011.json").exists()
    assert main(["simulate", *model, "--animation", str(animation), "--out", str(killed)]) == 0
    names = [f"frames/{f:06d}.displacement.npy" for f in range(12)] + ["activations.csv", "kinematics.csv", "frames.csv"]
    assert [name for name in names if (whole / name).read_bytes() != (killed / name).read_bytes()] == []


def test_modified_newton_plays_the_same_frames(fitted, shared_dir):
    """--reuse-factorization with a 1e-4 mm Newton tolerance: the frames of the default playback
    to within that tolerance (measured on the 5K face: 1e-6 mm)."""
    model, fit, played = fitted
    out = shared_dir / "reused"
    assert main(["simulate", *model, "--animation", str(fit), "--out", str(out), "--reuse-factorization",
                 "--newton-tolerance", "1e-4"]) == 0
    assert json.loads((out / "run.json").read_text())["reuse_factorization"] is True
    for frame in range(4):
        name = f"frames/{frame:06d}.displacement.npy"
        assert np.abs(np.load(out / name) - np.load(played / name)).max() < 1e-4


def test_pressure_on_a_model_without_an_oral_surface(model, shared_dir):
    """An animation that presses the mouth, played on a model with no 'oral' surface: one message
    naming the file, before the results folder exists."""
    import dataclasses
    from face_dolfinx.cli.main import parse_arguments, simulate_animation
    path = write_on_rank_0(shared_dir / "puff.csv", "time_s,buccinator_left,intraoral_pressure_kpa\n0,0,0\n0.1,0.2,0.4\n")
    out = shared_dir / "never_puffed"
    args, _ = parse_arguments(["simulate", "--animation", str(path), "--out", str(out)])
    without_oral = dataclasses.replace(model, boundary_ids={k: v for k, v in model.boundary_ids.items() if k != "oral"})
    with pytest.raises(SystemExit, match=r"puff\.csv: .*no facets tagged 'oral'"):
        simulate_animation(without_oral, args)
    assert not out.exists()


def test_an_animation_played_with_contact(model, builtin_model_path, shared_dir):
    """simulate --animation --contact: the orbicularis oris at 1 presses the lips together, which
    pass through each other when played without contact and stay apart with it, on the teeth, in
    quasistatic and dynamic playback; run.json records the contact."""
    from face_dolfinx.physics.problem import FaceProblem
    from face_dolfinx.physics.self_contact import LipContact, LipContactSettings, lip_facets
    from face_dolfinx.results.xdmf import FileNodeOrder
    sphincter = [m.name for m in model.muscles if m.name.startswith("orbicularis_oris")]
    path = write_on_rank_0(shared_dir / "press.csv", "time_s," + ",".join(sphincter) + "\n"
                           + "0" + ",0" * len(sphincter) + "\n" + "0.05" + ",1" * len(sphincter) + "\n")
    model_option = ["--model", str(builtin_model_path)]
    runs = {name: shared_dir / f"pressed_{name}" for name in ("plain", "contact", "dynamic")}
    assert main(["simulate", *model_option, "--animation", str(path), "--out", str(runs["plain"])]) == 0
    assert main(["simulate", *model_option, "--animation", str(path), "--out", str(runs["contact"]), "--contact"]) == 0
    assert main(["simulate", *model_option, "--animation", str(path), "--out", str(runs["dynamic"]), "--contact",
                 "--dynamic", "--time-step", "0.025"]) == 0
    problem = FaceProblem(model)
    lips = LipContact(problem.V, *lip_facets(model, LipContactSettings()), LipContactSettings(), problem.bone_blocks)
    node_order = FileNodeOrder(problem.V)
    penetration = {}
    for name, out in runs.items():
        record = json.loads((out / "run.json").read_text())
        assert record["contact"] is (name != "plain")
        assert record["contact_surfaces"] == ([] if name == "plain" else ["lips", "teeth"])
        stored = np.load(out / "frames" / "000001.displacement.npy") if MPI.COMM_WORLD.rank == 0 else None
        displacement = node_order.scatter(MPI.COMM_WORLD.bcast(stored, root=0))
        penetration[name] = lips.penetration(displacement)
        if name != "plain":
            assert lips.min_distance(displacement) > 0.0
    assert penetration["plain"] > 1.0 and penetration["contact"] == penetration["dynamic"] == 0.0  # mm
    with pytest.raises(SystemExit, match="contact: False there, True now"):
        main(["simulate", *model_option, "--animation", str(path), "--out", str(runs["plain"]), "--contact"])
