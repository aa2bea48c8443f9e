"""Rigid triangle-mesh contact objects (face_dolfinx.physics.rigid_mesh): distances, gradients and
Hessians against the IPC Toolkit's point-triangle ones, signs against analytic solids, the barrier's
gradient and Hessian against differences of its energy, the smooth barrier over the triangles,
edges and vertices (that of the distance on convex surfaces, against every feature, its derivatives
next to a concave edge and vertex), no node inside at any Newton iterate, the
tessellated sphere against the analytic one, files of every format, bad input, and
``run.py simulate --object mesh:FILE``.
"""
from mpi4py import MPI
import meshio
import numpy as np
import pytest

import ipctk
from face_dolfinx.alignment.surface import closest_points
from face_dolfinx.model.bones import AffineMap, rotation
from face_dolfinx.physics.contact import ContactSettings, Sphere, barrier, barrier_derivatives
from face_dolfinx.physics.problem import FaceProblem
from face_dolfinx.model.surface_file import read_triangle_surface
from face_dolfinx.physics.rigid_mesh import TriangleMesh
from test_contact import ACTIVATIONS, RADIUS, assert_barrier_derivatives, cheek_path, skin_slab, sphere_at

ICOSPHERE = Sphere(RADIUS).surface(4)  # 5120 triangles, edges about 0.6 mm


def box(size=(2.0, 3.0, 4.0), lower=(0.0, 0.0, 0.0)):
    """An axis-aligned box [lower, lower + size] as 12 outward triangles."""
    corners = np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)], dtype=float) * size + lower
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    triangles = [t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))]
    return corners, np.array(triangles)


def test_distances_and_hessians_are_the_ipc_toolkits():
    """Gap, normal and gap Hessian of points around a tilted tetrahedron (face, edge and vertex
    regions) against ipctk's point-triangle distance of the closest triangle and its Hessian."""
    points = np.array([[0.0, 0.0, 0.0], [3.0, 0.2, 0.1], [0.5, 2.5, -0.3], [0.7, 0.4, 2.2]])
    mesh = TriangleMesh(points, np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]]))
    pose = AffineMap(rotation(np.array([0.0, 0.6, 0.8]), 0.7), [5.0, -2.0, 1.0])
    rng = np.random.default_rng(1)
    local = rng.uniform(-1.5, 4.0, size=(400, 3))
    gap, normal, hessian = mesh.gaps(pose.apply(local), pose)
    seen = set()
    for x, g, n, h in zip(local, gap, normal, hessian):
        squared = [ipctk.point_triangle_distance(x, *corners) for corners in mesh.corners]
        k = int(np.argmin(squared))
        d = np.sqrt(squared[k])
        assert abs(g) == pytest.approx(d, rel=1e-12, abs=1e-12)
        if g <= 0.0:
            continue
        # d(d^2)/dx = 2 d n, d2(d^2)/dx2 = 2 n n^T + 2 d d2g/dx2; the point's 3 x 3 block, in the world.
        R = pose.matrix
        grad = ipctk.point_triangle_distance_gradient(x, *mesh.corners[k])[:3]
        assert R @ grad / (2 * d) == pytest.approx(n, abs=1e-10)
        full = ipctk.point_triangle_distance_hessian(x, *mesh.corners[k])[:3, :3]
        local_n = grad / (2 * d)
        expected = R @ ((full / 2 - np.outer(local_n, local_n)) / d) @ R.T
        assert np.abs(h - expected).max() <= 1e-9 * max(1.0, np.abs(expected).max())
        seen.add(int(closest_points(x[None], *mesh.corners[k][:, None, :])[2][0]))
    assert seen == set(range(7))  # every region: the face, three edges, three vertices


def test_signs_against_analytic_solids():
    corners, triangles = box()
    mesh = TriangleMesh(corners, triangles[:, ::-1])   # inward triangles are turned outward
    rng = np.random.default_rng(2)
    x = rng.uniform(-1.0, 5.0, size=(3000, 3))
    inside = (x > 0).all(axis=1) & (x < (2.0, 3.0, 4.0)).all(axis=1)
    outside_distance = np.linalg.norm(np.maximum(np.maximum(-x, x - (2.0, 3.0, 4.0)), 0.0), axis=1)
    inside_distance = np.minimum(x, (2.0, 3.0, 4.0) - x).min(axis=1)
    gap = mesh.gaps(x, AffineMap())[0]
    assert np.array_equal(gap > 0, ~inside)
    assert np.abs(gap - np.where(inside, -inside_distance, outside_distance)).max() < 1e-12
    sphere = TriangleMesh(*ICOSPHERE)
    around = (x - 2.0) * 4.0   # points from 0 to 12 mm from its centre
    r = np.linalg.norm(around, axis=1)
    gap = sphere.gaps(around, AffineMap())[0]
    # The inscribed polyhedron lies between the sphere and its faces' planes.
    sagitta = RADIUS - np.einsum("ij,ij->i", sphere.normals, sphere.corners[:, 0]).min() + 1e-12
    assert sagitta < 0.015
    clear = np.abs(r - RADIUS) > sagitta
    assert np.array_equal((gap > 0)[clear], (r > RADIUS)[clear])
    assert np.abs(gap - (r - RADIUS)).max() <= sagitta


