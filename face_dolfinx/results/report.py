"""The report of a fit folder: plots, rendered frames and a ParaView time series.

Built from the folder's files alone (frame records, per-frame displacements, the model folder
named in run.json, the copied truth of a synthetic take), serially, so ``run.py report FOLDER``
can (re)build it at any time, also for an unfinished fit (it says which frames are missing), and
the result does not depend on how many ranks, chunks or resumes produced the frames.

  activations.png   activation over time of the most active muscles (truth dashed)
  kinematics.png    jaw opening, head rotation angle and translation over time (truth dashed),
                    and the intraoral pressure of a fit that has that control
  marker_error.png  per-frame RMS and largest marker error; with a truth, the capture's own
                    noise (what a perfect fit would show) dashed and the error against the
                    clean markers dotted
  accuracy.png      per frame, fitted and validation markers: RMS error against their non-rigid
                    motion (what rigid head motion alone leaves), and the fraction explained
                    (results.accuracy); for folders that know their neutral markers
  renders/frame_NNNNNN.png   a few frames: deformed skin, captured markers red, simulated green
  face.xdmf (+ face.h5)      per frame: displacement at the nodes and each muscle's
                             activation x volume fraction per cell, for ParaView
"""
import logging
import math
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402  (after choosing the backend)
import numpy as np  # noqa: E402

from .xdmf import XdmfSeries  # noqa: E402
from .render import marker_caption, render_skin  # noqa: E402
from . import accuracy  # noqa: E402
from .folder import FitFolder  # noqa: E402
from face_dolfinx.model.folder import ModelArrays, read_model_arrays  # noqa: E402

log = logging.getLogger(__name__)

MOST_ACTIVE = 6      # muscles drawn in activations.png
RENDERED_FRAMES = 4  # frames rendered, evenly spread over the take


def write_report(path, rendered_frames: int = RENDERED_FRAMES) -> list[Path]:
    """(Re)build the report of the fit folder ``path``; returns the files written."""
    folder = FitFolder(path)
    results = folder.finished_frames()
    missing = folder.missing_frames()
    if missing:
        log.warning("%s: %d of %d frames are not fitted yet (%s); the report shows the others",
                    folder.path, len(missing), len(folder.times), frame_ranges(missing))
    if not results:
        raise ValueError(f"{folder.path}: no finished frame to report on")
    truth = folder.truth()
    model = read_model_arrays(folder.settings["model"], check=False)
    written = [_plot_activations(folder, results, truth), _plot_kinematics(folder, results, truth),
               _plot_marker_error(folder, results, truth)]
    measures = folder.motion_measures([results[frame] for frame in sorted(results)])
    if measures is not None:
        written.append(_plot_accuracy(folder, sorted(results), measures))
    written += _render_frames(folder, results, model, rendered_frames)
    written.append(_write_series(folder, results, model))
    log.info("report of %s: %s", folder.path, ", ".join(str(p.relative_to(folder.path)) for p in written))
    record = folder.accuracy()
    for line in accuracy.summary_lines(record) if record is not None else ():
        log.info("accuracy: %s", line)
    return written


def _series(results: dict, frames: int, value) -> np.ndarray:
    """value(result) per frame, NaN where a frame is not fitted (gaps in the curves)."""
    first = np.asarray(value(next(iter(results.values()))), dtype=float)
    table = np.full((frames,) + first.shape, np.nan)
    for frame, result in results.items():
        table[frame] = value(result)
    return table


def _rotation_angle(matrix: np.ndarray) -> float:
    return math.degrees(math.acos(max(-1.0, min(1.0, (np.trace(matrix) - 1.0) / 2.0))))


def _figure(rows: int):
    figure, axes = plt.subplots(rows, 1, figsize=(8.0, 2.6 * rows + 0.6), sharex=True, squeeze=False)
    return figure, axes[:, 0]


def _save(figure, path: Path) -> Path:
    figure.tight_layout()
    figure.savefig(path, dpi=120)
    plt.close(figure)
    return path


