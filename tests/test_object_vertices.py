"""A triangle-mesh object's vertices kept off the skin's triangles (face_dolfinx.physics.object_vertices):
a sharp tip pressed into the slab between its skin nodes, which the nodes' barrier lets through the
skin while the vertices' barrier dents the skin under it at every Newton iterate; the barrier's
gradient and Hessian against differences of its energy, the smooth sum over a vertex's skin
features, the pose rates against differences in the pose, force balance, and the same result on
1 and 2 ranks.
"""
from mpi4py import MPI
import numpy as np
import pytest

from face_dolfinx.alignment.surface import closest_points
from face_dolfinx.model.bones import AffineMap, rotation
from face_dolfinx.physics.contact import ContactSettings, barrier
from face_dolfinx.physics.object_vertices import ObjectVertexContact
from face_dolfinx.physics.problem import FaceProblem
from face_dolfinx.physics.rigid_mesh import TriangleMesh
from test_contact import ACTIVATIONS, assert_barrier_derivatives, assert_force_balance, skin_slab

# The tip's apex over the middle of a top-face triangle of the slab (corners (20, 10), (20, 12.5),
# (22.5, 12.5)), 1 mm above the skin in the tip's own frame; its base 1.6 mm wide 4 mm higher.
APEX = np.array([20.8, 11.6, 11.0])


def pyramid(apex=APEX, half_width=0.8, height=4.0):
    """A square pyramid pointing down (-z) from its base, outward triangles."""
    base = apex + [0.0, 0.0, height]
    corners = base + np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]]) * half_width
    points = np.vstack([apex, corners])
    sides = [(0, 2, 1), (0, 3, 2), (0, 4, 3), (0, 1, 4)]
    return points, np.array(sides + [(1, 2, 3), (1, 3, 4)])


def tip_at(depth):
    """The tip's pose with its apex ``depth`` mm below the undeformed top face."""
    return AffineMap(np.eye(3), [0.0, 0.0, -1.0 - depth])


def pressed_tip(depth=1.0, faces=True, comm=MPI.COMM_WORLD, monitor=None):
    settings = ContactSettings((TriangleMesh(*pyramid(), name="tip"),), (tip_at(-0.5),), dhat=0.05,
                               stiffness=10.0, faces=faces)
    problem = FaceProblem(skin_slab(comm), contact=settings)
    if monitor is not None:
        problem.solver.snes.setMonitor(lambda snes, it, norm: monitor(problem, snes.getSolution().array_r))
    report = problem.solve(activations=ACTIVATIONS, objects=(tip_at(depth),))
    problem.solver.snes.cancelMonitor()
    assert report.converged
    return problem


def apex_height(problem) -> float:
    """How far the apex lies above the deformed skin (mm, negative: inside the flesh): along the
    skin's normal, from the nearest point of the nearest top-face triangle."""
    contact = problem.contact
    apex = contact.poses[0].apply(APEX[None])
    x = contact.positions(problem.u.x.array)
    corners = x[contact.surface.triangles]
    nearest = closest_points(np.repeat(apex, len(corners), axis=0), corners[:, 0], corners[:, 1], corners[:, 2])[0]
    k = int(np.argmin(np.linalg.norm(nearest - apex, axis=1)))
    normal = np.cross(corners[k, 1] - corners[k, 0], corners[k, 2] - corners[k, 0])
    normal *= np.sign(normal[2]) / np.linalg.norm(normal)  # the top face's outward normal is +z
    return float((apex[0] - nearest[k]) @ normal)


@pytest.fixture(scope="module")
def tip():
    distances = []

    def record(problem, x):
        distances.append(problem.contact.vertex_gaps(x, within=1.0)[0][0])

    problem = pressed_tip(monitor=record)
    problem.iterate_distances = distances
    return problem


def test_the_nodes_barrier_lets_the_tip_through_the_skin():
    """Without the vertices' barrier (``faces=False``) the tip passes between the skin's nodes: its
    apex ends 1 mm inside the flesh and the skin carries no force."""
    problem = pressed_tip(faces=False)
    assert not isinstance(problem.contact, ObjectVertexContact)
    assert apex_height(problem) < -0.9
    assert np.abs(problem.contact.nodal_forces(problem.u.x.array)).max() == 0.0


