"""What lip and teeth contact cost in a warm-started tracking frame: the same frames tracked with
contact off and on in one run (docs/performance.md, "Contact in tracking").

A bilabial take ("ma ba pa", ``capture/synthetic.py``: the orbicularis oris at 0.9 presses the
lips together with the jaw closed, then an open vowel) of ``--take-frames`` frames at 60 Hz is
solved with contact (``--truth-contact``: by default the lips on each other and the lining on the
teeth, as ``fit --contact`` models the face; ``lips``: the lips only) at the model's marker sites,
with 0.5 mm noise and no head motion (``--head-motion``: as in a capture); the stretch of
``--frames`` frames from ``--start`` (by default the lips closing) is tracked by
``face_dolfinx.tracking.Tracker`` (the loop of ``run.py fit``, every frame written to a fit folder
under ``--out``) with ``fit --fast`` (``PRESETS["fast"]``), first without contact, then with the
lips' barrier and the teeth (``TrackingSettings(contact=True)``, what ``fit --contact`` builds),
each variant on a problem of its own (with ``--interleave`` frame by frame in turn, every variant's
problem built at once: a ratio of two variants' frames is then measured on the same stretch of the
machine's time, whose speed varied by half from run to run); a contact variant may switch off, by
a "+" in its name, what ``ABLATIONS`` lists.

One JSON line per frame as it is done (rank 0): seconds of the fit, Newton iterations (every
Newton solve of the frame, the teeth's push-out included), Gauss-Newton steps, factorisations,
residual evaluations, Newton corrections refused for climbing the energy (each solved again on a
fresh factor), seconds and calls inside the contact terms (energy, gradient, Hessian,
collision-free step and the pull-back of a Gauss-Newton prediction, timed by wrapping them; the
largest over the ranks), lip barrier pairs and teeth contact nodes at the fitted equilibrium, the
lips' smallest distance and penetration (also without contact: how far they pass), marker RMS and
activation error. Then one summary line: per variant the means over the warm frames (every frame
but the first, which starts from rest) and, per warm frame both variants fitted, the time ratio
contact on / off, against the target of at most 1.5, also per kind of contact at the fitted
equilibrium (``contact_state``: the lips pressed, the lining on the teeth only, nothing): over a
whole take (``--start 0 --frames 60``) what each costs.

It cannot run for ever: no variant starts a frame once it has tracked for ``--max-seconds``, and
the whole run stops (summary line with what it has, then MPI abort) after ``--abort-seconds``.

    python benchmarks/provenance.py run --out benchmarks/results/contact/tracking_5k_np1.jsonl --json-lines -- \\
        python benchmarks/contact_tracking.py --tets 5000
    python benchmarks/provenance.py run --out benchmarks/results/contact/tracking_404k_np2.jsonl --json-lines -- \\
        mpirun -n 2 python benchmarks/contact_tracking.py --tets 400000 --frames 4 --max-seconds 1800
"""
import argparse
from dataclasses import replace
import json
import logging
import pathlib
import sys
import threading
import time

from mpi4py import MPI
from petsc4py import PETSc
import numpy as np

