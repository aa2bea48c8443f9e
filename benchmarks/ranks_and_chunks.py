"""Tracking a whole take: 1 rank against 2, one sequential pass against frame-parallel chunks.

Runs ``run.py fit`` on one synthetic take (speech, 60 Hz, 0.5 mm noise, head motion; optionally
a stretch of a longer take, which moves at capture speed) of the built-in face in each layout
below, one after the other, and prints the wall time per frame (everything included: set-up, the
cold first frame of each chunk, writing), its ratio to the first layout, the fit's own seconds of
the frames fitted from rest and of the warm-started ones, the marker RMS, the activation error
against the truth and the peak memory of the largest process:

  1 rank              mpirun -n 1 run.py fit ...
  2 ranks             mpirun -n 2 run.py fit ...                one pass, the mesh split in two
  2 ranks, 2 chunks   mpirun -n 2 run.py fit ... --chunks 2     each rank fits half the take alone

A chunk's first frame starts from rest, not from the previous frame: it costs the first-frame
Gauss-Newton steps and its fit can differ from the one-pass fit there.

    python benchmarks/ranks_and_chunks.py --tets 20000 --frames 120 --fit-options="--reuse-factorization --fresh-jacobians 1"
    python benchmarks/ranks_and_chunks.py --tets 400000 --frames 16 --take-frames 240 --first-frame 80 --fit-options=--fast
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


def run(command: list[str], log: pathlib.Path) -> tuple[float, float]:
    """Wall seconds of a command, and the peak resident memory (GB) of its largest process (a
    rank: mpirun reaps its ranks, so their usage reaches us through it). Its output goes to `log`;
    a failure ends the benchmark with the end of that log."""
    began = time.perf_counter()
    with open(log, "w") as output:
        process = subprocess.Popen(command, cwd=ROOT, stdout=output, stderr=subprocess.STDOUT)
        _, status, usage = os.wait4(process.pid, 0)
    code = os.waitstatus_to_exitcode(status)
    if code != 0:
        tail = "".join(log.read_text().splitlines(keepends=True)[-30:])
        raise SystemExit(f"{shlex.join(command)}\nexited with {code}; the end of {log}:\n{tail}")
    return time.perf_counter() - began, usage.ru_maxrss / 1024**2


def frame_errors(folder: pathlib.Path) -> tuple[float, float]:
    """Marker RMS over the take and the largest activation error against the truth."""
    with open(folder / "frames.csv") as table:
        rows = [row for row in csv.DictReader(table)]
    rms = (sum(float(r["rms_error_mm"]) ** 2 for r in rows) / len(rows)) ** 0.5
    return rms, max(float(r["activation_error_max"]) for r in rows)


def frame_seconds(folder: pathlib.Path, chunks: int) -> tuple[float, float]:
    """Mean seconds of the frames fitted from rest (each chunk's first) and of the warm-started rest."""
    # Not face_dolfinx.fitting.fitter: it initialises MPI, and Open MPI's mpirun fails without a word when
    # started from a process that has.
    from face_dolfinx.capture import chunk_ranges
    with open(folder / "timings.csv") as table:
        seconds = {int(r["frame"]): float(r["seconds"]) for r in csv.DictReader(table)}
    cold = {chunk.start for chunk in chunk_ranges(len(seconds), chunks)}

    def mean(values):
        return sum(values) / len(values) if values else float("nan")
    return (mean([s for f, s in seconds.items() if f in cold]),
            mean([s for f, s in seconds.items() if f not in cold]))


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--tets", type=int, default=20_000)
    parser.add_argument("--frames", type=int, default=120, help="frames of the take (all are fitted)")
    parser.add_argument("--take-frames", type=int,
                        help="synthesise --frames frames of a take this long (default: --frames), so that a "
                             "short take moves at capture speed (run.py synth --take-frames)")
    parser.add_argument("--first-frame", type=int, default=0, help="with --take-frames: first frame of the stretch")
    parser.add_argument("--fit-options", default="", help="extra options for run.py fit")
    parser.add_argument("--out", default="runs/ranks_and_chunks", help="folder for the take and the fits")
    parser.add_argument("--layouts", nargs="+", default=list(LAYOUTS), choices=tuple(LAYOUTS))
    args = parser.parse_args()
    out = ROOT / args.out
    out.mkdir(parents=True, exist_ok=True)
    python = [sys.executable, str(ROOT / "run.py")]
    take_frames = args.take_frames or args.frames
    stretch = f"_of{take_frames}from{args.first_frame}" if args.take_frames else ""
    take = out / f"take_{args.tets}_{args.frames}{stretch}.trc"
    if not take.exists():  # not timed
        run(["mpirun", "-n", "2"] + python + [
            "synth", "--tets", str(args.tets), "--frames", str(args.frames), "--take-frames", str(take_frames),
            "--first-frame", str(args.first_frame), "--noise", "0.5", "--out", str(take)],
            take.with_suffix(".log"))
    rows = []
    for name in args.layouts:
        ranks, chunks = LAYOUTS[name]
        folder = out / f"fit_{args.tets}_{args.frames}_{ranks}r{chunks}c"
        command = ["mpirun", "-n", str(ranks)] + python + [
            "fit", str(take), "--tets", str(args.tets), "--chunks", str(chunks), "--out", str(folder),
            "--overwrite", *shlex.split(args.fit_options)]
        seconds, memory = run(command, folder.with_suffix(".log"))
        rms, activation_error = frame_errors(folder)
        cold_s, warm_s = frame_seconds(folder, chunks)
        rows.append(dict(layout=name, ranks=ranks, chunks=chunks, tets=args.tets, frames=args.frames,
                         take_frames=take_frames, first_frame=args.first_frame,
                         fit_options=args.fit_options, wall_s=round(seconds, 1),
                         s_per_frame=round(seconds / args.frames, 3), first_frames_s=round(cold_s, 2),
                         warm_frame_s=round(warm_s, 2), marker_rms_mm=round(rms, 3),
                         activation_error_max=round(activation_error, 3),
                         peak_memory_gb_per_process=round(memory, 2)))
        print(json.dumps(rows[-1]), flush=True)
    print(f"\n{args.frames} frames (from {args.first_frame} of a {take_frames}-frame take), {args.tets} tets, "
          f"fit options: {args.fit_options or '(defaults)'}")
    print("| layout | wall s | s / frame | ratio to first | frames from rest s | warm frames s | marker RMS mm "
          "| max activation error | peak GB per process |")
    print("|---|---|---|---|---|---|---|---|---|")
    for row in rows:
        print(f"| {row['layout']} | {row['wall_s']} | {row['s_per_frame']} | "
              f"{row['s_per_frame'] / rows[0]['s_per_frame']:.2f} | {row['first_frames_s']} | "
              f"{row['warm_frame_s']} | {row['marker_rms_mm']} | "
              f"{row['activation_error_max']} | {row['peak_memory_gb_per_process']} |")


if __name__ == "__main__":
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    main()
