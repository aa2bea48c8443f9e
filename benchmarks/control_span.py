"""What a model's controls can reach on a real take, and what its markers allow any model to predict.

Reads a finished fit of a real take (the folder of ``run.py fit`` or ``benchmarks/real_capture.py``)
and measures, with the fit's own accuracy measures (the fraction of the markers' non-rigid motion
explained, for the fitted and the validation markers; ``docs/accuracy.md``):

  fit           the nonlinear fit itself (from the folder);
  span          every frame matched by the model's controls linearised at rest (the marker Jacobian of
                the activations, the three TMJ values and, with ``--pressure``, the intraoral
                pressure), the head's rigid motion refitted with them: ``bounded`` as the fit bounds
                them, ``unbounded`` (activations of either sign and any size, any jaw pose): the most
                a model whose motions are these directions explains, whatever the activations;
  neighbours    the validation markers predicted from the fitted markers alone, by interpolating the
                fitted markers' non-rigid displacement over the neutral face (radial basis functions
                of the neutral positions, no model): what the marker layout lets a smooth model
                predict.

If the unbounded span falls short of a target, no activation or jaw pose of the model reaches it; if
the neighbours reach it, the markers allow it and the model's motions are what lacks.

    python benchmarks/control_span.py FIT_FOLDER --units cm [--pressure] [--results FILE]

Serial (the model is small; the fit folder holds everything else). One JSON line per variant, also
appended to ``--results`` with its provenance.
"""
import argparse
import json
import pathlib
import sys

from mpi4py import MPI
import numpy as np
from scipy.interpolate import RBFInterpolator
from scipy.optimize import lsq_linear

from face_dolfinx.alignment.placement import place_on_model
from face_dolfinx.alignment.similarity import similarity_transform
from face_dolfinx.capture import read_capture
from face_dolfinx.fitting import FitSettings, MarkerSet
from face_dolfinx.model.bones import AffineMap, jaw_pose, tmj_upper_limits
from face_dolfinx.model.folder import load_model
from face_dolfinx.physics.problem import FaceProblem
from face_dolfinx.results.accuracy import MotionMeasures, rigid_motions
from face_dolfinx.results.folder import FitFolder
from face_dolfinx.sensitivities.columns import EquilibriumSensitivity, bone_position_derivatives

ALTERNATIONS = 6      # head motion <-> controls rounds per frame (the last changes < 0.01 mm)
TMJ_STEP = 1e-6       # central-difference step of the jaw pose (rad, mm)
RBF_KERNELS = ("linear", "thin_plate_spline")


def marker_columns(model, placement, pressure: bool):
    """Markers at rest (markers, 3), the marker Jacobian at rest (controls, markers, 3) and the
    controls' bounds as the exact-mode fit has them."""
    problem = FaceProblem(model, intraoral_pressure=pressure)
    markers = MarkerSet(problem, placement.surface_points, placement.offsets)
    sensitivity = EquilibriumSensitivity(problem)
    sensitivity.factor()
    pose = lambda p: (AffineMap(), jaw_pose(model.jaw, *p))  # noqa: E731
    columns = [sensitivity.activation_columns(),
               sensitivity.boundary_columns(bone_position_derivatives(problem, pose, np.zeros(3), TMJ_STEP))]
    n = problem.num_muscles
    lower, upper = [0.0] * n + [0.0, 0.0, 0.0], [1.0] * n + list(tmj_upper_limits(model.jaw))
    if pressure:
        columns.append(sensitivity.pressure_columns())
        limit = FitSettings().pressure_limit
        lower.append(-limit)
        upper.append(limit)
    jacobian = markers.evaluator.values_many(np.concatenate(columns))
    rest = markers.positions(problem.u.x.array, AffineMap())
    return rest, jacobian, np.array(lower), np.array(upper)


def span_prediction(rest, jacobian, captured, fitted, bounds=None) -> np.ndarray:
    """Per frame, the best linear combination of the columns (within ``bounds`` if given) and rigid
    head motion, found by alternating the two; the predicted markers (frames, markers, 3)."""
    predicted = np.full(captured.shape, np.nan)
    A_all = jacobian.transpose(1, 2, 0)  # (markers, 3, controls)
    for frame, markers in enumerate(captured):
        use = fitted & np.all(np.isfinite(markers), axis=1)
        controls = np.zeros(len(jacobian))
        for _ in range(ALTERNATIONS):
            moved = rest + np.tensordot(controls, jacobian, axes=1)
            head = similarity_transform(moved[use], markers[use], allow_scale=False)
            in_head = (markers - head.translation) @ head.rotation  # the inverse rigid motion
            A = A_all[use].reshape(-1, len(jacobian))
            b = (in_head[use] - rest[use]).reshape(-1)
            controls = (lsq_linear(A, b, bounds=bounds, method="bvls").x if bounds is not None
                        else np.linalg.lstsq(A, b, rcond=None)[0])
        predicted[frame] = head.apply(rest + np.tensordot(controls, jacobian, axes=1))
    return predicted


