"""Where the methods fail (issue 5): the forward solver and the fitter pushed until they break.

Five studies (--studies, default all); a run that fails is a row with its failure mode, never a
crash of the script.

  forward  rest -> a hard load in ONE call on the --tets faces (default 5K and 20K): every muscle
           0 -> 1, the smile, the pucker, the jaw opened to its limit (asin of max_opening_sine)
           and 1.4 x beyond it, the widest jaw (limit + both condyle slides), every muscle + the
           jaw limit. Four solver variants (VARIANTS):
             newton    plain Newton: full steps (PETSc ``basic`` line search), no inversion
                       guard, no continuation
             cp        the critical-point line search, no guard, no continuation
             cp-guard  cp + the inversion guard, no continuation
             default   cp + guard + the continuation fallback (FaceProblem's defaults)
           Recorded: converged, failure mode (inverted: NaN residual; guard stall; line-search
           failure; iteration limit; for the default, how far its continuation got), Newton
           iterations, factorisations, load steps, the smallest cell volume ratio (det F) of the
           final iterate, the distance to the default's equilibrium, the residual history, seconds.
  ramp     the coarsest faces and one finer (--ramp-tets, default 1K, 2K, 5K, 20K) with loads
           of growing size, each in one call from rest: every muscle at a level, the jaw opened to
           a multiple of its limit (up to 5 x, far beyond the joint's range, to find where the
           default gives up), both together; the same four variants. Which variant fails first,
           and how close the default's equilibrium comes to inverting a cell.
  remote   a Gauss-Newton fit of one synthetic frame from a remote initial guess (rest, or the
           opposite activations with the widest jaw) on the --remote-tets face; REMOTE_TARGETS:
           expressions with the jaw open, a random activation pattern at growing distance, the
           head turned up to 180 degrees, one target with 0.5 mm noise. Methods (REMOTE_METHODS):
           exact (hard bounds) or paper (penalties) mode, with the line search or without it
           (``FitSettings(line_search=False)``: every full step is taken), and the same with a
           looser Newton tolerance (--remote-methods picks some). Recorded: marker RMS,
           activation and bone-pose errors against the truth, penalty violations, steps, whether
           the line search ran, the outcome (recovered; not identifiable or wrong minimum =
           markers fitted, activations far; stalled; step limit; failed).
  head     the smile with the jaw open and the head turned by 0..180 degrees (the --remote-tets
           face): rest -> turned, a second Newton solve in place (how far the residual of an
           equilibrium falls, against snes_atol), and back to rest. What broke the remote fits.
  damage   a short synthetic speech take (--damage-frames frames with head motion, --damage-tets
           face) fitted after damage of growing severity in every frame: outlier markers (how
           many jump 10 mm; how far one marker jumps), gaps (fraction of markers missing), noise.
           Recorded per take: marker RMS against the clean truth (all markers and the undamaged
           ones), the error at the damaged markers, activation error, flagged frames (and the
           controls named under-determined, with each frame's observability), failures.
           --damage-families picks takes (e.g. ``clean gaps``).

One JSON line per run goes to --out (appended; in the tables a later row of the same run replaces
an earlier one, so a study or method can be rerun alone). ``--collect`` prints the Markdown tables
from one or more such files, ``--plot PREFIX`` also writes the charts PREFIX_<study>.png:

    nice -n 19 python benchmarks/stability.py --out runs/stability.jsonl
    python benchmarks/stability.py --collect runs/stability.jsonl --plot docs/img/stability

Run it on one process: the study is about failure modes, not speed (wall times compare the
variants within a row).
"""
import argparse
from dataclasses import dataclass
import json
import math
import pathlib
import re
import time

from mpi4py import MPI
import numpy as np


STUDIES = ("forward", "ramp", "remote", "head", "damage")


@dataclass(frozen=True)
class Variant:
    """A forward-solver configuration: FaceProblem arguments and whether continuation may help."""
    petsc_options: dict
    inversion_guard: bool
    continuation: bool


VARIANTS = {
    "newton": Variant({"snes_linesearch_type": "basic"}, inversion_guard=False, continuation=False),
    "cp": Variant({}, inversion_guard=False, continuation=False),
    "cp-guard": Variant({}, inversion_guard=True, continuation=False),
    "default": Variant({}, inversion_guard=True, continuation=True),
}
# name: (activations: a level for every muscle or a named expression, jaw opening as a multiple of
# its limit, both condyles at the end of their tracks)
FORWARD_LOADS = {
    "all_muscles": (1.0, 0.0, False),
    "smile": ("smile", 0.0, False),
    "pucker": ("pucker", 0.0, False),
    "jaw_limit": (0.0, 1.0, False),
    "jaw_1.4x_limit": (0.0, 1.4, False),
    "jaw_widest": (0.0, 1.0, True),
    "all_muscles+jaw_limit": (1.0, 1.0, False),
}
# Ramp families: (activation level, jaw opening / limit) per unit level, and the levels.
# The jaw goes far beyond its limit (5 x 25 degrees) to find where even the default gives up.
RAMPS = {
    "muscles": ((1.0, 0.0), (0.1, 0.25, 0.5, 0.75, 1.0)),
    "jaw": ((0.0, 1.0), (0.25, 0.5, 1.0, 2.0, 3.0, 4.0, 5.0)),
    "muscles+jaw": ((1.0, 1.0), (0.25, 0.5, 0.75, 1.0)),
}
REMOTE_METHODS = {
    # name: (FitSettings fields, PETSc options of the equilibrium solver)
    "exact": (dict(mode="exact"), {}),
    "exact-no-ls": (dict(mode="exact", line_search=False), {}),
    "paper": (dict(mode="paper"), {}),
    "paper-no-ls": (dict(mode="paper", line_search=False), {}),
    # The default snes_atol (1e-9 mN) lies below the residual's round-off once the head is turned
    # far; these variants tell that failure apart from the Gauss-Newton's own.
    "exact atol 1e-7": (dict(mode="exact"), {"snes_atol": 1e-7}),
    "exact-no-ls atol 1e-7": (dict(mode="exact", line_search=False), {"snes_atol": 1e-7}),
    "paper atol 1e-7": (dict(mode="paper"), {"snes_atol": 1e-7}),
}


