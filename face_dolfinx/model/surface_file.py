"""Closed triangle surfaces in files: the rigid contact objects (``face_dolfinx.physics.rigid_mesh``)
and the teeth of a model folder (docs/model_format.md) are read and checked here.

A surface must be closed and consistently oriented (every edge shared by exactly two triangles
that run it in opposite directions); it is returned with outward normals. Any format meshio reads
(.obj, .stl, .ply, .off, ...) will do; the teeth of a model folder are written as PLY.
"""
from pathlib import Path

import numpy as np


def check_closed_surface(points: np.ndarray, triangles: np.ndarray, where: str) -> tuple[np.ndarray, np.ndarray]:
    """Points and triangles of a closed, consistently oriented triangle surface with outward
    normals: coincident points merged, unused points dropped, the orientation flipped if it
    encloses a negative volume. ValueError naming ``where`` and the problem otherwise."""
    points = np.asarray(points, dtype=float)
    triangles = np.asarray(triangles)
    if points.ndim != 2 or points.shape[1] != 3 or not np.isfinite(points).all():
        raise ValueError(f"{where}: the points must be finite 3D coordinates")
    if triangles.ndim != 2 or triangles.shape[1] != 3 or len(triangles) < 4:
        raise ValueError(f"{where}: not a closed triangle surface ({len(triangles)} triangles; a closed surface has at least 4)")
    if triangles.min() < 0 or triangles.max() >= len(points):
        raise ValueError(f"{where}: triangles refer to points that do not exist")
    unique, inverse = np.unique(points, axis=0, return_inverse=True)   # an STL file repeats its vertices
    triangles = inverse.reshape(-1)[triangles]
    used, triangles = np.unique(triangles, return_inverse=True)
    points, triangles = unique[used], triangles.reshape(-1, 3)
    corners = points[triangles]
    double_area = np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1)
    scale = np.ptp(points, axis=0).max()
    degenerate = np.flatnonzero(double_area <= 1e-12 * scale * scale)
    if degenerate.size:
        raise ValueError(f"{where}: {degenerate.size} triangles have no area (the first: triangle {degenerate[0]})")
    directed = np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]])
    undirected, counts = np.unique(np.sort(directed, axis=1), axis=0, return_counts=True)
    open_edges = undirected[counts != 2]
    if open_edges.size:
        kind = "open" if (counts == 1).any() else "shared by more than two triangles"
        raise ValueError(f"{where}: not a closed surface: {len(open_edges)} edges are {kind}, e.g. the edge from "
                         f"{points[open_edges[0, 0]].round(3).tolist()} to {points[open_edges[0, 1]].round(3).tolist()} "
                         "(every edge must be shared by exactly two triangles)")
    if len(np.unique(directed, axis=0)) != len(directed):
        raise ValueError(f"{where}: the triangles are not consistently oriented (an edge is run the same way by both "
                         "of its triangles): orient every triangle the same way round")
    volume = np.einsum("ij,ij->i", corners[:, 0], np.cross(corners[:, 1], corners[:, 2])).sum() / 6.0
    if volume < 0.0:
        triangles = triangles[:, ::-1].copy()
    return points, triangles


def read_triangle_surface(path) -> tuple[np.ndarray, np.ndarray]:
    """Points and triangles of a triangle surface file (.obj, .stl, .ply, .off, any format meshio
    reads), checked by ``check_closed_surface``; ValueError naming the file otherwise."""
    import meshio
    path = Path(path)
    try:
        mesh = meshio.read(path)
    except Exception as error:  # meshio raises many kinds for a file it cannot read
        raise ValueError(f"{path}: cannot read a triangle surface ({type(error).__name__}: {error})") from None
    kinds = {block.type for block in mesh.cells if len(block.data)}
    if kinds != {"triangle"}:
        raise ValueError(f"{path}: not a triangle surface (it holds {', '.join(sorted(kinds)) or 'no'} cells; "
                         "give a closed surface of triangles)")
    triangles = np.concatenate([block.data for block in mesh.cells if block.type == "triangle"])
    return check_closed_surface(mesh.points[:, :3] if mesh.points.shape[1] >= 3 else mesh.points, triangles, str(path))


def write_triangle_surface(path, points: np.ndarray, triangles: np.ndarray) -> None:
    """A triangle surface file; its format from the suffix (meshio)."""
    import meshio
    meshio.write(Path(path), meshio.Mesh(np.asarray(points, dtype=float), [("triangle", np.asarray(triangles, dtype=np.int32))]))
