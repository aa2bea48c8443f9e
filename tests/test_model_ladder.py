"""The model ladder's bookkeeping (``benchmarks/model_ladder.py``) without any solve: failed
rungs are rows that the tables and charts carry, the Pareto front, the variants' shape."""
import importlib.util
import math
import json
import pathlib

import numpy as np
import pytest

PATH = pathlib.Path(__file__).resolve().parents[1] / "benchmarks" / "model_ladder.py"
spec = importlib.util.spec_from_file_location("model_ladder", PATH)
ladder = importlib.util.module_from_spec(spec)
spec.loader.exec_module(ladder)


def row(method, scenario, seconds, marker, activation, failure="", tets=5000, truth_tets=20000, ranks=1):
    n = len(seconds)
    return dict(method=method, tets=tets, scenario=scenario, truth_tets=truth_tets, ranks=ranks, noise=0.5, frames=n,
                build_seconds=1.0, failure=failure, seconds=seconds, marker_rms=[marker] * n,
                lip_rms=[marker] * n, activation_rms=[activation] * n, activation_max=[2 * activation] * n,
                jaw_opening_error_deg=[0.1] * n, flagged=0, factorizations=[3] * n)


def test_variants_have_settings_petsc_and_problem_options():
    for name, entry in ladder.VARIANTS.items():
        settings, petsc, problem = entry
        assert all(isinstance(part, dict) for part in entry), name
    assert ladder.VARIANTS["reuse"][2] == dict(reuse_factorization=True)


def test_pareto_front():
    points = np.array([[1.0, 3.0], [2.0, 1.0], [3.0, 2.0], [0.5, 5.0], [4.0, 0.5]])
    assert list(ladder.pareto_front(points)) == [3, 0, 1, 4]


def test_failed_rungs_are_kept(tmp_path):
    rows = [row("fe", "speech", [9.0, 1.0, 3.0], 0.4, 0.05),
            row("fe", "jaw", [9.0], 0.6, 0.1, failure="frame 1: EquilibriumError: no"),
            row("fe-gn1", "speech", [], 0.0, 0.0, failure="frame 0: EquilibriumError: no"),
            row("choe-ko", "speech", [0.01, 0.01], 1.5, 0.3)]
    path = tmp_path / "ladder.jsonl"
    path.write_text("".join(json.dumps(r) + "\n" for r in rows))
    table = {e["method"]: e for e in ladder.aggregate(ladder.load_rows([path]))}
    assert table["fe"]["seconds"] == (1.0 + 3.0 + 9.0) / 3  # warm frames; a 1-frame take's only frame
    assert table["fe"]["failed"] and table["fe"]["scenarios"] == 2
    assert math.isnan(table["fe-gn1"]["seconds"]) and table["fe-gn1"]["frames"] == 0
    text = ladder.collect([path])
    assert "fe-gn1" in text and "FAILED after 1 frames" in text
    written = ladder.plot([path], str(tmp_path / "img" / "ladder"))
    assert all(p.exists() for p in written)


def test_rungs_on_different_ranks_are_apart_and_truths_do_not_mix(tmp_path):
    path = tmp_path / "ladder.jsonl"
    rows = [row("fe", "speech", [9.0, 1.0], 0.4, 0.05), row("fe", "speech", [5.0, 0.6], 0.4, 0.05, ranks=2)]
    path.write_text("".join(json.dumps(r) + "\n" for r in rows))
    seconds = {e["ranks"]: e["seconds"] for e in ladder.aggregate(ladder.load_rows([path]))}
    assert seconds == {1: 1.0, 2: 0.6}
    other = tmp_path / "other.jsonl"
    other.write_text(json.dumps(row("fe", "jaw", [9.0, 1.0], 0.4, 0.05, truth_tets=404124)) + "\n")
    with pytest.raises(SystemExit, match="different truths"):
        ladder.collect([path, other])
