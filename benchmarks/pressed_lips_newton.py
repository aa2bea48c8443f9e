"""Newton on pressed lips: corrections that climb the energy, refused or taken (docs/contact.md,
"Newton with pressed lips").

The frames of the bilabial take (``capture/synthetic.py``, "ma ba pa", 60 frames at 60 Hz) from
``--start``, solved one after the other from the last equilibrium as the synthetic take solves
its truth, with the lips on each other and the lining on the teeth (as ``fit --contact``), in two
variants, each on a problem of its own: ``refuse`` (the solver's default: a correction from a
tangent holding the lips' exact Hessian that is no descent direction of the total energy is solved
again with the projected Hessian, ``QuasistaticSolver.refuse_ascent``) and ``take`` (such
corrections taken). Per frame: Newton iterations, factorisations, refused corrections, accepted
Newton steps that raised the total energy (beyond 1e-9 of it), Newton solves whose start had no
finite residual (a node inside the teeth or the lips through each other: the solve fails at once),
load steps, seconds, whether the frame had to be solved from rest (a failed solve, as the synthetic
take does), the lips' smallest distance. ``--head-motion``: the take with the head moving.

    python benchmarks/pressed_lips_newton.py --tets 5000 --frames 4 \\
        --out benchmarks/results/contact/pressed_lips_newton_5k.json
"""
import argparse
import json
import pathlib
import sys
import time

from mpi4py import MPI
import numpy as np
from petsc4py import PETSc

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
from contact_tracking import NewtonCount  # noqa: E402
from provenance import record  # noqa: E402
from face_dolfinx.capture.synthetic import control_curves, truth_contact_options  # noqa: E402
from face_dolfinx.equilibrium.solver import EquilibriumError  # noqa: E402
from face_dolfinx.model.anatomy import build_builtin_face  # noqa: E402
from face_dolfinx.model.bones import jaw_pose  # noqa: E402
from face_dolfinx.model.folder import load_model  # noqa: E402
from face_dolfinx.physics.problem import FaceProblem  # noqa: E402

VARIANTS = ("refuse", "take")
ROUND_OFF = 1e-9  # relative energy change below which a rise is round-off


class EnergyRises:
    """SNES monitor: counts the Newton iterates whose total energy exceeds the previous one's."""

    def __init__(self, solver):
        self.solver, self.rises, self.last = solver, 0, None

    def __call__(self, snes, iteration: int, norm: float) -> None:
        unknown = self.solver.unknown.vector
        snes.getSolution().copy(unknown)
        unknown.ghostUpdate(addv=PETSc.InsertMode.INSERT, mode=PETSc.ScatterMode.FORWARD)
        energy = self.solver.energy()
        if iteration > 0 and self.last is not None and energy > self.last + ROUND_OFF * abs(self.last):
            self.rises += 1
        self.last = energy


def run(model, variant: str, frames: range, comm, head_motion: bool = False) -> list[dict]:
    problem = FaceProblem(model, **truth_contact_options(model, "lips+teeth", where="--variant"))
    solver = problem.solver
    solver.refuse_ascent = variant == "refuse"
    rises = EnergyRises(solver)
    solver.snes.setMonitor(rises)
    activations, tmj, head = control_curves(model, "bilabial", 60, head_motion=head_motion)
    newton = NewtonCount(solver, check_starts=True)
    rows = []
    for frame in frames:
        before = dict(its=newton.iterations, fact=solver.factorizations, refused=solver.refused_exact_tangents,
                      rises=rises.rises, nonfinite=newton.nonfinite_starts)
        controls = dict(activations=activations[frame], cranium=head[frame], jaw=jaw_pose(model.jaw, *tmj[frame]))
        began = time.perf_counter()
        from_rest = False
        try:
            report = problem.solve(**controls)
        except EquilibriumError:
            from_rest = True
            problem.reset_to_rest()
            report = problem.solve(**controls)
        rows.append(dict(variant=variant, frame=frame, newton_iterations=newton.iterations - before["its"],
                         factorizations=solver.factorizations - before["fact"],
                         refused_corrections=solver.refused_exact_tangents - before["refused"],
                         energy_rises=rises.rises - before["rises"],
                         nonfinite_starts=newton.nonfinite_starts - before["nonfinite"],
                         load_steps=report.load_steps, from_rest=from_rest,
                         seconds=round(time.perf_counter() - began, 2),
                         lip_distance_mm=problem.lips.min_distance(problem.u.x.array)))
        if comm.rank == 0:
            print(json.dumps(rows[-1]), flush=True)
    return rows


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tets", type=int, default=5000)
    parser.add_argument("--start", type=int, default=5, help="first frame of the take (5: the lips closing)")
    parser.add_argument("--frames", type=int, default=4)
    parser.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=VARIANTS)
    parser.add_argument("--head-motion", action="store_true", help="the take with the head moving")
    parser.add_argument("--out", required=True)
    args = parser.parse_args()
    comm = MPI.COMM_WORLD
    model = load_model(build_builtin_face(target_tets=args.tets, comm=comm), comm)
    frames = range(args.start, args.start + args.frames)
    rows = [row for variant in args.variants for row in run(model, variant, frames, comm, args.head_motion)]
    if comm.rank == 0:
        summary = {variant: {key: int(np.sum([r[key] for r in rows if r["variant"] == variant]))
                             for key in ("newton_iterations", "factorizations", "refused_corrections",
                                         "energy_rises", "nonfinite_starts", "load_steps", "from_rest")}
                   for variant in args.variants}
        out = pathlib.Path(args.out)
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(dict(rows=rows, totals=summary), indent=1) + "\n")
        print(json.dumps(summary))
        record(out, tets=args.tets, ranks=comm.size)


if __name__ == "__main__":
    main()