TARGET_RATIO = 1.5  # docs/performance.md: a warm frame with contact at most 1.5 times one without
# What a contact variant may change to measure it (docs/contact.md, "Newton with pressed lips"),
# appended to its name with "+": the lips' exact Hessian in Newton's tangent throughout, the
# factor refreshed after every iteration that cuts the residual less than ``refresh_contraction``
# however short the collision-free bound made its step, and Newton corrections that climb the
# energy taken (``QuasistaticSolver.refuse_ascent`` off), Newton stopped by the step tolerance
# alone (``--newton-energy-tolerance`` off; the result files recorded before the preset had it), and
# the contact nodes relaxed after each correction (``--contact-relaxation``, which the preset has not),
# and a Gauss-Newton prediction bounded against the teeth standing still at the last equilibrium's
# poses instead of moving with their bones (``ContactPotential.relative_fraction``), and a prediction
# that takes lining nodes into the teeth cut short instead of those nodes moved out of the teeth
# (``ContactPotential.projected_end``), and a prediction cut short with the head's rigid motion in
# it instead of from the equilibrium carried with the head (``FaceProblem.carry_head``), and the
# factor refreshed by the residual norm's contraction alone, not kept where the residual's energy norm
# contracts (``QuasistaticSolver.judge_factor_by_energy`` off), and the factor refreshed only after an
# iteration that cuts the residual less than ``--slow-refresh-contraction`` (against what a step of its
# bounded length achieves), and the lips' barrier of ``--stiff-lips`` kPa instead of the
# ``LipContactSettings`` default (the truth keeps the default), and the tangent's pattern holding every pair
# of lip nodes within WIDE_PATTERN_RADIUS of each other at rest, of one lip or both, instead of
# ``LipContact.coupled_blocks``'s, and Newton's tangent without the lips' barrier of wider reach
# (``LipContactSettings.newton_reach`` 0), and a Gauss-Newton prediction cut short as a whole
# where it flattens a few cells, not around them only (``FaceProblem.bound_prediction_locally``), and
# the factor kept by the residual's energy norm after a correction the collision-free bound cut
# however short (``FactorReusePolicy.judged_step_bound`` 0), and a Gauss-Newton step's fresh Jacobian
# from a factor of the exact tangent instead of Newton's (``FitSettings.fresh_jacobian_from_newton_tangent``), and
# Newton's tangent with the flesh's exact stiffness in every cell (``FaceProblem(definite_tangent=False)``), and
# an old factor kept however long its bounded corrections crawl (``FactorReusePolicy.crawl_refresh_iterations``
# None), and the relaxation started on a slow fall by the teeth's nodes' share of the residual alone, not the
# lips' too (``LipContact.relax_on_slow_fall`` off), and the lips' barrier of wider reach in Newton's tangent
# on pairs that have parted too (``LipContact.reach_on_parting_pairs``).
ABLATIONS = ("exact-lips", "contraction-refresh", "ascents", "step-stop-only", "relaxation", "static-teeth",
             "cut-lining", "cut-head", "residual-refresh", "slow-refresh", "stiff-lips", "wide-pattern",
             "narrow-newton-lips", "cut-whole", "judged-cuts", "exact-fresh-jacobians", "exact-flesh",
             "crawl-kept", "teeth-slow-fall", "parting-reach")
VARIANTS = ("no-contact", "contact", "contact-krylov", "contact+exact-lips", "contact+contraction-refresh",
            "contact+exact-lips+contraction-refresh", "contact+ascents", "contact+step-stop-only",
            "contact+relaxation", "contact+static-teeth", "contact+cut-lining", "contact+cut-head",
            "contact+residual-refresh", "contact+slow-refresh", "contact+stiff-lips", "contact+wide-pattern",
            "contact+narrow-newton-lips", "contact+cut-whole", "contact+judged-cuts", "contact+exact-fresh-jacobians", "contact+exact-flesh",
            "contact+no-crawl-relaxation", "contact+crawl-kept", "contact+teeth-slow-fall", "contact+parting-reach",
            "contact+teeth-slow-fall+parting-reach")
WIDE_PATTERN_RADIUS = 15.0  # mm
TIMED_TERMS = ("energy", "add_gradient", "add_hessian", "step_fraction", "admissible_fraction")
# QuasistaticSolver's counters, per frame
COUNTERS = ("factorizations", "residual_evaluations", "linear_iterations", "energy_stops", "refused_exact_tangents")


class TimedTerm:
    """A contact term's methods (those of ``TIMED_TERMS`` it has), timed: seconds and calls. A call
    made from inside another timed call (the step bound's ``admissible_fraction``) counts in that
    one only, so that the seconds add up."""

    def __init__(self, term):
        self.names = [name for name in TIMED_TERMS if hasattr(term, name)]
        self.seconds = dict.fromkeys(self.names, 0.0)
        self.calls = dict.fromkeys(self.names, 0)
        self._inside = False
        for name in self.names:
            setattr(term, name, self._wrap(name, getattr(term, name)))

    def _wrap(self, name, method):
        def timed(*args, **kwargs):
            if self._inside:
                return method(*args, **kwargs)
            began, self._inside = time.perf_counter(), True
            try:
                return method(*args, **kwargs)
            finally:
                self._inside = False
                self.seconds[name] += time.perf_counter() - began
                self.calls[name] += 1
        return timed


