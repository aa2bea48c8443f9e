"""Reading and writing captures: format choice, units, up axis, frame rate and the sanity checks."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from . import _c3d, _csv, _trc
from ._capture import Capture, CaptureError
from ._take import FileTake

_FORMATS = {"c3d": _c3d, "trc": _trc, "csv": _csv}
# Lab systems writing C3D put Z up; OpenSim (TRC) puts Y up; our own CSVs are in model axes (Y up).
_DEFAULT_UP_AXIS = {"c3d": "Z", "trc": "Y", "csv": "Y"}

_MM_PER_UNIT = {"mm": 1.0, "cm": 10.0, "m": 1000.0}
_UNIT_SPELLINGS = {
    "mm": "mm", "millimeter": "mm", "millimeters": "mm", "millimetre": "mm", "millimetres": "mm",
    "cm": "cm", "centimeter": "cm", "centimeters": "cm", "centimetre": "cm", "centimetres": "cm",
    "m": "m", "meter": "m", "meters": "m", "metre": "m", "metres": "m",
}
_UNIT_WORDS = {"mm": "millimetres", "cm": "centimetres", "m": "metres"}

# A face's markers span roughly 80-250 mm (bounding-box diagonal). The accepted band is wider, so
# that a partial marker set or a large head passes, yet narrow enough that a 10x unit mistake
# (mm read as cm or the reverse) always lands outside it.
_FACE_SPAN_MM = (40.0, 600.0)


def _format_of(path: Path, format: str | None) -> str:
    if format is not None:
        if format.lower().lstrip(".") not in _FORMATS:
            raise CaptureError(path, f"unknown capture format {format!r}: expected one of {', '.join(_FORMATS)}")
        return format.lower().lstrip(".")
    suffix = path.suffix.lower().lstrip(".")
    if suffix not in _FORMATS:
        raise CaptureError(path, f"unknown capture format {path.suffix or '(no suffix)'!r}: expected "
                                 f".c3d, .trc or .csv, or say which with format=")
    return suffix


def _unit(spelling: str, path: Path, where: str) -> str:
    unit = _UNIT_SPELLINGS.get(spelling.strip().lower())
    if unit is None:
        raise CaptureError(path, f"unknown length unit {spelling!r} {where}: expected mm, cm or m")
    return unit


def _up_axis(up_axis: str, path: Path) -> str:
    if str(up_axis).upper() not in ("Y", "Z"):
        raise CaptureError(path, f"up_axis must be 'Y' or 'Z', not {up_axis!r}")
    return str(up_axis).upper()


def _file_axes_to_model(positions: np.ndarray, up_axis: str) -> np.ndarray:
    """Rotate so that the file's up axis becomes +Y: a Z-up (x, y, z) becomes (x, z, -y)."""
    if up_axis == "Y":
        return positions
    return np.stack([positions[..., 0], positions[..., 2], -positions[..., 1]], axis=-1)


def _model_axes_to_file(positions: np.ndarray, up_axis: str) -> np.ndarray:
    """The inverse rotation: model (x, y, z) is written Z-up as (x, -z, y)."""
    if up_axis == "Y":
        return positions
    return np.stack([positions[..., 0], -positions[..., 2], positions[..., 1]], axis=-1)


def read_capture(path, units: str | None = None, up_axis: str | None = None, frame_rate: float | None = None,
                 format: str | None = None, *, check_scale: bool = True, skip_empty_frames: bool = False) -> Capture:
    """Read a C3D, TRC or CSV take into a Capture in millimetres with Y up.

    units: mm, cm or m. The file's own statement (C3D POINT:UNITS, TRC Units, a CSV header such
        as ``Nose_X (mm)``) is used when this is None; given, it overrides the file (for a
        mislabelled file). With neither, mm.
    up_axis: "Y" or "Z", the file's vertical axis. Default: Z for C3D, Y for TRC and CSV.
    frame_rate: Hz. Default: the file's (C3D POINT:RATE, TRC DataRate, or the span of a CSV time
        column); an error if the file has none.
    format: "c3d", "trc" or "csv"; default from the suffix.
    check_scale: False skips the check that the markers span a face (40-600 mm); allowed only
        when the units are stated, by ``units`` or by the file.
    skip_empty_frames: drop frames in which no marker is present instead of raising.

    Raises CaptureError naming the file and the problem: missing file, unknown format, unreadable
    or malformed file, no markers, no frames, no frame rate, frames with no marker present, and a
    scale that doesn't look like a face in the units used (likely a unit mistake).
    """
    path = Path(path)
    file_format = _format_of(path, format)
    if not path.exists():
        raise CaptureError(path, "file not found")
    if not path.is_file():
        raise CaptureError(path, "not a file")
    units_given = None if units is None else _unit(units, path, "passed as units=")
    up = _up_axis(_DEFAULT_UP_AXIS[file_format] if up_axis is None else up_axis, path)

    take = _FORMATS[file_format].read(path)
    if not take.marker_names:
        raise CaptureError(path, "no markers in the file")
    if len(take.positions) == 0:
        raise CaptureError(path, "no frames: the file has a header but no data")
    units_in_file = None if take.units is None else _unit(take.units, path, "in the file")
    units_used = units_given or units_in_file or "mm"
    if not check_scale and units_given is None and units_in_file is None:
        raise CaptureError(path, "check_scale=False needs the units stated: the file doesn't say, so pass "
                                 "units= too, lest a unit mistake go unnoticed")

    positions_mm = _file_axes_to_model(take.positions, up) * _MM_PER_UNIT[units_used]
    capture = Capture(take.marker_names, positions_mm, _frame_rate(take, frame_rate, path), take.times, path)

    empty = ~capture.present.any(axis=1)
    if empty.all():
        raise CaptureError(path, f"no marker is present in any of the {capture.n_frames} frames: all gaps "
                                 f"(NaN or exact zeros)")
    if empty.any():
        if not skip_empty_frames:
            raise CaptureError(path, f"no marker is present in {empty.sum()} of the {capture.n_frames} frames "
                                     f"({_frame_ranges(np.flatnonzero(empty))}, counting from 0): all gaps; trim "
                                     f"them from the file or pass skip_empty_frames=True")
        capture = capture.select(~empty)

    if check_scale:
        _check_scale(capture, units_used, units_given, units_in_file)
    return capture


