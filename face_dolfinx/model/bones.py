"""Bone frames: affine maps for the cranium and the mandible, and the TMJ articulation.

Sifakis et al. 2005 section 8 describe each bone frame by a general affine map (M, t), rigid only
through a penalty; the jaw frame is relative to the cranium. The exact-mode parameterisation of
the jaw is its three TMJ degrees of freedom: the two condyle slides along tracks parallel to v and
the opening rotation about the condyle axis.
"""
import math
from dataclasses import dataclass, field

import numpy as np
import scipy.linalg


@dataclass(frozen=True)
class AffineMap:
    """x -> M x + t."""

    matrix: np.ndarray = field(default_factory=lambda: np.eye(3))
    translation: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def __post_init__(self):
        object.__setattr__(self, "matrix", np.asarray(self.matrix, dtype=float).reshape(3, 3))
        object.__setattr__(self, "translation", np.asarray(self.translation, dtype=float).reshape(3))

    def apply(self, points: np.ndarray) -> np.ndarray:
        return points @ self.matrix.T + self.translation

    def compose(self, inner: "AffineMap") -> "AffineMap":
        """self o inner."""
        return AffineMap(self.matrix @ inner.matrix, self.matrix @ inner.translation + self.translation)

    def inverse(self) -> "AffineMap":
        inv = np.linalg.inv(self.matrix)
        return AffineMap(inv, -inv @ self.translation)

    def interpolate(self, other: "AffineMap", t: float) -> "AffineMap":
        """Linear blend of the 12 numbers, as the paper's line search uses."""
        return AffineMap((1 - t) * self.matrix + t * other.matrix,
                         (1 - t) * self.translation + t * other.translation)

    def same_as(self, other: "AffineMap") -> bool:
        """The same 12 numbers exactly."""
        return np.array_equal(self.matrix, other.matrix) and np.array_equal(self.translation, other.translation)

    def homogeneous(self) -> np.ndarray:
        H = np.eye(4)
        H[:3, :3], H[:3, 3] = self.matrix, self.translation
        return H

    def geodesic(self, other: "AffineMap", t: float) -> "AffineMap":
        """exp(t log(other o self^-1)) o self: the motion from self to other done a fraction t of
        the way. A rotation about an axis turns by t times its angle about the same axis (a screw
        motion), so rigid frames stay rigid; the linear blend of the 12 numbers instead scales a
        frame by cos(theta/2) half way through a turn by theta. Falls back to the linear blend
        where the relative map has no real logarithm (a half turn, a reflection)."""
        if t == 0.0:
            return self
        if t == 1.0:
            return other
        relative = other.homogeneous() @ np.linalg.inv(self.homogeneous())
        log = scipy.linalg.logm(relative)
        if np.abs(np.imag(log)).max(initial=0.0) > 1e-9 or not np.all(np.isfinite(log)):
            return self.interpolate(other, t)
        H = scipy.linalg.expm(t * np.real(log)) @ self.homogeneous()
        return AffineMap(H[:3, :3], H[:3, 3])


def rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    """Rotation matrix about a unit ``axis`` by ``angle`` radians (right hand rule)."""
    a = np.asarray(axis, dtype=float) / np.linalg.norm(axis)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K


def rigid_map(rotation_matrix: np.ndarray, center: np.ndarray, displacement: np.ndarray) -> AffineMap:
    """Rotation about ``center`` followed by a translation ``displacement``."""
    c = np.asarray(center, dtype=float)
    return AffineMap(rotation_matrix, c - rotation_matrix @ c + np.asarray(displacement, dtype=float))


def tmj_upper_limits(jaw) -> np.ndarray:
    """The TMJ values at their upper bounds: opening (rad), right and left condyle slides (mm); the
    lower bounds are 0."""
    return np.array([math.asin(jaw.max_opening_sine), jaw.track_length, jaw.track_length])


def jaw_pose(jaw, opening_angle: float = 0.0, slide_right: float = 0.0,
             slide_left: float = 0.0) -> AffineMap:
    """Mandible frame (relative to the cranium) from the three TMJ degrees of freedom.

    The condyles slide by ``slide_right``/``slide_left`` (mm) along v; unequal slides turn the jaw
    about w. The jaw then opens by ``opening_angle`` (radians, positive opens the mouth: the chin
    moves along -w) about the displaced condyle axis. The result satisfies psi_1..psi_3 exactly,
    psi_4 = slide_right, psi_5 = slide_left and psi_6 = -sin(opening_angle), all exactly.
    """
    u, v, w = jaw.u, jaw.v, jaw.w
    half = 0.5 * jaw.condyle_distance
    # sin(yaw) = (slide_left - slide_right) / l puts each condyle exactly at its slide along v.
    yaw = np.arcsin(np.clip((slide_left - slide_right) / (2 * half), -1.0, 1.0))
    turn = rotation(w, -yaw)  # the left condyle forward turns u towards +v: negative about w
    axis = turn @ u
    midpoint_shift = 0.5 * (slide_right + slide_left) * v
    opening = rotation(axis, opening_angle)
    M = opening @ turn
    new_mid = jaw.midpoint + midpoint_shift
    return AffineMap(M, new_mid - M @ jaw.midpoint)


def tmj_values(jaw, frame: AffineMap) -> np.ndarray:
    """The TMJ values (opening in rad, right and left condyle slides in mm) of a mandible frame:
    the inverse of ``jaw_pose``, exact for its frames; for any other affine frame (a paper-mode
    fit's, rigid only through a penalty) the values of psi_4, psi_5 and psi_6 (``penalties.tmj``)."""
    M, t = frame.matrix, frame.translation
    half_axis = 0.5 * jaw.condyle_distance * jaw.u
    slide_right = jaw.v @ (M @ (jaw.midpoint - half_axis) + t - jaw.midpoint)
    slide_left = jaw.v @ (M @ (jaw.midpoint + half_axis) + t - jaw.midpoint)
    opening = math.asin(float(np.clip(-(jaw.w @ M @ jaw.v), -1.0, 1.0)))
    return np.array([opening, slide_right, slide_left])
