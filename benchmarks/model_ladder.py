"""The model ladder (issue 5): the same synthetic takes fitted by models from cheap to faithful.

Rungs:
  choe-ko           Choe & Ko 2001 actuation basis from the FE model (muscle fully on, TMJ
                    limits), upper/lower regions, head solved jointly (``baselines.py``)
  choe-ko-kabsch    the same basis, head removed first by a rigid fit to every marker
  choe-ko-refined   the basis after the section 4.2 refinement on a training take
  linearized        the FE model's marker Jacobian at rest as a fixed linear model
  fe                the nonlinear FE fitter (exact mode, default FitSettings) at each --tets
  fe-<variant>      solver settings traded for time (--variants) at --variant-tets: FitSettings
                    fields, PETSc options of the equilibrium solver and FaceProblem keywords
                    (``VARIANTS``), e.g. ``reuse`` = modified Newton (factorisation kept while
                    the iterations contract)

The takes (--scenarios, 0.5 mm noise, head motion) are synthesised once with the model at
--truth-tets (default: the largest --tets) as --take-frames-long takes at 60 Hz (default 240
frames, 4 s), of which only the stretch of --frames frames from --start is solved and fitted, so
consecutive fitted frames are 1/60 s apart as in a real capture (the speech scenario packs 1.5-12
cycles per muscle into the take: a short whole take would move the face far faster than muscles
can). The default stretch, frames 114-125 of 240, sits on the peak of the smile and jaw pulses
(t = 0.5): the strongest contraction and the widest opening of those takes. Each stretch's first
frame is fitted from rest (not timed); the timings are of the warm-started frames after it. The
training take of the refined basis (Choe & Ko section 4.2) is synthesised whole. Every other model gets the truth
model's marker sites embedded in its own skin (closest point plus offset, as a real capture is
embedded), so a coarser model starts from the same rest markers and differs by its deformation
only. The linear rungs are built from the model at --linear-tets (default: --truth-tets).

Per rung and scenario one JSON line (per-frame seconds, marker RMS, lip marker RMS, activation
RMS and max error, jaw opening error; with --resimulate also the marker RMS of the FE model driven
by a linear rung's controls) goes to --out; the summary table is printed at the end.
``--collect`` rebuilds the tables and the two charts (log time per frame vs marker error and vs
activation error, Pareto front highlighted) from one or more such files:

    nice -n 19 python benchmarks/model_ladder.py --tets 5000 10000 20000 --truth-tets 20000 \
        --variant-tets 10000 --scenarios speech jaw smile --frames 12 --out runs/ladder.jsonl
    python benchmarks/model_ladder.py --collect runs/ladder.jsonl --plot docs/img/ladder

Stages can be separate runs appending to the same file (``--rungs linear``, ``--rungs fe``,
``--rungs --variants reuse gn1``): the takes are cached in --takes. A rung that fails (an
equilibrium that cannot be found, any exception) is written as a row with its ``failure`` and
the frames it finished; the run goes on.
"""
import argparse
import json
import math
import pathlib
import time

import numpy as np

VARIANTS = {
    # name: (FitSettings fields, PETSc options of the equilibrium solver, FaceProblem keywords)
    "reuse": ({}, {}, dict(reuse_factorization=True)),
    "gn1": (dict(max_gn_steps=1), {}, {}),
    "gn6": (dict(max_gn_steps=6, relative_decrease=1e-5), {}, {}),
    "ls2": (dict(line_search_depth=2), {}, {}),
    "fresh-jacobian": (dict(reuse_jacobian=False), {}, {}),
    "newton-1e-6": ({}, dict(snes_rtol=1e-6, snes_atol=1e-6), {}),
    "newton-1e-4": ({}, dict(snes_rtol=1e-4, snes_atol=1e-4), {}),
    # every time-saving setting at once: 1 GN step, shallow line search, loose Newton, reuse
    "fast": (dict(max_gn_steps=1, line_search_depth=2), dict(snes_rtol=1e-6, snes_atol=1e-6),
             dict(reuse_factorization=True)),
    "paper": (dict(mode="paper"), {}, {}),
}