@dataclass(frozen=True)
class RemoteTarget:
    """A synthetic frame to fit from a remote initial guess."""
    activations: str                # an expression's name, or "random" (a seeded U(0, 1) pattern)
    scale: float = 1.0              # activations x scale
    opening_deg: float = 0.0        # jaw opening
    head_deg: float = 0.0           # head turned about HEAD_AXIS through the markers' centre
    noise: float = 0.0              # marker noise, RMS of the 3D error (mm)
    opposite_start: bool = False    # start from 1 - activations and the widest jaw, not from rest


HEAD_AXIS = (0.3, 1.0, 0.2)  # mostly a turn to the side, with some nod and tilt
HEAD_TURNS = (0.0, 15.0, 30.0, 60.0, 90.0, 135.0, 180.0)
REMOTE_TARGETS = {
    "smile, jaw 15": RemoteTarget("smile", opening_deg=15.0),
    "pucker, jaw 20": RemoteTarget("pucker", opening_deg=20.0),
    "random x0.25, jaw 5, head 2.5": RemoteTarget("random", 0.25, 5.0, 2.5),
    "random x0.5, jaw 10, head 5": RemoteTarget("random", 0.5, 10.0, 5.0),
    "random x1, jaw 20, head 10": RemoteTarget("random", 1.0, 20.0, 10.0),
    "smile, jaw 15, head 30": RemoteTarget("smile", opening_deg=15.0, head_deg=30.0),
    "smile, jaw 15, head 60": RemoteTarget("smile", opening_deg=15.0, head_deg=60.0),
    "smile, jaw 15, head 90": RemoteTarget("smile", opening_deg=15.0, head_deg=90.0),
    "smile, jaw 15, head 135": RemoteTarget("smile", opening_deg=15.0, head_deg=135.0),
    "smile, jaw 15, head 180": RemoteTarget("smile", opening_deg=15.0, head_deg=180.0),
    "smile, jaw 15, from the opposite": RemoteTarget("smile", opening_deg=15.0, opposite_start=True),
    "random x1, jaw 20, head 10, noise 0.5": RemoteTarget("random", 1.0, 20.0, 10.0, noise=0.5),
}
# Markers within this (or 1.1 x the noise) are "fitted"; activations within this are "recovered".
FITTED_MARKER_RMS = 0.1
RECOVERED_ACTIVATION_ERROR = 0.1
DAMAGE = {
    # family: (severity, levels); outlier_count: how many markers jump OUTLIER_JUMP mm,
    # outlier_size: how far one marker jumps
    "outlier_count": ("markers jumping 10 mm", (1, 2, 4, 8, 16)),
    "outlier_size": ("jump of one marker (mm)", (5.0, 10.0, 20.0, 40.0)),
    "gaps": ("fraction of markers missing", (0.1, 0.2, 0.4, 0.6, 0.8, 0.9)),
    "noise": ("noise, RMS of the 3D error (mm)", (0.25, 0.5, 1.0, 2.0, 4.0)),
}
OUTLIER_JUMP = 10.0


# -- helpers ---------------------------------------------------------------------------------------
def tets_of(model) -> int:
    return int(model.mesh.topology.index_map(3).size_global)


def failure_mode(reason: str, guarded: bool) -> str:
    """Short name of why a Newton solve stopped, from the SNES reason or the solver's message."""
    if "FNORM_NAN" in reason:
        return "inverted (NaN residual)"
    if "LINE_SEARCH" in reason:
        # With the guard every trial step keeps cells above a tenth of their volume, so the line
        # search itself cannot fail on NaN: DIVERGED_LINE_SEARCH is the guard's stall test (three
        # heavily cut steps in a row). Without it, the line search met an inverted element.
        return "guard stall" if guarded else "line search failed"
    if "MAX_IT" in reason:
        return "iteration limit"
    if "Dirichlet" in reason:
        return "bone positions not reached"
    if "DTOL" in reason or "DIVERGED" in reason:
        return "diverged"
    return reason


def turned_head(model, degrees: float):
    """The cranium frame turned by ``degrees`` about HEAD_AXIS through the markers' centre."""
    from face_dolfinx.model.bones import rigid_map, rotation
    centre = np.array(list(model.markers.values())).mean(axis=0)
    return rigid_map(rotation(HEAD_AXIS, math.radians(degrees)), centre, np.zeros(3))


def load_controls(model, activations, opening: float, slide: bool):
    """Controls of a load: ``activations`` a level for every muscle or an expression's name,
    the jaw opened by ``opening`` times its limit (asin of max_opening_sine), the condyles at the
    end of their tracks if ``slide``."""
    from face_dolfinx.model.bones import AffineMap, jaw_pose
    from face_dolfinx.physics.problem import Controls

    jaw = model.jaw
    levels = np.zeros(len(model.muscles))
    if isinstance(activations, str):
        for muscle, value in model.expressions[activations].items():
            levels[model.muscle_index(muscle)] = value
    else:
        levels[:] = activations
    track = jaw.track_length if slide else 0.0
    return Controls(levels, AffineMap(), jaw_pose(jaw, opening * math.asin(jaw.max_opening_sine), track, track))


def to_rest(problem) -> None:
    """Put the problem back at rest, the exact equilibrium of zero controls, without a solve
    (FaceProblem.solve would walk the controls back from wherever they were)."""
    problem.reset_to_rest()


