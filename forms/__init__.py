"""Pure-UFL constitutive laws and load terms for face_dolfinx, free of solver code.

Each law is a small frozen dataclass with ``strain_energy(F)``. The face's laws (flesh, muscle)
also give ``first_piola(F)``, dPsi/dF written out by hand: ``face_dolfinx.physics.material``
composes them into one model, whose residual is built from these stresses, so the tangent is one
automatic derivative of the residual and the energy serves reports and checks (tests check each
stress against its energy). The verification laws (guccione, incompressible, loads) give the
energy or traction only; their problem differentiates it automatically.
"""
from .flesh import LogVolumetric, MooneyRivlin
from .kinematics import deformation_gradient, fiber_stretch, invariants
from .muscle import ActiveFiber, PassiveFiber

__all__ = ["ActiveFiber", "LogVolumetric", "MooneyRivlin", "PassiveFiber",
           "deformation_gradient", "fiber_stretch", "invariants"]
