"""The tangent's sparsity for lip contact: what its pattern costs the factorisation, and whether it
holds the pairs a hard closure couples.

The built-in face is built with lip self-contact once per pattern: the default (the pairs of an
upper and a lower lip node within ``PATTERN_SLIDE`` plus twice the lips' longest edge of each
other at rest, ``LipContact.coupled_blocks``), those pairs within each of ``--radii`` mm
(``LipContactSettings.pattern_radius``), and every pair of lip nodes, of one lip or both, within
each of ``--every-pair-within`` mm; and, for comparison, without lip contact. At rest every
pattern's tangent is factorised ``--rounds`` times (MUMPS Cholesky, the solver's options), the
patterns in turn within each round so that the machine's drift falls on all of them: the
tangent's entries, the factor's entries and flops (MUMPS INFOG(29), RINFOG(3)) and the median
seconds of the rounds after the first (which also analyses the pattern). Then, unless
``--no-closure``, the lips are closed hard (jaw ``--jaw`` degrees beyond rest, orbicularis oris at
1): pairs beyond the pattern are added as new nonzeros when they appear, and MUMPS analyses the
changed pattern at the next factorisation; the row gets the tangent's entries at the end, PETSc's
allocations during the solve, Newton iterations, factorisations and seconds. One JSON row per
pattern.

    python benchmarks/lip_pattern.py --tets 5000 --radii 0 3 --every-pair-within 15 \\
        --out benchmarks/results/contact/lip_pattern_5k.json
    mpirun -n 2 python benchmarks/lip_pattern.py --tets 400000 --radii --every-pair-within 15 --no-closure \\
        --out benchmarks/results/contact/lip_pattern_factor_404k_np2.json
"""
import argparse
import contextlib
import json
import pathlib
import sys
import time

from mpi4py import MPI
from petsc4py import PETSc
import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
from provenance import write_result  # noqa: E402
from face_dolfinx.model.anatomy import build_builtin_face  # noqa: E402
from face_dolfinx.model.bones import jaw_pose  # noqa: E402
from face_dolfinx.model.folder import load_model  # noqa: E402
from face_dolfinx.physics.problem import FaceProblem  # noqa: E402
from face_dolfinx.physics.self_contact import LipContact, LipContactSettings  # noqa: E402


@contextlib.contextmanager
def every_lip_pair_in_pattern(radius: float):
    """Problems built inside get a tangent whose pattern holds every pair of lip nodes within
    ``radius`` of each other at rest, of one lip or both (``LipContact.coupled_blocks`` replaced
    meanwhile)."""
    across = LipContact.coupled_blocks

    def every_pair(lips):
        rest = lips.surface.rest
        i, j = np.nonzero(np.linalg.norm(rest[:, None, :] - rest[None, :, :], axis=2) <= radius)
        return np.column_stack([lips.global_blocks[i], lips.global_blocks[j]])
    LipContact.coupled_blocks = every_pair
    try:
        yield
    finally:
        LipContact.coupled_blocks = across


def factor_costs(problems: list, rounds: int, comm) -> list[dict]:
    """Each problem's tangent at rest factorised ``rounds`` times, the problems in turn within a
    round: its entries, the factor's entries and flops, the median seconds after the first round."""
    seconds = [[] for _ in problems]
    for _ in range(rounds):
        for problem, spent in zip(problems, seconds):
            comm.Barrier()
            began = time.perf_counter()
            problem.solver.factorize()
            comm.Barrier()
            spent.append(time.perf_counter() - began)
    rows = []
    for problem, spent in zip(problems, seconds):
        factor = problem.solver.snes.getKSP().getPC().getFactorMatrix()
        rows.append(dict(tangent_entries=int(problem.solver.tangent.getInfo(PETSc.Mat.InfoType.GLOBAL_SUM)["nz_used"]),
                         factor_entries=int(factor.getMumpsInfog(29)),
                         factor_gflops=round(factor.getMumpsRinfog(3) / 1e9, 2),
                         factorise_seconds=round(float(np.median(spent[1:])), 2),
                         factorise_seconds_by_round=[round(t, 2) for t in spent]))
    return rows


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tets", type=int, default=5000)
    parser.add_argument("--jaw", type=float, default=-2.0)
    parser.add_argument("--radii", type=float, nargs="*", default=[0.0, 3.0],
                        help="upper-lower pairs within these rest distances (mm), besides the default pattern")
    parser.add_argument("--every-pair-within", type=float, nargs="*", default=[15.0], metavar="RADIUS",
                        help="every pair of lip nodes within these rest distances (mm)")
    parser.add_argument("--rounds", type=int, default=5, help="factorisations of each tangent at rest")
    parser.add_argument("--no-closure", action="store_true", help="measure the factorisation at rest only")
    parser.add_argument("--out", required=True)
    args = parser.parse_args()
    comm = MPI.COMM_WORLD
    model = load_model(build_builtin_face(target_tets=args.tets, comm=comm), comm)
    sphincter = {m.name: 1.0 for m in model.muscles if m.name.startswith("orbicularis_oris")}
    patterns = [("default", None, contextlib.nullcontext)] + [("upper-lower", r, contextlib.nullcontext)
                                                              for r in args.radii]
    patterns += [("every pair", r, lambda r=r: every_lip_pair_in_pattern(r)) for r in args.every_pair_within]
    problems, rows = [], []
    for pairs, radius, pattern in patterns:
        with pattern():
            problem = FaceProblem(model, lip_contact=LipContactSettings(pattern_radius=None if pairs == "every pair"
                                                                        else radius))
            lips = problem.lips
            rows.append(dict(pairs=pairs, pattern_radius=round(radius if pairs == "every pair" else lips.pattern_radius, 3),
                             pattern_pairs=len(lips.coupled_blocks()), lip_nodes=lips.surface.num_nodes))
        problems.append(problem)
    problems.append(FaceProblem(model))
    rows.append(dict(pairs="no lip contact"))
    for row, costs in zip(rows, factor_costs(problems, args.rounds, comm)):
        row.update(costs)
    for row, problem in zip(rows, problems):
        if not args.no_closure and problem.lips is not None:
            entries = problem.solver.tangent.getInfo(PETSc.Mat.InfoType.GLOBAL_SUM)["nz_allocated"]
            factorizations = problem.solver.factorizations
            began = time.perf_counter()
            report = problem.solve(activations=sphincter, jaw=jaw_pose(model.jaw, np.radians(args.jaw)))
            seconds = time.perf_counter() - began
            info = problem.solver.tangent.getInfo(PETSc.Mat.InfoType.GLOBAL_SUM)
            row.update(entries_at_setup=int(entries), entries_at_end=int(info["nz_allocated"]),
                       allocations_during_solve=int(info["mallocs"]), converged=report.converged,
                       newton_iterations=report.newton_iterations, load_steps=report.load_steps,
                       factorizations=problem.solver.factorizations - factorizations, seconds=round(seconds, 2))
        row.update(tets=model.mesh.topology.index_map(3).size_global, ranks=comm.size)
        if comm.rank == 0:
            print(json.dumps(row), flush=True)
    write_result(args.out, rows, tets=args.tets, ranks=comm.size)


if __name__ == "__main__":
    main()
