# # Tracking a take from a Python script
#
# This example drives face_dolfinx from Python, through the same tracking loop as
# `run.py fit`: it builds the built-in face, synthesises a short speech-like take whose truth is
# known, tracks it into a results folder and prints how well the fit recovered the markers and
# the muscle activations. It runs serially and in parallel:
#
# ```sh
# python examples/track_a_take.py
# mpirun -n 2 python examples/track_a_take.py --tets 20000 --frames 10
# ```
#
# The test suite runs it on a small face (`tests/test_examples.py`) and checks the numbers it
# returns.

import argparse
import pathlib

from mpi4py import MPI
import numpy as np

from face_dolfinx.alignment.placement import place_on_model
from face_dolfinx.capture.synthetic import save_truth, synthesize_take
from face_dolfinx.fitting import MarkerSet
from face_dolfinx.model.anatomy import build_builtin_face
from face_dolfinx.model.folder import load_model
from face_dolfinx.physics.problem import FaceProblem
from face_dolfinx.tracking import PRESETS, Tracker


def main(tets: int = 5000, frames: int = 6, out="results/example", preset: str = "default",
         noise: float = 0.5) -> dict:
    comm = MPI.COMM_WORLD
    out = pathlib.Path(out)

    # ## The model
    #
    # `build_builtin_face` generates the procedural face (tetrahedral flesh on a rigid cranium
    # and an articulated jaw, 32 embedded muscles, marker sites on the skin) at about `tets`
    # tetrahedra, or finds it in the cache under `meshes/cache/`. `load_model` reads a model
    # folder, the built-in one or your own (`docs/model_format.md`), distributed over the ranks.
    model = load_model(build_builtin_face(target_tets=tets), comm)

    # ## A take of known truth
    #
    # A `FaceProblem` solves the quasistatic equilibrium of the face for given controls: muscle
    # activations, the cranium's rigid motion and the jaw's articulation. The synthetic take
    # drives it along a speech-like scenario with head motion and samples the model's marker
    # sites, adding `noise` mm (RMS) to each marker. Its markers carry the names of the model's
    # marker sites, which is how the alignment below knows where each one belongs.
    names = list(model.markers)
    sites = np.array([model.markers[name] for name in names])
    truth_problem = FaceProblem(model)
    capture, truth = synthesize_take(truth_problem, MarkerSet(truth_problem, sites, names=names), model,
                                     "speech", n_frames=frames, noise=noise)
    del truth_problem
    truth_file = out / "take.truth.npz"
    if comm.rank == 0:
        out.mkdir(parents=True, exist_ok=True)
        save_truth(truth_file, truth, model.muscle_names)
    comm.barrier()

    # ## Alignment
    #
    # `place_on_model` puts the capture's markers on the model's skin: by the names of the marker
    # sites here, by a correspondence file or by ICP for a capture of your own (`docs/alignment.md`).
    placement = place_on_model(model, capture)

    # ## Tracking
    #
    # A `Tracker` holds the problem and the fitting settings: here a named preset,
    # `PRESETS["default"]` or `PRESETS["fast"]` (for takes at capture rate on large meshes), which
    # `TrackingSettings.updated` can change setting by setting. `track` fits every frame, each
    # warm-started from the last, and writes it to the results folder as soon as it is done;
    # rerun on an unfinished folder, it continues where it stopped.
    tracker = Tracker(model, PRESETS[preset])
    run = tracker.track(capture, placement, out / "fit", truth_file=truth_file, overwrite=True, progress=False)

    # ## Results
    #
    # The folder holds the tables (`activations.csv`, `kinematics.csv`, `frames.csv`, ...), the
    # plots, rendered frames and a ParaView series. Its frames can also be read back as
    # `FrameResult`s on any rank.
    results = [run.folder.finished_frames()[frame] for frame in range(capture.n_frames)]
    simulated = np.array([run.folder.frame_markers(r.frame)[1] for r in results])
    clean = truth.clean_positions

    def rms(a, b):
        return np.sqrt(np.mean(np.sum((a - b) ** 2, axis=-1), axis=-1))

    # Against the truth: the fitted face's markers should lie closer to the noise-free markers
    # than the captured ones do (the model cannot follow noise that no muscle makes).
    fit_to_truth, noise = rms(simulated, clean), rms(capture.positions, clean)
    activation_error = np.array([np.abs(r.activations - truth.activations[r.frame]).max() for r in results])
    if comm.rank == 0:
        print(f"{capture.n_frames} frames tracked into {run.folder.path}")
        print("frame  marker RMS to capture  to truth  capture to truth  largest activation error (mm, mm, mm, -)")
        for r, to_truth, captured, error in zip(results, fit_to_truth, noise, activation_error):
            print(f"{r.frame:5d}  {r.rms_error:21.3f}  {to_truth:8.3f}  {captured:16.3f}  {error:24.3f}")
    return dict(marker_rms=np.array([r.rms_error for r in results]), fit_to_truth=fit_to_truth,
                noise=noise, activation_error=activation_error, folder=run.folder.path, finished=run.finished)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description="Track a synthetic take through the public API.")
    parser.add_argument("--tets", type=int, default=5000)
    parser.add_argument("--frames", type=int, default=6)
    parser.add_argument("--out", default="results/example")
    parser.add_argument("--preset", choices=tuple(PRESETS), default="default")
    args = parser.parse_args()
    main(args.tets, args.frames, args.out, args.preset)
