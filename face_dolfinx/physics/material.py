"""The face's constitutive model: the laws of forms/ composed into one strain energy.

Flesh everywhere (Sifakis et al. 2005): isochoric Mooney-Rivlin plus a logarithmic volumetric
penalty. Muscles are embedded per tetrahedron in K "slots" (see ``face_dolfinx.physics.problem``):
slot k carries a fiber direction f_k, a weight w_k = sigma_max * volume fraction and an activation
a_k, all cellwise fields, and adds the passive and active tension along f_k:

    Psi(F) = Psi_MR(F) + Psi_vol(F) + sum_k [ s Psi_passive(F; f_k, w_k) + a_k Psi_active(F; f_k, w_k) ]

The flesh parameters (mu10, mu01, kappa) and the passive fibre scale s may be numbers or cellwise
fields (regional overrides, ``face_dolfinx.model.regions``).

The object only composes UFL; the problem that owns the fields and spaces builds the forms.
"""
from dataclasses import dataclass

import ufl

import forms


@dataclass(frozen=True)
class FiberSlot:
    """One muscle slot of every cell: unit rest fiber, weight sigma_max * fraction, activation."""

    fiber: ufl.core.expr.Expr
    weight: ufl.core.expr.Expr
    activation: ufl.core.expr.Expr


@dataclass(frozen=True)
class FaceMaterial:
    """Flesh laws plus the passive and active fiber laws of every muscle slot."""

    flesh: forms.MooneyRivlin
    volumetric: forms.LogVolumetric
    slots: tuple[FiberSlot, ...]
    passive_scale: float | ufl.core.expr.Expr = 1.0

    @classmethod
    def from_parameters(cls, parameters: dict, slots, passive_scale=1.0) -> "FaceMaterial":
        """From material parameters (mu10, mu01, kappa in kPa: numbers or cellwise fields), the
        slots and the scale of the passive fibre curves."""
        return cls(forms.MooneyRivlin(parameters["mu10"], parameters["mu01"]),
                   forms.LogVolumetric(parameters["kappa"]), tuple(slots), passive_scale)

    def laws(self) -> list:
        """Every law of the energy: the flesh, then each slot's passive and active fiber."""
        laws = [self.flesh, self.volumetric]
        for slot in self.slots:
            laws += [forms.PassiveFiber(slot.fiber, self.passive_scale * slot.weight),
                     forms.ActiveFiber(slot.fiber, slot.weight, slot.activation)]
        return laws

    def strain_energy(self, F):
        return sum(law.strain_energy(F) for law in self.laws())

    def first_piola(self, F):
        """dPsi/dF, from the laws' hand-written stresses (tests check them against the energy)."""
        return sum(law.first_piola(F) for law in self.laws())

    def active_first_piola(self, F, activations):
        """The active part of dPsi/dF with ``activations`` (one per slot) in place of the slots'
        own: with an activation direction, the derivative of the stress along it (Psi is linear
        in the activations)."""
        return sum(forms.ActiveFiber(slot.fiber, slot.weight, a).first_piola(F)
                   for slot, a in zip(self.slots, activations))
