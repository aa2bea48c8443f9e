"""A triangle-mesh object's vertices and edges kept off the skin (face_dolfinx.physics.object_features):
a sharp tip and a blade pressed into the slab between its skin nodes, which the nodes' barrier lets
through the skin while the object's vertices' and edges' barriers dent the skin under them at every
Newton iterate; the barrier's gradient and Hessian against differences of its energy (vertex and
edge terms), the smooth sum over a vertex's skin features, the pose rates against differences in
the pose, force balance, and the same result on 1 and 2 ranks.
"""
from mpi4py import MPI
import numpy as np
import pytest

from face_dolfinx.alignment.surface import closest_points
from face_dolfinx.model.bones import AffineMap, rotation
from face_dolfinx.physics.contact import ContactSettings, barrier
from face_dolfinx.physics.object_features import ObjectFeatureContact
from face_dolfinx.physics.problem import FaceProblem
from face_dolfinx.physics.rigid_mesh import TriangleMesh
from test_contact import ACTIVATIONS, assert_barrier_derivatives, assert_force_balance, skin_slab
from test_contact_mesh import box

# The tip's apex over the middle of a top-face triangle of the slab (corners (20, 10), (20, 12.5),
# (22.5, 12.5); nodes 2.5 mm apart), 1 mm above the skin in the tip's own frame; its base 1.6 mm
# wide 4 mm higher.
APEX = np.array([20.8, 11.6, 11.0])
# A blade 0.2 mm thick and 2 mm high along x between two rows of skin nodes (y = 10 and 12.5), its
# ends over the skin 10 mm from the bones, 1 mm above the skin in its own frame.
BLADE = box((19.4, 0.2, 2.0), lower=(10.3, 11.15, 11.0))


def pyramid(apex=APEX, half_width=0.8, height=4.0):
    """A square pyramid pointing down (-z) from its base, outward triangles."""
    base = apex + [0.0, 0.0, height]
    corners = base + np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]]) * half_width
    points = np.vstack([apex, corners])
    sides = [(0, 2, 1), (0, 3, 2), (0, 4, 3), (0, 1, 4)]
    return points, np.array(sides + [(1, 2, 3), (1, 3, 4)])


def lowered(depth):
    """The pose of an object 1 mm above the skin in its own frame with its lowest point ``depth``
    mm below the undeformed top face."""
    return AffineMap(np.eye(3), [0.0, 0.0, -1.0 - depth])


def pressed(surface, depth=1.0, faces=True, comm=MPI.COMM_WORLD, monitor=None):
    """The slab with the object ``surface`` (points, triangles) lowered ``depth`` mm into it in one
    solve; ``monitor(problem, x)`` at every Newton iterate."""
    settings = ContactSettings((TriangleMesh(*surface, name="instrument"),), (lowered(-0.5),), dhat=0.05,
                               stiffness=10.0, faces=faces)
    problem = FaceProblem(skin_slab(comm), contact=settings)
    if monitor is not None:
        problem.solver.snes.setMonitor(lambda snes, it, norm: monitor(problem, snes.getSolution().array_r))
    report = problem.solve(activations=ACTIVATIONS, objects=(lowered(depth),))
    problem.solver.snes.cancelMonitor()
    assert report.converged
    return problem


def height_above_skin(problem, point) -> float:
    """How far a world ``point`` lies above the deformed skin (mm, negative: inside the flesh):
    along the outward normal of the nearest top-face triangle, from its nearest point."""
    x = problem.contact.positions(problem.u.x.array)
    corners = x[problem.contact.surface.triangles]
    points = np.repeat(np.asarray(point, dtype=float)[None], len(corners), axis=0)
    nearest = closest_points(points, corners[:, 0], corners[:, 1], corners[:, 2])[0]
    k = int(np.argmin(np.linalg.norm(nearest - point, axis=1)))
    normal = np.cross(corners[k, 1] - corners[k, 0], corners[k, 2] - corners[k, 0])
    normal *= np.sign(normal[2]) / np.linalg.norm(normal)  # the top face's outward normal is +z
    return float((point - nearest[k]) @ normal)


