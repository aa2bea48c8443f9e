"""The command line: results appear whole or not at all, and earlier results are not overwritten."""
import json
import pathlib

import matplotlib.image as mpimg
from mpi4py import MPI
import numpy as np
import pytest

from face_dolfinx.cli.main import main
from killed_run import kill_after_frame

RED, GREEN = (1.0, 0.0, 0.0), (0.196, 0.804, 0.196)  # render markers: captured, simulated (limegreen)
LINE_COLOURS = [(0.122, 0.467, 0.706), (1.0, 0.498, 0.055), (0.173, 0.627, 0.173)]  # matplotlib C0-C2


def picture(path, width):
    """A PNG decoded to RGB in [0, 1], checked to be ``width`` pixels wide and not blank."""
    image = mpimg.imread(path)[:, :, :3]
    assert image.shape[1] == width and image.shape[0] > 100, path.name
    drawn = image.mean(axis=2) < 0.95  # not the white background
    assert drawn.mean() > 0.01, f"{path.name} is blank"
    return image


def pixels_of(image, colour, tolerance=0.06):
    """How many pixels have ``colour`` (each channel within ``tolerance``)."""
    return int(np.all(np.abs(image - colour) <= tolerance, axis=2).sum())


def check_face_render(path, marker_colours=()):
    """A shaded face fills a good part of the picture; markers of each colour are drawn."""
    image = picture(path, width=750)  # render_skin's 5 in at 150 dpi
    grey = image.mean(axis=2)
    covered = grey < 0.95
    assert 0.15 < covered.mean() < 0.95, path.name
    assert grey[covered].std() > 0.05, f"{path.name}: a flat silhouette, not a shaded face"
    for colour in marker_colours:
        assert pixels_of(image, colour, tolerance=0.2) > 20, f"{path.name}: no {colour} markers"


@pytest.fixture
def shared_tmp(tmp_path):
    """One temporary folder for all ranks (each rank's tmp_path differs under mpirun)."""
    return pathlib.Path(MPI.COMM_WORLD.bcast(str(tmp_path), root=0))


