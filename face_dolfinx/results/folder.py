"""Fit results on disk, one frame at a time, so that a killed run loses nothing and resumes
exactly where it stopped.

Layout of a fit folder:
  run.json          the settings of the run (a rerun must match them to resume)
  take.json         what the frames are: muscle and marker names, frame times and the take's own
                    frame numbers; each marker's role (fitted, validation, ignored) and group,
                    and the neutral frame's markers in model coordinates
  truth.npz         the truth of a synthetic take, copied from beside the capture (if known)
  run.log           the log of every run that wrote here
  frames/000123.displacement.npy   the frame's equilibrium displacement at the mesh file's nodes
  frames/000123.json               the frame's controls, errors, captured and simulated markers;
                                   written last and atomically: it existing means the frame is done
  checkpoint/000123.npz            the fitter's warm-start state after frame 123 (resume)
  activations.csv   frame, time, one column per muscle            } written when every frame is
  kinematics.csv    head rotation (row-major), translation, jaw   } done, from the frame files;
  marker_errors.csv frame, one column per marker (mm, empty = gap) } the same bytes however many
  frames.csv        per frame: RMS/max error, GN steps, flags;     } ranks, chunks or resumes
                    per role: RMS error, non-rigid motion, the fraction of it explained
  accuracy.json     the take's accuracy by role, group and marker, muscles pinned at 1 (results.accuracy)
  timings.csv       per frame: seconds, split by phase (these differ from run to run)
  face.xdmf, *.png, renders/   the report (face_dolfinx.results.report)
While a run is unfinished the folder holds ``IN_PROGRESS``; it is removed last, with the
checkpoints (only a resume needs them).

Checkpoints are stored in the mesh file's node order, so a run killed under ``mpirun -n 4`` can
be resumed with any number of ranks; with the same number it continues bit for bit.
"""
import csv
import io
import json
import pathlib
import shutil

import numpy as np

from face_dolfinx.model.bones import AffineMap
from face_dolfinx.fitting import ControlState, FitCheckpoint, FrameResult
from face_dolfinx.physics.problem import Controls
from face_dolfinx.capture.synthetic import load_truth
from face_dolfinx.files import atomic_write
from . import accuracy

IN_PROGRESS = "IN_PROGRESS"
RUN_FILE, TAKE_FILE, TRUTH_FILE, ACCURACY_FILE = "run.json", "take.json", "truth.npz", "accuracy.json"


class FitFolderError(FileExistsError):
    """The output folder holds something a fit must not replace or resume."""


def frame_to_dict(result: FrameResult) -> dict:
    return dict(
        frame=result.frame, activations=result.activations.tolist(),
        cranium_matrix=result.cranium.matrix.tolist(), cranium_translation=result.cranium.translation.tolist(),
        jaw_matrix=result.jaw.matrix.tolist(), jaw_translation=result.jaw.translation.tolist(),
        jaw_tmj=None if result.jaw_tmj is None else result.jaw_tmj.tolist(),
        marker_errors=_nullable(result.marker_errors),
        rms_error=result.rms_error, max_error=result.max_error, initial_rms=result.initial_rms,
        gn_steps=result.gn_steps, seconds=result.seconds, phases=result.phases, flag=result.flag,
        observability=_nullable([result.observability])[0], unobservable=result.unobservable,
        pressure=result.pressure)


def frame_from_dict(data: dict) -> FrameResult:
    return FrameResult(
        frame=data["frame"], activations=np.array(data["activations"]),
        cranium=AffineMap(data["cranium_matrix"], data["cranium_translation"]),
        jaw=AffineMap(data["jaw_matrix"], data["jaw_translation"]),
        jaw_tmj=None if data["jaw_tmj"] is None else np.array(data["jaw_tmj"]),
        marker_errors=_from_nullable(data["marker_errors"]),
        rms_error=data["rms_error"], max_error=data["max_error"], gn_steps=data["gn_steps"],
        seconds=data["seconds"], phases=data["phases"], flag=data["flag"],
        initial_rms=data["initial_rms"],
        # frame records written before the observability check have neither
        observability=float(_from_nullable([data.get("observability")])[0]),
        unobservable=data.get("unobservable", []),
        pressure=data.get("pressure", 0.0))  # frame records of fits without that control