class ForwardRunner:
    """One FaceProblem per variant; solves rest -> a load in one call and measures the result."""

    def __init__(self, model, variant: str):
        from face_dolfinx.physics.problem import FaceProblem
        from face_dolfinx.equilibrium.solver import InversionGuard

        self.variant = VARIANTS[variant]
        self.problem = FaceProblem(model, petsc_options=self.variant.petsc_options,
                                   inversion_guard=self.variant.inversion_guard)
        self.volume_meter = InversionGuard(self.problem.V)  # a measuring device here, guard or not
        self.residuals = []  # (Newton iteration within its SNES solve, residual norm)
        self.problem.solver.snes.setMonitor(lambda snes, its, fnorm: self.residuals.append((its, fnorm)))

    def solve(self, target) -> dict:
        from face_dolfinx.equilibrium.solver import EquilibriumError

        problem = self.problem
        to_rest(problem)
        self.residuals.clear()
        factorizations = problem.solver.factorizations
        began = time.perf_counter()
        reached, load_steps = 1.0, 1
        if self.variant.continuation:
            try:
                report = problem.solve(activations=target.activations, cranium=target.cranium,
                                       jaw=target.jaw)
                converged, reason, load_steps = True, "converged", report.load_steps
            except EquilibriumError as error:
                converged, reason = False, str(error)
                reached = float(re.search(r"beyond ([0-9.]+)", reason).group(1))
                load_steps = 0
        else:
            # What solve(max_halvings=0) does, except that the failed iterate is kept to be measured.
            problem.set_controls(target)
            converged, _, reason = problem.solver.newton()
        seconds = time.perf_counter() - began
        return dict(
            converged=bool(converged),
            failure="" if converged else failure_mode(reason, self.variant.inversion_guard),
            reason=reason,
            newton_iterations=sum(1 for its, _ in self.residuals if its > 0),
            factorizations=problem.solver.factorizations - factorizations,
            load_steps=load_steps, reached=reached,
            min_volume_ratio=self.volume_meter.min_ratio(problem.u.x.array),
            residuals=[fnorm for _, fnorm in self.residuals],
            residual_restarts=[k for k, (its, _) in enumerate(self.residuals) if its == 0],
            seconds=seconds)


def largest_distance(comm, a: np.ndarray, b: np.ndarray) -> float:
    """Largest nodal distance (mm) between two displacement arrays, over all ranks."""
    local = float(np.linalg.norm((a - b).reshape(-1, 3), axis=1).max(initial=0.0))
    return comm.allreduce(local, op=MPI.MAX)


# -- studies ---------------------------------------------------------------------------------------
def forward_study(model, loads: dict, write, study: str) -> None:
    """Every variant on every load; the default first, as the reference equilibrium."""
    comm = model.mesh.comm
    reference = {}
    for variant in sorted(VARIANTS, key=lambda v: v != "default"):
        runner = ForwardRunner(model, variant)
        for load, (family, level, target) in loads.items():
            row = runner.solve(target)
            if variant == "default" and row["converged"]:
                reference[load] = runner.problem.u.x.array.copy()
            if row["converged"] and load in reference:
                row["distance_to_default_mm"] = largest_distance(comm, runner.problem.u.x.array, reference[load])
            write(dict(study=study, tets=tets_of(model), variant=variant, load=load, family=family,
                       level=level, **row))
        del runner


def remote_study(model, args, write) -> None:
    """Single-frame fits of REMOTE_TARGETS from rest (or the opposite guess), every REMOTE_METHOD."""
    from face_dolfinx.model.bones import jaw_pose
    from face_dolfinx.fitting import FaceFitter, FitSettings, MarkerSet
    from face_dolfinx.physics.problem import FaceProblem
    from face_dolfinx.equilibrium.solver import EquilibriumError
    from face_dolfinx.fitting import penalties

    comm = model.mesh.comm
    sites = np.array(list(model.markers.values()))
    pattern = np.random.default_rng(args.seed).uniform(0.0, 1.0, len(model.muscles))
    widest_jaw = np.array([math.asin(model.jaw.max_opening_sine), model.jaw.track_length, model.jaw.track_length])
    truth_problem = FaceProblem(model)
    truth_markers = MarkerSet(truth_problem, sites)
    for number, (name, target) in enumerate(REMOTE_TARGETS.items()):
        activations = (target.scale * pattern if target.activations == "random"
                       else target.scale * load_controls(model, target.activations, 0.0, False).activations)
        tmj = np.array([math.radians(target.opening_deg), 0.0, 0.0])
        head = turned_head(model, target.head_deg)
        # From rest: walking the truth from one target's head pose to the next (90 degrees back
        # to 0) failed once.
        to_rest(truth_problem)
        truth_problem.solve(activations=activations, cranium=head, jaw=jaw_pose(model.jaw, *tmj))
        clean = truth_markers.positions(truth_problem.u.x.array, head)
        noise = np.random.default_rng([args.seed, number]).normal(scale=target.noise / math.sqrt(3.0),
                                                                   size=clean.shape)
        truth_bones = truth_problem.bone_positions(head, jaw_pose(model.jaw, *tmj))
        for method in args.remote_methods:
            settings, petsc_options = REMOTE_METHODS[method]
            problem = FaceProblem(model, petsc_options=petsc_options)
            fitter = FaceFitter(problem, MarkerSet(problem, sites), FitSettings(**settings))
            if target.opposite_start:
                fitter.state.activations = 1.0 - activations
                if fitter.state.mode == "exact":
                    fitter.state.tmj = widest_jaw.copy()
                else:
                    fitter.state.jaw = jaw_pose(model.jaw, *widest_jaw)
                problem.solve(activations=1.0 - activations, jaw=jaw_pose(model.jaw, *widest_jaw))
            began = time.perf_counter()
            row = dict(study="remote", tets=tets_of(model), method=method, target=name,
                       noise=target.noise, head_deg=target.head_deg,
                       truth_marker_rms=float(np.sqrt(np.mean(np.sum(noise**2, axis=1)))))
            try:
                result = fitter.fit_frame(clean + noise)
            except EquilibriumError as error:
                write(dict(row, outcome="failed", failure=str(error), seconds=time.perf_counter() - began))
                continue
            simulated = fitter.markers.positions(problem.u.x.array, result.cranium)
            bones = problem.bone_positions(result.cranium, result.jaw)
            bone_error = np.linalg.norm(bones - truth_bones, axis=1)
            on_cranium = np.arange(len(bones)) < len(problem.cranium_blocks)
            activation_error = np.abs(result.activations - activations)
            row.update(
                marker_rms=result.rms_error,
                clean_rms=float(np.sqrt(np.mean(np.sum((simulated - clean) ** 2, axis=1)))),
                gn_steps=result.gn_steps, max_gn_steps=fitter.settings.first_frame_gn_steps,
                line_search_seconds=result.phases["line_search"],
                activation_rms=float(np.sqrt(np.mean(activation_error**2))),
                activation_max=float(activation_error.max()),
                cranium_error_mm=comm.allreduce(float(bone_error[on_cranium].max(initial=0.0)), op=MPI.MAX),
                jaw_error_mm=comm.allreduce(float(bone_error[~on_cranium].max(initial=0.0)), op=MPI.MAX),
                activation_bound_violation=float(max(0.0, -result.activations.min(),
                                                     result.activations.max() - 1.0)),
                cranium_rigidity=math.sqrt(penalties.rigidity(result.cranium.matrix).value),
                jaw_rigidity=math.sqrt(penalties.rigidity(result.jaw.matrix).value),
                tmj_violation=math.sqrt(penalties.tmj(result.jaw.matrix, result.jaw.translation,
                                                      model.jaw).value),
                flag=result.flag, seconds=result.seconds)
            row["outcome"] = remote_outcome(row)
            write(row)