def _plot_activations(folder: FitFolder, results: dict, truth) -> Path:
    t = folder.times
    fitted = _series(results, len(t), lambda r: r.activations)
    peak = np.nanmax(fitted, axis=0)
    if truth is not None:
        peak = np.maximum(peak, truth.activations.max(axis=0))
    shown = np.argsort(-peak, kind="stable")[:MOST_ACTIVE]
    figure, (axes,) = _figure(1)
    for colour, muscle in enumerate(shown):
        axes.plot(t, fitted[:, muscle], color=f"C{colour}", label=folder.muscle_names[muscle])
        if truth is not None:
            axes.plot(t, truth.activations[:, muscle], color=f"C{colour}", linestyle="--")
    axes.set_ylim(-0.02, max(0.1, 1.1 * float(np.nanmax(peak[shown]))))
    axes.set_xlabel("time (s)")
    axes.set_ylabel("activation")
    axes.set_title(f"The {len(shown)} most active muscles"
                   + (" (fit solid, truth dashed)" if truth is not None else ""))
    axes.legend(fontsize=7, ncol=2, loc="upper right")
    return _save(figure, folder.path / "activations.png")


def _plot_kinematics(folder: FitFolder, results: dict, truth) -> Path:
    t = folder.times
    exact = all(r.jaw_tmj is not None for r in results.values())
    # Exact mode fits the TMJ opening itself; the paper's affine jaw frame has its rotation angle.
    opening = _series(results, len(t), lambda r: math.degrees(r.jaw_tmj[0]) if exact else _rotation_angle(r.jaw.matrix))
    head_angle = _series(results, len(t), lambda r: _rotation_angle(r.cranium.matrix))
    head_shift = _series(results, len(t), lambda r: r.cranium.translation)
    with_pressure = bool(folder.settings.get("intraoral_pressure"))
    figure, axes = _figure(4 if with_pressure else 3)
    axes[0].plot(t, opening, color="C0", label="fit")
    axes[0].set_ylabel("jaw opening (deg)" if exact else "jaw rotation (deg)")
    axes[1].plot(t, head_angle, color="C0")
    axes[1].set_ylabel("head rotation (deg)")
    for k, name in enumerate("xyz"):
        axes[2].plot(t, head_shift[:, k], color=f"C{k}", label=f"head t{name}")
    axes[2].set_ylabel("head translation (mm)")
    if truth is not None:
        axes[0].plot(t, np.degrees(truth.tmj[:, 0]), color="C0", linestyle="--", label="truth")
        axes[1].plot(t, [_rotation_angle(h.matrix) for h in truth.head], color="C0", linestyle="--")
        for k in range(3):
            axes[2].plot(t, [h.translation[k] for h in truth.head], color=f"C{k}", linestyle="--")
        axes[0].legend(fontsize=7)
    axes[2].legend(fontsize=7, ncol=3)
    if with_pressure:
        axes[3].plot(t, _series(results, len(t), lambda r: r.pressure), color="C0")
        axes[3].axhline(0.0, color="0.6", linewidth=0.8)
        axes[3].set_ylabel("intraoral pressure (kPa)")
    axes[-1].set_xlabel("time (s)")
    axes[0].set_title("Jaw and head motion" + (" (fit solid, truth dashed)" if truth is not None else ""))
    return _save(figure, folder.path / "kinematics.png")


def _plot_marker_error(folder: FitFolder, results: dict, truth) -> Path:
    t = folder.times
    figure, (axes,) = _figure(1)
    axes.plot(t, _series(results, len(t), lambda r: r.rms_error), color="C0", label="RMS, fit to capture")
    axes.plot(t, _series(results, len(t), lambda r: r.max_error), color="C0", linewidth=0.7, alpha=0.6,
              label="largest, fit to capture")
    if truth is not None and truth.clean_positions.shape[1] == len(folder.marker_names):
        noise = np.full(len(t), np.nan)
        to_clean = np.full(len(t), np.nan)
        for frame in results:
            captured, simulated = folder.frame_markers(frame)
            clean = truth.clean_positions[frame]
            present = np.all(np.isfinite(captured), axis=1)
            if present.any():
                noise[frame] = np.sqrt(np.mean(np.sum((captured - clean)[present] ** 2, axis=1)))
            to_clean[frame] = np.sqrt(np.mean(np.sum((simulated - clean) ** 2, axis=1)))
        axes.plot(t, noise, color="C1", linestyle="--", label="RMS, capture to truth (its noise)")
        axes.plot(t, to_clean, color="C2", linestyle=":", label="RMS, fit to truth")
    axes.set_xlabel("time (s)")
    axes.set_ylabel("marker error (mm)")
    axes.set_ylim(bottom=0.0)
    axes.set_title("Marker error per frame")
    axes.legend(fontsize=7)
    return _save(figure, folder.path / "marker_error.png")


