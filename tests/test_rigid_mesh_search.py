"""The candidate search of ``TriangleMesh`` (face_dolfinx.physics.rigid_mesh) on a surface of small
and long skinny triangles: gaps, normals and Hessians against brute force over every triangle (and
the IPC Toolkit's Hessians), the distance bounds and the cut-off of ``gaps(within=...)``, the
smooth barrier's terms against a sum over every feature, and the collision-free step bound next to
the skinny triangles.
"""
import numpy as np
import pytest

import ipctk
from face_dolfinx.alignment.surface import closest_points
from face_dolfinx.model.bones import AffineMap, rotation
from face_dolfinx.physics.contact import Sphere, barrier
from face_dolfinx.physics.rigid_mesh import TriangleMesh
from test_contact_mesh import box

BALL = 2.0
ROD_CORNER, ROD_SIZE = np.array([3.0, -6.0, -0.25]), np.array([0.5, 12.0, 0.5])
POSE = AffineMap(rotation(np.array([0.3, -0.5, 0.8]), 1.1), [4.0, 1.0, -3.0])


@pytest.fixture(scope="module")
def ball_and_rod():
    """A ball of radius 2 mm (1280 triangles, edges about 0.3 mm) and beside it a rod of
    0.5 x 12 x 0.5 mm made of 12 triangles (the built-in teeth's side walls are 1 x 8 mm)."""
    points, triangles = Sphere(BALL).surface(3)
    corners, rod = box(tuple(ROD_SIZE))
    mesh = TriangleMesh(np.vstack([points, corners + ROD_CORNER]), np.vstack([triangles, rod + len(points)]))
    # The rod's triangles are split into many samples; the covering radius stays that of the ball's.
    assert mesh.covering_radius < 0.5
    return mesh


def brute_force(mesh, points):
    """Distance, closest point and nearest triangle of each point, over every triangle."""
    a, b, c = mesh.corners[:, 0], mesh.corners[:, 1], mesh.corners[:, 2]
    distance, closest, nearest = np.empty(len(points)), np.empty((len(points), 3)), np.empty(len(points), dtype=int)
    for i, x in enumerate(points):
        p = closest_points(np.broadcast_to(x, a.shape), a, b, c)[0]
        d = np.linalg.norm(x - p, axis=1)
        nearest[i] = np.argmin(d)
        distance[i], closest[i] = d[nearest[i]], p[nearest[i]]
    return distance, closest, nearest


def near_and_far(mesh, count, seed):
    """Points (local frame) near the surface (within about 0.1 mm) and far from it (up to 10 mm)."""
    rng = np.random.default_rng(seed)
    triangles = rng.integers(len(mesh.triangles), size=count)
    weights = rng.dirichlet(np.ones(3), size=count)
    on_surface = np.einsum("ik,ikd->id", weights, mesh.corners[triangles])
    near = on_surface + rng.normal(scale=0.05, size=on_surface.shape)
    far = rng.uniform(-8.0, 10.0, size=(count, 3))
    return np.vstack([near, far])


def inside(x):
    in_rod = ((x >= ROD_CORNER) & (x <= ROD_CORNER + ROD_SIZE)).all(axis=1)
    return in_rod | (np.linalg.norm(x, axis=1) < BALL)


def test_gaps_normals_and_hessians_against_brute_force(ball_and_rod):
    mesh = ball_and_rod
    local = near_and_far(mesh, 300, seed=4)
    gap, normal, hessian = mesh.gaps(POSE.apply(local), POSE)
    distance, closest, nearest = brute_force(mesh, local)
    assert np.abs(np.abs(gap) - distance).max() <= 1e-12 * max(1.0, distance.max())
    # The sign: against the solids wherever the ball's facets cannot decide it.
    sagitta = BALL - np.einsum("ij,ij->i", mesh.normals, mesh.corners[:, 0])[:1280].min()
    clear = np.abs(np.linalg.norm(local, axis=1) - BALL) > sagitta
    assert np.array_equal((gap < 0)[clear], inside(local)[clear])
    R = POSE.matrix
    away = distance > 1e-9
    expected_normal = np.sign(gap)[:, None] * (local - closest) / np.maximum(distance, 1e-300)[:, None]
    assert np.abs(normal[away] - expected_normal[away] @ R.T).max() < 1e-9
    for x, g, h, d, k in zip(local[away], gap[away], hessian[away], distance[away], nearest[away]):
        grad = ipctk.point_triangle_distance_gradient(x, *mesh.corners[k])[:3]
        full = ipctk.point_triangle_distance_hessian(x, *mesh.corners[k])[:3, :3]
        local_n = grad / (2 * d)
        expected = np.sign(g) * R @ ((full / 2 - np.outer(local_n, local_n)) / d) @ R.T
        assert np.abs(h - expected).max() <= 1e-8 * max(1.0, np.abs(expected).max())


