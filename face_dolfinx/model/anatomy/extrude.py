"""Stacking layers of tetrahedra on the triangulated (theta, phi) domain.

Each triangle becomes a column of prisms, one per layer in t, and each prism three tetrahedra.
Neighbouring prisms must cut their shared quadrilateral face along the same diagonal, or the
mesh is not conforming. The rule that guarantees it: order the triangle's vertices by their
global index a < b < c and cut every quad face from the lower-index vertex at the bottom to the
higher-index vertex at the top (tets abcC, abBC, aABC with capitals on the upper layer).
Both prisms sharing a face see the same two indices, so they choose the same diagonal.
"""
from dataclasses import dataclass

import numpy as np

from .domain import PlanarMesh


@dataclass(frozen=True)
class LayeredMesh:
    coordinates: np.ndarray   # (n, 3) surface coordinates (theta, phi, t) of the nodes
    tets: np.ndarray          # (m, 4), positively oriented in (theta, phi, t)
    inner: np.ndarray         # (k, 3) triangles of the t = 0 surface
    inner_centres: np.ndarray  # (k, 2) their (theta, phi) centres
    outer: np.ndarray         # (k, 3) triangles of the t = 1 surface
    walls: np.ndarray         # (w, 3) triangles of the side walls (domain edges x layers)
    wall_centres: np.ndarray  # (w, 2) (theta, phi) centres of their domain edges
    wall_curve: np.ndarray    # (w,) index into PlanarMesh.curve_names


def extrude(planar: PlanarMesh, layers: int) -> LayeredMesh:
    n = len(planar.points)
    t = np.linspace(0.0, 1.0, layers + 1)
    coordinates = np.column_stack([np.tile(planar.points, (layers + 1, 1)), np.repeat(t, n)])

    a, b, c = np.sort(planar.triangles, axis=1).T
    # The three tets of the bottom layer's prisms; a vertex's copy one layer up is index + n.
    bottom_layer = [np.stack([a, b, c, c + n], -1),
                    np.stack([a, b, b + n, c + n], -1),
                    np.stack([a, a + n, b + n, c + n], -1)]
    offsets = n * np.arange(layers)[:, None]
    tets = np.concatenate([(prism[None] + offsets[..., None]).reshape(-1, 4) for prism in bottom_layer])
    tets = _orient_positive(tets, coordinates)

    centres = planar.points[planar.triangles].mean(axis=1)
    edges = np.sort(planar.boundary_edges, axis=1)
    low_bottom, high_bottom = edges[:, 0] + offsets, edges[:, 1] + offsets  # (layers, k)
    walls = np.concatenate([np.stack([low_bottom, high_bottom, high_bottom + n], -1),
                            np.stack([low_bottom, low_bottom + n, high_bottom + n], -1)]).reshape(-1, 3)
    edge_centres = planar.points[edges].mean(axis=1)
    repeat = 2 * layers  # two triangles per edge and layer, in the order built above
    return LayeredMesh(coordinates=coordinates, tets=tets,
                       inner=planar.triangles.copy(), inner_centres=centres,
                       outer=planar.triangles + layers * n,
                       walls=walls, wall_centres=np.tile(edge_centres, (repeat, 1)),
                       wall_curve=np.tile(planar.edge_curve, repeat))


def _orient_positive(tets: np.ndarray, coordinates: np.ndarray) -> np.ndarray:
    """Swap two vertices of the tets that are negatively oriented in (theta, phi, t).

    The prisms are straight in these coordinates, so no tet is degenerate there and the sign is
    purely a matter of vertex order; the physical map preserves orientation (see shape.py).
    """
    p = coordinates[tets]
    volume = np.einsum("ij,ij->i", np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), p[:, 3] - p[:, 0])
    flipped = tets.copy()
    flipped[volume < 0] = flipped[volume < 0][:, [0, 1, 3, 2]]
    return flipped
