"""Where a capture's markers sit on the model: the alignment a fit starts from.

Three cases, chosen by what the capture and the user give (docs/cli.md):
  "correspondence"  a correspondence file names >= 6 capture markers' model landmarks: the
                    similarity (scale, rotation, translation) of the neutral frame onto them, then
                    every capture marker embedded at its closest skin point, keeping its offset;
  "icp"             no correspondences and marker names that are not the model's marker sites: a
                    similarity ICP of the neutral frame against the skin from rough poses, then the
                    same embedding; its verdict says whether to trust it;
  "model_sites"     no correspondences and every marker named after a model marker site (synthetic
                    takes): the capture is already in model coordinates and each marker is its site.
Either way the result gives the transform from capture to model coordinates, each marker's
material point on the skin and its offset, which is what ``fitting.MarkerSet`` takes.
An alignment judged "wrong" (a left/right swap, a pair far from where the others put it, an
implausible scale: ``similarity.QualityThresholds``) is refused before anything is fitted, unless
the user accepts it; a "doubtful" one is logged as a warning.
"""
from __future__ import annotations

from dataclasses import dataclass, field
import logging
import pathlib

import numpy as np

from face_dolfinx.capture import Capture, frames_with_gaps
from face_dolfinx.parallel import on_rank_0
from .similarity import (AlignmentError, AlignmentQuality, Similarity, align_by_correspondences, align_by_icp,
                         read_correspondence_file)
from .surface import SkinSurface

log = logging.getLogger(__name__)

# With marker-site names, a neutral frame whose markers are farther than this (RMS, mm) from their
# sites is not in model coordinates: a face's expressions move markers by millimetres, a capture in
# its own lab frame by tens or hundreds.
SITE_DISTANCE_WARNING_MM = 10.0
# Frames offered as neutral-frame candidates in a message.
SUGGESTED_FRAMES = 5


@dataclass(frozen=True, eq=False)
class CapturePlacement:
    """A capture aligned to the model: the transform, and each marker as a skin point plus offset."""

    method: str                    # "correspondence", "icp" or "model_sites"
    neutral_frame: int             # index of the neutral frame (0-based, non-negative)
    transform: Similarity          # capture -> model coordinates
    marker_names: list[str]
    surface_points: np.ndarray     # (n, 3) each marker's material point on the skin, model frame
    offsets: np.ndarray            # (n, 3) marker minus its skin point in the neutral frame
    quality: AlignmentQuality | None   # markers-to-skin verdict (None for model sites)
    residuals: dict[str, float] = field(default_factory=dict)  # correspondence residuals, mm
    details: dict = field(default_factory=dict)   # method-specific numbers (ICP iterations, ...)

    @property
    def doubtful(self) -> bool:
        return (self.quality is not None and not self.quality.good) or bool(self.details.get("warning"))

    def aligned(self, capture: Capture) -> Capture:
        """The capture in model coordinates (gaps stay gaps)."""
        return Capture(capture.marker_names, self.transform.apply(capture.positions), capture.frame_rate,
                       capture.times, capture.source)

    def summary(self) -> str:
        """One line for the log."""
        t = self.transform
        angle = np.degrees(np.arccos(np.clip((np.trace(t.rotation) - 1) / 2, -1, 1)))
        text = (f"alignment by {self.method.replace('_', ' ')} on neutral frame {self.neutral_frame}: scale "
                f"{t.scale:.4f}, rotation {angle:.1f} deg, translation {np.linalg.norm(t.translation):.1f} mm")
        if self.residuals:
            values = np.array(list(self.residuals.values()))
            text += (f"; {len(values)} correspondences, residual RMS {np.sqrt(np.mean(values ** 2)):.2f} mm, "
                     f"max {values.max():.2f} mm")
        if "iterations" in self.details:
            text += f"; ICP {self.details['iterations']} iterations{'' if self.details['converged'] else ' (not converged)'}"
        if self.quality is not None:
            text += f"; {self.quality}"
        if self.details.get("warning"):
            text += f"; {self.details['warning']}"
        return text

    def to_json(self) -> dict:
        """The record written next to the results (alignment.json)."""
        t = self.transform
        record = dict(method=self.method, neutral_frame=self.neutral_frame,
                      transform=dict(direction="capture -> model", scale=t.scale, rotation=t.rotation.tolist(),
                                     translation=t.translation.tolist(),
                                     fit_rms_mm=None if not np.isfinite(t.rms) else t.rms),
                      verdict=None if self.quality is None else self.quality.verdict)
        if self.quality is not None:
            q = self.quality
            record["markers_to_skin_mm"] = dict(rms=q.rms, max=q.max, near_mm=q.near_mm,
                                                near_fraction=q.near_fraction,
                                                per_marker=dict(zip(self.marker_names, _plain(q.distances))))
        if self.residuals:
            record["correspondence_residuals_mm"] = dict(self.residuals)
        record.update(self.details)
        record["markers"] = {name: dict(skin_point=point.tolist(), offset=offset.tolist())
                             for name, point, offset in zip(self.marker_names, self.surface_points, self.offsets)}
        return record


