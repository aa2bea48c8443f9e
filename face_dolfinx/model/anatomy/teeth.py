"""The teeth of the built-in face: a rigid closed plate per jaw behind the lips.

Each plate covers a (theta, phi) window of the free inner surface (the oral vestibule). Its front
follows the inner surface of the flesh ``clearance`` mm inside it along the rays, so the lips
rest on it; its back lies ``depth`` mm further in; four side walls along the rays close it. In
the surface coordinates of shape.py (theta, phi, radius) it is a box, so its surface is a
structured grid of quads, each cut into two triangles, oriented outwards (the map from (theta,
phi, radius) to space keeps orientation, see shape.py).
"""
import numpy as np

from . import libm
from .description import DentalArch, Teeth
from .shape import FaceShape


def dental_arch(shape: FaceShape, arch: DentalArch, teeth: Teeth) -> tuple[np.ndarray, np.ndarray]:
    """Points (mm) and outward triangles of the closed plate over ``arch``'s window."""
    (theta0, theta1), (phi0, phi1) = arch.theta, arch.phi
    inner, _ = shape.radii(0.5 * (theta0 + theta1), 0.5 * (phi0 + phi1))
    along_theta = np.radians(theta1 - theta0) * float(inner) * libm.cos(np.radians(0.5 * (phi0 + phi1)))
    along_phi = np.radians(phi1 - phi0) * float(inner)
    counts = [max(2, int(np.ceil(length / teeth.spacing))) for length in (along_theta, along_phi)]
    theta, phi = np.meshgrid(np.linspace(theta0, theta1, counts[0] + 1), np.linspace(phi0, phi1, counts[1] + 1),
                             indexing="ij")
    front = shape.radii(theta, phi)[0] - teeth.clearance
    radius = np.stack([front - teeth.depth, front], axis=-1)               # (theta, phi, back/front)
    points = shape.center + radius[..., None] * shape.direction(theta, phi)[..., None, :]
    index = np.arange(points[..., 0].size).reshape(radius.shape)
    # Each face of the box as a grid whose two axes (u, v) have u x v pointing out of the box.
    faces = [index[:, :, 1], index[:, :, 0].T,              # front (+radius), back
             index[-1, :, :], index[0, :, :].T,             # theta1 (+theta), theta0
             index[:, -1, :].T, index[:, 0, :]]             # phi1 (+phi), phi0
    triangles = np.concatenate([_grid_triangles(face) for face in faces])
    return points.reshape(-1, 3), triangles


def _grid_triangles(grid: np.ndarray) -> np.ndarray:
    """Two triangles per cell of a grid of point indices, turning from its first axis to its second."""
    a, b = grid[:-1, :-1].ravel(), grid[1:, :-1].ravel()
    c, d = grid[1:, 1:].ravel(), grid[:-1, 1:].ravel()
    return np.concatenate([np.stack([a, b, c], -1), np.stack([a, c, d], -1)])
