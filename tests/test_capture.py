"""Reading and writing motion-capture takes (face_dolfinx.capture): formats, units, axes, gaps, errors."""

import importlib.util
from pathlib import Path

import numpy as np
import pytest

from face_dolfinx.capture import Capture, CaptureError, frames_with_gaps, read_capture, write_capture

needs_ezc3d = pytest.mark.skipif(importlib.util.find_spec("ezc3d") is None, reason="ezc3d not installed")
FORMATS = ["csv", "trc", pytest.param("c3d", marks=needs_ezc3d)]
# ezc3d stores coordinates as float32: about 1e-5 mm on a face.
TOLERANCE_MM = {"csv": 1e-6, "trc": 1e-6, "c3d": 1e-4}

# A face in model axes (mm, Y up, +Z out of the face): its markers span about 175 mm.
FACE_MARKERS = {
    "forehead": (0.0, 60.0, 80.0),
    "nose": (0.0, 0.0, 100.0),
    "chin": (0.0, -80.0, 70.0),
    "cheek_left": (50.0, -10.0, 70.0),
    "cheek_right": (-50.0, -10.0, 70.0),
    "mouth_left": (25.0, -45.0, 80.0),
    "mouth_right": (-25.0, -45.0, 80.0),
}
NAMES = list(FACE_MARKERS)
RATE = 120.0


def face_take(n_frames=6, seed=0):
    """Face markers carried by head motion (a turn and a drift) with a little expression jitter."""
    rng = np.random.default_rng(seed)
    rest = np.array(list(FACE_MARKERS.values()))
    frames = []
    for frame in range(n_frames):
        angle = 0.05 * frame
        turn = np.array([[np.cos(angle), 0, np.sin(angle)], [0, 1, 0], [-np.sin(angle), 0, np.cos(angle)]])
        frames.append(rest @ turn.T + [3.0 * frame, 200.0, -1.5 * frame] + rng.normal(0, 0.5, rest.shape))
    return np.array(frames)


def face_capture(n_frames=6):
    positions = face_take(n_frames)
    positions[2, NAMES.index("nose")] = np.nan  # occluded
    positions[4, NAMES.index("chin")] = np.nan
    return Capture(NAMES, positions, RATE)


def assert_same_capture(read, expected, tolerance_mm):
    assert read.marker_names == expected.marker_names
    np.testing.assert_array_equal(read.present, expected.present)
    np.testing.assert_allclose(read.positions, expected.positions, atol=tolerance_mm, rtol=0)
    assert read.frame_rate == pytest.approx(expected.frame_rate)
    np.testing.assert_allclose(read.times, expected.times, atol=1e-9)


def csv_text(positions, style="underscore", frame_column=True, time_column=True):
    """A CSV written here, independently of write_capture, in a given header style."""
    separator = {"underscore": "_", "colon": ":"}[style]
    header = (["Frame"] if frame_column else []) + (["Time"] if time_column else [])
    header += [f"{name}{separator}{axis}" for name in NAMES for axis in "XYZ"]
    rows = [",".join(header)]
    for frame, markers in enumerate(positions):
        leading = ([str(frame + 1)] if frame_column else []) + ([repr(frame / RATE)] if time_column else [])
        rows.append(",".join(leading + ["" if np.isnan(v) else repr(v) for v in markers.ravel()]))
    return "\n".join(rows) + "\n"


# --- round trips -----------------------------------------------------------------------------

@pytest.mark.parametrize("file_format", FORMATS)
def test_round_trip_keeps_positions_gaps_rate_and_times(tmp_path, file_format):
    capture = face_capture()
    path = write_capture(capture, tmp_path / f"take.{file_format}")
    read = read_capture(path)
    assert_same_capture(read, capture, TOLERANCE_MM[file_format])
    assert read.source == path
    assert not read.present[2, NAMES.index("nose")] and np.isnan(read.positions[2, NAMES.index("nose")]).all()


