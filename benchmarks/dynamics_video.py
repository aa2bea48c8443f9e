"""The soft-tissue smile of docs/dynamics.md as two playbacks of one animation, quasistatic and
dynamic, each a results folder (in ``--work``) with its MP4 (``run.py video``, copied to ``--out``),
and per frame the largest difference of the skin's marker sites between them.

The animation switches the model's smile on in 0.15 s and holds it to 0.5 s (60 Hz); the nose
and both cheeks are softened to 1/100 of the flesh stiffness (``benchmarks/dynamics.py``'s
regions, given to ``--material`` as a TOML file). Everything goes through the command line, as a
user would run it::

    python benchmarks/dynamics_video.py --tets 5000 --work /tmp/dynamics_video --out benchmarks/results/dynamics
"""
import argparse
import json
import pathlib
import shutil
import sys

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))
from dynamics import SOFT_FACTOR  # noqa: E402
from face_dolfinx.cli.main import main  # noqa: E402
from face_dolfinx.model.anatomy import build_builtin_face  # noqa: E402
from face_dolfinx.model.folder import read_model_arrays  # noqa: E402
from face_dolfinx.results.folder import FitFolder  # noqa: E402
import provenance  # noqa: E402

FRAME_RATE = 60
ONSET, DURATION = 0.15, 0.5  # s


def animation_text(smile: dict) -> str:
    """TOML keyframes: each muscle of the smile ramped smoothly from 0 over ONSET, then held."""
    lines = [f"frame_rate = {FRAME_RATE}", f"duration = {DURATION}", 'interpolation = "smooth"']
    for muscle, value in smile.items():
        lines += [f"[muscles.{muscle}]", f"times = [0.0, {ONSET}]", f"values = [0.0, {value}]"]
    return "\n".join(lines) + "\n"


def material_text(landmarks: dict) -> str:
    """The softened nose and cheeks as ``--material`` TOML regions (spheres, mm)."""
    spheres = [(*landmarks["nose_tip"], 18.0)]
    for side in ("left", "right"):
        x, y, z = landmarks[f"cheekbone_{side}"]
        spheres.append((x, y - 20.0, z, 22.0))
    return "".join(f'[[region]]\nsphere = [{", ".join(f"{v:.3f}" for v in s)}]\nscale = {{ all = {SOFT_FACTOR} }}\n\n'
                   for s in spheres)


def main_benchmark():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--tets", type=int, default=5000)
    parser.add_argument("--work", type=pathlib.Path, required=True, help="the two results folders")
    parser.add_argument("--out", type=pathlib.Path, required=True, help="the MP4s and the differences")
    args = parser.parse_args()
    model_path = build_builtin_face(target_tets=args.tets)
    arrays = read_model_arrays(model_path)
    args.work.mkdir(parents=True, exist_ok=True)
    args.out.mkdir(parents=True, exist_ok=True)
    animation, material = args.work / "smile.toml", args.work / "soft_nose_cheeks.toml"
    animation.write_text(animation_text(arrays.expressions["smile"]))
    material.write_text(material_text(arrays.landmarks))
    common = ["--model", str(model_path), "--animation", str(animation), "--material", str(material), "--overwrite"]
    folders = {"quasistatic": args.work / "quasistatic", "dynamic": args.work / "dynamic"}
    assert main(["simulate", *common, "--out", str(folders["quasistatic"])]) == 0
    assert main(["simulate", *common, "--dynamic", "--out", str(folders["dynamic"])]) == 0
    for folder in folders.values():
        assert main(["video", str(folder)]) == 0
    static, dynamic = (FitFolder(folders[k]) for k in ("quasistatic", "dynamic"))
    rows = []
    for frame, t in enumerate(static.times):
        simulated = [folder.frame_markers(frame)[1] for folder in (static, dynamic)]
        difference = np.linalg.norm(simulated[1] - simulated[0], axis=1)
        rows.append(dict(frame=frame, time_s=float(t), largest_marker_difference_mm=round(float(difference.max()), 4),
                         worst_marker=static.marker_names[int(difference.argmax())]))
    label = f"{round(args.tets / 1000)}k"
    result = args.out / f"soft_smile_{label}_differences.jsonl"
    result.write_text("".join(json.dumps(row) + "\n" for row in rows))
    provenance.record(result, tets=[args.tets], ranks=1)
    for kind, folder in folders.items():
        video = args.out / f"soft_smile_{label}_{kind}.mp4"
        shutil.copyfile(folder / "face.mp4", video)
        provenance.record(video, tets=[args.tets], ranks=1)
    print(f"largest marker difference {max(r['largest_marker_difference_mm'] for r in rows):.3f} mm; {result}")


if __name__ == "__main__":
    main_benchmark()
