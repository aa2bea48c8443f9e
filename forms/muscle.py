"""Transversely isotropic muscle fibers: passive and active tension along f0 (as energies).

Tension along the fiber (shared/reference/constitutive_and_controls.md, PhysBAM FACE_3D):
    T(lambda) = sigma_max * rho * (a f_L(lambda) + f_P(lambda)),   lambda = |F f0|,
with first Piola stress P = T/lambda (F f0) (x) f0. We write it as the energy
    Psi = sigma_max * rho * (a G_L(lambda - 1) + G_P(lambda - 1)),  G' = f,
so the tangent is symmetric and f = f0 + sum_i a_i f_i holds exactly (Psi is linear in a).
Here rho (the muscle's volume fraction in the tetrahedron) scales both the active and the
passive part, as sifakis2005 section 4 states ("both passive and active components scaled by the
volume fraction").
"""
from dataclasses import dataclass
import math

import ufl

from .kinematics import fiber_stretch

# Passive curve constants; p3, p4 continue the exponential as a C1 line beyond lambda = 1.4.
P1 = 0.05
P2 = 6.6
P3 = P1 * P2 * (math.exp(0.4 * P2) - 1.0)
P4 = P1 * (math.exp(0.4 * P2) * (1.0 - 1.4 * P2) + P2 - 1.0)

# Antiderivative of f_L at the kinks |lambda - 1| = 0.4 and 0.6.
_GL_04 = 0.4 - 25.0 / 18.0 * 0.4**3
_GL_06 = _GL_04 + 25.0 / 9.0 * (0.0 - (-0.2) ** 3)
# Antiderivative of f_P at lambda = 1.4.
_GP_04 = P1 * ((math.exp(0.4 * P2) - 1.0) / P2 - 0.5 * P2 * 0.4**2 - 0.4)


def active_force_length(stretch):
    """f_L: 1 at rest length, 1 - 25/6 s^2 for |s| < 0.4, 25/3 (|s| - 0.6)^2 up to 0.6, then 0."""
    e = abs(stretch - 1.0)
    return ufl.conditional(ufl.lt(e, 0.4), 1.0 - 25.0 / 6.0 * e**2,
                           ufl.conditional(ufl.lt(e, 0.6), 25.0 / 3.0 * (e - 0.6) ** 2, 0.0))


def passive_force_length(stretch):
    """f_P: zero in compression, p1 (exp(p2 s) - p2 s - 1) up to lambda = 1.4, then p3 lambda + p4."""
    e = stretch - 1.0
    return ufl.conditional(
        ufl.le(e, 0.0), 0.0,
        ufl.conditional(ufl.le(e, 0.4), P1 * (ufl.exp(P2 * e) - P2 * e - 1.0), P3 * stretch + P4))


def fiber_stress(F, fiber, tension):
    """First Piola stress of a fiber tension T along f0: P = T / lambda (F f0) (x) f0."""
    return tension / fiber_stretch(F, fiber) * ufl.outer(F * fiber, fiber)


def active_force_length_integral(stretch):
    """G_L(s) = integral of f_L over [0, s], s = lambda - 1, with
    f_L = 1 - 25/6 s^2 for |s| < 0.4, 25/3 (|s| - 0.6)^2 for 0.4 <= |s| < 0.6, else 0.
    Written branch by branch in s (no sign(s)) so that the force at rest length is exact."""
    s = stretch - 1.0

    def shoulder(e):  # G_L on 0.4 <= e < 0.6
        return _GL_04 + 25.0 / 9.0 * ((e - 0.6) ** 3 + 0.2**3)

    return ufl.conditional(
        ufl.lt(abs(s), 0.4), s - 25.0 / 18.0 * s**3,
        ufl.conditional(
            ufl.gt(s, 0.0),
            ufl.conditional(ufl.lt(s, 0.6), shoulder(s), _GL_06),
            ufl.conditional(ufl.gt(s, -0.6), -shoulder(-s), -_GL_06)))


def passive_force_length_integral(stretch):
    """G_P(s) = integral of f_P over [0, s]: f_P = 0 in compression,
    p1 (exp(p2 s) - p2 s - 1) up to lambda = 1.4, then the C1 line p3 lambda + p4."""
    e = stretch - 1.0
    return ufl.conditional(
        ufl.le(e, 0.0), 0.0,
        ufl.conditional(
            ufl.le(e, 0.4), P1 * ((ufl.exp(P2 * e) - 1.0) / P2 - 0.5 * P2 * e**2 - e),
            _GP_04 + 0.5 * P3 * (stretch**2 - 1.4**2) + P4 * (stretch - 1.4)))


@dataclass(frozen=True)
class PassiveFiber:
    """Passive fiber energy; ``weight`` = sigma_max * volume fraction (a DG0 field or number)."""

    fiber: ufl.core.expr.Expr
    weight: float | ufl.core.expr.Expr

    def strain_energy(self, F):
        return self.weight * passive_force_length_integral(fiber_stretch(F, self.fiber))

    def first_piola(self, F):
        return fiber_stress(F, self.fiber, self.weight * passive_force_length(fiber_stretch(F, self.fiber)))


@dataclass(frozen=True)
class ActiveFiber:
    """Active fiber energy, linear in ``activation`` (a in [0, 1]); ``weight`` as PassiveFiber."""

    fiber: ufl.core.expr.Expr
    weight: float | ufl.core.expr.Expr
    activation: float | ufl.core.expr.Expr

    def strain_energy(self, F):
        return self.activation * self.weight * active_force_length_integral(fiber_stretch(F, self.fiber))

    def first_piola(self, F):
        tension = self.activation * self.weight * active_force_length(fiber_stretch(F, self.fiber))
        return fiber_stress(F, self.fiber, tension)