def _frame_rate(take: FileTake, frame_rate: float | None, path: Path) -> float:
    """The caller's rate, else the file's rate field, else the mean step of its time column."""
    if take.times is not None and len(take.times) > 1:
        steps = np.diff(take.times)
        if not (steps > 0).all():
            first = int(np.argmin(steps > 0))
            raise CaptureError(path, f"time column does not increase from frame {first} to {first + 1} (0-based)")
    if frame_rate is not None:
        return frame_rate
    if take.frame_rate is not None:
        return take.frame_rate
    if take.times is not None and len(take.times) > 1:
        return (len(take.times) - 1) / (take.times[-1] - take.times[0])
    raise CaptureError(path, "no frame rate: the file gives none (no rate field, nor a time column over two "
                             "frames or more); pass frame_rate=")


def _frame_ranges(frames: np.ndarray, shown: int = 8) -> str:
    """'0-4, 17, 30-31' for frames [0 1 2 3 4 17 30 31]; past `shown` runs, '...' and the last."""
    runs = np.split(frames, np.flatnonzero(np.diff(frames) > 1) + 1)
    texts = [f"{run[0]}" if len(run) == 1 else f"{run[0]}-{run[-1]}" for run in runs]
    if len(texts) > shown:
        texts = texts[: shown - 1] + ["...", texts[-1]]
    return ", ".join(texts)


def _marker_span_mm(capture: Capture) -> float | None:
    """Median over frames of the bounding-box diagonal of the markers present (mm).

    Frames with fewer than two markers present have no span and don't count; None if no frame
    has two.
    """
    enough = capture.present.sum(axis=1) >= 2
    if not enough.any():
        return None
    positions = capture.positions[enough]
    diagonals = np.linalg.norm(np.nanmax(positions, axis=1) - np.nanmin(positions, axis=1), axis=1)
    return float(np.median(diagonals))


def _check_scale(capture: Capture, units_used: str, units_given: str | None, units_in_file: str | None):
    span_mm = _marker_span_mm(capture)
    low, high = _FACE_SPAN_MM
    if span_mm is None or low <= span_mm <= high:
        return
    span_in_file = span_mm / _MM_PER_UNIT[units_used]
    likely = [unit for unit, mm in _MM_PER_UNIT.items() if unit != units_used and low <= span_in_file * mm <= high]
    if units_given:
        stated = f"units={units_given!r} was passed" + (f"; the file says {units_in_file!r}" if units_in_file else "")
    elif units_in_file:
        stated = f"the file says {units_in_file!r}"
    else:
        stated = "the file doesn't say its units, so mm was assumed"
    advice = (f"likely a unit mistake: looks like {_UNIT_WORDS[likely[0]]}; pass units={likely[0]!r} "
              f"(--units {likely[0]} on the command line)" if likely else
              "not a face's span in mm, cm or m either: check the file")
    stated_units = units_given or units_in_file
    override = ("check_scale=False" + ("" if stated_units else " with units=") + "; on the command line "
                "--no-scale-check" + ("" if stated_units else " with --units"))
    raise CaptureError(
        capture.source,
        f"markers span {span_in_file:.3g} {units_used} ({stated}; median bounding-box diagonal over frames), "
        f"but a face's markers span roughly 80-250 mm — {advice} (if the scale is right: {override})")


def write_capture(capture: Capture, path, *, units: str = "mm", up_axis: str | None = None,
                  format: str | None = None) -> Path:
    """Write a capture as CSV, TRC or C3D (format from the suffix, or ``format``).

    units and up_axis are the file's; the defaults (mm, and the format's default up axis as in
    read_capture) make ``read_capture(write_capture(capture, path))`` give the capture back.
    Gaps are written as empty fields (CSV, TRC) or residual -1 (C3D). Returns the path.
    """
    path = Path(path)
    file_format = _format_of(path, format)
    unit = _unit(units, path, "passed as units=")
    up = _up_axis(_DEFAULT_UP_AXIS[file_format] if up_axis is None else up_axis, path)
    positions = _model_axes_to_file(capture.positions, up) / _MM_PER_UNIT[unit]
    _FORMATS[file_format].write(path, capture.marker_names, positions, unit, capture.frame_rate, capture.times)
    return path