def _fit_fast_variant():
    """``fit --fast`` (``face_dolfinx.tracking.PRESETS["fast"]``), the production setting of docs/performance.md."""
    import dataclasses
    from face_dolfinx.fitting import FitSettings
    from face_dolfinx.tracking import PRESETS
    fast = PRESETS["fast"]
    changed = {f.name: getattr(fast.fit, f.name) for f in dataclasses.fields(FitSettings)
               if getattr(fast.fit, f.name) != getattr(FitSettings(), f.name)}
    return changed, {}, fast.problem_options()


VARIANTS["fit-fast"] = _fit_fast_variant()
LINEAR_RUNGS = ("choe-ko", "choe-ko-kabsch", "choe-ko-refined", "linearized")


def lip_marker_mask(names: list[str]) -> np.ndarray:
    return np.array([("lip" in name) or ("mouth" in name) for name in names])


def jaw_opening(result) -> float:
    """Opening angle (rad) of a fitted frame: its TMJ value (exact mode, linear rungs) or, in
    paper mode (an affine jaw), the rotation angle of the jaw matrix's orthogonal polar factor
    (the opening when both condyles slide alike, as in the jaw scenario)."""
    if result.jaw_tmj is not None:
        return float(result.jaw_tmj[0])
    U, _, Vt = np.linalg.svd(result.jaw.matrix)
    R = U @ Vt
    return math.acos(float(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)))


def score(results, truth, lips: np.ndarray) -> dict:
    """Per-frame measures of one fitted take against its truth (its frames are take frames)."""
    frames = [r.frame for r in results]
    if not results:
        return dict(frame_numbers=[], seconds=[], marker_rms=[], lip_rms=[], activation_rms=[],
                    activation_max=[], jaw_opening_error_deg=[], flagged=0)
    activation_error = np.array([r.activations - truth.activations[r.frame] for r in results])
    return dict(
        frame_numbers=frames,
        seconds=[r.seconds for r in results],
        marker_rms=[r.rms_error for r in results],
        lip_rms=[float(np.sqrt(np.nanmean(r.marker_errors[lips] ** 2))) for r in results],
        activation_rms=np.sqrt(np.mean(activation_error**2, axis=1)).tolist(),
        activation_max=np.abs(activation_error).max(axis=1).tolist(),
        jaw_opening_error_deg=[math.degrees(abs(jaw_opening(r) - truth.tmj[f, 0])) for r, f in zip(results, frames)],
        flagged=sum(1 for r in results if r.flag))


def resimulated_rms(problem, markers, results, positions) -> list[float]:
    """Marker RMS error of the FE model driven by fitted controls (how usable a linear rung's
    activations are for the FE face)."""
    rms = []
    for result in results:
        problem.solve(activations=np.clip(result.activations, 0.0, 1.0), cranium=result.cranium, jaw=result.jaw)
        simulated = markers.positions(problem.u.x.array, result.cranium)
        error = np.linalg.norm(simulated - positions[result.frame], axis=1)
        rms.append(float(np.sqrt(np.nanmean(error**2))))
    return rms


