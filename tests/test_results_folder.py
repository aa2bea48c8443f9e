"""The fit results folder (face_dolfinx.results.folder): what is written is read back bit for bit,
a resume refuses other settings naming them, and an interrupted folder knows its missing frames.

Every rank works in its own folder here (the class is plain file handling; the CLI tests run it
under MPI with rank 0 writing).
"""
import json

from mpi4py import MPI
import numpy as np
import pytest

from face_dolfinx.fitting.fitter import ControlState, FitCheckpoint, FrameResult
from face_dolfinx.model.bones import AffineMap, rigid_map, rotation
from face_dolfinx.physics.problem import Controls
from face_dolfinx.results.folder import FitFolder, FitFolderError

MUSCLES, MARKERS, FRAMES = ["zygomatic", "frontalis", "mentalis"], ["m0", "m1", "m2", "m3"], 5
SETTINGS = {"mode": "exact", "gn_steps": 3, "noise_floor": 0.1}
TAKE = {"muscle_names": MUSCLES, "marker_names": MARKERS, "times": [f / 60.0 for f in range(FRAMES)]}


def frame_result(frame: int, rng) -> FrameResult:
    """A frame with every field set to values that a text round trip could spoil (1/3, 1e-17)."""
    errors = rng.uniform(0.0, 1.0, len(MARKERS)) / 3.0
    errors[1] = np.nan  # a gap
    return FrameResult(
        frame=frame, activations=rng.uniform(0.0, 1.0, len(MUSCLES)) + 1e-17,
        cranium=rigid_map(rotation(rng.normal(size=3), 0.1), rng.normal(size=3), rng.normal(size=3)),
        jaw=AffineMap(np.eye(3) + 1e-3 * rng.normal(size=(3, 3)), rng.normal(size=3)),
        jaw_tmj=rng.normal(size=3), marker_errors=errors, rms_error=float(np.sqrt(np.nanmean(errors**2))),
        max_error=float(np.nanmax(errors)), gn_steps=frame + 1, seconds=1.0 / 7.0,
        phases={"sensitivities": 0.25, "gn_solve": 1e-3}, flag="under-determined" if frame == 2 else "",
        initial_rms=2.0 / 3.0, observability=0.875, unobservable=["mentalis"] if frame == 2 else [],
        pressure=-12.0 / 7.0)


def assert_same_frame(read: FrameResult, written: FrameResult):
    for name, value in vars(written).items():
        stored = getattr(read, name)
        if isinstance(value, AffineMap):
            assert stored.same_as(value), name
        elif isinstance(value, np.ndarray):
            assert np.array_equal(stored, value, equal_nan=True), name
        else:
            assert stored == value, name


@pytest.fixture
def folder(tmp_path):
    fit, finished = FitFolder.prepare(tmp_path / "fit", SETTINGS, TAKE)
    assert not finished and not fit.finished
    return fit


def test_a_written_frame_reads_back_identical(folder):
    rng = np.random.default_rng(0)
    result = frame_result(3, rng)
    captured, simulated = rng.normal(size=(len(MARKERS), 3)), rng.normal(size=(len(MARKERS), 3))
    captured[1] = np.nan
    displacement = rng.normal(size=(20, 3))
    folder.write_frame(result, captured, simulated, displacement)

    again = FitFolder(folder.path)  # another process opening the folder
    assert again.muscle_names == MUSCLES and again.marker_names == MARKERS
    assert np.array_equal(again.times, TAKE["times"])
    assert list(again.finished_frames()) == [3]
    assert_same_frame(again.finished_frames()[3], result)
    read_captured, read_simulated = again.frame_markers(3)
    assert np.array_equal(read_captured, captured, equal_nan=True)
    assert np.array_equal(read_simulated, simulated)
    assert np.array_equal(again.displacement(3), displacement)


def test_missing_frames_after_an_interruption(folder):
    """A frame is done when its record exists: a displacement without it (a run killed between
    the two writes) or a temporary file left by a kill during the write does not count."""
    rng = np.random.default_rng(1)
    assert folder.missing_frames() == list(range(FRAMES))
    for frame in (0, 1, 3):
        folder.write_frame(frame_result(frame, rng), np.zeros((4, 3)), np.zeros((4, 3)), np.zeros((6, 3)))
    np.save(folder.frames_dir / "000002.displacement.npy", np.zeros((6, 3)))
    (folder.frames_dir / ".000004.json.tmp").write_text('{"frame": 4, "activ')
    assert folder.missing_frames() == [2, 4]
    assert sorted(folder.finished_frames()) == [0, 1, 3]


