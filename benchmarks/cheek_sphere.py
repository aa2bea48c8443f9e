"""A sphere pressed into the cheek of a face playing an expression (the paper's figure 9;
docs/contact.md, "Figure 9: a sphere pressed into the cheek").

The built-in face (``--tets``) holds an expression of the model (``--expression``, the smile by
default) with a rigid sphere of ``--radius`` mm waiting clear of the left cheek; the sphere then
moves along the cheek's outward normal (at the marker site ``--site`` of the smiling face) from
1 mm outside the skin to ``--depths`` mm into it, one solve per pose. At every pose: Newton
iterations, load steps, failed Newton solves (continuation took over), seconds; the smallest gap
of any skin node to the sphere over all Newton iterates (the held solve that moves the sphere
included) and where that node is; the deepest point of any skin triangle inside the sphere at
the equilibrium and over all iterates (measured here from the triangles' corners, independently
of the contact code); the contact nodes and triangles (within dhat) and the force on the sphere.
By default the barrier keeps the skin's triangles out of the sphere
(``face_contact.FaceContactPotential``); ``--nodes`` keeps only the nodes out (a flat triangle
between them can then dip in). At the deepest pose: the contact pressure per skin node (kPa), two
ways: the nodal barrier force over the node's area, (triangle barrier) the triangles' pressures
averaged over the triangles around the node (``face_pressure``), and the nodal forces and areas
summed with hat weights over one median skin edge (``smoothed_pressure``: the pressure the mesh
resolves), the one plotted (``--plot``: a map over the contact patch and a profile against the
distance from the sphere's axis). For each: the scatter about the best fitting Hertz
profile and the count of isolated spikes (a pressed node with more than twice the pressure of
every neighbour); ``--render``: a picture of the face with the sphere.

Rows are printed and written (``--out``, JSON) after every pose, so a long run keeps what it
measured; ``--max-poses`` stops after that many poses (404K tets on 2 ranks: a pose is minutes).

    python benchmarks/cheek_sphere.py --tets 5000 --out benchmarks/results/contact/cheek_sphere_5k.json \\
        --plot benchmarks/results/contact/cheek_sphere_5k_pressure.png --render cheek_sphere_5k.png
    mpirun -n 2 python benchmarks/cheek_sphere.py --tets 400000 --max-poses 3 --out ...
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
from face_dolfinx.model.bones import AffineMap, jaw_pose  # noqa: E402
from face_dolfinx.model.folder import load_model  # noqa: E402
from face_dolfinx.physics.contact import ContactSettings, Sphere  # noqa: E402
from face_dolfinx.physics.face_contact import FaceContactPotential, smoothed_pressure  # noqa: E402
from face_dolfinx.physics.problem import FaceProblem  # noqa: E402
from face_dolfinx.results.render import render_skin  # noqa: E402
from face_dolfinx.results.xdmf import displacement_at  # noqa: E402

# The sphere waits this far (mm) off the rest skin while the expression is solved.
WAITING_CLEARANCE = 10.0
# Skin triangles whose centroid lies within the radius plus this (mm) of the centre are measured.
TRIANGLE_REACH = 30.0
PENETRATION_LIMIT = 0.05  # mm: the criterion


def triangle_distances(centre: np.ndarray, corners: np.ndarray) -> np.ndarray:
    """Distance of ``centre`` to each triangle (corners (m, 3, 3)): to the projection on its plane
    where that falls inside the triangle, else to the nearest of its three edges."""
    a, b, c = corners[:, 0], corners[:, 1], corners[:, 2]
    ab, ac, ap = b - a, c - a, centre - a
    normal = np.cross(ab, ac)
    area2 = np.einsum("ij,ij->i", normal, normal)
    # Barycentric coordinates of the projection.
    v = np.einsum("ij,ij->i", np.cross(ap, ac), normal) / area2
    w = np.einsum("ij,ij->i", np.cross(ab, ap), normal) / area2
    inside = (v >= 0.0) & (w >= 0.0) & (v + w <= 1.0)
    plane = np.abs(np.einsum("ij,ij->i", ap, normal)) / np.sqrt(area2)

    def to_segment(p, q):
        d = q - p
        t = np.clip(np.einsum("ij,ij->i", centre - p, d) / np.einsum("ij,ij->i", d, d), 0.0, 1.0)
        return np.linalg.norm(centre - (p + t[:, None] * d), axis=1)

    edges = np.minimum(np.minimum(to_segment(a, b), to_segment(b, c)), to_segment(c, a))
    return np.where(inside, plane, edges)


def deepest_triangle_point(contact, displacement: np.ndarray, radius: float) -> float:
    """How far (mm) the deepest point of any contact-surface triangle lies inside the sphere
    (negative: every triangle is clear, by that much)."""
    x = contact.positions(displacement)
    centre = contact.poses[0].translation
    corners = x[contact.surface.triangles]
    near = np.linalg.norm(corners.mean(axis=1) - centre, axis=1) < radius + TRIANGLE_REACH
    if not near.any():
        return -np.inf
    return float(radius - triangle_distances(centre, corners[near]).min())


class FailureCount(logging.Handler):
    """Counts the equilibrium solver's failed Newton solves (continuation halves the step)."""

    def __init__(self):
        super().__init__()
        self.count = 0

    def emit(self, record):
        if record.getMessage().startswith("Newton failed"):
            self.count += 1

    @classmethod
    def attached(cls) -> "FailureCount":
        """A count listening to the equilibrium solver's log."""
        failures = cls()
        solver_log = logging.getLogger("face_dolfinx.equilibrium.solver")
        solver_log.addHandler(failures)
        solver_log.setLevel(min(solver_log.getEffectiveLevel(), logging.INFO))
        return failures

    def solve(self, problem, pose) -> tuple:
        """``problem`` solved with its one object at ``pose``, counting from 0: (report, seconds)."""
        self.count = 0
        started = time.perf_counter()
        report = problem.solve(objects=(pose,))
        return report, time.perf_counter() - started


