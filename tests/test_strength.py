"""Exaggeration by muscle strength (sifakis2005 section 9, figure 8): a model-level scale of the
peak stress, i.e. of the force-length curve, that simulate, synth and fit honour; activations stay
in [0, 1]."""
import json
import pathlib

from mpi4py import MPI
import numpy as np
import pytest

from face_dolfinx.cli.main import main, parse_arguments
from face_dolfinx.model.folder import ModelError
from face_dolfinx.physics.problem import FaceProblem

MUSCLE = "zygomaticus_major_left"


def test_strength_scales_the_muscle_s_whole_fiber_law(model):
    """The fiber tension is sigma_max * rho * (a f_L + f_P): strength s scales the active and the
    passive curve of that muscle alone (the paper's "overall anisotropic behavior"), so s at
    activation a is close to, but not exactly, the plain face at activation s a."""
    index = model.muscle_index(MUSCLE)
    strong = FaceProblem(model.with_strength({MUSCLE: 2.0}))
    plain = FaceProblem(model)
    assert strong.peak_stress(index) == 2.0 * plain.peak_stress(index)
    assert all(strong.peak_stress(i) == plain.peak_stress(i) for i in range(len(model.muscles)) if i != index)
    for k, (weight, plain_weight) in enumerate(zip(strong.slots.weight, plain.slots.weight)):
        mine = strong.slots.muscle_of_slot[k] == index
        assert np.array_equal(weight.x.array[mine], 2.0 * plain_weight.x.array[mine])
        assert np.array_equal(weight.x.array[~mine], plain_weight.x.array[~mine])
    activations = np.zeros(len(model.muscles))
    activations[index] = 0.3
    strong.solve(activations=activations)
    activations[index] = 0.6
    plain.solve(activations=activations)
    scale = MPI.COMM_WORLD.allreduce(np.abs(plain.u.x.array).max(), op=MPI.MAX)
    difference = MPI.COMM_WORLD.allreduce(np.abs(strong.u.x.array - plain.u.x.array).max(), op=MPI.MAX)
    assert scale > 1.0
    assert 1e-6 * scale < difference < 1e-2 * scale  # the passive part, stretched little, differs


def test_exaggeration_goes_beyond_full_activation(model):
    """At activation 1, 1.5 times the strength moves the mouth corner further than any activation can."""
    corner = model.markers["mouth_corner_left"]
    moved = []
    for scales in ({}, {"all": 1.5}):
        problem = FaceProblem(model.with_strength(scales) if scales else model)
        problem.solve(activations={MUSCLE: 1.0})
        nodes = problem.dof_coordinates
        nearest = np.argmin(np.linalg.norm(nodes - corner, axis=1))
        moved.append(np.linalg.norm(problem.u.x.array.reshape(-1, 3)[nearest]))
    moved = MPI.COMM_WORLD.allgather(moved)  # any rank's nearest node will do; all report
    assert all(exaggerated > plain * 1.1 for plain, exaggerated in moved if plain > 1.0)
    assert any(plain > 1.0 for plain, _ in moved)


def test_strength_option_and_its_mistakes(model, tmp_path):
    args, _ = parse_arguments(["simulate", "smile", "--strength", "1.5, mentalis_left=2,mentalis_left=1.5"])
    assert args.strength == {"all": 1.5, "mentalis_left": 3.0}
    config = pathlib.Path(MPI.COMM_WORLD.bcast(str(tmp_path), root=0)) / "run.toml"
    if MPI.COMM_WORLD.rank == 0:
        config.write_text("[simulate]\nstrength = 1.5\n")
    MPI.COMM_WORLD.barrier()
    assert parse_arguments(["simulate", "smile", "--config", str(config)])[0].strength == {"all": 1.5}
    for bad in ("0", "-1", "mentalis_left=x", ","):
        with pytest.raises(SystemExit):
            parse_arguments(["simulate", "smile", "--strength", bad])
    with pytest.raises(ModelError, match="unknown muscle 'zygomaticus_major_lft'.*zygomaticus_major_left"):
        model.with_strength({"zygomaticus_major_lft": 2.0})


def test_fit_records_the_strength(builtin_model_path, tmp_path):
    folder = pathlib.Path(MPI.COMM_WORLD.bcast(str(tmp_path), root=0))
    model = ["--model", str(builtin_model_path)]
    take = folder / "take.trc"
    assert main(["synth", *model, "--frames", "2", "--noise", "0", "--strength", "1.2", "--out", str(take)]) == 0
    assert main(["fit", str(take), *model, "--strength", "1.2", "--out", str(folder / "fit")]) == 0
    run = json.loads((folder / "fit" / "run.json").read_text())
    assert run["strength"] == {"all": 1.2}
    rows = (folder / "fit" / "frames.csv").read_text().splitlines()
    assert max(float(row.split(",")[1]) for row in rows[1:]) < 0.05  # the same model: markers reached