def lowest_height(problem, samples=200) -> float:
    """The smallest ``height_above_skin`` of points along the object's lowest edges."""
    obj, pose = problem.contact.objects[0], problem.contact.poses[0]
    points = pose.apply(obj.points)
    bottom = points[np.isclose(points[:, 2], points[:, 2].min())]
    if len(bottom) == 1:
        return height_above_skin(problem, bottom[0])
    a, b = bottom[np.argmin(bottom[:, 0])], bottom[np.argmax(bottom[:, 0])]
    return min(height_above_skin(problem, a + t * (b - a)) for t in np.linspace(0.0, 1.0, samples))


def with_smallest_gaps(surface, **options):
    """``pressed`` recording the smallest vertex and edge distance to the skin at every iterate."""
    gaps = []

    def record(problem, x):
        gaps.append(min(np.concatenate(problem.contact.vertex_gaps(x, within=1.0) + problem.contact.edge_gaps(x, within=1.0))))

    problem = pressed(surface, monitor=record, **options)
    problem.iterate_gaps = gaps
    return problem


@pytest.fixture(scope="module")
def tip():
    return with_smallest_gaps(pyramid())


@pytest.fixture(scope="module")
def blade():
    return with_smallest_gaps(BLADE)


@pytest.mark.parametrize("surface", [pyramid(), BLADE], ids=["tip", "blade"])
def test_the_nodes_barrier_lets_a_sharp_object_through_the_skin(surface):
    """Without the features' barriers (``faces=False``) the tip and the blade pass between the
    skin's nodes: their lowest points end 1 mm inside the flesh and the skin carries no force."""
    problem = pressed(surface, faces=False)
    assert not isinstance(problem.contact, ObjectFeatureContact)
    assert lowest_height(problem) < -0.9
    assert np.abs(problem.contact.nodal_forces(problem.u.x.array)).max() == 0.0


def test_the_tips_vertex_dents_the_skin(tip):
    """The apex stays outside the skin at every Newton iterate (the move's dent and the solve) and
    ends within dhat of it, 1 mm below the skin's rest height: the corners of the skin triangle
    under it pushed 0.5 mm or more down; the skin's force on the tip balances the bones'
    reactions."""
    assert isinstance(tip.contact, ObjectFeatureContact)
    assert len(tip.iterate_gaps) > 2 and min(tip.iterate_gaps) > 0.0
    assert 0.0 < lowest_height(tip) < tip.contact.dhat
    assert tip.contact.contact_features(tip.u.x.array)[0] == 1
    corners = tip.contact.surface.rest[tip.contact.surface.triangles]
    weights = closest_points(np.repeat(APEX[None] - [0.0, 0.0, 1.0], len(corners), axis=0), corners[:, 0],
                             corners[:, 1], corners[:, 2])[1]
    under = tip.contact.surface.triangles[np.flatnonzero((weights > 1e-9).all(axis=1)
                                                         & np.isclose(corners[:, :, 2], 10.0).all(axis=1))]
    assert len(under) == 1
    assert (tip.contact.positions(tip.u.x.array)[under[0], 2] < 10.0 - 0.5).all()
    assert_force_balance(tip)


def test_the_blades_edges_dent_the_skin(blade):
    """The blade's bottom edges cross the skin's edges: they, and its bottom corners, stay outside
    the skin at every Newton iterate and end within dhat of it along their whole length; the
    skin's force on the blade balances the bones' reactions."""
    assert len(blade.iterate_gaps) > 2 and min(blade.iterate_gaps) > 0.0
    assert 0.0 < lowest_height(blade) < blade.contact.dhat
    vertices, edges = blade.contact.contact_features(blade.u.x.array)
    assert edges >= 2 and vertices >= 1
    assert_force_balance(blade)