def _plot_accuracy(folder: FitFolder, frames: list[int], measures) -> Path:
    """Per frame, for the fitted and the validation markers: RMS error against RMS non-rigid
    motion (what rigid head motion alone leaves), and the fraction of it the fit explains."""
    t = folder.times[frames]
    figure, axes = _figure(2)
    roles = np.array(folder.marker_roles)
    for colour, role in enumerate(("fitted", "validation")):
        if not (roles == role).any():
            continue
        per_frame = measures.per_frame(roles == role)
        count = int((roles == role).sum())
        axes[0].plot(t, per_frame["non_rigid_mm"], color=f"C{colour}", linestyle="--",
                     label=f"{role} ({count}): non-rigid motion")
        axes[0].plot(t, per_frame["rms_mm"], color=f"C{colour}", label=f"{role}: fit error")
        axes[1].plot(t, 100 * per_frame["explained"], color=f"C{colour}", label=role)
    axes[0].set_ylabel("RMS (mm)")
    axes[0].set_ylim(bottom=0.0)
    axes[0].legend(fontsize=7)
    axes[0].set_title("Markers' motion beyond the rigid head motion, and the fit's error")
    axes[1].set_ylabel("explained (%)")
    axes[1].set_ylim(-50, 105)
    axes[1].axhline(0.0, color="grey", linewidth=0.5)
    axes[1].legend(fontsize=7)
    axes[1].set_xlabel("time (s)")
    return _save(figure, folder.path / "accuracy.png")


def _render_frames(folder: FitFolder, results: dict, model: ModelArrays, count: int) -> list[Path]:
    frames = sorted(results)
    chosen = sorted({frames[i] for i in np.linspace(0, len(frames) - 1, min(count, len(frames))).round().astype(int)})
    out = folder.path / "renders"
    out.mkdir(exist_ok=True)
    for stale in out.glob("frame_*.png"):  # a rerun of the report may choose other frames
        stale.unlink()
    written = []
    skin_points, skin_triangles = model.skin_surface()
    skin_nodes = model.skin_nodes
    for frame in chosen:
        moved = skin_points + folder.displacement(frame)[skin_nodes]
        captured, simulated = folder.frame_markers(frame)
        title = f"frame {frame} ({folder.times[frame]:.2f} s): {marker_caption(results[frame].rms_error)}"
        written.append(render_skin(moved, skin_triangles, out / f"frame_{frame:06d}.png",
                                   markers=captured, other_markers=simulated, title=title))
    return written


def _write_series(folder: FitFolder, results: dict, model: ModelArrays) -> Path:
    path = folder.path / "face.xdmf"
    fractions = []
    for muscle in model.muscles:
        field = np.zeros(len(model.cells))
        field[muscle.cells] = muscle.fraction
        fractions.append(field)
    with XdmfSeries(path, model.points, model.cells) as series:
        for frame in sorted(results):
            displacement = np.zeros_like(model.points)
            stored = folder.displacement(frame)
            displacement[:len(stored)] = stored  # nodes no cell uses (if any, last) do not move
            series.write(float(folder.times[frame]), {"displacement": displacement},
                         {f"activation_{name}": a * fraction for name, a, fraction
                          in zip([m.name for m in model.muscles], results[frame].activations, fractions)})
    return path


def frame_ranges(frames: list[int]) -> str:
    """'2-5, 9' for [2, 3, 4, 5, 9]."""
    parts, start = [], frames[0]
    for previous, current in zip(frames, frames[1:] + [None]):
        if current != previous + 1:
            parts.append(f"{start}" if start == previous else f"{start}-{previous}")
            start = current
    return ", ".join(parts)