class NewtonCount:
    """Newton iterations of every ``solver.newton()`` (continuation steps and push-outs included);
    with ``check_starts``, also the solves whose start has no finite residual (one more residual
    assembly per solve)."""

    def __init__(self, solver, check_starts: bool = False):
        self.iterations = self.nonfinite_starts = 0
        newton = solver.newton

        def counted(**options):
            if check_starts and not np.isfinite(solver.residual_norm()):
                self.nonfinite_starts += 1
            result = newton(**options)
            self.iterations += result[1]
            return result
        solver.newton = counted


class RelaxationCount:
    """Seconds in the solver's relaxation of the contact nodes (``ContactRelaxation``; 0 without
    it) and its local Newton steps; the contact terms' seconds inside it count in theirs too."""

    def __init__(self, relaxation):
        self.relaxation, self.seconds = relaxation, 0.0
        if relaxation is None:
            return
        relax = relaxation.relax

        def timed(*args, **options):
            began = time.perf_counter()
            try:
                relax(*args, **options)
            finally:
                self.seconds += time.perf_counter() - began
        relaxation.relax = timed

    @property
    def local_iterations(self) -> int:
        return 0 if self.relaxation is None else self.relaxation.local_iterations


class OutOfTime(Exception):
    """A variant's ``--max-seconds`` are used up: no frame is started after the one just done."""


class Turns:
    """Whose turn it is among the variants' threads (``--interleave``): one runs at a time (MPI
    and PETSc see one thread at work, as in a sequential run), each for one frame, in the order of
    ``--variants``; a variant that is done leaves the round. ``busy`` is each variant's seconds
    with the turn (``used``: its own wall clock for ``--max-seconds``)."""

    def __init__(self, names):
        self.order = list(names)
        self.current = self.order[0]
        self.busy = dict.fromkeys(names, 0.0)
        self._since = time.perf_counter()
        self._condition = threading.Condition()

    def used(self, name) -> float:
        """Seconds ``name``, whose turn it is, has had the turn so far."""
        return self.busy[name] + time.perf_counter() - self._since

    def wait(self, name) -> None:
        with self._condition:
            self._condition.wait_for(lambda: self.current == name)
            self._since = time.perf_counter()

    def _hand_on(self, name, leaving: bool) -> None:
        with self._condition:
            self.busy[name] = self.used(name)
            index = self.order.index(name)
            following = self.order[index + 1:] + self.order[:index + (0 if leaving else 1)]
            if leaving:
                self.order.remove(name)
            self.current = following[0] if following else None
            self._condition.notify_all()

    def pass_on(self, name) -> None:
        """After a frame: the next variant's turn, then this one's again."""
        self._hand_on(name, leaving=False)
        self.wait(name)

    def leave(self, name) -> None:
        self._hand_on(name, leaving=True)


