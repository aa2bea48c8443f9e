"""Freeze the small built-in face into ``meshes/small_face/``: the face every test runs on.

The generator's mesh depends on the CPU it runs on (docs/builtin_face.md, "Known weaknesses": the
same description and code gave 5 064 tets on one machine and 5 136 on another), and the contact
tests' Newton paths depend on the mesh. So the tests load this committed copy rather than build the
face. Run this after a change to ``meshes/builtin_face.toml`` or to the generator (a test in
tests/test_anatomy.py fails while the copy is stale), from the repository root::

    python meshes/freeze_small_face.py

It builds the face at SMALL_FACE_TETS (through the cache), replaces ``meshes/small_face/`` with it
and writes ``provenance.json`` there: the generator's cache key, the commit, the command, the
machine (with whether its CPU has AVX-512, which numpy's kernels use where present).
"""
import json
import pathlib
import shutil
import sys

from mpi4py import MPI

ROOT = pathlib.Path(__file__).resolve().parent.parent
SMALL_FACE = ROOT / "meshes" / "small_face"
SMALL_FACE_TETS = 5000
sys.path.insert(0, str(ROOT / "benchmarks"))

import provenance  # noqa: E402  (benchmarks/provenance.py: commit, machine)
from face_dolfinx.model.anatomy import build_builtin_face  # noqa: E402


def cpu_has_avx512() -> bool:
    try:
        return " avx512f" in pathlib.Path("/proc/cpuinfo").read_text()
    except OSError:
        return False


def main() -> None:
    built = build_builtin_face(target_tets=SMALL_FACE_TETS, comm=MPI.COMM_SELF)
    if SMALL_FACE.exists():
        shutil.rmtree(SMALL_FACE)
    shutil.copytree(built, SMALL_FACE)
    record = provenance.entry(provenance.this_command(1), SMALL_FACE_TETS, 1, avx512=cpu_has_avx512())
    (SMALL_FACE / "provenance.json").write_text(json.dumps(dict(cache_key=built.name, **record), indent=1) + "\n")
    print(f"{built} -> {SMALL_FACE}")


if __name__ == "__main__":
    main()