def test_collision_free_step_bound():
    """first_contact is a lower bound of the exact time at which a point comes within the
    clearance (measured by bisection along the step), and lets a point slide along a face."""
    corners, triangles = box((4.0, 4.0, 4.0))
    mesh = TriangleMesh(corners, triangles)
    rng = np.random.default_rng(3)
    x = rng.uniform(-2.0, 6.0, size=(150, 3))
    x = x[mesh.gaps(x, AffineMap())[0] > 0.05]
    steps = rng.normal(size=x.shape) * 3.0
    clearance = 0.2 * mesh.gaps(x, AffineMap())[0]
    bound = mesh.first_contact(x, steps, AffineMap(), clearance)
    times = np.linspace(0.0, 1.0, 1001)
    for point, step, c, t in zip(x, steps, clearance, bound):
        gaps = mesh.gaps(point + times[:, None] * step, AffineMap())[0]
        hit = np.flatnonzero(gaps <= c)
        exact = times[hit[0]] if hit.size else np.inf
        assert t <= exact + 1e-12
    # Sliding 1 mm along the top face at a gap of 0.01 mm (a step bound by the gap alone: 0.008).
    slide = mesh.first_contact(np.array([[1.0, 1.0, 4.01]]), np.array([[1.0, 0.0, 0.0]]), AffineMap(), np.array([0.002]))
    assert slide[0] >= 1.0


def test_files_and_bad_input(tmp_path):
    corners, triangles = box()
    for suffix in ("obj", "stl", "ply", "off"):
        path = tmp_path / f"box.{suffix}"
        meshio.write(path, meshio.Mesh(corners, [("triangle", triangles)]), **({"binary": False} if suffix == "stl" else {}))
        points, read = read_triangle_surface(path)
        assert len(read) == 12 and len(points) == 8
        volume = np.einsum("ij,ij->i", points[read[:, 0]], np.cross(points[read[:, 1]], points[read[:, 2]])).sum() / 6
        assert volume == pytest.approx(24.0)
    meshio.write(tmp_path / "open.obj", meshio.Mesh(corners, [("triangle", triangles[1:])]))
    with pytest.raises(ValueError, match=r"open.obj: not a closed surface: 3 edges are open"):
        TriangleMesh.read(tmp_path / "open.obj")
    flipped = triangles.copy()
    flipped[0] = flipped[0, ::-1]
    meshio.write(tmp_path / "flipped.off", meshio.Mesh(corners, [("triangle", flipped)]))
    with pytest.raises(ValueError, match="flipped.off: the triangles are not consistently oriented"):
        TriangleMesh.read(tmp_path / "flipped.off")
    meshio.write(tmp_path / "quads.obj", meshio.Mesh(corners, [("quad", np.array([[0, 1, 3, 2]]))]))
    with pytest.raises(ValueError, match="quads.obj: not a triangle surface .it holds quad cells"):
        TriangleMesh.read(tmp_path / "quads.obj")
    (tmp_path / "junk.stl").write_text("not a mesh\n")
    with pytest.raises(ValueError, match="junk.stl: cannot read a triangle surface"):
        TriangleMesh.read(tmp_path / "junk.stl")


def pressed_slab(obj, depth=1.5, comm=MPI.COMM_WORLD):
    """With the nodal barrier for an analytic sphere too, as for the triangle mesh."""
    settings = ContactSettings((obj,), (sphere_at(-1.0),), dhat=0.05, stiffness=10.0, faces=False)
    problem = FaceProblem(skin_slab(comm), contact=settings)
    problem.solve(activations=ACTIVATIONS, objects=(sphere_at(depth),))
    return problem


@pytest.fixture(scope="module")
def slab():
    return pressed_slab(TriangleMesh(*ICOSPHERE, name="icosphere"))


