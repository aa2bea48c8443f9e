"""Dynamic against quasistatic re-simulation of the face (sifakis2005 section 9).

For each motion (an expression switched on and held, a head shake, a jog) and each tissue (the
model's own, or the nose and cheeks softened by a regional override), the face is integrated in
time (``FaceProblem.dynamics``: Newmark's average acceleration, substeps of at most 1/240 s) and,
frame by frame at 60 Hz, solved quasistatically for the same controls (warm-started from the last
frame, as ``simulate`` and the fit do). Each frame gives one JSON line: the largest difference of
the skin's marker sites and of any node between the two, and the seconds each took. Summary lines
(``"summary": true``) give the largest difference over the motion and the cost ratio.

    python benchmarks/dynamics.py --tets 5000 --out benchmarks/results/dynamics/dynamics_5k.jsonl \
        --plot docs/img/dynamics_5k.png
"""
import argparse
import json
import math
import pathlib
import sys
import time

from mpi4py import MPI
import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent.parent))
sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
import provenance  # noqa: E402
from face_dolfinx.equilibrium.dynamics import DynamicsError, DynamicSettings  # noqa: E402
from face_dolfinx.equilibrium.solver import EquilibriumError  # noqa: E402
from face_dolfinx.model.anatomy import build_builtin_face  # noqa: E402
from face_dolfinx.model.bones import AffineMap  # noqa: E402
from face_dolfinx.model.folder import load_model  # noqa: E402
from face_dolfinx.model.regions import MaterialOverride, Region  # noqa: E402
from face_dolfinx.physics.problem import Controls, FaceProblem  # noqa: E402

FRAME_RATE = 60.0
SOFT_FACTOR = 0.01  # the softened nose and cheeks: 1/100 of the model's flesh stiffness


def rotation_about_y(angle: float, pivot: np.ndarray) -> AffineMap:
    c, s = math.cos(angle), math.sin(angle)
    matrix = np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
    return AffineMap(matrix, pivot - matrix @ pivot)


def motions(model, problem) -> dict:
    """name -> (duration in s, controls_at(t))."""
    rest = problem.rest_controls()
    smile = problem.activation_vector(model.expressions["smile"]) if "smile" in model.expressions else None
    pivot = np.array([0.0, -20.0, 0.0])  # behind the face, at the height of the mouth

    def expression(t):  # the smile switched on in 0.15 s, then held
        s = min(t / 0.15, 1.0)
        return Controls(s * s * (3 - 2 * s) * smile, rest.cranium, rest.jaw)

    def onset(t):  # the periodic motions start from rest, taking 0.1 s to reach their amplitude
        s = min(t / 0.1, 1.0)
        return s * s * (3 - 2 * s)

    def shake(t):  # +-12 degrees about the vertical at 2.5 Hz
        angle = math.radians(12.0) * onset(t) * math.sin(2 * math.pi * 2.5 * t)
        return Controls(rest.activations, rotation_about_y(angle, pivot), rest.jaw)

    def jog(t):  # 15 mm up and down at 2.5 Hz (0.37 g peak)
        height = 15.0 * onset(t) * math.sin(2 * math.pi * 2.5 * t)
        return Controls(rest.activations, AffineMap(np.eye(3), [0.0, height, 0.0]), rest.jaw)

    return {"expression": (0.3, expression), "shake": (0.4, shake), "jog": (0.4, jog)}


def soft_regions(model) -> list[MaterialOverride]:
    """The nose and both cheeks, spheres about their landmarks, at SOFT_FACTOR."""
    overrides = [MaterialOverride(Region("sphere", numbers=(*model.landmarks["nose_tip"], 18.0)),
                                  {"all": SOFT_FACTOR})]
    for side in ("left", "right"):
        centre = model.landmarks[f"cheekbone_{side}"] + np.array([0.0, -20.0, 0.0])
        overrides.append(MaterialOverride(Region("sphere", numbers=(*centre, 22.0)), {"all": SOFT_FACTOR}))
    return overrides


def marker_nodes(problem, model) -> np.ndarray:
    """The local dof block nearest each marker site (on every rank: the largest difference is
    reduced over ranks, each rank's own nearest nodes serve)."""
    X = problem.dof_coordinates
    sites = np.array(list(model.markers.values()))
    return np.array([np.argmin(np.linalg.norm(X - site, axis=1)) for site in sites]) if len(X) else np.zeros(0, int)