def remote_outcome(row: dict) -> str:
    """recovered; not identifiable (activations far, markers fitted at least as well as the truth
    fits them: the data cannot tell); wrong minimum (activations far, markers fitted but worse than
    the truth); step limit or stalled (markers not fitted)."""
    if row["marker_rms"] <= max(FITTED_MARKER_RMS, 1.1 * row["noise"]):
        if row["activation_max"] <= RECOVERED_ACTIVATION_ERROR:
            return "recovered"
        return "not identifiable" if row["marker_rms"] <= row["truth_marker_rms"] + 1e-3 else "wrong minimum"
    return "step limit" if row["gn_steps"] >= row["max_gn_steps"] else "stalled"


def head_study(model, write) -> None:
    """The smile with the jaw 15 degrees open and the head turned by HEAD_TURNS: from rest to
    there, a second Newton solve in place (how far the residual of an equilibrium can fall, against
    snes_atol), and back to rest (continuation between remote head poses)."""
    from face_dolfinx.model.bones import AffineMap, jaw_pose
    from face_dolfinx.equilibrium.solver import EquilibriumError

    smile = load_controls(model, "smile", 0.0, False).activations
    jaw = jaw_pose(model.jaw, math.radians(15.0))
    for degrees in HEAD_TURNS:
        runner = ForwardRunner(model, "default")
        problem = runner.problem
        row = dict(study="head", tets=tets_of(model), head_deg=degrees)
        legs = (("there", dict(activations=smile, cranium=turned_head(model, degrees), jaw=jaw)),
                ("back", dict(activations=np.zeros(problem.num_muscles), cranium=AffineMap(), jaw=AffineMap())))
        for leg, controls in legs:
            runner.residuals.clear()
            try:
                report = problem.solve(**controls)
                row[leg] = dict(converged=True, load_steps=report.load_steps, reached=1.0,
                                newton_iterations=report.newton_iterations)
            except EquilibriumError as error:
                row[leg] = dict(converged=False, load_steps=0, failure=str(error),
                                reached=float(re.search(r"beyond ([0-9.]+)", str(error)).group(1)),
                                newton_iterations=sum(1 for its, _ in runner.residuals if its > 0))
            if leg == "there" and row[leg]["converged"]:
                runner.residuals.clear()
                converged, iterations, reason = problem.solver.newton()
                row["in_place"] = dict(converged=converged, newton_iterations=iterations, reason=reason,
                                       first_residual=runner.residuals[0][1],
                                       smallest_residual=min(fnorm for _, fnorm in runner.residuals))
        write(row)


def damaged_takes(clean: np.ndarray, seed: int):
    """(family, level, positions, damaged mask (frames, markers)) for every DAMAGE level; the
    clean take first (family "clean")."""
    frames, markers, _ = clean.shape
    yield "clean", 0.0, clean.copy(), np.zeros((frames, markers), dtype=bool)
    for family, (_, levels) in DAMAGE.items():
        for level in levels:
            rng = np.random.default_rng([seed, list(DAMAGE).index(family), int(1000 * level)])
            positions, damaged = clean.copy(), np.zeros((frames, markers), dtype=bool)
            if family in ("outlier_count", "outlier_size"):
                count, jump = (int(level), OUTLIER_JUMP) if family == "outlier_count" else (1, level)
                chosen = rng.choice(markers, size=count, replace=False)
                directions = rng.normal(size=(count, 3))
                directions /= np.linalg.norm(directions, axis=1, keepdims=True)
                positions[:, chosen] += jump * directions  # a mislabelled marker, the whole take
                damaged[:, chosen] = True
            elif family == "gaps":
                for frame in range(frames):
                    missing = rng.choice(markers, size=int(round(level * markers)), replace=False)
                    positions[frame, missing] = np.nan
                    damaged[frame, missing] = True
            else:
                positions += rng.normal(scale=level / math.sqrt(3.0), size=positions.shape)
                damaged[:] = True
            yield family, level, positions, damaged


def damage_study(model, args, write) -> None:
    from face_dolfinx.fitting import FaceFitter, MarkerSet
    from face_dolfinx.tracking import track
    from face_dolfinx.physics.problem import FaceProblem
    from face_dolfinx.equilibrium.solver import EquilibriumError
    from face_dolfinx.capture.synthetic import synthesize_take

    sites = np.array(list(model.markers.values()))
    truth_problem = FaceProblem(model)
    _, truth = synthesize_take(truth_problem, MarkerSet(truth_problem, sites), model, "speech",
                               n_frames=args.damage_frames, noise=0.0, seed=args.seed)
    del truth_problem
    clean = truth.clean_positions
    for family, level, positions, damaged in damaged_takes(clean, args.seed):
        if family not in args.damage_families:
            continue
        problem = FaceProblem(model)
        markers = MarkerSet(problem, sites)
        fitter = FaceFitter(problem, markers)
        results, simulated, failure = [], [], ""

        def keep(result):
            # on_frame runs right after the frame's fit: the problem holds its equilibrium. The
            # frames done so far are kept even if a later one raises.
            results.append(result)
            simulated.append(markers.positions(problem.u.x.array, result.cranium))

        try:
            track(fitter, positions, on_frame=keep)
        except EquilibriumError as error:
            failure = f"frame {len(simulated)}: {error}"
        done = len(simulated)
        error = np.linalg.norm(np.array(simulated) - clean[:done], axis=2) if done else np.zeros((0, 0))
        undamaged = ~damaged[:done]
        activation_error = np.array([r.activations - truth.activations[r.frame] for r in results])

        def rms(values):
            return float(np.sqrt(np.mean(values**2))) if values.size else math.nan

        write(dict(study="damage", tets=tets_of(model), family=family, level=level,
                   frames=len(clean), frames_done=done, failure=failure,
                   clean_rms=rms(error), clean_rms_undamaged=rms(error[undamaged]),
                   damaged_marker_error=float(error[damaged[:done]].mean()) if damaged[:done].any() else math.nan,
                   clean_max=float(error.max(initial=0.0)),
                   activation_rms=rms(activation_error),
                   activation_max=float(np.abs(activation_error).max(initial=0.0)),
                   opening_error_deg=(float(np.mean([abs(math.degrees(r.jaw_tmj[0] - truth.tmj[r.frame, 0]))
                                                     for r in results])) if results else math.nan),
                   captured_rms=float(np.sqrt(np.nanmean([r.rms_error**2 for r in results]))) if results else math.nan,
                   line_search_seconds=float(sum(r.phases.get("line_search", 0.0) for r in results)),
                   flagged=sum(1 for r in results if r.flag),
                   flags=sorted({r.flag.split(":")[0] for r in results if r.flag}),
                   observability=[r.observability for r in results],
                   unobservable={name: sum(name in r.unobservable for r in results)
                                 for name in sorted({n for r in results for n in r.unobservable})},
                   seconds_per_frame=float(np.mean([r.seconds for r in results])) if results else math.nan))


