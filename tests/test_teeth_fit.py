"""Fitting with the teeth: the contact gradient's derivative in the objects' poses
(``ContactPotential.pose_rate_forces``) against central differences for every object kind, and the
jaw's sensitivities of the small face with the lips pressed on the lower teeth against central
differences of re-solved equilibria (with the teeth's mixed term, and measurably wrong without it).
"""
from mpi4py import MPI
import numpy as np
import pytest
from dolfinx import fem
from dolfinx import mesh as dmesh

from face_dolfinx.model.bones import AffineMap, rotation
from face_dolfinx.physics.contact import ContactPotential, ContactSettings, HalfSpace, Sphere
from face_dolfinx.physics.rigid_mesh import TriangleMesh
from slab import slab_model

DHAT = 1.5  # mm: wide, so that many nodes of the slab's top face feel the objects at rest


def box(size):
    """An axis-aligned box [0, size] as 12 outward triangles."""
    corners = np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)], dtype=float) * size
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    return corners, np.array([t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))])


@pytest.fixture(scope="module")
def top_face():
    """The P1 space of the slab and its top face z = 10 (the mesh must outlive the contact: the
    contact surface keeps its communicator)."""
    model = slab_model(cells=(16, 8, 4))
    space = fem.VectorFunctionSpace(model.mesh, ("Lagrange", 1))
    return space, dmesh.locate_entities_boundary(model.mesh, 2, lambda x: np.isclose(x[2], 10.0))


def top_face_contact(top_face, obj, pose):
    """A contact potential of the slab's top face against ``obj`` at ``pose``, and a zero
    displacement."""
    space, facets = top_face
    contact = ContactPotential(space, facets, ContactSettings((obj,), (pose,), dhat=DHAT, stiffness=10.0))
    return contact, np.zeros(space.dofmap.index_map_bs * (space.dofmap.index_map.size_local
                                                         + space.dofmap.index_map.num_ghosts))


# Each kind hovering just above the top face, turned so that gaps, normals and (sphere, the box's
# edges and corners) curvatures vary over the nodes within dhat.
TURN = rotation([0.3, -0.5, 0.8], 0.1)
OBJECTS = {
    "sphere": (Sphere(10.0), AffineMap(TURN, [20.0, 10.0, 20.3])),
    "half-space": (HalfSpace((0.0, 0.0, -1.0)), AffineMap(rotation([0.2, 1.0, 0.1], 0.02), [20.0, 10.0, 10.8])),
    "box": (TriangleMesh(*box((12.0, 8.0, 4.0)), name="box"), AffineMap(TURN, [14.0, 5.0, 9.9])),
}


@pytest.mark.parametrize("kind", OBJECTS)
def test_contact_gradient_rate_in_the_pose_against_differences(top_face, kind):
    obj, pose = OBJECTS[kind]
    contact, displacement = top_face_contact(top_face, obj, pose)
    gaps = contact.gaps(displacement)[0]
    assert gaps.min() > 0.0 and (gaps < DHAT).sum() >= 10, kind
    spin = np.array([0.4, -0.7, 0.5])  # the pose's angular velocity (rad per unit parameter) ...
    velocity = np.array([0.3, 0.2, -0.6])  # ... and its translation's rate (mm per unit)

    def pose_at(h):
        return AffineMap(rotation(spin, h * np.linalg.norm(spin)) @ pose.matrix, pose.translation + h * velocity)

    def forces_at(h):
        contact.set_poses((pose_at(h),))
        return contact.nodal_forces(displacement)

    step = 1e-5
    differences = (forces_at(step) - forces_at(-step)) / (2 * step)
    contact.set_poses((pose,))
    W = np.array([[0.0, -spin[2], spin[1]], [spin[2], 0.0, -spin[0]], [-spin[1], spin[0], 0.0]])
    rate = contact.pose_rate_forces(displacement, [(W @ pose.matrix, velocity)])
    scale = np.abs(differences).max()
    assert scale > 0.0
    assert np.abs(rate - differences).max() < 1e-6 * scale, kind
    assert not contact.pose_rate_forces(displacement, [None]).any()
    # The turn alone: nothing for a sphere turning about its centre, a good part of the rate for
    # the others (so the comparison above sees the turn's terms too).
    turn_only = np.abs(contact.pose_rate_forces(displacement, [(W @ pose.matrix, np.zeros(3))])).max()
    if kind == "sphere":
        assert turn_only < 1e-9 * scale
    else:
        assert turn_only > 0.1 * scale


def test_non_rigid_pose_rate_is_refused(top_face):
    obj, pose = OBJECTS["box"]
    contact, displacement = top_face_contact(top_face, obj, pose)
    stretch = np.diag([1.0, 0.0, 0.0])  # an affine frame's rate, not a rotation's
    with pytest.raises(ValueError, match="box .* moves non-rigidly .* needs rigid frames"):
        contact.pose_rate_forces(displacement, [(stretch, np.zeros(3))])
    contact.set_poses((AffineMap(1.01 * pose.matrix, pose.translation),))
    with pytest.raises(ValueError, match="moves non-rigidly"):
        contact.pose_rate_forces(displacement, [(np.zeros((3, 3)), np.ones(3))])
