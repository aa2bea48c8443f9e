"""OpenSim TRC marker files: tab-separated text, five header lines, then one row per frame.

    PathFileType  4  (X/Y/Z)  take.trc
    DataRate  CameraRate  NumFrames  NumMarkers  Units  OrigDataRate  OrigDataStartFrame  OrigNumFrames
    120  120  600  2  mm  120  1  600
    Frame#  Time  Nose  <tab>  <tab>  Chin  <tab>  <tab>
    <tab>  <tab>  X1  Y1  Z1  X2  Y2  Z2
    (blank line)
    1  0.0  12.1  80.4  95.2  10.9  20.3  90.1

An empty field (or NaN) is a missing sample; rows may stop early when their last markers are
missing. NumFrames and NumMarkers are not trusted: the marker names row and the data rows count.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ._capture import CaptureError
from ._take import FileTake, parse_numbers, read_text

_HEADER_KEYS = ["DataRate", "CameraRate", "NumFrames", "NumMarkers", "Units",
                "OrigDataRate", "OrigDataStartFrame", "OrigNumFrames"]


def _fields(line: str) -> list[str]:
    # The spec separates fields with tabs; files typed or re-saved by hand sometimes use spaces.
    return line.split("\t") if "\t" in line else line.split()


def read(path: Path) -> FileTake:
    lines = read_text(path).splitlines()
    if not lines or not lines[0].startswith("PathFileType"):
        raise CaptureError(path, "not a TRC file: the first line does not start with 'PathFileType'")
    if len(lines) < 5:
        raise CaptureError(path, f"TRC header cut short: {len(lines)} lines, the header has 5")
    header = {key.strip(): value.strip() for key, value in zip(_fields(lines[1]), _fields(lines[2]))}

    names = [name.strip() for name in _fields(lines[3])[2:] if name.strip()]
    coordinate_labels = [label for label in _fields(lines[4]) if label.strip()]
    if not names:
        raise CaptureError(path, "no markers: the marker names row (line 4, after Frame# and Time) is empty")
    if len(coordinate_labels) != 3 * len(names):
        raise CaptureError(path, f"line 4 names {len(names)} markers but line 5 has {len(coordinate_labels)} "
                                 f"coordinate labels (X1 Y1 Z1 ...), not {3 * len(names)}")

    column_names = ["Frame#", "Time"] + [f"{name} {axis}" for name in names for axis in "XYZ"]
    rows = []
    for line_number, line in enumerate(lines[5:], start=6):
        if not line.strip():
            continue
        fields = _fields(line)
        if any(field.strip() for field in fields[len(column_names):]):
            raise CaptureError(path, f"line {line_number} has {len(fields)} fields; Frame#, Time and "
                                     f"{len(names)} markers make {len(column_names)}")
        numbers = parse_numbers(fields, column_names, path, f"line {line_number}")
        rows.append(numbers + [np.nan] * (len(column_names) - len(numbers)))
    table = np.array(rows, dtype=np.float64).reshape(len(rows), len(column_names))

    times = table[:, 1]
    return FileTake(
        marker_names=names,
        positions=table[:, 2:].reshape(len(rows), len(names), 3),
        units=header.get("Units") or None,
        frame_rate=_rate(header, path),
        times=times if np.isfinite(times).all() else None,
    )


def _rate(header: dict[str, str], path: Path) -> float | None:
    text = header.get("DataRate")
    if not text:
        return None
    try:
        return float(text)
    except ValueError:
        raise CaptureError(path, f"DataRate {text!r} is not a number") from None


def write(path: Path, names: list[str], positions: np.ndarray, units: str, frame_rate: float, times: np.ndarray):
    for name in names:
        if any(character in name for character in "\t\r\n"):
            raise CaptureError(path, f"marker name {name!r} has a tab or line break, which TRC can't hold")
    n_frames, n_markers = positions.shape[:2]
    rate = f"{frame_rate:.10g}"
    lines = [
        "\t".join(["PathFileType", "4", "(X/Y/Z)", path.name]),
        "\t".join(_HEADER_KEYS),
        "\t".join([rate, rate, str(n_frames), str(n_markers), units, rate, "1", str(n_frames)]),
        "\t".join(["Frame#", "Time"] + [f"{name}\t\t" for name in names]),
        "\t".join(["", ""] + [f"X{k}\tY{k}\tZ{k}" for k in range(1, n_markers + 1)]),
        "",  # OpenSim's writer leaves a blank line before the data
    ]
    for frame, (time, markers) in enumerate(zip(times, positions), start=1):
        values = ["" if np.isnan(value) else f"{value:.10g}" for value in markers.ravel()]
        lines.append("\t".join([str(frame), f"{time:.10g}"] + values))
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