def test_the_vertices_barrier_dents_the_skin_under_the_tip(tip):
    """The apex stays outside the skin at every Newton iterate (the move's dent and the solve) and
    ends within dhat of it, 1 mm below the skin's rest height: the corners of the skin triangle
    under it pushed 0.5 mm or more down; the skin's force on the tip balances the bones'
    reactions."""
    assert isinstance(tip.contact, ObjectVertexContact)
    assert len(tip.iterate_distances) > 2 and min(tip.iterate_distances) > 0.0
    assert 0.0 < apex_height(tip) < tip.contact.dhat
    assert tip.contact.contact_vertices(tip.u.x.array) == 1
    corners = tip.contact.surface.rest[tip.contact.surface.triangles]
    weights = closest_points(np.repeat(APEX[None] - [0.0, 0.0, 1.0], len(corners), axis=0), corners[:, 0],
                             corners[:, 1], corners[:, 2])[1]
    under = tip.contact.surface.triangles[np.flatnonzero((weights > 1e-9).all(axis=1) & np.isclose(corners[:, :, 2], 10.0).all(axis=1))]
    assert len(under) == 1
    assert (tip.contact.positions(tip.u.x.array)[under[0], 2] < 10.0 - 0.5).all()
    assert_force_balance(tip)


def test_gradient_and_hessian_against_differences_of_the_energy(tip):
    """At the pressed state with the tip lifted 0.02 mm (the apex's terms active, their distances
    far above the differences' steps)."""
    contact = tip.contact
    pose = contact.poses[0]
    contact.set_poses((AffineMap(pose.matrix, pose.translation + [0.0, 0.0, 0.02]),))
    try:
        assert len(contact.vertex_terms(tip.u.x.array)[0][0]) >= 1
        assert_barrier_derivatives(tip, contact)
    finally:
        contact.set_poses((pose,))


def test_the_sum_over_a_vertexs_features_is_the_barrier_of_its_distance_to_the_skin(tip):
    """Over the flat skin the signed sum over the triangles, edges and corners within dhat of a
    vertex is b(distance to the nearest triangle), whichever feature is nearest: a point over a
    face, next to an edge and next to a corner of the undeformed top face."""
    contact = tip.contact
    pose = contact.poses[0]
    rest = np.zeros_like(tip.u.x.array)
    apex = int(np.argmin(np.linalg.norm(contact.objects[0].points - APEX, axis=1)))
    counts = []
    try:
        for over in ([20.8, 11.6], [21.25, 10.0], [22.5, 10.0]):  # a face, an edge, a corner
            contact.set_poses((AffineMap(np.eye(3), [*over, 10.02] - APEX),))
            _, weight, distance, *_ = contact.vertex_terms(rest)[0]
            sign = weight / contact.object_vertex_areas[0][apex]
            assert np.array_equal(np.abs(sign), np.ones(len(sign)))
            assert (sign * barrier(distance, 0.05)).sum() == pytest.approx(barrier(np.array([0.02]), 0.05)[0], rel=1e-12)
            counts.append(len(sign))
    finally:
        contact.set_poses((pose,))
    assert counts[0] == 1 and counts[1] == 3 and counts[2] > 3  # a corner: its triangles, edges, itself


def test_pose_rates_against_differences(tip):
    """d(dE_c/dx)/d(pose) . rate, the nodes held, against central differences in the pose: a
    translation and a rotation about a point off the tip."""
    contact, u = tip.contact, tip.u.x.array
    pose = contact.poses[0]
    axis, angle_rate = np.array([0.3, -0.5, 0.8]), 0.2
    a = axis / np.linalg.norm(axis)
    skew = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])  # skew y = a x y
    velocity = np.array([0.3, -0.2, 1.0])
    rate = contact.pose_rate_forces(u, [(angle_rate * skew @ pose.matrix, velocity)])
    h = 1e-6

    def forces(t):
        turned = rotation(axis, angle_rate * t) @ pose.matrix
        contact.set_poses((AffineMap(turned, pose.translation + t * velocity),))
        return contact.nodal_forces(u)

    fd = (forces(h) - forces(-h)) / (2 * h)
    contact.set_poses((pose,))
    assert np.abs(rate).max() > 1.0
    assert np.abs(rate - fd).max() <= 1e-5 * np.abs(rate).max()


def test_same_result_on_one_rank(tip):
    serial = pressed_tip(comm=MPI.COMM_SELF)
    here = tip.contact.nodal_forces(tip.u.x.array).sum(axis=0)
    alone = serial.contact.nodal_forces(serial.u.x.array).sum(axis=0)
    assert np.abs(here - alone).max() <= 1e-8 * np.abs(alone).max()
    assert apex_height(tip) == pytest.approx(apex_height(serial), rel=1e-8)
