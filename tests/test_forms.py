"""Constitutive laws against hand-computed homogeneous deformations.

Each term's energy and first Piola stress for a constant deformation gradient F0 is assembled on a
box (u = (F0 - I) X is exact in P1) and compared with an independent numpy evaluation: the fiber
curves are integrated numerically here (scipy quad) rather than with the closed forms in forms/.
"""
from mpi4py import MPI
import numpy as np
import pytest
from scipy.integrate import quad
import ufl
from dolfinx import fem, mesh as dmesh
import dolfinx.fem.petsc as fem_petsc

import forms
from face_dolfinx.physics.material import FaceMaterial, FiberSlot

P1, P2 = 0.05, 6.6
P3 = P1 * P2 * (np.exp(0.4 * P2) - 1.0)
P4 = P1 * (np.exp(0.4 * P2) * (1.0 - 1.4 * P2) + P2 - 1.0)
BOX = [np.zeros(3), np.array([2.0, 1.0, 1.5])]
VOLUME = 3.0


def f_active(stretch):
    e = abs(stretch - 1.0)
    return 1 - 25 / 6 * e**2 if e < 0.4 else (25 / 3 * (e - 0.6) ** 2 if e < 0.6 else 0.0)


def f_passive(stretch):
    e = stretch - 1.0
    if e <= 0:
        return 0.0
    return P1 * (np.exp(P2 * e) - P2 * e - 1) if e <= 0.4 else P3 * stretch + P4


def integral(curve, stretch):
    return quad(curve, 1.0, stretch, points=[0.4, 0.6, 1.4, 1.6], epsabs=1e-13, epsrel=1e-13)[0]


def mooney_rivlin_numpy(F, mu10, mu01):
    C = F.T @ F
    J, I1 = np.linalg.det(F), np.trace(C)
    I2 = 0.5 * (I1**2 - np.trace(C @ C))
    energy = mu10 * (J ** (-2 / 3) * I1 - 3) + mu01 * (J ** (-4 / 3) * I2 - 3)
    FinvT = np.linalg.inv(F).T
    stress = (mu10 * J ** (-2 / 3) * (2 * F - 2 / 3 * I1 * FinvT)
              + mu01 * J ** (-4 / 3) * (2 * (I1 * F - F @ C) - 4 / 3 * I2 * FinvT))
    return energy, stress


def volumetric_numpy(F, kappa):
    J = np.linalg.det(F)
    return 0.5 * kappa * np.log(J) ** 2, kappa * np.log(J) * np.linalg.inv(F).T


def fiber_numpy(F, f0, weight, activation):
    stretch = np.linalg.norm(F @ f0)
    energy = weight * (activation * integral(f_active, stretch) + integral(f_passive, stretch))
    tension = weight * (activation * f_active(stretch) + f_passive(stretch))
    return energy, tension / stretch * np.outer(F @ f0, f0)


@pytest.fixture(scope="module")
def box():
    domain = dmesh.create_box(MPI.COMM_WORLD, BOX, [2, 2, 2], dmesh.CellType.tetrahedron)
    V = fem.VectorFunctionSpace(domain, ("CG", 1))
    return domain, V


def homogeneous(V, F0):
    """The displacement of the homogeneous deformation F0 and its deformation gradient."""
    u = fem.Function(V)
    u.interpolate(lambda x: ((F0 - np.eye(3)) @ x))
    return u, forms.deformation_gradient(u)


def stress_from_residual(V, residual):
    """P : G / volume for the 9 unit G, from a residual form integral P : grad v dx."""
    r = fem_petsc.assemble_vector(fem.form(residual))
    r.ghostUpdate(addv=2, mode=1)  # ADD, REVERSE
    probe = fem.Function(V)
    stress = np.zeros((3, 3))
    for i in range(3):
        for j in range(3):
            G = np.zeros((3, 3))
            G[i, j] = 1.0
            probe.interpolate(lambda x: G @ x)
            stress[i, j] = r.dot(probe.vector) / VOLUME
    return stress


def assemble_energy_and_stress(V, F0, laws):
    """Energy, P : G from differentiating the energy, and P : G from the laws' hand-written
    first_piola (for the 9 unit G), for the homogeneous deformation F0."""
    u, F = homogeneous(V, F0)
    dx = ufl.dx(metadata={"quadrature_degree": 1})
    psi = sum(law.strain_energy(F) for law in laws)
    energy = V.mesh.comm.allreduce(fem.assemble_scalar(fem.form(psi * dx)), op=MPI.SUM)
    v = ufl.TestFunction(V)
    residuals = [ufl.derivative(psi * dx, u, v), ufl.inner(sum(law.first_piola(F) for law in laws), ufl.grad(v)) * dx]
    return energy / VOLUME, [stress_from_residual(V, residual) for residual in residuals]


DEFORMATIONS = {
    "stretch_shear": np.array([[1.2, 0.1, 0.0], [0.05, 0.9, 0.2], [0.0, -0.1, 1.05]]),
    "compression": np.diag([0.8, 1.1, 0.95]),
    "rotated_stretch": np.array([[0.0, -1.1, 0.0], [1.3, 0.0, 0.0], [0.0, 0.0, 0.9]]),
}


