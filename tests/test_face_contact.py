"""Skin triangles kept out of spheres (face_dolfinx.physics.face_contact): the point-triangle
distance and its derivatives against the IPC Toolkit and finite differences, the barrier's
gradient and Hessian against finite differences of its energy, no point of any skin triangle
inside the sphere at any Newton iterate (where the nodal barrier leaves triangles inside), the
collision-free step bound, the pose rates, force balance, the same result on 1 and 2 ranks, the
small face's cheek, and a sphere that cuts a triangle between its nodes refused at set-up.
"""
from mpi4py import MPI
from petsc4py import PETSc
import numpy as np
import pytest
import dolfinx.fem.petsc as fem_petsc

import ipctk
from face_dolfinx.model.bones import AffineMap
from face_dolfinx.physics.contact import CCD_KEEP, ContactSettings, Sphere
from face_dolfinx.physics.face_contact import FaceContactPotential, distance_derivatives, triangle_distances
from face_dolfinx.physics.problem import FaceProblem
from test_contact import RADIUS, assert_barrier_derivatives, assert_force_balance, gaps_while_pressing, cheek_path, skin_slab
from test_contact import pressed_slab as nodal_or_face_pressed_slab

# Off the slab's grid lines, so that no nearest point sits on a boundary between a triangle's
# face, edge and vertex regions (where the distance's Hessian jumps).
OFFSET = np.array([0.37, 0.61, 0.0])
CENTRE = np.array([20.0, 10.0, 10.0 + RADIUS]) + OFFSET


def sphere_at(depth):
    """The sphere's pose pressed ``depth`` mm into the undeformed top face."""
    return AffineMap(np.eye(3), CENTRE - [0.0, 0.0, depth])


def pressed_slab(comm=MPI.COMM_WORLD, depth=1.5, faces=True):
    return nodal_or_face_pressed_slab(comm, depth, faces=faces, at=sphere_at)


@pytest.fixture(scope="module")
def slab():
    return pressed_slab()


def test_point_triangle_distance_and_its_derivatives():
    """Against the IPC Toolkit's squared distance and central differences, in every region."""
    rng = np.random.default_rng(3)
    regions = set()
    for _ in range(40):
        point, corners = rng.normal(size=3) * 2.0, rng.normal(size=(3, 3))
        distance, weights, direction = triangle_distances(point, corners[None])
        regions.add(int((weights[0] > 0.0).sum()))  # 3: the face, 2: an edge, 1: a vertex
        assert distance[0] == pytest.approx(np.sqrt(ipctk.point_triangle_distance(point, *corners)), rel=1e-12)
        gradient, hessian = distance_derivatives(point, corners)
        # dd/dx_i = w_i n, dd/dp = -n.
        assert np.allclose(gradient[3:].reshape(3, 3), weights[0][:, None] * direction[0], atol=1e-12)
        assert np.allclose(gradient[:3], -direction[0], atol=1e-12)
        state = np.concatenate([point, corners.reshape(-1)])
        h = 1e-6

        def derivatives_at(y):
            return distance_derivatives(y[:3], y[3:].reshape(3, 3))

        for k in range(12):
            step = h * np.eye(12)[k]
            plus, minus = derivatives_at(state + step), derivatives_at(state - step)
            assert np.allclose((plus[0] - minus[0]) / (2 * h), hessian[:, k], atol=1e-6 * max(1.0, np.abs(hessian).max()))
    assert regions == {1, 2, 3}


def test_gradient_and_hessian_against_differences_of_the_energy(slab):
    """At the pressed state: triangles within dhat, no node within it."""
    contact = slab.contact
    assert isinstance(contact, FaceContactPotential)
    assert contact.contact_triangles(slab.u.x.array) >= 4
    assert contact.triangle_gaps(slab.u.x.array).min() > 0.01
    assert_barrier_derivatives(slab, contact)


def test_no_triangle_enters_the_sphere_at_any_newton_iterate():
    """Every triangle stays outside at every iterate, the moving solves included; the nodal
    barrier, pressed as far, leaves points of the triangles inside (the slab's 2.5 mm squares)."""
    problem = pressed_slab(depth=0.0)
    gaps = gaps_while_pressing(problem, lambda u: problem.contact.triangle_gaps(u).min(), sphere_at)
    assert len(gaps) > 5 and min(gaps) > 0.0
    assert 0.0 < problem.contact.triangle_gaps(problem.u.x.array).min() < problem.contact.dhat
    assert problem.residual_norm() < 1e-6

    nodal = pressed_slab(depth=2.5, faces=False)
    assert not isinstance(nodal.contact, FaceContactPotential) and nodal.contact.min_gap(nodal.u.x.array) > 0.0
    x = nodal.contact.positions(nodal.u.x.array)
    inside = RADIUS - triangle_distances(nodal.contact.poses[0].translation, x[nodal.contact.surface.triangles])[0]
    assert inside.max() > 0.05  # mm


def test_step_bound_keeps_every_triangle_clear(slab):
    """A step moving every free node 2 mm up, into the sphere (above the slab): cut so that no
    point of the segment brings a triangle closer than (1 - CCD_KEEP) of its gap now; twice the
    bound would."""
    contact, u = slab.contact, slab.u.vector
    gaps_now = contact.triangle_gaps(u.array_r)[0]
    step = u.duplicate()
    step.set(0.0)
    step.array.reshape(-1, 3)[:, 2] = -2.0  # the Newton update x - step
    fem_petsc.set_bc(step, slab.bcs, scale=0.0)
    fraction = contact.step_fraction(u, step, 1.0)
    assert 0.0 < fraction < 0.1

    def gaps_at(t):
        x = u.copy()
        x.axpy(-t, step)
        return contact.triangle_gaps(x.array_r)[0]

    for t in np.linspace(0.0, fraction, 11):
        assert (gaps_at(t) >= (1.0 - CCD_KEEP) * gaps_now - 1e-12).all()
    assert (gaps_at(2.0 * fraction) < (1.0 - CCD_KEEP) * gaps_now).any()