def test_simulate_writes_a_complete_result(builtin_model_path, shared_tmp):
    out = shared_tmp / "smile"
    assert main(["simulate", "smile", "--model", str(builtin_model_path), "--out", str(out)]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert [row["expression"] for row in summary["expressions"]] == ["smile"]
    assert summary["expressions"][0]["max_displacement_mm"] > 1.0
    assert (out / "face.xdmf").exists() and (out / "face.h5").exists()
    check_face_render(out / "01_smile.png")
    # A second run must not silently replace the first.
    with pytest.raises(FileExistsError, match="--overwrite"):
        main(["simulate", "frown", "--model", str(builtin_model_path), "--out", str(out)])
    assert main(["simulate", "frown", "--model", str(builtin_model_path), "--out", str(out),
                 "--overwrite", "--no-render"]) == 0
    assert json.loads((out / "summary.json").read_text())["expressions"][0]["expression"] == "frown"


def test_simulate_from_a_coarse_model(builtin_model_path, shared_tmp):
    """The plumbing of --coarse: with the model as its own coarse model the start of the jaw
    opening is the equilibrium itself, so the fine Newton has (almost) nothing left to do."""
    out = shared_tmp / "coarse"
    assert main(["simulate", "jaw_open", "--model", str(builtin_model_path), "--coarse",
                 str(builtin_model_path), "--out", str(out), "--no-render"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["coarse_model"] == str(builtin_model_path)
    assert summary["expressions"][0]["newton_iterations"] <= 1
    assert summary["expressions"][0]["max_displacement_mm"] > 1.0
    with pytest.raises(SystemExit, match="--coarse TETS builds the built-in face"):
        main(["simulate", "smile", "--model", str(builtin_model_path), "--coarse", "5000",
              "--out", str(shared_tmp / "never"), "--no-render"])


def test_failed_run_leaves_nothing_that_looks_like_a_result(builtin_model_path, shared_tmp):
    out = shared_tmp / "broken"
    with pytest.raises(SystemExit, match="unknown expression 'grin'"):
        main(["simulate", "smile", "grin", "--model", str(builtin_model_path), "--out", str(out),
              "--no-render"])
    MPI.COMM_WORLD.barrier()
    assert not out.exists()
    assert not [p for p in shared_tmp.iterdir() if p.name.startswith(".broken")]


TABLES = ["activations.csv", "kinematics.csv", "marker_errors.csv", "frames.csv"]
REPORT = ["activations.png", "kinematics.png", "marker_error.png", "face.xdmf", "face.h5"]


@pytest.fixture(scope="module")
def fitted_take(builtin_model_path, tmp_path_factory):
    """A 4-frame synthetic take (0.2 mm noise) and its uninterrupted fit."""
    folder = pathlib.Path(MPI.COMM_WORLD.bcast(str(tmp_path_factory.mktemp("take")), root=0))
    model = ["--model", str(builtin_model_path)]
    take = folder / "take.trc"
    assert main(["synth", *model, "--frames", "4", "--noise", "0.2", "--out", str(take)]) == 0
    assert main(["fit", str(take), *model, "--out", str(folder / "fit")]) == 0
    return take, model, folder / "fit"


def _same_files(first: pathlib.Path, second: pathlib.Path) -> list[str]:
    """The tables and report files that differ in content between two fit folders."""
    names = TABLES + REPORT + [p.relative_to(first).as_posix() for p in sorted((first / "renders").glob("*.png"))]
    return [name for name in names if (first / name).read_bytes() != (second / name).read_bytes()]


def test_fit_writes_tables_report_and_log(fitted_take):
    import h5py
    take, _, out = fitted_take
    assert take.with_name("take.truth.npz").exists()
    rows = (out / "frames.csv").read_text().splitlines()
    assert len(rows) == 5 and "activation_error_max" in rows[0]
    assert max(float(row.split(",")[1]) for row in rows[1:]) < 0.2 * 1.1  # marker RMS vs noise
    assert len((out / "timings.csv").read_text().splitlines()) == 5
    # The charts (8 in at 120 dpi) draw their curves: fitted and true activations and TMJ in
    # C0 (and more), the marker error in C0, the noise in C1 and the fit's error to truth in C2.
    for name, colours in (("activations.png", LINE_COLOURS), ("kinematics.png", LINE_COLOURS),
                          ("marker_error.png", LINE_COLOURS)):
        image = picture(out / name, width=960)
        for colour in colours:
            assert pixels_of(image, colour) > 100, f"{name}: no curve in {colour}"
    assert sorted(p.name for p in (out / "renders").iterdir()) == [f"frame_{f:06d}.png" for f in range(4)]
    for render in sorted((out / "renders").iterdir()):
        check_face_render(render, marker_colours=(RED, GREEN))
    with h5py.File(out / "face.h5") as h5:
        steps = sorted(h5.keys() - {"mesh"})
        assert len(steps) == 4
        nodes = h5["mesh/geometry"].shape[0]
        assert h5[f"{steps[2]}/displacement"].shape == (nodes, 3)
        assert abs(h5[f"{steps[2]}/displacement"][:]).max() > 1.0  # head motion and expression
        assert sum(name.startswith("activation_") for name in h5[steps[2]]) == 32
    assert (out / "face.xdmf").read_text().count("<Time Value=") == 4
    log = (out / "run.log").read_text()
    assert "frame 4/4: marker RMS" in log and "report of" in log
    assert not (out / "IN_PROGRESS").exists() and not (out / "checkpoint").exists()


def test_resume_after_stop_is_bit_identical(fitted_take, shared_tmp, capsys):
    """Stopped after 2 frames, then rerun: every table, plot, render and the XDMF series are the
    bytes of the uninterrupted fit (only timings.csv differs).

    Under MPI even two uninterrupted fits in one process (same, reproducible partition) differ
    at round-off (measured; the parallel MUMPS factorisation is the suspect). There the resumed
    tables must agree with the uninterrupted ones to 1e-7, far closer than re-solving from the last frame's controls came (2e-3 in activations)."""
    take, model, uninterrupted = fitted_take
    out = shared_tmp / "resumed"
    assert main(["fit", str(take), *model, "--out", str(out), "--stop-after", "2"]) == 0
    assert (out / "IN_PROGRESS").exists() and not (out / "activations.csv").exists()
    assert sorted(p.name for p in (out / "frames").glob("*.json")) == ["000000.json", "000001.json"]
    assert [p.name for p in (out / "checkpoint").iterdir()] == ["000001.npz"]  # only the latest

    capsys.readouterr()
    assert main(["report", str(out)]) == 0  # a partial report says what is missing
    if MPI.COMM_WORLD.rank == 0:
        assert "2 of 4 frames are not fitted yet (2-3)" in capsys.readouterr().out
        assert len(list((out / "renders").iterdir())) == 2

    assert main(["fit", str(take), *model, "--out", str(out)]) == 0
    assert not (out / "IN_PROGRESS").exists()
    if MPI.COMM_WORLD.size == 1:
        assert _same_files(uninterrupted, out) == []
    else:
        for name in TABLES[:3]:
            resumed, reference = (np.genfromtxt(folder / name, delimiter=",", skip_header=1)
                                  for folder in (out, uninterrupted))
            assert resumed.shape == reference.shape == (4, resumed.shape[1])
            assert np.nanmax(np.abs(resumed - reference)) < 1e-7, name
    assert (uninterrupted / "timings.csv").read_text() != (out / "timings.csv").read_text()


@pytest.mark.skipif(MPI.COMM_WORLD.size > 1, reason="kills a serial subprocess")
def test_resume_after_kill_9_is_bit_identical(fitted_take, tmp_path):
    take, model, uninterrupted = fitted_take
    out = tmp_path / "killed"
    kill_after_frame(["fit", str(take), *model, "--out", str(out)], out, 1)
    assert (out / "IN_PROGRESS").exists() and not (out / "frames" / "000003.json").exists()
    assert main(["fit", str(take), *model, "--out", str(out)]) == 0
    assert _same_files(uninterrupted, out) == []


def test_rerun_of_a_finished_fit_and_other_settings(fitted_take, shared_tmp, capsys):
    """The same command on a finished folder says so and changes nothing; other settings are
    refused, naming them; a folder that is no fit result is never replaced."""
    take, model, out = fitted_take
    before = {name: (out / name).stat().st_mtime_ns for name in TABLES + REPORT}
    capsys.readouterr()
    assert main(["fit", str(take), *model, "--out", str(out)]) == 0
    if MPI.COMM_WORLD.rank == 0:
        assert "already holds this fit, finished: nothing to do" in capsys.readouterr().out
    assert {name: (out / name).stat().st_mtime_ns for name in before} == before
    with pytest.raises(SystemExit, match="finished fit with other settings \\(gn_steps: 3 there, 5 now\\)"):
        main(["fit", str(take), *model, "--out", str(out), "--gn-steps", "5"])
    other = shared_tmp / "notes"
    if MPI.COMM_WORLD.rank == 0:
        other.mkdir()
        (other / "mine.txt").write_text("not a fit")
    MPI.COMM_WORLD.barrier()
    with pytest.raises(SystemExit, match="not a fit results folder"):
        main(["fit", str(take), *model, "--out", str(other), "--overwrite"])
    assert (other / "mine.txt").read_text() == "not a fit"


def test_reuse_and_a_looser_newton_tolerance_fit_the_same_take(fitted_take, shared_tmp):
    """--reuse-factorization --newton-tolerance 1e-4 (mm) fits every frame as the default does
    (here to 1e-9 mm in the marker RMS); a tolerance that is no distance is refused before any
    folder exists. (--fresh-jacobians 1, the third part of the fast setting, is not: on this take,
    which crosses a whole expression in 4 frames, it left frame 2 at 0.27 mm against 0.17 mm;
    docs/performance.md.)"""
    take, model, default = fitted_take
    fast = shared_tmp / "fast"
    assert main(["fit", str(take), *model, "--out", str(fast), "--reuse-factorization",
                 "--newton-tolerance", "1e-4"]) == 0
    rms = [np.loadtxt(folder / "frames.csv", delimiter=",", skiprows=1, usecols=1) for folder in (default, fast)]
    assert np.abs(rms[1] - rms[0]).max() < 1e-3  # mm
    assert json.loads((fast / "run.json").read_text())["newton_tolerance"] == 1e-4
    with pytest.raises(SystemExit, match="--newton-tolerance 0.0: give a positive distance"):
        main(["fit", str(take), *model, "--out", str(shared_tmp / "never"), "--newton-tolerance", "0"])
    with pytest.raises(SystemExit, match="--line-search-iterations 0: give 1 or more"):
        main(["fit", str(take), *model, "--out", str(shared_tmp / "never"), "--line-search-iterations", "0"])
    assert not (shared_tmp / "never").exists()


def test_report_help(capsys):
    with pytest.raises(SystemExit) as stop:
        main(["report", "--help"])
    assert stop.value.code == 0
    assert "missing" in capsys.readouterr().out


def test_chunks_in_ranks_or_separate_processes(builtin_model_path, shared_tmp):
    """A take split into 2 chunks (each starting from rest) gives every frame; under mpirun -n 2
    the ranks fit one chunk each; run chunk by chunk, the second call completes the tables."""
    take = shared_tmp / "take.trc"
    model = ["--model", str(builtin_model_path)]
    assert main(["synth", *model, "--frames", "4", "--noise", "0.0", "--out", str(take)]) == 0
    together = shared_tmp / "chunks"
    assert main(["fit", str(take), *model, "--chunks", "2", "--gn-steps", "6", "--out", str(together)]) == 0
    frames = np.loadtxt(together / "frames.csv", delimiter=",", skiprows=1, usecols=(0, 1, 5))
    assert list(frames[:, 0]) == [0, 1, 2, 3]
    assert frames[:, 1].max() < 0.05  # marker RMS (mm), noise-free take
    assert frames[:, 2].max() < 0.02  # activation error against the truth

    apart = shared_tmp / "apart"
    assert main(["fit", str(take), *model, "--chunks", "2", "--chunk", "1", "--out", str(apart)]) == 0
    assert (apart / "IN_PROGRESS").exists() and not (apart / "frames.csv").exists()
    assert main(["fit", str(take), *model, "--chunks", "2", "--chunk", "0", "--out", str(apart)]) == 0
    assert (apart / "frames.csv").exists() and not (apart / "IN_PROGRESS").exists()


def test_synth_writes_a_stretch_of_a_longer_take(builtin_model_path, shared_tmp):
    """--take-frames/--first-frame: the frames of a long take at its own spacing, so a short
    take moves at capture speed; a stretch past the take's end is refused."""
    from face_dolfinx.model.folder import load_model
    from face_dolfinx.capture.synthetic import control_curves, load_truth
    model = ["--model", str(builtin_model_path)]
    take = shared_tmp / "stretch.trc"
    assert main(["synth", *model, "--scenario", "smile", "--frames", "2", "--take-frames", "240",
                 "--first-frame", "114", "--noise", "0.0", "--out", str(take)]) == 0
    truth = load_truth(take.with_name("stretch.truth.npz"))
    activations, tmj, _ = control_curves(load_model(builtin_model_path, MPI.COMM_WORLD), "smile", 240)
    assert np.array_equal(truth.activations, activations[114:116])
    assert np.array_equal(truth.tmj, tmj[114:116])
    assert np.abs(truth.activations[1] - truth.activations[0]).max() < 0.05  # 1/60 s apart
    with pytest.raises(SystemExit, match="runs past the 240-frame take"):
        main(["synth", *model, "--frames", "2", "--take-frames", "240", "--first-frame", "239",
              "--out", str(shared_tmp / "never.trc")])


def test_video_of_a_fit_folder(fitted_take, shared_tmp):
    """The whole take at its own rate, every frame the shaded face with both marker sets; a GIF on
    request; a folder that is no fit folder gets one clear message."""
    imageio = pytest.importorskip("imageio.v2")
    _, _, out = fitted_take
    mp4, gif = shared_tmp / "take.mp4", shared_tmp / "take.gif"
    assert main(["video", str(out), "--out", str(mp4)]) == 0
    assert main(["video", str(out), "--out", str(gif), "--gif", "--step", "2"]) == 0
    if MPI.COMM_WORLD.rank == 0:
        reader = imageio.get_reader(mp4)
        assert reader.get_meta_data()["fps"] == pytest.approx(60.0)  # the synthetic take's rate
        frames = [frame / 255.0 for frame in reader]
        assert len(frames) == 4
        for frame in frames:
            grey = frame.mean(axis=2)
            assert frame.shape == (900, 750, 3) and 0.15 < (grey < 0.95).mean() < 0.95
            for colour in (RED, GREEN):  # lossy encoding: colours within 0.25
                assert pixels_of(frame, colour, tolerance=0.25) > 20
        assert len(imageio.mimread(gif)) == 2
    with pytest.raises(SystemExit, match="is not a fit results folder"):
        main(["video", str(shared_tmp)])
