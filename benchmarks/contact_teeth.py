"""The lips on the teeth: Newton iterations, load steps and the smallest gap over all Newton
iterates of solves with and without the teeth contact, in the same run.

Cases (``--cases``): ``oo:LEVEL`` solves the orbicularis oris at LEVEL from rest; ``jaw:DEG``
opens the jaw by DEG degrees from rest and closes it again (two solves). Variants
(``--variants``): ``none`` (no teeth contact), ``teeth`` (``ContactSettings(teeth=True,
stiffness=TEETH_STIFFNESS)``: the teeth's dhat ``TEETH_DHAT`` and the model's teeth) and
``thin`` (dhat 0.05 mm with the built-in teeth placed 0.3 mm behind the lining, the barrier
that reaches no further than the lips' resting gap).

Prints one JSON line per solve: Newton iterations, load steps, seconds of the solve, seconds in
the contact terms (energy, gradient, Hessian, collision-free step) and how often they ran, the
Newton steps the collision-free bound cut and their median fraction, contact nodes, the smallest
gap over all Newton iterates and at the end, the force the lips put on the teeth, the markers'
distance to the teeth at rest and how far each marker ends from where the other teeth variant
left it. Run through provenance.py:

    python benchmarks/provenance.py run --out benchmarks/results/contact/teeth_newton_5k.jsonl \\
        --json-lines -- python benchmarks/contact_teeth.py --tets 5000
"""
import argparse
from dataclasses import replace
import json
import time

from mpi4py import MPI
import numpy as np

from face_dolfinx.model.anatomy import build_builtin_face
from face_dolfinx.model.anatomy.builder import DESCRIPTION_FILE
from face_dolfinx.model.anatomy.description import load_description
from face_dolfinx.model.anatomy.teeth import dental_arch
from face_dolfinx.model.bones import jaw_pose
from face_dolfinx.model.folder import load_model
from face_dolfinx.physics.contact import TEETH_STIFFNESS, ContactSettings
from face_dolfinx.physics.points import PointEvaluator
from face_dolfinx.physics.problem import FaceProblem

TERMS = ("energy", "add_gradient", "add_hessian", "add_newton_correction", "step_fraction")
THIN_DHAT, THIN_CLEARANCE = 0.05, 0.3


class Timed:
    """The contact term's methods, timed (seconds and calls per method), and the fractions of the
    collision-free bound."""

    def __init__(self, term):
        self.seconds = {name: 0.0 for name in TERMS}
        self.calls = {name: 0 for name in TERMS}
        self.fractions = []
        for name in TERMS:
            setattr(term, name, self._wrap(name, getattr(term, name)))

    def _wrap(self, name, method):
        def timed(*args):
            began = time.perf_counter()
            try:
                result = method(*args)
                if name == "step_fraction":
                    self.fractions.append(result)
                return result
            finally:
                self.seconds[name] += time.perf_counter() - began
                self.calls[name] += 1
        return timed

    def take(self) -> dict:
        """The counts since the last call, and reset them."""
        fractions = np.array(self.fractions)
        cut = fractions[fractions < 1.0]
        row = dict(contact_seconds=round(MPI.COMM_WORLD.allreduce(sum(self.seconds.values()), op=MPI.MAX), 2),
                   contact_seconds_by_term={k: round(v, 3) for k, v in self.seconds.items()},
                   contact_calls=dict(self.calls), cut_steps=int(cut.size),
                   median_cut_fraction=float(np.median(cut)) if cut.size else None)
        self.seconds = {name: 0.0 for name in TERMS}
        self.calls = {name: 0 for name in TERMS}
        self.fractions = []
        return row


def thin_teeth(model):
    """The model with the built-in teeth placed THIN_CLEARANCE mm behind the lining."""
    description = load_description(DESCRIPTION_FILE)
    teeth = replace(description.teeth, clearance=THIN_CLEARANCE)
    return replace(model, teeth={"cranium": dental_arch(description.shape, teeth.upper, teeth),
                                 "mandible": dental_arch(description.shape, teeth.lower, teeth)})


