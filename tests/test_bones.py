"""Bone frames (face_dolfinx.model.bones): affine maps against 4x4 homogeneous matrices, rotations
and rigid maps, and the TMJ articulation: each condyle stays on its track, slid as far as asked,
and the jaw opens by the angle asked, chin down."""
import math

import numpy as np
import pytest

from face_dolfinx.model.bones import AffineMap, jaw_pose, rigid_map, rotation
from face_dolfinx.model.folder import JawGeometry

RNG = np.random.default_rng(7)
POINTS = RNG.normal(scale=50.0, size=(20, 3))
# The built-in face's joint: condyles 100 mm apart, tracks forward and slightly down.
JAW = JawGeometry.from_condyles([-50.0, -10.0, -40.0], [50.0, -10.0, -40.0], [0.0, -0.2, 1.0],
                                track_length=10.0, max_opening_sine=0.4)


def random_map() -> AffineMap:
    return AffineMap(np.eye(3) + 0.4 * RNG.normal(size=(3, 3)), RNG.normal(scale=10.0, size=3))


def homogeneous_apply(H, points):
    return (np.c_[points, np.ones(len(points))] @ H.T)[:, :3]


def assert_rotation(M):
    np.testing.assert_allclose(M.T @ M, np.eye(3), atol=1e-14)
    assert np.linalg.det(M) == pytest.approx(1.0, abs=1e-14)


def rotation_angle(M):
    return math.acos(np.clip((np.trace(M) - 1.0) / 2.0, -1.0, 1.0))


