"""Kinematic quantities of a displacement field, in pure UFL."""
import ufl


def deformation_gradient(u):
    """F = I + grad u for a displacement u on the reference configuration."""
    return ufl.variable(ufl.Identity(len(u)) + ufl.grad(u))


def invariants(F):
    """Right Cauchy-Green tensor C = F^T F with J = det F, I1 = tr C, I2 = (I1^2 - tr C^2) / 2."""
    C = F.T * F
    I1 = ufl.tr(C)
    I2 = 0.5 * (I1**2 - ufl.tr(C * C))
    return C, ufl.det(F), I1, I2


def fiber_stretch(F, fiber):
    """Stretch |F f0| of the unit rest direction f0 (not the isochoric stretch)."""
    return ufl.sqrt(ufl.dot(F * fiber, F * fiber))
