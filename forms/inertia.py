"""Inertia and viscous damping of the flesh, in pure UFL, for time integration.

In the project's units (mm, kPa, mN) the consistent mass unit is the kilogram and the time unit the
second: kPa mm^2 = 1e3 N/m^2 * 1e-6 m^2 = 1e-3 N = mN, and 1 mN = 1e-3 kg m/s^2 = 1 kg mm/s^2.
Soft tissue's 1000 kg/m^3 is then 1e-6 kg/mm^3; a shear modulus mu (kPa) and a density rho
(kg/mm^3) give the shear wave speed sqrt(mu/rho) in mm/s.
"""
from dataclasses import dataclass

import ufl


@dataclass(frozen=True)
class Inertia:
    """d'Alembert force of a body of ``density`` (kg/mm^3)."""

    density: float | ufl.core.expr.Expr

    def virtual_work(self, acceleration, v):
        """Integrand of the inertial virtual work rho a . v (mN/mm^3 times mm)."""
        return self.density * ufl.inner(acceleration, v)

    def kinetic_energy(self, velocity):
        """Integrand of 1/2 rho |v|^2 (mN mm per mm^3)."""
        return 0.5 * self.density * ufl.inner(velocity, velocity)


@dataclass(frozen=True)
class ViscousDamping:
    """Rayleigh-like damping, linear in the velocity: a drag ``mass_proportional`` (1/s) times the
    inertia (C = alpha M), plus a Kelvin-Voigt viscous stress 2 eta sym(grad v) of ``viscosity``
    eta (kPa s), which damps the fast, short modes most (stiffness-like)."""

    density: float | ufl.core.expr.Expr
    mass_proportional: float | ufl.core.expr.Expr
    viscosity: float | ufl.core.expr.Expr

    def virtual_work(self, velocity, v):
        return (self.mass_proportional * self.density * ufl.inner(velocity, v)
                + 2.0 * self.viscosity * ufl.inner(ufl.sym(ufl.grad(velocity)), ufl.sym(ufl.grad(v))))
