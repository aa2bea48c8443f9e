"""Building the built-in face: tets, nodes, layers, seconds, peak memory and element quality per
resolution (the table of docs/builtin_face.md, "Measured").

Each resolution is built in a process of its own with an empty cache, one rank: "first call" is
``build_builtin_face`` whole (generation, writing the folder, the check load), "generation" the
geometry alone (the folder's ``[generator] generation_seconds``), peak RSS that of the process
(DOLFINx imported). Prints one JSON line per resolution::

    python benchmarks/provenance.py run --out benchmarks/results/model/builtin_face_build.jsonl \\
        --json-lines -- python benchmarks/builtin_face_build.py --tets 5000 50000 400000 1000000
"""
import argparse
import subprocess
import sys
import tempfile

ONE_BUILD = """
import json, resource, sys, time, tomllib
from pathlib import Path
from mpi4py import MPI
from face_dolfinx.model.anatomy import build_builtin_face
target, cache = int(sys.argv[1]), sys.argv[2]
began = time.perf_counter()
folder = build_builtin_face(target_tets=target, cache_dir=cache, comm=MPI.COMM_SELF)
first_call = time.perf_counter() - began
generator = tomllib.loads((Path(folder) / "model.toml").read_text())["generator"]
print(json.dumps(dict(target_tets=target, tets=generator["tets"], nodes=generator["nodes"],
                      layers=generator["layers"], first_call_s=round(first_call, 2),
                      generation_s=generator["generation_seconds"],
                      peak_rss_gb=round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20, 3),
                      min_quality=round(generator["min_quality"], 3), mean_quality=round(generator["mean_quality"], 3),
                      cache_key=Path(folder).name)))
"""


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--tets", type=int, nargs="+", default=[5000, 50000, 400000, 1000000])
    args = parser.parse_args()
    for target in args.tets:
        with tempfile.TemporaryDirectory() as cache:
            line = subprocess.run([sys.executable, "-c", ONE_BUILD, str(target), cache], check=True,
                                  capture_output=True, text=True).stdout.strip().splitlines()[-1]
        print(line, flush=True)


if __name__ == "__main__":
    main()