def keep_pose(summary: dict, row: dict, out: pathlib.Path, comm) -> None:
    """A pose's row joins ``summary``, which rank 0 writes to ``out`` at once (a long run keeps
    what it measured) after printing the row."""
    summary["poses"].append(row)
    if comm.rank == 0:
        print(json.dumps(row), flush=True)
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(summary, indent=1) + "\n")


def cheek_frame(model, site_name: str, u=None) -> tuple[np.ndarray, np.ndarray]:
    """The marker site on the skin displaced by ``u`` (at rest without) and the skin's outward unit
    normal there (area-weighted over the triangles within 12 mm). Collective."""
    points, triangles = model.skin_surface()
    site = np.asarray(model.markers[site_name], dtype=float)
    if u is not None:
        points = points + displacement_at(u, points)
        site = site + displacement_at(u, site[None])[0]
    moved = points
    corners = moved[triangles]
    normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    normal = normals[np.linalg.norm(corners.mean(axis=1) - site, axis=1) < 12.0].sum(axis=0)
    return site, normal / np.linalg.norm(normal)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tets", type=int, default=5000)
    parser.add_argument("--expression", default="smile", help="an expression of the model ('neutral': none)")
    parser.add_argument("--radius", type=float, default=15.0, help="mm")
    parser.add_argument("--depths", default="0,1,2,3,4",
                        help="comma-separated depths (mm) of the sphere into the skin, one pose each, after a "
                             "first pose 1 mm outside")
    parser.add_argument("--site", default="nasolabial_left_3", help="the marker site the sphere aims at")
    parser.add_argument("--degree", type=int, default=1, help="the displacement's polynomial degree (1 or 2)")
    parser.add_argument("--dhat", type=float, default=0.05)
    parser.add_argument("--stiffness", type=float, default=10.0)
    parser.add_argument("--nodes", action="store_true", help="keep only the skin's nodes out of the sphere, not its "
                                                             "triangles")
    parser.add_argument("--max-poses", type=int, default=None, help="stop after this many poses")
    parser.add_argument("--out", required=True)
    parser.add_argument("--plot")
    parser.add_argument("--render", help="PNG of the face with the sphere at the deepest pose")
    parser.add_argument("--view", default="side", help="the render's view (front, three_quarter, side)")
    args = parser.parse_args()
    comm = MPI.COMM_WORLD
    depths = [-1.0] + [float(d) for d in args.depths.split(",")]
    if args.max_poses is not None:
        depths = depths[:args.max_poses]

    model = load_model(build_builtin_face(target_tets=args.tets, comm=comm), comm)
    if args.expression not in model.expressions:
        raise SystemExit(f"--expression {args.expression}: the model defines {', '.join(sorted(model.expressions))}")
    if args.site not in model.markers:
        raise SystemExit(f"--site {args.site}: not a marker site of the model")
    radius = args.radius
    rest_site, rest_normal = cheek_frame(model, args.site)
    waiting = AffineMap(np.eye(3), rest_site + (radius + WAITING_CLEARANCE) * rest_normal)
    began = time.perf_counter()
    settings = ContactSettings((Sphere(radius),), (waiting,), dhat=args.dhat, stiffness=args.stiffness,
                               faces=not args.nodes)
    problem = FaceProblem(model, degree=args.degree, contact=settings)
    contact = problem.contact
    failures = FailureCount.attached()
    spec = dict(model.expressions[args.expression])
    opening = np.radians(spec.pop("jaw_opening_deg", 0.0))
    report = problem.solve(activations=spec, jaw=jaw_pose(model.jaw, opening) if opening else AffineMap())
    site, normal = cheek_frame(model, args.site, problem.u)
    rest = contact.surface.rest[contact.surface.triangles]  # flat triangles (four per P2 facet)
    median_edge = float(np.median(np.linalg.norm(rest - np.roll(rest, 1, axis=1), axis=2)))
    faces = isinstance(contact, FaceContactPotential)
    summary = dict(tets=model.mesh.topology.index_map(3).size_global, ranks=comm.size, degree=args.degree,
                   barrier="skin triangles" if faces else "skin nodes",
                   expression=args.expression, radius_mm=radius, dhat_mm=args.dhat, stiffness_kPa=args.stiffness, site=args.site,
                   site_mm=site.round(4).tolist(), normal=normal.round(6).tolist(),
                   skin_nodes=contact.surface.num_nodes, skin_triangles=len(contact.surface.triangles),
                   median_skin_edge_mm=round(median_edge, 3), expression_newton_iterations=report.newton_iterations,
                   expression_load_steps=report.load_steps, expression_seconds=round(report.seconds, 2),
                   set_up_and_expression_seconds=round(time.perf_counter() - began, 2), poses=[])
    if comm.rank == 0:
        print(json.dumps({k: v for k, v in summary.items() if k != "poses"}), flush=True)

    iterate_gaps, iterate_dips = [], []

    def monitor(snes, iteration, norm):
        x = snes.getSolution().array_r
        gaps = contact.gaps(x)[0]
        deepest = int(np.argmin(gaps))
        iterate_gaps.append((float(gaps[deepest]), deepest))
        iterate_dips.append(deepest_triangle_point(contact, x, radius))

    problem.solver.snes.setMonitor(monitor)
    out = pathlib.Path(args.out)
    for index, depth in enumerate(depths):
        pose = AffineMap(np.eye(3), site + (radius - depth) * normal)
        iterate_gaps.clear()
        iterate_dips.clear()
        report, seconds = failures.solve(problem, pose)
        u = problem.u.x.array
        gap, node = min(iterate_gaps) if iterate_gaps else (contact.min_gap(u), 0)
        forces = contact.nodal_forces(u)
        on_sphere = forces.sum(axis=0)
        dip = deepest_triangle_point(contact, u, radius)
        row = dict(pose=index, depth_mm=depth, converged=report.converged, newton_iterations=report.newton_iterations,
                   load_steps=report.load_steps, failed_newton_solves=failures.count, seconds=round(seconds, 2),
                   smallest_gap_any_iterate_mm=gap, deepest_node_rest_mm=contact.surface.rest[node].round(3).tolist(),
                   smallest_gap_mm=contact.min_gap(u), contact_nodes=contact.contact_nodes(u),
                   contact_triangles=contact.contact_triangles(u) if faces else None,
                   force_on_sphere_mN=on_sphere.round(4).tolist(),
                   force_along_normal_mN=round(float(on_sphere @ normal), 4),
                   deepest_triangle_point_inside_mm=dip,
                   deepest_triangle_point_inside_any_iterate_mm=max(iterate_dips, default=dip))
        keep_pose(summary, row, out, comm)
    problem.solver.snes.cancelMonitor()

    # Pressure per skin node at the deepest pose: the barrier's nodal force over the node's area,
    # the triangles' pressures averaged around the node, and the nodal forces and areas summed
    # with hat weights over one median skin edge (plotted).
    u = problem.u.x.array
    x = contact.positions(u)
    centre = contact.poses[0].translation
    axial = (x - centre) @ normal
    off_axis = np.linalg.norm((x - centre) - axial[:, None] * normal, axis=1)
    force_over_area = np.linalg.norm(contact.nodal_forces(u), axis=1) / contact.surface.areas
    summary.update(nodal_force_over_area=pressure_statistics(contact.surface.triangles, force_over_area, off_axis, x, normal))
    pressure = force_over_area
    if faces:
        pressure = contact.face_pressure(u)
        summary.update(triangle_average=pressure_statistics(contact.surface.triangles, pressure, off_axis, x, normal))
    filtered = smoothed_pressure(x, contact.nodal_forces(u), contact.surface.areas, median_edge)
    summary.update(filtered_at_one_edge=pressure_statistics(contact.surface.triangles, filtered, off_axis, x, normal))
    pressure = filtered
    pressed = pressure > 0.0
    summary.update(plotted_pressure="filtered_at_one_edge",
                   **summary["filtered_at_one_edge"],
                   pressure_kPa_by_distance_from_axis_mm=[[round(float(r), 3), round(float(p), 3)] for r, p in
                                                          sorted(zip(off_axis[pressed], pressure[pressed]))],
                   total_seconds=round(time.perf_counter() - began, 2))
    if args.render:
        skin_points, skin_triangles = model.skin_surface()
        moved = skin_points + displacement_at(problem.u, skin_points)
        if comm.rank == 0:
            sphere_points, sphere_triangles = Sphere(radius).surface(refinements=4)
            deepest = summary["poses"][-1]
            render_skin(moved, skin_triangles, args.render, view=args.view,
                        objects=[(sphere_points + centre, sphere_triangles)],
                        title=f"{args.expression}, sphere R {radius:g} mm {deepest['depth_mm']:g} mm into the cheek, "
                              f"{summary['tets']} tets")
            record(args.render, tets=args.tets, ranks=comm.size)
    if comm.rank == 0:
        print(json.dumps({k: v for k, v in summary.items() if k not in ("poses", "pressure_kPa_by_distance_from_axis_mm",
                                                                        "nodal_force_over_area", "triangle_average",
                                                                        "filtered_at_one_edge")}),
              flush=True)
        out.write_text(json.dumps(summary, indent=1) + "\n")
        record(out, tets=args.tets, ranks=comm.size)
        if args.plot:
            plot(args.plot, summary, x, pressure, centre, normal, off_axis)
            record(args.plot, tets=args.tets, ranks=comm.size)


