"""CSV marker tables: one header row, one column per marker coordinate, one row per frame.

Coordinate columns are named ``Nose_X`` or ``Nose:X`` (also ``Nose.X`` or ``Nose X``; the axis
letter in either case), optionally with a unit, ``Nose_X (mm)`` or ``Nose_X [mm]``. A frame column
(``Frame``, ``Frame#``, ``Frame number``) and a time column in seconds (``Time``, ``Time (s)``,
``t``) are optional. Any other column is an error, so that a misspelt coordinate is not dropped
silently. Commas separate fields; a header with semicolons or tabs and no comma switches to those.
An empty field or NaN is a missing sample.
"""

from __future__ import annotations

import csv
import re
from pathlib import Path

import numpy as np

from ._capture import CaptureError
from ._take import FileTake, parse_numbers, read_text

_COORDINATE_COLUMN = re.compile(
    r"^(?P<marker>.+?)\s*[_:.\s]\s*(?P<axis>[XYZ])\s*(?:[\[(]\s*(?P<unit>[a-z]+)\s*[\])])?$", re.IGNORECASE)
_FRAME_COLUMN = re.compile(r"^frame\s*(#|number|no\.?|index)?$", re.IGNORECASE)
_TIME_COLUMN = re.compile(r"^(time|t)\s*([\[(]\s*s\s*[\])]|_s)?$", re.IGNORECASE)
_AXES = "XYZ"


def read(path: Path) -> FileTake:
    lines = [line for line in read_text(path).splitlines() if line.strip()]
    if not lines:
        raise CaptureError(path, "empty file: no header row")
    header_line = lines[0]
    delimiter = next((d for d in ",;\t" if d in header_line), ",")
    rows = list(csv.reader(lines, delimiter=delimiter))
    header = [column.strip() for column in rows[0]]

    time_column = None
    columns_of_marker: dict[str, dict[str, int]] = {}  # marker -> axis -> column index
    units_in_header = set()
    for index, column in enumerate(header):
        coordinate = _COORDINATE_COLUMN.match(column)
        if _FRAME_COLUMN.match(column):
            continue  # frame numbers add nothing to the row order
        if _TIME_COLUMN.match(column) and time_column is None:
            time_column = index
        elif coordinate:
            axes = columns_of_marker.setdefault(coordinate["marker"], {})
            axis = coordinate["axis"].upper()
            if axis in axes:
                raise CaptureError(path, f"column {column!r} repeats {coordinate['marker']} {axis}")
            axes[axis] = index
            if coordinate["unit"]:
                units_in_header.add(coordinate["unit"].lower())
        else:
            raise CaptureError(path, f"column {column!r} is neither Frame, Time nor a marker coordinate "
                                     f"(Name_X, Name_Y, Name_Z or Name:X, Name:Y, Name:Z)")
    if not columns_of_marker:
        raise CaptureError(path, "no markers: no column is a marker coordinate (Name_X, Name_Y, Name_Z or Name:X ...)")
    for marker, axes in columns_of_marker.items():
        if len(axes) < 3:
            missing = ", ".join(axis for axis in _AXES if axis not in axes)
            raise CaptureError(path, f"marker {marker!r} has no column for {missing}")
    if len(units_in_header) > 1:
        raise CaptureError(path, f"coordinate columns disagree on units: {', '.join(sorted(units_in_header))}")

    names = list(columns_of_marker)
    wanted = ([time_column] if time_column is not None else []) + [
        columns_of_marker[name][axis] for name in names for axis in _AXES]
    wanted_names = [repr(header[i]) for i in wanted]
    table = np.full((len(rows) - 1, len(wanted)), np.nan)
    for row_index, fields in enumerate(rows[1:]):
        if any(field.strip() for field in fields[len(header):]):
            raise CaptureError(path, f"data row {row_index + 1} has {len(fields)} fields, the header {len(header)}")
        # A row that stops early has gaps in the columns it doesn't reach.
        fields = fields + [""] * (len(header) - len(fields))
        table[row_index] = parse_numbers([fields[i] for i in wanted], wanted_names, path, f"data row {row_index + 1}")

    coordinates = table[:, 1:] if time_column is not None else table
    return FileTake(
        marker_names=names,
        positions=coordinates.reshape(len(table), len(names), 3),
        units=units_in_header.pop() if units_in_header else None,
        frame_rate=None,  # CSV has no rate field; read_capture takes it from the time column or the caller
        times=table[:, 0] if time_column is not None else None,
    )


def write(path: Path, names: list[str], positions: np.ndarray, units: str, frame_rate: float, times: np.ndarray):
    """Header ``Frame,Time,Name_X,Name_Y,Name_Z,...``; frames count from 1; gaps are empty fields.

    The header carries no unit (the plainest table for other tools): a file written in cm or m is
    read back with ``units=``.
    """
    with path.open("w", newline="", encoding="utf-8") as file:
        writer = csv.writer(file)
        writer.writerow(["Frame", "Time"] + [f"{name}_{axis}" for name in names for axis in _AXES])
        for frame, (time, markers) in enumerate(zip(times, positions), start=1):
            values = ["" if np.isnan(value) else f"{value:.10g}" for value in markers.ravel()]
            writer.writerow([frame, f"{time:.10g}"] + values)
