"""A sharp instrument pressed into the cheek: a tip or a blade between the skin's nodes
(docs/contact.md, "A mesh object's vertices and edges against the skin").

The built-in face (``--tets``) holds an expression (``--expression``, none by default) with a rigid
instrument (``--instrument``) waiting clear of the left cheek; the instrument then moves along the
cheek's outward normal at the marker site ``--site`` from 1 mm outside the skin to ``--depths`` mm
into it, one solve per pose. Instruments (closed triangle surfaces, ``TriangleMesh``):

- ``tip``: a square pyramid, its apex on the path, its base 2 mm wide 6 mm up the path;
- ``blade``: a wedge 30 mm long across the face, its edge on the path, 0.3 mm thick 5 mm up.

By default the instrument's vertices and edges are kept off the skin (``ObjectFeatureContact``);
``--nodes`` keeps only the skin's nodes out of it (the sharp part then passes between them). At
every pose: Newton iterations, load steps, failed Newton solves (continuation took over), seconds;
the smallest distance of the instrument's vertices and edges to the skin over all Newton iterates
(the contact code's, with the features' barrier); the deepest point of the instrument inside the
flesh at the equilibrium, measured here independently of the contact code (points every
0.1 mm along the instrument's edges, each signed by the outward normal of the nearest skin
triangle of the deformed skin); features and nodes within dhat; the force on the instrument.

Rows are printed and written (``--out``, JSON) after every pose, so a long run keeps what it
measured; ``--max-poses`` stops after that many poses.

    python benchmarks/instrument.py --tets 5000 --instrument tip --out benchmarks/results/contact/instrument_tip_5k.json
    python benchmarks/instrument.py --tets 5000 --instrument tip --nodes --out ...
"""
import argparse
import json
import pathlib
import sys
import time

from mpi4py import MPI
import numpy as np
from scipy.spatial import cKDTree

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
from cheek_sphere import FailureCount, cheek_frame, keep_pose  # noqa: E402
from provenance import record  # noqa: E402
from face_dolfinx.alignment.surface import closest_points  # noqa: E402
from face_dolfinx.model.anatomy import build_builtin_face  # noqa: E402
from face_dolfinx.model.bones import AffineMap, jaw_pose  # noqa: E402
from face_dolfinx.model.folder import load_model  # noqa: E402
from face_dolfinx.physics.contact import ContactSettings  # noqa: E402
from face_dolfinx.physics.object_features import ObjectFeatureContact  # noqa: E402
from face_dolfinx.physics.problem import FaceProblem  # noqa: E402
from face_dolfinx.physics.rigid_mesh import TriangleMesh  # noqa: E402
from face_dolfinx.results.xdmf import displacement_at  # noqa: E402

# The instrument waits this far (mm) off the rest skin while the expression is solved.
WAITING_CLEARANCE = 10.0
# mm between the points sampled along the instrument's edges for the independent depth.
SAMPLE_SPACING = 0.1


def instrument(name: str) -> tuple[np.ndarray, np.ndarray]:
    """The instrument's closed surface in its own frame: its sharp part at the origin, pointing
    down -z (outward triangles; ``TriangleMesh`` turns inward ones)."""
    if name == "tip":
        corners = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], dtype=float)
        points = np.vstack([[0.0, 0.0, 0.0], np.column_stack([corners, np.full(4, 6.0)])])
        return points, np.array([(0, 2, 1), (0, 3, 2), (0, 4, 3), (0, 1, 4), (1, 2, 3), (1, 3, 4)])
    if name == "blade":
        # A wedge: the edge along x at z = 0, the back 0.3 mm wide at z = 5.
        points = np.array([[x, y, z] for x in (-15.0, 15.0) for y, z in ((0.0, 0.0), (-0.15, 5.0), (0.15, 5.0))])
        triangles = [(0, 3, 4), (0, 4, 1), (0, 2, 5), (0, 5, 3), (1, 4, 5), (1, 5, 2), (0, 1, 2), (3, 5, 4)]
        return points, np.array(triangles)
    raise SystemExit(f"--instrument {name}: give tip or blade")


def path_frame(normal: np.ndarray) -> np.ndarray:
    """A rotation taking the instrument's +z to the cheek's outward ``normal`` and its x across the
    face (the model's x made orthogonal to the normal)."""
    across = np.array([1.0, 0.0, 0.0]) - normal[0] * normal
    across /= np.linalg.norm(across)
    return np.column_stack([across, np.cross(normal, across), normal])


