"""A speech-like take with lip closures fitted without contact and with contact (docs/contact.md,
"Fitting with contact").

The synthetic take ``bilabial`` ("ma ba pa": the orbicularis oris at 0.9 presses the lips together
three times, open vowels between) is solved with contact (``--truth-contact``: by default the lips
on each other and the lining on the teeth, as ``fit --contact`` models the face; ``lips``: the
lips only), sampled at the model's marker sites with noise, and fitted by
``face_dolfinx.tracking.Tracker`` (the loop of ``run.py fit``) in the ``--variants``: ``off``,
``lips`` (lip self-contact) and ``lips+teeth`` (``fit --contact``). Per frame: marker RMS error
against the noisy take and against the noise-free truth markers, activation errors against the
truth (largest, and that of the orbicularis oris), the jaw's errors (opening in degrees, condyle
slides in mm), the lips' penetration and smallest distance and the lining's deepest penetration
into the teeth in the fitted equilibrium, and the Newton iterations of the frame. One JSON row per
frame, then a summary row per variant.

    python benchmarks/provenance.py run --out benchmarks/results/contact/bilabial_teeth_5k.jsonl --json-lines -- \\
        python benchmarks/bilabial_fit.py --tets 5000 --frames 12 --variants off,lips+teeth
"""
import argparse
import json
import pathlib
import time

from mpi4py import MPI
import numpy as np

from face_dolfinx.capture.synthetic import TRUTH_CONTACTS