def test_a_resume_refuses_other_settings_naming_them(folder):
    path = folder.path
    resumed, finished = FitFolder.prepare(path, SETTINGS, TAKE)
    assert not finished and resumed.settings == SETTINGS
    other = {**SETTINGS, "gn_steps": 5, "chunks": 2}
    with pytest.raises(FitFolderError, match=r"an unfinished fit with other settings \(chunks: '\(not set\)' "
                                             r"there, 2 now; gn_steps: 3 there, 5 now\)"):
        FitFolder.prepare(path, other, TAKE)
    folder.write_frame(frame_result(0, np.random.default_rng(2)), np.zeros((4, 3)), np.zeros((4, 3)),
                       np.zeros((6, 3)))
    folder.mark_finished()
    assert FitFolder.prepare(path, SETTINGS, TAKE)[1]  # the same fit, finished: nothing to do
    with pytest.raises(FitFolderError, match=r"a finished fit with other settings \(chunks"):
        FitFolder.prepare(path, other, TAKE)
    replaced, finished = FitFolder.prepare(path, other, TAKE, overwrite=True)
    assert not finished and replaced.settings == other and replaced.missing_frames() == list(range(FRAMES))


def test_a_folder_that_is_no_fit_is_never_replaced(tmp_path):
    notes = tmp_path / "notes"
    notes.mkdir()
    (notes / "mine.txt").write_text("not a fit")
    with pytest.raises(FitFolderError, match="is not a fit results folder"):
        FitFolder.prepare(notes, SETTINGS, TAKE, overwrite=True)
    assert (notes / "mine.txt").read_text() == "not a fit"
    with pytest.raises(FileNotFoundError, match="not a fit results folder"):
        FitFolder(notes)
    empty = tmp_path / "empty"
    empty.mkdir()
    assert FitFolder.prepare(empty, SETTINGS, TAKE)[0].missing_frames() == list(range(FRAMES))


class IdentityNodeOrder:
    """The node order of a mesh whose local dofs are the file's nodes (one rank's own mesh)."""
    comm = MPI.COMM_SELF

    def gather(self, values):
        return np.array(values, copy=True)

    def scatter(self, values):
        return np.array(values, copy=True)


def test_a_checkpoint_reads_back_identical(folder):
    rng = np.random.default_rng(3)
    state = ControlState("exact", rng.uniform(size=3), rigid_map(rotation([0, 0, 1], 0.2), [1, 2, 3], [0, 1, 0]),
                         AffineMap(np.eye(3), [0.0, -1.0, 0.5]), tmj=np.array([0.1, 0.5, 0.7]), pressure=1.0 / 3.0)
    checkpoint = FitCheckpoint(
        state=state, previous_activations=rng.uniform(size=3), frames_done=4,
        displacement=rng.normal(size=30),
        problem_controls=Controls(rng.uniform(size=3), state.cranium, state.jaw, state.pressure),
        jacobian_state=state.copy(), jacobian_dofs=rng.normal(size=(12, 30)),
        jacobian_markers=rng.normal(size=(12, 4, 3)))
    order = IdentityNodeOrder()
    assert folder.load_checkpoint(3, order) is None
    folder.save_checkpoint(3, checkpoint, order)
    loaded = folder.load_checkpoint(3, order)
    for name in ("previous_activations", "displacement", "jacobian_dofs", "jacobian_markers"):
        assert np.array_equal(getattr(loaded, name), getattr(checkpoint, name)), name
    assert loaded.frames_done == 4
    for read, written in ((loaded.state, state), (loaded.jacobian_state, state)):
        assert read.mode == "exact" and np.array_equal(read.activations, written.activations)
        assert np.array_equal(read.tmj, written.tmj) and read.pressure == written.pressure
        assert read.cranium.same_as(written.cranium) and read.jaw.same_as(written.jaw)
    controls = loaded.problem_controls
    assert controls.same_as(checkpoint.problem_controls)
    assert np.array_equal(controls.activations, checkpoint.problem_controls.activations)
    assert controls.cranium.same_as(state.cranium) and controls.jaw.same_as(state.jaw)
    folder.drop_checkpoint(3)
    assert folder.load_checkpoint(3, order) is None


