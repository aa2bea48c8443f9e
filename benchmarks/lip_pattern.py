"""The tangent's sparsity for lip contact: widened once at set-up, or grown as pairs appear.

The built-in face's lips are closed hard (jaw ``--jaw`` degrees beyond rest, orbicularis oris at
1) with lip self-contact, once per ``--radii``: the tangent is built with the lip node pairs within
that rest distance (``LipContactSettings.pattern_radius``); pairs beyond it are added as new
nonzeros when they appear, and MUMPS analyses the changed pattern at the next factorisation. One
JSON row per radius: the tangent's entries at set-up and at the end, PETSc's allocations during
the solve, Newton iterations, factorisations and seconds.

    python benchmarks/lip_pattern.py --tets 5000 --radii 0 3 15 --out benchmarks/results/contact/lip_pattern_5k.json
"""
import argparse
import json
import pathlib
import sys
import time

from mpi4py import MPI
from petsc4py import PETSc
import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
from provenance import record  # noqa: E402
from face_dolfinx.model.anatomy import build_builtin_face  # noqa: E402
from face_dolfinx.model.bones import jaw_pose  # noqa: E402
from face_dolfinx.model.folder import load_model  # noqa: E402
from face_dolfinx.physics.problem import FaceProblem  # noqa: E402
from face_dolfinx.physics.self_contact import LipContactSettings  # noqa: E402


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tets", type=int, default=5000)
    parser.add_argument("--jaw", type=float, default=-2.0)
    parser.add_argument("--radii", type=float, nargs="+", default=[0.0, 3.0, 15.0])
    parser.add_argument("--out", required=True)
    args = parser.parse_args()
    comm = MPI.COMM_WORLD
    model = load_model(build_builtin_face(target_tets=args.tets, comm=comm), comm)
    sphincter = {m.name: 1.0 for m in model.muscles if m.name.startswith("orbicularis_oris")}
    rows = []
    for radius in args.radii:
        problem = FaceProblem(model, lip_contact=LipContactSettings(pattern_radius=radius))
        tangent = problem.solver.tangent
        entries = tangent.getInfo(PETSc.Mat.InfoType.GLOBAL_SUM)["nz_allocated"]
        began = time.perf_counter()
        report = problem.solve(activations=sphincter, jaw=jaw_pose(model.jaw, np.radians(args.jaw)))
        seconds = time.perf_counter() - began
        info = problem.solver.tangent.getInfo(PETSc.Mat.InfoType.GLOBAL_SUM)
        rows.append(dict(pattern_radius=radius, entries_at_setup=int(entries), entries_at_end=int(info["nz_allocated"]),
                         allocations_during_solve=int(info["mallocs"]), converged=report.converged,
                         newton_iterations=report.newton_iterations, load_steps=report.load_steps,
                         factorizations=problem.solver.factorizations, seconds=round(seconds, 2),
                         tets=model.mesh.topology.index_map(3).size_global, ranks=comm.size))
        if comm.rank == 0:
            print(json.dumps(rows[-1]), flush=True)
    if comm.rank == 0:
        out = pathlib.Path(args.out)
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(rows, indent=1) + "\n")
    record(args.out, tets=args.tets, ranks=comm.size)


if __name__ == "__main__":
    main()
