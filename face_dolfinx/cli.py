"""Command line of face_dolfinx (``python run.py ...`` or ``face-dolfinx ...``, also under mpirun).

Subcommands:
  build     generate the built-in face at a resolution and print the model folder
  simulate  equilibrium shapes for named expressions -> XDMF + PNG
  synth     a synthetic take of known truth (markers with noise, outliers, gaps) -> TRC/CSV/C3D
  fit       a take -> activations, head and jaw motion per frame (resumable)
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


def _root_first(action):
    """Run ``action`` on rank 0 and re-raise its exception on every rank."""
    comm = MPI.COMM_WORLD
    value, error = None, None
    if comm.rank == 0:
        try:
            value = action()
        except Exception as exc:  # every rank must stop, not only rank 0
            error = exc
    error = comm.bcast(error, root=0)
    if error is not None:
        raise error
    return comm.bcast(value, root=0)


def synth(model, args) -> None:
    """Solve the face along a scenario, sample its marker sites, write capture + truth."""
    from .capture import write_capture
    from .fitting import MarkerSet
    from .problem import FaceProblem
    from .synthetic import synthesize_take
    out = pathlib.Path(args.out)
    if out.exists() and not args.overwrite:
        raise FileExistsError(f"{out} already exists; pass --overwrite to replace it")
    problem = FaceProblem(model)
    names = list(model.markers)
    markers = MarkerSet(problem, np.array([model.markers[n] for n in names]), names=names)
    capture, truth = synthesize_take(
        problem, markers, model, args.scenario, n_frames=args.frames, frame_rate=args.rate,
        noise=args.noise, outliers=args.outliers, gaps=args.gaps, head_motion=not args.no_head_motion,
        seed=args.seed, progress=lambda f: log.info("synth frame %d/%d", f + 1, args.frames))

    def write():
        out.parent.mkdir(parents=True, exist_ok=True)
        write_capture(capture, out)
        np.savez(truth_path(out), activations=truth.activations, tmj=truth.tmj,
                 head_matrices=np.array([h.matrix for h in truth.head]),
                 head_translations=np.array([h.translation for h in truth.head]),
                 clean_positions=truth.clean_positions, muscle_names=np.array(model.muscle_names))
    _root_first(write)
    log.info("wrote %s (%d frames, %d markers) and its truth %s", out, args.frames, len(names), truth_path(out))


def truth_path(capture_path: pathlib.Path) -> pathlib.Path:
    return capture_path.with_name(capture_path.stem + ".truth.npz")


def load_truth(path: pathlib.Path):
    from .bones import AffineMap
    from .synthetic import TakeTruth
    data = np.load(path)
    head = [AffineMap(M, t) for M, t in zip(data["head_matrices"], data["head_translations"])]
    return TakeTruth(data["activations"], data["tmj"], head, data["clean_positions"])


def fit(model, args) -> None:
    """Fit every frame of a take, writing each as soon as it is done; resumes a killed run."""
    from .bones import AffineMap
    from .capture import read_capture
    from .fitting import FaceFitter, FitSettings, MarkerSet, chunk_ranges
    from .model import load_model
    from .problem import FaceProblem
    from .results import FitFolder
    comm = MPI.COMM_WORLD
    capture_path = pathlib.Path(args.capture)
    capture = read_capture(capture_path, units=args.units, up_axis=args.up_axis)
    unknown = [n for n in capture.marker_names if n not in model.markers]
    if unknown:
        raise SystemExit(f"{capture_path}: markers {', '.join(unknown[:5])}{' ...' if len(unknown) > 5 else ''} "
                         f"are not marker sites of model {model.name}; this capture needs aligning to "
                         f"the model first")
    truth_file = pathlib.Path(args.truth) if args.truth else truth_path(capture_path)
    truth = load_truth(truth_file) if truth_file.exists() else None
    settings = FitSettings(mode=args.mode, max_gn_steps=args.gn_steps,
                           temporal_smoothness=args.smoothness)
    run = dict(capture=str(capture_path.resolve()), model=str(model.path), mode=args.mode,
               gn_steps=args.gn_steps, smoothness=args.smoothness, frames=capture.n_frames)
    folder = _root_first(lambda: FitFolder(args.out, run, overwrite=args.overwrite))
    done = _root_first(folder.finished_frames)
    chunks = chunk_ranges(capture.n_frames, args.chunks)
    if args.chunk is not None:  # one chunk in this (separate) process
        if not 0 <= args.chunk < len(chunks):
            raise SystemExit(f"--chunk {args.chunk}: the take has chunks 0..{len(chunks) - 1}")
        chunks = [chunks[args.chunk]]
    # MPI ranks split into groups, each fitting whole chunks on its own copy of the mesh.
    groups = min(len(chunks), comm.size)
    group = comm.rank * groups // comm.size
    group_comm = comm.Split(group, comm.rank) if groups > 1 else comm
    group_model = load_model(model.path, group_comm) if groups > 1 else model
    problem = FaceProblem(group_model)
    sites = np.array([model.markers[n] for n in capture.marker_names])
    markers = MarkerSet(problem, sites, names=capture.marker_names)
    for chunk in chunks[group::groups]:
        todo = [f for f in chunk if f not in done]
        if not todo:
            continue
        fitter = FaceFitter(problem, markers, settings)
        problem.u.x.array[:] = 0.0
        problem.solve(activations=np.zeros(problem.num_muscles), cranium=AffineMap(), jaw=AffineMap())
        previous = max((f for f in done if chunk.start <= f < todo[0]), default=None)
        if previous is not None:  # resume inside this chunk from its last finished frame
            _warm_start(fitter, done[previous])
            log.info("resuming %s at frame %d (%d frames already done)", args.out, todo[0], len(done))
        for frame in todo:
            result = fitter.fit_frame(capture.positions[frame], frame=frame)
            if group_comm.rank == 0:
                folder.write_frame(result)
            error = "" if truth is None else \
                f", activation error {np.abs(result.activations - truth.activations[frame]).max():.3f}"
            log.info("frame %d/%d: marker RMS %.3f mm (max %.3f), %d GN steps, %.1f s%s%s", frame + 1,
                     capture.n_frames, result.rms_error, result.max_error, result.gn_steps,
                     result.seconds, error, f" [{result.flag}]" if result.flag else "")
    comm.barrier()
    missing = capture.n_frames - len(_root_first(folder.finished_frames))
    if missing:
        log.info("%d frames still to fit (other chunks); rerun to finish %s", missing, args.out)
        return
    _root_first(lambda: folder.finish(model.muscle_names, capture.marker_names, capture.times, truth))
    log.info("results: %s", pathlib.Path(args.out).resolve())


def _warm_start(fitter, last) -> None:
    """Continue a fit from a finished frame: its controls and the equilibrium there."""
    fitter.state.activations = last.activations.copy()
    fitter.state.cranium = last.cranium
    if last.jaw_tmj is not None:
        fitter.state.tmj = last.jaw_tmj.copy()
    else:
        fitter.state.jaw = last.jaw
    fitter.problem.solve(activations=last.activations, cranium=last.cranium, jaw=last.jaw)
    fitter.previous_activations, fitter.frames_done = last.activations.copy(), 1


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

    def model_options(p, out):
        p.add_argument("--model", help="model folder (default: the built-in face)")
        p.add_argument("--tets", type=int, default=20_000, help="built-in face resolution")
        p.add_argument("--out", default=out, help="output path")
        p.add_argument("--overwrite", action="store_true", help="replace existing output")

    p = sub.add_parser("synth", help="synthetic take with known truth")
    model_options(p, "takes/speech.trc")
    p.add_argument("--scenario", default="speech",
                   help="smile, jaw, brow, speech, mixed or training (Choe & Ko's: each muscle alone, "
                        "jaw limits, expressions; give frames = a multiple of the segment count)")
    p.add_argument("--frames", type=int, default=30)
    p.add_argument("--rate", type=float, default=60.0, help="frame rate (Hz)")
    p.add_argument("--noise", type=float, default=0.5, help="marker noise, RMS of the 3D error (mm)")
    p.add_argument("--outliers", type=int, default=0, help="markers jumping 10 mm for 3 frames")
    p.add_argument("--gaps", type=int, default=0, help="markers missing for a stretch of frames")
    p.add_argument("--no-head-motion", action="store_true")
    p.add_argument("--seed", type=int, default=0)

    p = sub.add_parser("fit", help="fit activations and bone motion to a take")
    model_options(p, "results/fit")
    p.add_argument("capture", help="TRC, CSV or C3D file whose markers are model marker sites")
    p.add_argument("--units", help="mm, cm or m when the file does not say")
    p.add_argument("--up-axis", choices=("Y", "Z"), help="vertical axis of the file")
    p.add_argument("--mode", choices=("exact", "paper"), default="exact")
    p.add_argument("--gn-steps", type=int, default=3, help="Gauss-Newton steps per frame")
    p.add_argument("--smoothness", type=float, default=0.0,
                   help="temporal smoothness weight on activations (off by default)")
    p.add_argument("--truth", help="truth .npz of a synthetic take (default: next to the capture)")
    p.add_argument("--chunks", type=int, default=1,
                   help="split the take into independent chunks (each starts from rest); under "
                        "mpirun the ranks share them out")
    p.add_argument("--chunk", type=int, help="fit only this chunk (for separate processes)")

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
    if args.command == "synth":
        synth(model, args)
        return 0
    if args.command == "fit":
        fit(model, args)
        return 0
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
