"""Closest points on a triangle surface, normals, and markers embedded in it (face_dolfinx.alignment.surface)."""

import numpy as np
import pytest
from scipy.spatial import ConvexHull

from face_dolfinx.alignment.surface import MarkerEmbedding, SkinSurface

TOLERANCE = 1e-12


def grid_surface(n=25, height=lambda x, y: 0.2 * np.sin(3 * x) * np.cos(4 * y)):
    """A height field over [-1, 1]^2, two triangles per grid cell."""
    x, y = np.meshgrid(np.linspace(-1, 1, n), np.linspace(-1, 1, n))
    points = np.column_stack([x.ravel(), y.ravel(), height(x, y).ravel()])
    index = np.arange(n * n).reshape(n, n)
    lower = np.column_stack([index[:-1, :-1].ravel(), index[:-1, 1:].ravel(), index[1:, :-1].ravel()])
    upper = np.column_stack([index[1:, :-1].ravel(), index[:-1, 1:].ravel(), index[1:, 1:].ravel()])
    return points, np.concatenate([lower, upper])


def sphere_surface(n=300, seed=0):
    """A closed triangulated unit sphere (convex hull of random points), triangles oriented outwards."""
    rng = np.random.default_rng(seed)
    points = rng.normal(size=(n, 3))
    points /= np.linalg.norm(points, axis=1, keepdims=True)
    triangles = ConvexHull(points).simplices
    a, b, c = (points[triangles[:, k]] for k in range(3))
    inward = np.einsum("ij,ij->i", np.cross(b - a, c - a), a) < 0
    triangles[inward] = triangles[inward][:, ::-1]
    return points, triangles


def bumpy_surface():
    return grid_surface()


def graded_surface():
    """A fine grid next to one huge triangle (50x the grid spacing): tests the proxy splitting."""
    points, triangles = grid_surface(n=20, height=lambda x, y: 0.05 * x * y)
    start = len(points)
    points = np.vstack([points, [[1.0, -1.0, 0.0], [4.0, -1.0, 1.0], [1.0, 3.0, -0.5]]])
    return points, np.vstack([triangles, [[start, start + 1, start + 2]]])


SURFACES = {"sphere": sphere_surface, "bumpy": bumpy_surface, "graded": graded_surface}


def brute_force_closest(query, points, triangles):
    """Distances and closest points by a different method: the plane projection when it falls
    inside the triangle, else the nearest of the three edges, over every triangle."""
    a, b, c = (points[triangles[:, k]] for k in range(3))
    normal = np.cross(b - a, c - a)
    normal_squared = np.einsum("ij,ij->i", normal, normal)
    best_distance = np.full(len(query), np.inf)
    best_point = np.zeros_like(query)
    for i, x in enumerate(query):
        candidates = []
        # Degenerate triangles divide by zero here; their NaN candidates are skipped below.
        with np.errstate(divide="ignore", invalid="ignore"):
            projection = x - (np.einsum("ij,ij->i", x - a, normal) / normal_squared)[:, None] * normal
            # Barycentric coordinates of the projection from signed sub-areas.
            u = np.einsum("ij,ij->i", np.cross(c - b, projection - b), normal) / normal_squared
            v = np.einsum("ij,ij->i", np.cross(a - c, projection - c), normal) / normal_squared
            inside = (u >= 0) & (v >= 0) & (u + v <= 1)
            candidates.append(np.where(inside[:, None], projection, np.nan))
            for start, end in ((a, b), (b, c), (c, a)):
                edge = end - start
                t = np.clip(np.einsum("ij,ij->i", x - start, edge) / np.einsum("ij,ij->i", edge, edge), 0, 1)
                candidates.append(start + t[:, None] * edge)
        candidates = np.concatenate(candidates)
        distance = np.linalg.norm(candidates - x, axis=1)
        best = np.nanargmin(distance)
        best_distance[i], best_point[i] = distance[best], candidates[best]
    return best_distance, best_point


