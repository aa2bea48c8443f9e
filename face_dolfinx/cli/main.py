"""Command line of face_dolfinx (``python run.py ...`` or ``face-dolfinx ...``, also under mpirun).

Subcommands:
  build     generate the built-in face at a resolution and print the model folder; with --subject
            (a capture) or --surface (a scan), the face adapted to a subject
  simulate  equilibrium shapes for named expressions -> XDMF + PNG; with --object and --path, a
            rigid object moved along a path against the face; with --contact, the lips on the
            teeth and on each other (docs/contact.md); with --animation, an animation or fit
            played back into a results folder (docs/animation.md)
  synth     a synthetic take of known truth (markers with noise, outliers, gaps) -> TRC/CSV/C3D
  fit       a take -> activations, head and jaw motion per frame (resumable), tables and report;
            a capture of your own is aligned to the model first (--correspondence, or ICP)
  report    (re)build the plots, rendered frames and ParaView series of a fit folder
  edit      edit a fit or animation in activation space (in-betweens, exaggeration, splices,
            keyframes, smoothing) -> an animation CSV for simulate --animation
  demo      the README's main job: build the face, synthesise a take, fit it
  retarget  a fit's (or an animation's) activations, head and jaw motion carried onto another model:
            an animation file for simulate --animation (docs/retargeting.md)
Every subcommand takes --config FILE.toml (docs/cli.md).
"""
import argparse
import contextlib
import json
import logging
import math
import pathlib
import sys
import time

from mpi4py import MPI
import numpy as np

from face_dolfinx.parallel import on_rank_0

log = logging.getLogger("face_dolfinx")

def _setup_logging(folder: pathlib.Path | None = None, verbose: bool = False) -> None:
    """Log to the console and (optionally) ``folder``/run.log, from rank 0 only."""
    root = logging.getLogger()
    for handler in root.handlers:
        handler.close()
    root.handlers.clear()
    if MPI.COMM_WORLD.rank != 0:
        root.addHandler(logging.NullHandler())
        return
    level = logging.DEBUG if verbose else logging.INFO
    root.setLevel(logging.WARNING)
    log.setLevel(level)
    fmt = logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s", "%H:%M:%S")
    handlers = [_ConsoleHandler()]
    if folder is not None:
        handlers.append(logging.FileHandler(folder / "run.log"))  # appends: a resume adds its log
    for handler in handlers:
        handler.setFormatter(fmt)
        # The form compiler logs its C builds at INFO on the root logger: keep only ours and warnings.
        handler.addFilter(lambda record: record.name.startswith("face_dolfinx") or record.levelno >= logging.WARNING)
        root.addHandler(handler)


class _ConsoleHandler(logging.StreamHandler):
    """Log lines on stdout that go above a progress bar instead of through it."""

    def __init__(self):
        super().__init__(sys.stdout)

    def emit(self, record):
        from tqdm import tqdm
        try:
            tqdm.write(self.format(record), file=self.stream)
        except Exception:  # as logging.StreamHandler does: a failed log line must not stop the run
            self.handleError(record)


def _model_from_args(args):
    from face_dolfinx.model.anatomy import build_builtin_face
    from face_dolfinx.model.folder import load_model
    path = pathlib.Path(args.model) if args.model else build_builtin_face(target_tets=args.tets)
    return _with_overrides(load_model(path, MPI.COMM_WORLD), args)


def _with_overrides(model, args):
    """``model`` with the ``--strength`` and ``--material`` overrides of the command line."""
    model = model.with_strength(args.strength) if args.strength else model
    return model.with_material(args.material) if args.material else model


def material_option(text: str) -> tuple:
    """``--material``: a TOML file of ``[[region]]`` tables, or ``REGION:PARAM=FACTOR,...`` overrides
    separated by ``;`` (``face_dolfinx.model.regions``)."""
    from face_dolfinx.model.regions import MaterialError, parse_material_option, read_material_file
    try:
        if text.strip().endswith(".toml"):
            return tuple(read_material_file(text.strip()))
        overrides = tuple(parse_material_option(item) for item in text.split(";") if item.strip())
    except MaterialError as error:
        raise argparse.ArgumentTypeError(str(error)) from None
    if not overrides:
        raise argparse.ArgumentTypeError(f"{text!r}: give REGION:PARAM=FACTOR or a TOML file")
    return overrides


def add_material_option(parser) -> None:
    parser.add_argument("--material", type=material_option, metavar="REGION:PARAM=F[;...]|FILE.toml",
                        help="regional flesh overrides: REGION = muscle:NAME, sphere:X,Y,Z,R or "
                             "box:X0,Y0,Z0,X1,Y1,Z1 (mm), PARAM = mu10, mu01, kappa, passive or all, F its "
                             "factor (e.g. sphere:0,95,20,12:all=0.3 softens the nose); or a TOML file of "
                             "[[region]] tables that may also set values (docs/dynamics.md)")


def strength_option(text: str) -> dict[str, float]:
    """``--strength``: a factor for every muscle (``1.5``) and/or per muscle (``mentalis_left=2``),
    comma-separated; factors of one muscle multiply."""
    scales = {}
    for item in filter(None, (part.strip() for part in text.split(","))):
        name, _, value = item.rpartition("=")
        name = name.strip() or "all"
        try:
            factor = float(value)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{item!r}: give FACTOR or MUSCLE=FACTOR") from None
        if not (math.isfinite(factor) and factor > 0):
            raise argparse.ArgumentTypeError(f"{item!r}: a strength factor must be positive")
        scales[name] = scales.get(name, 1.0) * factor
    if not scales:
        raise argparse.ArgumentTypeError(f"{text!r}: give FACTOR or MUSCLE=FACTOR")
    return scales


def add_strength_option(parser) -> None:
    parser.add_argument("--strength", type=strength_option, metavar="F|MUSCLE=F,...",
                        help="scale muscles' peak stress (their force-length curves), all (F) or by name "
                             "(MUSCLE=F): exaggerates beyond the physical range, activations staying in [0, 1]")


def _coarse_model(args):
    """The model named by ``--coarse``: a number is a built-in face resolution, else a folder; with
    the same ``--strength`` and ``--material`` as the fine one."""
    if not args.coarse:
        return None
    from face_dolfinx.model.anatomy import build_builtin_face
    from face_dolfinx.model.folder import load_model
    if args.coarse.isdigit():
        if args.model:
            raise SystemExit("--coarse TETS builds the built-in face; with --model give a coarse model folder")
        model = load_model(build_builtin_face(target_tets=int(args.coarse)), MPI.COMM_WORLD)
    else:
        model = load_model(pathlib.Path(args.coarse), MPI.COMM_WORLD)
    return _with_overrides(model, args)


def _expression_controls(model, name: str):
    """Activations (dict) and jaw frame of a named expression stored in the model."""
    from face_dolfinx.model.bones import AffineMap, jaw_pose
    if name not in model.expressions:
        known = ", ".join(sorted(model.expressions))
        raise SystemExit(f"unknown expression {name!r}; the model defines: {known}")
    spec = dict(model.expressions[name])
    opening = math.radians(spec.pop("jaw_opening_deg", 0.0))
    jaw = jaw_pose(model.jaw, opening) if opening else AffineMap()
    return spec, jaw


def simulate(model, expressions: list[str], out: pathlib.Path, *, degree: int = 1,
             overwrite: bool = False, render: bool = True, coarse_model=None, contact=None,
             lip_contact=None, contact_solver: dict | None = None) -> list[dict]:
    """Solve each expression from the previous equilibrium and write one result folder. With a
    ``coarse_model`` of the same face, each solve starts from the coarse model's equilibrium
    (``face_dolfinx.equilibrium.coarse``). ``contact``: (``ContactSettings``, poses of its object):
    the object starts at the first pose, the expressions are solved against it, then it moves along
    the rest of the poses, one frame each (object.xdmf shows it); no poses: no object (the
    settings' teeth, say). ``lip_contact``: ``LipContactSettings``, the lips pressing on each other.
    ``contact_solver``: ``FaceProblem``'s contact solver options (``contact_relaxation``,
    ``newton_energy_tolerance``; ``_contact_solver``)."""
    from face_dolfinx.equilibrium.coarse import CoarseStart
    from face_dolfinx.files import atomic_directory
    from face_dolfinx.results.xdmf import FaceWriter
    from face_dolfinx.physics.problem import FaceProblem
    comm = MPI.COMM_WORLD
    for name in expressions:  # fail before any work, not halfway through
        _expression_controls(model, name)
    if (contact is not None or lip_contact is not None) and coarse_model is not None:
        raise SystemExit("--object or --contact and --coarse do not go together: the coarse model has no contact")
    start = time.perf_counter()
    problem = FaceProblem(model, degree=degree, contact=contact[0] if contact is not None else None,
                          lip_contact=lip_contact, **(contact_solver or {}))
    solver = problem
    if coarse_model is not None:
        solver = CoarseStart(FaceProblem(coarse_model), problem)
        log.info("coarse start from %s (%d tets)", coarse_model.path,
                 coarse_model.mesh.topology.index_map(3).size_global)
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
                report = solver.solve(activations=activations, jaw=jaw)
                displacement = comm.allreduce(np.abs(problem.u.x.array).max() if problem.u.x.array.size else 0.0,
                                              op=MPI.MAX)
                row = dict(expression=name, newton_iterations=report.newton_iterations,
                           load_steps=report.load_steps, seconds=round(report.seconds, 3),
                           max_displacement_mm=round(displacement, 4))
                if problem.teeth_contact is not None:
                    row["teeth"] = _contact_row(problem.teeth_contact, problem.u.x.array)
                rows.append(row)
                log.info("%-12s Newton %2d its, %d load step(s), %.2f s, max |u| %.2f mm", name,
                         report.newton_iterations, report.load_steps, report.seconds, displacement)
                writer.write(float(step))
                if render:
                    _render_expression(problem, staging / f"{step:02d}_{name}.png", name)
            object_rows = (_move_object(problem, contact[1], writer, staging / "object.xdmf", len(expressions),
                                        render=render)
                           if contact is not None and contact[1] else None)
        if comm.rank == 0:
            (staging / "summary.json").write_text(json.dumps(
                dict(model=str(model.path), expressions=rows, object=object_rows, ranks=comm.size,
                     material=[override.describe() for override in model.material_overrides],
                     coarse_model=str(coarse_model.path) if coarse_model is not None else None),
                indent=2))
    return rows


