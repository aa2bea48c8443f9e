"""Warm-started tracking cost per frame on the built-in face, with a per-phase breakdown.

Generates a speech-like take (60 Hz, 0.5 mm noise, head motion) at the given resolution, fits a stretch of it
frame by frame and prints one JSON line per frame (phases: sensitivities = factorisation and the
dX/dc solves, gn_solve = the small least-squares step, equilibrium = the solve at the full step,
line_search = golden-section trials) and a summary line with the mean over the warm-started frames
(every frame but the first, which starts from rest).

    mpirun -n 2 python benchmarks/tracking_speed.py --tets 400000 --frames 6
"""
import argparse
import json
import resource
import time

from mpi4py import MPI
import numpy as np


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--tets", type=int, default=50_000)
    parser.add_argument("--frames", type=int, default=6, help="frames fitted")
    parser.add_argument("--take-frames", type=int, default=60,
                        help="length of the synthetic take at 60 Hz; the fitted frames are a stretch "
                             "of it, so consecutive frames are 1/60 s apart as in a capture")
    parser.add_argument("--start", type=int, default=20, help="first fitted frame of the take")
    parser.add_argument("--mode", default="exact", choices=("exact", "paper"))
    parser.add_argument("--gn-steps", type=int, default=3)
    parser.add_argument("--reuse-factorization", action="store_true",
                        help="keep the MUMPS factor as a GMRES preconditioner across solves and frames")
    args = parser.parse_args()

    from face_dolfinx.anatomy import build_builtin_face
    from face_dolfinx.fitting import FaceFitter, FitSettings, MarkerSet, track
    from face_dolfinx.model import load_model
    from face_dolfinx.problem import FaceProblem
    from face_dolfinx.synthetic import synthesize_take

    comm = MPI.COMM_WORLD
    model = load_model(build_builtin_face(args.tets), comm)
    sites = np.array(list(model.markers.values()))
    truth_problem = FaceProblem(model)
    t0 = time.perf_counter()
    capture, truth = synthesize_take(truth_problem, MarkerSet(truth_problem, sites), model, "speech",
                                     n_frames=args.take_frames, noise=0.5,
                                     frames=range(args.start, args.start + args.frames))
    synth_seconds = time.perf_counter() - t0
    del truth_problem
    problem = FaceProblem(model, reuse_factorization=args.reuse_factorization)
    fitter = FaceFitter(problem, MarkerSet(problem, sites),
                        FitSettings(mode=args.mode, max_gn_steps=args.gn_steps))
    rows = []
    factorizations = [0]

    def report(result):
        done, factorizations[0] = factorizations[0], problem.solver.factorizations
        row = dict(frame=result.frame, seconds=round(result.seconds, 2), gn_steps=result.gn_steps,
                   factorizations=factorizations[0] - done,
                   rms_mm=round(result.rms_error, 3),
                   activation_error=round(float(np.abs(result.activations - truth.activations[result.frame]).max()), 3),
                   **{k: round(v, 2) for k, v in result.phases.items()})
        rows.append(row)
        if comm.rank == 0:
            print(json.dumps(row), flush=True)

    track(fitter, capture.positions, on_frame=report)
    warm = rows[1:]
    memory = comm.allreduce(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss, op=MPI.SUM) / 1024**2
    summary = dict(tets=model.mesh.topology.index_map(3).size_global, ranks=comm.size, mode=args.mode,
                   reuse_factorization=args.reuse_factorization,
                   warm_factorizations=round(float(np.mean([r["factorizations"] for r in warm])), 1),
                   frames=args.frames, synth_seconds=round(synth_seconds, 1),
                   first_frame_s=rows[0]["seconds"],
                   warm_mean_s=round(float(np.mean([r["seconds"] for r in warm])), 2),
                   warm_phases_s={k: round(float(np.mean([r[k] for r in warm])), 2)
                                  for k in ("sensitivities", "gn_solve", "equilibrium", "line_search")},
                   warm_mean_rms_mm=round(float(np.mean([r["rms_mm"] for r in warm])), 3),
                   peak_memory_gb=round(memory, 2))
    if comm.rank == 0:
        print(json.dumps(dict(summary=summary)), flush=True)


if __name__ == "__main__":
    main()
