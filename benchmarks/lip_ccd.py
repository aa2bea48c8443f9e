"""The narrow phase of the lips' collision-free step bound: additive CCD against tight-inclusion CCD.

The lips of the built-in face are closed hard (jaw ``--jaw`` degrees beyond rest, orbicularis oris
at 1) with lip self-contact; every Newton step's line-search segment (the lip nodes at the iterate
and at the step's far end) is recorded. Each narrow phase then bounds every recorded segment:
``ipctk.compute_collision_free_stepsize`` with the minimum distance the solver asks for. Prints a
JSON row per narrow phase: mean and largest milliseconds per call, and the step fractions' range.

    python benchmarks/lip_ccd.py --tets 5000 --out benchmarks/results/contact/lip_ccd_5k.json
"""
import argparse
import json
import pathlib
import sys
import time

import ipctk
from mpi4py import MPI
import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
from provenance import record  # noqa: E402
from face_dolfinx.model.anatomy import build_builtin_face  # noqa: E402
from face_dolfinx.model.bones import jaw_pose  # noqa: E402
from face_dolfinx.model.folder import load_model  # noqa: E402
from face_dolfinx.physics.problem import FaceProblem  # noqa: E402
from face_dolfinx.physics.self_contact import CCD_KEEP, LipContactSettings  # noqa: E402


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tets", type=int, default=5000)
    parser.add_argument("--jaw", type=float, default=-2.0)
    parser.add_argument("--out", required=True)
    args = parser.parse_args()
    comm = MPI.COMM_SELF  # one process: the narrow phase is per rank anyway
    model = load_model(build_builtin_face(target_tets=args.tets, comm=comm), comm)
    problem = FaceProblem(model, lip_contact=LipContactSettings())
    lips = problem.lips
    segments = []
    bound = lips.admissible_fraction

    def recorded(start, end):
        segments.append((lips.positions(start), lips.positions(end),
                         (1.0 - CCD_KEEP) * lips.min_distance(start, lips.dhat)))
        return bound(start, end)

    lips.admissible_fraction = recorded  # this benchmark's probe, on its own object
    sphincter = {m.name: 1.0 for m in model.muscles if m.name.startswith("orbicularis_oris")}
    problem.solve(activations=sphincter, jaw=jaw_pose(model.jaw, np.radians(args.jaw)))
    rows = []
    for name, narrow_phase in (("additive", ipctk.AdditiveCCD()), ("tight_inclusion", ipctk.TightInclusionCCD())):
        seconds, fractions = [], []
        for v0, v1, keep in segments:
            began = time.perf_counter()
            fractions.append(ipctk.compute_collision_free_stepsize(lips.mesh, v0, v1, keep,
                                                                   narrow_phase_ccd=narrow_phase))
            seconds.append(time.perf_counter() - began)
        rows.append(dict(narrow_phase=name, calls=len(segments), mean_ms=round(1e3 * float(np.mean(seconds)), 2),
                         max_ms=round(1e3 * float(np.max(seconds)), 2), smallest_fraction=float(np.min(fractions)),
                         mean_fraction=round(float(np.mean(fractions)), 4), lip_nodes=lips.surface.num_nodes,
                         tets=model.mesh.topology.index_map(3).size_global))
    out = pathlib.Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(rows, indent=1) + "\n")
    print(json.dumps(rows, indent=1))
    record(out, tets=args.tets, ranks=1)


if __name__ == "__main__":
    main()
