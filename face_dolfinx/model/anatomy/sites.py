"""Marker sites and landmarks: named points exactly on the triangulated skin.

A site is given by surface angles (theta, phi). It is placed by finding the triangle of the
meshed (theta, phi) domain that contains it and interpolating that triangle's skin nodes
linearly, so the point lies on the skin triangulation itself (distance 0 up to round-off), not
merely on the smooth surface the triangulation approximates.
"""
import numpy as np
from matplotlib.tri import Triangulation

from .description import DescriptionError, SiteGroup
from .domain import PlanarMesh
from .openings import Opening, anchor_point


def site_angles(groups: tuple[SiteGroup, ...], openings: tuple[Opening, ...]) -> dict[str, np.ndarray]:
    """{name: (theta, phi)} in file order; mirrored sites have theta negated."""
    angles = {}
    for group in groups:
        for name, location, mirrored in group.named_sites():
            point = anchor_point(location, openings) if isinstance(location, str) else np.array(location)
            angles[name] = point * ((-1.0 if mirrored else 1.0), 1.0)
    return angles


def place_on_skin(angles: dict[str, np.ndarray], planar: PlanarMesh, skin_nodes: np.ndarray) -> dict[str, np.ndarray]:
    """{name: point on the skin triangulation}; skin_nodes (n, 3) are the t = 1 copies of the
    planar mesh's nodes."""
    if not angles:
        return {}
    triangulation = Triangulation(planar.points[:, 0], planar.points[:, 1], planar.triangles)
    where = np.array(list(angles.values()))
    found = triangulation.get_trifinder()(where[:, 0], where[:, 1])
    if np.any(found < 0):
        missing = [name for name, index in zip(angles, found) if index < 0]
        raise DescriptionError(f"sites {missing} are outside the mask or inside an opening")
    corners = planar.points[planar.triangles[found]]             # (k, 3, 2)
    # Barycentric coordinates of each site in its triangle.
    matrix = np.stack([corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]], axis=2)
    l1, l2 = np.linalg.solve(matrix, (where - corners[:, 0])[..., None])[..., 0].T
    weights = np.column_stack([1.0 - l1 - l2, l1, l2])
    points = np.einsum("kv,kvd->kd", weights, skin_nodes[planar.triangles[found]])
    return dict(zip(angles, points))