def run(args) -> None:
    from face_dolfinx.model.anatomy import build_builtin_face
    from face_dolfinx.model.folder import load_model

    comm = MPI.COMM_WORLD
    out = pathlib.Path(args.out)
    if comm.rank == 0:
        out.parent.mkdir(parents=True, exist_ok=True)
    models = {}

    def model_at(tets):
        if tets not in models:
            models[tets] = load_model(build_builtin_face(target_tets=tets, comm=comm), comm)
        return models[tets]

    def write(row):
        row = dict(row, ranks=comm.size)
        if comm.rank == 0:
            with open(out, "a") as handle:
                handle.write(json.dumps(row) + "\n")
            print(summary_line(row), flush=True)

    began = time.perf_counter()
    if "forward" in args.studies:
        for tets in args.tets:
            model = model_at(tets)
            loads = {name: (name, 1.0, load_controls(model, *spec)) for name, spec in FORWARD_LOADS.items()}
            forward_study(model, loads, write, "forward")
    if "ramp" in args.studies:
        for tets in args.ramp_tets:
            model = model_at(tets)
            loads = {f"{family} x{level:g}": (family, level,
                                              load_controls(model, level * muscles, level * opening, False))
                     for family, ((muscles, opening), levels) in RAMPS.items() for level in levels}
            forward_study(model, loads, write, "ramp")
    if "remote" in args.studies:
        remote_study(model_at(args.remote_tets), args, write)
    if "head" in args.studies:
        head_study(model_at(args.remote_tets), write)
    if "damage" in args.studies:
        damage_study(model_at(args.damage_tets), args, write)
    from provenance import record
    record(out, tets=sorted(models), ranks=comm.size)
    if comm.rank == 0:
        print(f"studies {' '.join(args.studies)}: {time.perf_counter() - began:.0f} s", flush=True)


def summary_line(row: dict) -> str:
    if row["study"] in ("forward", "ramp"):
        what = "converged" if row["converged"] else f"FAILED: {row['failure']}"
        return (f"{row['study']} {row['tets']} {row['variant']:>8} {row['load']:>22}: {what}, "
                f"{row['newton_iterations']} its, {row['factorizations']} factorisations, "
                f"min det F {row['min_volume_ratio']:.3f}, {row['seconds']:.1f} s")
    if row["study"] == "remote":
        if row["outcome"] == "failed":
            return f"remote {row['method']:>12} {row['target']:>22}: FAILED {row['failure'][:80]}"
        return (f"remote {row['method']:>12} {row['target']:>22}: {row['outcome']}, markers "
                f"{row['marker_rms']:.3f} mm, activations max {row['activation_max']:.3f}, "
                f"{row['gn_steps']} steps, {row['seconds']:.1f} s")
    if row["study"] == "head":
        return f"head {row['head_deg']:>5g}: " + ", ".join(
            f"{leg} {row[leg]['converged']}" for leg in ("there", "in_place", "back") if leg in row)
    return (f"damage {row['family']:>13} {row['level']:>5g}: clean RMS {row['clean_rms']:.3f} mm "
            f"(undamaged {row['clean_rms_undamaged']:.3f}), activations RMS {row['activation_rms']:.3f}, "
            f"flagged {row['flagged']}/{row['frames']} {row['failure'][:60]}")



# -- tables and charts ----------------------------------------------------------------------------
def load_rows(paths) -> list[dict]:
    rows = []
    for path in paths:
        rows += [json.loads(line) for line in pathlib.Path(path).read_text().splitlines() if line.strip()]
    return rows


def latest(rows, key) -> dict:
    """The last row of each key (a rerun of a study replaces the earlier rows)."""
    return {key(r): r for r in rows}


def forward_cell(r: dict) -> str:
    if r["converged"]:
        steps = f" in {r['load_steps']} load steps" if r["load_steps"] > 1 else ""
        return (f"ok: {r['factorizations']} fact.{steps}, det F {r['min_volume_ratio']:.2f}, "
                f"{r['seconds']:.1f} s")
    where = f" at {r['reached']:.2f} of the load" if r["variant"] == "default" else ""
    return (f"**{r['failure']}**{where} after {r['factorizations']} fact., "
            f"det F {r['min_volume_ratio']:.3g}")


def forward_tables(rows) -> list[str]:
    cells = latest([r for r in rows if r["study"] == "forward"], lambda r: (r["tets"], r["load"], r["variant"]))
    if not cells:
        return []
    lines = ["Forward solves, rest -> load in one call (fact. = factorisations = Newton iterations "
             "incl. failed attempts; det F = smallest cell volume ratio of the final iterate):", "",
             "| tets | load | " + " | ".join(VARIANTS) + " |", "|---|---|" + "---|" * len(VARIANTS)]
    for tets in sorted({k[0] for k in cells}):
        for load in FORWARD_LOADS:
            if (tets, load, "default") in cells:
                entries = [forward_cell(cells[(tets, load, v)]) if (tets, load, v) in cells else ""
                           for v in VARIANTS]
                lines.append(f"| {tets} | {load} | " + " | ".join(entries) + " |")
    lines += ["", "| tets | " + " | ".join(f"{v} failed" for v in VARIANTS) + " |",
              "|---|" + "---|" * len(VARIANTS)]
    for tets in sorted({k[0] for k in cells}):
        counts = []
        for v in VARIANTS:
            mine = [r for k, r in cells.items() if k[0] == tets and k[2] == v]
            counts.append(f"{sum(not r['converged'] for r in mine)} / {len(mine)}")
        lines.append(f"| {tets} | " + " | ".join(counts) + " |")
    return lines


