"""Fit results on disk, one frame at a time, so that a killed run loses nothing and resumes.

Layout of a fit folder:
  run.json              the settings of the run (a rerun must match them to resume)
  frames/000123.json    one finished frame, written atomically (temporary file + rename)
  activations.csv       frame, time, one column per muscle            } written when the run
  kinematics.csv        head rotation (row-major), translation, jaw   } completes, from the
  marker_errors.csv     frame, one column per marker (mm, empty = gap) } frame files, atomically
  frames.csv            per frame: RMS/max error, GN steps, seconds, phases, flag
While a run is unfinished the folder holds ``IN_PROGRESS``; it is removed last.
"""
import csv
import io
import json
import os
import pathlib

import numpy as np

from .bones import AffineMap
from .fitting import FrameResult

IN_PROGRESS = "IN_PROGRESS"


def atomic_write_text(path: pathlib.Path, text: str) -> None:
    temporary = path.with_name(f".{path.name}.tmp")
    with open(temporary, "w") as handle:
        handle.write(text)
        handle.flush()
        os.fsync(handle.fileno())
    os.replace(temporary, path)


def frame_to_dict(result: FrameResult) -> dict:
    return dict(
        frame=result.frame, activations=result.activations.tolist(),
        cranium_matrix=result.cranium.matrix.tolist(), cranium_translation=result.cranium.translation.tolist(),
        jaw_matrix=result.jaw.matrix.tolist(), jaw_translation=result.jaw.translation.tolist(),
        jaw_tmj=None if result.jaw_tmj is None else result.jaw_tmj.tolist(),
        marker_errors=[None if not np.isfinite(e) else float(e) for e in result.marker_errors],
        rms_error=result.rms_error, max_error=result.max_error, initial_rms=result.initial_rms,
        gn_steps=result.gn_steps, seconds=result.seconds, phases=result.phases, flag=result.flag)


def frame_from_dict(data: dict) -> FrameResult:
    return FrameResult(
        frame=data["frame"], activations=np.array(data["activations"]),
        cranium=AffineMap(data["cranium_matrix"], data["cranium_translation"]),
        jaw=AffineMap(data["jaw_matrix"], data["jaw_translation"]),
        jaw_tmj=None if data["jaw_tmj"] is None else np.array(data["jaw_tmj"]),
        marker_errors=np.array([np.nan if e is None else e for e in data["marker_errors"]]),
        rms_error=data["rms_error"], max_error=data["max_error"], gn_steps=data["gn_steps"],
        seconds=data["seconds"], phases=data["phases"], flag=data["flag"],
        initial_rms=data["initial_rms"])


class FitFolder:
    """The result folder of one fit (rank 0 writes; every rank may read)."""

    def __init__(self, path, settings: dict, overwrite: bool = False):
        self.path = pathlib.Path(path)
        self.frames_dir = self.path / "frames"
        self.settings = settings
        run_file = self.path / "run.json"
        if self.path.exists():
            previous = json.loads(run_file.read_text()) if run_file.exists() else None
            resumable = (self.path / IN_PROGRESS).exists() and previous == settings
            if not resumable and not overwrite:
                reason = ("it holds a finished run" if not (self.path / IN_PROGRESS).exists()
                          else "it holds an unfinished run with other settings")
                raise FileExistsError(f"{self.path} already exists and {reason}; pass --overwrite to "
                                      f"replace it")
            if not resumable:
                for child in sorted(self.path.rglob("*"), reverse=True):
                    child.unlink() if child.is_file() else child.rmdir()
        self.frames_dir.mkdir(parents=True, exist_ok=True)
        (self.path / IN_PROGRESS).touch()
        atomic_write_text(run_file, json.dumps(settings, indent=2))

    def finished_frames(self) -> dict[int, FrameResult]:
        done = {}
        for file in sorted(self.frames_dir.glob("*.json")):
            result = frame_from_dict(json.loads(file.read_text()))
            done[result.frame] = result
        return done

    def write_frame(self, result: FrameResult) -> None:
        atomic_write_text(self.frames_dir / f"{result.frame:06d}.json", json.dumps(frame_to_dict(result)))

    def finish(self, muscle_names, marker_names, times, truth=None) -> None:
        """Write the CSV tables from the frame files, then mark the run complete."""
        results = [r for _, r in sorted(self.finished_frames().items())]
        atomic_write_text(self.path / "activations.csv", _table(
            ["frame", "time_s"] + list(muscle_names),
            [[r.frame, times[r.frame], *r.activations] for r in results]))
        atomic_write_text(self.path / "kinematics.csv", _table(
            ["frame", "time_s"] + [f"cranium_M{i}{j}" for i in range(3) for j in range(3)]
            + ["cranium_tx", "cranium_ty", "cranium_tz"]
            + [f"jaw_M{i}{j}" for i in range(3) for j in range(3)] + ["jaw_tx", "jaw_ty", "jaw_tz"]
            + ["jaw_opening_rad", "jaw_slide_right_mm", "jaw_slide_left_mm"],
            [[r.frame, times[r.frame], *r.cranium.matrix.reshape(-1), *r.cranium.translation,
              *r.jaw.matrix.reshape(-1), *r.jaw.translation,
              *(r.jaw_tmj if r.jaw_tmj is not None else [np.nan] * 3)] for r in results]))
        atomic_write_text(self.path / "marker_errors.csv", _table(
            ["frame"] + list(marker_names), [[r.frame, *r.marker_errors] for r in results]))
        columns = ["frame", "rms_error_mm", "max_error_mm", "initial_rms_mm", "gn_steps", "seconds",
                   "sensitivities_s", "gn_solve_s", "equilibrium_s", "line_search_s"]
        rows = [[r.frame, r.rms_error, r.max_error, r.initial_rms, r.gn_steps, r.seconds,
                 *(r.phases.get(k, 0.0) for k in ("sensitivities", "gn_solve", "equilibrium", "line_search"))]
                for r in results]
        if truth is not None:
            columns += ["activation_error_max", "jaw_error_max"]
            for row, r in zip(rows, results):
                row += [float(np.abs(r.activations - truth.activations[r.frame]).max()),
                        float(np.abs(r.jaw_tmj - truth.tmj[r.frame]).max()) if r.jaw_tmj is not None else np.nan]
        columns.append("flag")
        for row, r in zip(rows, results):
            row.append(r.flag)
        atomic_write_text(self.path / "frames.csv", _table(columns, rows))
        (self.path / IN_PROGRESS).unlink(missing_ok=True)


def _table(header, rows) -> str:
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(header)
    for row in rows:
        writer.writerow(["" if isinstance(v, float) and not np.isfinite(v) else
                         (f"{v:.9g}" if isinstance(v, (float, np.floating)) else v) for v in row])
    return buffer.getvalue()