def run(args) -> None:
    from mpi4py import MPI
    from face_dolfinx.model.anatomy import build_builtin_face
    from face_dolfinx.fitting.baselines import ActuationBasis, LinearFitter, LinearizedModel
    from face_dolfinx.model.bones import AffineMap
    from face_dolfinx.fitting import FaceFitter, FitSettings, MarkerSet
    from face_dolfinx.tracking import track
    from face_dolfinx.model.folder import load_model
    from face_dolfinx.physics.problem import FaceProblem
    from face_dolfinx.alignment.surface import SkinSurface
    from face_dolfinx.capture.synthetic import SCENARIOS, TakeTruth, synthesize_take, training_segments

    comm = MPI.COMM_WORLD
    out = pathlib.Path(args.out)
    if comm.rank == 0:
        out.parent.mkdir(parents=True, exist_ok=True)
    truth_tets = args.truth_tets or max(args.tets)
    linear_tets = args.linear_tets or truth_tets
    variant_tets = args.variant_tets or [min(args.tets)]
    models = {}

    def model_at(tets):
        if tets not in models:
            models[tets] = load_model(build_builtin_face(target_tets=tets, comm=comm), comm)
        return models[tets]

    def log(message):
        if comm.rank == 0:
            print(message, flush=True)

    truth_model = model_at(truth_tets)
    names = list(truth_model.markers)
    sites = np.array([truth_model.markers[n] for n in names])
    lips = lip_marker_mask(names)

    def markers_on(problem):
        """The truth's marker sites embedded in this model's skin: closest point + offset."""
        embedding = SkinSurface(*problem.model.skin_surface()).embed(sites)
        return MarkerSet(problem, sites - embedding.offsets, embedding.offsets, names=names)

    truth_problem = None

    def take(scenario, n_frames, stretch=None):
        """(positions, truth) of a take at the truth model, only the frames in ``stretch`` (a
        range; default all) solved and returned: from --takes if made before."""
        nonlocal truth_problem
        seed = args.seed + SCENARIOS.index(scenario)
        part = "" if stretch is None else f"_frames{stretch.start}-{stretch.stop - 1}"
        path = pathlib.Path(args.takes) / (f"{scenario}_{truth_tets}tets_{n_frames}f{part}_"
                                           f"{args.noise}mm_seed{seed}.npz")
        if path.exists():
            stored = np.load(path)
            head = [AffineMap(M, t) for M, t in zip(stored["head_matrices"], stored["head_translations"])]
            return stored["positions"], TakeTruth(stored["activations"], stored["tmj"], head, stored["clean"])
        if truth_problem is None:
            truth_problem = FaceProblem(truth_model)
        began = time.perf_counter()
        capture, truth = synthesize_take(truth_problem, markers_on(truth_problem), truth_model, scenario,
                                         n_frames=n_frames, noise=args.noise, seed=seed, frames=stretch)
        log(f"take {scenario}: {len(capture.positions)} of {n_frames} frames at {truth_tets} tets, "
            f"{time.perf_counter() - began:.1f} s")
        if comm.rank == 0:
            path.parent.mkdir(parents=True, exist_ok=True)
            np.savez(path, positions=capture.positions, activations=truth.activations, tmj=truth.tmj,
                     head_matrices=[h.matrix for h in truth.head],
                     head_translations=[h.translation for h in truth.head], clean=truth.clean_positions)
        return capture.positions, truth

    stretch = range(args.start, args.start + args.frames)
    if stretch.stop > args.take_frames:
        raise SystemExit(f"--start {args.start} + --frames {args.frames} runs past --take-frames {args.take_frames}")
    takes = {scenario: take(scenario, args.take_frames, stretch) for scenario in args.scenarios}
    training = None
    if "linear" in args.rungs:
        training, _ = take("training", args.training_levels * len(training_segments(truth_model)))
    truth_problem = None  # free the truth model's solver before the rungs

    def tets_of(model):
        return int(model.mesh.topology.index_map(3).size_global)

    def write(row):
        base = dict(truth_tets=tets_of(truth_model), noise=args.noise, frames=args.frames, ranks=comm.size,
                    take_frames=args.take_frames, start=args.start)
        row = {**base, **row}
        if comm.rank == 0:
            with open(out, "a") as handle:
                handle.write(json.dumps(row) + "\n")
        summary = {k: round(float(np.mean(row[k])), 4) if row[k] else None
                   for k in ("marker_rms", "activation_rms", "activation_max")}
        seconds = row["seconds"][1:] or row["seconds"]
        log(f"{row['method']:>22} {row['tets']:>7} {row['scenario']:>8}: "
            f"{np.mean(seconds) if seconds else float('nan'):.3f} s/frame {summary}"
            + (f" FAILED {row['failure']}" if row.get("failure") else ""))

    if "linear" in args.rungs:
        model = model_at(linear_tets)
        problem = FaceProblem(model)
        markers = markers_on(problem)
        basis = ActuationBasis.from_face(problem, markers)
        refined, history = basis.refined(training, max_iterations=args.refine_iterations)
        log(f"basis {basis.build_seconds:.1f} s; refinement {refined.build_seconds - basis.build_seconds:.1f} s, "
            f"training error {history[0]:.0f} -> {min(history):.0f} mm^2 in {len(history) - 1} updates")
        linearized = LinearizedModel.from_face(problem, markers)
        rungs = {"choe-ko": (basis, "joint"), "choe-ko-kabsch": (basis, "kabsch"),
                 "choe-ko-refined": (refined, "joint"), "linearized": (linearized, "joint")}
        for method, (linear_model, head) in rungs.items():
            for scenario, (positions, truth) in takes.items():
                results, failure = [], ""
                try:
                    track(LinearFitter(linear_model, model.jaw, head=head), positions, on_frame=results.append)
                except Exception as error:  # a rung that breaks is a result too: record, go on
                    failure = f"frame {len(results)}: {type(error).__name__}: {error}"
                row = dict(method=method, tets=tets_of(model), scenario=scenario, failure=failure,
                           build_seconds=linear_model.build_seconds, **score(results, truth, lips))
                if method == "choe-ko-refined":
                    row["training_error_history"] = history
                if args.resimulate and results:
                    try:
                        row["resimulated_rms"] = resimulated_rms(problem, markers, results, positions)
                    except Exception as error:
                        row["resimulation_failure"] = f"{type(error).__name__}: {error}"
                write(row)
        del problem

    fe_runs = [("fe", tets, {}, {}, {}) for tets in args.tets] if "fe" in args.rungs else []
    fe_runs += [(f"fe-{name}", tets, *VARIANTS[name]) for name in args.variants for tets in variant_tets]
    for method, tets, settings, petsc_options, problem_options in fe_runs:
        model = model_at(tets)
        for scenario, (positions, truth) in takes.items():
            results, failure, factorizations = [], "", []
            setup = math.nan
            try:
                began = time.perf_counter()
                problem = FaceProblem(model, petsc_options=petsc_options, **problem_options)
                fitter = FaceFitter(problem, markers_on(problem), FitSettings(**settings))
                setup = time.perf_counter() - began

                counted = [0]

                def done(result):
                    results.append(result)
                    factorizations.append(problem.solver.factorizations - counted[0])
                    counted[0] = problem.solver.factorizations

                track(fitter, positions, on_frame=done)
            except Exception as error:  # a rung that breaks is a result too: record, go on
                failure = f"frame {len(results)}: {type(error).__name__}: {error}"
            write(dict(method=method, tets=tets_of(model), scenario=scenario, build_seconds=setup,
                       settings=settings, petsc_options=petsc_options, problem_options=problem_options,
                       failure=failure, factorizations=factorizations,
                       gn_steps=[r.gn_steps for r in results], **score(results, truth, lips)))
            problem = fitter = None
    from provenance import record
    record(out, tets=sorted(models), ranks=comm.size)
    if comm.rank == 0:
        print(collect([out]))


