"""How far the lips slide on each other in a speech-like take: the room the tangent's pattern needs.

The synthetic bilabial take (lips pressed together with the jaw closed, then an open vowel;
``--take-frames`` frames at 60 Hz, the head moving) is solved on the built-in face with the
lips on each other and the lining on the teeth, as ``fit --contact`` solves it. After each frame:
the largest rest distance between the two primitives of a barrier pair (``LipContact.slide``, the
lips' slide with their rest gap), the barrier pairs, and the entries the contact added outside the
tangent's pattern (PETSc's reallocations; each costs MUMPS a new analysis). One JSON line per
frame, then a summary with the pattern's radius (``LipContact.pattern_radius``) and
``PATTERN_SLIDE``.

    python benchmarks/lip_slide.py --tets 5000 --out benchmarks/results/contact/lip_slide_5k.json
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
from provenance import write_result  # noqa: E402
from face_dolfinx.capture.synthetic import synthesize_take, truth_contact_options  # noqa: E402
from face_dolfinx.fitting import MarkerSet  # noqa: E402
from face_dolfinx.model.anatomy import build_builtin_face  # noqa: E402
from face_dolfinx.model.folder import load_model  # noqa: E402
from face_dolfinx.physics.problem import FaceProblem  # noqa: E402
from face_dolfinx.physics.self_contact import PATTERN_SLIDE  # noqa: E402


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tets", type=int, default=5000)
    parser.add_argument("--take-frames", type=int, default=60)
    parser.add_argument("--out", required=True)
    args = parser.parse_args()
    comm = MPI.COMM_WORLD
    began = time.perf_counter()
    model = load_model(build_builtin_face(target_tets=args.tets, comm=comm), comm)
    problem = FaceProblem(model, **truth_contact_options(model))
    lips, tangent = problem.lips, problem.solver.tangent
    names = list(model.markers)
    sites = np.array([model.markers[name] for name in names])
    rows = []

    def measure(frame):
        u = problem.u.x.array
        allocations = int(tangent.getInfo(PETSc.Mat.InfoType.GLOBAL_SUM)["mallocs"])
        rows.append(dict(frame=frame, slide_mm=round(lips.slide(u), 3), lip_pairs=lips.pairs(u),
                         tangent_allocations=allocations))
        if comm.rank == 0:
            print(json.dumps(rows[-1]), flush=True)

    synthesize_take(problem, MarkerSet(problem, sites, names=names), model, "bilabial", n_frames=args.take_frames,
                    head_motion=True, progress=measure)
    summary = dict(tets=model.mesh.topology.index_map(3).size_global, ranks=comm.size, lip_nodes=lips.surface.num_nodes,
                   largest_slide_mm=max(row["slide_mm"] for row in rows), pattern_slide_mm=PATTERN_SLIDE,
                   pattern_radius_mm=round(lips.pattern_radius, 3), pattern_pairs=len(lips.coupled_blocks()),
                   tangent_allocations=rows[-1]["tangent_allocations"],
                   seconds=round(time.perf_counter() - began, 1), frames=rows)
    if comm.rank == 0:
        print(json.dumps({key: value for key, value in summary.items() if key != "frames"}), flush=True)
    write_result(args.out, summary, tets=args.tets, ranks=comm.size)


if __name__ == "__main__":
    main()
