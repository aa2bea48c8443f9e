"""What every format reader returns, and the text handling that the TRC and CSV readers share."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ._capture import CaptureError


@dataclass
class FileTake:
    """A take as its file holds it: the file's units and axes, NaN where the file has no sample.

    ``units``, ``frame_rate`` and ``times`` are None where the file doesn't say; the caller's
    options and defaults fill them in (``read_capture``).
    """

    marker_names: list[str]
    positions: np.ndarray  # (n_frames, n_markers, 3)
    units: str | None
    frame_rate: float | None  # Hz
    times: np.ndarray | None  # (n_frames,) s


def read_text(path: Path) -> str:
    # utf-8-sig drops the byte-order mark that spreadsheet programs put before the first header.
    try:
        return path.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError as error:
        raise CaptureError(path, f"not a text file (byte {error.start} is not UTF-8)") from error


def parse_numbers(fields: list[str], column_names: list[str], path: Path, where: str) -> list[float]:
    """Floats of one data row; an empty field is a gap (NaN), as is "nan" in any case."""
    numbers = []
    for text, column in zip(fields, column_names):
        if not text.strip():
            numbers.append(np.nan)
            continue
        try:
            numbers.append(float(text))
        except ValueError:
            raise CaptureError(path, f"{where}, column {column}: {text.strip()!r} is not a number") from None
    return numbers