def test_gradient_and_hessian_against_differences_of_the_energy(slab):
    gaps = slab.contact.gaps(slab.u.x.array)[0]
    assert (gaps < slab.contact.dhat).sum() >= 4
    assert_barrier_derivatives(slab, slab.contact)


def test_tessellated_sphere_against_the_analytic_one(slab):
    """Same indentation: the force on the 5120-triangle sphere within 1 % of the analytic sphere's,
    no node inside at any Newton iterate of a further press."""
    analytic = pressed_slab(Sphere(RADIUS))
    force = slab.contact.nodal_forces(slab.u.x.array).sum(axis=0)[2]
    expected = analytic.contact.nodal_forces(analytic.u.x.array).sum(axis=0)[2]
    assert force == pytest.approx(expected, rel=0.01)
    gaps = []
    slab.solver.snes.setMonitor(lambda snes, it, norm: gaps.append(slab.contact.min_gap(snes.getSolution().array_r)))
    report = slab.solve(objects=(sphere_at(2.5),))
    slab.solver.snes.cancelMonitor()
    assert report.converged and len(gaps) > 3 and min(gaps) > 0.0
    assert slab.residual_norm() < 1e-6


def test_same_result_on_one_rank(slab):
    slab.solve(objects=(sphere_at(1.5),))
    serial = pressed_slab(TriangleMesh(*ICOSPHERE), comm=MPI.COMM_SELF)
    here = slab.contact.nodal_forces(slab.u.x.array).sum(axis=0)
    alone = serial.contact.nodal_forces(serial.u.x.array).sum(axis=0)
    assert np.abs(here - alone).max() <= 1e-7 * np.abs(alone).max()


def test_object_mesh_starting_inside_is_refused():
    settings = ContactSettings((TriangleMesh(*ICOSPHERE, name="ball.stl"),), (sphere_at(0.5),), where="path.txt")
    with pytest.raises(ValueError, match=r"path.txt: the triangle surface ball.stl \(5120 triangles\) .* starts inside the skin"):
        FaceProblem(skin_slab(cells=(8, 4, 2)), contact=settings)


@pytest.mark.parametrize("obj, pose, message", [
    # an instrument's tip 1 mm deep between the top face's nodes (5 mm apart)
    (TriangleMesh(*box((1.0, 1.0, 5.0), lower=(21.0, 11.0, 9.0)), name="tip.stl"), AffineMap(),
     r"triangle surface tip.stl \(12 triangles\) at \[0.0, 0.0, 0.0\]: 4 of its 8 vertices lie inside the flesh"),
    # a blade 0.2 mm thick through the top face between two rows of nodes, its ends beyond the slab
    (TriangleMesh(*box((50.0, 0.2, 2.0), lower=(-5.0, 12.0, 9.0)), name="blade.stl"), AffineMap(),
     r"triangle surface blade.stl \(12 triangles\) at \[0.0, 0.0, 0.0\] crosses the triangles of the skin between their nodes"),
    # a ball smaller than the cells, inside the flesh
    (Sphere(0.5), AffineMap(np.eye(3), [21.3, 11.7, 6.2]), r"sphere .* its centre lies inside the flesh"),
])
def test_object_inside_the_flesh_with_no_node_inside_it_is_refused(obj, pose, message):
    """Objects that no skin node is inside but that lie inside the face (smaller than its cells,
    through its triangles between their nodes): one clear error before any solve."""
    with pytest.raises(ValueError, match="path.txt: the " + message):
        FaceProblem(skin_slab(cells=(8, 4, 2)), contact=ContactSettings((obj,), (pose,), where="path.txt"))