def teeth_poses(model, controls) -> tuple:
    """World poses of the model's teeth, bones in sorted order: the upper ones in the cranium frame, the
    lower ones in the mandible's."""
    return tuple(controls.cranium if bone == "cranium" else controls.cranium.compose(controls.jaw)
                 for bone in sorted(model.teeth))


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tets", type=int, default=5000)
    parser.add_argument("--frames", type=int, default=12)
    parser.add_argument("--noise", type=float, default=0.5, help="marker noise, RMS of the 3D error (mm)")
    parser.add_argument("--out", default="runs/bilabial_fit", help="folder for the fit folders")
    parser.add_argument("--variants", default="off,lips+teeth", help="comma-separated: off, lips, lips+teeth")
    parser.add_argument("--truth-contact", choices=TRUTH_CONTACTS,
                        help="what touches in the truth's solves (default: as fit --contact, lips+teeth)")
    args = parser.parse_args()

    from face_dolfinx.alignment.placement import place_on_model
    from face_dolfinx.capture.synthetic import synthesize_take, truth_contact_options
    from face_dolfinx.fitting import MarkerSet
    from face_dolfinx.model.anatomy import build_builtin_face
    from face_dolfinx.model.folder import load_model
    from face_dolfinx.physics.contact import TEETH_STIFFNESS, ContactPotential, ContactSettings
    from face_dolfinx.physics.problem import FaceProblem
    from face_dolfinx.physics.rigid_mesh import TriangleMesh
    from face_dolfinx.physics.self_contact import LipContact, LipContactSettings, lip_facets
    from face_dolfinx.tracking import Tracker, TrackingSettings

    variants = args.variants.split(",")
    unknown = set(variants) - {"off", "lips", "lips+teeth"}
    if unknown:
        raise SystemExit(f"--variants {args.variants}: unknown {', '.join(sorted(unknown))} (use off, lips, lips+teeth)")

    comm = MPI.COMM_WORLD
    model = load_model(build_builtin_face(args.tets, comm=comm), comm)
    names = list(model.markers)
    sites = np.array([model.markers[name] for name in names])
    truth_problem = FaceProblem(model, **truth_contact_options(model, args.truth_contact, where="--truth-contact"))
    truth_contact = "lips+teeth" if truth_problem.teeth_contact is not None else "lips"
    newton = []  # the Newton iterations of the frame being solved or fitted
    truth_problem.solver.snes.setMonitor(lambda snes, iteration, norm: newton.append(iteration))
    truth_newton = []

    def truth_frame_done(frame):
        truth_newton.append(sum(1 for i in newton if i > 0))
        newton.clear()
    began = time.perf_counter()
    capture, truth = synthesize_take(truth_problem, MarkerSet(truth_problem, sites, names=names), model, "bilabial",
                                     n_frames=args.frames, noise=args.noise, head_motion=False,
                                     progress=truth_frame_done)
    truth_seconds = time.perf_counter() - began
    del truth_problem
    placement = place_on_model(model, capture)
    sphincter = [i for i, m in enumerate(model.muscles) if m.name.startswith("orbicularis_oris")]
    summaries = []
    for contact in variants:
        # "lips": the tracker's problem without contact, the lips' barrier given as a problem option.
        lip_option = dict(lip_contact=LipContactSettings()) if contact == "lips" else {}
        tracker = Tracker(model, TrackingSettings(contact=contact == "lips+teeth"), problem_options=lip_option)
        problem = tracker.problem
        lips = problem.lips or LipContact(problem.V, *lip_facets(model, LipContactSettings()), LipContactSettings(),
                                          problem.bone_blocks)
        # The lining against the teeth, measured in every variant (the fit's own barrier, or a probe).
        teeth = problem.teeth_contact or ContactPotential(
            problem.V, model.facet_tags.find(model.boundary_ids["oral"]),
            ContactSettings(tuple(TriangleMesh(*model.teeth[bone]) for bone in sorted(model.teeth)),
                            teeth_poses(model, problem.controls), stiffness=TEETH_STIFFNESS))
        teeth.ignore(problem.bone_blocks)
        # The fitted face's marker sites (the placement's: the model's sites, no offsets), scored
        # against the noise-free truth markers.
        fitted_markers = MarkerSet(problem, sites, names=names)
        rows = []
        newton.clear()
        problem.solver.snes.setMonitor(lambda snes, iteration, norm: newton.append(iteration))

        def report(result, contact=contact, problem=problem, lips=lips, teeth=teeth, rows=rows,
                   fitted_markers=fitted_markers):
            u = problem.u.x.array
            teeth.set_poses(teeth_poses(model, problem.controls))
            error = np.abs(result.activations - truth.activations[result.frame])
            to_truth = np.linalg.norm(fitted_markers.positions(u, result.cranium) - truth.clean_positions[result.frame],
                                      axis=1)
            jaw_error = np.abs(result.jaw_tmj - truth.tmj[result.frame])
            row = dict(contact=contact, frame=result.frame, seconds=round(result.seconds, 2),
                       gn_steps=result.gn_steps, newton_iterations=sum(1 for i in newton if i > 0),
                       rms_mm=round(result.rms_error, 4),
                       truth_rms_mm=round(float(np.sqrt(np.mean(to_truth ** 2))), 4),
                       jaw_opening_error_deg=round(float(np.degrees(jaw_error[0])), 4),
                       jaw_slide_error_mm=round(float(jaw_error[1:].max()), 4),
                       activation_error=round(float(error.max()), 4),
                       orbicularis_error=round(float(error[sphincter].max()), 4),
                       truth_orbicularis=round(float(truth.activations[result.frame][sphincter].max()), 3),
                       penetration_mm=round(lips.penetration(u), 4), lip_distance_mm=round(lips.min_distance(u), 5),
                       teeth_penetration_mm=round(max(0.0, -teeth.min_gap(u)), 4),
                       teeth_contact_nodes=teeth.contact_nodes(u))
            newton.clear()
            rows.append(row)
            if comm.rank == 0:
                print(json.dumps(row), flush=True)

        tracker.track(capture, placement, pathlib.Path(args.out) / contact,
                      overwrite=True, on_frame=report, progress=False)
        closed = [r for r in rows if r["truth_orbicularis"] > 0.5]
        summaries.append(dict(
            contact=contact, frames=len(rows), mean_seconds=round(float(np.mean([r["seconds"] for r in rows])), 2),
            mean_rms_mm=round(float(np.mean([r["rms_mm"] for r in rows])), 4),
            mean_truth_rms_mm=round(float(np.mean([r["truth_rms_mm"] for r in rows])), 4),
            max_jaw_opening_error_deg=round(float(np.max([r["jaw_opening_error_deg"] for r in rows])), 4),
            max_jaw_slide_error_mm=round(float(np.max([r["jaw_slide_error_mm"] for r in rows])), 4),
            max_activation_error=round(float(np.max([r["activation_error"] for r in rows])), 4),
            mean_activation_error=round(float(np.mean([r["activation_error"] for r in rows])), 4),
            closed_frames=len(closed),
            closed_mean_rms_mm=round(float(np.mean([r["rms_mm"] for r in closed])), 4) if closed else None,
            closed_mean_truth_rms_mm=round(float(np.mean([r["truth_rms_mm"] for r in closed])), 4) if closed else None,
            closed_max_orbicularis_error=round(float(np.max([r["orbicularis_error"] for r in closed])), 4)
            if closed else None,
            max_penetration_mm=round(float(np.max([r["penetration_mm"] for r in rows])), 4),
            min_lip_distance_mm=round(float(np.min([r["lip_distance_mm"] for r in rows])), 5),
            max_teeth_penetration_mm=round(float(np.max([r["teeth_penetration_mm"] for r in rows])), 4),
            mean_newton_iterations=round(float(np.mean([r["newton_iterations"] for r in rows])), 1)))
    if comm.rank == 0:
        print(json.dumps(dict(summary=dict(tets=model.mesh.topology.index_map(3).size_global, ranks=comm.size,
                                           frames=args.frames, noise_mm=args.noise, truth_contact=truth_contact,
                                           truth_seconds=round(truth_seconds, 1),
                                           truth_newton_iterations=truth_newton, variants=summaries))),
              flush=True)


if __name__ == "__main__":
    main()
