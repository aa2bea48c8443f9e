"""Forward solve cost against mesh size: neutral -> expression on the built-in face.

For each resolution this builds (or reuses) the built-in face, sets up the problem and solves
the equilibrium from rest to each named expression (rest again between them), recording wall time,
Newton iterations, load steps and peak memory (summed over ranks). One line of JSON per
resolution goes to stdout; ``--table`` appends the rows to a Markdown table.

    mpirun -n 2 python benchmarks/forward_scaling.py --tets 5000 50000 400000
    python benchmarks/forward_scaling.py --collect docs/forward_performance.md runs/*.jsonl
"""
import argparse
import json
import math
import pathlib
import resource
import time

from mpi4py import MPI
import numpy as np


def peak_memory_gb(comm) -> float:
    """Peak resident memory of all ranks together (GB)."""
    kilobytes = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return comm.allreduce(kilobytes, op=MPI.SUM) / 1024**2


def run_resolution(target_tets: int, expressions: list[str], degree: int,
                   reuse_factorization: bool = False, coarse_tets: int | None = None,
                   krylov: bool = False, refresh_contraction: float | None = None) -> dict:
    from face_dolfinx.model.anatomy import build_builtin_face
    from face_dolfinx.model.bones import AffineMap, jaw_pose
    from face_dolfinx.equilibrium.coarse import CoarseStart
    from face_dolfinx.model.folder import load_model
    from face_dolfinx.physics.problem import FaceProblem

    comm = MPI.COMM_WORLD
    t0 = time.perf_counter()
    path = build_builtin_face(target_tets=target_tets)
    t_build = time.perf_counter() - t0
    t0 = time.perf_counter()
    model = load_model(path, comm)
    t_load = time.perf_counter() - t0
    t0 = time.perf_counter()
    problem = FaceProblem(model, degree=degree, reuse_factorization=reuse_factorization,
                          krylov_on_old_factor=krylov,
                          **({} if refresh_contraction is None else dict(refresh_contraction=refresh_contraction)))
    start = None
    if coarse_tets:
        coarse = FaceProblem(load_model(build_builtin_face(target_tets=coarse_tets), comm))
        start = CoarseStart(coarse, problem)
    t_setup = time.perf_counter() - t0
    row = dict(target_tets=target_tets, tets=model.mesh.topology.index_map(3).size_global,
               dofs=3 * problem.V.dofmap.index_map.size_global, ranks=comm.size, degree=degree,
               reuse_factorization=reuse_factorization, krylov=krylov, coarse_tets=coarse_tets,
               refresh_contraction=problem.solver.reuse_policy.refresh_contraction,
               build_s=round(t_build, 2), load_s=round(t_load, 2), setup_s=round(t_setup, 2),
               solves={})
    for name in expressions:
        spec = dict(model.expressions[name])
        opening = math.radians(spec.pop("jaw_opening_deg", 0.0))
        jaw = jaw_pose(model.jaw, opening) if opening else AffineMap()
        for rested in (problem, start.coarse) if start else (problem,):
            rested.u.x.array[:] = 0.0
            rested.solve(activations=np.zeros(problem.num_muscles), jaw=AffineMap())
        comm.barrier()
        t0 = time.perf_counter()
        factorizations = problem.solver.factorizations
        report = (start or problem).solve(activations=spec, jaw=jaw)
        comm.barrier()
        row["solves"][name] = dict(seconds=round(time.perf_counter() - t0, 2),
                                   newton=report.newton_iterations, load_steps=report.load_steps,
                                   factorizations=problem.solver.factorizations - factorizations)
    row["peak_memory_gb"] = round(peak_memory_gb(comm), 2)
    return row


TABLE_HEADER = ("| tets | dofs | ranks | factor reuse | coarse start | build s | setup s | expression | "
                "solve s | Newton its | factorisations | load steps | peak memory GB |\n"
                "|---|---|---|---|---|---|---|---|---|---|---|---|---|\n")


def _factor_reuse(row: dict) -> str:
    if not row.get("reuse_factorization"):
        return "no"
    return "krylov" if row.get("krylov") else "yes"


def markdown_rows(row: dict) -> str:
    return "".join(
        f"| {row['tets']} | {row['dofs']} | {row['ranks']} | {_factor_reuse(row)} | "
        f"{row.get('coarse_tets') or 'no'} | "
        f"{row['build_s']} | {row['setup_s']} | {name} | {s['seconds']} | {s['newton']} | "
        f"{s.get('factorizations', s['newton'])} | {s['load_steps']} | {row['peak_memory_gb']} |\n"
        for name, s in row["solves"].items())


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--tets", type=int, nargs="+", default=[5000, 20000, 50000])
    parser.add_argument("--expressions", nargs="+", default=["smile", "jaw_open"])
    parser.add_argument("--degree", type=int, default=1)
    parser.add_argument("--reuse-factorization", action="store_true",
                        help="modified Newton: the last MUMPS factor kept while iterations contract fast")
    parser.add_argument("--krylov", action="store_true",
                        help="with --reuse-factorization: GMRES on the exact tangent preconditioned by the "
                             "old factor instead of refactorising when modified Newton slows")
    parser.add_argument("--refresh-contraction", type=float, metavar="R",
                        help="with --reuse-factorization: refactorise when an iteration cuts the residual "
                             "less than this factor (FaceProblem's default if not given)")
    parser.add_argument("--coarse", type=int, metavar="TETS",
                        help="start every fine solve from the equilibrium of the built-in face at TETS "
                             "(face_dolfinx.equilibrium.coarse; Newton counts and factorisations are the fine model's)")
    parser.add_argument("--collect", nargs="+", metavar=("TABLE", "JSONL"),
                        help="write a Markdown table TABLE from JSON-lines files")
    args = parser.parse_args()
    if args.collect:
        table, *sources = args.collect
        rows = [json.loads(line) for src in sources for line in pathlib.Path(src).read_text().splitlines() if line]
        rows.sort(key=lambda r: (r["tets"], r["ranks"], r.get("reuse_factorization", False),
                                 r.get("coarse_tets") or 0))
        pathlib.Path(table).write_text(TABLE_HEADER + "".join(markdown_rows(r) for r in rows))
        return
    for target in args.tets:
        row = run_resolution(target, args.expressions, args.degree, args.reuse_factorization, args.coarse,
                             args.krylov, args.refresh_contraction)
        if MPI.COMM_WORLD.rank == 0:
            print(json.dumps(row), flush=True)


if __name__ == "__main__":
    main()