def place_capture(capture: Capture, neutral_frame: int, skin: SkinSurface, model_markers: dict,
                  model_landmarks: dict, correspondence: dict[str, str] | str | pathlib.Path | None = None,
                  *, accept_wrong: bool = False) -> CapturePlacement:
    """Align ``capture`` to the model and embed its markers (see the module docstring).

    ``correspondence`` maps capture markers to model landmarks, or is a correspondence file
    (``read_correspondence_file``). Raises AlignmentError, its message starting with the capture
    file (and the correspondence file), when the neutral frame lacks markers that must be
    embedded, the correspondences can't be used, or the alignment is "wrong": then the message
    lists why (pairs that stand out, a left/right swap, ...). With ``accept_wrong`` a wrong
    alignment is kept, as a doubtful one, and the placement records that it was accepted.
    """
    source = capture.source or "<in-memory capture>"
    where = source
    if isinstance(correspondence, (str, pathlib.Path)):
        where = f"{source} with {correspondence}"
        correspondence = read_correspondence_file(correspondence)
    neutral = capture.neutral(neutral_frame)
    frame = neutral_frame % capture.n_frames
    names = list(capture.marker_names)
    if correspondence is None and all(name in model_markers for name in names):
        return _at_model_sites(names, neutral, frame, model_markers)

    missing = [name for name, present in zip(names, capture.present[frame]) if not present]
    complete = np.setdiff1d(np.arange(capture.n_frames), frames_with_gaps(capture))
    # Every marker is embedded in the skin from the neutral frame, so each must be present there.
    choose = ("choose a neutral frame where every marker is present (" +
              (f"frames {', '.join(map(str, complete[:SUGGESTED_FRAMES]))}{' ...' if len(complete) > SUGGESTED_FRAMES else ''}"
               if complete.size else "no frame has them all: leave the markers out") + ")")
    if correspondence is not None:
        try:
            result = align_by_correspondences(neutral, names, model_landmarks, correspondence, skin)
        except AlignmentError as error:
            raise AlignmentError(f"{where}: {error}" + (f"\n  {choose}" if missing else "")) from None
        method, transform, quality, residuals = "correspondence", result.transform, result.quality, result.residuals
        details = dict(pairs_standing_out_mm=result.pairs.standing_out,
                       mirrored_assignment=None if result.pairs.mirrored_rms is None else
                       dict(landmark_rms_mm=result.pairs.mirrored_rms, scale=result.pairs.mirrored_scale))
        embedding = result.embedding
        advice = "check the correspondences"
    else:
        if missing:
            raise AlignmentError(f"{source}: neutral frame {frame} lacks markers {_listed(missing)}; {choose}")
        try:
            result = align_by_icp(neutral, skin)
        except AlignmentError as error:
            raise AlignmentError(f"{source}: {error}") from None
        method, transform, quality, residuals = "icp", result.transform, result.quality, {}
        details = dict(iterations=int(result.iterations), converged=bool(result.converged))
        embedding = skin.embed(transform.apply(neutral), names)
        advice = "give a correspondence file (capture marker -> model landmark)"
    if quality.wrong:
        if not accept_wrong:
            raise AlignmentError(f"{where}: the alignment by {method} to the model is wrong; nothing is fitted:\n  "
                                 + "\n  ".join(quality.reasons) + f"\n  {advice}, or pass accept_alignment=True "
                                 "(--accept-alignment on the command line) to fit with this alignment anyway")
        details["accepted"] = "the wrong alignment was accepted by the user (accept_alignment)"
    return CapturePlacement(method, frame, transform, names, embedding.positions(skin.points) - embedding.offsets,
                            embedding.offsets, quality, residuals, details)


def place_on_model(model, capture: Capture, neutral_frame: int = 0,
                   correspondence: dict[str, str] | str | pathlib.Path | None = None,
                   accept_alignment: bool = False) -> CapturePlacement:
    """``place_capture`` for a loaded model (collective): computed on rank 0 and sent to the other
    ranks, so that every rank fits the same markers; logged, with a warning when doubtful (or wrong
    and accepted by ``accept_alignment``); a wrong alignment otherwise raises AlignmentError on
    every rank. ``correspondence`` is a mapping or a correspondence file."""
    skin_points, skin_triangles = model.skin_surface()  # collective
    comm = model.mesh.comm

    def place():
        return place_capture(capture, neutral_frame, SkinSurface(skin_points, skin_triangles),
                             model.markers, model.landmarks, correspondence, accept_wrong=accept_alignment)
    placement = on_rank_0(place, comm)
    log.info("%s", placement.summary())
    if placement.doubtful:
        quality = placement.quality
        reasons = placement.details["warning"] if quality is None else "; ".join(quality.reasons)
        level = "doubtful" if quality is None or not quality.wrong else "wrong (accepted)"
        advice = ("check the correspondences" if placement.method == "correspondence" else
                  "give --correspondence (capture marker -> model landmark) for a reliable alignment")
        log.warning("the alignment of %s to model %s is %s: %s. The fit goes on, but its results are "
                    "only as good as the alignment: %s, or adapt the model to the subject (build --subject)",
                    capture.source, model.name, level, reasons, advice)
    return placement


def _at_model_sites(names, neutral, frame, model_markers) -> CapturePlacement:
    sites = np.array([model_markers[name] for name in names], dtype=np.float64)
    distance = np.linalg.norm(neutral - sites, axis=1)
    present = np.isfinite(distance)
    rms = float(np.sqrt(np.mean(distance[present] ** 2))) if present.any() else float("nan")
    details = dict(neutral_to_sites_rms_mm=rms)
    if rms > SITE_DISTANCE_WARNING_MM:
        details["warning"] = (f"the markers are named after the model's marker sites, but in the neutral frame "
                              f"they are {rms:.0f} mm (RMS) from those sites: the capture does not look like it "
                              f"is in model coordinates")
    return CapturePlacement("model_sites", frame, Similarity.identity(), names, sites, np.zeros_like(sites),
                            None, {}, details)


def _listed(names, shown=8) -> str:
    return ", ".join(names[:shown]) + (f" and {len(names) - shown} more" if len(names) > shown else "")


def _plain(values) -> list:
    return [None if not np.isfinite(v) else float(v) for v in values]