@pytest.mark.parametrize("name", ["tip", "blade"])
def test_gradient_and_hessian_against_differences_of_the_energy(name, request):
    """At the pressed state with the object lifted until no vertex or edge is closer to the skin
    than 0.02 mm (its terms active, their distances far above the differences' steps): the tip's
    vertex terms, the blade's edge terms too."""
    problem = request.getfixturevalue(name)
    contact = problem.contact
    pose = contact.poses[0]
    u = problem.u.x.array
    smallest = min(np.concatenate(contact.vertex_gaps(u, within=1.0) + contact.edge_gaps(u, within=1.0)))
    contact.set_poses((AffineMap(pose.matrix, pose.translation + [0.0, 0.0, max(0.02 - smallest, 0.0)]),))
    try:
        ends = contact.object_terms(problem.u.x.array)[0][6]
        assert (ends[:, 1] < 0).any() and (name == "tip" or (ends[:, 1] >= 0).any())
        assert_barrier_derivatives(problem, contact)
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
    area = contact.features[0].vertex_areas[apex]
    counts = []
    try:
        for over in ([20.8, 11.6], [21.25, 10.0], [22.5, 10.0]):  # a face, an edge, a corner
            contact.set_poses((AffineMap(np.eye(3), [*over, 10.02] - APEX),))
            _, weight, value, *_, ends = contact.object_terms(rest)[0]
            mine = (ends[:, 0] == apex) & (ends[:, 1] < 0)  # the apex's terms, not its edges'
            sign = weight[mine] / area
            assert np.array_equal(np.abs(sign), np.ones(len(sign)))
            assert sign @ value[mine] == pytest.approx(barrier(np.array([0.02]), 0.05)[0], rel=1e-12)
            counts.append(len(sign))
    finally:
        contact.set_poses((pose,))
    assert counts[0] == 1 and counts[1] == 3 and counts[2] > 3  # a corner: its triangles, edges, itself


@pytest.mark.parametrize("name", ["tip", "blade"])
def test_pose_rates_against_differences(name, request):
    """d(dE_c/dx)/d(pose) . rate, the nodes held, against central differences in the pose: a
    translation and a rotation about a point off the object."""
    problem = request.getfixturevalue(name)
    contact, u = problem.contact, problem.u.x.array
    pose = contact.poses[0]
    axis, angle_rate = np.array([0.3, -0.5, 0.8]), 0.02
    a = axis / np.linalg.norm(axis)
    skew = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])  # skew y = a x y
    velocity = np.array([0.3, -0.2, 1.0])
    rate = contact.pose_rate_forces(u, [(angle_rate * skew @ pose.matrix, velocity)])
    h = 1e-6

    def forces(t):
        turned = rotation(axis, angle_rate * t) @ pose.matrix
        contact.set_poses((AffineMap(turned, pose.translation + t * velocity),))
        return contact.nodal_forces(u)

    try:
        fd = (forces(h) - forces(-h)) / (2 * h)
    finally:
        contact.set_poses((pose,))
    assert np.abs(rate).max() > 1.0
    assert np.abs(rate - fd).max() <= 1e-5 * np.abs(rate).max()


@pytest.mark.parametrize("name, surface", [("tip", pyramid()), ("blade", BLADE)])
def test_same_result_on_one_rank(name, surface, request):
    problem = request.getfixturevalue(name)
    serial = pressed(surface, comm=MPI.COMM_SELF)
    here = problem.contact.nodal_forces(problem.u.x.array).sum(axis=0)
    alone = serial.contact.nodal_forces(serial.u.x.array).sum(axis=0)
    assert np.abs(here - alone).max() <= 1e-8 * np.abs(alone).max()
    assert lowest_height(problem) == pytest.approx(lowest_height(serial), rel=1e-8)
