"""What the lips' contact terms cost per call inside a solve, and a fingerprint of its iterates.

The lip closure of ``benchmarks/lip_contact.py`` (the jaw ``--jaw`` degrees beyond its rest pose,
the orbicularis oris at 1, ``FaceProblem(lip_contact=LipContactSettings())``), solved once from
rest with the contact terms timed (energy, gradient, Hessian, collision-free step: calls and ms
per call). The SHA-256 of every Newton iterate (each rank's owned values, in order) fingerprints
the solve, so that two versions of the contact code can be shown to take the same iterates bit
for bit: run this script with each on the same machine and compare ``iterates_sha256`` (with
``--ipctk-threads 1``: the IPC Toolkit's threaded sums differ in their last bits from run to run).
Then, at the pressed lips, ``--rounds`` times what one Newton iteration asks of the lips (gradient,
Hessian and the bound of a step as long as the lips' smallest distance, at one state), at the
equilibrium and at a state moved by a tenth of that distance in turn, so that every round meets a new state: ms per round and per call,
free of the solve's other work; ``--compare-with`` times another version's ``LipContact`` in the
same rounds, in turn with this one.

    python benchmarks/provenance.py run --out benchmarks/results/contact/lip_calls_5k-20k.jsonl --json-lines -- \\
        python benchmarks/lip_contact_calls.py --tets 5000 20000
"""
import argparse
import hashlib
import importlib.util
import json
import pathlib
import sys
import time

import ipctk
from mpi4py import MPI
from petsc4py import PETSc
import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
from contact_teeth import TERMS, Timed  # noqa: E402
from face_dolfinx.model.anatomy import build_builtin_face  # noqa: E402
from face_dolfinx.model.bones import jaw_pose  # noqa: E402
from face_dolfinx.model.folder import load_model  # noqa: E402
from face_dolfinx.physics.problem import FaceProblem  # noqa: E402
from face_dolfinx.physics.self_contact import LipContactSettings  # noqa: E402


def iteration_rounds(problem, versions: dict, rounds: int) -> dict:
    """ms per call of the lips' gradient, Hessian and step bound, called in that order at one state
    per round, the states alternating between the equilibrium and a nearby one; ``versions``
    (name: a LipContact of the problem's lips) take their rounds in turn, so that they share the
    machine's load alike."""
    here = problem.u.vector.copy()
    step = here.duplicate()
    step.array[:] = np.random.default_rng(problem.comm.rank).uniform(-1.0, 1.0, step.getLocalSize())
    # A step of the lips' smallest distance: the step bound runs its CCD, as in the closing solve.
    step.scale(problem.lips.min_distance(problem.u.x.array) / max(step.norm(PETSc.NormType.NORM_INFINITY), 1e-300))
    there = here.copy()
    there.axpy(0.1, step)
    b, A = here.duplicate(), problem.solver.tangent.duplicate()
    no_dofs = np.zeros(0, dtype=np.int32)
    names = ("add_gradient", "add_hessian", "step_fraction")
    seconds = {version: np.zeros((rounds, len(names))) for version in versions}
    for round_ in range(rounds):
        x = here if round_ % 2 == 0 else there
        for version, lips in versions.items():
            calls = (lambda: lips.add_gradient(x, b), lambda: lips.add_hessian(x, A, no_dofs),
                     lambda: lips.step_fraction(x, step, 1.0))
            for k, call in enumerate(calls):
                began = time.perf_counter()
                call()
                seconds[version][round_, k] = time.perf_counter() - began
    out = {}
    for version, table in seconds.items():
        table = problem.comm.allreduce(table, op=MPI.MAX)
        out[version] = dict(rounds=rounds, ms_per_round_median=round(1e3 * float(np.median(table.sum(axis=1))), 2),
                            ms_per_round_mean=round(1e3 * float(table.sum(axis=1).mean()), 2),
                            ms_per_call_median={name: round(1e3 * float(np.median(table[:, k])), 2)
                                                for k, name in enumerate(names)},
                            ms_per_call_mean={name: round(1e3 * float(table[:, k].mean()), 2)
                                              for k, name in enumerate(names)})
    return out


def version_of(path: str, problem, model) -> object:
    """A LipContact of the problem's lips from another version of self_contact.py at ``path``."""
    spec = importlib.util.spec_from_file_location("other_self_contact", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    settings = module.LipContactSettings()
    return module.LipContact(problem.V, *module.lip_facets(model, settings), settings, problem.bone_blocks)


def run(tets: int, angle: float, label: str, rounds: int, compare_with: str | None) -> dict:
    comm = MPI.COMM_WORLD
    model = load_model(build_builtin_face(target_tets=tets, comm=comm), comm)
    problem = FaceProblem(model, lip_contact=LipContactSettings())
    timer = Timed(problem.lips)
    digest, iterates = hashlib.sha256(), [0]

    def monitor(snes, iteration, norm):
        digest.update(snes.getSolution().array_r.tobytes())
        iterates[0] += 1

    problem.solver.snes.setMonitor(monitor)
    sphincter = {m.name: 1.0 for m in model.muscles if m.name.startswith("orbicularis_oris")}
    began = time.perf_counter()
    report = problem.solve(activations=sphincter, jaw=jaw_pose(model.jaw, np.radians(angle)))
    seconds = comm.allreduce(time.perf_counter() - began, op=MPI.MAX)
    versions = {label or "this": problem.lips}
    if compare_with:
        versions[compare_with] = version_of(compare_with, problem, model)
    contact_seconds = {name: comm.allreduce(timer.seconds[name], op=MPI.MAX) for name in TERMS}
    ranks_digest = hashlib.sha256("".join(comm.allgather(digest.hexdigest())).encode()).hexdigest()
    return dict(study="lip_contact_calls", code=label, ipctk_threads=ipctk.get_num_threads(), tets=model.mesh.topology.index_map(3).size_global,
                ranks=comm.size, jaw_deg=angle, converged=report.converged,
                newton_iterations=report.newton_iterations, load_steps=report.load_steps, iterates=iterates[0],
                seconds=round(seconds, 2), contact_seconds=round(sum(contact_seconds.values()), 2),
                calls=dict(timer.calls),
                ms_per_call={name: round(1e3 * contact_seconds[name] / max(timer.calls[name], 1), 2) for name in TERMS},
                lip_nodes=problem.lips.surface.num_nodes, pairs=problem.lips.pairs(problem.u.x.array),
                iterates_sha256=ranks_digest,
                iteration_rounds=iteration_rounds(problem, versions, rounds))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--tets", type=int, nargs="+", default=[5000])
    parser.add_argument("--jaw", type=float, default=-2.0, help="jaw opening, degrees (negative: beyond closed)")
    parser.add_argument("--label", default="", help="names the code version in the rows (e.g. its commit)")
    parser.add_argument("--rounds", type=int, default=200, help="rounds of the lips' terms at the pressed lips")
    parser.add_argument("--compare-with", metavar="FILE",
                        help="another version of face_dolfinx/physics/self_contact.py (e.g. from git show): "
                             "its LipContact takes the rounds in turn with this one's")
    parser.add_argument("--ipctk-threads", type=int, default=0,
                        help="threads of the IPC Toolkit (0: its default); with 1 its sums are reproducible")
    args = parser.parse_args()
    if args.ipctk_threads:
        ipctk.set_num_threads(args.ipctk_threads)
    for tets in args.tets:
        row = run(tets, args.jaw, args.label, args.rounds, args.compare_with)
        if MPI.COMM_WORLD.rank == 0:
            print(json.dumps(row), flush=True)


if __name__ == "__main__":
    main()