@pytest.mark.parametrize("file_format", FORMATS)
@pytest.mark.parametrize("unit, mm_per_unit", [("mm", 1.0), ("cm", 10.0), ("m", 1000.0)])
def test_units_are_converted_to_millimetres(tmp_path, file_format, unit, mm_per_unit):
    capture = face_capture()
    path = write_capture(capture, tmp_path / f"take.{file_format}", units=unit)
    in_file = read_capture(path, units=unit, check_scale=False)
    assert_same_capture(in_file, capture, TOLERANCE_MM[file_format] * mm_per_unit)
    if file_format != "csv":  # TRC and C3D say their units: no option needed
        assert_same_capture(read_capture(path), capture, TOLERANCE_MM[file_format] * mm_per_unit)


@pytest.mark.parametrize("file_format", FORMATS)
@pytest.mark.parametrize("up_axis", ["Y", "Z"])
def test_up_axis_round_trip(tmp_path, file_format, up_axis):
    capture = face_capture()
    path = write_capture(capture, tmp_path / f"take.{file_format}", up_axis=up_axis)
    assert_same_capture(read_capture(path, up_axis=up_axis), capture, TOLERANCE_MM[file_format])


def test_z_up_file_is_rotated_so_that_z_becomes_y(tmp_path):
    capture = face_capture()
    path = write_capture(capture, tmp_path / "take.trc", up_axis="Y")  # the file holds model axes as they are
    x, y, z = np.moveaxis(capture.positions, -1, 0)
    read_z_up = read_capture(path, up_axis="z")
    np.testing.assert_allclose(read_z_up.positions, np.stack([x, z, -y], axis=-1), atol=1e-6)


@needs_ezc3d
def test_c3d_from_another_writer_is_z_up_by_default_and_zeros_are_gaps(tmp_path):
    import ezc3d

    positions_z_up = face_take()[:, :, [0, 2, 1]] * [1, -1, 1]  # model (x, y, z) -> lab (x, -z, y)
    positions_z_up[1, 3] = 0.0  # how some systems write an occluded marker
    c3d = ezc3d.c3d()
    c3d["parameters"]["POINT"]["RATE"]["value"] = [RATE]
    c3d["parameters"]["POINT"]["LABELS"]["value"] = NAMES + ["JawAngles"]
    c3d["parameters"]["POINT"]["UNITS"]["value"] = ["mm"]
    c3d.add_parameter("POINT", "ANGLES", ["JawAngles"])  # a model output, not a marker
    points = np.ones((4, len(NAMES) + 1, len(positions_z_up)))
    points[:3, : len(NAMES)] = positions_z_up.transpose(2, 1, 0)
    points[:3, len(NAMES)] = 5.0
    c3d["data"]["points"] = points
    c3d.write(str(tmp_path / "lab.c3d"))

    read = read_capture(tmp_path / "lab.c3d")
    assert read.marker_names == NAMES
    expected = face_take()
    expected[1, 3] = np.nan
    np.testing.assert_allclose(read.positions, expected, atol=1e-4)
    assert not read.present[1, 3] and read.present.sum() == read.present.size - 1


@needs_ezc3d
def test_c3d_written_with_an_upper_case_suffix_stays_at_that_path(tmp_path):
    path = write_capture(face_capture(), tmp_path / "TAKE.C3D")
    assert [p.name for p in tmp_path.iterdir()] == ["TAKE.C3D"]
    assert_same_capture(read_capture(path), face_capture(), TOLERANCE_MM["c3d"])


# --- files written by other tools ------------------------------------------------------------

HAND_WRITTEN_TRC = (
    "PathFileType\t4\t(X/Y/Z)\tsmile.trc\n"
    "DataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\tOrigDataRate\tOrigDataStartFrame\tOrigNumFrames\n"
    "60.00\t60.00\t4\t3\tmm\t60.00\t1\t4\n"
    "Frame#\tTime\tNose\t\t\tChin\t\t\tCheek L\t\t\n"
    "\t\tX1\tY1\tZ1\tX2\tY2\tZ2\tX3\tY3\tZ3\n"
    "\n"
    "1\t0.000\t0.0\t0.0\t100.0\t0.0\t-80.0\t70.0\t50.0\t-10.0\t70.0\n"
    "2\t0.017\t1.0\t0.5\t100.0\t\t\t\t51.0\t-10.0\t70.0\n"      # Chin: empty fields
    "3\t0.033\t0\t0\t0\tNaN\tNaN\tNaN\t52.0\t-10.0\t70.0\n"       # Nose: exact zeros
    "4\t0.050\t2.0\t1.0\t100.0\t0.0\t-81.0\t70.0\n"               # Cheek L: row stops early
)