def test_simulate_moves_a_mesh_along_a_path(model, shared_dir):
    """run.py simulate --object mesh:FILE --path FILE on the small face: the icosphere in the
    cheek (its vertices kept off the skin's triangles), a frame per pose, the object's series; bad
    files stop it before any solve."""
    import json
    from face_dolfinx.cli.main import main
    from conftest import on_rank_0
    mesh_file, path, out = shared_dir / "ball.ply", shared_dir / "path.txt", shared_dir / "pressed"
    points, triangles = Sphere(15.0).surface(3)
    centres = cheek_path(model, [-1.0, 2.0, 0.0])
    on_rank_0(lambda: (meshio.write(mesh_file, meshio.Mesh(points, [("triangle", triangles)])),
                       path.write_text("\n".join(" ".join(f"{v:.6f}" for v in c) for c in centres) + "\n")))
    model_path = str(model.path)
    assert main(["simulate", "--model", model_path, "--object", f"mesh:{mesh_file}", "--path", str(path),
                 "--out", str(out), "--no-render"]) == 0
    rows = json.loads((out / "summary.json").read_text())["object"]
    assert [row["pose"] for row in rows] == [0, 1, 2]
    # Pressed 2 mm in, the ball's vertices hold the skin's triangles off it (object_features.py):
    # they, not the skin's nodes (0.39 mm away around them), carry the contact; on the small face's
    # flat triangles (edges of several mm) only the vertices next to a triangle's tangent point are
    # within dhat of it.
    assert rows[1]["contact_vertices"] >= 1 and 0.0 < rows[1]["min_vertex_gap_mm"] < 0.05
    assert rows[1]["min_gap_mm"] > 0.0 and np.linalg.norm(rows[1]["force_on_object_mN"]) > 100.0 and rows[2]["contact_nodes"] == 0
    assert (out / "object.xdmf").exists()
    on_rank_0(lambda: meshio.write(shared_dir / "open.ply", meshio.Mesh(points, [("triangle", triangles[1:])])))
    with pytest.raises(SystemExit, match="open.ply: not a closed surface"):
        main(["simulate", "--model", model_path, "--object", f"mesh:{shared_dir / 'open.ply'}", "--path", str(path),
              "--out", str(shared_dir / "never"), "--no-render"])
    with pytest.raises(SystemExit, match="missing.obj: cannot read"):
        main(["simulate", "--model", model_path, "--object", f"mesh:{shared_dir / 'missing.obj'}", "--path", str(path),
              "--out", str(shared_dir / "never"), "--no-render"])
    inside, pressed_in = shared_dir / "inside.txt", cheek_path(model, [3.0])[0]   # collective
    on_rank_0(lambda: inside.write_text(" ".join(f"{v:.6f}" for v in pressed_in) + "\n"))
    with pytest.raises(SystemExit, match=r"inside.txt .its first pose.: the triangle surface .*ball.ply .* starts inside the skin"):
        main(["simulate", "--model", model_path, "--object", f"mesh:{mesh_file}", "--path", str(inside),
              "--out", str(shared_dir / "never"), "--no-render"])


def dented_box(depth=0.1):
    """[0, 4] x [0, 4] x [-3, 0] with the top's centre pushed ``depth`` down: a concave vertex at
    (2, 2, -depth) and four concave edges to the top's corners (2.9 degrees for 0.1 mm, about the
    built-in teeth's steepest)."""
    points = np.array([[0, 0, 0], [4, 0, 0], [4, 4, 0], [0, 4, 0], [0, 0, -3], [4, 0, -3], [4, 4, -3], [0, 4, -3],
                       [2, 2, -depth]], dtype=float)
    triangles = [(8, 0, 1), (8, 1, 2), (8, 2, 3), (8, 3, 0), (4, 6, 5), (4, 7, 6), (0, 4, 5), (0, 5, 1), (1, 5, 6),
                 (1, 6, 2), (2, 6, 7), (2, 7, 3), (3, 7, 4), (3, 4, 0)]
    return TriangleMesh(points, np.array(triangles), name="dented box")


def smooth_barrier(mesh, x, dhat=0.5):
    """Per point: the barrier of ``mesh``'s terms summed (``barrier_terms``), its gradient and its
    Hessian."""
    which, sign, d, n, H = mesh.barrier_terms(x, AffineMap(), within=dhat)
    first, second = barrier_derivatives(d, dhat)
    energy, gradient, hessian = np.zeros(len(x)), np.zeros((len(x), 3)), np.zeros((len(x), 3, 3))
    np.add.at(energy, which, sign * barrier(d, dhat))
    np.add.at(gradient, which, (sign * first)[:, None] * n)
    np.add.at(hessian, which, sign[:, None, None] * (second[:, None, None] * n[:, :, None] * n[:, None, :]
                                                   + first[:, None, None] * H))
    return energy, gradient, hessian


def test_smooth_barrier_on_convex_surfaces_is_that_of_the_nearest_distance():
    """On a convex surface the terms of the edges cancel the duplicates of the triangles and
    vertices: the barrier is b of the distance to the surface, its gradient b' n."""
    rng = np.random.default_rng(4)
    for mesh in (TriangleMesh(*ICOSPHERE), TriangleMesh(*box())):
        centre = mesh.points.mean(axis=0)
        directions = rng.normal(size=(2000, 3))
        directions /= np.linalg.norm(directions, axis=1)[:, None]
        # Points outside, from the surface's farthest point out to 0.6 mm beyond it.
        reach = np.linalg.norm(mesh.points - centre, axis=1).max()
        x = centre + directions * rng.uniform(0.3 * reach, reach + 0.6, size=(2000, 1))
        gap, normal, _ = mesh.gaps(x, AffineMap())
        x, gap, normal = x[gap > 0.01], gap[gap > 0.01], normal[gap > 0.01]
        energy, gradient, _ = smooth_barrier(mesh, x)
        assert (gap < 0.5).sum() > 100
        assert np.abs(energy - barrier(gap, 0.5)).max() <= 1e-12 * np.abs(energy).max()
        expected = barrier_derivatives(gap, 0.5)[0][:, None] * normal
        assert np.abs(gradient - expected).max() <= 1e-10 * np.abs(expected).max()