def edge_samples(points: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """Points every SAMPLE_SPACING mm along the edges, the ends included."""
    out = []
    for a, b in points[edges]:
        count = max(int(np.ceil(np.linalg.norm(b - a) / SAMPLE_SPACING)), 1)
        out.append(a + np.linspace(0.0, 1.0, count + 1)[:, None] * (b - a))
    return np.vstack(out)


def deepest_inside(skin_points: np.ndarray, skin_triangles: np.ndarray, samples: np.ndarray) -> float:
    """How far (mm) the deepest sample lies inside the skin (negative: every sample is outside, by
    that much): each sample's distance to the nearest skin triangle (among the 40 of nearest
    centroid), signed by that triangle's outward normal."""
    corners = skin_points[skin_triangles]
    near = cKDTree(corners.mean(axis=1)).query(samples, k=min(40, len(corners)))[1]
    c = corners[near.reshape(-1)]
    repeated = np.repeat(samples, near.shape[1], axis=0)
    nearest = closest_points(repeated, c[:, 0], c[:, 1], c[:, 2])[0]
    distance = np.linalg.norm(repeated - nearest, axis=1).reshape(near.shape)
    k = np.arange(len(samples)) * near.shape[1] + distance.argmin(axis=1)
    normal = np.cross(c[k, 1] - c[k, 0], c[k, 2] - c[k, 0])
    normal /= np.linalg.norm(normal, axis=1)[:, None]
    return float((-np.einsum("ij,ij->i", samples - nearest[k], normal)).max())


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tets", type=int, default=5000)
    parser.add_argument("--instrument", default="tip", help="tip or blade")
    parser.add_argument("--expression", default="neutral", help="an expression of the model ('neutral': none)")
    parser.add_argument("--depths", default="0,1,2,3", help="comma-separated depths (mm) of the instrument's sharp "
                                                             "part into the skin, one pose each, after a first pose "
                                                             "1 mm outside")
    parser.add_argument("--site", default="nasolabial_left_3", help="the marker site the instrument aims at")
    parser.add_argument("--dhat", type=float, default=0.05)
    parser.add_argument("--stiffness", type=float, default=10.0)
    parser.add_argument("--nodes", action="store_true", help="keep only the skin's nodes out of the instrument")
    parser.add_argument("--max-poses", type=int, default=None, help="stop after this many poses")
    parser.add_argument("--out", required=True)
    args = parser.parse_args()
    comm = MPI.COMM_WORLD
    depths = [-1.0] + [float(d) for d in args.depths.split(",")]
    if args.max_poses is not None:
        depths = depths[:args.max_poses]
    surface = TriangleMesh(*instrument(args.instrument), name=args.instrument)

    model = load_model(build_builtin_face(target_tets=args.tets, comm=comm), comm)
    if args.expression != "neutral" and args.expression not in model.expressions:
        raise SystemExit(f"--expression {args.expression}: the model defines {', '.join(sorted(model.expressions))}")
    if args.site not in model.markers:
        raise SystemExit(f"--site {args.site}: not a marker site of the model")
    rest_site, rest_normal = cheek_frame(model, args.site)
    waiting = AffineMap(path_frame(rest_normal), rest_site + WAITING_CLEARANCE * rest_normal)
    began = time.perf_counter()
    settings = ContactSettings((surface,), (waiting,), dhat=args.dhat, stiffness=args.stiffness, faces=not args.nodes)
    problem = FaceProblem(model, contact=settings)
    contact = problem.contact
    features = isinstance(contact, ObjectFeatureContact)
    failures = FailureCount.attached()
    report = None
    if args.expression != "neutral":
        spec = dict(model.expressions[args.expression])
        opening = np.radians(spec.pop("jaw_opening_deg", 0.0))
        report = problem.solve(activations=spec, jaw=jaw_pose(model.jaw, opening) if opening else AffineMap())
    site, normal = cheek_frame(model, args.site, problem.u if report is not None else None)
    frame = path_frame(normal)
    skin_points, skin_triangles = model.skin_surface()
    summary = dict(tets=model.mesh.topology.index_map(3).size_global, ranks=comm.size, instrument=args.instrument,
                   barrier="instrument's vertices and edges, and skin nodes" if features else "skin nodes",
                   expression=args.expression, dhat_mm=args.dhat, stiffness_kPa=args.stiffness, site=args.site,
                   site_mm=site.round(4).tolist(), normal=normal.round(6).tolist(),
                   skin_nodes=contact.surface.num_nodes, skin_triangles=len(contact.surface.triangles),
                   set_up_and_expression_seconds=round(time.perf_counter() - began, 2), poses=[])
    if comm.rank == 0:
        print(json.dumps({k: v for k, v in summary.items() if k != "poses"}), flush=True)

    iterate_gaps = []

    def monitor(snes, iteration, norm):
        x = snes.getSolution().array_r
        gaps = contact.vertex_gaps(x, within=1.0) + contact.edge_gaps(x, within=1.0)
        iterate_gaps.append(float(np.concatenate(gaps).min()))

    if features:
        problem.solver.snes.setMonitor(monitor)
    out = pathlib.Path(args.out)
    for index, depth in enumerate(depths):
        pose = AffineMap(frame, site - depth * normal)
        iterate_gaps.clear()
        report, seconds = failures.solve(problem, pose)
        u = problem.u.x.array
        on_instrument = contact.nodal_forces(u).sum(axis=0)
        moved = skin_points + displacement_at(problem.u, skin_points)  # collective
        deepest = deepest_inside(moved, skin_triangles, edge_samples(pose.apply(surface.points), surface.edges))
        row = dict(pose=index, depth_mm=depth, converged=report.converged, newton_iterations=report.newton_iterations,
                   load_steps=report.load_steps, failed_newton_solves=failures.count, seconds=round(seconds, 2),
                   smallest_feature_gap_any_iterate_mm=min(iterate_gaps, default=None),
                   deepest_instrument_point_inside_mm=round(deepest, 5),
                   contact_nodes=contact.contact_nodes(u),
                   contact_vertices_edges=list(contact.contact_features(u)) if features else None,
                   force_on_instrument_mN=on_instrument.round(4).tolist(),
                   force_along_normal_mN=round(float(on_instrument @ normal), 4))
        keep_pose(summary, row, out, comm)
    problem.solver.snes.cancelMonitor()
    summary.update(total_seconds=round(time.perf_counter() - began, 2))
    if comm.rank == 0:
        out.write_text(json.dumps(summary, indent=1) + "\n")
        record(out, tets=args.tets, ranks=comm.size)


if __name__ == "__main__":
    main()
