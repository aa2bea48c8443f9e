"""Warm-started forward frames of an edited animation, as ``run.py simulate --animation`` plays them.

The animation is the synthetic speech scenario at 60 Hz (``capture.synthetic.control_curves``:
mouth muscles at 1.5-12 cycles over the take, the jaw opening with the syllables, a nod, turn and
drift of the head; 240 frames = 4 s, the pace of real speech), edited as an animator would:
exaggerated 1.3x about neutral, a smile keyed on top (zygomaticus major, both sides, blended in and
out over 0.1 s), smoothed with a 20 ms Gaussian. ``--frames`` frames from ``--first`` are played
through ``face_dolfinx.animation.playback.play`` into a results folder under ``--out`` (every frame
written, as the command does; the report at the end is not timed), once per ``--variants`` entry:

  default   Newton to 1e-8 mm corrections, a factorisation per iteration (simulate's default)
  loose     Newton to 1e-4 mm (``--newton-tolerance 1e-4``; docs/performance.md found no fitted
            marker changed by it)
  reuse     loose, and modified Newton keeping the last MUMPS factor across iterations and frames
            (``FaceProblem(reuse_factorization=True)``)

One JSON line per variant: the warm frames' solve seconds (every frame but the first, which
starts from rest) and Newton iterations, the wall time per frame of the whole loop (the cold
first frame, marker evaluation and writing included) and rank 0's CPU time per frame, and the
machine's load average (the figures are only comparable at the same load).

    mpirun -n 2 python benchmarks/edit_speed.py --tets 20000 --out benchmarks/results/edit/edit_20k_np2.jsonl
"""
import argparse
import json
import os
import pathlib
import shutil
import tempfile
import time

from mpi4py import MPI
import numpy as np

VARIANTS = {"default": dict(newton_tolerance=1e-8), "loose": dict(newton_tolerance=1e-4),
            "reuse": dict(newton_tolerance=1e-4, reuse_factorization=True)}


def edited_speech(model, frames: int, rate: float):
    from face_dolfinx.animation import Animation, editing
    from face_dolfinx.capture.synthetic import control_curves
    activations, tmj, head = control_curves(model, "speech", frames, head_motion=True)
    times = np.arange(frames) / rate
    take = Animation(times, model.muscle_names, activations, head, None, None, tmj, source="speech scenario")
    edited = editing.scaled(take, 1.3)
    middle = times[frames // 2]
    for side in ("left", "right"):
        edited = editing.with_keyframes(edited, f"zygomaticus_major_{side}", [middle - 0.3, middle, middle + 0.3],
                                        [0.2, 0.8, 0.2], blend=0.1)
    return editing.smoothed(edited, 0.02)


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--tets", type=int, default=20000)
    parser.add_argument("--take-frames", type=int, default=240, help="frames of the whole animation (60 Hz)")
    parser.add_argument("--first", type=int, default=100, help="first frame played")
    parser.add_argument("--frames", type=int, default=21, help="frames played (the first from rest)")
    parser.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    parser.add_argument("--out", help="JSON-lines result file (default: print)")
    args = parser.parse_args()

    from face_dolfinx.animation import editing
    from face_dolfinx.animation.playback import PlaybackMarkers, open_playback, play
    from face_dolfinx.model.anatomy import build_builtin_face
    from face_dolfinx.model.folder import load_model
    from face_dolfinx.physics.problem import FaceProblem
    comm = MPI.COMM_WORLD
    model = load_model(build_builtin_face(target_tets=args.tets, comm=comm), comm)
    rate = 60.0
    animation = edited_speech(model, args.take_frames, rate)
    # One frame more than played: the playback stays unfinished, so no report is written in the timing.
    part = editing.segment(animation, args.first / rate, (args.first + args.frames) / rate)
    scratch = pathlib.Path(comm.bcast(tempfile.mkdtemp(prefix="edit_speed_") if comm.rank == 0 else None))
    rows = []
    try:
        for variant in args.variants:
            problem = FaceProblem(model, **VARIANTS[variant])
            folder, markers = open_playback(model, part, scratch / variant, markers=PlaybackMarkers.of_model(model))
            began, cpu = time.perf_counter(), time.process_time()
            run = play(problem, part, folder, markers, stop_after=args.frames, progress=False)
            wall, cpu = time.perf_counter() - began, time.process_time() - cpu
            warm = np.array(run.seconds[1:])
            iterations = np.array(run.newton_iterations[1:])
            rows.append(dict(
                study="edit_speed", variant=variant, tets=model.mesh.topology.index_map(3).size_global,
                ranks=comm.size, dofs=problem.V.dofmap.index_map.size_global * 3, frames=len(run.frames),
                first_frame=args.first, frame_rate_hz=rate, **VARIANTS[variant],
                warm_solve_s_median=round(float(np.median(warm)), 4), warm_solve_s_mean=round(float(warm.mean()), 4),
                warm_solve_s_max=round(float(warm.max()), 4), cold_solve_s=round(run.seconds[0], 4),
                warm_newton_median=int(np.median(iterations)), warm_newton_max=int(iterations.max()),
                newton_iterations=run.newton_iterations, solve_s=[round(v, 4) for v in run.seconds],
                wall_s_per_frame=round(wall / len(run.frames), 4),
                # CPU time of rank 0 per frame: less sensitive to other work on the machine than the
                # wall time (MPI's busy waiting included)
                cpu_s_per_frame_rank0=round(cpu / len(run.frames), 4),
                max_activation_step=round(float(np.abs(np.diff(part.activations, axis=0)).max()), 4),
                load_average_1min=round(os.getloadavg()[0], 2)))  # other work on the machine meanwhile
    finally:
        if comm.rank == 0:
            shutil.rmtree(scratch, ignore_errors=True)
    if comm.rank != 0:
        return
    lines = "".join(json.dumps(row) + "\n" for row in rows)
    if args.out:
        out = pathlib.Path(args.out)
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(lines)
        from provenance import record
        record(out, tets=[args.tets], ranks=comm.size)
    else:
        print(lines, end="")


if __name__ == "__main__":
    main()