# -- tables and charts ----------------------------------------------------------------------------
def load_rows(paths) -> list[dict]:
    rows = []
    for path in paths:
        rows += [json.loads(line) for line in pathlib.Path(path).read_text().splitlines() if line.strip()]
    return rows


def aggregate(rows) -> list[dict]:
    """One entry per (method, tets) over its scenarios: warm seconds per frame (every frame
    but each take's first, which starts from rest), marker RMS over all frames, mean of the
    per-frame activation RMS, largest activation error and where it happened, factorisations
    per warm frame (FE rungs), failures. A rung with no finished frame gets NaN measures."""
    groups = {}
    for row in rows:
        groups.setdefault((row["method"], row["tets"], row.get("ranks", 1)), []).append(row)
    table = []
    for (method, tets, ranks), group in groups.items():
        done = [r for r in group if r["seconds"]]

        def frames(key, rows=done):
            values = [np.asarray(r[key], dtype=float) for r in rows]
            return np.concatenate(values) if values else np.full(1, math.nan)

        def warm(key, rows=done):
            values = [np.asarray(r[key][1:] or r[key], dtype=float) for r in rows]
            return float(np.mean(np.concatenate(values))) if values else math.nan

        worst = "" if not done else max(
            ((r["scenario"], i, v) for r in done for i, v in enumerate(r["activation_max"])),
            key=lambda e: e[2])
        counted = [r for r in done if r.get("factorizations")]
        table.append(dict(
            method=method, tets=tets, ranks=ranks,
            seconds=warm("seconds"),
            build_seconds=float(np.nanmean([r["build_seconds"] for r in group]))
            if any(np.isfinite(r["build_seconds"]) for r in group) else math.nan,
            marker_rms=float(np.sqrt(np.mean(frames("marker_rms") ** 2))),
            lip_rms=float(np.sqrt(np.mean(frames("lip_rms") ** 2))),
            resimulated_rms=(float(np.sqrt(np.mean(frames("resimulated_rms") ** 2)))
                             if done and all("resimulated_rms" in r for r in done) else math.nan),
            activation_rms=float(np.mean(frames("activation_rms"))),
            activation_max=float(np.max(frames("activation_max"))),
            jaw_error_deg=float(np.mean(frames("jaw_opening_error_deg"))),
            factorizations=warm("factorizations", counted) if counted else math.nan,
            worst=f"{worst[0]}:{worst[1]}" if worst else "",
            flagged=int(sum(r["flagged"] for r in group)),
            scenarios=len(done), frames=int(sum(len(r["seconds"]) for r in group)),
            failed=[f"{r['scenario']} {r['failure']}" for r in group if r.get("failure")]))
    return sorted(table, key=lambda e: (math.isnan(e["seconds"]), e["seconds"]))