def solves(model, case: str):
    """(label, keyword arguments of FaceProblem.solve) of a case."""
    kind, _, value = case.partition(":")
    if kind == "oo":
        level = float(value)
        return [(f"orbicularis oris {level:g}",
                 dict(activations={n: level for n in model.muscle_names if n.startswith("orbicularis_oris")}))]
    if kind == "jaw":
        degrees = float(value)
        return [(f"jaw opened {degrees:g} deg", dict(jaw=jaw_pose(model.jaw, np.radians(degrees)))),
                ("jaw closed again", dict(jaw=jaw_pose(model.jaw, 0.0)))]
    raise SystemExit(f"--cases {case}: give oo:LEVEL or jaw:DEGREES")


def run(tets: int, case: str, variant: str, markers_of: dict):
    """The rows of one case and variant; ``markers_of`` collects the marker positions per solve and
    variant (the rows compare the teeth variants' markers)."""
    model = load_model(build_builtin_face(tets))
    if variant == "none":
        settings = None
    elif variant == "teeth":
        settings = ContactSettings(teeth=True, stiffness=TEETH_STIFFNESS)
    elif variant == "thin":
        model = thin_teeth(model)
        settings = ContactSettings(teeth=True, stiffness=TEETH_STIFFNESS, teeth_dhat=THIN_DHAT)
    else:
        raise SystemExit(f"--variants {variant}: give none, teeth or thin")
    problem = FaceProblem(model, contact=settings)
    contact = problem.teeth_contact
    sites = np.array(list(model.markers.values()))
    markers = PointEvaluator(problem.V, sites)
    timer = Timed(contact) if contact is not None else None
    gaps = []
    if contact is not None:
        problem.solver.snes.setMonitor(
            lambda snes, it, norm: gaps.append(contact.min_gap(snes.getSolution().array_r)))
    for label, controls in solves(model, case):
        gaps.clear()
        began = time.perf_counter()
        report = problem.solve(**controls)
        seconds = MPI.COMM_WORLD.allreduce(time.perf_counter() - began, op=MPI.MAX)
        row = dict(study="contact_teeth", tets=model.mesh.topology.index_map(3).size_global,
                   ranks=MPI.COMM_WORLD.size, case=case, solve=label, variant=variant,
                   teeth_dhat_mm=None if contact is None else contact.dhat, converged=report.converged,
                   newton_iterations=report.newton_iterations, load_steps=report.load_steps,
                   seconds=round(seconds, 2))
        placed = sites + markers.values(problem.u.x.array)
        markers_of[(case, label, variant)] = placed
        for other in ("thin", "teeth"):
            if other != variant and (case, label, other) in markers_of:
                row[f"markers_from_{other}_mm"] = float(np.linalg.norm(
                    placed - markers_of[(case, label, other)], axis=1).max())
        if contact is not None:
            forces = contact.nodal_forces(problem.u.x.array)
            row.update(timer.take())
            row.update(surface_nodes=contact.surface.num_nodes, contact_nodes=contact.contact_nodes(problem.u.x.array),
                       min_gap_over_iterates_mm=min(gaps), min_gap_mm=contact.min_gap(problem.u.x.array),
                       pressed_mN=float(np.linalg.norm(forces, axis=1).sum()),
                       markers_to_teeth_at_rest_mm=min(float(obj.gaps(sites, pose)[0].min())
                                                       for obj, pose in zip(contact.objects, problem.teeth_poses(
                                                           problem.rest_controls()))))
        yield row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--tets", type=int, nargs="+", default=[5000])
    parser.add_argument("--cases", nargs="+", default=["oo:0.1", "oo:1", "jaw:10"])
    parser.add_argument("--variants", nargs="+", default=["none", "thin", "teeth"])
    args = parser.parse_args()
    markers_of = {}
    for tets in args.tets:
        for case in args.cases:
            for variant in args.variants:
                for row in run(tets, case, variant, markers_of):
                    if MPI.COMM_WORLD.rank == 0:
                        print(json.dumps(row), flush=True)


if __name__ == "__main__":
    main()
