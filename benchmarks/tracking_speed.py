"""Warm-started tracking cost per frame on the built-in face, per phase, for solver variants.

Synthesises a speech-like take (60 Hz, 0.5 mm noise, head motion) once at the given resolution,
then tracks the same stretch of it with each ``--variants`` entry through
``face_dolfinx.tracking.Tracker``, the loop ``run.py fit`` runs (every frame and its checkpoint
written to a fit folder under ``--out``), one fresh problem each:

  fresh     the default loop: Newton assembles and factorises the tangent at every iteration
            until it converges (last correction <= 0.1 mm), a Jacobian per Gauss-Newton step
  reuse     modified Newton: the last factor (of the sensitivities or of an earlier iteration) is
            kept while each iteration cuts the residual at least 4-fold (``reuse_factorization``)
  reuse-1j  reuse, and one fresh Jacobian per warm frame (``max_fresh_jacobians=1``): the first
            Gauss-Newton step reuses the last frame's, the third the second's
  naive     the baseline: a factorisation at every Newton iteration, and the paper's
            golden-section line search on every Gauss-Newton step (the full step one of its
            candidates), not only when the full step fails
  reuse-1j-loose-gn2   reuse-1j with Newton stopping at 1e-4 mm corrections (not 1e-8 mm) and
            2 Gauss-Newton steps per warm frame (not 3)
  krylov-1j-loose-gn2  the same, the old factor preconditioning GMRES on the exact tangent instead
            of refactorising when modified Newton slows (``krylov_on_old_factor``)
  fast      ``fit --fast``: reuse-1j with 2 Gauss-Newton steps, Newton stopping at 1e-2 mm,
            3 secant iterations in its line search,
            refactorising only when an iteration cuts the residual less than 2-fold, and Jacobians
            from the equilibrium solve's last factor when it was made within 0.3 mm of the
            equilibrium (only the remaining one per frame is exact)

Per frame one JSON line (seconds = the frame's fit, loop_seconds = wall time from the previous
frame's end, writing included; solver counters: factorisations, residual evaluations, GMRES iterations;
phases: sensitivities = factorisation and the dX/dc solves, gn_solve =
the small least-squares step, equilibrium = the solve at the full step, line_search =
golden-section trials), per variant a summary over the warm-started frames (every frame but the
first, which starts from rest), and at the end the time ratio of each variant to the first.

The speech scenario puts 1.5 to 12 cycles per muscle into the take, so its length sets how fast
the face moves: 240 frames (4 s, the default) keep every activation within 0.11 of the previous
frame, as in real speech; 60 frames (1 s) change activations by up to 0.45 per 1/60 s, faster
than muscles can, a stress test for the warm start.

    mpirun -n 2 python benchmarks/tracking_speed.py --tets 400000 --frames 4
"""
import argparse
import json
import pathlib
import resource
import time

from mpi4py import MPI
import numpy as np

LOOSE = dict(newton_tolerance=1e-4)  # mm


def _variants() -> dict:
    """name: (TrackingSettings, further FaceProblem keywords, FactorReusePolicy attributes)."""
    from face_dolfinx.tracking import PRESETS, TrackingSettings
    from face_dolfinx.fitting import FitSettings
    reuse = dict(reuse_factorization=True)
    return {
        "fresh": (PRESETS["default"], {}, {}),
        "reuse": (TrackingSettings(**reuse), {}, {}),
        "reuse-1j": (TrackingSettings(FitSettings(max_fresh_jacobians=1), **reuse), {}, {}),
        "naive": (TrackingSettings(FitSettings(line_search_every_step=True)), {}, dict(converging_correction=0.0)),
        "reuse-1j-loose-gn2": (TrackingSettings(FitSettings(max_fresh_jacobians=1, max_gn_steps=2), **reuse, **LOOSE),
                               {}, {}),
        "krylov-1j-loose-gn2": (TrackingSettings(FitSettings(max_fresh_jacobians=1, max_gn_steps=2), **reuse, **LOOSE),
                                dict(krylov_on_old_factor=True), {}),
        "fast": (PRESETS["fast"], {}, {}),
    }


VARIANT_NAMES = ("fresh", "reuse", "reuse-1j", "naive", "reuse-1j-loose-gn2", "krylov-1j-loose-gn2", "fast")
COUNTERS = ("factorizations", "residual_evaluations", "linear_iterations")  # QuasistaticSolver's
PHASES = ("sensitivities", "gn_solve", "equilibrium", "line_search")


