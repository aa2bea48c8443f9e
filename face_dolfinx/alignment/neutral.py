"""Choosing a take's neutral frame when nobody labelled one: its most typical frame.

The neutral frame is the face at rest: the subject model is shaped on it, the markers are embedded
in the skin there, and every frame's non-rigid motion is measured from it. A take that starts with
an expression (or with lips pressed, cheeks drawn in) makes every later rest look like a motion no
muscle of a model at rest makes. A performer's face spends most of a take near rest, so the frame
whose markers, with the head's rigid motion removed, lie closest to the take's median shape is a
good rest. On the AnimFace NoseMoCap take frame 0 lies 1.58 mm RMS from that median shape and frame
862 0.75 mm; fitted from frame 862 the fit's errors drop by a sixth to a third (docs/accuracy.md).
"""
from dataclasses import dataclass

import numpy as np

from face_dolfinx.capture import Capture, frames_with_gaps
from .similarity import AlignmentError, similarity_transform

# Rounds of (align every frame rigidly to the reference shape, take the median shape as the new
# reference): the second changes the chosen frame's distance by < 0.01 mm on the real sample.
MEDIAN_ROUNDS = 3


@dataclass(frozen=True)
class TypicalFrame:
    frame: int               # the frame closest to the median shape
    rms_mm: float            # its markers' RMS distance from that shape (head motion removed)
    first_frame_rms_mm: float  # the same for frame 0, for comparison (NaN if frame 0 has gaps)


def typical_frame(capture: Capture) -> TypicalFrame:
    """The frame of ``capture`` whose markers, moved rigidly onto the take's median shape, lie
    closest to it, among the frames where every marker is present."""
    complete = np.setdiff1d(np.arange(capture.n_frames), frames_with_gaps(capture))
    if complete.size == 0:
        raise AlignmentError(f"{capture.source}: no frame has every marker, so none can be the neutral frame; "
                             "give --neutral-frame N for a frame whose missing markers can be left out")
    frames = capture.positions[complete]
    reference = frames[0]
    for _ in range(MEDIAN_ROUNDS):
        aligned = np.array([similarity_transform(markers, reference, allow_scale=False).apply(markers)
                            for markers in frames])
        reference = np.median(aligned, axis=0)
    distance = np.sqrt(np.mean(np.sum((aligned - reference) ** 2, axis=2), axis=1))
    best = int(np.argmin(distance))
    first = distance[0] if complete[0] == 0 else float("nan")
    return TypicalFrame(int(complete[best]), float(distance[best]), float(first))
