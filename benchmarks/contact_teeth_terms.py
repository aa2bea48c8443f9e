"""The teeth's contact terms per call: the sampled candidate search with the cut-off of
``TriangleMesh.gaps(within=...)`` against a reference search, on the states of one solve.

The solve of ``contact_teeth.py`` (the orbicularis oris at --level, teeth on) records its Newton
iterates. At each recorded iterate (at most --states of them, evenly spaced) the teeth's gradient,
Hessian and collision-free step bound (the step to the next iterate) are timed with both searches,
one right after the other, so that the ratio is fair on a shared machine. The reference is
``face_dolfinx/physics/rigid_mesh.py`` at --reference (read with ``git show``): exact distances
of every lining node at every call, candidate triangles from a KD-tree of the centroids inflated by
the largest triangle's bounding radius. Both must give the same terms (to round-off): the largest
differences are printed too, next to the machine-independent counts (lining nodes whose distance is
computed exactly, candidate point-triangle pairs of the gradient). One JSON line per face; run
through provenance.py:

    python benchmarks/provenance.py run --out benchmarks/results/contact/teeth_terms_5k-20k_np1.jsonl \\
        --json-lines -- python benchmarks/contact_teeth_terms.py --tets 5000 20000
"""
import argparse
import json
import pathlib
import subprocess
import time
import types

from mpi4py import MPI
from petsc4py import PETSc
import numpy as np

from face_dolfinx.model.anatomy import build_builtin_face
from face_dolfinx.model.folder import load_model
from face_dolfinx.physics.contact import TEETH_STIFFNESS, ContactSettings
from face_dolfinx.physics.problem import FaceProblem

ROOT = pathlib.Path(__file__).resolve().parent.parent
# The last commit whose rigid_mesh.py searches candidates by centroids and bounding radius.
REFERENCE = "944f7b8"


def reference_module(commit: str) -> types.ModuleType:
    """face_dolfinx/physics/rigid_mesh.py as of ``commit``, as a module of its own."""
    path = "face_dolfinx/physics/rigid_mesh.py"
    source = subprocess.run(["git", "show", f"{commit}:{path}"], cwd=ROOT, capture_output=True, text=True,
                            check=True).stdout
    module = types.ModuleType("rigid_mesh_reference")
    exec(compile(source, f"{commit}:{path}", "exec"), module.__dict__)
    return module


class Reference:
    """A reference TriangleMesh under the contact terms' interface: the cut-off is not used."""

    def __init__(self, mesh):
        self.mesh = mesh

    def gaps(self, points, pose, within=None):
        return self.mesh.gaps(points, pose)

    def first_contact(self, points, steps, pose, clearance):
        return self.mesh.first_contact(points, steps, pose, clearance)


def counts(contact, objects, displacement) -> tuple[int, int]:
    """Lining nodes whose distance the gradient computes exactly, and its candidate point-triangle
    pairs, summed over the teeth: sampled search (``objects`` None) or the reference's."""
    x = contact.positions(displacement)
    exact = pairs = 0
    for obj, pose in zip(objects or contact.objects, contact.poses):
        local = (x - pose.translation) @ pose.matrix
        if objects is None:
            lower, upper = obj.distance_bounds(local)
            near = lower < contact.dhat
            exact += int(near.sum())
            pairs += len(obj.candidate_pairs(local[near], upper[near])[0])
        else:
            mesh = obj.mesh
            upper = np.minimum(mesh.vertex_tree.query(local)[0], mesh.centroid_tree.query(local)[0])
            exact += len(local)
            pairs += int(mesh.centroid_tree.query_ball_point(local, upper + 1.000001 * mesh.bounding_radius,
                                                             return_length=True).sum())
    return exact, pairs