def _nullable(values: np.ndarray) -> list:
    """An array as nested lists with NaN as null (JSON has no NaN); floats keep every bit."""
    values = np.asarray(values, dtype=float)
    if values.ndim == 1:
        return [float(v) if np.isfinite(v) else None for v in values]
    return [_nullable(v) if np.all(np.isfinite(v)) else None for v in values]


def _from_nullable(values: list, width: int | None = None) -> np.ndarray:
    """The inverse of ``_nullable``: values (n,) or rows (n, width), null as NaN."""
    if width is None:
        return np.array([np.nan if v is None else v for v in values], dtype=float)
    return np.array([[np.nan] * width if v is None else v for v in values], dtype=float).reshape(-1, width)


# Settings that a run.json lacks when its fit ran before the software recorded them. A record
# without "contact" fitted without contact, one without "krylov" without Krylov; one without
# "contact_surfaces" and with no contact touched nothing (with contact on it does not say what
# touched what: it stays unset).
ABSENT_SETTINGS = {"contact": False, "krylov": False, "contact_surfaces": []}


def _completed(record: dict, other: dict) -> dict:
    """``record`` with the settings that ``other`` has and it lacks, as far as their absence tells
    them (``ABSENT_SETTINGS``)."""
    record = dict(record)
    for key in ("contact", "krylov"):
        if key in other:
            record.setdefault(key, ABSENT_SETTINGS[key])
    if "contact_surfaces" in other and record.get("contact") is False:
        record.setdefault("contact_surfaces", ABSENT_SETTINGS["contact_surfaces"])
    return record


def settings_differences(before: dict, now: dict) -> list[str]:
    """'name: before there, now now' for every setting that differs (JSON values compared); the
    settings one side lacks are what their absence means (``_completed``)."""
    before, now = json.loads(json.dumps(before)), json.loads(json.dumps(now))
    before, now = _completed(before, now), _completed(now, before)
    return [f"{key}: {before.get(key, '(not set)')!r} there, {now.get(key, '(not set)')!r} now"
            for key in sorted(set(before) | set(now)) if before.get(key) != now.get(key)]


