"""Guccione's exponential law for passive myocardium and an active stress along the fiber.

Guccione, Costa & McCulloch (1995), in the form of the cardiac verification benchmark
(Land et al. 2015):
    W = C/2 (exp(Q) - 1),
    Q = b_f E_ff^2 + b_t (E_ss^2 + E_nn^2 + E_sn^2 + E_ns^2) + b_fs (E_fs^2 + E_sf^2 + E_fn^2 + E_nf^2),
with E = (F^T F - I)/2 the Green strain in an orthonormal fiber frame (f, s, n).

b_t weighs both transverse directions alike and b_fs both fiber shears, so Q depends on f alone:
    E_ss^2 + E_nn^2 + 2 E_sn^2 = E:E - 2 |E f|^2 + E_ff^2,    E_fs^2 + E_fn^2 = |E f|^2 - E_ff^2,
hence
    Q = (b_f - 2 b_fs + b_t) E_ff^2 + b_t E:E + 2 (b_fs - b_t) |E f|^2.
That is what we code: no sheet field is needed, and any completion of f to a frame gives the same
energy (tests/test_land2015.py checks it against the frame formula in numpy).
"""
from dataclasses import dataclass

import ufl


def green_strain(F):
    """E = (F^T F - I) / 2."""
    return 0.5 * (F.T * F - ufl.Identity(F.ufl_shape[0]))


@dataclass(frozen=True)
class Guccione:
    """Transversely isotropic Guccione energy; ``fiber`` is the unit rest fiber direction f0.

    C in stress units (kPa in the benchmarks), b_f, b_t, b_fs dimensionless.
    """

    C: float | ufl.core.expr.Expr
    b_f: float | ufl.core.expr.Expr
    b_t: float | ufl.core.expr.Expr
    b_fs: float | ufl.core.expr.Expr
    fiber: ufl.core.expr.Expr

    def exponent(self, F):
        """Q of the module docstring."""
        E = green_strain(F)
        E_f = E * self.fiber
        E_ff = ufl.dot(self.fiber, E_f)
        return ((self.b_f - 2.0 * self.b_fs + self.b_t) * E_ff**2 + self.b_t * ufl.inner(E, E)
                + 2.0 * (self.b_fs - self.b_t) * ufl.dot(E_f, E_f))

    def strain_energy(self, F):
        return 0.5 * self.C * (ufl.exp(self.exponent(F)) - 1.0)


@dataclass(frozen=True)
class ActiveFiberStress:
    """Active tension ``tension`` (Ta) along the rest fiber f0: second Piola stress S_a = Ta f0 (x) f0.

    Written as the energy Ta E_ff = Ta/2 (f0.C f0 - 1), whose derivative with respect to E is that
    stress, so the active part adds a symmetric term to the tangent. (The face muscles of
    forms/muscle.py use a force-length curve instead; this is the constant-tension model of the
    cardiac benchmark.)
    """

    fiber: ufl.core.expr.Expr
    tension: float | ufl.core.expr.Expr

    def strain_energy(self, F):
        return self.tension * ufl.dot(self.fiber, green_strain(F) * self.fiber)
