"""C3D files, read and written with ezc3d.

Markers are the POINT group's points, labelled by POINT:LABELS (continued in LABELS2, LABELS3, ...
past 255 points). Points that C3D producers list as model outputs (POINT:ANGLES, FORCES, MOMENTS,
POWERS, SCALARS, REACTIONS) are not markers and are left out. ezc3d gives NaN for a point whose
residual is negative (the C3D mark of an invalid sample); the writer marks gaps that way too.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from face_dolfinx.files import AtomicFile
from ._capture import CaptureError
from ._take import FileTake

_MODEL_OUTPUT_GROUPS = ("ANGLES", "FORCES", "MOMENTS", "POWERS", "SCALARS", "REACTIONS")


def _ezc3d(path: Path, action: str):
    try:
        import ezc3d
    except ImportError:
        raise CaptureError(path, f"{action} C3D needs the ezc3d package (pip install ezc3d)") from None
    return ezc3d


def _values(point_group: dict, name: str) -> list:
    return list(point_group[name]["value"]) if name in point_group else []


def read(path: Path) -> FileTake:
    ezc3d = _ezc3d(path, "reading")
    try:
        c3d = ezc3d.c3d(str(path))
    except (OSError, RuntimeError, ValueError) as error:
        raise CaptureError(path, f"not a readable C3D file ({error})") from error
    point_group = c3d["parameters"]["POINT"]

    labels = _values(point_group, "LABELS")
    continuation = 2
    while f"LABELS{continuation}" in point_group:
        labels += _values(point_group, f"LABELS{continuation}")
        continuation += 1
    points = c3d["data"]["points"]  # (4, n_points, n_frames): x, y, z, 1
    labels = labels[: points.shape[1]]  # LABELS may be padded past the points actually stored
    model_outputs = {label for group in _MODEL_OUTPUT_GROUPS for label in _values(point_group, group)}
    markers = [index for index, label in enumerate(labels) if label not in model_outputs]

    units = _values(point_group, "UNITS")
    rates = _values(point_group, "RATE")
    rate = float(rates[0]) if rates else float(c3d["header"]["points"]["frame_rate"])
    return FileTake(
        marker_names=[labels[index] for index in markers],
        positions=points[:3, markers, :].transpose(2, 1, 0),
        units=units[0].strip() if units and units[0].strip() else None,
        frame_rate=rate if rate > 0 else None,
        times=None,
    )


def write(path: Path, names: list[str], positions: np.ndarray, units: str, frame_rate: float, times: np.ndarray):
    """A float C3D with POINT:RATE, LABELS and UNITS; gaps get residual -1 and zero coordinates."""
    ezc3d = _ezc3d(path, "writing")
    n_frames, n_markers = positions.shape[:2]
    c3d = ezc3d.c3d()
    c3d["parameters"]["POINT"]["RATE"]["value"] = [frame_rate]
    c3d["parameters"]["POINT"]["LABELS"]["value"] = list(names)
    c3d["parameters"]["POINT"]["UNITS"]["value"] = [units]
    gap = np.isnan(positions).any(axis=2).T  # (n_markers, n_frames)
    points = np.ones((4, n_markers, n_frames))
    points[:3] = np.nan_to_num(positions.transpose(2, 1, 0), nan=0.0)
    c3d["data"]["points"] = points
    c3d["data"]["meta_points"] = {
        "residuals": np.where(gap, -1.0, 0.0)[np.newaxis],
        "camera_masks": np.zeros((7, n_markers, n_frames), dtype=bool),
    }
    # Whole or not at all; the temporary name ends in ".c3d", as ezc3d appends it to any other.
    with AtomicFile(path, suffix=".c3d") as temporary:
        c3d.write(str(temporary))