def track_variant(name, model, capture, placement, truth, args, comm, began, rows: list,
                  turns: Turns | None = None) -> None:
    """Track the stretch with contact off (``no-contact``) or on (``contact``), appending a row per
    frame to ``rows`` as it is done; with ``turns``, one frame at a time in turn with the other
    variants."""
    from face_dolfinx.physics.self_contact import LipContact, LipContactSettings, lip_facets
    from face_dolfinx.tracking import PRESETS, Tracker

    base, *ablations = name.split("+")
    contact = base != "no-contact"
    settings = PRESETS["fast"].updated(dict(contact=contact, krylov=base == "contact-krylov" or None,
                                            newton_energy_tolerance=args.newton_energy_tolerance,
                                            refresh_contraction=args.refresh_contraction if contact else None,
                                            contact_relaxation=(True if "relaxation" in ablations else
                                                                False if "no-crawl-relaxation" in ablations else None)))
    if "exact-fresh-jacobians" in ablations:
        settings = replace(settings, fit=replace(settings.fit, fresh_jacobian_from_newton_tangent=False))
    lip_settings = LipContactSettings(where="--contact",
                                      stiffness=args.stiff_lips if "stiff-lips" in ablations else LipContactSettings.stiffness,
                                      newton_reach=0.0 if "narrow-newton-lips" in ablations else LipContactSettings.newton_reach)
    tracker = Tracker(model, settings, problem_options=dict(
        lip_contact=lip_settings, definite_tangent=False if "exact-flesh" in ablations else None) if contact else None)
    if "wide-pattern" in ablations:
        from lip_pattern import every_lip_pair_in_pattern
        with every_lip_pair_in_pattern(WIDE_PATTERN_RADIUS):
            problem = tracker.problem
    else:
        problem = tracker.problem
    if "exact-lips" in ablations:
        problem.lips.add_newton_correction = lambda x, A, constrained: False
    if "ascents" in ablations:
        problem.solver.refuse_ascent = False
    if "static-teeth" in ablations:
        teeth = problem.teeth_contact
        relative = teeth.relative_fraction
        teeth.relative_fraction = lambda start, end, end_poses: relative(start, end, teeth.poses)
    if "cut-head" in ablations:
        problem.carry_head = False
    if "cut-whole" in ablations:
        problem.bound_prediction_locally = False
    if "cut-lining" in ablations:
        problem.teeth_contact.projected_end = lambda start, end, end_poses, limit: None
    if "residual-refresh" in ablations:
        problem.solver.judge_factor_by_energy = False
    if "judged-cuts" in ablations:
        problem.solver.reuse_policy.judged_step_bound = 0.0
    if "crawl-kept" in ablations:
        problem.solver.reuse_policy.crawl_refresh_iterations = None
    if "teeth-slow-fall" in ablations:
        problem.lips.relax_on_slow_fall = False
    if "parting-reach" in ablations:
        problem.lips.reach_on_parting_pairs = True
    if "slow-refresh" in ablations:
        problem.solver.reuse_policy.refresh_contraction = args.slow_refresh_contraction
    if "step-stop-only" in ablations:
        problem.solver.energy_tolerance = None
    if "contraction-refresh" in ablations:
        policy = problem.solver.reuse_policy
        record = policy.record_correction
        policy.record_correction = lambda size, cut=False, bound=1.0: record(size, cut)
    # Without contact the lips are only measured (how far they pass), by a LipContact of their own.
    lips = problem.lips or LipContact(problem.V, *lip_facets(model, LipContactSettings()), LipContactSettings(),
                                      problem.bone_blocks)
    timers = {label: TimedTerm(term) for label, term in (("lips", problem.lips), ("teeth", problem.teeth_contact))
              if term is not None}
    newton = NewtonCount(problem.solver)
    relaxation = RelaxationCount(problem.solver.relaxation)
    last = dict(newton=0, allocations=0, **{c: 0 for c in COUNTERS}, relaxation=(0.0, 0),
                **{f"{label}.{term}": (0.0, 0) for label, t in timers.items() for term in t.names})
    start = time.perf_counter()

    def report(result):
        u = problem.u.x.array
        row = dict(variant=name, frame=args.start + result.frame, warm=bool(rows), seconds=round(result.seconds, 2),
                   gn_steps=result.gn_steps, newton_iterations=newton.iterations - last["newton"])
        last["newton"] = newton.iterations
        # Entries the contact added outside the tangent's pattern (each a reallocation).
        allocations = int(problem.solver.tangent.getInfo(PETSc.Mat.InfoType.GLOBAL_SUM)["mallocs"])
        row["tangent_allocations"], last["allocations"] = allocations - last["allocations"], allocations
        for counter in COUNTERS:
            value = getattr(problem.solver, counter)
            row[counter], last[counter] = value - last[counter], value
        seconds, steps = relaxation.seconds, relaxation.local_iterations
        row.update(relaxation_seconds=round(comm.allreduce(seconds - last["relaxation"][0], op=MPI.MAX), 2),
                   relaxation_steps=steps - last["relaxation"][1])
        last["relaxation"] = (seconds, steps)
        by_term, calls = {}, {}
        for label, timer in timers.items():
            for term in timer.names:
                key = f"{label}.{term}"
                seconds, count = timer.seconds[term], timer.calls[term]
                by_term[key] = round(comm.allreduce(seconds - last[key][0], op=MPI.MAX), 3)
                calls[key] = count - last[key][1]
                last[key] = (seconds, count)
        row.update(contact_seconds=round(sum(by_term.values()), 2),
                   **{f"{label}_seconds": round(sum(v for k, v in by_term.items() if k.startswith(label + ".")), 2)
                      for label in ("lips", "teeth")},
                   contact_share=round(sum(by_term.values()) / max(result.seconds, 1e-9), 3),
                   contact_seconds_by_term=by_term, contact_calls=calls,
                   lip_pairs=problem.lips.pairs(u) if problem.lips is not None else None,
                   teeth_contact_nodes=(problem.teeth_contact.contact_nodes(u)
                                        if problem.teeth_contact is not None else None),
                   lip_distance_mm=round(lips.min_distance(u), 5), lip_penetration_mm=round(lips.penetration(u), 3),
                   rms_mm=round(result.rms_error, 3),
                   activation_error=round(float(np.abs(result.activations - truth.activations[result.frame]).max()), 3),
                   elapsed_s=round(time.perf_counter() - began, 1))
        rows.append(row)
        if comm.rank == 0:
            print(json.dumps(row), flush=True)
            if args.verbose and turns is not None:  # which variant the log's lines above were
                print(f"{name}: frame {row['frame']} done", file=sys.stderr, flush=True)
        used = time.perf_counter() - start if turns is None else turns.used(name)
        if comm.allreduce(used, op=MPI.MAX) > args.max_seconds:
            raise OutOfTime
        if turns is not None:
            turns.pass_on(name)

    try:
        tracker.track(capture, placement, pathlib.Path(args.out) / name, overwrite=True, on_frame=report,
                      progress=False)
    except OutOfTime:
        if comm.rank == 0:
            print(json.dumps(dict(variant=name, stopped=f"--max-seconds {args.max_seconds:g} used up after "
                                  f"{len(rows)} of {args.frames} frames")), flush=True)


