"""Command line of face_dolfinx (``python run.py ...`` or ``face-dolfinx ...``, also under mpirun).

Subcommands:
  build     generate the built-in face at a resolution and print the model folder
  simulate  equilibrium shapes for named expressions or given activations -> XDMF + PNG
  demo      the README's main job: build the default face, simulate a few expressions
"""
import argparse
import json
import logging
import math
import pathlib
import sys
import time

from mpi4py import MPI
import numpy as np

log = logging.getLogger("face_dolfinx")

DEMO_EXPRESSIONS = ["smile", "jaw_open", "brow_raise", "frown", "pucker"]


def _setup_logging(folder: pathlib.Path | None = None, verbose: bool = False) -> None:
    """Log to the console and (optionally) a file in ``folder``, from rank 0 only."""
    root = logging.getLogger()
    root.handlers.clear()
    if MPI.COMM_WORLD.rank != 0:
        root.addHandler(logging.NullHandler())
        return
    level = logging.DEBUG if verbose else logging.INFO
    root.setLevel(logging.WARNING)
    log.setLevel(level)
    fmt = logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s", "%H:%M:%S")
    console = logging.StreamHandler(sys.stdout)
    console.setFormatter(fmt)
    # The form compiler logs its C builds at INFO on the root logger: keep only ours and warnings.
    console.addFilter(lambda record: record.name.startswith("face_dolfinx") or record.levelno >= logging.WARNING)
    root.addHandler(console)
    if folder is not None:
        handler = logging.FileHandler(folder / "run.log")
        handler.setFormatter(fmt)
        root.addHandler(handler)


def _model_from_args(args):
    from .anatomy import build_builtin_face
    from .model import load_model
    path = pathlib.Path(args.model) if args.model else build_builtin_face(target_tets=args.tets)
    return load_model(path, MPI.COMM_WORLD)


def _expression_controls(model, name: str):
    """Activations (dict) and jaw frame of a named expression stored in the model."""
    from .bones import AffineMap, jaw_pose
    if name not in model.expressions:
        known = ", ".join(sorted(model.expressions))
        raise SystemExit(f"unknown expression {name!r}; the model defines: {known}")
    spec = dict(model.expressions[name])
    opening = math.radians(spec.pop("jaw_opening_deg", 0.0))
    jaw = jaw_pose(model.jaw, opening) if opening else AffineMap()
    return spec, jaw


def simulate(model, expressions: list[str], out: pathlib.Path, *, degree: int = 1,
             overwrite: bool = False, render: bool = True) -> list[dict]:
    """Solve each expression from the previous equilibrium and write one result folder."""
    from .output import FaceWriter, atomic_directory
    from .problem import FaceProblem
    comm = MPI.COMM_WORLD
    for name in expressions:  # fail before any work, not halfway through
        _expression_controls(model, name)
    start = time.perf_counter()
    problem = FaceProblem(model, degree=degree)
    log.info("model %s: %d tets, %d muscles, %d dofs, %d muscle slots per cell; set-up %.1f s",
             model.name, model.mesh.topology.index_map(3).size_global, problem.num_muscles,
             problem.V.dofmap.index_map.size_global * 3, len(problem.slots.weight),
             time.perf_counter() - start)
    rows = []
    with atomic_directory(out, comm, overwrite=overwrite) as staging:
        with FaceWriter(problem, staging / "face.xdmf") as writer:
            writer.write(0.0)
            for step, name in enumerate(expressions, start=1):
                activations, jaw = _expression_controls(model, name)
                report = problem.solve(activations=activations, jaw=jaw)
                displacement = comm.allreduce(np.abs(problem.u.x.array).max() if problem.u.x.array.size else 0.0,
                                              op=MPI.MAX)
                row = dict(expression=name, newton_iterations=report.newton_iterations,
                           load_steps=report.load_steps, seconds=round(report.seconds, 3),
                           max_displacement_mm=round(displacement, 4))
                rows.append(row)
                log.info("%-12s Newton %2d its, %d load step(s), %.2f s, max |u| %.2f mm", name,
                         report.newton_iterations, report.load_steps, report.seconds, displacement)
                writer.write(float(step))
                if render:
                    _render_expression(problem, staging / f"{step:02d}_{name}.png", name)
        if comm.rank == 0:
            (staging / "summary.json").write_text(json.dumps(
                dict(model=str(model.path), expressions=rows, ranks=comm.size), indent=2))
    return rows


def _render_expression(problem, path: pathlib.Path, title: str) -> None:
    from .output import displacement_at
    from .render import render_skin
    points, triangles = problem.model.skin_surface()
    moved = points + displacement_at(problem.u, points)
    if MPI.COMM_WORLD.rank == 0:
        render_skin(moved, triangles, path, title=title)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="face-dolfinx", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("-v", "--verbose", action="store_true")
    sub = parser.add_subparsers(dest="command", required=True)

    build = sub.add_parser("build", help="generate the built-in face model")
    build.add_argument("--tets", type=int, default=50_000, help="target number of tetrahedra")

    for name, helptext in (("simulate", "shapes for named expressions"),
                           ("demo", "the main job: default face, a few expressions")):
        p = sub.add_parser(name, help=helptext)
        p.add_argument("--model", help="model folder (default: the built-in face)")
        p.add_argument("--tets", type=int, default=50_000, help="built-in face resolution")
        p.add_argument("--degree", type=int, default=1, choices=(1, 2), help="displacement degree")
        p.add_argument("--out", default=f"results/{name}", help="result folder")
        p.add_argument("--overwrite", action="store_true", help="replace an existing result folder")
        p.add_argument("--no-render", action="store_true", help="skip the PNG renders")
        if name == "simulate":
            p.add_argument("expressions", nargs="+", help="expression names defined in the model")

    args, petsc_args = parser.parse_known_args(argv)
    # Unparsed -face_* arguments are PETSc options (e.g. -face_pc_type hypre).
    if petsc_args:
        from petsc4py import PETSc
        unknown = [a for a in petsc_args if not a.startswith("-face_") and not _is_value(a, petsc_args)]
        if unknown:
            parser.error(f"unrecognised arguments: {' '.join(unknown)}")
        PETSc.Options().insertString(" ".join(petsc_args))
    _setup_logging(verbose=args.verbose)

    if args.command == "build":
        from .anatomy import build_builtin_face
        path = build_builtin_face(target_tets=args.tets)
        if MPI.COMM_WORLD.rank == 0:
            print(path)
        return 0

    model = _model_from_args(args)
    expressions = args.expressions if args.command == "simulate" else \
        [e for e in DEMO_EXPRESSIONS if e in model.expressions]
    out = pathlib.Path(args.out)
    rows = simulate(model, expressions, out, degree=args.degree, overwrite=args.overwrite,
                    render=not args.no_render)
    if MPI.COMM_WORLD.rank == 0:
        print(f"results: {out.resolve()} ({len(rows)} expressions; face.xdmf for ParaView, PNG renders)")
    return 0


def _is_value(arg: str, args: list[str]) -> bool:
    """True if ``arg`` is the value following a -face_* option."""
    i = args.index(arg)
    return i > 0 and args[i - 1].startswith("-face_") and not arg.startswith("-")