def fit_variant(name, model, capture, placement, truth, args, comm, out) -> dict:
    """Track the take with one variant through ``face_dolfinx.tracking.Tracker`` (the loop of
    ``run.py fit``: every frame and its checkpoint written to a fit folder)."""
    from face_dolfinx.tracking import Tracker

    settings, problem_options, policy_attributes = _variants()[name]
    settings = settings.updated(dict(mode=args.mode, gn_steps=args.gn_steps))
    tracker = Tracker(model, settings, problem_options=problem_options)
    problem = tracker.problem
    for attribute, value in policy_attributes.items():
        setattr(problem.solver.reuse_policy, attribute, value)
    rows = []
    counted = dict.fromkeys(COUNTERS, 0)
    last = [time.perf_counter()]

    def report(result):
        now = time.perf_counter()
        counts = {}
        for counter in COUNTERS:
            counts[counter] = getattr(problem.solver, counter) - counted[counter]
            counted[counter] = getattr(problem.solver, counter)
        row = dict(variant=name, frame=args.start + result.frame, seconds=round(result.seconds, 2),
                   loop_seconds=round(now - last[0], 2), gn_steps=result.gn_steps, **counts,
                   rms_mm=round(result.rms_error, 3),
                   activation_error=round(float(np.abs(result.activations - truth.activations[result.frame]).max()), 3),
                   **{k: round(v, 2) for k, v in result.phases.items()})
        last[0] = now
        rows.append(row)
        if comm.rank == 0:
            print(json.dumps(row), flush=True)

    last[0] = time.perf_counter()
    tracker.track(capture, placement, out / name, overwrite=True, on_frame=report, progress=False)
    warm = rows[1:]
    return dict(variant=name, first_frame_s=rows[0]["seconds"],
                warm_mean_s=round(float(np.mean([r["seconds"] for r in warm])), 2),
                warm_mean_loop_s=round(float(np.mean([r["loop_seconds"] for r in warm])), 2),
                **{"warm_" + c: round(float(np.mean([r[c] for r in warm])), 1) for c in COUNTERS},
                warm_phases_s={k: round(float(np.mean([r[k] for r in warm])), 2) for k in PHASES},
                warm_mean_rms_mm=round(float(np.mean([r["rms_mm"] for r in warm])), 3),
                warm_max_activation_error=round(float(np.max([r["activation_error"] for r in warm])), 3))


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--tets", type=int, default=50_000)
    parser.add_argument("--frames", type=int, default=6, help="frames fitted")
    parser.add_argument("--take-frames", type=int, default=240,
                        help="length of the synthetic take at 60 Hz (sets how fast the face moves); "
                             "the fitted frames are a stretch of it, 1/60 s apart as in a capture")
    parser.add_argument("--start", type=int, default=80, help="first fitted frame of the take")
    parser.add_argument("--mode", default="exact", choices=("exact", "paper"))
    parser.add_argument("--gn-steps", type=int, default=3)
    parser.add_argument("--variants", nargs="+", default=["fresh", "reuse"], choices=VARIANT_NAMES)
    parser.add_argument("--out", default="runs/tracking_speed", help="folder for the variants' fit folders")
    args = parser.parse_args()

    from face_dolfinx.alignment.placement import place_on_model
    from face_dolfinx.capture.synthetic import synthesize_take
    from face_dolfinx.fitting import MarkerSet
    from face_dolfinx.model.anatomy import build_builtin_face
    from face_dolfinx.model.folder import load_model
    from face_dolfinx.physics.problem import FaceProblem

    comm = MPI.COMM_WORLD
    model = load_model(build_builtin_face(args.tets), comm)
    names = list(model.markers)
    sites = np.array([model.markers[name] for name in names])
    truth_problem = FaceProblem(model, reuse_factorization=True)
    t0 = time.perf_counter()
    capture, truth = synthesize_take(truth_problem, MarkerSet(truth_problem, sites, names=names), model, "speech",
                                     n_frames=args.take_frames, noise=0.5,
                                     frames=range(args.start, args.start + args.frames))
    synth_seconds = time.perf_counter() - t0
    del truth_problem
    placement = place_on_model(model, capture)  # the take is at the model's marker sites
    out = pathlib.Path(args.out)
    summaries = [fit_variant(name, model, capture, placement, truth, args, comm, out) for name in args.variants]
    memory = comm.allreduce(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss, op=MPI.SUM) / 1024**2
    if comm.rank == 0:
        base = summaries[0]
        for summary in summaries:
            summary["warm_time_ratio_to_" + base["variant"]] = round(summary["warm_mean_s"] / base["warm_mean_s"], 3)
        print(json.dumps(dict(summary=dict(
            tets=model.mesh.topology.index_map(3).size_global, ranks=comm.size, mode=args.mode,
            frames=args.frames, take_frames=args.take_frames, synth_seconds=round(synth_seconds, 1),
            peak_memory_gb=round(memory, 2), variants=summaries))), flush=True)


if __name__ == "__main__":
    main()