def contact_state(row: dict) -> str:
    """What touches in a frame with contact on: "lips" (barrier pairs between the lips, the teeth
    maybe too), "teeth" (the lining on the teeth only) or "none"."""
    if row["lip_pairs"]:
        return "lips"
    return "teeth" if row["teeth_contact_nodes"] else "none"


def summary(rows: dict, args, comm, model, setup_seconds: float, aborted: bool = False) -> dict:
    variants = []
    for name, frames in rows.items():
        warm = [r for r in frames if r["warm"]]
        mean = (lambda key: round(float(np.mean([r[key] for r in warm])), 3)) if warm else (lambda key: None)
        variants.append(dict(
            variant=name, frames=len(frames), warm_frames=len(warm),
            first_frame_s=frames[0]["seconds"] if frames else None,
            **{f"warm_mean_{key}": mean(key) for key in ("seconds", "newton_iterations", "gn_steps",
                                                           "factorizations", "residual_evaluations",
                                                           "linear_iterations", "contact_seconds", "lips_seconds", "teeth_seconds",
                                                           "relaxation_seconds", "relaxation_steps", "rms_mm")},
            warm_max_activation_error=max((r["activation_error"] for r in warm), default=None),
            warm_mean_lip_pairs=mean("lip_pairs") if warm and warm[0]["lip_pairs"] is not None else None,
            warm_mean_teeth_contact_nodes=(mean("teeth_contact_nodes")
                                           if warm and warm[0]["teeth_contact_nodes"] is not None else None),
            max_lip_penetration_mm=max((r["lip_penetration_mm"] for r in frames), default=None)))
    off = {r["frame"]: r for r in rows.get("no-contact", []) if r["warm"]}
    ratios, mean_ratios, by_contact = {}, {}, {}
    for name in rows:
        if name == "no-contact":
            continue
        on = {r["frame"]: r for r in rows[name] if r["warm"]}
        both = sorted(frame for frame in off if frame in on)
        ratios[name] = {frame: round(on[frame]["seconds"] / off[frame]["seconds"], 2) for frame in both}
        mean_ratios[name] = (round(sum(on[f]["seconds"] for f in both) / sum(off[f]["seconds"] for f in both), 2)
                             if both else None)
        # The frames by what touches at the fitted equilibrium: what each kind of contact costs.
        groups = {}
        for frame in both:
            groups.setdefault(contact_state(on[frame]), []).append(frame)
        by_contact[name] = {state: dict(
            frames=len(frames),
            ratio=round(sum(on[f]["seconds"] for f in frames) / sum(off[f]["seconds"] for f in frames), 2),
            within_target=sum(ratios[name][f] <= TARGET_RATIO for f in frames),
            mean_factorizations=round(float(np.mean([on[f]["factorizations"] for f in frames])), 2),
            mean_factorizations_without=round(float(np.mean([off[f]["factorizations"] for f in frames])), 2))
            for state, frames in groups.items()}
    return dict(summary=dict(
        tets=model.mesh.topology.index_map(3).size_global, ranks=comm.size,
        truth_tets=args.truth_tets or args.tets, take_frames=args.take_frames,
        first_frame=args.start, frames=args.frames, max_seconds=args.max_seconds, aborted=aborted,
        setup_seconds=round(setup_seconds, 1), variants=variants, warm_ratio_by_frame=ratios,
        warm_ratio=mean_ratios, warm_ratio_by_contact=by_contact, target_ratio=TARGET_RATIO,
        within_target={name: None if ratio is None else ratio <= TARGET_RATIO for name, ratio in mean_ratios.items()}))


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--tets", type=int, default=5000)
    parser.add_argument("--frames", type=int, default=6, help="frames tracked (the first starts from rest)")
    parser.add_argument("--take-frames", type=int, default=60,
                        help="length of the bilabial take at 60 Hz: 60 frames put a closure into about 12")
    parser.add_argument("--start", type=int, default=5, help="first tracked frame of the take (5: the lips closing)")
    parser.add_argument("--noise", type=float, default=0.5, help="marker noise, RMS of the 3D error (mm)")
    parser.add_argument("--head-motion", action="store_true",
                        help="the take's head moves as in a capture (default: still, as the result files before it)")
    parser.add_argument("--truth-contact", choices=("lips", "lips+teeth"),
                        help="what touches in the truth's solves (default: as fit --contact, lips+teeth)")
    parser.add_argument("--max-seconds", type=float, default=1800.0,
                        help="a variant starts no frame after tracking this long")
    parser.add_argument("--abort-seconds", type=float,
                        help="the whole run stops after this long (default: set-up + 3 x --max-seconds)")
    parser.add_argument("--variants", nargs="+", default=["no-contact", "contact"], choices=VARIANTS,
                        help="what is tracked, in this order (contact-krylov: with contact and fit --krylov)")
    parser.add_argument("--truth-tets", type=int,
                        help="solve the take's truth on a face of this many tets (default --tets): at 404K "
                             "the truth's own solves would take longer than the tracking")
    parser.add_argument("--newton-energy-tolerance", type=float, metavar="MJ",
                        help="fit --newton-energy-tolerance of the contact variants (mN mm; default: the preset's)")
    parser.add_argument("--refresh-contraction", type=float, metavar="RATIO",
                        help="fit --refresh-contraction of the contact variants (default: the preset's)")
    parser.add_argument("--slow-refresh-contraction", type=float, default=0.75, metavar="RATIO",
                        help="refresh contraction of the variant contact+slow-refresh")
    parser.add_argument("--stiff-lips", type=float, default=100.0, metavar="KPA",
                        help="the lips' barrier stiffness of the variant contact+stiff-lips")
    parser.add_argument("--interleave", action="store_true",
                        help="track the variants frame by frame in turn (every variant's problem built, one "
                             "thread each, one at work at a time) instead of one after the other: the machine's "
                             "slow and fast stretches then fall on all variants alike")
    parser.add_argument("--out", default="runs/contact_tracking", help="folder for the variants' fit folders")
    parser.add_argument("-v", "--verbose", action="store_true",
                        help="log every Newton solve, Gauss-Newton step and pulled-back prediction to standard "
                             "error (rank 0)")
    parser.add_argument("--trace-newton", action="store_true",
                        help="with -v, also every Newton iteration: residual, correction, bound, factor fresh or old")
    args = parser.parse_args()
    if not 0 <= args.start < args.start + args.frames <= args.take_frames:
        raise SystemExit(f"--start {args.start} + --frames {args.frames} must lie within --take-frames "
                         f"{args.take_frames}")
    if not args.max_seconds > 0 or (args.abort_seconds is not None and not args.abort_seconds > 0):
        raise SystemExit("--max-seconds and --abort-seconds: give positive seconds")

    from face_dolfinx.alignment.placement import place_on_model
    from face_dolfinx.capture.synthetic import synthesize_take, truth_contact_options
    from face_dolfinx.fitting import MarkerSet
    from face_dolfinx.model.anatomy import build_builtin_face
    from face_dolfinx.model.folder import load_model
    from face_dolfinx.physics.problem import FaceProblem

    comm = MPI.COMM_WORLD
    if args.verbose and comm.rank == 0:
        logging.basicConfig(format="%(asctime)s %(name)s: %(message)s", force=True)
        logging.getLogger("face_dolfinx").setLevel(logging.DEBUG)
        if args.trace_newton:
            logging.getLogger("face_dolfinx.equilibrium.solver.iterations").setLevel(logging.DEBUG)
    began = time.perf_counter()
    model = load_model(build_builtin_face(args.tets, comm=comm), comm)
    truth_model = (model if args.truth_tets in (None, args.tets)
                   else load_model(build_builtin_face(args.truth_tets, comm=comm), comm))
    names = list(truth_model.markers)
    sites = np.array([truth_model.markers[name] for name in names])
    truth_problem = FaceProblem(truth_model, **truth_contact_options(truth_model, args.truth_contact,
                                                                     where="--truth-contact"))
    frames = range(args.start, args.start + args.frames)

    def progress(index):
        if comm.rank == 0:
            print(json.dumps(dict(truth_frame=args.start + index, elapsed_s=round(time.perf_counter() - began, 1))),
                  flush=True)
    capture, truth = synthesize_take(truth_problem, MarkerSet(truth_problem, sites, names=names), truth_model, "bilabial",
                                     n_frames=args.take_frames, noise=args.noise, head_motion=args.head_motion, frames=frames,
                                     progress=progress)
    del truth_problem, truth_model
    placement = place_on_model(model, capture)
    setup_seconds = time.perf_counter() - began

    rows = {}
    if comm.rank == 0:
        # A frame may run for ever (a Newton crawl): past the limit, report what is done and stop.
        limit = args.abort_seconds if args.abort_seconds is not None else setup_seconds + 3 * args.max_seconds

        def abort():
            print(json.dumps(summary(rows, args, comm, model, setup_seconds, aborted=True)), flush=True)
            comm.Abort(2)
        watchdog = threading.Timer(max(limit - (time.perf_counter() - began), 0.0), abort)
        watchdog.daemon = True
        watchdog.start()
    if args.interleave:
        turns, failures = Turns(args.variants), []

        def run(name):
            turns.wait(name)
            try:
                track_variant(name, model, capture, placement, truth, args, comm, began, rows[name], turns)
            except BaseException as error:  # re-raised below, once every variant is done
                failures.append(error)
            finally:
                turns.leave(name)
        threads = [threading.Thread(target=run, args=(name,)) for name in args.variants]
        for name, thread in zip(args.variants, threads):
            rows[name] = []
            thread.start()
        for thread in threads:
            thread.join()
        if failures:
            raise failures[0]
    else:
        for name in args.variants:
            rows[name] = []
            track_variant(name, model, capture, placement, truth, args, comm, began, rows[name])
    if comm.rank == 0:
        watchdog.cancel()
        print(json.dumps(summary(rows, args, comm, model, setup_seconds)), flush=True)


if __name__ == "__main__":
    main()
