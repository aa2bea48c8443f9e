"""How far Newton's energy stop leaves a contact equilibrium from the converged one
(docs/performance.md, "Stopping on energy").

The bilabial take (``capture/synthetic.py``, "ma ba pa", 60 frames at 60 Hz, the head moving) is
solved as its truth (``fit --contact``'s lips and teeth, Newton to its default step tolerance) for
the frames from ``--start``. Then each frame after the first is solved again on a problem with
``fit --fast``'s solver (``--contact``), from the truth's equilibrium of the frame before, once per
``--newton-energy-tolerance`` in ``--tolerances``; from where that stop left it, Newton goes on to a
step tolerance of ``--converged`` mm without the energy stop. Per frame and tolerance: the Newton
iterations of the stopped solve, the largest node distance and the marker distances (largest,
RMS) between the stopped and the converged equilibrium, the lip barrier pairs.

    python benchmarks/energy_stop_accuracy.py --tets 20000 \\
        --out benchmarks/results/contact/energy_stop_accuracy_20k.json
"""
import argparse
import json
import pathlib
import sys

from mpi4py import MPI
import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
from provenance import record  # noqa: E402
from face_dolfinx.capture.synthetic import synthesize_take, truth_contact_options  # noqa: E402
from face_dolfinx.fitting import MarkerSet  # noqa: E402
from face_dolfinx.model.anatomy import build_builtin_face  # noqa: E402
from face_dolfinx.model.folder import load_model  # noqa: E402
from face_dolfinx.physics.problem import FaceProblem  # noqa: E402
from face_dolfinx.tracking import PRESETS, Tracker  # noqa: E402


def truth_equilibria(model, sites, names, frames):
    """The truth's equilibrium (controls, displacement) per frame, kept as the take solves it."""
    problem = FaceProblem(model, **truth_contact_options(model))
    states = {}

    def keep(index):  # called with the frame's equilibrium in the problem
        states[frames[index]] = (problem.controls.copy(), problem.u.x.array.copy())
    synthesize_take(problem, MarkerSet(problem, sites, names=names), model, "bilabial", n_frames=60,
                    noise=0.5, head_motion=True, frames=frames, progress=keep)
    return states


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tets", type=int, default=20000)
    parser.add_argument("--start", type=int, default=4, help="first frame of the take (5: the lips closing)")
    parser.add_argument("--frames", type=int, default=9)
    parser.add_argument("--tolerances", type=float, nargs="+", default=[10.0, 100.0, 300.0, 1000.0],
                        help="Newton energy tolerances (mN mm)")
    parser.add_argument("--converged", type=float, default=1e-7, help="step tolerance of the converged solve (mm)")
    parser.add_argument("--out", required=True)
    args = parser.parse_args()
    comm = MPI.COMM_WORLD
    model = load_model(build_builtin_face(args.tets, comm=comm), comm)
    names = list(model.markers)
    sites = np.array([model.markers[name] for name in names])
    frames = range(args.start, args.start + args.frames)
    states = truth_equilibria(model, sites, names, frames)
    settings = PRESETS["fast"].updated(dict(contact=True))
    problem = Tracker(model, settings).problem
    markers = MarkerSet(problem, sites, names=names)
    solver = problem.solver
    rows = []
    for frame in frames[1:]:
        controls = states[frame][0]
        for tolerance in args.tolerances:
            problem.adopt(*states[frame - 1])
            solver.energy_tolerance, solver.step_tolerance = tolerance, settings.newton_tolerance
            report = problem.solve(activations=controls.activations, cranium=controls.cranium, jaw=controls.jaw)
            stopped = problem.u.x.array.copy()
            solver.energy_tolerance, solver.step_tolerance = None, args.converged
            converged, iterations, reason = solver.newton()
            if not converged:
                raise SystemExit(f"frame {frame}, tolerance {tolerance}: the converged solve failed ({reason})")
            node = np.linalg.norm((stopped - problem.u.x.array).reshape(-1, 3), axis=1)
            marker = np.linalg.norm(markers.positions(stopped, controls.cranium)
                                    - markers.positions(problem.u.x.array, controls.cranium), axis=1)
            rows.append(dict(frame=frame, energy_tolerance=tolerance, newton_iterations=report.newton_iterations,
                             iterations_to_converge=iterations,
                             max_node_mm=round(comm.allreduce(float(node.max(initial=0.0)), op=MPI.MAX), 5),
                             max_marker_mm=round(float(marker.max()), 5),
                             rms_marker_mm=round(float(np.sqrt(np.mean(marker**2))), 5),
                             lip_pairs=problem.lips.pairs(problem.u.x.array)))
            if comm.rank == 0:
                print(json.dumps(rows[-1]), flush=True)
    if comm.rank == 0:
        summary = {str(tolerance): dict(
            newton_iterations=sum(r["newton_iterations"] for r in rows if r["energy_tolerance"] == tolerance),
            **{key: max(r[key] for r in rows if r["energy_tolerance"] == tolerance)
               for key in ("max_node_mm", "max_marker_mm", "rms_marker_mm")})
            for tolerance in args.tolerances}
        out = pathlib.Path(args.out)
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(dict(rows=rows, by_tolerance=summary), indent=1) + "\n")
        print(json.dumps(summary))
    record(args.out, tets=args.tets, ranks=comm.size)


if __name__ == "__main__":
    main()