def test_smooth_barrier_against_every_feature():
    """The terms of points near the dented box's concave edges and vertex against the sum over all
    its triangles, edges and vertices of ipctk's point-triangle, point-edge and point-point
    distances (signs +1, -1, +1)."""
    mesh = dented_box()
    rng = np.random.default_rng(5)
    x = np.column_stack([rng.uniform(0.5, 3.5, 300), rng.uniform(0.5, 3.5, 300), rng.uniform(0.02, 0.6, 300)])
    energy = smooth_barrier(mesh, x)[0]
    edges = np.unique(np.sort(np.concatenate([mesh.triangles[:, [0, 1]], mesh.triangles[:, [1, 2]],
                                              mesh.triangles[:, [2, 0]]]), axis=1), axis=0)
    for point, value in zip(x, energy):
        squared = ([(1.0, ipctk.point_triangle_distance(point, *corners)) for corners in mesh.corners]
                   + [(-1.0, ipctk.point_edge_distance(point, *mesh.points[e])) for e in edges]
                   + [(1.0, ipctk.point_point_distance(point, v)) for v in mesh.points])
        expected = sum(sign * barrier(np.sqrt(s), 0.5) for sign, s in squared)
        assert value == pytest.approx(expected, rel=1e-12, abs=1e-14)
    assert (energy > 0.0).sum() > 200


def test_smooth_barrier_derivatives_at_a_concave_edge_and_vertex():
    """Near the dented box's concave edges and vertex, where the nearest triangle changes and the
    gradient of b(distance to the surface) jumps: the smooth barrier's gradient and Hessian against
    central differences of its energy and gradient, and its gradient continuous across an edge."""
    mesh = dented_box()
    rng = np.random.default_rng(6)
    # Above the concave vertex, above points of the concave edges, and around them.
    on_edges = np.array([[2.0, 2.0, 0.0], [1.0, 1.0, 0.0], [3.0, 1.0, 0.0], [1.5, 2.5, 0.0]])
    x = np.vstack([on_edges + [0.0, 0.0, 0.2], rng.uniform((1.5, 1.5, 0.05), (2.5, 2.5, 0.45), size=(60, 3))])
    _, gradient, hessian = smooth_barrier(mesh, x)
    h = 1e-6
    for k in range(3):
        step = np.zeros(3)
        step[k] = h
        energy_difference = (smooth_barrier(mesh, x + step)[0] - smooth_barrier(mesh, x - step)[0]) / (2 * h)
        gradient_difference = (smooth_barrier(mesh, x + step)[1] - smooth_barrier(mesh, x - step)[1]) / (2 * h)
        assert np.abs(energy_difference - gradient[:, k]).max() <= 1e-6 * np.abs(gradient).max()
        assert np.abs(gradient_difference - hessian[:, :, k]).max() <= 1e-5 * np.abs(hessian).max()
    # Across the edge from the vertex to (0, 0, 0) at 0.2 mm: b(distance)'s gradient turns by the
    # edge's angle there, the smooth barrier's changes in proportion to the step.
    across = np.column_stack([1.0 + np.linspace(-0.05, 0.05, 1001), 1.0 - np.linspace(-0.05, 0.05, 1001),
                              np.full(1001, 0.2)])
    gap, normal, _ = mesh.gaps(across, AffineMap())
    nearest = barrier_derivatives(gap, 0.5)[0][:, None] * normal
    smooth, curvature = smooth_barrier(mesh, across)[1:]
    jump = np.linalg.norm(np.diff(nearest, axis=0), axis=1).max()
    change = np.linalg.norm(np.diff(smooth, axis=0), axis=1).max()
    spacing = np.linalg.norm(across[1] - across[0])
    assert jump > 0.05 * np.linalg.norm(nearest, axis=1).max()  # the nearest triangle's gradient jumps
    assert change <= 1.01 * spacing * np.linalg.norm(curvature, ord=2, axis=(1, 2)).max()
    assert change < 0.05 * jump