def queries_for(points, triangles, rng):
    """Random points near the surface, far from it, on vertices and on edges."""
    a, b, c = (points[triangles[:, k]] for k in range(3))
    extent = np.ptp(points, axis=0).max()
    centre = points.mean(axis=0)
    near = centre + rng.uniform(-0.7, 0.7, (150, 3)) * extent
    far = centre + rng.normal(size=(40, 3)) * 20 * extent
    on_vertices = points[np.unique(triangles)[rng.integers(0, len(np.unique(triangles)), 30)]]
    pick = rng.integers(0, len(triangles), 30)
    t = rng.uniform(size=(30, 1))
    on_edges = a[pick] + t * (b[pick] - a[pick])
    return np.vstack([near, far, on_vertices, on_edges])


@pytest.mark.parametrize("name", SURFACES)
def test_closest_matches_brute_force(name):
    points, triangles = SURFACES[name]()
    skin = SkinSurface(points, triangles)
    query = queries_for(points, triangles, np.random.default_rng(1))
    triangle, barycentric, point, distance = skin.closest(query)
    expected_distance, expected_point = brute_force_closest(query, points, triangles)
    np.testing.assert_allclose(distance, expected_distance, rtol=0, atol=TOLERANCE * max(1, np.abs(query).max()))
    np.testing.assert_allclose(point, expected_point, rtol=0, atol=1e-10)
    # The barycentric coordinates describe the returned point on the returned triangle.
    assert np.all(barycentric >= -TOLERANCE)
    np.testing.assert_allclose(barycentric.sum(axis=1), 1.0, atol=TOLERANCE)
    rebuilt = np.einsum("nk,nkd->nd", barycentric, points[triangles[triangle]])
    np.testing.assert_allclose(rebuilt, point, atol=TOLERANCE)
    np.testing.assert_allclose(np.linalg.norm(query - point, axis=1), distance, atol=TOLERANCE)


def test_points_on_the_surface_are_their_own_closest_points():
    points, triangles = bumpy_surface()
    skin = SkinSurface(points, triangles)
    rng = np.random.default_rng(2)
    pick = rng.integers(0, len(triangles), 500)
    weights = rng.dirichlet([1, 1, 1], 500)
    on_surface = np.einsum("nk,nkd->nd", weights, points[triangles[pick]])
    _, _, point, distance = skin.closest(on_surface)
    assert np.all(distance < TOLERANCE)
    np.testing.assert_allclose(point, on_surface, atol=TOLERANCE)


def test_degenerate_triangles_are_treated_as_their_edges():
    points, triangles = grid_surface(n=6)
    start = len(points)
    # A collinear triangle standing off the grid, and one with two coincident corners.
    points = np.vstack([points, [[0, 0, 1], [1, 0, 1], [3, 0, 1], [0, 1, 2], [0, 1, 2], [1, 1, 2]]])
    triangles = np.vstack([triangles, [[start, start + 2, start + 1], [start + 3, start + 4, start + 5]]])
    skin = SkinSurface(points, triangles)
    assert skin.degenerate.tolist() == [False] * (len(triangles) - 2) + [True, True]
    np.testing.assert_array_equal(skin.triangle_normals[-2:], 0.0)
    query = queries_for(points, triangles, np.random.default_rng(3))
    query = np.vstack([query, [[2.0, 0.3, 1.2], [0.5, 1.0, 2.1]]])
    _, _, point, distance = skin.closest(query)
    expected_distance, expected_point = brute_force_closest(query, points, triangles)
    np.testing.assert_allclose(distance, expected_distance, atol=1e-10)
    np.testing.assert_allclose(point, expected_point, atol=1e-10)


def test_triangle_normals_are_unit_and_follow_the_vertex_order():
    points, triangles = sphere_surface()
    skin = SkinSurface(points, triangles)
    normals = skin.triangle_normals
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, atol=TOLERANCE)
    a, b, c = (points[triangles[:, k]] for k in range(3))
    for edge in (b - a, c - a):
        np.testing.assert_allclose(np.einsum("ij,ij->i", normals, edge), 0.0, atol=TOLERANCE)
    # Outward triangles give outward normals on the sphere.
    assert np.all(np.einsum("ij,ij->i", normals, (a + b + c) / 3) > 0)
    np.testing.assert_allclose(skin.areas.sum(), 4 * np.pi, rtol=0.05)