def test_pose_rates_against_differences(slab):
    """d(dE_c/dx)/d(centre) . velocity, the nodes held, against central differences in the pose."""
    contact, u = slab.contact, slab.u.x.array
    velocity = np.array([0.3, -0.2, 1.0])
    pose = contact.poses[0]
    rate = contact.pose_rate_forces(u, [(np.zeros((3, 3)), velocity)])
    h = 1e-6

    def forces(t):
        contact.set_poses((AffineMap(pose.matrix, pose.translation + t * velocity),))
        return contact.nodal_forces(u)

    fd = (forces(h) - forces(-h)) / (2 * h)
    contact.set_poses((pose,))
    assert np.abs(rate).max() > 1.0
    assert np.abs(rate - fd).max() <= 1e-5 * np.abs(rate).max()


def test_contact_force_balances_the_bone_reactions(slab):
    on_sphere = assert_force_balance(slab)
    # The triangles' pressure carries the same force: sum_i p_i A_i = sum_T p_T A_T.
    pressure = slab.contact.face_pressure(slab.u.x.array)
    assert (pressure >= 0.0).all()
    assert pressure @ slab.contact.surface.areas == pytest.approx(np.linalg.norm(on_sphere), rel=0.05)


def test_same_result_on_one_rank(slab):
    """The distributed solve against the same problem on this rank alone."""
    serial = pressed_slab(comm=MPI.COMM_SELF)
    here = slab.contact.nodal_forces(slab.u.x.array).sum(axis=0)
    alone = serial.contact.nodal_forces(serial.u.x.array).sum(axis=0)
    assert np.abs(here - alone).max() <= 1e-8 * np.abs(alone).max()
    assert slab.contact.triangle_gaps(slab.u.x.array).min() == \
        pytest.approx(serial.contact.triangle_gaps(serial.u.x.array).min(), rel=1e-8)


def test_sphere_cutting_a_triangle_between_nodes_is_refused():
    """Over the middle of a top triangle, 0.02 mm into it: every node is outside (the nodes are
    over 1 mm off the axis, where the sphere is 0.05 mm higher), the triangle is not."""
    model = skin_slab(cells=(8, 4, 2))
    points = FaceProblem(model, contact=ContactSettings((Sphere(RADIUS),), (AffineMap(np.eye(3), [20.0, 10.0, 40.0]),),
                                                        where="sphere.json")).contact
    corners = points.surface.rest[points.surface.triangles]
    top = np.flatnonzero(np.isclose(corners[:, :, 2], 10.0).all(axis=1))
    middle = corners[top[0]].mean(axis=0)
    settings = ContactSettings((Sphere(RADIUS),), (AffineMap(np.eye(3), middle + [0.0, 0.0, RADIUS - 0.02]),),
                               where="sphere.json")
    nodal = FaceProblem(model, contact=ContactSettings(settings.objects, settings.poses, faces=False))
    assert nodal.contact.min_gap(nodal.u.x.array) > 0.0
    with pytest.raises(ValueError, match="sphere.json: the sphere of radius 10 mm .* cuts 1 triangles of the skin"):
        FaceProblem(model, contact=settings)


def test_sphere_pressed_into_the_cheek_of_the_small_face(model):
    """The paper's figure 9 on the 5K face (skin edges of 12 mm, where the nodal barrier leaves
    triangle points over 1 mm inside a 15 mm ball): no point of any skin triangle inside the ball
    at any Newton iterate, equilibrium, the bones carry the ball's force."""
    radius = 15.0
    problem = FaceProblem(model, contact=ContactSettings((Sphere(radius),),
                                                         (AffineMap(np.eye(3), cheek_path(model, [-1.0], radius)[0]),)))
    problem.solve(activations={"zygomaticus_major_left": 0.5})
    gaps = []
    problem.solver.snes.setMonitor(
        lambda snes, it, norm: gaps.append(problem.contact.triangle_gaps(snes.getSolution().array_r).min()))
    report = problem.solve(objects=(AffineMap(np.eye(3), cheek_path(model, [4.0], radius)[0]),))
    problem.solver.snes.cancelMonitor()
    assert report.converged and min(gaps) > 0.0
    assert problem.contact.contact_triangles(problem.u.x.array) >= 3
    assert problem.residual_norm() < 1e-6
    on_ball = problem.contact.nodal_forces(problem.u.x.array).sum(axis=0)
    internal = fem_petsc.create_vector(problem.solver.residual_form)
    fem_petsc.assemble_vector(internal, problem.solver.residual_form)
    internal.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
    owned = problem.bone_blocks[problem.bone_blocks < problem.V.dofmap.index_map.size_local]
    reaction = MPI.COMM_WORLD.allreduce(internal.array_r.reshape(-1, 3)[owned].sum(axis=0), op=MPI.SUM)
    assert np.linalg.norm(on_ball) > 10.0
    assert np.abs(reaction - on_ball).max() <= 1e-5 * np.abs(on_ball).max()
