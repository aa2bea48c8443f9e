"""A speech-like take with lip closures fitted with and without lip self-contact (docs/contact.md,
"Fitting with contact").

The synthetic take ``bilabial`` ("ma ba pa": the orbicularis oris at 0.9 presses the lips together
three times, open vowels between) is solved with lip self-contact (the truth: lips that touch and
do not pass), sampled at the model's marker sites with noise, and fitted by
``face_dolfinx.tracking.Tracker`` (the loop of ``run.py fit``) with ``contact`` off and on. Per
frame: marker RMS error (against the noisy take), activation errors against the truth (largest,
and that of the orbicularis oris), and the lips' penetration and smallest distance in the fitted
equilibrium. One JSON row per frame, then a summary row per variant.

    python benchmarks/provenance.py run --out benchmarks/results/contact/bilabial_5k.jsonl --json-lines -- \\
        python benchmarks/bilabial_fit.py --tets 5000 --frames 12
"""
import argparse
import json
import pathlib
import time

from mpi4py import MPI
import numpy as np


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tets", type=int, default=5000)
    parser.add_argument("--frames", type=int, default=12)
    parser.add_argument("--noise", type=float, default=0.5, help="marker noise, RMS of the 3D error (mm)")
    parser.add_argument("--out", default="runs/bilabial_fit", help="folder for the fit folders")
    args = parser.parse_args()

    from face_dolfinx.alignment.placement import place_on_model
    from face_dolfinx.capture.synthetic import synthesize_take
    from face_dolfinx.fitting import MarkerSet
    from face_dolfinx.model.anatomy import build_builtin_face
    from face_dolfinx.model.folder import load_model
    from face_dolfinx.physics.problem import FaceProblem
    from face_dolfinx.physics.self_contact import LipContact, LipContactSettings, lip_facets
    from face_dolfinx.tracking import Tracker, TrackingSettings

    comm = MPI.COMM_WORLD
    model = load_model(build_builtin_face(args.tets, comm=comm), comm)
    names = list(model.markers)
    sites = np.array([model.markers[name] for name in names])
    truth_problem = FaceProblem(model, lip_contact=LipContactSettings())
    began = time.perf_counter()
    capture, truth = synthesize_take(truth_problem, MarkerSet(truth_problem, sites, names=names), model, "bilabial",
                                     n_frames=args.frames, noise=args.noise, head_motion=False)
    truth_seconds = time.perf_counter() - began
    del truth_problem
    placement = place_on_model(model, capture)
    sphincter = [i for i, m in enumerate(model.muscles) if m.name.startswith("orbicularis_oris")]
    summaries = []
    for contact in (False, True):
        tracker = Tracker(model, TrackingSettings(lip_contact=contact))
        problem = tracker.problem
        lips = problem.lips or LipContact(problem.V, *lip_facets(model, LipContactSettings()), LipContactSettings(),
                                          problem.bone_blocks)
        rows = []

        def report(result, contact=contact, problem=problem, lips=lips, rows=rows):
            u = problem.u.x.array
            error = np.abs(result.activations - truth.activations[result.frame])
            row = dict(contact=contact, frame=result.frame, seconds=round(result.seconds, 2),
                       gn_steps=result.gn_steps, rms_mm=round(result.rms_error, 4),
                       activation_error=round(float(error.max()), 4),
                       orbicularis_error=round(float(error[sphincter].max()), 4),
                       truth_orbicularis=round(float(truth.activations[result.frame][sphincter].max()), 3),
                       penetration_mm=round(lips.penetration(u), 4), lip_distance_mm=round(lips.min_distance(u), 5))
            rows.append(row)
            if comm.rank == 0:
                print(json.dumps(row), flush=True)

        tracker.track(capture, placement, pathlib.Path(args.out) / ("contact" if contact else "no-contact"),
                      overwrite=True, on_frame=report, progress=False)
        closed = [r for r in rows if r["truth_orbicularis"] > 0.5]
        summaries.append(dict(
            contact=contact, frames=len(rows), mean_seconds=round(float(np.mean([r["seconds"] for r in rows])), 2),
            mean_rms_mm=round(float(np.mean([r["rms_mm"] for r in rows])), 4),
            max_activation_error=round(float(np.max([r["activation_error"] for r in rows])), 4),
            mean_activation_error=round(float(np.mean([r["activation_error"] for r in rows])), 4),
            closed_frames=len(closed),
            closed_mean_rms_mm=round(float(np.mean([r["rms_mm"] for r in closed])), 4) if closed else None,
            closed_max_orbicularis_error=round(float(np.max([r["orbicularis_error"] for r in closed])), 4)
            if closed else None,
            max_penetration_mm=round(float(np.max([r["penetration_mm"] for r in rows])), 4)))
    if comm.rank == 0:
        print(json.dumps(dict(summary=dict(tets=model.mesh.topology.index_map(3).size_global, ranks=comm.size,
                                           frames=args.frames, noise_mm=args.noise,
                                           truth_seconds=round(truth_seconds, 1), variants=summaries))),
              flush=True)


if __name__ == "__main__":
    main()