def test_vertex_normals_are_area_weighted():
    # Two triangles meeting at vertex 0: a large one in the plane z = 0 and a small one in x = 0.
    points = np.array([[0, 0, 0], [4, 0, 0], [0, 4, 0], [0, 0, 1], [0, -1, 0], [9, 9, 9.0]])
    triangles = np.array([[0, 1, 2], [0, 3, 4]])
    skin = SkinSurface(points, triangles)
    large_area, small_area = 8.0, 0.5
    expected = large_area * np.array([0, 0, 1.0]) + small_area * np.array([1.0, 0, 0])
    np.testing.assert_allclose(skin.vertex_normals[0], expected / np.linalg.norm(expected), atol=TOLERANCE)
    np.testing.assert_allclose(skin.vertex_normals[1], [0, 0, 1], atol=TOLERANCE)
    np.testing.assert_array_equal(skin.vertex_normals[5], 0.0)  # used by no triangle


def test_vertex_normals_of_a_sphere_point_outwards():
    points, triangles = sphere_surface(n=2000)
    skin = SkinSurface(points, triangles)
    assert np.min(np.einsum("ij,ij->i", skin.vertex_normals, points)) > 0.99


def embedded_markers(points, triangles, rng, n=60, lift=0.05):
    """Points on the surface, and the same lifted off it along the triangle normal (by up to
    ``lift``; where the surface curves, a lifted point may be closest to another triangle)."""
    skin = SkinSurface(points, triangles)
    pick = rng.integers(0, len(triangles), n)
    weights = rng.dirichlet([2, 2, 2], n)
    on_surface = np.einsum("nk,nkd->nd", weights, points[triangles[pick]])
    return skin, on_surface, on_surface + lift * rng.uniform(-1, 1, (n, 1)) * skin.triangle_normals[pick]


def test_embedding_round_trip_keeps_offsets():
    points, triangles = bumpy_surface()
    skin, on_surface, lifted = embedded_markers(points, triangles, np.random.default_rng(4))
    names = [f"m{i}" for i in range(len(lifted))]
    for query in (on_surface, lifted):
        embedding = skin.embed(query, names)
        assert isinstance(embedding, MarkerEmbedding) and len(embedding) == len(query)
        assert embedding.names == tuple(names)
        np.testing.assert_allclose(embedding.positions(points), query, rtol=0, atol=TOLERANCE)
        np.testing.assert_allclose(embedding.weights.sum(axis=1), 1.0, atol=TOLERANCE)
    np.testing.assert_allclose(np.linalg.norm(embedding.offsets, axis=1),
                               brute_force_closest(lifted, points, triangles)[0], atol=TOLERANCE)


def test_embedded_markers_move_with_the_vertices():
    points, triangles = bumpy_surface()
    skin, _, lifted = embedded_markers(points, triangles, np.random.default_rng(5))
    embedding = skin.embed(lifted)
    shift = np.array([1.0, -2.0, 0.5])
    np.testing.assert_allclose(embedding.positions(points + shift), lifted + shift, atol=TOLERANCE)


def test_matrix_equals_positions():
    points, triangles = sphere_surface()
    skin, _, lifted = embedded_markers(points, triangles, np.random.default_rng(6))
    embedding = skin.embed(lifted)
    deformed = points + 0.1 * np.random.default_rng(7).normal(size=points.shape)
    w = embedding.matrix(len(points))
    assert w.shape == (3 * len(lifted), 3 * len(points)) and w.format == "csr"
    np.testing.assert_allclose(w @ deformed.ravel() + embedding.offsets.ravel(),
                               embedding.positions(deformed).ravel(), atol=TOLERANCE)
    with pytest.raises(ValueError, match="n_vertices"):
        embedding.matrix(int(embedding.triangles.max()))


def test_invalid_input_is_rejected():
    points, triangles = grid_surface(n=4)
    with pytest.raises(ValueError, match="points must have shape"):
        SkinSurface(points[:, :2], triangles)
    with pytest.raises(ValueError, match="finite"):
        SkinSurface(np.where(np.arange(len(points))[:, None] == 3, np.nan, points), triangles)
    with pytest.raises(ValueError, match="vertex ids"):
        SkinSurface(points, triangles + 1)
    with pytest.raises(ValueError, match="integer"):
        SkinSurface(points, triangles.astype(float))
    skin = SkinSurface(points, triangles)
    with pytest.raises(ValueError, match="finite"):
        skin.closest([[0.0, np.nan, 0.0]])
    with pytest.raises(ValueError, match="shape"):
        skin.closest([0.0, 0.0, 0.0])