def ramp_tables(rows) -> list[str]:
    cells = latest([r for r in rows if r["study"] == "ramp"], lambda r: (r["tets"], r["family"], r["level"], r["variant"]))
    if not cells:
        return []
    lines = ["Load ramps, each level in one call from rest: the first level that fails (jaw levels "
             "are multiples of the 25 degree opening limit):", "",
             "| tets | family | " + " | ".join(VARIANTS) + " |", "|---|---|" + "---|" * len(VARIANTS)]
    everything = sorted({(k[0], k[1]) for k in cells}, key=lambda k: (k[0], list(RAMPS).index(k[1])))
    for tets, family in everything:
        entries = []
        for v in VARIANTS:
            mine = sorted((r for k, r in cells.items() if k[:2] == (tets, family) and k[3] == v),
                          key=lambda r: r["level"])
            failed = [r for r in mine if not r["converged"]]
            entries.append(f"x{failed[0]['level']:g}: {failed[0]['failure']}" if failed
                           else f"none up to x{mine[-1]['level']:g}")
        lines.append(f"| {tets} | {family} | " + " | ".join(entries) + " |")
    lines += ["", "The default's equilibria: smallest det F (load steps) per level:", ""]
    for family, (_, levels) in RAMPS.items():
        lines += [f"| tets | {family} " + " | ".join(f"x{level:g}" for level in levels) + " |",
                  "|---|" + "---|" * len(levels)]
        for tets in sorted({k[0] for k in cells if k[1] == family}):
            entries = []
            for level in levels:
                r = cells.get((tets, family, level, "default"))
                entries.append("" if r is None else
                               f"{r['min_volume_ratio']:.2f} ({r['load_steps']})" if r["converged"]
                               else f"**{r['failure']}** at {r['reached']:.2f}")
            lines.append(f"| {tets} | " + " | ".join(entries) + " |")
        lines.append("")
    return lines


def plural(count: int, noun: str) -> str:
    return f"{count} {noun}{'' if count == 1 else 's'}"


def remote_cell(r: dict) -> str:
    if r["outcome"] == "failed":
        last = re.search(r"last failure: (\w+)", r["failure"])
        return f"**failed**: no equilibrium ({last.group(1) if last else r['failure'][:40]})"
    # Without the line search the fitter still enters it, to return at once (microseconds).
    searched = ", line search ran" if r["line_search_seconds"] > 1e-3 else ""
    if r["outcome"] == "recovered":
        return f"ok: {plural(r['gn_steps'], 'step')}, {r['seconds']:.0f} s{searched}"
    return (f"**{r['outcome']}**: {plural(r['gn_steps'], 'step')}, markers {r['marker_rms']:.2f} mm, "
            f"act. err {r['activation_max']:.2f}{searched}")


def remote_tables(rows) -> list[str]:
    cells = latest([r for r in rows if r["study"] == "remote"], lambda r: (r["target"], r["method"]))
    if not cells:
        return []
    lines = ["One frame fitted from a remote initial guess (ok = markers within 0.1 mm and every "
             "activation within 0.1 of the truth; markers = RMS against the captured targets; act. err "
             "= largest activation error):", "", "| target | " + " | ".join(REMOTE_METHODS) + " |",
             "|---|" + "---|" * len(REMOTE_METHODS)]
    for target in REMOTE_TARGETS:
        if any((target, m) in cells for m in REMOTE_METHODS):
            lines.append(f"| {target} | " + " | ".join(remote_cell(cells[(target, m)]) if (target, m) in cells
                                                        else "" for m in REMOTE_METHODS) + " |")
    lines += ["", "Constraints at the end of the recovered fits (largest over the targets): "
              "activations outside [0, 1], ||M^T M - I|| of the head and jaw frames, TMJ terms "
              "(psi, mm), bone pose errors against the truth (mm):", "",
              "| method | activation bound | head rigidity | jaw rigidity | TMJ | head pose mm | jaw pose mm |",
              "|---|---|---|---|---|---|---|"]
    for method in REMOTE_METHODS:
        done = [r for (_, m), r in cells.items() if m == method and r["outcome"] == "recovered"]
        if done:
            keys = ("activation_bound_violation", "cranium_rigidity", "jaw_rigidity", "tmj_violation",
                    "cranium_error_mm", "jaw_error_mm")
            lines.append(f"| {method} | " + " | ".join(f"{max(r[k] for r in done):.2g}" for k in keys) + " |")
    return lines


def head_tables(rows) -> list[str]:
    cells = latest([r for r in rows if r["study"] == "head"], lambda r: r["head_deg"])
    if not cells:
        return []

    def leg(r):
        if r["converged"]:
            return f"ok in {plural(r['load_steps'], 'load step')}, {r['newton_iterations']} its"
        return f"**failed** at {r['reached']:.2f} of the way, {r['newton_iterations']} its"

    lines = ["The smile with the jaw 15 degrees open and the head turned (default solver): rest -> "
             "turned, then a second Newton solve in place (residual in mN; snes_atol is 1e-9), then "
             "back to rest:", "",
             "| head turn deg | rest -> turned | in place: first / smallest residual | in place | turned -> rest |",
             "|---|---|---|---|---|"]
    for degrees, r in sorted(cells.items()):
        place = r.get("in_place")
        lines.append(
            f"| {degrees:g} | {leg(r['there'])} | "
            + (f"{place['first_residual']:.2g} / {place['smallest_residual']:.2g} | "
               f"{'ok' if place['converged'] else '**' + place['reason'] + '**'}, {place['newton_iterations']} its"
               if place else " | ")
            + f" | {leg(r['back'])} |")
    return lines


