"""Pure-UFL constitutive laws and load terms for face_dolfinx, free of solver code.

Each law is a small frozen dataclass with ``strain_energy(F)``. The face's laws (flesh, muscle)
also give ``first_piola(F)``, dPsi/dF written out by hand: ``face_dolfinx.physics.material``
composes them into one model, whose residual is built from these stresses, so the tangent is one
automatic derivative of the residual and the energy serves reports and checks (tests check each
stress against its energy). The verification laws (guccione, incompressible) give the energy
only; their problem differentiates it automatically. ``FollowerPressure`` (loads) is the
intraoral pressure of the face and the cavity pressure of the verification problems. ``Inertia``
and ``ViscousDamping`` (inertia) are the terms time integration adds (their units there).
"""
from .flesh import LogVolumetric, MooneyRivlin
from .inertia import Inertia, ViscousDamping
from .kinematics import deformation_gradient, fiber_stretch, invariants
from .loads import FollowerPressure
from .muscle import ActiveFiber, PassiveFiber

__all__ = ["ActiveFiber", "FollowerPressure", "Inertia", "LogVolumetric", "MooneyRivlin", "PassiveFiber",
           "ViscousDamping", "deformation_gradient", "fiber_stretch", "invariants"]
