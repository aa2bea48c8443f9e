"""The frame loop of a take: the one that ``run.py fit``, the benchmarks and Python scripts run.

``track`` fits frames in order, each warm-started from the last (sifakis2005 section 9), with any
fitter that has ``fit_frame``. ``Tracker`` is the production loop around it: every frame written to
a fit folder as soon as it is done, with the checkpoint the next frame starts from, so that a killed
run resumes bit for bit; the take optionally split into chunks that start from rest, shared out over
groups of MPI ranks (each group fits whole chunks on its own copy of the mesh); the tables and report
once every frame is done.
"""
from __future__ import annotations

from dataclasses import dataclass, field
import functools
import json
import logging
import pathlib

import numpy as np

from face_dolfinx.capture import Capture, chunk_ranges
from face_dolfinx.fitting import FaceFitter, FrameResult, MarkerSet
from face_dolfinx.model.folder import load_model
from face_dolfinx.parallel import on_rank_0
from face_dolfinx.physics.problem import FaceProblem
from face_dolfinx.files import atomic_write
from face_dolfinx.results.folder import FitFolder
from face_dolfinx.results.report import write_report
from face_dolfinx.results.xdmf import FileNodeOrder
from .markers import MarkerSetup
from .settings import PRESETS, TrackingSettings

log = logging.getLogger(__name__)


def track(fitter, positions: np.ndarray, frames=None, on_frame=None) -> list[FrameResult]:
    """Fit ``frames`` of ``positions`` (frames, markers, 3) in order, each warm-started from the
    last; ``on_frame(result)`` is called as soon as a frame is done (e.g. to write it to disk)."""
    frames = range(len(positions)) if frames is None else frames
    results = []
    for frame in frames:
        result = fitter.fit_frame(positions[frame], frame=frame)
        results.append(result)
        if on_frame is not None:
            on_frame(result)
    return results


@dataclass
class TrackingRun:
    """What one ``Tracker.run`` did: the frames this rank group fitted, and what is left."""
    folder: FitFolder
    results: list[FrameResult] = field(default_factory=list)
    missing: list[int] = field(default_factory=list)  # frames of the take still to fit, every group's

    @property
    def finished(self) -> bool:
        return not self.missing