@pytest.mark.parametrize("name", DEFORMATIONS)
def test_mooney_rivlin_and_volumetric(box, name):
    _, V = box
    F0 = DEFORMATIONS[name]
    energy, stresses = assemble_energy_and_stress(V, F0, [forms.MooneyRivlin(60.0, 20.0)])
    expected_energy, expected_stress = mooney_rivlin_numpy(F0, 60.0, 20.0)
    assert energy == pytest.approx(expected_energy, rel=1e-12, abs=1e-12)
    for stress in stresses:
        assert np.allclose(stress, expected_stress, rtol=1e-11, atol=1e-10)
    energy, stresses = assemble_energy_and_stress(V, F0, [forms.LogVolumetric(3000.0)])
    expected_energy, expected_stress = volumetric_numpy(F0, 3000.0)
    assert energy == pytest.approx(expected_energy, rel=1e-12)
    for stress in stresses:
        assert np.allclose(stress, expected_stress, rtol=1e-11, atol=1e-9)


def test_isochoric_energy_vanishes_for_rotation_and_dilation(box):
    """Mooney-Rivlin is isochoric: a rotation times a dilation stores no deviatoric energy."""
    _, V = box
    c, s = np.cos(0.7), np.sin(0.7)
    F0 = 1.3 * np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    energy, _ = assemble_energy_and_stress(V, F0, [forms.MooneyRivlin(60.0, 20.0)])
    assert abs(energy) < 1e-11


# Fiber stretches covering every branch of f_L (inner parabola, shoulder, zero) and f_P
# (none, exponential, linear), in compression and extension.
STRETCHES = [0.35, 0.5, 0.7, 1.0, 1.15, 1.39, 1.45, 1.55, 1.8]


@pytest.mark.parametrize("stretch", STRETCHES)
def test_fiber_energy_and_stress_along_fiber(box, stretch):
    _, V = box
    f0 = np.array([1.0, 2.0, 2.0]) / 3.0
    # Uniaxial stretch along f0 plus a transverse shear that leaves |F f0| = stretch.
    transverse = np.array([2.0, -1.0, 0.0]) / np.sqrt(5.0)
    F0 = np.eye(3) + (stretch - 1.0) * np.outer(f0, f0) + 0.2 * np.outer(transverse, np.cross(f0, transverse))
    assert np.linalg.norm(F0 @ f0) == pytest.approx(stretch)
    weight, activation = 300.0 * 0.7, 0.6
    fiber = ufl.as_vector(f0.tolist())
    energy, stresses = assemble_energy_and_stress(
        V, F0, [forms.PassiveFiber(fiber, weight), forms.ActiveFiber(fiber, weight, activation)])
    expected_energy, expected_stress = fiber_numpy(F0, f0, weight, activation)
    assert energy == pytest.approx(expected_energy, rel=1e-10, abs=1e-10)
    for stress in stresses:
        assert np.allclose(stress, expected_stress, rtol=1e-10, atol=1e-9)


def test_active_tension_at_rest_length_is_peak_stress(box):
    """At lambda = 1 the active tension is sigma_max * rho * a (f_L(1) = 1), with no passive part."""
    _, V = box
    fiber = ufl.as_vector([0.0, 0.0, 1.0])
    _, stresses = assemble_energy_and_stress(V, np.eye(3), [forms.ActiveFiber(fiber, 300.0 * 0.5, 0.8)])
    expected = np.zeros((3, 3))
    expected[2, 2] = 300.0 * 0.5 * 0.8
    for stress in stresses:
        assert np.allclose(stress, expected, atol=1e-10)


def test_face_material_is_the_flesh_plus_every_muscle_slot(box):
    """FaceMaterial's energy and stress are the Mooney-Rivlin, volumetric and per-slot fiber
    terms evaluated independently; its active stress along activation directions d_k is
    sum_k d_k dP/da_k (the energy is linear in each activation)."""
    _, V = box
    F0 = DEFORMATIONS["stretch_shear"]
    fibers = [np.array([1.0, 2.0, 2.0]) / 3.0, np.array([0.0, 0.6, 0.8])]
    weights, activations, directions = [210.0, 90.0], [0.6, 0.3], [0.5, 1.0]
    slots = [FiberSlot(ufl.as_vector(f0.tolist()), w, a) for f0, w, a in zip(fibers, weights, activations)]
    material = FaceMaterial.from_parameters(dict(mu10=60.0, mu01=20.0, kappa=3000.0), slots)
    parts = [mooney_rivlin_numpy(F0, 60.0, 20.0), volumetric_numpy(F0, 3000.0)] + [
        fiber_numpy(F0, f0, w, a) for f0, w, a in zip(fibers, weights, activations)]
    energy, stresses = assemble_energy_and_stress(V, F0, [material])
    assert energy == pytest.approx(sum(e for e, _ in parts), rel=1e-10)
    for stress in stresses:
        assert np.allclose(stress, sum(p for _, p in parts), rtol=1e-10, atol=1e-8)
    _, F = homogeneous(V, F0)
    active = stress_from_residual(V, ufl.inner(material.active_first_piola(F, directions), ufl.grad(ufl.TestFunction(V)))
                                  * ufl.dx(metadata={"quadrature_degree": 1}))
    expected = sum(fiber_numpy(F0, f0, w, d)[1] - fiber_numpy(F0, f0, w, 0.0)[1]
                   for f0, w, d in zip(fibers, weights, directions))
    assert np.abs(expected).max() > 10.0
    assert np.allclose(active, expected, rtol=1e-10, atol=1e-9)