def pressure_statistics(triangles: np.ndarray, pressure: np.ndarray, off_axis: np.ndarray, x: np.ndarray,
                        normal: np.ndarray) -> dict:
    """Pressed nodes, peak and median pressure, the patch radius, isolated spikes (a pressed node
    with more than twice the pressure of every neighbour) and the fit of Hertz's profile against
    the distance from the sphere's axis and, as well, from the line along the path through the
    centre of pressure (the pressure-weighted mean of the nodes): on the curved cheek the patch
    need not be centred on the sphere's path."""
    edges = np.unique(np.sort(np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]]),
                              axis=1), axis=0)
    neighbour_peak = np.zeros(len(pressure))
    np.maximum.at(neighbour_peak, edges[:, 0], pressure[edges[:, 1]])
    np.maximum.at(neighbour_peak, edges[:, 1], pressure[edges[:, 0]])
    pressed = pressure > 0.0
    centre = pressure @ x / max(pressure.sum(), 1e-300)
    offset = x - centre
    off_centre = np.linalg.norm(offset - (offset @ normal)[:, None] * normal, axis=1)
    return dict(pressed_nodes=int(pressed.sum()), peak_pressure_kPa=float(pressure.max()),
                median_pressure_of_pressed_nodes_kPa=float(np.median(pressure[pressed])) if pressed.any() else 0.0,
                contact_patch_radius_mm=float(off_axis[pressed].max()) if pressed.any() else 0.0,
                isolated_spikes=int((pressed & (pressure > 2.0 * neighbour_peak)).sum()),
                hertz_fit=hertz_profile(off_axis[pressed], pressure[pressed]) if pressed.sum() >= 2 else None,
                hertz_fit_about_centre_of_pressure=(hertz_profile(off_centre[pressed], pressure[pressed])
                                                    if pressed.sum() >= 2 else None))