class FitFolder:
    """The result folder of one fit. Rank 0 writes; every rank may read."""

    def __init__(self, path):
        self.path = pathlib.Path(path)
        self.frames_dir = self.path / "frames"
        self.checkpoint_dir = self.path / "checkpoint"
        if not (self.path / RUN_FILE).is_file():
            raise FileNotFoundError(f"{self.path} is not a fit results folder (no {RUN_FILE})")
        self.settings = json.loads((self.path / RUN_FILE).read_text())
        take = json.loads((self.path / TAKE_FILE).read_text())
        self.muscle_names, self.marker_names = take["muscle_names"], take["marker_names"]
        self.times = np.array(take["times"], dtype=float)
        # The take's own frame numbers (a fit of part of a take), each marker's role in the fit
        # (accuracy.ROLES) and group, and the neutral frame's markers in model coordinates.
        self.take_frames = np.array(take.get("take_frames", range(len(self.times))), dtype=int)
        self.marker_weights = np.array(take.get("marker_weights", [1.0] * len(self.marker_names)), dtype=float)
        self.marker_roles = take.get("marker_roles", ["fitted"] * len(self.marker_names))
        self.marker_groups = take.get("marker_groups", [None] * len(self.marker_names))
        neutral = take.get("neutral_markers")
        self.neutral_markers = None if neutral is None else _from_nullable(neutral, 3)

    @classmethod
    def prepare(cls, path, settings: dict, take: dict, truth_file=None,
                overwrite: bool = False) -> tuple["FitFolder", bool]:
        """The folder for a fit with ``settings``; True if it already holds that fit, finished.

        A new folder is created. A rerun with the same settings resumes an unfinished folder.
        Anything else is refused, naming the settings that differ, unless ``overwrite``; a
        non-empty folder that is no fit result is never replaced.
        """
        path = pathlib.Path(path)
        if path.exists():
            run_file = path / RUN_FILE
            if not run_file.is_file():
                if any(path.iterdir()):
                    raise FitFolderError(f"{path} exists and is not a fit results folder (no {RUN_FILE}); "
                                         f"choose another --out")
            else:
                finished = not (path / IN_PROGRESS).exists()
                differences = settings_differences(json.loads(run_file.read_text()), settings)
                state = "a finished fit" if finished else "an unfinished fit"
                if overwrite:
                    shutil.rmtree(path)
                elif differences:
                    raise FitFolderError(f"{path} holds {state} with other settings ({'; '.join(differences)}); "
                                         f"pass --overwrite to replace it or choose another --out")
                elif finished:
                    return cls(path), True
        (path / "frames").mkdir(parents=True, exist_ok=True)
        (path / IN_PROGRESS).touch()
        atomic_write(path / RUN_FILE, json.dumps(settings, indent=2))
        atomic_write(path / TAKE_FILE, json.dumps(take))
        if truth_file is not None:
            atomic_write(path / TRUTH_FILE, pathlib.Path(truth_file).read_bytes())
        return cls(path), False

    @property
    def finished(self) -> bool:
        return not (self.path / IN_PROGRESS).exists()

    def truth(self):
        """The truth of the fitted frames (``TakeTruth``, indexed like them), None if unknown."""
        return load_truth(self.truth_file).select(self.take_frames) if self.truth_file else None

    @property
    def truth_file(self) -> pathlib.Path | None:
        file = self.path / TRUTH_FILE
        return file if file.is_file() else None

    # -- frames -------------------------------------------------------------------------------
    def _frame_file(self, frame: int, suffix: str) -> pathlib.Path:
        return self.frames_dir / f"{frame:06d}{suffix}"

    def finished_frames(self) -> dict[int, FrameResult]:
        done = {}
        for file in sorted(self.frames_dir.glob("*.json")):
            result = frame_from_dict(json.loads(file.read_text()))
            done[result.frame] = result
        return done

    def missing_frames(self) -> list[int]:
        done = {int(file.stem) for file in self.frames_dir.glob("*.json")}
        return [frame for frame in range(len(self.times)) if frame not in done]

    def write_frame(self, result: FrameResult, captured: np.ndarray, simulated: np.ndarray,
                    displacement: np.ndarray) -> None:
        """One finished frame: its displacement (file node order) first, then the record that
        says the frame is done."""
        atomic_write(self._frame_file(result.frame, ".displacement.npy"),
                      lambda handle: np.save(handle, displacement))
        record = frame_to_dict(result)
        record.update(captured_markers=_nullable(captured), simulated_markers=_nullable(simulated))
        atomic_write(self._frame_file(result.frame, ".json"), json.dumps(record))

    def frame_markers(self, frame: int) -> tuple[np.ndarray, np.ndarray]:
        """Captured (NaN rows for gaps) and simulated marker positions (markers, 3) of a frame."""
        record = json.loads(self._frame_file(frame, ".json").read_text())
        return (_from_nullable(record["captured_markers"], 3),
                _from_nullable(record["simulated_markers"], 3))

    def displacement(self, frame: int) -> np.ndarray:
        """The frame's equilibrium displacement (file nodes, 3)."""
        return np.load(self._frame_file(frame, ".displacement.npy"))

    # -- checkpoints --------------------------------------------------------------------------
    def save_checkpoint(self, frame: int, checkpoint: FitCheckpoint, node_order) -> None:
        """Store the warm-start state after ``frame`` (collective over the fitter's ranks;
        ``node_order`` is the problem's ``output.FileNodeOrder``)."""
        displacement = node_order.gather(checkpoint.displacement)
        has_jacobian = checkpoint.jacobian_state is not None
        jacobian_dofs = node_order.gather(checkpoint.jacobian_dofs) if has_jacobian else None
        if node_order.comm.rank != 0:
            return
        arrays = dict(frame=frame, frames_done=checkpoint.frames_done, displacement=displacement,
                      **_state_arrays("state", checkpoint.state),
                      **_controls_arrays("problem", checkpoint.problem_controls))
        if checkpoint.previous_activations is not None:
            arrays["previous_activations"] = checkpoint.previous_activations
        if has_jacobian:
            arrays.update(jacobian_dofs=jacobian_dofs, jacobian_markers=checkpoint.jacobian_markers,
                          **_state_arrays("jacobian_state", checkpoint.jacobian_state))
        self.checkpoint_dir.mkdir(exist_ok=True)
        atomic_write(self.checkpoint_dir / f"{frame:06d}.npz", lambda handle: np.savez(handle, **arrays))

    def load_checkpoint(self, frame: int, node_order) -> FitCheckpoint | None:
        """The state saved after ``frame`` on this rank's part of the mesh, None if there is
        none. Every rank reads the file."""
        file = self.checkpoint_dir / f"{frame:06d}.npz"
        if not file.is_file():
            return None
        with np.load(file) as data:
            has_jacobian = "jacobian_dofs" in data
            return FitCheckpoint(
                state=_state_from_arrays("state", data),
                previous_activations=data["previous_activations"] if "previous_activations" in data else None,
                frames_done=int(data["frames_done"]),
                displacement=node_order.scatter(data["displacement"]),
                problem_controls=_controls_from_arrays("problem", data),
                jacobian_state=_state_from_arrays("jacobian_state", data) if has_jacobian else None,
                jacobian_dofs=node_order.scatter(data["jacobian_dofs"]) if has_jacobian else None,
                jacobian_markers=data["jacobian_markers"] if has_jacobian else None)

    def drop_checkpoint(self, frame: int) -> None:
        (self.checkpoint_dir / f"{frame:06d}.npz").unlink(missing_ok=True)

    # -- the end ------------------------------------------------------------------------------
    def write_tables(self) -> None:
        """The CSV tables from the frame files (with errors against the truth if known)."""
        results = [r for _, r in sorted(self.finished_frames().items())]
        truth = self.truth()
        times = self.times
        atomic_write(self.path / "activations.csv", _table(
            ["frame", "time_s"] + list(self.muscle_names),
            [[r.frame, times[r.frame], *r.activations] for r in results]))
        atomic_write(self.path / "kinematics.csv", _table(
            ["frame", "time_s"] + [f"cranium_M{i}{j}" for i in range(3) for j in range(3)]
            + ["cranium_tx", "cranium_ty", "cranium_tz"]
            + [f"jaw_M{i}{j}" for i in range(3) for j in range(3)] + ["jaw_tx", "jaw_ty", "jaw_tz"]
            + ["jaw_opening_rad", "jaw_slide_right_mm", "jaw_slide_left_mm", "intraoral_pressure_kpa"],
            [[r.frame, times[r.frame], *r.cranium.matrix.reshape(-1), *r.cranium.translation,
              *r.jaw.matrix.reshape(-1), *r.jaw.translation,
              *(r.jaw_tmj if r.jaw_tmj is not None else [np.nan] * 3), r.pressure] for r in results]))
        atomic_write(self.path / "marker_errors.csv", _table(
            ["frame"] + list(self.marker_names), [[r.frame, *r.marker_errors] for r in results]))
        columns = ["frame", "rms_error_mm", "max_error_mm", "initial_rms_mm", "gn_steps"]
        rows = [[r.frame, r.rms_error, r.max_error, r.initial_rms, r.gn_steps] for r in results]
        if truth is not None:
            columns += ["activation_error_max", "jaw_error_max"]
            for row, r in zip(rows, results):
                row += [float(np.abs(r.activations - truth.activations[r.frame]).max()),
                        float(np.abs(r.jaw_tmj - truth.tmj[r.frame]).max()) if r.jaw_tmj is not None else np.nan]
        columns.append("take_frame")
        for row, r in zip(rows, results):
            row.append(self.take_frames[r.frame])
        measures = self.motion_measures(results)
        if measures is not None:
            for role in ("fitted", "validation"):
                markers = np.array(self.marker_roles) == role
                if markers.any():
                    columns += [f"{role}_rms_mm", f"{role}_non_rigid_mm", f"{role}_explained"]
                    per_frame = measures.per_frame(markers)
                    for i, row in enumerate(rows):
                        row += [per_frame["rms_mm"][i], per_frame["non_rigid_mm"][i], per_frame["explained"][i]]
            record = accuracy.summary(measures, self.marker_names, self.marker_roles, self.marker_groups)
            record["pinned_muscles"] = accuracy.pinned_stretches(
                np.array([r.activations for r in results]), times[[r.frame for r in results]], self.muscle_names)
            atomic_write(self.path / ACCURACY_FILE, json.dumps(record, indent=2))
        columns += ["observability", "unobservable", "flag"]  # free text last
        for row, r in zip(rows, results):
            row += [r.observability, " ".join(r.unobservable), r.flag]
        atomic_write(self.path / "frames.csv", _table(columns, rows))
        phases = ("sensitivities", "gn_solve", "equilibrium", "line_search")
        atomic_write(self.path / "timings.csv", _table(
            ["frame", "seconds"] + [f"{phase}_s" for phase in phases],
            [[r.frame, r.seconds, *(r.phases.get(phase, 0.0) for phase in phases)] for r in results]))

    def motion_measures(self, results: list[FrameResult] | None = None) -> accuracy.MotionMeasures | None:
        """Errors and non-rigid motion of every marker in the fitted frames (in frame order), None
        for a folder that does not know its neutral markers."""
        if self.neutral_markers is None:
            return None
        frames = [r.frame for r in results] if results is not None else sorted(self.finished_frames())
        captured, simulated = zip(*(self.frame_markers(frame) for frame in frames)) if frames else ((), ())
        shape = (len(frames), len(self.marker_names), 3)
        return accuracy.MotionMeasures.of(self.neutral_markers, np.reshape(captured, shape),
                                          np.reshape(simulated, shape))

    def accuracy(self) -> dict | None:
        """The accuracy record of a finished fit (``accuracy.summary``), None if it has none."""
        file = self.path / ACCURACY_FILE
        return json.loads(file.read_text()) if file.is_file() else None

    def mark_finished(self) -> None:
        """Drop the checkpoints (only a resume needs them), then the IN_PROGRESS mark."""
        shutil.rmtree(self.checkpoint_dir, ignore_errors=True)
        (self.path / IN_PROGRESS).unlink(missing_ok=True)