def damage_tables(rows) -> list[str]:
    cells = latest([r for r in rows if r["study"] == "damage"], lambda r: (r["family"], r["level"]))
    if not cells:
        return []
    frames = next(iter(cells.values()))["frames"]
    lines = [f"The {frames}-frame speech take with head motion, damaged in every frame; marker errors "
             "against the clean truth (mm; RMS over frames and markers; the damaged markers: mean "
             "distance), activation errors over frames and muscles:", "",
             "| damage | level | markers RMS | undamaged markers RMS | damaged markers mean | activation "
             "RMS | activation max | jaw opening err deg | flagged frames | named under-determined (frames) "
             "| failure |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for (family, level), r in sorted(cells.items(), key=lambda kv: (["clean", *DAMAGE].index(kv[0][0]), kv[0][1])):
        name = "clean" if family == "clean" else DAMAGE[family][0]

        def number(value, digits):
            return "" if math.isnan(value) else f"{value:.{digits}f}"

        lines.append(f"| {name} | {level:g} | {r['clean_rms']:.3f} | {number(r['clean_rms_undamaged'], 3)} | "
                     f"{number(r['damaged_marker_error'], 2)} | {r['activation_rms']:.3f} | {r['activation_max']:.2f} | "
                     f"{r['opening_error_deg']:.2f} | {r['flagged']} / {r['frames']} | "
                     f"{named_controls(r.get('unobservable', {}))} | {r['failure'][:60]} |")
    return lines


def named_controls(counts: dict, shown: int = 3) -> str:
    """The controls most often named under-determined, with their frame counts."""
    ranked = sorted(counts.items(), key=lambda item: (-item[1], item[0]))
    text = ", ".join(f"{name} {frames}" for name, frames in ranked[:shown])
    return text + (f" (+{len(ranked) - shown} more)" if len(ranked) > shown else "")


def collect(paths) -> str:
    rows = load_rows(paths)
    sections = [forward_tables(rows), ramp_tables(rows), remote_tables(rows), head_tables(rows),
                damage_tables(rows)]
    return "\n\n".join("\n".join(lines) for lines in sections if lines)


OUTCOME_COLOURS = {"converged": "tab:green", "inverted (NaN residual)": "tab:red", "guard stall": "tab:orange",
                   "line search failed": "tab:pink", "iteration limit": "tab:purple"}


def outcome_colour(r: dict) -> str:
    return OUTCOME_COLOURS["converged" if r["converged"] else r["failure"]] if (
        r["converged"] or r["failure"] in OUTCOME_COLOURS) else "tab:gray"


def plot(paths, prefix: str) -> list[pathlib.Path]:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Patch

    rows = load_rows(paths)
    written = []

    def save(figure, name):
        path = pathlib.Path(f"{prefix}_{name}.png")
        path.parent.mkdir(parents=True, exist_ok=True)
        figure.tight_layout()
        figure.savefig(path, dpi=120)
        plt.close(figure)
        written.append(path)

    seen = {outcome_colour(r) for r in rows if r["study"] in ("forward", "ramp")}
    legend = [Patch(color=c, label=k) for k, c in OUTCOME_COLOURS.items() if c in seen]
    forward = latest([r for r in rows if r["study"] == "forward"], lambda r: (r["tets"], r["load"], r["variant"]))
    if forward:
        # Outcome matrix: variant x load, coloured by outcome, labelled with factorisations.
        sizes = sorted({k[0] for k in forward})
        figure, axes = plt.subplots(len(sizes), 1, figsize=(11, 2.3 * len(sizes) + 0.8), squeeze=False)
        for ax, tets in zip(axes[:, 0], sizes):
            for i, variant in enumerate(VARIANTS):
                for j, load in enumerate(FORWARD_LOADS):
                    r = forward.get((tets, load, variant))
                    if r is None:
                        continue
                    ax.add_patch(plt.Rectangle((j, i), 0.95, 0.9, color=outcome_colour(r)))
                    ax.text(j + 0.47, i + 0.45, f"{r['factorizations']}", ha="center", va="center", fontsize=9)
            ax.set_xlim(0, len(FORWARD_LOADS))
            ax.set_ylim(len(VARIANTS), 0)
            ax.set_xticks(np.arange(len(FORWARD_LOADS)) + 0.47, FORWARD_LOADS, fontsize=8)
            ax.set_yticks(np.arange(len(VARIANTS)) + 0.45, list(VARIANTS))
            ax.set_title(f"{tets} tets: rest -> load in one call (number = factorisations)", fontsize=10)
        axes[0, 0].legend(handles=legend, loc="lower left", bbox_to_anchor=(0.0, 1.15), ncol=5, fontsize=8)
        save(figure, "forward")

        # Residual histories of the hardest loads on the smallest face.
        tets = sizes[0]
        figure, axes = plt.subplots(1, 2, figsize=(11, 4), sharey=True)
        for ax, load in zip(axes, ("all_muscles", "jaw_limit")):
            for variant in VARIANTS:
                r = forward.get((tets, load, variant))
                if r is None:
                    continue
                line, = ax.semilogy(r["residuals"], marker=".", label=variant)
                for k in r["residual_restarts"][1:]:
                    ax.axvline(k, color=line.get_color(), linewidth=0.5, alpha=0.5)
                if not r["converged"]:
                    ax.plot(len(r["residuals"]) - 1, r["residuals"][-1], "x", color=line.get_color(), markersize=12)
            ax.set_title(f"{tets} tets, rest -> {load}", fontsize=10)
            ax.set_xlabel("residual evaluations at Newton iterates (thin lines: new load step)")
            ax.grid(True, alpha=0.3)
        axes[0].set_ylabel("residual norm (mN)")
        axes[0].legend(title="x: gave up")
        save(figure, "residuals")

    ramp = latest([r for r in rows if r["study"] == "ramp"], lambda r: (r["tets"], r["family"], r["level"], r["variant"]))
    if ramp:
        sizes = sorted({k[0] for k in ramp})
        figure, axes = plt.subplots(len(RAMPS), len(sizes), figsize=(3.6 * len(sizes), 2.8 * len(RAMPS)),
                                    squeeze=False, sharey=True)
        for row, (family, (_, levels)) in enumerate(RAMPS.items()):
            for col, tets in enumerate(sizes):
                ax = axes[row, col]
                for offset, variant in enumerate(VARIANTS):
                    mine = [ramp[(tets, family, level, variant)] for level in levels
                            if (tets, family, level, variant) in ramp]
                    x = np.array([r["level"] for r in mine]) * (1 + 0.02 * (offset - 1.5))
                    y = np.clip([r["min_volume_ratio"] for r in mine], -1.0, 1.0)
                    ax.plot(x, y, color="0.8", zorder=1)
                    ax.scatter(x, y, c=[outcome_colour(r) for r in mine], marker="osD^"[offset], zorder=2,
                               edgecolors="k", linewidths=0.4, label=variant)
                ax.axhline(0.0, color="k", linewidth=0.6)
                ax.set_xscale("log")
                ax.set_xticks(levels, [f"{level:g}" for level in levels], fontsize=7)
                ax.minorticks_off()
                ax.set_title(f"{tets} tets: {family}", fontsize=9)
                if col == 0:
                    ax.set_ylabel("smallest det F (clipped at -1)")
                if row == len(RAMPS) - 1:
                    ax.set_xlabel("load level (activation; jaw: x opening limit)")
        shapes = [plt.Line2D([], [], marker="osD^"[k], color="w", markeredgecolor="k", label=v)
                  for k, v in enumerate(VARIANTS)]
        axes[0, 0].legend(handles=shapes + legend, fontsize=6, loc="lower left")
        save(figure, "ramp")

    remote = latest([r for r in rows if r["study"] == "remote"], lambda r: (r["target"], r["method"]))
    if remote:
        targets = [t for t in REMOTE_TARGETS if any((t, m) in remote for m in REMOTE_METHODS)]
        figure, axes = plt.subplots(1, 2, figsize=(12, 4.8), sharey=True)
        width = 0.8 / len(REMOTE_METHODS)
        for k, method in enumerate(REMOTE_METHODS):
            y = np.arange(len(targets)) + (k - (len(REMOTE_METHODS) - 1) / 2) * width
            for ax, key, floor in ((axes[0], "clean_rms", 1e-6), (axes[1], "activation_max", 1e-6)):
                values = [max(remote[(t, method)].get(key, math.nan), floor) if (t, method) in remote else math.nan
                          for t in targets]
                failed = [(t, method) in remote and remote[(t, method)]["outcome"] == "failed" for t in targets]
                bars = ax.barh(y, values, height=width, label=method)
                for yy, bad in zip(y, failed):
                    if bad:
                        ax.plot(floor * 2, yy, "X", color=bars.patches[0].get_facecolor(), markersize=9,
                                markeredgecolor="k")
        for ax, title in zip(axes, ("marker RMS against the clean truth (mm)", "largest activation error")):
            ax.set_xscale("log")
            ax.set_xlabel(title + ", log; X = failed")
            ax.grid(True, axis="x", alpha=0.3)
        axes[1].axvline(RECOVERED_ACTIVATION_ERROR, color="k", linestyle="--", linewidth=0.8)
        axes[0].set_yticks(np.arange(len(targets)), targets, fontsize=8)
        axes[0].invert_yaxis()
        axes[1].legend(fontsize=8)
        save(figure, "remote")

    damage = latest([r for r in rows if r["study"] == "damage"], lambda r: (r["family"], r["level"]))
    if damage:
        figure, axes = plt.subplots(2, len(DAMAGE), figsize=(3.4 * len(DAMAGE), 5.5), squeeze=False)
        clean = damage.get(("clean", 0.0))
        for col, (family, (label, levels)) in enumerate(DAMAGE.items()):
            mine = [damage[(family, level)] for level in levels if (family, level) in damage]
            x = [r["level"] for r in mine]
            top, bottom = axes[0, col], axes[1, col]
            top.plot(x, [r["clean_rms"] for r in mine], "o-", label="all markers")
            top.plot(x, [r["clean_rms_undamaged"] for r in mine], "s--", label="undamaged markers")
            bottom.plot(x, [r["activation_rms"] for r in mine], "o-", color="tab:red", label="RMS")
            bottom.plot(x, [r["activation_max"] for r in mine], "^:", color="tab:red", label="max")
            for r in mine:
                if r["flagged"]:  # how many frames, and why: "under-determined", "targets not reachable"
                    why = ", ".join(r.get("flags", []))
                    top.annotate(f"{r['flagged']} flagged\n{why}", (r["level"], r["clean_rms"]), fontsize=6,
                                 textcoords="offset points", xytext=(-60, 4))
            if clean is not None:
                top.axhline(clean["clean_rms"], color="0.5", linewidth=0.8, label="clean take")
                bottom.axhline(clean["activation_rms"], color="0.5", linewidth=0.8)
            for ax in (top, bottom):
                ax.set_xscale("log")
                ax.set_xticks(levels, [f"{level:g}" for level in levels], fontsize=7)
                ax.minorticks_off()
                ax.grid(True, alpha=0.3)
            bottom.set_xlabel(label, fontsize=8)
            if col == 0:
                top.set_ylabel("marker error vs clean (mm)")
                bottom.set_ylabel("activation error")
                top.legend(fontsize=7)
                bottom.legend(fontsize=7)
        save(figure, "damage")
    return written


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--studies", nargs="+", default=list(STUDIES), choices=list(STUDIES))
    parser.add_argument("--tets", type=int, nargs="+", default=[5000, 20000], help="faces of the forward study")
    parser.add_argument("--ramp-tets", type=int, nargs="+", default=[1000, 2000, 5000, 20000],
                        help="faces of the ramp study")
    parser.add_argument("--remote-tets", type=int, default=5000, help="face of the remote-guess fits")
    parser.add_argument("--remote-methods", nargs="+", default=list(REMOTE_METHODS), choices=list(REMOTE_METHODS))
    parser.add_argument("--damage-tets", type=int, default=5000, help="face of the damaged takes")
    parser.add_argument("--damage-frames", type=int, default=8, help="frames of the damaged take")
    parser.add_argument("--damage-families", nargs="+", default=["clean", *DAMAGE], choices=["clean", *DAMAGE],
                        help="damage study: only these takes (each level's damage is the same either way)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default="runs/stability.jsonl", help="JSON lines, appended")
    parser.add_argument("--collect", nargs="+", metavar="JSONL", help="only print tables from these files")
    parser.add_argument("--plot", metavar="PREFIX", help="with --collect: write PREFIX_<study>.png")
    args = parser.parse_args()
    if args.collect:
        print(collect(args.collect))
        if args.plot:
            for path in plot(args.collect, args.plot):
                print(f"wrote {path}")
        return
    run(args)


if __name__ == "__main__":
    main()
