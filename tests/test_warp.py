"""Subject adaptation by radial basis functions: the warp, fibers and inverted tets (face_dolfinx.subjects.warp)."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from face_dolfinx.subjects.warp import RBFWarp, fiber_transform, inverted_tets, signed_volumes, warp_residual

KERNELS = ["thin_plate", "biharmonic"]


def control_points(n=40, seed=0):
    """Template points (mm) and their subject counterparts: a smooth nonlinear deformation."""
    rng = np.random.default_rng(seed)
    source = rng.uniform(-80, 80, (n, 3))
    target = source + 4 * np.sin(source / 30) + rng.normal(0, 0.5, source.shape)
    return source, target


def affine_map(seed=1):
    rng = np.random.default_rng(seed)
    matrix = Rotation.random(random_state=seed).as_matrix() @ np.diag([1.1, 0.9, 1.05]) + 0.05 * rng.normal(size=(3, 3))
    return matrix, rng.normal(0, 10, 3)


@pytest.mark.parametrize("kernel", KERNELS)
def test_warp_interpolates_its_control_points(kernel):
    source, target = control_points()
    warp = RBFWarp.fit(source, target, kernel=kernel)
    np.testing.assert_allclose(warp.apply(source), target, rtol=0, atol=1e-9)
    assert np.max(warp_residual(warp, source, target)) < 1e-9


@pytest.mark.parametrize("kernel", KERNELS)
def test_warp_reproduces_an_affine_map(kernel):
    source = control_points()[0]
    matrix, shift = affine_map()
    warp = RBFWarp.fit(source, source @ matrix.T + shift, kernel=kernel)
    elsewhere = np.random.default_rng(2).uniform(-150, 150, (1000, 3))  # also outside the controls
    np.testing.assert_allclose(warp.apply(elsewhere), elsewhere @ matrix.T + shift, rtol=0, atol=1e-8)
    np.testing.assert_allclose(warp.apply(elsewhere[0]), elsewhere[0] @ matrix.T + shift, atol=1e-8)


def test_smoothing_trades_interpolation_for_smoothness():
    source, target = control_points()
    smooth = RBFWarp.fit(source, target, smoothing=10.0)
    residual = warp_residual(smooth, source, target)
    assert 0.01 < residual.mean() < 2.0  # the 0.5 mm noise, partly smoothed away
    # On correspondences it was not fitted to, the residual measures the prediction.
    without_first_five = RBFWarp.fit(source[5:], target[5:])
    assert np.all(warp_residual(without_first_five, source[:5], target[:5]) < 5.0)


def test_warp_without_affine_part():
    source, target = control_points()
    warp = RBFWarp.fit(source, target, kernel="biharmonic", affine=False)
    np.testing.assert_allclose(warp.apply(source), target, atol=1e-9)
    with pytest.raises(ValueError, match="needs the affine part"):
        RBFWarp.fit(source, target, kernel="thin_plate", affine=False)


def test_warp_input_errors():
    source, target = control_points(n=10)
    with pytest.raises(ValueError, match="unknown kernel"):
        RBFWarp.fit(source, target, kernel="gaussian")
    with pytest.raises(ValueError, match="repeated source points"):
        RBFWarp.fit(np.vstack([source, source[3]]), np.vstack([target, target[3]]))
    with pytest.raises(ValueError, match="at least 4"):
        RBFWarp.fit(source[:3], target[:3])
    with pytest.raises(ValueError, match="same shape"):
        RBFWarp.fit(source, target[:-1])
    flat = source * [1, 1, 0]
    with pytest.raises(ValueError, match="singular"):
        RBFWarp.fit(flat, flat + 1)


def test_fibers_follow_an_affine_warp():
    source = control_points()[0]
    matrix, shift = affine_map(3)
    warp = RBFWarp.fit(source, source @ matrix.T + shift)
    rng = np.random.default_rng(4)
    points = rng.uniform(-60, 60, (200, 3))
    fibers = rng.normal(size=(200, 3))
    fibers /= np.linalg.norm(fibers, axis=1, keepdims=True)
    expected = fibers @ matrix.T
    expected /= np.linalg.norm(expected, axis=1, keepdims=True)
    np.testing.assert_allclose(fiber_transform(warp, points, fibers), expected, atol=1e-8)
    # Not unit on input: only the direction matters.
    np.testing.assert_allclose(fiber_transform(warp, points, 3 * fibers), expected, atol=1e-8)
    with pytest.raises(ValueError, match="zero fiber"):
        fiber_transform(warp, points[:2], np.zeros((2, 3)))


def test_fibers_follow_a_nonlinear_warp_to_second_order():
    source, target = control_points()
    warp = RBFWarp.fit(source, target)
    points = np.random.default_rng(5).uniform(-50, 50, (20, 3))
    fibers = np.tile([1.0, 0.0, 0.0], (20, 1))
    # A much smaller one-sided difference of the same warp: agrees to its O(h) error.
    h = 1e-5
    reference = warp.apply(points + h * fibers) - warp.apply(points)
    reference /= np.linalg.norm(reference, axis=1, keepdims=True)
    np.testing.assert_allclose(fiber_transform(warp, points, fibers), reference, atol=1e-5)


def cube_tets():
    """The unit cube split into 6 positively oriented tets around the diagonal 0-7."""
    points = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], dtype=float)
    tets = np.array([[0, 4, 6, 7], [0, 6, 2, 7], [0, 2, 3, 7], [0, 3, 1, 7], [0, 1, 5, 7], [0, 5, 4, 7]])
    return points, tets


def test_inverted_tets_finds_a_flipped_tet():
    points, tets = cube_tets()
    volumes = signed_volumes(points, tets)
    np.testing.assert_allclose(volumes, 1 / 6)
    assert inverted_tets(points, tets).size == 0
    # Push corner 4 = (1, 0, 0) through the opposite face of the tets that use it.
    moved = points.copy()
    moved[4] = [-0.5, 0.3, 0.2]
    flipped = inverted_tets(moved, tets)
    assert flipped.size > 0
    np.testing.assert_array_equal(flipped, np.flatnonzero(signed_volumes(moved, tets) <= 0))
    assert set(flipped) <= {0, 5}  # only the tets using vertex 4 can change
    flattened = points.copy()
    flattened[4] = points[0]  # onto vertex 0: a zero volume counts as inverted
    assert {0, 5} <= set(inverted_tets(flattened, tets))


def test_inverted_tets_against_a_reference_for_mixed_orientation():
    points, tets = cube_tets()
    tets = tets.copy()
    tets[2] = tets[2][[1, 0, 2, 3]]  # negatively oriented, but not inverted by anything
    assert inverted_tets(points, tets).tolist() == [2]
    assert inverted_tets(points, tets, reference_points=points).size == 0
    mirrored = points * [-1, 1, 1]  # a reflection inverts every tet
    assert inverted_tets(mirrored, tets, reference_points=points).tolist() == list(range(6))


def test_warped_mesh_stays_valid_under_a_mild_warp():
    points, tets = cube_tets()
    source, target = control_points()
    warp = RBFWarp.fit(source / 100, target / 100)  # a gentle warp of the unit cube region
    assert inverted_tets(warp.apply(points), tets).size == 0
