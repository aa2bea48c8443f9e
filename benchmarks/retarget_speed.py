"""Retargeted forward frames: seconds per warm-started frame on a subject adapted from the built-in face.

The source animation is the speech scenario's controls on the built-in face at ``--tets`` (a
stretch of ``--frames`` frames of a ``--take-frames``-long take at 60 Hz, head and jaw moving, as
``synth`` makes them). It is retargeted (``face_dolfinx.animation.retarget``) onto subject B, the
built-in face adapted (``subjects.carry_model``) to its own skin scaled by diag(1.15, 0.9, 1.05)
(wider, shorter, deeper), and played on B by ``face_dolfinx.animation.playback.play``, the loop of
``simulate --animation`` (every frame's displacement and record written), once per ``--variants``
entry, each on a fresh problem:

  default   FaceProblem's defaults: Newton to 1e-8 mm, a factorisation per iteration
  fast      the problem options of ``fit --fast`` (``PRESETS["fast"].problem_options()``): the
            factor kept while an iteration halves the residual, Newton to 1e-2 mm, 3 secant
            iterations in its line search

One JSON line per variant: the first frame (from rest) apart, then the warm-started frames' solve
seconds (median, mean, max) and Newton iterations (median), the model's exact tet count, the ranks,
the retarget record's head scale and RMS, and the machine's 1-minute load average before and after
(timings on a loaded machine are longer by about the load over the cores).

    mpirun -n 2 python benchmarks/retarget_speed.py --tets 20000 --frames 20 --out results/retarget/x.jsonl
"""
import argparse
import json
import os
import pathlib
import sys

from mpi4py import MPI
import numpy as np

STRETCH = np.diag([1.15, 0.9, 1.05])


def subject_b(template_path: pathlib.Path, folder: pathlib.Path, comm) -> pathlib.Path:
    """The template adapted to its own skin stretched by ``STRETCH`` (written once, on rank 0)."""
    from face_dolfinx.model.folder import read_model_arrays
    from face_dolfinx.parallel import on_rank_0
    from face_dolfinx.subjects.adaptation import carry_model

    def write():
        if not (folder / "model.toml").is_file():
            template = read_model_arrays(template_path, check=False)
            carry_model(template, template.points[template.skin_nodes] @ STRETCH.T, name="subject_b")[0].write(folder)
        return folder
    return on_rank_0(write, comm)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--tets", type=int, default=20_000)
    parser.add_argument("--frames", type=int, default=20)
    parser.add_argument("--take-frames", type=int, default=240, help="the take's length (60 Hz)")
    parser.add_argument("--first-frame", type=int, default=80)
    parser.add_argument("--variants", nargs="+", default=["default", "fast"], choices=["default", "fast"])
    parser.add_argument("--work", default="runs/retarget_speed", help="subject model and playback folders")
    parser.add_argument("--out", help="JSON-lines result file (default: standard output)")
    args = parser.parse_args(argv)

    from face_dolfinx.animation import Animation
    from face_dolfinx.animation.playback import open_playback, play
    from face_dolfinx.animation.retarget import retarget
    from face_dolfinx.capture.synthetic import control_curves
    from face_dolfinx.model.anatomy import build_builtin_face
    from face_dolfinx.model.folder import load_model, read_model_arrays
    from face_dolfinx.physics.problem import FaceProblem
    from face_dolfinx.tracking import PRESETS
    comm = MPI.COMM_WORLD
    work = pathlib.Path(args.work)
    source_path = build_builtin_face(target_tets=args.tets, comm=comm)
    target_path = subject_b(source_path, work / f"subject_b_{source_path.name}", comm)
    source = load_model(source_path, comm)
    activations, tmj, head = control_curves(source, "speech", args.take_frames)
    frames = range(args.first_frame, args.first_frame + args.frames)
    animation = Animation(np.array(frames) / 60.0, source.muscle_names, activations[frames], [head[f] for f in frames],
                          None, tmj=tmj[frames], source=f"speech frames {frames.start}:{frames.stop} of {args.take_frames}")
    moved, record = retarget(animation, read_model_arrays(source_path, check=False),
                             read_model_arrays(target_path, check=False), target_label=str(target_path))
    target = load_model(target_path, comm)
    options = dict(default={}, fast=PRESETS["fast"].problem_options())
    lines = []
    for variant in args.variants:
        problem = FaceProblem(target, **options[variant])
        folder, markers = open_playback(target, moved, work / f"play_{source_path.name}_{variant}", overwrite=True)
        load = os.getloadavg()[0]  # the machine is shared: what else ran
        run = play(problem, moved, folder, markers, progress=False)
        warm, iterations = np.array(run.seconds[1:]), np.array(run.newton_iterations[1:])
        lines.append(dict(
            study="retarget_speed", variant=variant, problem_options=options[variant],
            tets=target.mesh.topology.index_map(3).size_global, ranks=comm.size, frames=len(run.seconds),
            take=animation.source, first_frame_s=run.seconds[0], first_frame_newton=run.newton_iterations[0],
            warm_median_s=float(np.median(warm)), warm_mean_s=float(warm.mean()), warm_max_s=float(warm.max()),
            warm_newton_median=float(np.median(iterations)), warm_newton_max=int(iterations.max()),
            head_scale=record["head"]["scale"], head_rms_mm=record["head"]["rms_mm"],
            jaw_clamped_frames=record["jaw"]["clamped_frames"], load_average_1min=load,
            load_average_1min_after=os.getloadavg()[0]))
    if comm.rank == 0:
        text = "".join(json.dumps(line) + "\n" for line in lines)
        if args.out:
            out = pathlib.Path(args.out)
            out.parent.mkdir(parents=True, exist_ok=True)
            out.write_text(text)
            sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
            from provenance import record as record_provenance
            record_provenance(out, tets=[args.tets], ranks=comm.size)
        else:
            sys.stdout.write(text)


if __name__ == "__main__":
    main()
