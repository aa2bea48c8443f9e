"""A video of a fit folder: the rendered skin over time, captured markers red and simulated green.

Every fitted frame (or every ``step``-th) is drawn as ``render.render_skin`` draws the report's
renders, from one fixed camera box that holds the face in all of them, with the frame's time and
marker error in its caption, and played at the take's own rate. MP4 (H.264, by the ffmpeg that
``imageio-ffmpeg`` ships) or, where no encoder is found or asked for, an animated GIF. Serial: it
reads only the folder's files, like ``report``.
"""
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
from tqdm import tqdm

from face_dolfinx.model.folder import read_model_arrays
from .folder import FitFolder
from .render import camera_rotation, draw_skin, marker_caption, view_box

MAX_FPS = 60.0


def ffmpeg_available() -> bool:
    """Whether an MP4 encoder is found (imageio-ffmpeg's ffmpeg)."""
    try:
        import imageio_ffmpeg
        return Path(imageio_ffmpeg.get_ffmpeg_exe()).exists()
    except (ImportError, RuntimeError):
        return False


def write_video(path, out=None, *, view: str = "front", step: int = 1, fps: float | None = None,
                gif: bool = False, progress: bool = True) -> Path:
    """Write the video of fit folder ``path`` to ``out`` (default ``path``/face.mp4, or face.gif)
    and return where it went. ``fps`` defaults to real time: the take's frame rate over ``step``."""
    import imageio.v2 as imageio
    if step < 1:
        raise ValueError(f"step {step}: give 1 or more")
    folder = FitFolder(path)
    results = folder.finished_frames()
    frames = sorted(results)[::step]
    if not frames:
        raise ValueError(f"{folder.path}: no finished frame to make a video of")
    gif = gif or not ffmpeg_available()
    out = Path(out) if out is not None else folder.path / ("face.gif" if gif else "face.mp4")
    if fps is None:
        spacing = np.diff(folder.times[frames])
        fps = 1.0 / float(np.median(spacing)) if len(spacing) and np.median(spacing) > 0 else 1.0
    fps = min(max(fps, 1.0), MAX_FPS)

    model = read_model_arrays(folder.settings["model"], check=False)
    skin_points, skin_triangles = model.skin_surface()
    rotation = camera_rotation(view)

    def skin_at(frame):
        return skin_points + folder.displacement(frame)[model.skin_nodes]

    # One camera box for the whole video, so that the face does not jump from frame to frame.
    extent = np.concatenate([(skin_at(frame) @ rotation.T)[:, :2] for frame in frames[::max(1, len(frames) // 50)]])
    box = view_box(extent)
    writer = (imageio.get_writer(out, mode="I", duration=1000.0 / fps, loop=0) if gif else
              imageio.get_writer(out, fps=fps, codec="libx264", quality=7, macro_block_size=1,
                                 pixelformat="yuv420p"))
    with writer:
        for frame in tqdm(frames, desc=f"video {out.name}", unit="frame", disable=not progress):
            captured, simulated = folder.frame_markers(frame)
            result = results[frame]
            title = f"{folder.times[frame]:6.2f} s (frame {folder.take_frames[frame]}): {marker_caption(result.rms_error)}"
            figure = draw_skin(skin_at(frame), skin_triangles, markers=captured, other_markers=simulated,
                               title=title, view=view, box=box)
            figure.canvas.draw()
            writer.append_data(np.asarray(figure.canvas.buffer_rgba())[:, :, :3].copy())
            plt.close(figure)
    return out
