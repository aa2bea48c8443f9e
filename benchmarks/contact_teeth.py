"""The lips pressed on the teeth: one solve of the orbicularis oris with and without the teeth
contact, in the same run, and the time the contact terms take within the solve.

Prints one JSON line per (tets, variant): Newton iterations, load steps, seconds of the solve,
seconds in the contact terms (energy, gradient, Hessian, collision-free step) and how often they
ran, contact nodes, the smallest gap over all Newton iterates and at the end, and the force the
lips put on the teeth. Run through provenance.py (benchmarks/run_all.sh):

    python benchmarks/provenance.py run --out benchmarks/results/contact/teeth_5k-20k_np1.jsonl \
        --json-lines -- python benchmarks/contact_teeth.py --tets 5000 20000
"""
import argparse
import json
import time

from mpi4py import MPI
import numpy as np

from face_dolfinx.model.anatomy import build_builtin_face
from face_dolfinx.model.folder import load_model
from face_dolfinx.physics.contact import TEETH_STIFFNESS, ContactSettings
from face_dolfinx.physics.problem import FaceProblem

TERMS = ("energy", "add_gradient", "add_hessian", "step_fraction")


class Timed:
    """The contact term's methods, timed (seconds and calls per method)."""

    def __init__(self, term):
        self.seconds = {name: 0.0 for name in TERMS}
        self.calls = {name: 0 for name in TERMS}
        for name in TERMS:
            setattr(term, name, self._wrap(name, getattr(term, name)))

    def _wrap(self, name, method):
        def timed(*args):
            began = time.perf_counter()
            try:
                return method(*args)
            finally:
                self.seconds[name] += time.perf_counter() - began
                self.calls[name] += 1
        return timed


def run(tets: int, level: float, teeth: bool) -> dict:
    model = load_model(build_builtin_face(tets))
    settings = ContactSettings(teeth=True, stiffness=TEETH_STIFFNESS) if teeth else None
    problem = FaceProblem(model, contact=settings)
    activations = {name: level for name in model.muscle_names if name.startswith("orbicularis_oris")}
    contact = problem.teeth_contact
    timer = Timed(contact) if teeth else None
    gaps = []
    if teeth:
        problem.solver.snes.setMonitor(lambda snes, it, norm: gaps.append(contact.min_gap(snes.getSolution().array_r)))
    began = time.perf_counter()
    report = problem.solve(activations=activations)
    seconds = MPI.COMM_WORLD.allreduce(time.perf_counter() - began, op=MPI.MAX)
    row = dict(study="contact_teeth", tets=model.mesh.topology.index_map(3).size_global, ranks=MPI.COMM_WORLD.size,
               orbicularis_oris=level, teeth=teeth, converged=report.converged,
               newton_iterations=report.newton_iterations, load_steps=report.load_steps, seconds=round(seconds, 2))
    if teeth:
        forces = contact.nodal_forces(problem.u.x.array)
        row.update(contact_seconds=round(MPI.COMM_WORLD.allreduce(sum(timer.seconds.values()), op=MPI.MAX), 2),
                   contact_seconds_by_term={k: round(v, 3) for k, v in timer.seconds.items()}, contact_calls=timer.calls,
                   surface_nodes=contact.surface.num_nodes, teeth_triangles=[len(o.triangles) for o in contact.objects],
                   contact_nodes=contact.contact_nodes(problem.u.x.array), min_gap_over_iterates_mm=min(gaps),
                   min_gap_mm=contact.min_gap(problem.u.x.array),
                   pressed_mN=float(np.linalg.norm(forces, axis=1).sum()))
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--tets", type=int, nargs="+", default=[5000, 20000])
    parser.add_argument("--level", type=float, default=0.1, help="activation of the orbicularis oris")
    args = parser.parse_args()
    for tets in args.tets:
        for teeth in (False, True):
            row = run(tets, args.level, teeth)
            if MPI.COMM_WORLD.rank == 0:
                print(json.dumps(row), flush=True)


if __name__ == "__main__":
    main()
