"""Playing an animation back on a model: one quasistatic equilibrium per frame, into a results
folder of the same kind as a fit's (``face_dolfinx.results.folder.FitFolder``), so that ``run.py
report`` and ``run.py video`` work on it.

Each frame is solved from the equilibrium of the frame before (the warm start of sifakis2005
section 9), written as soon as it is done (its displacement, then its record, each atomically),
and a rerun of the same playback resumes at the first frame not written, from the displacement
of the frame before as stored: the frames after it are then the same bytes as an uninterrupted
run's. The folder also holds ``animation.csv``, the animation played (``Animation.read`` takes
it, and the folder itself).

Markers: those of the fit the animation came from when it came from a fit folder (its marker
sites, and its captured markers as the reference of each frame's marker error), else the model's
marker sites (no capture: the errors are empty).
"""
from __future__ import annotations

import hashlib
import json
import logging
import math
import pathlib
import time
from dataclasses import dataclass, field

import numpy as np

from face_dolfinx.files import atomic_write
from face_dolfinx.fitting import FrameResult, MarkerSet
from face_dolfinx.parallel import on_rank_0
from face_dolfinx.physics.problem import FaceProblem
from face_dolfinx.results.folder import FitFolder, FitFolderError
from face_dolfinx.results.report import write_report
from face_dolfinx.results.xdmf import FileNodeOrder
from .animation import Animation

log = logging.getLogger(__name__)

ANIMATION_FILE = "animation.csv"
ALIGNMENT_FILE = "alignment.json"


@dataclass
class PlaybackMarkers:
    """Markers followed by a playback: material points on the skin plus offsets (model frame,
    turning with the head), their fit's roles, groups and neutral positions, and the captured
    positions per frame (frames, markers, 3; NaN for gaps) where a capture exists."""

    names: list[str]
    surface_points: np.ndarray
    offsets: np.ndarray
    captured: np.ndarray | None = None
    roles: list[str] | None = None
    groups: list | None = None
    neutral: np.ndarray | None = None

    @classmethod
    def of_model(cls, model) -> "PlaybackMarkers":
        """The model's marker sites, no capture."""
        names = list(model.markers)
        points = np.array([model.markers[n] for n in names], dtype=float).reshape(-1, 3)
        return cls(names, points, np.zeros_like(points))

    @classmethod
    def of_fit_folder(cls, path, animation: Animation) -> "PlaybackMarkers | None":
        """The markers of the fit (or playback) in ``path`` (its alignment.json), and its captured
        markers at the animation's frames; None if the folder does not record its marker sites."""
        folder = FitFolder(path)
        file = folder.path / ALIGNMENT_FILE
        if not file.is_file():
            return None
        sites = json.loads(file.read_text()).get("markers")
        if not sites or list(sites) != list(folder.marker_names):
            return None
        frames = [int(np.flatnonzero(folder.times == t)[0]) for t in animation.times]
        captured = np.array([folder.frame_markers(frame)[0] for frame in frames]).reshape(len(frames), -1, 3)
        return cls(list(folder.marker_names), np.array([sites[n]["skin_point"] for n in folder.marker_names]),
                   np.array([sites[n]["offset"] for n in folder.marker_names]),
                   captured if np.isfinite(captured).any() else None, list(folder.marker_roles),
                   list(folder.marker_groups), folder.neutral_markers)

    def alignment_record(self) -> dict:
        """What ``of_fit_folder`` reads back (alignment.json of a playback folder)."""
        return dict(method="playback", markers={name: dict(skin_point=p.tolist(), offset=o.tolist())
                                                for name, p, o in zip(self.names, self.surface_points, self.offsets)})


@dataclass
class PlaybackRun:
    """What one ``play`` did: the frames it solved (their Newton iterations and seconds)."""
    folder: FitFolder
    frames: list[int] = field(default_factory=list)
    newton_iterations: list[int] = field(default_factory=list)
    seconds: list[float] = field(default_factory=list)
    missing: list[int] = field(default_factory=list)

    @property
    def finished(self) -> bool:
        return not self.missing


def animation_digest(animation: Animation) -> str:
    """SHA-256 of the animation's CSV form: a resume must play the same numbers."""
    return hashlib.sha256(animation.csv_text().encode()).hexdigest()


def open_playback(model, animation: Animation, out, *, markers: PlaybackMarkers | None = None,
                  overwrite: bool = False, extra: dict | None = None) -> tuple[FitFolder, PlaybackMarkers]:
    """The results folder of playing ``animation`` on ``model`` at ``out``: new, or the unfinished
    one of the same playback to resume, or the finished one (``folder.finished``); another
    playback's or a fit's folder raises ``FitFolderError`` unless ``overwrite``. Collective.

    Every check of the input comes first: nothing is written for an animation the model cannot
    play (``AnimationError``).
    """
    animation.check(model)
    markers = markers if markers is not None else PlaybackMarkers.of_model(model)
    n = animation.n_frames
    settings = dict(kind="playback", animation=animation.source, animation_sha256=animation_digest(animation),
                    model=str(model.path), frames=n, intraoral_pressure=animation.has_pressure, **(extra or {}))
    neutral = markers.neutral
    take = dict(muscle_names=model.muscle_names, marker_names=markers.names,
                times=[float(t) for t in animation.times], take_frames=list(range(n)),
                marker_weights=[1.0] * len(markers.names),
                marker_roles=markers.roles or ["fitted"] * len(markers.names),
                marker_groups=markers.groups or [None] * len(markers.names),
                neutral_markers=None if neutral is None else
                [[None if not np.isfinite(v) else float(v) for v in p] for p in neutral])
    text, alignment = animation.csv_text(), json.dumps(markers.alignment_record(), indent=2)

    def prepare():
        folder, finished = FitFolder.prepare(out, settings, take, overwrite=overwrite)
        if not finished:
            atomic_write(folder.path / ANIMATION_FILE, text)
            atomic_write(folder.path / ALIGNMENT_FILE, alignment)
        return folder.path
    return FitFolder(on_rank_0(prepare, model.mesh.comm)), markers


