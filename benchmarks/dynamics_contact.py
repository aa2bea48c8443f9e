"""Dynamic against quasistatic re-simulation of the face with contact (the lips on each other and on
the teeth, as ``simulate --contact``; docs/dynamics.md).

For each motion (the smile, and the lips pressed: the pucker, orbicularis oris at 0.9, each
switched on in 0.15 s and held to 0.3 s) the face with contact is integrated in time
(``FaceProblem.dynamics``: Newmark's average acceleration, substeps of at most ``--time-step``) and,
frame by frame at 60 Hz, solved quasistatically for the same controls (warm-started from the last
frame; a frame whose quasistatic solve fails is recorded, ``quasistatic_failed``, and the next one
starts from the last equilibrium). Each frame gives one JSON line: the largest difference of the marker sites and of any node
between the two, seconds and Newton iterations of each, the lips' barrier pairs and smallest
distance, the lining nodes within the teeth's dhat and their smallest gap, and the dynamic steps
started from the held move so far. Summary lines (``"summary": true``) give the largest
difference, the means per frame and the cost ratio.

    python benchmarks/dynamics_contact.py --tets 5000 --out benchmarks/results/dynamics/contact_5k.jsonl
"""
import argparse
import pathlib
import sys
import time

from mpi4py import MPI
import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent.parent))
sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
from dynamics import FRAME_RATE, marker_nodes, start_rows  # noqa: E402
import provenance  # noqa: E402
from face_dolfinx.equilibrium.dynamics import DynamicsError, DynamicSettings  # noqa: E402
from face_dolfinx.equilibrium.solver import EquilibriumError  # noqa: E402
from face_dolfinx.model.folder import load_model  # noqa: E402
from face_dolfinx.physics.contact import TEETH_STIFFNESS, ContactSettings  # noqa: E402
from face_dolfinx.physics.problem import Controls, FaceProblem  # noqa: E402
from face_dolfinx.physics.self_contact import LipContactSettings  # noqa: E402

EXPRESSIONS = {"smile": "smile", "lips_pressed": "pucker"}
ONSET, DURATION = 0.15, 0.3  # s


def contact_problem(model) -> FaceProblem:
    """The face with the contact of ``simulate --contact``."""
    return FaceProblem(model, contact=ContactSettings(teeth=True, stiffness=TEETH_STIFFNESS),
                       lip_contact=LipContactSettings())


def contact_state(problem) -> dict:
    u = problem.u.x.array
    return dict(lip_pairs=problem.lips.pairs(u), lip_min_distance_mm=problem.lips.min_distance(u),
                teeth_nodes=problem.teeth_contact.contact_nodes(u), teeth_min_gap_mm=problem.teeth_contact.min_gap(u))


def run(model_path, motion: str, comm, time_step: float, write) -> dict:
    model = load_model(model_path, comm)
    dynamic_problem, quasistatic = contact_problem(model), contact_problem(model)
    rest = dynamic_problem.rest_controls()
    target = dynamic_problem.activation_vector(model.expressions[EXPRESSIONS[motion]])

    def controls_at(t):  # switched on along a smooth ramp, then held
        s = min(t / ONSET, 1.0)
        return Controls(s * s * (3 - 2 * s) * target, rest.cranium, rest.jaw)

    dynamic = dynamic_problem.dynamics(DynamicSettings(time_step=time_step))
    markers = marker_nodes(dynamic_problem, model)
    times = np.arange(0.0, DURATION + 0.5 / FRAME_RATE, 1.0 / FRAME_RATE)
    rows = []
    tets = model.mesh.topology.index_map(3).size_global

    def frame(index, t, report):
        began = time.perf_counter()
        qs, failed = None, None
        try:
            qs = quasistatic.solve(activations=controls_at(t).activations) if index else None
        except EquilibriumError as error:  # recorded; the quasistatic face stays at its last equilibrium
            failed = str(error)
        qs_seconds = comm.allreduce(time.perf_counter() - began, op=MPI.MAX)
        norms = np.linalg.norm((dynamic_problem.u.x.array - quasistatic.u.x.array).reshape(-1, 3), axis=1)
        row = dict(tets=tets, ranks=comm.size, motion=motion, frame=index, time_s=round(t, 6),
                   quasistatic_failed=failed,
                   marker_difference_mm=None if failed else comm.allreduce(float(norms[markers].max(initial=0.0)),
                                                                           op=MPI.MAX),
                   max_difference_mm=None if failed else comm.allreduce(float(norms.max(initial=0.0)), op=MPI.MAX),
                   dynamic_seconds=comm.allreduce(report.seconds if report else 0.0, op=MPI.MAX),
                   substeps=report.substeps if report else 0,
                   dynamic_newton_iterations=report.newton_iterations if report else 0,
                   held_moves_so_far=dynamic.held_moves,
                   quasistatic_seconds=qs_seconds, quasistatic_newton_iterations=qs.newton_iterations if qs else 0,
                   dynamic_contact=contact_state(dynamic_problem), quasistatic_contact=contact_state(quasistatic))
        rows.append(row)
        write(row)

    try:
        dynamic.run(controls_at, times, frame)
    except DynamicsError as error:  # recorded; the other motions still run
        failure = dict(summary=True, tets=tets, ranks=comm.size, motion=motion, time_step_s=time_step,
                       frames=len(rows), failed=str(error))
        write(failure)
        return failure
    moving = [row for row in rows if row["frame"] > 0]
    compared = [row for row in rows if row["quasistatic_failed"] is None]
    summary = dict(summary=True, tets=tets, ranks=comm.size, motion=motion, time_step_s=time_step, frames=len(rows),
                   quasistatic_failures=len(rows) - len(compared),
                   max_marker_difference_mm=max(row["marker_difference_mm"] for row in compared),
                   max_difference_mm=max(row["max_difference_mm"] for row in compared),
                   dynamic_seconds_per_frame=float(np.mean([row["dynamic_seconds"] for row in moving])),
                   dynamic_newton_per_frame=float(np.mean([row["dynamic_newton_iterations"] for row in moving])),
                   quasistatic_seconds_per_frame=float(np.mean([row["quasistatic_seconds"] for row in moving])),
                   quasistatic_newton_per_frame=float(np.mean([row["quasistatic_newton_iterations"] for row in moving])),
                   held_moves=dynamic.held_moves,
                   max_lip_pairs=max(row["dynamic_contact"]["lip_pairs"] for row in rows),
                   min_lip_distance_mm=min(row["dynamic_contact"]["lip_min_distance_mm"] for row in rows),
                   max_teeth_nodes=max(row["dynamic_contact"]["teeth_nodes"] for row in rows),
                   min_teeth_gap_mm=min(row["dynamic_contact"]["teeth_min_gap_mm"] for row in rows))
    summary["cost_ratio"] = summary["dynamic_seconds_per_frame"] / summary["quasistatic_seconds_per_frame"]
    write(summary)
    return summary


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--tets", type=int, default=5000)
    parser.add_argument("--motions", nargs="+", default=list(EXPRESSIONS), choices=list(EXPRESSIONS))
    parser.add_argument("--time-step", type=float, default=1.0 / 240.0, help="largest substep (s)")
    parser.add_argument("--out", type=pathlib.Path, required=True, help="JSON-lines file")
    args = parser.parse_args()
    comm = MPI.COMM_WORLD
    started, path, write = start_rows(args, comm)
    for motion in args.motions:
        run(path, motion, comm, args.time_step, write)
    if comm.rank == 0:
        provenance.append(args.out, started)


if __name__ == "__main__":
    main()
