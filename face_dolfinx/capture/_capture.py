"""A motion-capture take in memory: marker positions over time, in millimetres, Y up, NaN for gaps."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

_IN_MEMORY = "<in-memory capture>"


class CaptureError(ValueError):
    """A capture that can't be used as asked. The message names the file and the problem."""

    def __init__(self, source: Path | str | None, problem: str):
        self.source = None if source is None else Path(source)
        self.problem = problem
        super().__init__(f"{_IN_MEMORY if source is None else source}: {problem}")

    def __reduce__(self):
        # Rebuilt from both parts (the default would pass the message alone), so that the error can
        # be pickled, e.g. sent from rank 0 to the other MPI ranks.
        return type(self), (self.source, self.problem)


@dataclass(frozen=True, eq=False, repr=False)
class Capture:
    """Marker trajectories of one take, in the model's units (mm) and axes (right-handed, Y up).

    A gap (occluded or missing sample) is NaN in all three coordinates of ``positions`` and False
    in ``present``: it is left out of that frame's objective, never treated as a position. On
    construction every sample with a non-finite coordinate, or exactly (0, 0, 0) as some systems
    write an occluded marker, becomes a gap. Head motion is part of the positions: nothing is
    stabilised. The arrays are read-only; ``select`` makes a new capture.
    """

    marker_names: list[str]
    positions: np.ndarray  # (n_frames, n_markers, 3) float64, mm
    frame_rate: float  # Hz
    times: np.ndarray | None = None  # (n_frames,) s; None: frame index / frame_rate
    source: Path | None = None  # the file read, None for a capture made in memory
    present: np.ndarray = field(init=False)  # (n_frames, n_markers) bool

    def __post_init__(self):
        source = None if self.source is None else Path(self.source)
        names = [str(name) for name in self.marker_names]
        positions = np.array(self.positions, dtype=np.float64)  # a copy: the capture owns its data
        if positions.ndim != 3 or positions.shape[2] != 3:
            raise CaptureError(source, f"positions must have shape (n_frames, n_markers, 3), not {positions.shape}")
        n_frames, n_markers = positions.shape[:2]
        if len(names) != n_markers:
            raise CaptureError(source, f"{len(names)} marker names for {n_markers} markers")
        if "" in (name.strip() for name in names):
            raise CaptureError(source, "a marker has an empty name")
        repeated = sorted({name for name in names if names.count(name) > 1})
        if repeated:
            raise CaptureError(source, f"marker names must be unique; repeated: {', '.join(repeated)}")
        frame_rate = float(self.frame_rate)
        if not (np.isfinite(frame_rate) and frame_rate > 0):
            raise CaptureError(source, f"frame rate must be a positive number of Hz, not {self.frame_rate!r}")
        if self.times is None:
            times = np.arange(n_frames) / frame_rate
        else:
            times = np.array(self.times, dtype=np.float64)
            if times.shape != (n_frames,):
                raise CaptureError(source, f"times must have shape ({n_frames},), not {times.shape}")

        gap = ~np.isfinite(positions).all(axis=2) | (positions == 0.0).all(axis=2)
        positions[gap] = np.nan
        present = ~gap
        for array in (positions, times, present):
            array.flags.writeable = False

        for name, value in [("marker_names", names), ("positions", positions), ("frame_rate", frame_rate),
                            ("times", times), ("source", source), ("present", present)]:
            object.__setattr__(self, name, value)

    @property
    def n_frames(self) -> int:
        return self.positions.shape[0]

    @property
    def n_markers(self) -> int:
        return self.positions.shape[1]

    def neutral(self, frame: int = 0) -> np.ndarray:
        """Marker positions (n_markers, 3) of the frame the user names as the neutral (rest) pose.

        Captures carry no neutral label, so the caller chooses; the first frame is the default.
        Markers with a gap in that frame are NaN rows (see ``present[frame]``): the caller decides
        whether those markers can be done without or another frame is needed.
        """
        if not -self.n_frames <= frame < self.n_frames:
            raise CaptureError(self.source, f"neutral frame {frame} is out of range: the capture has {self.n_frames} frames")
        return self.positions[frame].copy()

    def select(self, frames) -> Capture:
        """A capture of some frames only: a slice, an array of frame indices or a boolean mask."""
        indices = np.atleast_1d(np.arange(self.n_frames)[frames])
        return Capture(self.marker_names, self.positions[indices], self.frame_rate, self.times[indices], self.source)

    def summary(self) -> str:
        """Markers, frames, rate and the share of gaps per marker, as text for a person."""
        gap_percent = 100.0 * (1.0 - self.present.mean(axis=0)) if self.n_frames else np.zeros(self.n_markers)
        total_percent = float(gap_percent.mean()) if self.n_markers else 0.0
        duration = self.times[-1] - self.times[0] if self.n_frames else 0.0
        lines = [
            f"{self.source or _IN_MEMORY}: {self.n_markers} markers, {self.n_frames} frames at "
            f"{self.frame_rate:g} Hz ({duration:.3f} s); gaps: {total_percent:.1f}% of samples, "
            f"{len(frames_with_gaps(self))} frames with at least one",
        ]
        width = max([len("marker")] + [len(name) for name in self.marker_names])
        lines.append(f"  {'marker':<{width}}  {'gaps':>6}")
        lines += [f"  {name:<{width}}  {percent:5.1f}%" for name, percent in zip(self.marker_names, gap_percent)]
        return "\n".join(lines)

    def __repr__(self) -> str:
        return (f"Capture({self.source or _IN_MEMORY}, {self.n_markers} markers, {self.n_frames} frames, "
                f"{self.frame_rate:g} Hz)")


def frames_with_gaps(capture: Capture) -> np.ndarray:
    """Indices of the frames in which at least one marker is missing."""
    return np.flatnonzero(~capture.present.all(axis=1))


def chunk_ranges(n_frames: int, n_chunks: int) -> list[range]:
    """Split frames 0..n-1 into ``n_chunks`` contiguous, nearly equal ranges (none empty)."""
    n_chunks = max(1, min(n_chunks, n_frames))
    edges = np.linspace(0, n_frames, n_chunks + 1).round().astype(int)
    return [range(a, b) for a, b in zip(edges[:-1], edges[1:])]