def test_hand_written_trc_header_and_gaps(tmp_path):
    path = tmp_path / "smile.trc"
    path.write_text(HAND_WRITTEN_TRC)
    capture = read_capture(path)
    assert capture.marker_names == ["Nose", "Chin", "Cheek L"]
    assert capture.frame_rate == 60.0  # DataRate, not the rounded times
    np.testing.assert_allclose(capture.times, [0.0, 0.017, 0.033, 0.050])
    np.testing.assert_array_equal(capture.present, [[1, 1, 1], [1, 0, 1], [0, 0, 1], [1, 1, 0]])
    np.testing.assert_allclose(capture.positions[0], [[0, 0, 100], [0, -80, 70], [50, -10, 70]])
    np.testing.assert_allclose(capture.positions[3, :2], [[2, 1, 100], [0, -81, 70]])
    assert np.isnan(capture.positions[~capture.present]).all()


def test_trc_units_line_is_read(tmp_path):
    in_mm, in_cm = tmp_path / "smile_mm.trc", tmp_path / "smile_cm.trc"
    in_mm.write_text(HAND_WRITTEN_TRC)
    in_cm.write_text(HAND_WRITTEN_TRC.replace("\tmm\t", "\tcm\t"))
    # The same numbers in cm span ten times a face; the file states its units, so the check may go.
    np.testing.assert_allclose(read_capture(in_cm, check_scale=False).positions, 10 * read_capture(in_mm).positions)


HAND_WRITTEN_CSV = """Frame,Time,Nose:X,Nose:Y,Nose:Z,Chin:X,Chin:Y,Chin:Z,Cheek L:X,Cheek L:Y,Cheek L:Z
1,0.00,0.0,0.0,100.0,0.0,-80.0,70.0,50.0,-10.0,70.0
2,0.01,1.0,0.5,100.0,nan,nan,nan,51.0,-10.0,70.0
3,0.02,0,0,0,,,,52.0,-10.0,70.0
"""


def test_hand_written_csv_with_colon_headers_and_gaps(tmp_path):
    path = tmp_path / "smile.csv"
    path.write_text(HAND_WRITTEN_CSV)
    capture = read_capture(path)
    assert capture.marker_names == ["Nose", "Chin", "Cheek L"]
    assert capture.frame_rate == pytest.approx(100.0)  # from the time column
    np.testing.assert_allclose(capture.times, [0.0, 0.01, 0.02])
    np.testing.assert_array_equal(capture.present, [[1, 1, 1], [1, 0, 1], [0, 0, 1]])
    np.testing.assert_allclose(capture.positions[1, [0, 2]], [[1, 0.5, 100], [51, -10, 70]])


@pytest.mark.parametrize("style", ["underscore", "colon"])
@pytest.mark.parametrize("frame_column", [True, False])
@pytest.mark.parametrize("time_column", [True, False])
def test_csv_header_styles_with_and_without_frame_and_time(tmp_path, style, frame_column, time_column):
    capture = face_capture()
    path = tmp_path / "take.csv"
    path.write_text(csv_text(capture.positions, style, frame_column, time_column))
    # Without a time column a CSV has no rate: it must be given.
    read = read_capture(path, frame_rate=None if time_column else RATE)
    assert_same_capture(read, capture, 1e-9)


def test_csv_unit_in_header_semicolons_and_byte_order_mark(tmp_path):
    path = tmp_path / "export.csv"
    text = csv_text(face_capture().positions / 10.0).replace(",", ";")
    text = text.replace("_X;", "_X (cm);").replace("_Y;", "_Y (cm);").replace("_Z;", "_Z (cm);")
    text = text.replace("_Z\n", "_Z (cm)\n")
    path.write_bytes("\ufeff".encode() + text.encode())
    assert_same_capture(read_capture(path), face_capture(), 1e-9)


def test_partial_nan_makes_the_whole_sample_a_gap():
    positions = face_take()
    positions[1, 0, 2] = np.nan
    capture = Capture(NAMES, positions, RATE)
    assert not capture.present[1, 0] and np.isnan(capture.positions[1, 0]).all()
    assert capture.present.sum() == capture.present.size - 1


