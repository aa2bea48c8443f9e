"""A take's neutral frame chosen as its most typical frame (``alignment.neutral``; ``--neutral-frame
typical``): a take that starts with an expression gets a frame at rest, whatever the head does."""
import pathlib

from mpi4py import MPI
import numpy as np
import pytest

from face_dolfinx.alignment.neutral import typical_frame
from face_dolfinx.alignment.similarity import AlignmentError
from face_dolfinx.capture import Capture
from face_dolfinx.cli.main import parse_arguments
from face_dolfinx.model.bones import rigid_map, rotation

FRAMES = 12


def take_starting_with_an_expression(rng) -> tuple[Capture, np.ndarray]:
    """30 markers; frames 0-2 with the lower lip 6 mm forward, the rest at rest with noise, and
    the head turning and moving throughout. Returns the capture and the expression's frames."""
    rest = rng.uniform(-60.0, 60.0, size=(30, 3))
    lip = np.arange(5)
    frames = []
    for frame in range(FRAMES):
        shape = rest + rng.normal(scale=0.2, size=rest.shape)
        if frame < 3:
            shape[lip, 2] += 6.0
        head = rigid_map(rotation(rng.normal(size=3), 0.2 * rng.uniform()), rng.normal(scale=30.0, size=3), np.zeros(3))
        frames.append(head.apply(shape))
    return Capture([f"m{i}" for i in range(30)], np.array(frames), 60.0), np.arange(3)


def test_the_typical_frame_is_at_rest_whatever_the_head_does():
    capture, expression = take_starting_with_an_expression(np.random.default_rng(4))
    typical = typical_frame(capture)
    assert typical.frame not in expression
    assert typical.rms_mm < 0.5                 # the noise (0.35 mm RMS in 3D), not the expression
    assert typical.first_frame_rms_mm > 1.0     # frame 0's lip: 6 mm on 5 of 30 markers


def test_frames_with_gaps_are_not_chosen_and_a_take_without_a_complete_frame_is_refused():
    capture, _ = take_starting_with_an_expression(np.random.default_rng(5))
    chosen = typical_frame(capture).frame
    positions = capture.positions.copy()
    positions[chosen, 7] = np.nan
    gappy = Capture(capture.marker_names, positions, 60.0)
    again = typical_frame(gappy)
    assert again.frame != chosen and again.frame >= 3
    positions[:, 7] = np.nan
    with pytest.raises(AlignmentError, match="no frame has every marker"):
        typical_frame(Capture(capture.marker_names, positions, 60.0))


def test_the_option_takes_a_number_or_typical(tmp_path):
    for command in (["fit", "take.trc"], ["build"]):
        assert parse_arguments([*command, "--neutral-frame", "typical"])[0].neutral_frame == "typical"
        assert parse_arguments([*command, "--neutral-frame", "-1"])[0].neutral_frame == -1
        with pytest.raises(SystemExit):
            parse_arguments([*command, "--neutral-frame", "rest"])
    folder = pathlib.Path(MPI.COMM_WORLD.bcast(str(tmp_path), root=0))
    config = folder / "run.toml"
    if MPI.COMM_WORLD.rank == 0:
        config.write_text('[fit]\ncapture = "take.trc"\nneutral-frame = "typical"\n[build]\nneutral-frame = 7\n')
    MPI.COMM_WORLD.barrier()
    assert parse_arguments(["fit", "--config", str(config)])[0].neutral_frame == "typical"
    assert parse_arguments(["build", "--config", str(config)])[0].neutral_frame == 7
