"""Provenance of benchmark results: a manifest beside every result file.

Each folder of ``benchmarks/results/`` holds a ``manifest.json`` that maps every result file in
it to the runs that wrote it (a file that several runs append to has several entries)::

    {"ladder_truth20k.jsonl": [{"commit": "2a2d63d...", "dirty": false,
                                "command": "python benchmarks/model_ladder.py --tets 5000 ...",
                                "machine": {"hostname": ..., "cpu": ..., "cores": 2, "memory_gb": 24.0},
                                "date": "2026-11-23T23:30:00+00:00", "tets": [5000], "ranks": 1}]}

``dirty`` says whether tracked files differed from ``commit`` when the run started, so a result of
uncommitted code is never mistaken for one of the commit. A benchmark that writes its own file
calls ``record(path, tets=..., ranks=...)`` once the file is written (on rank 0 only; under MPI
the other ranks return). Commands that print their results are run through this module, which
writes their standard output to the result file and records the command::

    python benchmarks/provenance.py run --out benchmarks/results/forward/x.jsonl --json-lines -- \\
        mpirun -n 2 python benchmarks/forward_scaling.py --tets 5000 20000
    python benchmarks/provenance.py record FILE... --command "..." [--tets N...] [--ranks N]
    python benchmarks/provenance.py start FILE    # empty FILE and drop its entries before runs append to it

``tets`` are the resolutions asked for (``--tets``; the built face's exact count is in the
result rows), ``ranks`` the MPI processes of the run.
"""
import argparse
import datetime
import json
import os
import pathlib
import platform
import shlex
import subprocess
import sys

ROOT = pathlib.Path(__file__).resolve().parent.parent
MANIFEST = "manifest.json"


def git_commit() -> tuple[str, bool | None]:
    """The checked-out commit and whether tracked files other than the manifests differ from it
    ("unknown", None outside git): a run that writes two files records the second after its
    manifest took the first."""
    def git(*args):
        return subprocess.run(["git", *args], cwd=ROOT, capture_output=True, text=True, check=True).stdout.strip()
    try:
        return git("rev-parse", "HEAD"), bool(git("status", "--porcelain", "--untracked-files=no", "--", ".",
                                                  f":(exclude,glob)**/{MANIFEST}"))
    except (OSError, subprocess.CalledProcessError):
        return "unknown", None


def machine() -> dict:
    """Host name, CPU model, logical cores and memory of this machine."""
    cpu = platform.processor() or "unknown"
    try:
        for line in pathlib.Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    try:
        memory_gb = round(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 1024**3, 1)
    except (ValueError, OSError):
        memory_gb = None
    return dict(hostname=platform.node(), cpu=cpu, cores=os.cpu_count(), memory_gb=memory_gb)


def mpi_world() -> tuple[int, int]:
    """(rank, size) of MPI's world if this process uses MPI, else (0, 1); never starts MPI itself."""
    mpi = sys.modules.get("mpi4py.MPI")
    if mpi is None or not mpi.Is_initialized():
        return 0, 1
    return mpi.COMM_WORLD.rank, mpi.COMM_WORLD.size


def this_command(ranks: int) -> str:
    """The command line of this process, as it would be typed from the repository root."""
    launcher = f"mpirun -n {ranks} " if ranks > 1 else ""
    return launcher + shlex.join(["python", *sys.argv])


def entry(command: str, tets, ranks: int, **extra) -> dict:
    """One manifest entry for a run of `command` started now."""
    commit, dirty = git_commit()
    tets = [int(t) for t in (tets if isinstance(tets, (list, tuple)) else [tets])] if tets is not None else []
    return dict(commit=commit, dirty=dirty, command=command, machine=machine(),
                date=datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
                tets=tets, ranks=int(ranks), **extra)


def update(path, change) -> pathlib.Path:
    """Apply `change` to the entries (a list, perhaps new) of result file `path` in the manifest
    of its folder."""
    path = pathlib.Path(path)
    manifest = path.parent / MANIFEST
    entries = json.loads(manifest.read_text()) if manifest.exists() else {}
    entries[path.name] = change(entries.get(path.name, []))
    if not entries[path.name]:
        del entries[path.name]
    temporary = manifest.with_suffix(".json.tmp")
    temporary.write_text(json.dumps(entries, indent=1) + "\n")
    os.replace(temporary, manifest)  # a reader never sees half a manifest
    return manifest


