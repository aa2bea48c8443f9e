"""Incompressibility J = 1 enforced by a Lagrange multiplier, for a mixed formulation.

Adding -p (J - 1) to the strain energy gives the Lagrangian
    L(u, p) = integral of W(F) - p (J - 1) dx  (- external work),
whose stationary points satisfy equilibrium with the hydrostatic pressure p and J = 1 exactly
(weakly, in the pressure space). The tangent is symmetric but indefinite, and L is a saddle
function: a line search must not minimise it. With Taylor-Hood elements (P2 displacement, P1
pressure) the pair is inf-sup stable and does not lock. The nearly incompressible alternative, a
penalty kappa/2 (ln J)^2 on a displacement-only formulation, is forms.flesh.LogVolumetric.
"""
from dataclasses import dataclass

import ufl


@dataclass(frozen=True)
class IncompressibilityMultiplier:
    """The term -p (J - 1) of the Lagrangian; ``pressure`` is the multiplier field p (kPa)."""

    pressure: ufl.core.expr.Expr

    def strain_energy(self, F):
        return -self.pressure * (ufl.det(F) - 1.0)