# --- the Capture ------------------------------------------------------------------------------

def test_neutral_defaults_to_the_first_frame_and_keeps_gaps_as_nan():
    capture = face_capture()
    np.testing.assert_array_equal(capture.neutral(), capture.positions[0])
    neutral = capture.neutral(frame=2)
    assert np.isnan(neutral[NAMES.index("nose")]).all() and np.isfinite(np.delete(neutral, NAMES.index("nose"), 0)).all()
    neutral[:] = 0.0  # a copy: the capture is untouched
    assert np.isfinite(capture.positions[2, 0]).all()
    with pytest.raises(CaptureError, match="neutral frame 6 is out of range: the capture has 6 frames"):
        capture.neutral(6)


@pytest.mark.parametrize("frames, expected", [(slice(1, 4), [1, 2, 3]), (np.array([5, 0]), [5, 0]),
                                              (np.arange(6) % 2 == 0, [0, 2, 4]), (3, [3])])
def test_select_frames(frames, expected):
    capture = face_capture()
    part = capture.select(frames)
    np.testing.assert_array_equal(part.positions, capture.positions[expected])
    np.testing.assert_array_equal(part.times, capture.times[expected])
    assert part.marker_names == capture.marker_names and part.frame_rate == capture.frame_rate


def test_frames_with_gaps_and_summary():
    capture = face_capture()
    np.testing.assert_array_equal(frames_with_gaps(capture), [2, 4])
    summary = capture.summary()
    assert "7 markers, 6 frames at 120 Hz" in summary
    assert "2 frames with at least one" in summary
    assert [line.split() for line in summary.splitlines() if line.split()[0] in ("nose", "chin", "forehead")] == [
        ["forehead", "0.0%"], ["nose", "16.7%"], ["chin", "16.7%"]]


def test_capture_arrays_are_read_only():
    capture = face_capture()
    with pytest.raises(ValueError):
        capture.positions[0, 0, 0] = 1.0


def test_capture_rejects_repeated_marker_names():
    with pytest.raises(CaptureError, match="marker names must be unique; repeated: nose"):
        Capture(["nose", "nose"], np.ones((1, 2, 3)), RATE)


# --- bad input: one clear message naming the file and the problem ----------------------------

def test_missing_file(tmp_path):
    with pytest.raises(CaptureError, match=r"nothing\.trc: file not found"):
        read_capture(tmp_path / "nothing.trc")


@pytest.mark.parametrize("name, kwargs, message", [
    ("take.txt", {}, r"take\.txt: unknown capture format '\.txt': expected \.c3d, \.trc or \.csv"),
    ("take", {}, r"take: unknown capture format '\(no suffix\)'"),
    ("take.csv", {"format": "xlsx"}, r"take\.csv: unknown capture format 'xlsx'"),
])
def test_unknown_format(tmp_path, name, kwargs, message):
    (tmp_path / name).write_text(HAND_WRITTEN_CSV)
    with pytest.raises(CaptureError, match=message):
        read_capture(tmp_path / name, **kwargs)


def test_format_option_overrides_the_suffix(tmp_path):
    path = tmp_path / "take.txt"
    path.write_text(HAND_WRITTEN_CSV)
    assert read_capture(path, format="csv").marker_names == ["Nose", "Chin", "Cheek L"]


@pytest.mark.parametrize("name, text", [
    ("frames_only.csv", "Frame,Time\n1,0.0\n"),
    ("no_names.trc", HAND_WRITTEN_TRC.replace("Nose\t\t\tChin\t\t\tCheek L\t\t", "")),
])
def test_no_markers(tmp_path, name, text):
    (tmp_path / name).write_text(text)
    with pytest.raises(CaptureError, match=f"{name}: no markers"):
        read_capture(tmp_path / name)