def test_cut_off_returns_lower_bounds_for_far_points_only(ball_and_rod):
    """gaps(within=...) (a number per point): the exact gap, normal and Hessian of every point
    closer than its cut-off, the same as without a cut-off; for the others a lower bound of the
    distance, at least the cut-off, and zeros. The distance bounds bracket the distance."""
    mesh = ball_and_rod
    local = near_and_far(mesh, 300, seed=5)
    local = local[~inside(local)]
    world = POSE.apply(local)
    exact, exact_normal, exact_hessian = mesh.gaps(world, POSE)
    within = np.random.default_rng(6).uniform(0.0, 3.0, size=len(local))
    gap, normal, hessian = mesh.gaps(world, POSE, within=within)
    computed = np.linalg.norm(normal, axis=1) > 0.0
    assert 50 < computed.sum() < len(local) - 50
    assert computed[exact < within].all()
    assert np.array_equal(gap[computed], exact[computed])
    assert np.array_equal(normal[computed], exact_normal[computed])
    assert np.array_equal(hessian[computed], exact_hessian[computed])
    skipped = ~computed
    assert (gap[skipped] >= within[skipped]).all() and (gap[skipped] <= exact[skipped]).all()
    assert not hessian[skipped].any()
    lower, upper = mesh.distance_bounds(local)
    assert (lower <= exact).all() and (exact <= upper).all()
    assert (upper - lower <= mesh.covering_radius + 1e-12).all()
    # A single cut-off for every point: dhat, as the contact terms ask.
    gap, normal, _ = mesh.gaps(world, POSE, within=0.05)
    assert np.array_equal(gap[exact < 0.05], exact[exact < 0.05])
    assert (gap[exact >= 0.05] <= exact[exact >= 0.05]).all()


def test_collision_free_step_bound_next_to_skinny_triangles(ball_and_rod):
    """first_contact is a lower bound of the exact time at which a point comes within the
    clearance (sampled along the step), also for points moving along the rod, and a point sliding
    2 mm along the rod's long face at a gap of 0.01 mm is not held back (the gap alone would
    allow 0.4 % of the step)."""
    mesh = ball_and_rod
    rng = np.random.default_rng(7)
    x = rng.uniform((2.0, -7.0, -1.25), (4.5, 7.0, 1.25), size=(120, 3))   # around the rod
    x = x[mesh.gaps(x, AffineMap())[0] > 0.05]
    steps = rng.normal(size=x.shape) * (1.5, 4.0, 1.5)
    clearance = 0.2 * mesh.gaps(x, AffineMap())[0]
    bound = mesh.first_contact(x, steps, AffineMap(), clearance)
    times = np.linspace(0.0, 1.0, 401)
    reached = 0
    for point, step, c, t in zip(x, steps, clearance, bound):
        gaps = mesh.gaps(point + times[:, None] * step, AffineMap())[0]
        hit = np.flatnonzero(gaps <= c)
        exact = times[hit[0]] if hit.size else np.inf
        reached += hit.size > 0
        assert t <= exact + 1e-12
    assert reached >= 20
    top = ROD_CORNER[2] + ROD_SIZE[2]
    slide = mesh.first_contact(np.array([[3.25, -5.5, top + 0.01]]), np.array([[0.0, 2.0, 0.0]]), AffineMap(),
                               np.array([0.002]))
    assert slide[0] >= 1.0


def test_barrier_terms_against_every_feature(ball_and_rod):
    """The smooth barrier's terms from the sampled search against a sum over every triangle, edge
    and vertex (brute force), for points near the ball and along the rod's skinny triangles."""
    mesh, dhat = ball_and_rod, 0.3
    local = near_and_far(mesh, 200, 7)
    local = local[~inside(local)]
    which, sign, distance, _, _ = mesh.barrier_terms(POSE.apply(local), POSE, within=dhat)
    energy = np.zeros(len(local))
    np.add.at(energy, which, sign * barrier(distance, dhat))
    a, b, c = mesh.corners[:, 0], mesh.corners[:, 1], mesh.corners[:, 2]
    edges = np.unique(np.sort(np.concatenate([mesh.triangles[:, [0, 1]], mesh.triangles[:, [1, 2]],
                                              mesh.triangles[:, [2, 0]]]), axis=1), axis=0)
    start, along = mesh.points[edges[:, 0]], mesh.points[edges[:, 1]] - mesh.points[edges[:, 0]]
    expected = np.empty(len(local))
    for i, x in enumerate(local):
        to_triangles = np.linalg.norm(x - closest_points(np.broadcast_to(x, a.shape), a, b, c)[0], axis=1)
        t = np.clip(np.einsum("ij,ij->i", x - start, along) / np.einsum("ij,ij->i", along, along), 0.0, 1.0)
        to_edges = np.linalg.norm(x - start - t[:, None] * along, axis=1)
        to_vertices = np.linalg.norm(x - mesh.points, axis=1)
        expected[i] = (barrier(to_triangles, dhat).sum() - barrier(to_edges, dhat).sum()
                       + barrier(to_vertices, dhat).sum())
    assert (expected > 0.0).sum() > 50
    assert np.abs(energy - expected).max() <= 1e-10 * np.abs(expected).max()