def expression_sequence(model, expressions: list[str], seconds_each: float):
    """``controls_at(t)`` and the duration of the named expressions played one after another, each
    reached from the previous one (rest for the first) along a smooth ramp of ``seconds_each``,
    the last one then held as long again (to watch the flesh settle)."""
    from face_dolfinx.physics.problem import Controls
    from face_dolfinx.model.bones import AffineMap
    names = [None, *expressions]
    keys = []
    for name in names:
        if name is None:
            keys.append(Controls(np.zeros(len(model.muscles)), AffineMap(), AffineMap()))
            continue
        activations, jaw = _expression_controls(model, name)
        vector = np.zeros(len(model.muscles))
        for muscle, value in activations.items():
            vector[model.muscle_index(muscle)] = value
        keys.append(Controls(vector, AffineMap(), jaw))

    def controls_at(t: float):
        if not expressions:  # the rest, held (an object's path may follow)
            return keys[0]
        segment = min(int(t // seconds_each), len(expressions) - 1) if t > 0 else 0
        s = min(max(t / seconds_each - segment, 0.0), 1.0)
        return keys[segment].interpolate(keys[segment + 1], s * s * (3.0 - 2.0 * s))

    return controls_at, (len(expressions) + 1) * seconds_each


def simulate_dynamic(model, controls_at, times, out: pathlib.Path, settings, *, degree: int = 1,
                     overwrite: bool = False, intraoral_pressure: bool = False,
                     source: dict | None = None, contact=None, lip_contact=None,
                     contact_solver: dict | None = None) -> list[dict]:
    """Integrate the face in time (``FaceProblem.dynamics``) from the equilibrium of
    ``controls_at(times[0])`` through ``times`` (s), one XDMF frame per time, into the results
    folder ``out`` with summary.json. A time step that cannot converge ends the run with one
    message after the folder is written with the frames before it (summary.json says where it
    stopped). ``intraoral_pressure``: the controls carry a pressure. ``source``: what drove it, for
    summary.json. ``contact`` (``ContactSettings``: objects, whose poses ``controls_at`` gives, and
    teeth), ``lip_contact`` (``LipContactSettings``) and ``contact_solver`` as in ``simulate``; an object's surface is
    written as object.xdmf, and summary.json gives per frame the contact of each."""
    from face_dolfinx.equilibrium.dynamics import DynamicsError
    from face_dolfinx.files import atomic_directory
    from face_dolfinx.physics.problem import FaceProblem
    from face_dolfinx.results.xdmf import FaceWriter
    comm = MPI.COMM_WORLD
    times = np.asarray(times, dtype=float)
    if times.size < 2 or np.any(np.diff(times) <= 0):
        raise SystemExit("simulate --dynamic: the frame times must increase (two or more)")
    first = controls_at(float(times[0]))
    try:  # the model may lack what the controls need (an 'oral' surface for a pressure, teeth)
        problem = FaceProblem(model, degree=degree, intraoral_pressure=intraoral_pressure, contact=contact,
                              lip_contact=lip_contact, **(contact_solver or {}))
        if problem.contact is not None:  # an object whose first pose overlaps the skin: before any solve
            problem.contact.set_poses(first.objects)
            problem.contact.check_clear(problem.u.x.array)
    except ValueError as error:
        raise SystemExit(f"face-dolfinx simulate --dynamic: {error}") from None
    problem.solve(activations=first.activations, cranium=first.cranium, jaw=first.jaw,
                  pressure=first.pressure if intraoral_pressure else None,
                  objects=first.objects if problem.contact is not None else None)
    dynamic = problem.dynamics(settings)
    dynamic.start(float(times[0]))
    rows, failure = [], None
    with atomic_directory(out, comm, overwrite=overwrite) as staging:
        with FaceWriter(problem, staging / "face.xdmf") as writer, \
                _ObjectSeries(problem, staging / "object.xdmf") as objects:
            def frame(index, t, report):
                u = problem.u.x.array
                displacement = comm.allreduce(float(np.abs(u).max(initial=0.0)), op=MPI.MAX)
                row = dict(frame=index, time_s=round(t, 6), substeps=report.substeps if report else 0,
                           newton_iterations=report.newton_iterations if report else 0,
                           seconds=round(report.seconds, 3) if report else 0.0,
                           max_displacement_mm=round(displacement, 4), kinetic_energy_uJ=dynamic.kinetic_energy())
                row.update(_contact_rows(problem))
                rows.append(row)
                writer.write(t)
                objects.write(t)
                if report is not None:
                    log.info("t = %.4f s: %d substep(s), Newton %d its, %.2f s, max |u| %.2f mm", t, report.substeps,
                             report.newton_iterations, report.seconds, displacement)

            try:
                dynamic.run(controls_at, times, frame)
            except DynamicsError as error:
                failure = str(error)
        if comm.rank == 0:
            (staging / "summary.json").write_text(json.dumps(
                dict(model=str(model.path), dynamic=vars(settings), source=source or {}, frames=rows,
                     ranks=comm.size, failure=failure,
                     material=[override.describe() for override in model.material_overrides]), indent=2))
    if failure is not None:
        raise SystemExit(f"face-dolfinx simulate --dynamic: {failure}; {out} holds the {len(rows)} frames before it")
    return rows


def _contact_rows(problem) -> dict:
    """The contact of the problem's object, teeth and lips at its state, for a frame of summary.json."""
    u, rows = problem.u.x.array, {}
    if problem.contact is not None:
        rows["object"] = dict(centre_mm=problem.controls.objects[0].translation.round(4).tolist(),
                              **_contact_row(problem.contact, u), **_triangle_contact_row(problem.contact, u))
    if problem.teeth_contact is not None:
        rows["teeth"] = _contact_row(problem.teeth_contact, u)
    if problem.lips is not None:
        rows["lips"] = dict(pairs=problem.lips.pairs(u), min_distance_mm=round(problem.lips.min_distance(u), 6))
    return rows


class _ObjectSeries:
    """The problem's contact object (if any) as its own XDMF series (a fan of tetrahedra from the
    origin of its frame over its surface, moved by a displacement field), one frame per ``write``."""

    def __init__(self, problem, path: pathlib.Path):
        from face_dolfinx.results.xdmf import XdmfSeries
        self.problem, self.series = problem, None
        if problem.contact is None:
            return
        points, triangles = problem.contact.objects[0].surface()
        self.points = np.vstack([points, np.zeros(3)])
        cells = np.c_[np.full(len(triangles), len(self.points) - 1), triangles]
        if MPI.COMM_WORLD.rank == 0:
            self.series = XdmfSeries(path, self.points, cells)

    def write(self, t: float) -> None:
        if self.series is not None:
            pose = self.problem.controls.objects[0]
            self.series.write(t, {"displacement": pose.apply(self.points) - self.points}, {})

    def __enter__(self):
        return self

    def __exit__(self, kind, error, trace):
        if self.series is not None:
            self.series.abort() if kind is not None else self.series.close()
        return False


def object_path_controls(controls_at, start: float, poses, interval: float, hold: float):
    """``controls_at(t)`` with the contact object at the first of ``poses`` until ``start`` (s),
    then along them, one every ``interval`` s (a straight line between two), then at the last one
    for ``hold`` s; and the duration."""
    from dataclasses import replace

    def at(t: float):
        position = min(max((t - start) / interval, 0.0), len(poses) - 1.0)
        k = min(int(position), len(poses) - 2)
        pose = poses[0] if len(poses) == 1 else poses[k].geodesic(poses[k + 1], position - k)
        return replace(controls_at(t), objects=(pose,))

    return at, start + (len(poses) - 1) * interval + hold


def dynamic_settings(args):
    """``DynamicSettings`` of the simulate options, or a usage error naming the option."""
    from face_dolfinx.equilibrium.dynamics import DynamicsError, DynamicSettings
    try:
        return DynamicSettings(density=args.density, mass_damping=args.damping, viscosity=args.viscosity,
                               scheme=args.scheme, time_step=args.time_step)
    except DynamicsError as error:
        raise SystemExit(f"face-dolfinx simulate --dynamic: {error}") from None


def simulate_animation(model, args) -> None:
    """Play an animation (a CSV or TOML file, or a fit or simulation results folder) on the model
    into a results folder like a fit's, resumable frame by frame
    (``face_dolfinx.animation.playback``); ``--contact``: the lips on each other and on the teeth,
    in quasistatic and dynamic playback alike (run.json records it)."""
    from face_dolfinx.animation.playback import animation_and_markers, open_playback, play
    from face_dolfinx.physics.problem import FaceProblem
    from face_dolfinx.results.folder import FitFolderError
    # Every input is checked before the result folder exists: a bad input leaves nothing behind.
    animation, markers = animation_and_markers(args.animation)
    if args.stop_after is not None and args.stop_after < 1:
        raise SystemExit(f"--stop-after {args.stop_after}: give 1 or more")
    if args.dynamic and args.stop_after is not None:
        raise SystemExit("--stop-after: a dynamic playback runs whole (its velocities are not stored to resume)")
    settings = dynamic_settings(args) if args.dynamic else None
    animation.check(model)
    start = time.perf_counter()
    contact = _object_from_args(args)  # --contact: the lips on the teeth (objects are refused with --animation)
    contact_solver = _contact_solver(args)
    try:  # the model may lack what the animation needs (an 'oral' surface for its pressure) or teeth
        problem = FaceProblem(model, degree=args.degree, intraoral_pressure=animation.has_pressure,
                              newton_tolerance=args.newton_tolerance, reuse_factorization=args.reuse_factorization,
                              contact=contact[0] if contact is not None else None, lip_contact=_lip_contact(args),
                              **contact_solver)
    except ValueError as error:
        raise SystemExit(f"face-dolfinx: error: {animation.source}{' with --contact' if args.contact else ''}: "
                         f"{error}") from None
    setup = time.perf_counter() - start
    try:
        folder, markers = open_playback(model, animation, args.out, markers=markers, overwrite=args.overwrite,
                                        extra=dict(degree=args.degree, strength=args.strength,
                                                   material=[override.describe() for override in model.material_overrides],
                                                   newton_tolerance=args.newton_tolerance,
                                                   reuse_factorization=args.reuse_factorization,
                                                   dynamic=vars(settings) if settings is not None else None,
                                                   contact=args.contact,
                                                   contact_surfaces=["lips", "teeth"] if args.contact else [],
                                                   # recorded when set, so that older folders resume
                                                   **{key: value for key, value in contact_solver.items() if value}))
    except FitFolderError as error:
        raise SystemExit(str(error)) from None
    if folder.finished:
        log.info("%s already holds this simulation, finished: nothing to do (--overwrite simulates again)",
                 folder.path)
        return
    _setup_logging(folder.path, verbose=args.verbose)
    log.info("model %s: %d tets, %d muscles; animation %s: %d frames, %.3g s; set-up %.1f s", model.name,
             model.mesh.topology.index_map(3).size_global, problem.num_muscles, animation.source,
             animation.n_frames, animation.times[-1] - animation.times[0], setup)
    from face_dolfinx.equilibrium.dynamics import DynamicsError
    try:
        run = play(problem, animation, folder, markers, stop_after=args.stop_after,
                   dynamic=problem.dynamics(settings) if settings is not None else None)
    except FitFolderError as error:
        raise SystemExit(str(error)) from None
    except DynamicsError as error:
        raise SystemExit(f"face-dolfinx simulate --dynamic: {error}; {folder.path} keeps the frames before it") from None
    if run.seconds:
        log.info("%d frames: Newton %d its per frame (median), %.2f s per frame (median)", len(run.frames),
                 int(np.median(run.newton_iterations)), float(np.median(run.seconds)))
    if not run.finished:
        log.info("%d frames still to simulate; rerun the same command to continue %s", len(run.missing),
                 folder.path)
        return
    log.info("results: %s (plots: *.png and renders/; ParaView: face.xdmf; run.py video %s)",
             folder.path.resolve(), folder.path)


def retarget_animation(args) -> None:
    """Carry an animation (a fit or simulation results folder, a CSV or TOML file) onto another
    model: an animation file that ``simulate --animation`` plays, and the record of what was
    mapped, dropped and clamped beside it (``face_dolfinx.animation.retarget``). Runs on rank 0."""
    from face_dolfinx.animation import Animation
    from face_dolfinx.animation.retarget import (RetargetError, record_path, retarget, source_model_path,
                                                 write_record)
    from face_dolfinx.model.anatomy import build_builtin_face
    from face_dolfinx.model.folder import read_model_arrays
    if not args.animation or not args.out:
        raise SystemExit("retarget: give the fit folder or animation file and --out FILE.csv")
    out = pathlib.Path(args.out)
    # Every input is checked before anything is written: a bad input leaves nothing behind.
    if out.suffix.lower() != ".csv":
        raise SystemExit(f"--out {out}: an animation is written as a .csv table")
    if not args.overwrite and (out.exists() or record_path(out).exists()):
        raise SystemExit(f"--out {out} exists; pass --overwrite to replace it")
    source_path = pathlib.Path(args.source_model) if args.source_model else source_model_path(args.animation)
    if source_path is None:
        raise SystemExit(f"{args.animation}: an animation file does not name the model it was made for; "
                         f"give --source-model FOLDER")
    target_path = pathlib.Path(args.model) if args.model else build_builtin_face(target_tets=args.tets)

    def carry():
        animation = Animation.read(args.animation)
        source = read_model_arrays(source_path, check=False)
        target = read_model_arrays(target_path, check=False)
        moved, record = retarget(animation, source, target, target_label=str(target_path))
        record["source_model"] = str(source_path)
        out.parent.mkdir(parents=True, exist_ok=True)
        moved.write(out)
        write_record(out, record)
        return record

    try:
        record = on_rank_0(carry, MPI.COMM_WORLD)
    except RetargetError as error:
        raise SystemExit(f"face-dolfinx: error: {error}") from None
    muscles = record["muscles"]
    log.info("retargeted %d frames onto %s: %d muscles mapped, %d dropped, %d held at rest; head scale %.4g "
             "(RMS %.3g mm over %d points); animation %s, record %s", record["frames"], target_path,
             len(muscles["mapped"]), len(muscles["dropped"]), len(muscles["held_at_rest"]),
             record["head"]["scale"], record["head"]["rms_mm"], len(record["head"]["points"]), out,
             record_path(out))


def animation_source(text: str, model=None):
    """An animation or pose named on the command line: ``PATH`` (a CSV or TOML file, a results
    folder), ``PATH@T`` (its pose at T seconds), ``PATH#N`` (its frame N), or ``expression:NAME``
    (the model's named expression; needs ``model``)."""
    from face_dolfinx.animation import Animation, AnimationError
    if text.startswith("expression:"):
        if model is None:
            raise AnimationError(f"{text}: an expression needs the model that defines it (give --model or --tets)")
        return Animation.from_expression(model, text.partition(":")[2])
    for mark in ("@", "#"):
        path, found, where = text.rpartition(mark)
        if found and path and not pathlib.Path(text).exists():
            try:
                value = float(where) if mark == "@" else int(where)
            except ValueError:
                raise AnimationError(f"{text}: give PATH{mark}{'SECONDS' if mark == '@' else 'FRAME'}") from None
            animation = Animation.read(path)
            if mark == "@":
                return animation.at(value)
            if not 0 <= value < animation.n_frames:
                raise AnimationError(f"{text}: frame {value} of the {animation.n_frames} frames of {path}")
            return animation.at(float(animation.times[value]))
    return Animation.read(text)


def splice_part(text: str):
    """A splice part: ``PATH[@START:STOP][xSPEED]`` -> (animation, start, stop, speed)."""
    from face_dolfinx.animation import Animation, AnimationError
    path, found, spec = text.rpartition("@")
    if not found or pathlib.Path(text).exists():
        return Animation.read(text), None, None, 1.0
    window, _, speed = spec.partition("x")
    start, colon, stop = window.partition(":")
    try:
        if window and not colon:
            raise ValueError
        values = [float(v) if v.strip() else None for v in (start, stop)] + [float(speed) if speed else 1.0]
    except ValueError:
        raise AnimationError(f"{text}: give PATH@START:STOP (seconds, either may be left out), optionally "
                             f"followed by xSPEED") from None
    return (Animation.read(path), *values)


def edit(args) -> None:
    """``run.py edit OPERATION``: an edited animation (``face_dolfinx.animation.editing``) -> a
    CSV that ``simulate --animation`` plays."""
    from face_dolfinx.animation import editing
    from face_dolfinx.model.folder import load_model
    from face_dolfinx.model.anatomy import build_builtin_face
    out = pathlib.Path(args.out)
    if out.suffix.lower() != ".csv":
        raise SystemExit(f"--out {out}: an edited animation is written as a .csv table")
    # Rank 0 decides: the ranks run this command out of step (nothing collective before the
    # write), and a rank that looked after rank 0 had written refused its own output.
    if on_rank_0(out.exists, MPI.COMM_WORLD) and not args.overwrite:
        raise SystemExit(f"{out} already exists; pass --overwrite to replace it")
    model = None
    if args.model or args.tets:
        model = load_model(pathlib.Path(args.model) if args.model else build_builtin_face(target_tets=args.tets),
                           MPI.COMM_WORLD)
    if args.operation == "between":
        result = editing.between(animation_source(args.first, model), animation_source(args.second, model),
                                 args.frames, args.duration)
    elif args.operation == "scale":
        about = animation_source(args.about, model) if args.about else None
        result = editing.scaled(animation_source(args.source, model), args.factor, about)
    elif args.operation == "splice":
        parts = [editing.segment(animation, start, stop, speed, args.frame_rate)
                 for animation, start, stop, speed in map(splice_part, args.parts)]
        result = editing.splice(parts, args.transition)
    elif args.operation == "keyframes":
        times, values = keyframe_option(args.keys)
        result = editing.with_keyframes(animation_source(args.source, model), args.muscle, times, values,
                                        blend=args.blend, interpolation=args.interpolation)
    else:
        result = editing.smoothed(animation_source(args.source, model), args.time_constant, args.method)
    if model is not None:
        result.check(model)
    on_rank_0(lambda: result.write(out), MPI.COMM_WORLD)
    log.info("%s: %d frames, %.3g s, %d muscles named (from %s)", out, result.n_frames,
             result.times[-1] - result.times[0], len(result.muscle_names), result.source)


def keyframe_option(text: str) -> tuple[list[float], list[float]]:
    """``--keys T=V,T=V,...`` -> (times, values)."""
    pairs = [item.partition("=") for item in filter(None, (p.strip() for p in text.split(",")))]
    try:
        if not pairs or any(not sep for _, sep, _ in pairs):
            raise ValueError
        return [float(t) for t, _, _ in pairs], [float(v) for _, _, v in pairs]
    except ValueError:
        raise SystemExit(f"--keys {text}: give TIME=ACTIVATION pairs, comma-separated, e.g. 0.5=0.8,1.2=0") from None
def _contact_row(contact, displacement) -> dict:
    """The contact of a surface with its objects at a state, for summary.json."""
    forces = contact.nodal_forces(displacement)
    return dict(contact_nodes=contact.contact_nodes(displacement), min_gap_mm=round(contact.min_gap(displacement), 6),
                force_mN=forces.sum(axis=0).round(4).tolist(),
                pressed_mN=round(float(np.linalg.norm(forces, axis=1).sum()), 4))


def _triangle_contact_row(contact, displacement) -> dict:
    """The skin triangles' contact with spheres (``face_contact.FaceContactPotential``) and with
    triangle meshes' vertices and edges (``object_features.ObjectFeatureContact``; their smallest
    gaps up to 1 mm), if any."""
    from face_dolfinx.physics.face_contact import FaceContactPotential
    from face_dolfinx.physics.object_features import ObjectFeatureContact
    row = {}
    if isinstance(contact, FaceContactPotential) and any(contact.by_faces):
        row.update(contact_triangles=contact.contact_triangles(displacement),
                   min_triangle_gap_mm=round(float(contact.triangle_gaps(displacement).min()), 6))
    if isinstance(contact, ObjectFeatureContact):
        vertices, edges = contact.contact_features(displacement)
        row.update(contact_vertices=vertices, contact_edges=edges,
                   min_vertex_gap_mm=round(float(np.concatenate(contact.vertex_gaps(displacement, within=1.0)).min()), 6),
                   min_edge_gap_mm=round(float(np.concatenate(contact.edge_gaps(displacement, within=1.0)).min()), 6))
    return row


def _move_object(problem, poses, writer, path: pathlib.Path, first_frame: int, render: bool = False) -> list[dict]:
    """The contact object along ``poses`` (the first is where it stands), one solve and one face
    frame per pose; the object's surface as its own XDMF series (a fan of tetrahedra from its
    centre, moved by a displacement field: ParaView's Warp By Vector shows it in place). With
    ``render``, a PNG of the face with the object per frame (``NN_object.png`` beside ``path``;
    the first pose's frame is the last expression's render, if any)."""
    from face_dolfinx.results.xdmf import XdmfSeries
    comm = MPI.COMM_WORLD
    contact = problem.contact
    points, triangles = contact.objects[0].surface()
    points = np.vstack([points, np.zeros(3)])
    cells = np.c_[np.full(len(triangles), len(points) - 1), triangles]
    series = XdmfSeries(path, points, cells) if comm.rank == 0 else None
    rows = []
    try:
        for index, pose in enumerate(poses):
            frame = first_frame + index
            report = problem.solve(objects=(pose,)) if index else None
            force = contact.nodal_forces(problem.u.x.array).sum(axis=0)
            row = dict(pose=index, centre_mm=pose.translation.round(4).tolist(),
                       newton_iterations=report.newton_iterations if report else 0,
                       load_steps=report.load_steps if report else 0,
                       seconds=round(report.seconds, 3) if report else 0.0,
                       force_on_object_mN=force.round(4).tolist(),
                       min_gap_mm=round(contact.min_gap(problem.u.x.array), 6),
                       contact_nodes=contact.contact_nodes(problem.u.x.array),
                       **_triangle_contact_row(contact, problem.u.x.array))
            rows.append(row)
            log.info("object pose %d: Newton %d its, force %.3f mN, min gap %.4f mm, %d contact nodes", index,
                     row["newton_iterations"], float(np.linalg.norm(force)), row["min_gap_mm"], row["contact_nodes"])
            if index:
                writer.write(float(frame))
            if render and (index or not first_frame):
                _render_expression(problem, path.parent / f"{frame:02d}_object.png",
                                   f"object pose {index}: {np.linalg.norm(force):.0f} mN on it")
            if series is not None:
                series.write(float(frame), {"displacement": pose.apply(points) - points}, {})
    except BaseException:
        if series is not None:
            series.abort()
        raise
    if series is not None:
        series.close()
    return rows


def _object_from_args(args):
    """(ContactSettings, poses) of ``--object sphere:RADIUS|mesh:FILE --path FILE`` and
    ``--contact`` (the lips on the teeth; no poses without an object), or None."""
    from face_dolfinx.physics.contact import TEETH_STIFFNESS, ContactSettings
    if args.object is None and args.path is None:
        return (ContactSettings(teeth=True, stiffness=TEETH_STIFFNESS, where="--contact"), ()) if args.contact else None
    if args.object is None or args.path is None:
        raise SystemExit("--object and --path go together")
    from face_dolfinx.physics.contact import Sphere, read_path
    from face_dolfinx.physics.rigid_mesh import TriangleMesh
    kind, _, size = args.object.partition(":")
    if kind == "mesh" and size:
        try:
            obj = TriangleMesh.read(size)
        except ValueError as error:
            raise SystemExit(str(error)) from None
    else:
        try:
            radius = float(size)
        except ValueError:
            radius = math.nan
        if kind != "sphere" or not radius > 0.0:
            raise SystemExit(f"--object {args.object}: give sphere:RADIUS (mm), e.g. sphere:15, or mesh:FILE "
                             "(a closed triangle surface, .obj/.stl/.ply/.off)")
        obj = Sphere(radius)
    try:
        poses = read_path(args.path)
    except ValueError as error:
        raise SystemExit(str(error)) from None
    teeth = dict(teeth=True, stiffness=TEETH_STIFFNESS) if args.contact else {}
    return ContactSettings((obj,), (poses[0],), where=f"{args.path} (its first pose)", **teeth), poses


def _contact_solver(args) -> dict:
    """``simulate``'s contact solver options (``FaceProblem``'s keywords): ``--contact-relaxation``
    and ``--newton-energy-tolerance``, which act on contact terms only (``--contact``, ``--object``)."""
    options = dict(contact_relaxation=args.contact_relaxation, newton_energy_tolerance=args.newton_energy_tolerance)
    if (args.contact_relaxation is not None or args.newton_energy_tolerance is not None) and not (
            args.contact or args.object):
        raise SystemExit("--contact-relaxation and --newton-energy-tolerance act on contact: give --contact or "
                         "--object with them")
    tolerance = args.newton_energy_tolerance
    if tolerance is not None and not (math.isfinite(tolerance) and tolerance > 0):
        raise SystemExit(f"--newton-energy-tolerance {tolerance}: give a positive energy (mN mm)")
    return options


def _lip_contact(args):
    """The lip self-contact settings of ``--contact`` (None without it)."""
    from face_dolfinx.physics.self_contact import LipContactSettings
    return LipContactSettings(where="--contact") if args.contact else None


def synth(model, args) -> None:
    """Solve the face along a scenario, sample its marker sites, write capture + truth."""
    from face_dolfinx.capture import write_capture
    from face_dolfinx.fitting import MarkerSet
    from face_dolfinx.physics.problem import FaceProblem
    from face_dolfinx.capture.synthetic import save_truth, synthesize_take, truth_contact_options, truth_path
    out = pathlib.Path(args.out)
    if out.exists() and not args.overwrite:
        raise FileExistsError(f"{out} already exists; pass --overwrite to replace it")
    take_frames = args.take_frames or args.frames
    if args.first_frame < 0 or args.first_frame + args.frames > take_frames:
        raise SystemExit(f"--first-frame {args.first_frame} + --frames {args.frames} runs past the "
                         f"{take_frames}-frame take (--take-frames)")
    if args.truth_contact is not None and not args.contact:
        raise SystemExit(f"synth --truth-contact {args.truth_contact}: give --contact too")
    try:
        contact = (truth_contact_options(model, args.truth_contact, where="synth --truth-contact")
                   if args.contact else {})
    except ValueError as error:
        raise SystemExit(str(error)) from None
    problem = FaceProblem(model, **contact)
    names = list(model.markers)
    markers = MarkerSet(problem, np.array([model.markers[n] for n in names]), names=names)
    capture, truth = synthesize_take(
        problem, markers, model, args.scenario, n_frames=take_frames, frame_rate=args.rate,
        noise=args.noise, outliers=args.outliers, gaps=args.gaps, head_motion=not args.no_head_motion,
        seed=args.seed, progress=lambda f: log.info("synth frame %d/%d", f + 1, args.frames),
        frames=range(args.first_frame, args.first_frame + args.frames))

    def write():
        out.parent.mkdir(parents=True, exist_ok=True)
        write_capture(capture, out)
        save_truth(truth_path(out), truth, model.muscle_names)
    on_rank_0(write, MPI.COMM_WORLD)
    log.info("wrote %s (%d frames, %d markers) and its truth %s", out, args.frames, len(names), truth_path(out))


def build_subject(args) -> None:
    """Adapt a template model to a subject (a capture's neutral frame, or a surface scan) -> --out."""
    from face_dolfinx.alignment.similarity import read_correspondence_file
    from face_dolfinx.model.anatomy import build_builtin_face
    from face_dolfinx.capture import read_capture
    from face_dolfinx.model.folder import read_model_arrays
    from face_dolfinx.subjects import adaptation as subject
    source = "subject" if args.subject else "surface"
    out = pathlib.Path(args.out)
    template_path = pathlib.Path(args.model) if args.model else build_builtin_face(target_tets=args.tets)

    def adapt():
        began = time.perf_counter()
        if out.exists() and not args.overwrite:  # before the work, not after
            raise FileExistsError(f"{out} already exists; pass --overwrite to replace it")
        template = read_model_arrays(template_path)
        if args.subject:
            capture = read_capture(args.subject, units=args.units, up_axis=args.up_axis,
                                   check_scale=not args.no_scale_check)
            neutral_frame = resolved_neutral_frame(args.neutral_frame, capture)
            neutral = capture.neutral(neutral_frame)
            correspondence = read_correspondence_file(args.correspondence)
            inputs = dict(subject_capture=str(pathlib.Path(args.subject).resolve()),
                          neutral_frame=neutral_frame % capture.n_frames,
                          correspondence_file=str(pathlib.Path(args.correspondence).resolve()))
            with _naming(args.subject):
                adaptation = subject.adapt_to_markers(template, neutral, capture.marker_names, correspondence,
                                                      name=out.name)
        else:
            scan = subject.read_surface(args.surface, units=args.units or "mm")
            landmarks = subject.read_landmark_file(args.landmarks, scan, units=args.units or "mm")
            inputs = dict(subject_surface=str(pathlib.Path(args.surface).resolve()),
                          landmarks_file=str(pathlib.Path(args.landmarks).resolve()))
            with _naming(args.surface):
                adaptation = subject.adapt_to_surface(template, scan, landmarks, name=out.name)
        info = dict(template=str(template_path.resolve()), template_name=template.name, **inputs,
                    residual_rms_mm=adaptation.rms, residual_max_mm=adaptation.max,
                    matching_rounds=adaptation.iterations, seconds=round(time.perf_counter() - began, 2))
        subject.write_adapted_model(adaptation, out, info=info, overwrite=args.overwrite)
        return subject.summary(adaptation, str(getattr(args, source)), template.name)
    log.info("%s", on_rank_0(adapt, MPI.COMM_WORLD))
    if MPI.COMM_WORLD.rank == 0:
        print(out.resolve())


@contextlib.contextmanager
def _naming(path):
    """Subject errors prefixed with the file they concern."""
    from face_dolfinx.subjects.adaptation import SubjectError
    try:
        yield
    except SubjectError as error:
        raise SubjectError(f"{path}: {error}") from None


def tracking_settings(args):
    """The fit command's settings: its preset (``--fast`` or the default), with every option given on
    the command line or in the --config file in place of the preset's."""
    from face_dolfinx.tracking import PRESETS, RECORD_FIELDS, SettingError
    preset = PRESETS["fast" if args.fast else "default"]
    try:
        return preset.updated({key: getattr(args, key) for key in RECORD_FIELDS})
    except SettingError as error:
        raise SystemExit(f"--{error.key.replace('_', '-')} {error.value}: {error.requirement}") from None


def fit(model, args) -> None:
    """Fit every frame of a take into a results folder (``face_dolfinx.tracking.Tracker``)."""
    from face_dolfinx.alignment.placement import place_on_model
    from face_dolfinx.capture import chunk_ranges, read_capture
    from face_dolfinx.capture.synthetic import truth_path
    from face_dolfinx.fitting.formulations import check_contact
    from face_dolfinx.results.folder import FitFolderError
    from face_dolfinx.tracking import Tracker
    comm = MPI.COMM_WORLD
    capture_path = pathlib.Path(args.capture)
    # Every input is checked before the result folder exists: a bad input leaves nothing behind.
    capture = read_capture(capture_path, units=args.units, up_axis=args.up_axis,
                           check_scale=not args.no_scale_check)
    neutral_frame = on_rank_0(lambda: resolved_neutral_frame(args.neutral_frame, capture), comm)
    placement = place_on_model(model, capture, neutral_frame, args.correspondence, args.accept_alignment)
    take_frames = np.arange(capture.n_frames)[_frame_slice(args.frames, capture.n_frames)]
    capture = capture.select(take_frames)
    truth_file = pathlib.Path(args.truth) if args.truth else truth_path(capture_path)
    settings = tracking_settings(args)
    setup = _marker_setup(args)
    chunks = len(chunk_ranges(capture.n_frames, args.chunks))
    if args.chunk is not None and not 0 <= args.chunk < chunks:
        raise SystemExit(f"--chunk {args.chunk}: the take has chunks 0..{chunks - 1}")
    tracker = Tracker(model, settings, rank_groups=1 if args.chunk is not None else min(chunks, comm.size))
    try:  # a formulation that cannot carry the contact: refused before the folder exists
        check_contact(tracker.problem, settings.fit)
    except ValueError as error:
        raise SystemExit(f"face-dolfinx fit: {error}") from None
    correspondence = str(pathlib.Path(args.correspondence).resolve()) if args.correspondence else None
    try:
        folder = tracker.open_folder(args.out, capture, placement, chunks=args.chunks, overwrite=args.overwrite,
                                     truth_file=truth_file if truth_file.exists() else None, setup=setup,
                                     take_frames=take_frames,
                                     extra=dict(correspondence=correspondence, take_frame_selection=args.frames,
                                                strength=args.strength,
                                                material=[override.describe() for override in model.material_overrides]))
    except FitFolderError as error:
        raise SystemExit(str(error)) from None
    if folder.finished:
        log.info("%s already holds this fit, finished: nothing to do (run.py report %s rebuilds its "
                 "plots; --overwrite fits again)", folder.path, folder.path)
        return
    _setup_logging(folder.path, verbose=args.verbose)
    run = tracker.run(folder, capture, placement, chunk=args.chunk, stop_after=args.stop_after)
    if not run.finished:
        log.info("%d frames still to fit; rerun the same command to continue %s", len(run.missing), folder.path)
        return
    log.info("results: %s (plots: *.png and renders/; ParaView: face.xdmf)", folder.path.resolve())


def neutral_frame_option(text: str) -> int | str:
    """``--neutral-frame``: a frame number or ``typical``."""
    if text.strip() == "typical":
        return "typical"
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: give a frame number or 'typical'") from None


def resolved_neutral_frame(choice: int | str, capture) -> int:
    """The neutral frame's number: ``choice`` itself, or the take's most typical frame."""
    if choice != "typical":
        return choice
    from face_dolfinx.alignment.neutral import typical_frame
    typical = typical_frame(capture)
    log.info("neutral frame %d: the take's most typical frame (its markers %.2f mm RMS from the take's median "
             "shape, head motion removed; frame 0: %.2f mm)", typical.frame, typical.rms_mm,
             typical.first_frame_rms_mm)
    return typical.frame


def _frame_slice(text: str | None, n_frames: int) -> slice:
    """``--frames START:STOP[:STEP]`` (Python slice syntax, STOP excluded; parts may be left out)."""
    if text is None:
        return slice(None)
    parts = text.split(":")
    try:
        if not 2 <= len(parts) <= 3:
            raise ValueError
        frames = slice(*(int(part) if part.strip() else None for part in parts))
    except ValueError:
        raise SystemExit(f"--frames {text}: give START:STOP or START:STOP:STEP (frame numbers, STOP excluded)") \
            from None
    if frames.step is not None and frames.step < 1:
        raise SystemExit(f"--frames {text}: the step must be 1 or more")
    if not len(range(n_frames)[frames]):
        raise SystemExit(f"--frames {text}: no frame of the {n_frames}-frame take")
    return frames


def _marker_setup(args):
    """The fit's marker setup: the --marker-setup file, with --validation-markers (names or a count)
    in place of the file's; None when neither is given."""
    from face_dolfinx.tracking import MarkerSetup
    if args.marker_setup is None and args.validation_markers is None:
        return None
    setup = MarkerSetup.read(args.marker_setup) if args.marker_setup else MarkerSetup()
    if args.validation_markers is not None:
        text = args.validation_markers.strip()
        setup = setup.with_validation(int(text) if text.isdigit() else
                                      tuple(name.strip() for name in text.split(",") if name.strip()))
    return setup


def demo(args) -> int:
    """The README's main job: build the built-in face, synthesise a speech-like take with head
    motion and 0.5 mm marker noise (its truth kept beside it), fit it, and write the results
    folder with its tables, plots, rendered frames, video and ParaView series. Rerun after an
    interruption, it continues where it stopped; once finished, it says so."""
    from face_dolfinx.model.anatomy import build_builtin_face
    out = pathlib.Path(args.out)
    verbose = ["--verbose"] if args.verbose else []
    model = ["--model", str(build_builtin_face(target_tets=args.tets))]
    take = out / "take.trc"
    if args.overwrite or not take.exists():
        main([*verbose, "synth", *model, "--frames", str(args.frames), "--out", str(take), "--overwrite"])
    fit_folder = out / "fit"
    main([*verbose, "fit", str(take), *model, "--out", str(fit_folder), *(["--overwrite"] if args.overwrite else [])])
    main([*verbose, "video", str(fit_folder)])
    if MPI.COMM_WORLD.rank == 0:
        print(f"take: {take.resolve()} (truth: {take.with_name('take.truth.npz').name})\n"
              f"results: {fit_folder.resolve()}\n"
              f"  plots: activations.png, kinematics.png, marker_error.png; renders/ (captured markers "
              f"red, simulated green); the take as a video: face.mp4 (or face.gif)\n"
              f"  tables: activations.csv, kinematics.csv, marker_errors.csv, frames.csv; "
              f"ParaView: face.xdmf")
    return 0


def _render_expression(problem, path: pathlib.Path, title: str) -> None:
    """The deformed skin, and the contact objects at their poses, as a PNG (rank 0 writes)."""
    from face_dolfinx.results.xdmf import displacement_at
    from face_dolfinx.results.render import render_skin
    points, triangles = problem.model.skin_surface()
    moved = points + displacement_at(problem.u, points)
    if MPI.COMM_WORLD.rank == 0:
        render_skin(moved, triangles, path, title=title, objects=_object_surfaces(problem))


def _object_surfaces(problem) -> list[tuple[np.ndarray, np.ndarray]]:
    """Points and triangles of each contact object's surface at its current pose (none without)."""
    if problem.contact is None:
        return []
    surfaces = []
    for obj, pose in zip(problem.contact.objects, problem.controls.objects):
        object_points, object_triangles = obj.surface()
        surfaces.append((pose.apply(object_points), object_triangles))
    return surfaces


def main(argv=None) -> int:
    """Run a command line; errors in what the user gave (files, options) end it with one message."""
    from face_dolfinx.alignment.similarity import AlignmentError
    from face_dolfinx.animation import AnimationError
    from face_dolfinx.capture import CaptureError
    from .config import ConfigError
    from face_dolfinx.model.folder import ModelError
    from face_dolfinx.subjects.adaptation import SubjectError
    from face_dolfinx.tracking import MarkerSetupError
    try:
        return _main(argv)
    except (AlignmentError, AnimationError, CaptureError, ConfigError, MarkerSetupError, ModelError,
            SubjectError) as error:
        raise SystemExit(f"face-dolfinx: error: {error}") from None


def parse_arguments(argv=None) -> tuple[argparse.Namespace, list[str]]:
    """The options of a command line, with those of its --config file under them; and the PETSc
    options (-face_*). Wrong or missing options end it with a usage message (SystemExit 2)."""
    from face_dolfinx.tracking import PRESETS
    parser = argparse.ArgumentParser(prog="face-dolfinx", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("-v", "--verbose", action="store_true")
    sub = parser.add_subparsers(dest="command", required=True)

    build = sub.add_parser("build", help="generate the built-in face model, or adapt a model to a subject")
    build.add_argument("--tets", type=int, default=50_000, help="target number of tetrahedra")
    build.add_argument("--model", help="template model folder to adapt (default: the built-in face)")
    build.add_argument("--subject", help="capture (TRC, CSV, C3D) whose neutral frame shapes the subject; "
                                         "needs --correspondence")
    build.add_argument("--surface", help="the subject's face surface (OBJ, STL, PLY, ...); needs --landmarks")
    build.add_argument("--correspondence", help="TOML or CSV: capture marker -> model landmark (>= 6)")
    build.add_argument("--landmarks", help="TOML or CSV: model landmark -> surface vertex id or [x, y, z]")
    build.add_argument("--neutral-frame", type=neutral_frame_option, default=0, metavar="N|typical",
                       help="frame of the subject capture at rest, or 'typical': the frame closest to the "
                            "take's median shape (default 0)")
    build.add_argument("--units", help="mm, cm or m: the capture's when it does not say, the surface's (default mm)")
    build.add_argument("--up-axis", choices=("Y", "Z"), help="vertical axis of the capture file")
    build.add_argument("--no-scale-check", action="store_true",
                       help="accept a capture whose markers do not span a face's 40-600 mm (needs the units "
                            "stated, by the file or --units)")
    build.add_argument("--out", help="folder of the adapted model (with --subject or --surface)")
    build.add_argument("--overwrite", action="store_true", help="replace an existing model folder")

    p = sub.add_parser("simulate", help="shapes for named expressions")
    p.add_argument("--model", help="model folder (default: the built-in face)")
    p.add_argument("--tets", type=int, default=50_000, help="built-in face resolution")
    p.add_argument("--degree", type=int, default=1, choices=(1, 2), help="displacement degree")
    p.add_argument("--out", default="results/simulate", help="result folder")
    p.add_argument("--overwrite", action="store_true", help="replace an existing result folder")
    p.add_argument("--no-render", action="store_true", help="skip the PNG renders")
    add_strength_option(p)
    add_material_option(p)
    p.add_argument("--coarse", metavar="TETS|FOLDER",
                   help="start each solve from the equilibrium of a coarse model of the same face: "
                        "the built-in face at TETS tets, or a model folder (docs/performance.md: "
                        "15 degree jaw opening at 404K tets 5x faster from the 50K face)")
    p.add_argument("--object", metavar="sphere:RADIUS|mesh:FILE",
                   help="a rigid sphere (radius in mm) or a closed triangle surface (.obj/.stl/.ply/.off, mm) "
                        "pressed against the skin along --path (docs/contact.md)")
    p.add_argument("--path", metavar="FILE",
                   help="the object's position over time: one 'x y z' line (mm, model frame) per frame, the "
                        "sphere's centre or the offset of the mesh file's origin")
    p.add_argument("--dynamic", action="store_true",
                   help="integrate in time with inertia (docs/dynamics.md): the --animation, one frame at each of "
                        "its times, or the expressions one after another, each reached in --expression-time "
                        "seconds, frames at --frame-rate")
    p.add_argument("--expression-time", type=float, default=0.3, metavar="S",
                   help="with --dynamic: seconds to reach each expression (default 0.3)")
    p.add_argument("--frame-rate", type=float, default=60.0, metavar="HZ", help="with --dynamic: frames per second")
    p.add_argument("--time-step", type=float, default=1.0 / 240.0, metavar="S",
                   help="with --dynamic: the largest time step (default 1/240 s), halved where Newton fails")
    p.add_argument("--scheme", choices=("newmark", "backward_euler"), default="newmark",
                   help="with --dynamic: Newmark's average acceleration (no numerical damping) or backward Euler")
    p.add_argument("--density", type=float, default=1e-6, metavar="KG_PER_MM3",
                   help="with --dynamic: tissue density (default 1e-6 kg/mm^3 = 1000 kg/m^3)")
    p.add_argument("--damping", type=float, default=0.0, metavar="ALPHA",
                   help="with --dynamic: mass-proportional damping (1/s)")
    p.add_argument("--viscosity", type=float, default=0.0, metavar="ETA",
                   help="with --dynamic: Kelvin-Voigt viscosity of the flesh (kPa s)")
    p.add_argument("--animation", metavar="FILE|FOLDER",
                   help="play an animation: a CSV or TOML file (docs/animation.md) or a fit or simulation "
                        "results folder; writes a results folder like a fit's, resumable frame by frame")
    p.add_argument("--stop-after", type=int, metavar="N",
                   help="with --animation: stop after N frames, leaving the folder unfinished; the same "
                        "command without it continues where this one stopped")
    p.add_argument("--newton-tolerance", type=float, default=1e-8, metavar="MM",
                   help="with --animation: Newton stops once a correction moves no node further than this "
                        "(default 1e-8 mm)")
    p.add_argument("--reuse-factorization", action="store_true",
                   help="with --animation: modified Newton, keeping the last MUMPS factor across iterations "
                        "and frames while each iteration cuts the residual 4-fold (faster; a resumed run then "
                        "matches an uninterrupted one to solver tolerance, not bit for bit)")
    p.add_argument("--contact", action="store_true",
                   help="keep the lips and cheeks outside the model's teeth (their oral lining) and the lips "
                        "outside each other (docs/contact.md)")
    p.add_argument("--contact-relaxation", action=argparse.BooleanOptionalAction, default=None,
                   help="with --contact or --object: after each Newton correction the nodes in contact are brought "
                        "to their own equilibrium by a local Newton, the rest of the face held (fit "
                        "--contact-relaxation; by default only once a Newton solve crawls on them or its residual "
                        "falls slowly on the teeth's nodes, never with "
                        "--no-contact-relaxation); "
                        "with --newton-energy-tolerance 10 the lips closed hard on the 404K face without a failed "
                        "Newton solve, which fail without it; on the 5K face it costs more than it saves "
                        "(docs/contact.md, \"Lip self-contact\")")
    p.add_argument("--newton-energy-tolerance", type=float, metavar="MJ",
                   help="with --contact or --object: Newton also stops once a correction would release less "
                        "energy than this (mN mm; fit --fast takes 100): pressed lips slide along each other in "
                        "corrections of a millimetre that release micro-joules")
    p.add_argument("expressions", nargs="*", help="expression names defined in the model")

    p = sub.add_parser("retarget", help="carry a fit's or an animation's motion onto another model",
                       description=retarget_animation.__doc__)
    p.add_argument("animation", nargs="?",
                   help="a fit or simulation results folder, or an animation file (CSV, TOML)")
    p.add_argument("--model", help="the target model folder (default: the built-in face at --tets)")
    p.add_argument("--tets", type=int, default=20_000, help="built-in face resolution")
    p.add_argument("--source-model", help="the model the animation was made for (default: the one a results "
                                          "folder names in its run.json)")
    p.add_argument("--out", help="the animation file to write (.csv)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing animation file")

    p = sub.add_parser("edit", help="edit an animation or fit in activation space -> an animation CSV",
                       description="Edits of fitted or written animations, each control on its own space "
                                   "(docs/animation.md): in-betweens of two poses, exaggeration about neutral, "
                                   "splicing and retiming, keyframes of one muscle, smoothing. SOURCE is a "
                                   "CSV or TOML animation or a fit or simulation folder; a POSE is SOURCE@SECONDS, "
                                   "SOURCE#FRAME or expression:NAME. The result is a CSV for simulate --animation.")
    operations = p.add_subparsers(dest="operation", required=True)

    def edit_options(q):
        q.add_argument("--out", required=True, help="the edited animation (.csv)")
        q.add_argument("--overwrite", action="store_true", help="replace an existing --out")
        q.add_argument("--model", help="model folder: for expression:NAME poses, and to check the result against")
        q.add_argument("--tets", type=int, help="the built-in face at this resolution, as --model")

    q = operations.add_parser("between", help="in-betweens of two poses (sifakis2005 figure 10)")
    q.add_argument("first", metavar="POSE")
    q.add_argument("second", metavar="POSE")
    q.add_argument("--frames", type=int, default=11, help="poses from the first to the second, both included")
    q.add_argument("--duration", type=float, default=1.0, help="seconds from the first pose to the second")
    edit_options(q)
    q = operations.add_parser("scale", help="exaggerate or tone down activations, clamped to [0, 1]")
    q.add_argument("source", metavar="SOURCE")
    q.add_argument("--factor", type=float, required=True, help="> 1 exaggerates, < 1 tones down")
    q.add_argument("--about", metavar="POSE", help="scale about this pose's activations (default: neutral, 0)")
    edit_options(q)
    q = operations.add_parser("splice", help="segments of animations one after another, retimed")
    q.add_argument("parts", nargs="+", metavar="SOURCE[@START:STOP][xSPEED]",
                   help="a time range of a source (seconds of its own clock), played SPEED times as fast")
    q.add_argument("--transition", type=float, metavar="S",
                   help="seconds of in-betweens across each seam (default: one frame)")
    q.add_argument("--frame-rate", type=float, metavar="HZ", help="resample every part at this rate")
    edit_options(q)
    q = operations.add_parser("keyframes", help="keyframes of one muscle on top of an animation")
    q.add_argument("source", metavar="SOURCE")
    q.add_argument("--muscle", required=True)
    q.add_argument("--keys", required=True, metavar="T=A,...", help="activation A at time T (s), comma-separated")
    q.add_argument("--blend", type=float, default=0.1, metavar="S",
                   help="seconds over which the keys blend in before the first and out after the last (0.1)")
    q.add_argument("--interpolation", choices=("smooth", "linear"), default="smooth")
    edit_options(q)
    q = operations.add_parser("smooth", help="smooth the curves in time, clamped")
    q.add_argument("source", metavar="SOURCE")
    q.add_argument("--time-constant", type=float, required=True, metavar="S",
                   help="the Gaussian's standard deviation (s); Savitzky-Golay's window is +- 2 of them")
    q.add_argument("--method", choices=("gaussian", "savgol"), default="gaussian")
    edit_options(q)

    p = sub.add_parser("demo", help="the main job: build the face, synthesise a take, fit it",
                       description=demo.__doc__)
    p.add_argument("--tets", type=int, default=20_000, help="built-in face resolution")
    p.add_argument("--frames", type=int, default=20, help="frames of the synthetic take")
    p.add_argument("--out", default="results/demo", help="folder for the take and the fit")
    p.add_argument("--overwrite", action="store_true", help="synthesise and fit again from scratch")

    p = sub.add_parser("report", help="(re)build the plots, renders and XDMF of a fit folder",
                       description="Rebuild activations.png, kinematics.png, marker_error.png, "
                                   "renders/ and face.xdmf of a fit results folder from its frame "
                                   "files; for an unfinished fit, of the frames done so far (the "
                                   "missing ones are named). Runs on one process.")
    p.add_argument("folder", help="results folder written by fit")
    p.add_argument("--renders", type=int, default=4, help="number of frames to render")

    p = sub.add_parser("video", help="MP4 (or GIF) of a fit folder: the rendered skin over time",
                       description="The skin of every fitted frame (or every STEP-th), captured markers red "
                                   "and simulated green, time and marker error in the caption, played at "
                                   "the take's rate: FOLDER/face.mp4 (H.264), or face.gif where no encoder "
                                   "is found or with --gif. Runs on one process.")
    p.add_argument("folder", help="results folder written by fit")
    p.add_argument("--out", help="the video file (default FOLDER/face.mp4 or face.gif)")
    p.add_argument("--view", choices=("front", "three_quarter", "side"), default="front")
    p.add_argument("--step", type=int, default=1, help="every STEP-th fitted frame (default 1: all)")
    p.add_argument("--fps", type=float, help="frames per second (default: real time)")
    p.add_argument("--gif", action="store_true", help="an animated GIF instead of an MP4")

    def model_options(p, out):
        p.add_argument("--model", help="model folder (default: the built-in face)")
        p.add_argument("--tets", type=int, default=20_000, help="built-in face resolution")
        p.add_argument("--out", default=out, help="output path")
        p.add_argument("--overwrite", action="store_true", help="replace existing output")
        add_strength_option(p)
        add_material_option(p)

    p = sub.add_parser("synth", help="synthetic take with known truth")
    model_options(p, "takes/speech.trc")
    p.add_argument("--scenario", default="speech",
                   help="smile, jaw, brow, speech, mixed, training (Choe & Ko's: each muscle alone, "
                        "jaw limits, expressions; give frames = a multiple of the segment count) or bilabial "
                        "(ma ba pa: lips pressed together three times; with --contact)")
    p.add_argument("--contact", action="store_true",
                   help="contact in the truth's solves, what fit --contact models: the lips on each other and "
                        "the lining on the model's teeth (docs/contact.md)")
    p.add_argument("--truth-contact", choices=("lips", "lips+teeth"),
                   help="with --contact: lips (the lips only) or lips+teeth (default for a model with teeth)")
    p.add_argument("--frames", type=int, default=30)
    p.add_argument("--take-frames", type=int,
                   help="write only --frames frames of a take this long (the scenario's motion spans the "
                        "whole take, so a short stretch of a long take moves at capture speed)")
    p.add_argument("--first-frame", type=int, default=0, help="with --take-frames: where the stretch starts")
    p.add_argument("--rate", type=float, default=60.0, help="frame rate (Hz)")
    p.add_argument("--noise", type=float, default=0.5, help="marker noise, RMS of the 3D error (mm)")
    p.add_argument("--outliers", type=int, default=0, help="markers jumping 10 mm for 3 frames")
    p.add_argument("--gaps", type=int, default=0, help="markers missing for a stretch of frames")
    p.add_argument("--no-head-motion", action="store_true")
    p.add_argument("--seed", type=int, default=0)

    p = sub.add_parser("fit", help="fit activations and bone motion to a take")
    model_options(p, "results/fit")
    p.add_argument("capture", nargs="?", help="TRC, CSV or C3D file of the take")
    p.add_argument("--correspondence",
                   help="TOML or CSV: capture marker -> model landmark (>= 6), to align a capture whose "
                        "markers are not the model's marker sites (without it: ICP against the skin)")
    p.add_argument("--neutral-frame", type=neutral_frame_option, default=0, metavar="N|typical",
                   help="frame of the take at rest: aligned to the model, its markers embedded in the skin; "
                        "'typical': the frame closest to the take's median shape, head motion removed "
                        "(for takes that do not start at rest; default 0)")
    p.add_argument("--accept-alignment", action="store_true",
                   help="fit even when the alignment to the model is judged wrong (a left/right swap, a pair "
                        "far off, an implausible scale): warned about and recorded in alignment.json")
    p.add_argument("--units", help="mm, cm or m when the file does not say")
    p.add_argument("--up-axis", choices=("Y", "Z"), help="vertical axis of the file")
    p.add_argument("--no-scale-check", action="store_true",
                   help="accept markers that do not span a face's 40-600 mm (needs the units stated, by the "
                        "file or --units)")
    # The tracking settings default to None: the preset (--fast or the default) fills in what
    # neither the command line nor the --config file gives.
    default = PRESETS["default"]
    p.add_argument("--mode", choices=("exact", "paper"), help=f"formulation (default {default.fit.mode})")
    p.add_argument("--gn-steps", type=int, help=f"Gauss-Newton steps per frame (default {default.fit.max_gn_steps})")
    p.add_argument("--smoothness", type=float,
                   help="temporal smoothness weight on activations (default 0: off)")
    p.add_argument("--effort", type=float,
                   help="weight of the effort term, the sum of squared activations (mm^2; default 0: off)")
    p.add_argument("--intraoral-pressure", action="store_true", default=None,
                   help="fit the air pressure in the mouth too (a follower load on the lining of lips and "
                        "cheeks, kPa; the model needs an 'oral' surface; LU instead of Cholesky)")
    p.add_argument("--pressure-limit", type=float, metavar="KPA",
                   help=f"bound of the intraoral pressure, +- (default {default.fit.pressure_limit:g} kPa)")
    p.add_argument("--validation-markers", metavar="A,B,...|N",
                   help="markers left out of the fit to measure prediction (embedded at the neutral frame, "
                        "followed, reported in frames.csv and accuracy.json): names, or a count picked "
                        "spread over the face")
    p.add_argument("--marker-setup", metavar="FILE",
                   help="TOML file of marker groups, weights (0: not fitted) and validation markers "
                        "(docs/cli.md)")
    p.add_argument("--frames", metavar="START:STOP[:STEP]",
                   help="fit part of the take, or every STEP-th frame (frame numbers of the take, STOP excluded)")
    p.add_argument("--truth", help="truth .npz of a synthetic take (default: next to the capture)")
    p.add_argument("--reuse-factorization", action="store_true", default=None,
                   help="modified Newton: keep the last MUMPS factor across Newton iterations and "
                        "frames, refactorising only when an iteration cuts the residual less than "
                        "4-fold (faster on large meshes; a resumed run then matches an uninterrupted "
                        "one to solver tolerance, not bit for bit)")
    p.add_argument("--fresh-jacobians", type=int, metavar="N",
                   help="fresh Jacobians per warm frame after its first Gauss-Newton step, which "
                        "reuses the last frame's (default: one per step; 1 with "
                        "--reuse-factorization is the fast setting of docs/performance.md)")
    p.add_argument("--newton-tolerance", type=float, metavar="MM",
                   help="Newton stops once a correction moves no node further than this (default "
                        "1e-8 mm; 1e-4 and 1e-3 mm changed no fitted marker or activation error in "
                        "docs/performance.md and save iterations)")
    p.add_argument("--newton-energy-tolerance", type=float, metavar="MJ",
                   help="with --contact: Newton also stops once a correction would release less energy than "
                        "this (mN mm), which the pressed lips' sliding corrections of a millimetre do "
                        "(default: off; see docs/performance.md, \"Contact in tracking\")")
    p.add_argument("--refresh-contraction", type=float, metavar="R",
                   help=f"with --reuse-factorization: refactorise when a Newton iteration cuts the "
                        f"residual by less than this factor (default {default.refresh_contraction})")
    p.add_argument("--line-search-iterations", type=int, metavar="N",
                   help="secant iterations of Newton's line search (default 1; 3 cut the slowest "
                        "frames at 404K tets, where the lips move fast, from 94 to 21 s)")
    p.add_argument("--krylov", action="store_true", default=None,
                   help="with --reuse-factorization: solve each Newton correction by GMRES preconditioned "
                        "by the old factor instead of refactorising when Newton slows (fewer factorisations, "
                        "more residuals and solves; see docs/performance.md, \"Contact in tracking\")")
    p.add_argument("--contact", action="store_true", default=None,
                   help="contact in every equilibrium, as simulate --contact: the upper and lower lip press on "
                        "each other instead of passing through, and the lining of the lips and cheeks rests on "
                        "the model's teeth (a model without teeth: the lips only, with a note in the log); "
                        "run.json's contact_surfaces records which. The sensitivities include it; exact "
                        "mode only (docs/contact.md)")
    p.add_argument("--contact-relaxation", action=argparse.BooleanOptionalAction, default=None,
                   help="with --contact: after each Newton correction the nodes in contact are brought to their "
                        "own equilibrium by a local Newton, the rest of the face held (tracking at 20K-404K tets "
                        "paid more for it than it saved; docs/performance.md, \"Contact in tracking\"); by "
                        "default only once a Newton solve crawls on them (the lips peeling apart, \"The lips' "
                        "opening\") or its residual falls slowly on the teeth's nodes (\"Settling on the teeth\"), "
                        "never with --no-contact-relaxation")
    p.add_argument("--approximate-jacobians", type=float, metavar="MM",
                   help="a Jacobian may use the last factor of the equilibrium solve if it was made at "
                        "a state this close to the equilibrium, instead of a new factorisation, and is "
                        "otherwise from a factor of Newton's tangent at the equilibrium, which the next "
                        "Newton solves keep (default 0: always the exact tangent)")
    p.add_argument("--fast", action="store_true",
                   help="the preset for takes at capture rate (face_dolfinx.tracking, docs/performance.md): "
                        + " ".join(f"--{key.replace('_', '-')}" + ("" if value is True else f" {value}")
                                   for key, value in PRESETS["fast"].record().items()
                                   if value != default.value(key))
                        + " (options given here or in --config win)")
    p.add_argument("--chunks", type=int, default=1,
                   help="split the take into independent chunks (each starts from rest); under "
                        "mpirun the ranks share them out")
    p.add_argument("--chunk", type=int, help="fit only this chunk (for separate processes)")
    p.add_argument("--stop-after", type=int, metavar="N",
                   help="stop after fitting N frames, leaving the folder unfinished; the same "
                        "command without it continues where this one stopped")

    for command_parser in sub.choices.values():
        command_parser.add_argument("--config", help="TOML file of options (docs/cli.md); flags given here win")
    args, petsc_args = parser.parse_known_args(argv)
    # Precedence: options given here, then the --config file (as defaults), then the preset
    # (``tracking_settings``), then the defaults.
    if args.config:
        from .config import option_defaults
        main_defaults, command_defaults = option_defaults(args.config, args.command, parser, sub.choices)
        parser.set_defaults(**main_defaults)
        sub.choices[args.command].set_defaults(**command_defaults)
        args, petsc_args = parser.parse_known_args(argv)
    for command, positional in (("fit", "capture"), ("simulate", "expressions")):
        moving_an_object = command == "simulate" and getattr(args, "path", None) is not None
        animating = command == "simulate" and getattr(args, "animation", None) is not None
        if args.command == command and not getattr(args, positional) and not (moving_an_object or animating):
            sub.choices[command].error(f"the {positional} argument is required (on the command line or "
                                       f"as {positional!r} in the --config file)")
    if args.command == "build" and (args.subject or args.surface):
        if args.subject and args.surface:
            build.error("give --subject (a capture) or --surface (a scan), not both")
        source, needed = ("subject", "correspondence") if args.subject else ("surface", "landmarks")
        for option in (needed, "out"):
            if not getattr(args, option):
                build.error(f"--{source} needs --{option}")
    # Unparsed -face_* arguments are PETSc options (e.g. -face_pc_type hypre).
    unknown = [a for a in petsc_args if not a.startswith("-face_") and not _is_value(a, petsc_args)]
    if unknown:
        parser.error(f"unrecognised arguments: {' '.join(unknown)}")
    return args, petsc_args


def _main(argv=None) -> int:
    args, petsc_args = parse_arguments(argv)
    if petsc_args:
        from petsc4py import PETSc
        PETSc.Options().insertString(" ".join(petsc_args))
    _setup_logging(verbose=args.verbose)

    if args.command == "build":
        from face_dolfinx.model.anatomy import build_builtin_face
        if args.subject or args.surface:
            build_subject(args)
            return 0
        path = build_builtin_face(target_tets=args.tets)
        if MPI.COMM_WORLD.rank == 0:
            print(path)
        return 0

    if args.command == "report":
        from face_dolfinx.results.report import write_report
        on_rank_0(lambda: write_report(args.folder, rendered_frames=args.renders), MPI.COMM_WORLD)
        return 0
    if args.command == "video":
        from face_dolfinx.results.video import write_video

        try:
            written = on_rank_0(lambda: write_video(args.folder, args.out, view=args.view, step=args.step,
                                                    fps=args.fps, gif=args.gif), MPI.COMM_WORLD)
        except (FileNotFoundError, ValueError) as error:
            raise SystemExit(f"face-dolfinx video: error: {error}") from None
        log.info("video: %s", written)
        return 0
    if args.command == "retarget":
        retarget_animation(args)
        return 0
    if args.command == "demo":
        return demo(args)
    if args.command == "edit":
        edit(args)
        return 0

    model = _model_from_args(args)
    if args.command == "synth":
        synth(model, args)
        return 0
    if args.command == "fit":
        fit(model, args)
        return 0
    if args.animation is not None:
        if args.expressions or args.object or args.path or args.coarse:
            raise SystemExit("--animation plays the animation alone: give no expressions, --object, --path "
                             "or --coarse with it")
        simulate_animation(model, args)
        return 0
    out = pathlib.Path(args.out)
    if args.dynamic:
        return _simulate_dynamic_expressions(model, args, out)
    contact = _object_from_args(args)
    try:
        rows = simulate(model, args.expressions, out, degree=args.degree, overwrite=args.overwrite,
                        render=not args.no_render, coarse_model=_coarse_model(args), contact=contact,
                        lip_contact=_lip_contact(args), contact_solver=_contact_solver(args))
    except ValueError as error:
        if contact is None and not args.contact:
            raise
        raise SystemExit(str(error)) from None
    if MPI.COMM_WORLD.rank == 0:
        print(f"results: {out.resolve()} ({len(rows)} expressions; face.xdmf for ParaView, PNG renders)")
    return 0


def _simulate_dynamic_expressions(model, args, out: pathlib.Path) -> int:
    """``simulate --dynamic``: the named expressions played in time (``simulate_dynamic``); with
    ``--object``/``--path`` the object then moves along its path, one pose per frame, and stays at
    the last one for ``--expression-time``; ``--contact``: the lips and the teeth."""
    if args.coarse:
        raise SystemExit("simulate --dynamic: --coarse is for quasistatic simulation")
    settings = dynamic_settings(args)
    if not (math.isfinite(args.expression_time) and args.expression_time > 0):
        raise SystemExit(f"simulate --dynamic: --expression-time {args.expression_time}: give a positive number of seconds")
    if not (math.isfinite(args.frame_rate) and args.frame_rate > 0):
        raise SystemExit(f"simulate --dynamic: --frame-rate {args.frame_rate}: give a positive rate (Hz)")
    for name in args.expressions:  # fail before any work
        _expression_controls(model, name)
    controls_at, duration = expression_sequence(model, args.expressions, args.expression_time)
    contact = _object_from_args(args)
    source = dict(expressions=args.expressions, expression_time_s=args.expression_time)
    if contact is not None and contact[1]:
        first = math.ceil(duration * args.frame_rate - 1e-9) / args.frame_rate  # each pose on a frame
        controls_at, duration = object_path_controls(controls_at, first, contact[1], 1.0 / args.frame_rate,
                                                     args.expression_time)
        source.update(object=args.object, path=args.path)
    times = np.arange(0.0, duration + 0.5 / args.frame_rate, 1.0 / args.frame_rate)
    rows = simulate_dynamic(model, controls_at, times, out, settings, degree=args.degree, overwrite=args.overwrite,
                            source=source, contact=contact[0] if contact is not None else None,
                            lip_contact=_lip_contact(args), contact_solver=_contact_solver(args))
    if MPI.COMM_WORLD.rank == 0:
        print(f"results: {out.resolve()} ({len(rows)} frames; face.xdmf for ParaView)")
    return 0


def _is_value(arg: str, args: list[str]) -> bool:
    """True if ``arg`` is the value following a -face_* option."""
    i = args.index(arg)
    return i > 0 and args[i - 1].startswith("-face_") and not arg.startswith("-")
