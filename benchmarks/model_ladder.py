"""The model ladder (issue 5): the same synthetic takes fitted by models from cheap to faithful.

Rungs:
  choe-ko           Choe & Ko 2001 actuation basis from the FE model (muscle fully on, TMJ
                    limits), upper/lower regions, head solved jointly (``baselines.py``)
  choe-ko-kabsch    the same basis, head removed first by a rigid fit to every marker
  choe-ko-refined   the basis after the section 4.2 refinement on a training take
  linearized        the FE model's marker Jacobian at rest as a fixed linear model
  fe                the nonlinear FE fitter (exact mode, default FitSettings) at each --tets
  fe-<variant>      solver settings traded for time (--variants) at --variant-tets

The takes (--scenarios, 0.5 mm noise, head motion) and the training take are synthesised once
with the model at --truth-tets (default: the largest --tets). Every other model gets the truth
model's marker sites embedded in its own skin (closest point plus offset, as a real capture is
embedded), so a coarser model starts from the same rest markers and differs by its deformation
only. The linear rungs are built from the model at --linear-tets (default: --truth-tets).

Per rung and scenario one JSON line (per-frame seconds, marker RMS, lip marker RMS, activation
RMS and max error, jaw opening error; with --resimulate also the marker RMS of the FE model driven
by a linear rung's controls) goes to --out; the summary table is printed at the end.
``--collect`` rebuilds the tables and the two charts (log time per frame vs marker error and vs
activation error, Pareto front highlighted) from one or more such files:

    nice -n 5 python benchmarks/model_ladder.py --tets 5000 10000 --frames 12 --resimulate --out runs/ladder.jsonl
    python benchmarks/model_ladder.py --collect runs/ladder.jsonl --plot docs/img/ladder
"""
import argparse
import json
import math
import pathlib
import time

import numpy as np

VARIANTS = {
    # name: (FitSettings fields, PETSc options of the equilibrium solver)
    "gn1": (dict(max_gn_steps=1), {}),
    "gn6": (dict(max_gn_steps=6, relative_decrease=1e-5), {}),
    "ls2": (dict(line_search_depth=2), {}),
    "fresh-jacobian": (dict(reuse_jacobian=False), {}),
    "newton-1e-6": ({}, dict(snes_rtol=1e-6, snes_atol=1e-6)),
    "paper": (dict(mode="paper"), {}),
}
LINEAR_RUNGS = ("choe-ko", "choe-ko-kabsch", "choe-ko-refined", "linearized")


def lip_marker_mask(names: list[str]) -> np.ndarray:
    return np.array([("lip" in name) or ("mouth" in name) for name in names])


