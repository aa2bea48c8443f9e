"""Lips closed hard, with and without lip self-contact (docs/contact.md, "Lip self-contact").

The built-in face with the jaw closed ``--jaw`` degrees beyond its rest pose and the orbicularis
oris (upper and lower, left and right) at 1, solved from rest without and with
``FaceProblem(lip_contact=...)``: in one solve, or along a ramp of ``--load-steps`` equilibria
(each from the last; a Newton solve that fails falls back on continuation, counted in
``solves_with_continuation``). At every Newton iterate: the smallest distance between the lips
and the deepest lip node inside the other lip. At the end: Newton iterations, seconds, barrier
pairs, and the contact pressure per lip node (kPa), plotted along the mouth (``--plot``).

    python benchmarks/lip_contact.py --tets 5000 --out benchmarks/results/contact/lips_5k.json \\
        --plot benchmarks/results/contact/lips_5k_pressure.png
"""
import argparse
import json
import logging
import pathlib
import sys
import time

from mpi4py import MPI
import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
from provenance import record  # noqa: E402
from face_dolfinx.model.anatomy import build_builtin_face  # noqa: E402
from face_dolfinx.model.bones import jaw_pose  # noqa: E402
from face_dolfinx.model.folder import load_model  # noqa: E402
from face_dolfinx.physics.problem import FaceProblem  # noqa: E402
from face_dolfinx.physics.self_contact import LipContact, LipContactSettings, LipIterates, lip_facets  # noqa: E402


def run(model, angle: float, settings: LipContactSettings | None, load_steps: int = 1,
        **solver) -> tuple[dict, FaceProblem, LipContact]:
    problem = FaceProblem(model, lip_contact=settings, **solver)
    lips = problem.lips or LipContact(problem.V, *lip_facets(model, LipContactSettings()), LipContactSettings(),
                                      problem.bone_blocks)
    iterates = LipIterates(lips, problem.V)
    problem.solver.snes.setMonitor(iterates)
    sphincter = {m.name: 1.0 for m in model.muscles if m.name.startswith("orbicularis_oris")}
    began = time.perf_counter()
    reports = [problem.solve(activations={name: t * a for name, a in sphincter.items()},
                             jaw=jaw_pose(model.jaw, np.radians(t * angle)))
               for t in np.arange(1, load_steps + 1) / load_steps]
    seconds = time.perf_counter() - began
    u = problem.u.x.array
    row = dict(self_contact=settings is not None, dhat=settings.dhat if settings else None,
               stiffness=settings.stiffness if settings else None, **solver, jaw_deg=angle,
               converged=all(r.converged for r in reports),
               newton_iterations=sum(r.newton_iterations for r in reports),
               load_steps=sum(r.load_steps for r in reports), ramp_steps=load_steps,
               solves_with_continuation=sum(r.load_steps > 1 for r in reports),
               seconds=round(seconds, 2),
               iterates=len(iterates.distances), smallest_distance_any_iterate=min(iterates.distances),
               deepest_penetration_any_iterate=max(iterates.depths), final_distance=lips.min_distance(u),
               final_penetration=lips.penetration(u), pairs=lips.pairs(u) if settings else 0,
               tets=model.mesh.topology.index_map(3).size_global, lip_nodes=lips.surface.num_nodes)
    return row, problem, lips


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tets", type=int, default=5000)
    parser.add_argument("--jaw", type=float, default=-2.0, help="jaw opening, degrees (negative: beyond closed)")
    parser.add_argument("--dhat", type=float, default=0.05)
    parser.add_argument("--stiffness", type=float, default=10.0)
    parser.add_argument("--contact-relaxation", action="store_true",
                        help="relax the nodes in contact after each Newton correction (fit --contact-relaxation)")
    parser.add_argument("--newton-energy-tolerance", type=float,
                        help="mN mm: also stop Newton once a correction would release less (as `fit --fast`)")
    parser.add_argument("--load-steps", type=int, default=1,
                        help="reach the closure in this many equilibria along a linear ramp of the jaw and "
                             "the muscle, each solved from the last")
    parser.add_argument("--out", required=True)
    parser.add_argument("--plot")
    parser.add_argument("-v", "--verbose", action="store_true", help="log every Newton solve to standard error")
    args = parser.parse_args()
    comm = MPI.COMM_WORLD
    if args.verbose and comm.rank == 0:
        logging.basicConfig(format="%(asctime)s %(name)s: %(message)s", force=True)
        logging.getLogger("face_dolfinx").setLevel(logging.DEBUG)
    solver = dict(contact_relaxation=args.contact_relaxation, newton_energy_tolerance=args.newton_energy_tolerance)
    model = load_model(build_builtin_face(target_tets=args.tets, comm=comm), comm)
    rows = []
    without, _, _ = run(model, args.jaw, None, **solver)
    rows.append(without)
    with_contact, problem, lips = run(model, args.jaw, LipContactSettings(dhat=args.dhat, stiffness=args.stiffness),
                                        args.load_steps, **solver)
    pressure = lips.nodal_pressure(problem.u.x.array)
    x = lips.positions(problem.u.x.array)
    with_contact.update(peak_pressure=float(pressure.max()),
                        median_pressure_of_pressed_nodes=float(np.median(pressure[pressure > 0])) if (pressure > 0).any() else 0.0,
                        pressed_nodes=int((pressure > 0).sum()))
    rows.append(with_contact)
    if comm.rank == 0:
        out = pathlib.Path(args.out)
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(rows, indent=1) + "\n")
        print(json.dumps(rows, indent=1))
        if args.plot:
            import matplotlib
            matplotlib.use("Agg")
            import matplotlib.pyplot as plt
            figure, axis = plt.subplots(figsize=(7, 3.5))
            depth = x @ np.cross(lips.up, [1.0, 0.0, 0.0])
            for nodes, label, marker in ((lips.upper_nodes, "upper lip", "v"), (lips.lower_nodes, "lower lip", "^")):
                scatter = axis.scatter(x[nodes, 0], pressure[nodes], c=depth[nodes], marker=marker, label=label, s=22)
            figure.colorbar(scatter, label="depth into the slit (mm)")
            axis.set_xlabel("x along the mouth (mm)")
            axis.set_ylabel("contact pressure (kPa)")
            axis.set_title(f"lips pressed: jaw {args.jaw:g} deg, orbicularis oris 1, {with_contact['tets']} tets")
            axis.legend()
            figure.tight_layout()
            figure.savefig(args.plot, dpi=120)
        record(out, tets=args.tets, ranks=comm.size)
        if args.plot:
            record(args.plot, tets=args.tets, ranks=comm.size)


if __name__ == "__main__":
    main()
