"""The command line: results appear whole or not at all, and earlier results are not overwritten."""
import json
import pathlib

from mpi4py import MPI
import pytest

from face_dolfinx.cli import main


@pytest.fixture
def shared_tmp(tmp_path):
    """One temporary folder for all ranks (each rank's tmp_path differs under mpirun)."""
    return pathlib.Path(MPI.COMM_WORLD.bcast(str(tmp_path), root=0))


def test_simulate_writes_a_complete_result(builtin_model_path, shared_tmp):
    out = shared_tmp / "smile"
    assert main(["simulate", "smile", "--model", str(builtin_model_path), "--out", str(out)]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert [row["expression"] for row in summary["expressions"]] == ["smile"]
    assert summary["expressions"][0]["max_displacement_mm"] > 1.0
    assert (out / "face.xdmf").exists() and (out / "face.h5").exists()
    assert (out / "01_smile.png").stat().st_size > 10_000
    # A second run must not silently replace the first.
    with pytest.raises(FileExistsError, match="--overwrite"):
        main(["simulate", "frown", "--model", str(builtin_model_path), "--out", str(out)])
    assert main(["simulate", "frown", "--model", str(builtin_model_path), "--out", str(out),
                 "--overwrite", "--no-render"]) == 0
    assert json.loads((out / "summary.json").read_text())["expressions"][0]["expression"] == "frown"


def test_failed_run_leaves_nothing_that_looks_like_a_result(builtin_model_path, shared_tmp):
    out = shared_tmp / "broken"
    with pytest.raises(SystemExit, match="unknown expression 'grin'"):
        main(["simulate", "smile", "grin", "--model", str(builtin_model_path), "--out", str(out),
              "--no-render"])
    MPI.COMM_WORLD.barrier()
    assert not out.exists()
    assert not [p for p in shared_tmp.iterdir() if p.name.startswith(".broken")]