def run(model_path, tissue: str, motion: str, comm, time_step: float, write) -> dict:
    model = load_model(model_path, comm)
    if tissue == "soft":
        model = model.with_material(soft_regions(model))
    dynamic_problem = FaceProblem(model)
    quasistatic = FaceProblem(model)
    duration, controls_at = motions(model, dynamic_problem)[motion]
    dynamic = dynamic_problem.dynamics(DynamicSettings(time_step=time_step))
    markers = marker_nodes(dynamic_problem, model)
    times = np.arange(0.0, duration + 0.5 / FRAME_RATE, 1.0 / FRAME_RATE)
    rows = []

    def frame(index, t, report):
        began = time.perf_counter()
        quasistatic.solve(**vars_of(controls_at(t)))
        qs_seconds = comm.allreduce(time.perf_counter() - began, op=MPI.MAX)
        difference = (dynamic_problem.u.x.array - quasistatic.u.x.array).reshape(-1, 3)
        norms = np.linalg.norm(difference, axis=1)
        row = dict(tets=model.mesh.topology.index_map(3).size_global, ranks=comm.size, tissue=tissue, motion=motion,
                   frame=index, time_s=round(t, 6),
                   marker_difference_mm=comm.allreduce(float(norms[markers].max(initial=0.0)), op=MPI.MAX),
                   max_difference_mm=comm.allreduce(float(norms.max(initial=0.0)), op=MPI.MAX),
                   dynamic_seconds=comm.allreduce(report.seconds if report else 0.0, op=MPI.MAX),
                   substeps=report.substeps if report else 0,
                   dynamic_newton_iterations=report.newton_iterations if report else 0,
                   quasistatic_seconds=qs_seconds)
        rows.append(row)
        write(row)

    try:
        dynamic.run(controls_at, times, frame)
    except (DynamicsError, EquilibriumError) as error:  # recorded; the other variants still run
        failure = dict(summary=True, tets=model.mesh.topology.index_map(3).size_global, ranks=comm.size,
                       tissue=tissue, motion=motion, time_step_s=time_step, frames=len(rows), failed=str(error))
        write(failure)
        return dict(rows=rows, summary=failure)
    moving = [row for row in rows if row["frame"] > 0]
    summary = dict(summary=True, tets=rows[0]["tets"], ranks=comm.size, tissue=tissue, motion=motion,
                   time_step_s=time_step, frames=len(rows),
                   max_marker_difference_mm=max(row["marker_difference_mm"] for row in rows),
                   max_difference_mm=max(row["max_difference_mm"] for row in rows),
                   dynamic_seconds_per_frame=float(np.mean([row["dynamic_seconds"] for row in moving])),
                   quasistatic_seconds_per_frame=float(np.mean([row["quasistatic_seconds"] for row in moving])))
    summary["cost_ratio"] = summary["dynamic_seconds_per_frame"] / summary["quasistatic_seconds_per_frame"]
    write(summary)
    return dict(rows=rows, summary=summary)


def vars_of(controls) -> dict:
    return dict(activations=controls.activations, cranium=controls.cranium, jaw=controls.jaw)


def plot(results: list[dict], path: pathlib.Path, noise: float) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    motions_seen = list(dict.fromkeys(r["summary"]["motion"] for r in results))
    figure, axes = plt.subplots(1, len(motions_seen), figsize=(4.2 * len(motions_seen), 3.4), squeeze=False)
    for axis, motion in zip(axes[0], motions_seen):
        for result in results:
            if result["summary"]["motion"] != motion or "failed" in result["summary"]:
                continue
            rows = result["rows"]
            axis.plot([r["time_s"] for r in rows], [r["marker_difference_mm"] for r in rows],
                      label=f"{result['summary']['tissue']} tissue")
        axis.axhline(noise, color="grey", linestyle="--", label=f"marker noise {noise} mm")
        axis.set_title(f"{motion}, {results[0]['summary']['tets']} tets")
        axis.set_xlabel("time (s)")
        axis.set_ylabel("dynamic - quasistatic, worst marker (mm)")
        axis.set_yscale("log")
        axis.legend(fontsize=8)
    figure.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path, dpi=110)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--tets", type=int, default=5000)
    parser.add_argument("--motions", nargs="+", default=["expression", "shake", "jog"])
    parser.add_argument("--tissues", nargs="+", default=["model", "soft"])
    parser.add_argument("--time-step", type=float, default=1.0 / 240.0, help="largest substep (s)")
    parser.add_argument("--out", type=pathlib.Path, required=True, help="JSON-lines file")
    parser.add_argument("--plot", type=pathlib.Path, help="PNG chart of the marker differences")
    args = parser.parse_args()
    comm = MPI.COMM_WORLD
    started, path, write = start_rows(args, comm)
    results = [run(path, tissue, motion, comm, args.time_step, write)
               for motion in args.motions for tissue in args.tissues]
    if comm.rank == 0:
        if args.plot:
            plot(results, args.plot, noise=0.5)
        provenance.append(args.out, started)


def start_rows(args, comm):
    """The run's provenance as it starts (rank 0; the commit and its dirty flag then, the tree may
    change while it runs), the built-in face at ``args.tets`` and a writer of result rows to
    ``args.out`` (emptied first; each row also printed)."""
    started = provenance.entry(provenance.this_command(comm.size), [args.tets], comm.size) if comm.rank == 0 else None
    path = build_builtin_face(target_tets=args.tets, comm=comm)
    if comm.rank == 0:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text("")

    def write(row):
        if comm.rank == 0:
            with args.out.open("a") as stream:
                stream.write(json.dumps(row) + "\n")
            print(json.dumps(row), flush=True)
    return started, path, write


if __name__ == "__main__":
    main()