def test_tables_are_the_same_bytes_whatever_order_the_frames_came_in(tmp_path):
    """A resumed or chunked run writes its frames out of order; the tables do not show it. A gap
    is an empty cell, and the flags and unobservable controls reach frames.csv."""
    rng = np.random.default_rng(4)
    results = [frame_result(frame, rng) for frame in range(FRAMES)]
    tables = []
    for name, order in (("in_order", range(FRAMES)), ("resumed", [3, 4, 0, 2, 1])):
        fit, _ = FitFolder.prepare(tmp_path / name, SETTINGS, TAKE)
        for frame in order:
            fit.write_frame(results[frame], np.zeros((4, 3)), np.zeros((4, 3)), np.zeros((6, 3)))
        fit.write_tables()
        fit.mark_finished()
        assert fit.finished and not fit.checkpoint_dir.exists()
        tables.append({table: (fit.path / table).read_text()
                       for table in ("activations.csv", "kinematics.csv", "marker_errors.csv", "frames.csv")})
    assert tables[0] == tables[1]
    errors = tables[0]["marker_errors.csv"].splitlines()
    assert errors[0] == "frame," + ",".join(MARKERS)
    assert errors[1].split(",")[2] == ""  # marker m1's gap
    assert float(errors[1].split(",")[1]) == pytest.approx(results[0].marker_errors[0], rel=1e-8)
    frames = tables[0]["frames.csv"].splitlines()
    assert len(frames) == FRAMES + 1 and frames[3].endswith("mentalis,under-determined")
    assert json.loads((tmp_path / "resumed" / "run.json").read_text()) == SETTINGS


# -- the contact settings of folders whose run.json predates them ----------------------------------
WITHOUT_CONTACT = {**SETTINGS, "contact": False, "contact_surfaces": []}
WITH_CONTACT = {**SETTINGS, "contact": True, "contact_surfaces": ["lips", "teeth"]}


def test_a_record_without_contact_settings_resumes_without_contact(folder):
    """A run.json with neither ``contact`` nor ``contact_surfaces`` (the fixture's) fitted without
    contact: a run without contact resumes it and records them; one with contact is refused,
    naming the folder and the difference."""
    with pytest.raises(FitFolderError) as refused:
        FitFolder.prepare(folder.path, WITH_CONTACT, TAKE)
    assert str(refused.value).startswith(f"{folder.path} holds an unfinished fit with other settings (")
    assert "contact: False there, True now; contact_surfaces: [] there, ['lips', 'teeth'] now)" in str(refused.value)
    resumed, finished = FitFolder.prepare(folder.path, WITHOUT_CONTACT, TAKE)
    assert not finished and resumed.settings == WITHOUT_CONTACT


def test_a_record_with_contact_but_no_surfaces_says_nothing_of_them(tmp_path):
    """contact on without ``contact_surfaces``: what touched what is unknown, so no resume."""
    FitFolder.prepare(tmp_path / "fit", {**SETTINGS, "contact": True}, TAKE)
    with pytest.raises(FitFolderError, match=r"contact_surfaces: '\(not set\)' there, \['lips', 'teeth'\] now"):
        FitFolder.prepare(tmp_path / "fit", WITH_CONTACT, TAKE)


@pytest.mark.parametrize("now, difference", [
    (WITHOUT_CONTACT, "contact: True there, False now; contact_surfaces: ['lips', 'teeth'] there, [] now"),
    ({**WITH_CONTACT, "contact_surfaces": ["lips"]}, "contact_surfaces: ['lips', 'teeth'] there, ['lips'] now"),
    ({**SETTINGS}, "contact: True there, False now; contact_surfaces: ['lips', 'teeth'] there, [] now"),
])
def test_a_fit_with_contact_resumes_only_with_the_same_contact(tmp_path, now, difference):
    path = tmp_path / "fit"
    FitFolder.prepare(path, WITH_CONTACT, TAKE)
    with pytest.raises(FitFolderError) as refused:
        FitFolder.prepare(path, now, TAKE)
    assert str(refused.value) == (f"{path} holds an unfinished fit with other settings ({difference}); "
                                  "pass --overwrite to replace it or choose another --out")
    assert not FitFolder.prepare(path, WITH_CONTACT, TAKE)[1]


def test_a_record_without_krylov_resumes_without_it(tmp_path):
    """A run.json without ``krylov`` fitted without Krylov on the old factor."""
    path = tmp_path / "fit"
    FitFolder.prepare(path, SETTINGS, TAKE)
    with pytest.raises(FitFolderError, match=r"krylov: False there, True now"):
        FitFolder.prepare(path, {**SETTINGS, "krylov": True}, TAKE)
    assert not FitFolder.prepare(path, {**SETTINGS, "krylov": False}, TAKE)[1]