def score(results, truth, lips: np.ndarray) -> dict:
    """Per-frame measures of one fitted take against its truth."""
    frames = [r.frame for r in results]
    activation_error = np.array([r.activations - truth.activations[r.frame] for r in results])
    return dict(
        seconds=[r.seconds for r in results],
        marker_rms=[r.rms_error for r in results],
        lip_rms=[float(np.sqrt(np.nanmean(r.marker_errors[lips] ** 2))) for r in results],
        activation_rms=np.sqrt(np.mean(activation_error**2, axis=1)).tolist(),
        activation_max=np.abs(activation_error).max(axis=1).tolist(),
        jaw_opening_error_deg=[math.degrees(abs(r.jaw_tmj[0] - truth.tmj[f, 0])) for r, f in zip(results, frames)],
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
    from face_dolfinx.anatomy import build_builtin_face
    from face_dolfinx.baselines import ActuationBasis, LinearFitter, LinearizedModel
    from face_dolfinx.bones import AffineMap
    from face_dolfinx.fitting import FaceFitter, FitSettings, MarkerSet, track
    from face_dolfinx.model import load_model
    from face_dolfinx.problem import FaceProblem
    from face_dolfinx.solver import EquilibriumError
    from face_dolfinx.surface import SkinSurface
    from face_dolfinx.synthetic import SCENARIOS, TakeTruth, synthesize_take, training_segments

    comm = MPI.COMM_WORLD
    out = pathlib.Path(args.out)
    if comm.rank == 0:
        out.parent.mkdir(parents=True, exist_ok=True)
    truth_tets = args.truth_tets or max(args.tets)
    linear_tets = args.linear_tets or truth_tets
    variant_tets = args.variant_tets or min(args.tets)
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

    def take(scenario, n_frames):
        """(positions, truth) of a take at the truth model: from --takes if made before."""
        nonlocal truth_problem
        seed = args.seed + SCENARIOS.index(scenario)
        path = pathlib.Path(args.takes) / f"{scenario}_{truth_tets}tets_{n_frames}f_{args.noise}mm_seed{seed}.npz"
        if path.exists():
            stored = np.load(path)
            head = [AffineMap(M, t) for M, t in zip(stored["head_matrices"], stored["head_translations"])]
            return stored["positions"], TakeTruth(stored["activations"], stored["tmj"], head, stored["clean"])
        if truth_problem is None:
            truth_problem = FaceProblem(truth_model)
        began = time.perf_counter()
        capture, truth = synthesize_take(truth_problem, markers_on(truth_problem), truth_model, scenario,
                                         n_frames=n_frames, noise=args.noise, seed=seed)
        log(f"take {scenario}: {n_frames} frames at {truth_tets} tets, {time.perf_counter() - began:.1f} s")
        if comm.rank == 0:
            path.parent.mkdir(parents=True, exist_ok=True)
            np.savez(path, positions=capture.positions, activations=truth.activations, tmj=truth.tmj,
                     head_matrices=[h.matrix for h in truth.head],
                     head_translations=[h.translation for h in truth.head], clean=truth.clean_positions)
        return capture.positions, truth

    takes = {scenario: take(scenario, args.frames) for scenario in args.scenarios}
    training, _ = take("training", args.training_levels * len(training_segments(truth_model)))
    truth_problem = None  # free the truth model's solver before the rungs

    def tets_of(model):
        return int(model.mesh.topology.index_map(3).size_global)

    def write(row):
        base = dict(truth_tets=tets_of(truth_model), noise=args.noise, frames=args.frames, ranks=comm.size)
        row = {**base, **row}
        if comm.rank == 0:
            with open(out, "a") as handle:
                handle.write(json.dumps(row) + "\n")
        summary = {k: round(float(np.mean(row[k])), 4) for k in ("marker_rms", "activation_rms", "activation_max")}
        log(f"{row['method']:>22} {row['tets']:>7} {row['scenario']:>8}: "
            f"{np.mean(row['seconds'][1:] or row['seconds']):.3f} s/frame {summary}")

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
                results = track(LinearFitter(linear_model, model.jaw, head=head), positions)
                row = dict(method=method, tets=tets_of(model), scenario=scenario,
                           build_seconds=linear_model.build_seconds, **score(results, truth, lips))
                if method == "choe-ko-refined":
                    row["training_error_history"] = history
                if args.resimulate:
                    row["resimulated_rms"] = resimulated_rms(problem, markers, results, positions)
                write(row)
        del problem

    fe_runs = [("fe", tets, {}, {}) for tets in args.tets] if "fe" in args.rungs else []
    fe_runs += [(f"fe-{name}", variant_tets, *VARIANTS[name]) for name in args.variants]
    for method, tets, settings, petsc_options in fe_runs:
        model = model_at(tets)
        for scenario, (positions, truth) in takes.items():
            began = time.perf_counter()
            problem = FaceProblem(model, petsc_options=petsc_options)
            fitter = FaceFitter(problem, markers_on(problem), FitSettings(**settings))
            setup = time.perf_counter() - began
            results, failure = [], ""
            try:
                track(fitter, positions, on_frame=results.append)
            except EquilibriumError as error:  # a rung that breaks is a result too: record, go on
                failure = f"frame {len(results)}: {error}"
                log(f"{method} {tets} {scenario} failed at {failure}")
            if results:
                write(dict(method=method, tets=tets_of(model), scenario=scenario, build_seconds=setup,
                           settings=settings, petsc_options=petsc_options, failure=failure,
                           **score(results, truth, lips)))
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
    per-frame activation RMS, largest activation error and where it happened."""
    groups = {}
    for row in rows:
        groups.setdefault((row["method"], row["tets"]), []).append(row)
    table = []
    for (method, tets), group in groups.items():
        def frames(key):
            return np.concatenate([np.asarray(r[key], dtype=float) for r in group])
        worst_row = max(group, key=lambda r: max(r["activation_max"]))
        worst_frame = int(np.argmax(worst_row["activation_max"]))
        table.append(dict(
            method=method, tets=tets,
            seconds=float(np.mean(np.concatenate([r["seconds"][1:] or r["seconds"] for r in group]))),
            build_seconds=float(np.mean([r["build_seconds"] for r in group])),
            marker_rms=float(np.sqrt(np.mean(frames("marker_rms") ** 2))),
            lip_rms=float(np.sqrt(np.mean(frames("lip_rms") ** 2))),
            resimulated_rms=(float(np.sqrt(np.mean(frames("resimulated_rms") ** 2)))
                             if all("resimulated_rms" in r for r in group) else math.nan),
            activation_rms=float(np.mean(frames("activation_rms"))),
            activation_max=float(frames("activation_max").max()),
            jaw_error_deg=float(np.mean(frames("jaw_opening_error_deg"))),
            worst=f"{worst_row['scenario']}:{worst_frame}",
            flagged=int(sum(r["flagged"] for r in group)),
            failed=[f"{r['scenario']} {r['failure']}" for r in group if r.get("failure")]))
    return sorted(table, key=lambda e: e["seconds"])


def collect(paths) -> str:
    rows = load_rows(paths)
    lines = ["| method | tets | s/frame | build s | marker RMS mm | lips RMS mm | FE resim RMS mm "
             "| activation RMS | activation max | jaw err deg | worst (scenario:frame) | flagged | failed |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for e in aggregate(rows):
        resim = "" if math.isnan(e["resimulated_rms"]) else f"{e['resimulated_rms']:.3f}"
        lines.append(f"| {e['method']} | {e['tets']} | {e['seconds']:.3g} | {e['build_seconds']:.3g} "
                     f"| {e['marker_rms']:.3f} | {e['lip_rms']:.3f} | {resim} | {e['activation_rms']:.3f} "
                     f"| {e['activation_max']:.3f} | {e['jaw_error_deg']:.2f} | {e['worst']} | {e['flagged']} "
                     f"| {'; '.join(failure[:60] for failure in e['failed'])} |")
    lines += ["", "Per scenario (marker RMS mm / lips RMS mm / activation RMS / jaw err deg):", ""]
    scenarios = sorted({r["scenario"] for r in rows})
    lines += ["| method | tets | " + " | ".join(scenarios) + " |", "|---|---|" + "---|" * len(scenarios)]
    cells = {(r["method"], r["tets"], r["scenario"]): r for r in rows}
    for e in aggregate(rows):
        entries = []
        for scenario in scenarios:
            r = cells.get((e["method"], e["tets"], scenario))
            entries.append("" if r is None else
                           f"{np.sqrt(np.mean(np.square(r['marker_rms']))):.2f} / "
                           f"{np.sqrt(np.mean(np.square(r['lip_rms']))):.2f} / "
                           f"{np.mean(r['activation_rms']):.3f} / {np.mean(r['jaw_opening_error_deg']):.2f}")
        lines.append(f"| {e['method']} | {e['tets']} | " + " | ".join(entries) + " |")
    return "\n".join(lines)


def pareto_front(points: np.ndarray) -> np.ndarray:
    """Indices of the points (time, error) that no other point beats in both, by time."""
    order = np.lexsort((points[:, 1], points[:, 0]))
    front, best = [], math.inf
    for i in order:
        if points[i, 1] < best:
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
        points = np.array([(e["seconds"], e[key]) for e in entries])
        front = pareto_front(points)
        figure, axes = plt.subplots(figsize=(7.5, 5.0))
        axes.scatter(points[:, 0], points[:, 1], color="0.6", zorder=2)
        axes.step(points[front, 0], points[front, 1], where="post", color="tab:red", zorder=1,
                  label="Pareto front")
        axes.scatter(points[front, 0], points[front, 1], color="tab:red", zorder=3)
        for e, (x, y) in zip(entries, points):
            axes.annotate(f"{e['method']} {e['tets'] // 1000}K", (x, y), textcoords="offset points",
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
    parser.add_argument("--variant-tets", type=int, help="resolution of the solver variants (default: min --tets)")
    parser.add_argument("--variants", nargs="*", default=list(VARIANTS), choices=list(VARIANTS))
    parser.add_argument("--rungs", nargs="*", default=["linear", "fe"], choices=["linear", "fe"])
    parser.add_argument("--scenarios", nargs="+", default=["smile", "jaw", "speech"])
    parser.add_argument("--frames", type=int, default=12)
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