def append(path, run: dict) -> pathlib.Path:
    """Add `run` to the entries of result file `path`."""
    return update(path, lambda runs: runs + [run])


def start(path) -> None:
    """Empty result file `path` and drop its manifest entries: the runs that follow append anew."""
    path = pathlib.Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("")
    update(path, lambda runs: [])


def record(path, tets=None, ranks: int | None = None, command: str | None = None, **extra):
    """Record that this process wrote result file `path` (rank 0 writes; others return None)."""
    rank, size = mpi_world()
    if rank != 0:
        return None
    ranks = size if ranks is None else ranks
    return append(path, entry(command or this_command(ranks), tets, ranks, **extra))


def write_result(path, data, tets=None, ranks: int | None = None):
    """Rank 0 writes ``data`` to the result file ``path`` (indented JSON) and records it (``record``)."""
    if mpi_world()[0] == 0:
        out = pathlib.Path(path)
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(data, indent=1) + "\n")
    return record(path, tets=tets, ranks=ranks)


def parse_command(command: list[str]) -> tuple[list[int], int]:
    """The ``--tets`` values and the ``mpirun -n`` ranks of a command line (1 without mpirun)."""
    tets, ranks = [], 1
    for i, word in enumerate(command):
        if word in ("-n", "-np") and i > 0 and command[i - 1] in ("mpirun", "mpiexec"):
            ranks = int(command[i + 1])
        if word == "--tets":
            for value in command[i + 1:]:
                if not value.isdigit():
                    break
                tets.append(int(value))
        elif word.startswith("--tets="):
            tets.append(int(word.split("=", 1)[1]))
    return tets, ranks


def run(command: list[str], out: pathlib.Path, json_lines: bool, append_to: bool = False) -> int:
    """Run `command` with its standard output written to `out` (with `json_lines`, only the lines
    that are JSON objects; the others pass through to this process's output), then record it.
    With `append_to` the output is added to `out` and the run to its entries; otherwise both
    replace what was there."""
    run_entry = entry(shlex.join(command), *parse_command(command))  # commit and date at the start
    out.parent.mkdir(parents=True, exist_ok=True)
    with open(out, "a" if append_to else "w") as target:
        process = subprocess.Popen(command, cwd=ROOT, stdout=subprocess.PIPE, text=True)
        for line in process.stdout:
            if json_lines and not line.startswith("{"):
                sys.stdout.write(line)
                sys.stdout.flush()
            else:
                target.write(line)
                target.flush()
        code = process.wait()
    if code == 0:
        update(out, lambda runs: (runs if append_to else []) + [run_entry])
    return code


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    actions = parser.add_subparsers(dest="action", required=True)
    p = actions.add_parser("run", help="run a command, its output into a result file, and record it")
    p.add_argument("--out", type=pathlib.Path, required=True, help="result file for the command's output")
    p.add_argument("--json-lines", action="store_true", help="keep only the JSON lines of the output")
    p.add_argument("--append", action="store_true", help="add to the result file instead of replacing it")
    p.add_argument("command", nargs=argparse.REMAINDER, help="-- then the command")
    p = actions.add_parser("start", help="empty result files and drop their entries")
    p.add_argument("files", nargs="+", type=pathlib.Path)
    p = actions.add_parser("record", help="record result files that a command wrote")
    p.add_argument("files", nargs="+", type=pathlib.Path)
    p.add_argument("--command", required=True, help="the command that wrote them")
    p.add_argument("--tets", type=int, nargs="*", help="default: the command's --tets")
    p.add_argument("--ranks", type=int, help="default: the command's mpirun -n, else 1")
    args = parser.parse_args()
    if args.action == "run":
        command = args.command[1:] if args.command[:1] == ["--"] else args.command
        if not command:
            parser.error("run: give the command after --")
        sys.exit(run(command, args.out, args.json_lines, args.append))
    if args.action == "start":
        for path in args.files:
            start(path)
        return
    tets, ranks = parse_command(shlex.split(args.command))
    run_entry = entry(args.command, tets if args.tets is None else args.tets,
                      ranks if args.ranks is None else args.ranks)
    for path in args.files:
        append(path, run_entry)


if __name__ == "__main__":
    main()
