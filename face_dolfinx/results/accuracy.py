"""Accuracy of a fit without a truth: how much of the markers' non-rigid motion it explains.

On a real capture nothing says where the face really was, so a fit is judged by prediction. A
marker's *non-rigid motion* in a frame is its distance from where the rigid head motion would put
its neutral position: what rigid head motion alone cannot explain. The head motion is the best rigid
motion of the neutral frame's markers onto the frame's, fitted to the half that move most rigidly.
The fit *explains* the fraction ``1 - sum error^2 / sum non_rigid^2`` of it, where ``error`` is the
distance between the simulated and the captured marker. Markers left out of the fit (validation
markers, weight 0) measure prediction: their errors come from the physics and the other markers
only. A marker predicted worse than by rigid motion alone (error above its non-rigid motion) is one
the model does not follow.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from face_dolfinx.alignment.similarity import AlignmentError, similarity_transform

ROLES = ("fitted", "validation", "ignored")


# The rigid motion of a frame is fitted to the markers that move most rigidly: the RIGID_SHARE of
# them closest to the last fit's prediction, refitted RIGID_ROUNDS times (a least-trimmed-squares
# fit). Fitted to all markers, an opening jaw drags the head's estimate and makes the forehead look
# as if it moved.
RIGID_SHARE = 0.5
RIGID_ROUNDS = 3


def rigid_motions(neutral: np.ndarray, captured: np.ndarray) -> list:
    """Each frame's rigid head motion (``Similarity``, scale 1): the best rigid motion of the
    neutral markers (markers, 3) onto the captured ones (frames, markers, 3), over the markers seen
    in both that move most rigidly; None in a frame with fewer than 3 of them (or collinear)."""
    motions = []
    for markers in captured:
        weights = np.ones(len(neutral))
        try:
            for _ in range(RIGID_ROUNDS + 1):
                motion = similarity_transform(neutral, markers, weights, allow_scale=False)
                distance = np.linalg.norm(motion.apply(neutral) - markers, axis=1)
                seen = np.isfinite(distance)
                kept = max(3, int(np.ceil(RIGID_SHARE * seen.sum())))
                weights = np.zeros(len(neutral))
                weights[np.argsort(np.where(seen, distance, np.inf))[:kept]] = 1.0
        except AlignmentError:
            motion = None
        motions.append(motion)
    return motions


def rigid_prediction(neutral: np.ndarray, captured: np.ndarray) -> np.ndarray:
    """(frames, markers, 3): the neutral markers moved by each frame's rigid head motion
    (``rigid_motions``); NaN where a frame has none."""
    predicted = np.full(captured.shape, np.nan)
    for frame, motion in enumerate(rigid_motions(neutral, captured)):
        if motion is not None:
            predicted[frame] = motion.apply(neutral)
    return predicted


@dataclass
class MotionMeasures:
    """Per frame and marker (frames, markers), NaN where a marker was not seen: the fit's error
    and the marker's non-rigid motion, in mm."""
    error: np.ndarray
    non_rigid: np.ndarray

    @classmethod
    def of(cls, neutral, captured, simulated) -> "MotionMeasures":
        captured, simulated = np.asarray(captured, float), np.asarray(simulated, float)
        return cls(np.linalg.norm(simulated - captured, axis=2),
                   np.linalg.norm(rigid_prediction(np.asarray(neutral, float), captured) - captured, axis=2))

    def per_frame(self, markers: np.ndarray) -> dict[str, np.ndarray]:
        """RMS error, RMS non-rigid motion and the fraction explained, per frame, over ``markers``
        (a boolean mask); NaN for a frame where none of them was seen."""
        seen = np.isfinite(self.error) & np.isfinite(self.non_rigid) & markers[None, :]
        count = seen.sum(axis=1)
        error2 = np.where(seen, self.error, 0.0) ** 2
        motion2 = np.where(seen, self.non_rigid, 0.0) ** 2
        with np.errstate(invalid="ignore", divide="ignore"):
            return dict(rms_mm=np.sqrt(error2.sum(axis=1) / count),
                        non_rigid_mm=np.sqrt(motion2.sum(axis=1) / count),
                        explained=1.0 - error2.sum(axis=1) / motion2.sum(axis=1))

    def pooled(self, markers: np.ndarray) -> dict[str, float]:
        """Over the whole take and ``markers``: the median of the per-frame RMS error, the RMS error
        and non-rigid motion, and the fraction explained (of the summed squares)."""
        seen = np.isfinite(self.error) & np.isfinite(self.non_rigid) & markers[None, :]
        if not seen.any():
            return dict(median_frame_rms_mm=np.nan, rms_mm=np.nan, non_rigid_mm=np.nan, explained=np.nan)
        error2, motion2 = self.error[seen] ** 2, self.non_rigid[seen] ** 2
        return dict(median_frame_rms_mm=float(np.nanmedian(self.per_frame(markers)["rms_mm"])),
                    rms_mm=float(np.sqrt(error2.mean())), non_rigid_mm=float(np.sqrt(motion2.mean())),
                    explained=float(1.0 - error2.sum() / motion2.sum()))

    def per_marker(self) -> dict[str, np.ndarray]:
        """Over the take, per marker: RMS error, RMS non-rigid motion, the fraction explained."""
        seen = np.isfinite(self.error) & np.isfinite(self.non_rigid)
        count = seen.sum(axis=0)
        error2 = (np.where(seen, self.error, 0.0) ** 2).sum(axis=0)
        motion2 = (np.where(seen, self.non_rigid, 0.0) ** 2).sum(axis=0)
        with np.errstate(invalid="ignore", divide="ignore"):
            return dict(rms_mm=np.sqrt(error2 / count), non_rigid_mm=np.sqrt(motion2 / count),
                        explained=1.0 - error2 / motion2)