@needs_ezc3d
def test_no_markers_in_c3d(tmp_path):
    import ezc3d

    c3d = ezc3d.c3d()  # model outputs only: points, but none of them a marker
    c3d["parameters"]["POINT"]["RATE"]["value"] = [RATE]
    c3d["parameters"]["POINT"]["LABELS"]["value"] = ["JawAngles"]
    c3d.add_parameter("POINT", "ANGLES", ["JawAngles"])
    c3d["data"]["points"] = np.ones((4, 1, 3))
    c3d.write(str(tmp_path / "angles.c3d"))
    with pytest.raises(CaptureError, match=r"angles\.c3d: no markers"):
        read_capture(tmp_path / "angles.c3d")


def test_no_frames(tmp_path):
    path = tmp_path / "header_only.csv"
    path.write_text(HAND_WRITTEN_CSV.splitlines()[0] + "\n")
    with pytest.raises(CaptureError, match=r"header_only\.csv: no frames"):
        read_capture(path)


def test_all_gap_frames_are_reported_by_index(tmp_path):
    positions = face_take(8)
    positions[[1, 3, 4, 5]] = np.nan
    positions[6] = 0.0
    path = tmp_path / "dropouts.csv"
    path.write_text(csv_text(positions))
    with pytest.raises(CaptureError, match=r"dropouts\.csv: no marker is present in 5 of the 8 frames \(1, 3-6, counting from 0\)"):
        read_capture(path)
    kept = read_capture(path, skip_empty_frames=True)
    np.testing.assert_allclose(kept.positions, positions[[0, 2, 7]], atol=1e-9)
    np.testing.assert_allclose(kept.times, np.array([0, 2, 7]) / RATE)


def test_every_frame_a_gap(tmp_path):
    path = tmp_path / "blank.csv"
    path.write_text(csv_text(np.zeros((3, len(NAMES), 3))))
    with pytest.raises(CaptureError, match=r"blank\.csv: no marker is present in any of the 3 frames"):
        read_capture(path, skip_empty_frames=True)


@pytest.mark.parametrize("written_in, read_as, likely", [
    ("cm", None, "cm"),    # 10x small: cm read as the default mm
    ("m", None, "m"),      # 1000x small
    ("mm", "cm", "mm"),    # 10x large
    ("m", "cm", "m"),      # 100x small
    ("cm", "m", "cm"),     # 100x large
])
def test_unit_mistakes_are_caught_by_the_face_scale(tmp_path, written_in, read_as, likely):
    path = write_capture(face_capture(), tmp_path / "take.csv", units=written_in)
    words = {"mm": "millimetres", "cm": "centimetres", "m": "metres"}
    with pytest.raises(CaptureError, match=rf"take\.csv: markers span .* looks like {words[likely]}; "
                                           rf"pass units='{likely}'"):
        read_capture(path, units=read_as)


def test_scale_message_shows_the_span_and_what_was_assumed(tmp_path):
    path = write_capture(face_capture(), tmp_path / "take.csv", units="m")
    with pytest.raises(CaptureError) as caught:
        read_capture(path)
    assert "markers span 0.17" in str(caught.value) and "mm was assumed" in str(caught.value)


def test_mislabelled_file_units_are_caught_and_can_be_overridden(tmp_path):
    path = tmp_path / "mislabelled.trc"
    path.write_text(HAND_WRITTEN_TRC.replace("\tmm\t", "\tm\t"))  # the numbers are mm
    with pytest.raises(CaptureError, match=r"the file says 'm'.*looks like millimetres; pass units='mm'"):
        read_capture(path)
    assert read_capture(path, units="mm").positions[0, 0, 2] == 100.0


def test_capture_errors_survive_pickling():
    """Errors raised on one MPI rank are pickled to the others."""
    import pickle
    error = pickle.loads(pickle.dumps(CaptureError("take.trc", "file not found")))
    assert (str(error), error.source, error.problem) == ("take.trc: file not found", Path("take.trc"), "file not found")


def test_check_scale_false_needs_stated_units(tmp_path):
    tiny = Capture(["a", "b"], [[[0.0, 0.0, 1.0], [0.0, 10.0, 1.0]]] * 2, RATE)  # 10 mm apart: not a face
    path = write_capture(tiny, tmp_path / "wand.csv")
    with pytest.raises(CaptureError, match="markers span 10"):
        read_capture(path)
    with pytest.raises(CaptureError, match=r"wand\.csv: check_scale=False needs the units stated"):
        read_capture(path, check_scale=False)
    assert read_capture(path, units="mm", check_scale=False).positions[0, 1, 1] == 10.0