def hertz_profile(radii: np.ndarray, pressures: np.ndarray) -> dict:
    """The least-squares fit p0 sqrt(1 - (r / a)^2) (0 beyond a) of the pressed nodes' pressures
    against their distance r from the sphere's axis (Hertz's profile; a over a grid from 0.3 to 2
    times the outermost pressed node's r, p0 in closed form), and the pressures' RMS scatter about
    it relative to p0: a smooth pressure lies close to one such profile, node-to-node noise does
    not. (A field with a faint rim, as a filtered one has, fits an a inside its outermost node.)"""
    best = None
    for a in np.linspace(0.3, 2.0, 171) * radii.max():
        shape = np.sqrt(np.clip(1.0 - (radii / a) ** 2, 0.0, None))
        if not shape.any():  # a inside every pressed node
            continue
        p0 = float(shape @ pressures / (shape @ shape))
        rms = float(np.sqrt(np.mean((pressures - p0 * shape) ** 2)))
        if best is None or rms < best["rms_kPa"]:
            best = dict(p0_kPa=round(p0, 3), a_mm=round(float(a), 3), rms_kPa=rms)
    best.update(rms_kPa=round(best["rms_kPa"], 3), relative_scatter=round(best["rms_kPa"] / best["p0_kPa"], 4))
    return best


