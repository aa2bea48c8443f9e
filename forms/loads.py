"""Surface loads that follow the deformation, in pure UFL.

A pressure p acts on the deformed surface along its normal n: the traction is -p n per deformed
area. Nanson's formula n da = J F^-T N dA carries it back to the reference surface, where we
integrate:
    external virtual work = integral over the reference surface of  -p J F^-T N . v  dA.
The load depends on u through F, so it contributes to the tangent, and that contribution is not
symmetric in general (it is for a closed cavity whose rim is fixed, where p times the cavity
volume is a potential, but not for an open face such as the bottom of the Land et al. beam).
Pair it with an LU factorisation, not Cholesky, and with a residual-based line search.
"""
from dataclasses import dataclass

import ufl


@dataclass(frozen=True)
class FollowerPressure:
    """Pressure ``pressure`` (kPa, positive pushes into the body) on the deformed surface."""

    pressure: float | ufl.core.expr.Expr

    def traction(self, F, N):
        """First Piola traction -p J F^-T N: force per reference area on a face of normal N."""
        return -self.pressure * ufl.det(F) * ufl.inv(F).T * N

    def virtual_work(self, F, N, v):
        """Integrand of the external virtual work for a test function v (integrate over ds)."""
        return ufl.dot(self.traction(F, N), v)
