"""Motion-capture takes: marker trajectories read from C3D, TRC or CSV files.

    from face_dolfinx.capture import read_capture
    capture = read_capture("take.c3d")          # mm, Y up, NaN where a marker is missing
    rest = capture.neutral(frame=0)             # the user names the neutral frame
    print(capture.summary())

File formats, units, axes and gap conventions: docs/capture_formats.md.
"""

from ._capture import Capture, CaptureError, chunk_ranges, frames_with_gaps
from ._io import read_capture, write_capture

__all__ = ["Capture", "CaptureError", "chunk_ranges", "frames_with_gaps", "read_capture", "write_capture"]