def play(problem: FaceProblem, animation: Animation, folder: FitFolder, markers: PlaybackMarkers, *,
         stop_after: int | None = None, progress: bool = True, dynamic=None) -> PlaybackRun:
    """Solve the frames of ``animation`` that ``folder`` lacks, in order, each from the last
    equilibrium, writing each as it is done; then, if none is left, the tables and the report.
    ``stop_after``: solve at most that many frames. ``dynamic``: a ``DynamicFace`` of ``problem``
    (``FaceProblem.dynamics``): the first frame is the equilibrium of its controls, every later one
    is integrated in time from the frame before (inertia, damping; docs/dynamics.md); such a
    playback starts at its first frame (its velocities are not stored), and a time step that cannot
    converge raises ``DynamicsError`` with the frames before it written. Collective; rank 0 writes."""
    from tqdm import tqdm
    comm = problem.comm
    model = problem.model
    node_order = FileNodeOrder(problem.V)
    followed = MarkerSet(problem, markers.surface_points, markers.offsets, names=markers.names) \
        if markers.names else None
    missing = on_rank_0(folder.missing_frames, comm)
    todo = missing if stop_after is None else missing[:max(0, stop_after)]
    if dynamic is not None and todo and todo[0] != 0:
        raise FitFolderError(f"{folder.path}: a dynamic playback cannot resume at frame {todo[0]} (its velocities are "
                             f"not stored); --overwrite starts it again")
    run = PlaybackRun(folder)
    at = None  # the frame whose equilibrium the problem holds (None: rest)
    problem.reset_to_rest()
    hidden = None if progress and comm.rank == 0 else True
    with tqdm(total=len(todo), unit="frame", desc="simulate", dynamic_ncols=True, disable=hidden) as bar:
        for frame in todo:
            if frame > 0 and at != frame - 1:
                previous = on_rank_0(lambda f=frame - 1: _stored_displacement(folder, f), comm)
                if previous is not None:
                    problem.adopt(animation.frame_controls(frame - 1, model), node_order.scatter(previous))
                    log.info("resuming %s at frame %d from the stored equilibrium of frame %d", folder.path,
                             frame, frame - 1)
            controls = animation.frame_controls(frame, model)
            began = time.perf_counter()
            if dynamic is not None and frame > 0:
                report = dynamic.advance(float(animation.times[frame]), lambda t: animation.controls_at(t, model))
                flag = ""
            else:
                report = problem.solve(activations=controls.activations, cranium=controls.cranium, jaw=controls.jaw,
                                       pressure=controls.pressure if problem.has_pressure else None)
                flag = "" if report.load_steps == 1 else f"{report.load_steps} load steps"
                if dynamic is not None:
                    dynamic.start(float(animation.times[frame]))
            seconds = time.perf_counter() - began
            at = frame
            simulated = (followed.positions(problem.u.x.array, controls.cranium) if followed is not None
                         else np.zeros((0, 3)))
            captured = (markers.captured[frame] if markers.captured is not None
                        else np.full_like(simulated, np.nan))
            errors = np.linalg.norm(simulated - captured, axis=1)
            present = errors[np.isfinite(errors)]
            result = FrameResult(
                frame=frame, activations=controls.activations, cranium=controls.cranium, jaw=controls.jaw,
                jaw_tmj=None if animation.tmj is None else animation.tmj[frame].copy(),
                marker_errors=errors,
                rms_error=float(np.sqrt(np.mean(present ** 2))) if present.size else math.nan,
                max_error=float(present.max()) if present.size else math.nan,
                gn_steps=0, seconds=seconds, phases={"equilibrium": seconds}, flag=flag,
                pressure=controls.pressure)
            displacement = node_order.gather(problem.u.x.array)
            if comm.rank == 0:
                folder.write_frame(result, captured, simulated, displacement)
            run.frames.append(frame)
            run.newton_iterations.append(report.newton_iterations)
            run.seconds.append(seconds)
            log.debug("frame %d/%d (%.3f s): Newton %d its, %.3f s%s", frame + 1, animation.n_frames,
                      animation.times[frame], report.newton_iterations, seconds,
                      f", {report.substeps} time step(s)" if dynamic is not None and frame > 0 else "")
            bar.set_postfix_str(f"frame {frame}: {report.newton_iterations} Newton its, {seconds:.2f} s",
                                refresh=False)
            bar.update()
    comm.barrier()
    run.missing = on_rank_0(folder.missing_frames, comm)
    if not run.missing:
        on_rank_0(lambda: _finish(folder), comm)
    return run


def _stored_displacement(folder: FitFolder, frame: int) -> np.ndarray | None:
    try:
        return folder.displacement(frame)
    except FileNotFoundError:
        return None


def _finish(folder: FitFolder) -> None:
    folder.write_tables()
    write_report(folder.path)
    folder.mark_finished()


def animation_and_markers(source) -> tuple[Animation, PlaybackMarkers | None]:
    """The animation in ``source`` (a file or a results folder) and, for a results folder, its
    markers and capture (``PlaybackMarkers.of_fit_folder``)."""
    animation = Animation.read(source)
    markers = PlaybackMarkers.of_fit_folder(source, animation) if pathlib.Path(source).is_dir() else None
    return animation, markers