def plot(path, summary, x, pressure, centre, normal, off_axis):
    """Left: the pressure of the skin nodes around the patch seen along the sphere's path; right:
    the pressure against the distance from the sphere's axis."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    pressed = pressure > 0.0
    reach = max(1.5 * summary["contact_patch_radius_mm"], 3.0 * summary["median_skin_edge_mm"])
    shown = (off_axis < reach) & ((x - centre) @ normal < 0.0)  # the cheek, not the skin behind the sphere
    # In-plane axes: the model's x (across the face) and the direction up the face, made orthogonal to the normal.
    across = np.array([1.0, 0.0, 0.0]) - normal[0] * normal
    across /= np.linalg.norm(across)
    up = np.cross(normal, across)
    plane = (x - centre) @ np.c_[across, up]
    figure, (left, right) = plt.subplots(1, 2, figsize=(10, 4.2))
    scatter = left.scatter(plane[shown, 0], plane[shown, 1], c=pressure[shown], s=14 + 30 * pressed[shown],
                           cmap="inferno", edgecolors="grey", linewidths=0.3)
    left.add_patch(plt.Circle((0.0, 0.0), summary["contact_patch_radius_mm"], fill=False, linestyle="--"))
    left.set_aspect("equal")
    left.set_xlabel("across the face (mm)")
    left.set_ylabel("up the face (mm)")
    left.set_title("skin nodes seen along the sphere's path")
    figure.colorbar(scatter, ax=left, label="contact pressure (kPa)")
    right.scatter(off_axis[shown], pressure[shown], s=12, label="skin nodes")
    fit = summary["hertz_fit"]
    if fit is not None:
        r = np.linspace(0.0, fit["a_mm"], 100)
        right.plot(r, fit["p0_kPa"] * np.sqrt(1.0 - (r / fit["a_mm"]) ** 2), "k--",
                   label=f"p0 sqrt(1 - (r/a)^2), scatter {100 * fit['relative_scatter']:.0f} % of p0")
        right.legend(fontsize=8)
    right.set_xlabel("distance from the sphere's axis (mm)")
    right.set_ylabel("contact pressure (kPa)")
    right.set_title("pressure profile")
    deepest = summary["poses"][-1]
    figure.suptitle(f"sphere R {summary['radius_mm']:g} mm, {deepest['depth_mm']:g} mm into the cheek, "
                    f"{summary['expression']}, {summary['tets']} tets P{summary['degree']}, barrier on the {summary['barrier']}: "
                    f"{summary['pressed_nodes']} pressed nodes, "
                    f"force {deepest['force_along_normal_mN']:.0f} mN", fontsize=10)
    figure.tight_layout()
    figure.savefig(path, dpi=120)
    plt.close(figure)


if __name__ == "__main__":
    main()