def test_csv_without_time_needs_a_frame_rate(tmp_path):
    path = tmp_path / "untimed.csv"
    path.write_text(csv_text(face_take(), time_column=False))
    with pytest.raises(CaptureError, match=r"untimed\.csv: no frame rate.*pass frame_rate="):
        read_capture(path)


@pytest.mark.parametrize("name, text, message", [
    ("extra.csv", "Frame,Nose_X,Nose_Y,Nose_Z,Quality\n1,0,0,100,1\n",
     r"column 'Quality' is neither Frame, Time nor a marker coordinate"),
    ("two_axes.csv", "Nose_X,Nose_Y,Chin_X,Chin_Y,Chin_Z\n0,0,0,-80,70\n", r"marker 'Nose' has no column for Z"),
    ("word.csv", "Nose_X,Nose_Y,Nose_Z\n0,0,100\n0,oops,100\n", r"data row 2, column 'Nose_Y': 'oops' is not a number"),
    ("long_row.csv", "Nose_X,Nose_Y,Nose_Z\n0,0,100,7\n", r"data row 1 has 4 fields, the header 3"),
    ("backwards.csv", "Time,Nose_X,Nose_Y,Nose_Z\n0.0,0,0,100\n0.2,0,0,100\n0.1,0,0,100\n",
     r"time column does not increase from frame 1 to 2"),
    ("units.csv", "Nose_X (mm),Nose_Y (cm),Nose_Z (mm)\n0,0,100\n", r"coordinate columns disagree on units: cm, mm"),
    ("inches.csv", "Nose_X (in),Nose_Y (in),Nose_Z (in)\n0,0,100\n", r"unknown length unit 'in' in the file"),
    ("not.trc", HAND_WRITTEN_CSV, r"not a TRC file: the first line does not start with 'PathFileType'"),
    ("short.trc", "\n".join(HAND_WRITTEN_TRC.splitlines()[:3]), r"TRC header cut short"),
    ("triples.trc", HAND_WRITTEN_TRC.replace("\tX3\tY3\tZ3", ""),
     r"line 4 names 3 markers but line 5 has 6 coordinate labels"),
    ("wide.trc", HAND_WRITTEN_TRC.replace("70.0\n2", "70.0\t9\n2"), r"line 7 has 12 fields"),
    ("rate.trc", HAND_WRITTEN_TRC.replace("60.00\t60.00", "sixty\t60.00"), r"DataRate 'sixty' is not a number"),
])
def test_malformed_text_files(tmp_path, name, text, message):
    (tmp_path / name).write_text(text)
    with pytest.raises(CaptureError, match=rf"{name.replace('.', '[.]')}: {message}"):
        read_capture(tmp_path / name)


def test_binary_file_with_a_text_suffix(tmp_path):
    (tmp_path / "take.trc").write_bytes(bytes(range(128, 256)))
    with pytest.raises(CaptureError, match=r"take\.trc: not a text file"):
        read_capture(tmp_path / "take.trc")


@needs_ezc3d
def test_garbage_c3d(tmp_path):
    (tmp_path / "take.c3d").write_bytes(b"not a c3d file" * 10)
    with pytest.raises(CaptureError, match=r"take\.c3d: not a readable C3D file"):
        read_capture(tmp_path / "take.c3d")


@pytest.mark.parametrize("kwargs, message", [
    ({"units": "inch"}, r"unknown length unit 'inch' passed as units="),
    ({"up_axis": "X"}, r"up_axis must be 'Y' or 'Z', not 'X'"),
    ({"frame_rate": -5}, r"frame rate must be a positive number of Hz"),
])
def test_bad_options(tmp_path, kwargs, message):
    path = tmp_path / "smile.trc"
    path.write_text(HAND_WRITTEN_TRC)
    with pytest.raises(CaptureError, match=rf"smile\.trc: {message}"):
        read_capture(path, **kwargs)


def test_capture_error_is_a_value_error_that_names_the_file(tmp_path):
    with pytest.raises(ValueError) as caught:
        read_capture(tmp_path / "gone.c3d")
    assert caught.value.source == tmp_path / "gone.c3d" and caught.value.problem == "file not found"
