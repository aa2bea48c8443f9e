"""Accuracy of a fit on a real capture, where there is no truth: prediction of markers left out.

Fits a real take (by default the whole take) through ``run.py fit`` and reports what
``results.accuracy`` measures: per role (fitted, validation markers) the median per-frame RMS error,
the non-rigid motion (beyond the head's rigid motion) and the fraction of it the fit explains, the
markers predicted worse than by rigid motion alone, and the muscles pinned at activation 1. One
JSON line, also appended to ``--results`` with its provenance (commit, command, machine).

The targets of a usable subject fit on a real take: median per-frame RMS of the fitted markers
<= 1.0 mm; >= 85 % of the fitted and >= 75 % of the validation markers' non-rigid motion explained;
no validation marker predicted worse than by rigid motion alone. The line says which are met.

The development capture is AnimFace's NoseMoCap (41 markers, centimetres; not in this repository,
CC BY-SA 4.0): with the correspondence file beside this script, on a model adapted to the take's most
typical frame (``benchmarks/run_real_capture.sh`` runs what docs/accuracy.md cites),

    python run.py build --subject PATH/NoseMoCap_cm.csv --units cm --neutral-frame typical \\
        --correspondence benchmarks/real_capture/animface_correspondence.toml --tets 20000 --out runs/me
    mpirun -n 2 python benchmarks/real_capture.py PATH/NoseMoCap_cm.csv --units cm --model runs/me \\
        --correspondence benchmarks/real_capture/animface_correspondence.toml --neutral-frame typical \\
        --marker-setup benchmarks/real_capture/animface_markers.toml

Options it does not know (``--neutral-frame``, ``--effort``, ``--intraoral-pressure``, ...) go to the fit.
"""
import argparse
import json
import pathlib
import sys

from mpi4py import MPI

TARGETS = dict(fitted_median_frame_rms_mm=1.0, fitted_explained=0.85, validation_explained=0.75)


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("capture")
    parser.add_argument("--correspondence", required=True)
    parser.add_argument("--units", default="cm")
    parser.add_argument("--model", help="model folder (e.g. adapted to the subject); default the built-in face")
    parser.add_argument("--tets", type=int, default=20000)
    parser.add_argument("--marker-setup")
    parser.add_argument("--validation-markers", default="6")
    parser.add_argument("--frames", help="START:STOP[:STEP] of the take")
    parser.add_argument("--out", default="runs/real_capture", help="fit folder")
    parser.add_argument("--results", default="benchmarks/results/real_capture/real_capture.jsonl")
    args, fit_options = parser.parse_known_args(argv)

    from face_dolfinx.cli.main import main as run
    from face_dolfinx.results.folder import FitFolder
    model = ["--model", args.model] if args.model else ["--tets", str(args.tets)]
    command = ["fit", args.capture, *model, "--units", args.units, "--correspondence", args.correspondence,
               "--validation-markers", args.validation_markers, "--out", args.out, *fit_options]
    for option, value in (("--marker-setup", args.marker_setup), ("--frames", args.frames)):
        if value:
            command += [option, value]
    run(command)
    record = FitFolder(args.out).accuracy()
    roles = record["roles"]
    row = dict(capture=pathlib.Path(args.capture).name, model=args.model or f"builtin {args.tets}",
               fit=command[3:], ranks=MPI.COMM_WORLD.size, roles=roles, worse_than_rigid=record["worse_than_rigid"],
               pinned_muscles=record["pinned_muscles"],
               groups={name: dict(markers=g["markers"], rms_mm=g["rms_mm"], explained=g["explained"])
                       for name, g in record["groups"].items()})
    row["targets_met"] = dict(
        fitted_median_frame_rms=roles["fitted"]["median_frame_rms_mm"] <= TARGETS["fitted_median_frame_rms_mm"],
        fitted_explained=roles["fitted"]["explained"] >= TARGETS["fitted_explained"],
        validation_explained="validation" in roles and roles["validation"]["explained"] >= TARGETS["validation_explained"],
        no_validation_marker_worse_than_rigid=not record["worse_than_rigid"].get("validation"))
    if MPI.COMM_WORLD.rank == 0:
        print(json.dumps(row), flush=True)
        results = pathlib.Path(args.results)
        results.parent.mkdir(parents=True, exist_ok=True)
        with open(results, "a") as file:
            file.write(json.dumps(row) + "\n")
        sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
        from provenance import record as provenance
        provenance(results, tets=[args.tets] if not args.model else None, ranks=MPI.COMM_WORLD.size)
    return row


if __name__ == "__main__":
    main()
