"""Tracking a whole take: 1 rank against 2, one sequential pass against frame-parallel chunks.

Runs ``run.py fit`` on one synthetic take (speech, 60 Hz, 0.5 mm noise, head motion) of the
built-in face in each layout below, one after the other, and prints the wall time per frame
(everything included: set-up, the cold first frame of each chunk, writing), its ratio to the
first layout, the marker RMS and the activation error against the truth:

  1 rank              mpirun -n 1 run.py fit ...
  2 ranks             mpirun -n 2 run.py fit ...                one pass, the mesh split in two
  2 ranks, 2 chunks   mpirun -n 2 run.py fit ... --chunks 2     each rank fits half the take alone

A chunk's first frame starts from rest, not from the previous frame: it costs the first-frame
Gauss-Newton steps and its fit can differ from the one-pass fit there.

    python benchmarks/ranks_and_chunks.py --tets 20000 --frames 120 --fit-options="--reuse-factorization --fresh-jacobians 1"
"""
import argparse
import csv
import json
import os
import pathlib
import shlex
import subprocess
import sys
import time

ROOT = pathlib.Path(__file__).resolve().parent.parent
LAYOUTS = {"1 rank": (1, 1), "2 ranks": (2, 1), "2 ranks, 2 chunks": (2, 2)}


def run(command: list[str]) -> float:
    began = time.perf_counter()
    subprocess.run(command, check=True, cwd=ROOT, stdout=subprocess.DEVNULL)
    return time.perf_counter() - began


def frame_errors(folder: pathlib.Path) -> tuple[float, float]:
    """Marker RMS over the take and the largest activation error against the truth."""
    with open(folder / "frames.csv") as table:
        rows = [row for row in csv.DictReader(table)]
    rms = (sum(float(r["rms_error_mm"]) ** 2 for r in rows) / len(rows)) ** 0.5
    return rms, max(float(r["activation_error_max"]) for r in rows)


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--tets", type=int, default=20_000)
    parser.add_argument("--frames", type=int, default=120, help="frames of the take (all are fitted)")
    parser.add_argument("--fit-options", default="", help="extra options for run.py fit")
    parser.add_argument("--out", default="runs/ranks_and_chunks", help="folder for the take and the fits")
    parser.add_argument("--layouts", nargs="+", default=list(LAYOUTS), choices=tuple(LAYOUTS))
    args = parser.parse_args()
    out = ROOT / args.out
    python = [sys.executable, str(ROOT / "run.py")]
    take = out / f"take_{args.tets}_{args.frames}.trc"
    if not take.exists():
        run(python + ["synth", "--tets", str(args.tets), "--frames", str(args.frames),
                      "--noise", "0.5", "--out", str(take)])
    rows = []
    for name in args.layouts:
        ranks, chunks = LAYOUTS[name]
        folder = out / f"fit_{args.tets}_{args.frames}_{ranks}r{chunks}c"
        command = ["mpirun", "-n", str(ranks)] + python + [
            "fit", str(take), "--tets", str(args.tets), "--chunks", str(chunks), "--out", str(folder),
            "--overwrite", *shlex.split(args.fit_options)]
        seconds = run(command)
        rms, activation_error = frame_errors(folder)
        rows.append(dict(layout=name, ranks=ranks, chunks=chunks, tets=args.tets, frames=args.frames,
                         fit_options=args.fit_options, wall_s=round(seconds, 1),
                         s_per_frame=round(seconds / args.frames, 3), marker_rms_mm=round(rms, 3),
                         activation_error_max=round(activation_error, 3)))
        print(json.dumps(rows[-1]), flush=True)
    print(f"\n{args.frames} frames, {args.tets} tets, fit options: {args.fit_options or '(defaults)'}")
    print("| layout | wall s | s / frame | ratio to first | marker RMS mm | max activation error |")
    print("|---|---|---|---|---|---|")
    for row in rows:
        print(f"| {row['layout']} | {row['wall_s']} | {row['s_per_frame']} | "
              f"{row['s_per_frame'] / rows[0]['s_per_frame']:.2f} | {row['marker_rms_mm']} | "
              f"{row['activation_error_max']} |")


if __name__ == "__main__":
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    main()
