"""Freeze the small built-in face into ``meshes/small_face/``: the face every test runs on.

The tests' Newton paths, iteration budgets and tolerances are tuned on this face, so they read this
committed copy rather than build it: a change of the generator or of ``meshes/builtin_face.toml``
changes their face only when the copy is rebuilt, from the repository root::

    python meshes/freeze_small_face.py

(a test in tests/test_anatomy.py fails while the copy is stale; another checks that the generator
builds it bit for bit on the machine the tests run on). It builds the face at SMALL_FACE_TETS
(through the cache), replaces ``meshes/small_face/`` with it and writes ``provenance.json`` there:
the generator's cache key, the commit, the command, the machine (with whether its CPU has
AVX-512, where numpy's own kernels differ from the C library's; docs/builtin_face.md).
"""
import json
import pathlib
import shutil
import sys

from mpi4py import MPI

ROOT = pathlib.Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "benchmarks"))

import provenance  # noqa: E402  (benchmarks/provenance.py: commit, machine)
from face_dolfinx.model.anatomy import build_builtin_face  # noqa: E402
from face_dolfinx.model.anatomy.builder import SMALL_FACE, SMALL_FACE_TETS  # noqa: E402


def cpu_has_avx512() -> bool:
    try:
        return " avx512f" in pathlib.Path("/proc/cpuinfo").read_text()
    except OSError:
        return False


def main() -> None:
    built = build_builtin_face(target_tets=SMALL_FACE_TETS, comm=MPI.COMM_SELF)
    # Before the copy replaces the committed one: "dirty" then says whether the code was.
    record = provenance.entry(provenance.this_command(1), SMALL_FACE_TETS, 1, avx512=cpu_has_avx512())
    if SMALL_FACE.exists():
        shutil.rmtree(SMALL_FACE)
    shutil.copytree(built, SMALL_FACE)
    (SMALL_FACE / "provenance.json").write_text(json.dumps(dict(cache_key=built.name, **record), indent=1) + "\n")
    print(f"{built} -> {SMALL_FACE}")


if __name__ == "__main__":
    main()