def _map_arrays(prefix: str, frame: AffineMap) -> dict:
    return {f"{prefix}_matrix": frame.matrix, f"{prefix}_translation": frame.translation}


def _map_from_arrays(prefix: str, data) -> AffineMap:
    return AffineMap(data[f"{prefix}_matrix"], data[f"{prefix}_translation"])


def _state_arrays(prefix: str, state: ControlState) -> dict:
    arrays = {f"{prefix}_mode": np.array(state.mode), f"{prefix}_activations": state.activations,
              **_map_arrays(f"{prefix}_cranium", state.cranium), **_map_arrays(f"{prefix}_jaw", state.jaw),
              f"{prefix}_pressure": np.array(state.pressure)}
    if state.tmj is not None:
        arrays[f"{prefix}_tmj"] = state.tmj
    return arrays


def _state_from_arrays(prefix: str, data) -> ControlState:
    return ControlState(str(data[f"{prefix}_mode"]), data[f"{prefix}_activations"],
                        _map_from_arrays(f"{prefix}_cranium", data), _map_from_arrays(f"{prefix}_jaw", data),
                        data[f"{prefix}_tmj"] if f"{prefix}_tmj" in data else None,
                        float(data[f"{prefix}_pressure"]))


def _controls_arrays(prefix: str, controls: Controls) -> dict:
    return {f"{prefix}_activations": controls.activations, f"{prefix}_pressure": np.array(controls.pressure),
            **_map_arrays(f"{prefix}_cranium", controls.cranium), **_map_arrays(f"{prefix}_jaw", controls.jaw)}


def _controls_from_arrays(prefix: str, data) -> Controls:
    return Controls(data[f"{prefix}_activations"], _map_from_arrays(f"{prefix}_cranium", data),
                    _map_from_arrays(f"{prefix}_jaw", data), float(data[f"{prefix}_pressure"]))


def _table(header, rows) -> str:
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(header)
    for row in rows:
        writer.writerow(["" if isinstance(v, float) and not np.isfinite(v) else
                         (f"{v:.9g}" if isinstance(v, (float, np.floating)) else v) for v in row])
    return buffer.getvalue()