# An activation at least this high counts as pinned at the upper bound; a stretch this long
# (seconds) of a muscle pinned there is reported.
PINNED_ACTIVATION = 0.99
PINNED_SECONDS = 0.5


def pinned_stretches(activations: np.ndarray, times: np.ndarray, names: list[str]) -> list[dict]:
    """Muscles at their upper bound for PINNED_SECONDS or longer: the longest such stretch of each
    (start and end time, seconds), longest first. ``activations`` (frames, muscles) in time order."""
    stretches = []
    for index, name in enumerate(names):
        pinned = activations[:, index] >= PINNED_ACTIVATION
        best, start = None, None
        for frame, at_bound in enumerate(np.append(pinned, False)):
            if at_bound and start is None:
                start = frame
            elif not at_bound and start is not None:
                span = (times[start], times[frame - 1])
                if best is None or span[1] - span[0] > best[1] - best[0]:
                    best = span
                start = None
        if best is not None and best[1] - best[0] >= PINNED_SECONDS:
            stretches.append(dict(muscle=name, start_s=float(best[0]), end_s=float(best[1]),
                                  seconds=float(best[1] - best[0])))
    return sorted(stretches, key=lambda s: -s["seconds"])


def summary(measures: MotionMeasures, names: list[str], roles: list[str], groups: list[str | None]) -> dict:
    """The accuracy of a fitted take by marker role and group, and per marker (``accuracy.json``)."""
    roles, groups = np.array(roles), np.array([g or "" for g in groups])
    per_marker = measures.per_marker()
    record = dict(roles={role: dict(markers=int((roles == role).sum()), **measures.pooled(roles == role))
                         for role in ROLES if (roles == role).any()},
                  groups={group: dict(markers=int((groups == group).sum()), **measures.pooled(groups == group))
                          for group in sorted(set(groups) - {""})},
                  markers={name: dict(role=str(role), group=str(group) or None,
                                      rms_mm=_number(per_marker["rms_mm"][i]),
                                      non_rigid_mm=_number(per_marker["non_rigid_mm"][i]),
                                      explained=_number(per_marker["explained"][i]),
                                      worse_than_rigid=bool(per_marker["rms_mm"][i] > per_marker["non_rigid_mm"][i]))
                           for i, (name, role, group) in enumerate(zip(names, roles, groups))})
    record["worse_than_rigid"] = {role: [name for name, m in record["markers"].items()
                                         if m["role"] == role and m["worse_than_rigid"]] for role in record["roles"]}
    return record


def summary_lines(record: dict) -> list[str]:
    """The accuracy of a fitted take for a person: by role, by group, the markers the model does
    not follow and the muscles pinned at 1."""
    lines = []
    for role, pooled in record["roles"].items():
        if role == "ignored":
            continue
        worse = record["worse_than_rigid"][role]
        lines.append(f"{pooled['markers']} {role} markers: median frame RMS {pooled['median_frame_rms_mm']:.2f} mm, "
                     f"{100 * pooled['explained']:.0f} % of their non-rigid motion ({pooled['non_rigid_mm']:.2f} mm "
                     f"RMS) explained" + (f", {len(worse)} predicted worse than by rigid motion alone "
                                          f"({', '.join(worse)})" if worse else ""))
    if record["groups"]:
        lines.append("by group: " + "; ".join(
            f"{name} ({group['markers']}) {group['rms_mm']:.2f} mm, {100 * group['explained']:.0f} %"
            for name, group in record["groups"].items()))
    pinned = record.get("pinned_muscles", [])
    if pinned:
        lines.append("at activation 1 for 0.5 s or longer: " + ", ".join(
            f"{stretch['muscle']} {stretch['seconds']:.1f} s" for stretch in pinned))
    return lines


def _number(value) -> float | None:
    return float(value) if np.isfinite(value) else None