def _number(value, spec) -> str:
    return "" if value is None or (isinstance(value, float) and math.isnan(value)) else format(value, spec)


def collect(paths) -> str:
    rows = load_rows(paths)
    truths = sorted({r["truth_tets"] for r in rows})
    if len(truths) > 1:
        raise SystemExit(f"rows fitted against different truths ({', '.join(map(str, truths))} tets): "
                         "collect each truth's rows on their own")
    lines = ["| method | tets | ranks | s/frame | factorisations/frame | build s | marker RMS mm | lips RMS mm "
             "| FE resim RMS mm | activation RMS | activation max | jaw err deg | worst (scenario:frame) "
             "| flagged | frames | failed |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for e in aggregate(rows):
        lines.append(f"| {e['method']} | {e['tets']} | {e['ranks']} | {_number(e['seconds'], '.3g')} "
                     f"| {_number(e['factorizations'], '.1f')} | {_number(e['build_seconds'], '.3g')} "
                     f"| {_number(e['marker_rms'], '.3f')} | {_number(e['lip_rms'], '.3f')} "
                     f"| {_number(e['resimulated_rms'], '.3f')} | {_number(e['activation_rms'], '.3f')} "
                     f"| {_number(e['activation_max'], '.3f')} | {_number(e['jaw_error_deg'], '.2f')} "
                     f"| {e['worst']} | {e['flagged']} | {e['frames']} "
                     f"| {'; '.join(failure[:80] for failure in e['failed'])} |")
    lines += ["", "Per scenario (s/frame warm / marker RMS mm / lips RMS mm / activation RMS / "
              "activation max / jaw opening err deg; FAILED = the rung stopped, after the frames shown):", ""]
    scenarios = sorted({r["scenario"] for r in rows})
    lines += ["| method | tets | ranks | " + " | ".join(scenarios) + " |", "|---|---|---|" + "---|" * len(scenarios)]
    cells = {(r["method"], r["tets"], r.get("ranks", 1), r["scenario"]): r for r in rows}
    for e in aggregate(rows):
        entries = []
        for scenario in scenarios:
            r = cells.get((e["method"], e["tets"], e["ranks"], scenario))
            if r is None:
                entries.append("")
                continue
            text = "" if not r["seconds"] else (
                f"{np.mean(r['seconds'][1:] or r['seconds']):.3g} / "
                f"{np.sqrt(np.mean(np.square(r['marker_rms']))):.2f} / "
                f"{np.sqrt(np.mean(np.square(r['lip_rms']))):.2f} / "
                f"{np.mean(r['activation_rms']):.3f} / {np.max(r['activation_max']):.2f} / "
                f"{np.mean(r['jaw_opening_error_deg']):.2f}")
            if r.get("failure"):
                text += f" FAILED after {len(r['seconds'])} frames"
            entries.append(text)
        lines.append(f"| {e['method']} | {e['tets']} | {e['ranks']} | " + " | ".join(entries) + " |")
    return "\n".join(lines)


def pareto_front(points: np.ndarray, tolerance: float = 1e-3) -> np.ndarray:
    """Indices of the points (time, error) that no other point beats in both, by time. A slower
    point must lower the error by more than ``tolerance`` (relative) to count: settings that
    converge to the same fit differ only by round-off."""
    order = np.lexsort((points[:, 1], points[:, 0]))
    front, best = [], math.inf
    for i in order:
        if points[i, 1] < best * (1.0 - tolerance):
            front.append(i)
            best = points[i, 1]
    return np.array(front, dtype=int)


def plot(paths, prefix: str) -> list[pathlib.Path]:
    """Two charts: log seconds per frame vs marker RMS and vs activation RMS error."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = load_rows(paths)
    entries = aggregate(rows)
    noise = sorted({r["noise"] for r in rows})
    written = []
    for key, label, suffix in (("marker_rms", "marker RMS error (mm)", "marker"),
                               ("activation_rms", "activation error (RMS over muscles, mean over frames)",
                                "activation")):
        shown = [e for e in entries if np.isfinite(e["seconds"]) and np.isfinite(e[key])]
        points = np.array([(e["seconds"], e[key]) for e in shown])
        front = pareto_front(points)
        figure, axes = plt.subplots(figsize=(7.5, 5.0))
        axes.scatter(points[:, 0], points[:, 1], color="0.6", zorder=2)
        axes.step(points[front, 0], points[front, 1], where="post", color="tab:red", zorder=1,
                  label="Pareto front")
        axes.scatter(points[front, 0], points[front, 1], color="tab:red", zorder=3)
        for e, (x, y) in zip(shown, points):
            failed = f" (failed {len(e['failed'])}/{len(e['failed']) + e['scenarios']})" if e["failed"] else ""
            ranks = f" {e['ranks']} ranks" if e["ranks"] > 1 else ""
            axes.annotate(f"{e['method']} {round(e['tets'] / 1000)}K{ranks}{failed}", (x, y), textcoords="offset points",
                          xytext=(4, 3), fontsize=7)
        if key == "marker_rms":
            for level in noise:  # a fit below the noise is fitting the noise
                axes.axhline(level, color="0.3", linestyle="--", linewidth=0.8, label=f"marker noise {level} mm")
        axes.set_xscale("log")
        axes.set_xlabel("seconds per frame (warm-started, log)")
        axes.set_ylabel(label)
        axes.grid(True, which="both", alpha=0.3)
        axes.legend()
        figure.tight_layout()
        path = pathlib.Path(f"{prefix}_{suffix}.png")
        path.parent.mkdir(parents=True, exist_ok=True)
        figure.savefig(path, dpi=130)
        plt.close(figure)
        written.append(path)
    return written


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--tets", type=int, nargs="+", default=[5000, 10000], help="FE rung resolutions")
    parser.add_argument("--truth-tets", type=int, help="resolution of the takes' truth (default: max --tets)")
    parser.add_argument("--linear-tets", type=int, help="model the linear rungs come from (default: truth)")
    parser.add_argument("--variant-tets", type=int, nargs="+",
                        help="resolutions of the solver variants (default: min --tets)")
    parser.add_argument("--variants", nargs="*", default=list(VARIANTS), choices=list(VARIANTS))
    parser.add_argument("--rungs", nargs="*", default=["linear", "fe"], choices=["linear", "fe"],
                        help="give none (--rungs alone) to run only --variants")
    parser.add_argument("--scenarios", nargs="+", default=["speech", "jaw", "smile"])
    parser.add_argument("--frames", type=int, default=12, help="frames fitted per scenario (a stretch)")
    parser.add_argument("--take-frames", type=int, default=240,
                        help="length of each synthetic take at 60 Hz (sets how fast the face moves)")
    parser.add_argument("--start", type=int, default=114,
                        help="first fitted frame of the take (default: the stretch on the smile/jaw peak)")
    parser.add_argument("--noise", type=float, default=0.5, help="marker noise, RMS of the 3D error (mm)")
    parser.add_argument("--training-levels", type=int, default=2,
                        help="frames per segment of the training take (levels 1/n .. 1)")
    parser.add_argument("--refine-iterations", type=int, default=20, help="most basis refinement updates")
    parser.add_argument("--resimulate", action="store_true",
                        help="also drive the FE model with each linear rung's controls")
    parser.add_argument("--seed", type=int, default=0, help="take seeds: this + the scenario's index")
    parser.add_argument("--takes", default="runs/ladder_takes",
                        help="folder of synthesised takes, reused by later runs with the same parameters")
    parser.add_argument("--out", default="runs/ladder.jsonl", help="JSON lines, appended")
    parser.add_argument("--collect", nargs="+", metavar="JSONL", help="only print tables from these files")
    parser.add_argument("--plot", metavar="PREFIX", help="with --collect: write PREFIX_marker.png, PREFIX_activation.png")
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