def test_affine_map_apply_compose_inverse_against_homogeneous_matrices():
    a, b = random_map(), random_map()
    np.testing.assert_allclose(a.apply(POINTS), homogeneous_apply(a.homogeneous(), POINTS), rtol=1e-14)
    np.testing.assert_allclose(a.compose(b).homogeneous(), a.homogeneous() @ b.homogeneous(), rtol=1e-13)
    np.testing.assert_allclose(a.compose(b).apply(POINTS), a.apply(b.apply(POINTS)), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(a.inverse().homogeneous(), np.linalg.inv(a.homogeneous()), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(a.inverse().apply(a.apply(POINTS)), POINTS, atol=1e-11)
    assert AffineMap().same_as(AffineMap(np.eye(3), np.zeros(3)))
    assert not a.same_as(b) and a.same_as(AffineMap(a.matrix.copy(), a.translation.copy()))


def test_interpolation_and_geodesic_between_frames():
    """The linear blend of the 12 numbers reaches both ends and shrinks a turning frame half
    way; the geodesic keeps it rigid, turning by half the angle about the same axis."""
    a, b = random_map(), random_map()
    assert a.interpolate(b, 0.0).same_as(a) and a.interpolate(b, 1.0).same_as(b)
    np.testing.assert_allclose(a.interpolate(b, 0.25).apply(POINTS),
                               0.75 * a.apply(POINTS) + 0.25 * b.apply(POINTS), atol=1e-10)
    start = rigid_map(rotation([0.2, 1.0, 0.1], 0.3), [5.0, 0.0, 2.0], [1.0, 2.0, 3.0])
    turn = rotation([1.0, -0.5, 0.3], 1.2)
    end = AffineMap(turn, [4.0, -2.0, 1.0]).compose(start)
    halfway = start.geodesic(end, 0.5)
    assert_rotation(halfway.matrix)
    relative = halfway.matrix @ start.matrix.T
    assert rotation_angle(relative) == pytest.approx(0.6, abs=1e-12)
    np.testing.assert_allclose(relative @ [1.0, -0.5, 0.3], [1.0, -0.5, 0.3], atol=1e-12)  # same axis
    np.testing.assert_allclose(halfway.geodesic(end, 1.0).matrix, end.matrix)
    np.testing.assert_allclose(start.geodesic(end, 1.0).apply(POINTS), end.apply(POINTS), atol=1e-12)
    blended = start.interpolate(end, 0.5).matrix
    assert np.linalg.det(blended) < 0.9  # cos(0.6)^2 of the volume: not rigid
    # A reflection has no real logarithm: the geodesic falls back to the linear blend.
    mirror = AffineMap(np.diag([-1.0, 1.0, 1.0]))
    assert AffineMap().geodesic(mirror, 0.5).same_as(AffineMap().interpolate(mirror, 0.5))


@pytest.mark.parametrize("axis, angle", [([0, 0, 1], 0.5), ([1.0, 2.0, -0.5], 2.5), ([0.3, 0, 0], -1.0)])
def test_rotation_is_a_right_handed_turn_about_its_axis(axis, angle):
    R = rotation(axis, angle)
    assert_rotation(R)
    unit = np.asarray(axis, float) / np.linalg.norm(axis)
    np.testing.assert_allclose(R @ unit, unit, atol=1e-14)
    assert rotation_angle(R) == pytest.approx(abs(angle), abs=1e-12)
    # Right hand rule: a vector across the axis turns towards axis x vector.
    across = np.cross(unit, [0.3, -0.7, 0.2])
    assert np.dot(R @ across, np.cross(unit, across)) * np.sign(angle) > 0
    np.testing.assert_allclose(rotation([0, 0, 1], math.pi / 2) @ [1, 0, 0], [0, 1, 0], atol=1e-15)


def test_rigid_map_turns_about_its_centre_then_moves():
    R = rotation([0.4, -1.0, 0.3], 0.7)
    centre, displacement = np.array([3.0, -2.0, 10.0]), np.array([1.0, 0.5, -2.0])
    frame = rigid_map(R, centre, displacement)
    assert_rotation(frame.matrix)
    np.testing.assert_allclose(frame.apply(centre), centre + displacement, atol=1e-13)
    # Distances are kept: a rotation and a translation.
    before = np.linalg.norm(POINTS[:, None] - POINTS[None], axis=-1)
    moved = frame.apply(POINTS)
    np.testing.assert_allclose(np.linalg.norm(moved[:, None] - moved[None], axis=-1), before, atol=1e-11)


@pytest.mark.parametrize("opening, right, left", [(0.0, 0.0, 0.0), (0.3, 0.0, 0.0), (0.0, 4.0, 4.0),
                                                  (0.0, 1.0, 6.0), (0.25, 7.0, 2.5)])
def test_jaw_pose_keeps_the_condyles_on_their_tracks(opening, right, left):
    """Each condyle moves along v by its slide, staying in its track's plane; the jaw stays
    rigid; it turns by the asked opening about the (slid) condyle axis, the chin along -w."""
    pose = jaw_pose(JAW, opening, right, left)
    assert_rotation(pose.matrix)
    yaw = math.asin((left - right) / JAW.condyle_distance)
    for condyle, slide in ((JAW.condyle_right, right), (JAW.condyle_left, left)):
        moved = pose.apply(condyle) - condyle
        assert moved @ JAW.v == pytest.approx(slide, abs=1e-12)  # as far along the track as asked
        assert moved @ JAW.w == pytest.approx(0.0, abs=1e-12)    # not off its plane
        # Unequal slides turn the condyle axis, bringing the condyles closer along u by l/2 (1 - cos yaw).
        assert abs(moved @ JAW.u) == pytest.approx(0.5 * JAW.condyle_distance * (1 - math.cos(yaw)), abs=1e-12)
    slid = jaw_pose(JAW, 0.0, right, left)  # the same slides, mouth closed
    opened = pose.matrix @ slid.matrix.T
    assert rotation_angle(opened) == pytest.approx(opening, abs=1e-12)
    axis = slid.matrix @ JAW.u  # the condyle axis after the slides
    np.testing.assert_allclose(opened @ axis, axis, atol=1e-12)
    chin = JAW.midpoint + 80.0 * JAW.v  # in front of the joint
    drop = pose.apply(chin) - slid.apply(chin)
    if opening:
        assert drop @ JAW.w < -70.0 * math.sin(opening)  # the chin goes down by about 80 sin(opening)
    else:
        np.testing.assert_allclose(drop, 0.0, atol=1e-12)
    # Unequal slides turn the jaw about w only; the left condyle further forward turns u
    # towards +v.
    assert abs(axis @ JAW.w) < 1e-12
    assert math.atan2(axis @ JAW.v, axis @ JAW.u) == pytest.approx(yaw, abs=1e-12)


def test_jaw_geometry_from_condyles():
    """u across the condyles, v the slide direction made orthogonal to u, w = v x u, m between."""
    assert np.allclose([JAW.u @ JAW.v, JAW.u @ JAW.w, JAW.v @ JAW.w], 0.0)
    np.testing.assert_allclose(JAW.u, [1.0, 0.0, 0.0])
    np.testing.assert_allclose(JAW.w, np.cross(JAW.v, JAW.u))
    assert JAW.condyle_distance == 100.0 and np.allclose(JAW.midpoint, [0.0, -10.0, -40.0])
    with pytest.raises(ValueError, match="parallel to the condyle axis"):
        JawGeometry.from_condyles([0, 0, 0], [1, 0, 0], [2, 0, 0], 5.0, 0.5)
    with pytest.raises(ValueError, match="coincide"):
        JawGeometry.from_condyles([1, 0, 0], [1, 0, 0], [0, 0, 1], 5.0, 0.5)
