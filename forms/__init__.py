"""Pure-UFL constitutive laws and load terms for face_dolfinx, free of solver code.

Each law is a small frozen dataclass with ``strain_energy(F)``; a problem composes them into one
strain energy and differentiates it (fenicsx-pulse style).
"""
from .flesh import LogVolumetric, MooneyRivlin
from .kinematics import deformation_gradient, fiber_stretch, invariants
from .muscle import ActiveFiber, PassiveFiber

__all__ = ["ActiveFiber", "LogVolumetric", "MooneyRivlin", "PassiveFiber",
           "deformation_gradient", "fiber_stretch", "invariants"]