class Tracker:
    """Tracks takes on ``model`` with ``settings`` (``PRESETS["default"]``, ``PRESETS["fast"]``, ...).

    ``rank_groups`` > 1 splits the model's communicator into that many groups of ranks, each
    fitting whole chunks of a take on its own copy of the mesh (``open_folder(chunks=...)``). The
    problem (spaces, compiled forms, solver) is built on first use and kept for every take tracked;
    ``problem_options`` are further ``FaceProblem`` keywords (e.g. ``petsc_options``, ``degree``);
    they take the place of the settings' own (e.g. ``lip_contact``, the lips' barrier).
    """

    def __init__(self, model, settings: TrackingSettings = PRESETS["default"], *, rank_groups: int = 1,
                 problem_options: dict | None = None):
        comm = model.mesh.comm
        if not 1 <= rank_groups <= comm.size:
            raise ValueError(f"rank_groups = {rank_groups}: give 1 to {comm.size} (the number of ranks)")
        self.model, self.settings, self.comm = model, settings, comm
        self.rank_groups, self.problem_options = rank_groups, dict(problem_options or {})
        self.group = comm.rank * rank_groups // comm.size
        self.group_comm = comm.Split(self.group, comm.rank) if rank_groups > 1 else comm
        self._problem = None

    @property
    def problem(self) -> FaceProblem:
        """This rank group's ``FaceProblem``."""
        if self._problem is None:
            model = load_model(self.model.path, self.group_comm) if self.rank_groups > 1 else self.model
            if self.settings.contact and not model.teeth and self.comm.rank == 0:
                log.warning("model %s has no teeth ([teeth] in its model.toml): contact holds the lips on each "
                            "other only", model.path)
            self._problem = FaceProblem(model, **{**self.settings.problem_options(model), **self.problem_options})
        return self._problem

    def record(self, capture: Capture, placement, *, chunks: int = 1, extra: dict | None = None) -> dict:
        """The settings a fit folder stores and compares on resume (``run.json``)."""
        source = capture.source
        return dict(capture=str(pathlib.Path(source).resolve()) if source else None, model=str(self.model.path),
                    **self.settings.record(), contact_surfaces=list(self.settings.contact_surfaces(self.model)),
                    frames=capture.n_frames, chunks=chunks,
                    alignment=placement.method, neutral_frame=placement.neutral_frame, **(extra or {}))

    def open_folder(self, out, capture: Capture, placement, *, chunks: int = 1, truth_file=None,
                    overwrite: bool = False, setup: MarkerSetup | None = None, take_frames=None,
                    extra: dict | None = None) -> FitFolder:
        """The fit folder of this take at ``out``: new, or the unfinished one to resume, or the
        finished one (``folder.finished``); a folder with other settings raises ``FitFolderError``
        unless ``overwrite``. Collective; rank 0 writes.

        ``setup`` gives the markers' weights, groups and validation markers (default: every
        marker fitted with weight 1); ``take_frames`` the take's own numbers of the capture's
        frames when it is part of a longer take (``Capture.select``); ``extra`` adds entries to
        the record.
        """
        neutral = placement.surface_points + placement.offsets  # model coordinates
        weights, roles, groups = (setup or MarkerSetup()).resolve(list(capture.marker_names), neutral)
        record = dict(extra or {})
        if setup is not None:
            record["marker_setup"] = setup.record()
        settings = self.record(capture, placement, chunks=chunks, extra=record)
        take = dict(muscle_names=self.model.muscle_names, marker_names=list(capture.marker_names),
                    times=[float(t) for t in capture.times],
                    take_frames=[int(f) for f in (range(capture.n_frames) if take_frames is None else take_frames)],
                    marker_weights=weights.tolist(), marker_roles=roles, marker_groups=groups,
                    neutral_markers=[[None if not np.isfinite(v) else float(v) for v in p] for p in neutral])
        alignment = json.dumps(placement.to_json(), indent=2)

        def prepare():
            folder, finished = FitFolder.prepare(out, settings, take, truth_file, overwrite=overwrite)
            if not finished:
                atomic_write(folder.path / "alignment.json", alignment)
            return folder.path
        return FitFolder(on_rank_0(prepare, self.comm))

    def run(self, folder: FitFolder, capture: Capture, placement, *, chunk: int | None = None,
            stop_after: int | None = None, on_frame=None, progress: bool = True) -> TrackingRun:
        """Fit the frames of ``capture`` (aligned to the model by ``placement``) that ``folder``
        lacks, writing each as it is done; then, if none is left, the tables and the report.

        The take is split into the folder's number of chunks, each fitted from rest; ``chunk``
        fits only that one. A chunk is resumed from its first unfinished frame, starting from the
        checkpoint of the frame before, so that every frame after it is fitted from exactly the
        state an uninterrupted run would have had. ``stop_after`` fits at most that many frames.
        ``on_frame(result)`` is called after each frame is written.
        """
        from tqdm import tqdm
        chunks = chunk_ranges(capture.n_frames, folder.settings["chunks"])
        if chunk is not None:
            if not 0 <= chunk < len(chunks):
                raise ValueError(f"chunk {chunk}: the take has chunks 0..{len(chunks) - 1}")
            chunks = [chunks[chunk]]
        aligned = placement.aligned(capture)
        truth = folder.truth()
        done = set(range(capture.n_frames)) - set(on_rank_0(folder.missing_frames, self.comm))
        problem = self.problem
        node_order = FileNodeOrder(problem.V)
        markers = MarkerSet(problem, placement.surface_points, placement.offsets, names=capture.marker_names,
                            weights=folder.marker_weights)
        starts = {c: min((f for f in c if f not in done), default=None) for c in chunks[self.group::self.rank_groups]}
        todo = sum(c.stop - start for c, start in starts.items() if start is not None)
        if stop_after is not None:
            todo = min(todo, stop_after)
        results = []

        def save(result: FrameResult, fitter: FaceFitter, first: int) -> None:
            frame = result.frame
            simulated = markers.positions(problem.u.x.array, fitter.state.cranium)
            displacement = node_order.gather(problem.u.x.array)
            # Checkpoint first, frame record last: a frame on disk always has its checkpoint.
            folder.save_checkpoint(frame, fitter.checkpoint(), node_order)
            if self.group_comm.rank == 0:
                folder.write_frame(result, aligned.positions[frame], simulated, displacement)
                if frame > first:
                    folder.drop_checkpoint(frame - 1)
            results.append(result)
            error = "" if truth is None else \
                f", activation error {np.abs(result.activations - truth.activations[frame]).max():.3f}"
            log.info("frame %d/%d: marker RMS %.3f mm (max %.3f), %d GN steps, %.1f s%s%s", frame + 1,
                     capture.n_frames, result.rms_error, result.max_error, result.gn_steps,
                     result.seconds, error, f" [{result.flag}]" if result.flag else "")
            bar.set_postfix_str(f"frame {frame}: {result.seconds:.1f} s, RMS {result.rms_error:.3f} mm",
                                refresh=False)
            bar.update()
            if on_frame is not None:
                on_frame(result)

        hidden = None if progress and self.comm.rank == 0 else True  # None: shown on a terminal only
        with tqdm(total=todo, unit="frame", desc="fit", dynamic_ncols=True, disable=hidden) as bar:
            for frames, start in starts.items():
                if start is None or len(results) == todo:
                    continue
                fitter = FaceFitter(problem, markers, self.settings.fit)
                problem.reset_to_rest()
                if start > frames.start:
                    checkpoint = folder.load_checkpoint(start - 1, node_order)
                    if checkpoint is None:
                        log.warning("%s has no checkpoint after frame %d: refitting from frame %d", folder.path,
                                    start - 1, frames.start)
                        start = frames.start
                    else:
                        fitter.restore(checkpoint)
                        log.info("resuming %s at frame %d (%d frames already done)", folder.path, start, len(done))
                stop = min(frames.stop, start + todo - len(results))
                track(fitter, aligned.positions, range(start, stop),
                      on_frame=functools.partial(save, fitter=fitter, first=frames.start))
        self.comm.barrier()
        missing = on_rank_0(folder.missing_frames, self.comm)
        if not missing:
            on_rank_0(lambda: finish(folder), self.comm)
        return TrackingRun(folder, results, missing)

    def track(self, capture: Capture, placement, out, *, chunks: int = 1, chunk: int | None = None,
              truth_file=None, overwrite: bool = False, setup: MarkerSetup | None = None, take_frames=None,
              stop_after: int | None = None, on_frame=None, progress: bool = True,
              extra: dict | None = None) -> TrackingRun:
        """``open_folder`` then ``run``: the whole take into the fit folder ``out`` (resumed if it
        holds this take unfinished; nothing is fitted if it holds it finished)."""
        folder = self.open_folder(out, capture, placement, chunks=chunks, truth_file=truth_file,
                                  overwrite=overwrite, setup=setup, take_frames=take_frames, extra=extra)
        if folder.finished:
            return TrackingRun(folder)
        return self.run(folder, capture, placement, chunk=chunk, stop_after=stop_after, on_frame=on_frame,
                        progress=progress)


def finish(folder: FitFolder) -> None:
    """Tables and report of a fit whose frames are all done, then mark it finished (rank 0)."""
    folder.write_tables()
    write_report(folder.path)
    folder.mark_finished()