def run(tets: int, level: float, states: int, reference: str) -> dict:
    comm = MPI.COMM_WORLD
    model = load_model(build_builtin_face(tets))
    problem = FaceProblem(model, contact=ContactSettings(teeth=True, stiffness=TEETH_STIFFNESS))
    contact = problem.teeth_contact
    iterates = []
    problem.solver.snes.setMonitor(lambda snes, it, norm: iterates.append((it, snes.getSolution().array_r.copy())))
    activations = {name: level for name in model.muscle_names if name.startswith("orbicularis_oris")}
    report = problem.solve(activations=activations)
    # (state, accepted step to the next iterate of the same load step)
    steps = [(x, x - y) for (i, x), (j, y) in zip(iterates, iterates[1:]) if j == i + 1]
    chosen = np.unique(np.linspace(0, len(steps) - 1, min(states, len(steps))).round().astype(int))

    module = reference_module(reference)
    sampled = contact.objects
    old = tuple(Reference(module.TriangleMesh(*obj.surface(), name=obj.name)) for obj in sampled)
    variants = {"reference": old, "sampled": sampled}
    seconds = {v: {"gradient": 0.0, "hessian": 0.0, "step": 0.0} for v in variants}
    exact = {v: 0 for v in variants}
    pairs = {v: 0 for v in variants}
    gradient_difference = hessian_difference = step_difference = 0.0
    x, step = problem.u.vector.copy(), problem.u.vector.copy()
    b = problem.u.vector.copy()
    A = problem.solver.tangent.duplicate()
    none = np.zeros(0, dtype=np.int32)
    for k in chosen:
        x.array[:], step.array[:] = steps[k]
        results = {}
        for name, objects in variants.items():
            contact.objects = objects
            b.set(0.0)
            began = time.perf_counter()
            contact.add_gradient(x, b)
            seconds[name]["gradient"] += time.perf_counter() - began
            A.zeroEntries()
            began = time.perf_counter()
            contact.add_hessian(x, A, none)
            seconds[name]["hessian"] += time.perf_counter() - began
            began = time.perf_counter()
            fraction = contact.step_fraction(x, step, 1.0)
            seconds[name]["step"] += time.perf_counter() - began
            results[name] = (b.copy(), A.copy(), fraction)
            c = counts(contact, None if name == "sampled" else objects, x.array_r)
            exact[name] += c[0]
            pairs[name] += c[1]
        (b_old, A_old, t_old), (b_new, A_new, t_new) = results["reference"], results["sampled"]
        b_new.axpy(-1.0, b_old)
        gradient_difference = max(gradient_difference, b_new.norm(PETSc.NormType.NORM_INFINITY)
                                  / max(b_old.norm(PETSc.NormType.NORM_INFINITY), 1e-300))
        A_new.axpy(-1.0, A_old)
        hessian_difference = max(hessian_difference, A_new.norm(PETSc.NormType.FROBENIUS)
                                 / max(A_old.norm(PETSc.NormType.FROBENIUS), 1e-300))
        step_difference = max(step_difference, abs(t_new - t_old))
    contact.objects = sampled
    n = len(chosen)
    ms = {v: {term: round(1e3 * comm.allreduce(s, op=MPI.MAX) / n, 2) for term, s in by_term.items()}
          for v, by_term in seconds.items()}
    return dict(study="contact_teeth_terms", tets=model.mesh.topology.index_map(3).size_global, ranks=comm.size,
                orbicularis_oris=level, converged=report.converged, newton_iterations=report.newton_iterations,
                states_timed=int(n), reference_commit=reference, lining_nodes=contact.surface.num_nodes,
                teeth_triangles=[len(o.triangles) for o in sampled],
                samples=[o.sample_tree.n for o in sampled], covering_radius_mm=[round(o.covering_radius, 4) for o in sampled],
                ms_per_call=ms,
                speedup={term: round(ms["reference"][term] / max(ms["sampled"][term], 1e-9), 1) for term in ms["sampled"]},
                exact_nodes_per_gradient={v: round(e / n, 1) for v, e in exact.items()},
                candidate_pairs_per_gradient={v: round(p / n, 1) for v, p in pairs.items()},
                max_relative_difference=dict(gradient=gradient_difference, hessian=hessian_difference),
                max_step_fraction_difference=step_difference)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--tets", type=int, nargs="+", default=[5000, 20000])
    parser.add_argument("--level", type=float, default=0.1, help="activation of the orbicularis oris")
    parser.add_argument("--states", type=int, default=40, help="Newton iterates to time the terms at")
    parser.add_argument("--reference", default=REFERENCE, help="commit of the reference rigid_mesh.py")
    args = parser.parse_args()
    for tets in args.tets:
        row = run(tets, args.level, args.states, args.reference)
        if MPI.COMM_WORLD.rank == 0:
            print(json.dumps(row), flush=True)


if __name__ == "__main__":
    main()