def neighbour_prediction(neutral, captured, fitted, kernel: str) -> np.ndarray:
    """Every marker predicted from the fitted markers' non-rigid displacement, interpolated over
    the neutral positions by an RBF, carried by the frame's rigid head motion."""
    predicted = np.full(captured.shape, np.nan)
    for frame, (markers, head) in enumerate(zip(captured, rigid_motions(neutral, captured))):
        if head is None:
            continue
        displacement = (markers - head.translation) @ head.rotation - neutral
        use = fitted & np.all(np.isfinite(displacement), axis=1)
        interpolant = RBFInterpolator(neutral[use], displacement[use], kernel=kernel, smoothing=1.0)
        predicted[frame] = head.apply(neutral + interpolant(neutral))
    return predicted


def scores(neutral, captured, predicted, roles, names, reported) -> dict:
    """The accuracy of ``predicted`` for the ``reported`` roles and per validation marker."""
    measures = MotionMeasures.of(neutral, captured, predicted)
    result = {role: {key: round(value, 4) for key, value in measures.pooled(roles == role).items()}
              for role in reported if (roles == role).any()}
    per_marker = measures.per_marker()["explained"]
    result["validation_markers"] = {names[i]: round(float(per_marker[i]), 3) for i in np.flatnonzero(roles == "validation")}
    return result


def main(argv=None) -> list[dict]:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("fit_folder")
    parser.add_argument("--units", default="mm", help="the capture's units, as given to the fit")
    parser.add_argument("--pressure", action="store_true", help="add the intraoral pressure column")
    parser.add_argument("--results", default="benchmarks/results/real_capture/control_span.jsonl")
    args = parser.parse_args(argv)
    if MPI.COMM_WORLD.size > 1:
        raise SystemExit("control_span.py runs serially")

    folder = FitFolder(args.fit_folder)
    run = folder.settings
    model = load_model(run["model"], MPI.COMM_WORLD)
    capture = read_capture(run["capture"], units=args.units)
    placement = place_on_model(model, capture, run["neutral_frame"], run.get("correspondence"), True)
    frames = sorted(folder.finished_frames())
    captured = np.array([folder.frame_markers(frame)[0] for frame in frames])
    simulated = np.array([folder.frame_markers(frame)[1] for frame in frames])
    roles, names = np.array(folder.marker_roles), folder.marker_names
    fitted = roles == "fitted"
    neutral = folder.neutral_markers

    rest, jacobian, lower, upper = marker_columns(model, placement, args.pressure)
    controls = "muscles+jaw" + ("+pressure" if args.pressure else "")
    variants = [("fit", "nonlinear fit", simulated)]
    variants += [("span", f"{controls} bounded", span_prediction(rest, jacobian, captured, fitted, (lower, upper))),
                 ("span", f"{controls} unbounded", span_prediction(rest, jacobian, captured, fitted))]
    variants += [("neighbours", f"rbf {kernel}", neighbour_prediction(neutral, captured, fitted, kernel))
                 for kernel in RBF_KERNELS]
    rows = []
    for kind, name, predicted in variants:
        # The neighbours interpolate the fitted markers: only the validation markers test them.
        reported = ("validation",) if kind == "neighbours" else ("fitted", "validation")
        row = dict(fit_folder=str(folder.path), model=run["model"], frames=len(frames), kind=kind, variant=name,
                   **scores(neutral, captured, predicted, roles, names, reported))
        print(json.dumps(row), flush=True)
        rows.append(row)
    results = pathlib.Path(args.results)
    results.parent.mkdir(parents=True, exist_ok=True)
    with open(results, "a") as file:
        file.writelines(json.dumps(row) + "\n" for row in rows)
    sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
    from provenance import record as provenance
    provenance(results, ranks=1)
    return rows


if __name__ == "__main__":
    main()
