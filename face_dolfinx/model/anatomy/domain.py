"""Triangulating the mask's (theta, phi) parameter domain with gmsh.

The domain is the rectangle of [domain] minus the openings (mouth slit, eyes). Element sizes
are wanted in millimetres on the skin, but gmsh meshes the parameter plane, so the size field
divides the physical size by the local stretch of the map (theta, phi) -> skin (the geometric
mean of its singular values, mm per degree): elements come out about the same area on the skin
whether they sit on the flat forehead or on the steep side of the nose. (The largest singular
value would over-refine steep places such as the nose, whose columns of tets are the thickest,
and make them needle-shaped.)

The overall scale of the size field is calibrated to hit a requested triangle count: first from
the integral of the element density, then once more from gmsh's actual count.
"""
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from . import libm
from .description import Description, Refinement
from .openings import Opening

GRID_STEP = 0.5            # degrees: resolution of the tabulated size field
TRIANGLE_AREA = np.sqrt(3.0) / 4.0   # area of an equilateral triangle of unit edge
COUNT_TOLERANCE = 0.08     # accept gmsh's triangle count within 8 % of the request
OUTER_EDGES = ("bottom", "right", "top", "left")


@dataclass(frozen=True)
class PlanarMesh:
    points: np.ndarray          # (n, 2) (theta, phi) in degrees
    triangles: np.ndarray       # (m, 3), counter-clockwise in the (theta, phi) plane
    boundary_edges: np.ndarray  # (k, 2)
    edge_curve: np.ndarray      # (k,) index into curve_names
    curve_names: tuple[str, ...]


class SizeField:
    """Element size in degrees over the (theta, phi) plane, tabulated on a grid."""

    def __init__(self, description: Description, openings: tuple[Opening, ...], sites: np.ndarray):
        shape, settings = description.shape, description.mesh
        (t0, t1), (p0, p1) = description.theta_range, description.phi_range
        self.theta = np.arange(t0, t1 + GRID_STEP, GRID_STEP)
        self.phi = np.arange(p0, p1 + GRID_STEP, GRID_STEP)
        theta, phi = np.meshgrid(self.theta, self.phi, indexing="ij")
        skin = shape.point(theta, phi, 1.0).reshape(-1, 3)

        d_theta, d_phi = shape.tangents(theta, phi, 1.0)
        # Geometric mean of the singular values of the 3x2 Jacobian [d_theta d_phi]: the square
        # root of its area stretch, from the determinant of its Gram matrix.
        a, b, c = (d_theta * d_theta).sum(-1), (d_theta * d_phi).sum(-1), (d_phi * d_phi).sum(-1)
        stretch = libm.power(a * c - b * b, 0.25)

        def on_skin(curve_points):
            return shape.point(curve_points[:, 0], curve_points[:, 1], 1.0)

        mouth = [o for o in openings if o.name == "mouth"]
        eyes = [o for o in openings if o.name != "mouth"]
        factor = np.ones(len(skin))
        for group, refinement in ((mouth, settings.refine_mouth), (eyes, settings.refine_eyes)):
            curve = np.concatenate([on_skin(np.concatenate([o.upper, o.lower])) for o in group])
            factor = np.minimum(factor, _blend(cKDTree(curve).query(skin)[0], refinement))
        if len(sites):
            distance = cKDTree(on_skin(sites)).query(skin)[0]
            factor = np.minimum(factor, _blend(distance, settings.refine_markers))
        # Degrees per mm of requested skin size.
        self.per_mm = factor.reshape(theta.shape) / stretch
        self._table = self.per_mm.tolist()  # plain floats: the gmsh callback runs per point
        self.scale = 1.0

    def density_integral(self) -> float:
        """Integral of 1 / (triangle area) over the plane for scale 1: triangles ~ this / scale^2."""
        cell = GRID_STEP * GRID_STEP
        return float(np.sum(cell / (TRIANGLE_AREA * self.per_mm ** 2)))

    def __call__(self, dim, tag, theta, phi, z) -> float:
        """Bilinear interpolation of the table, times the current scale (gmsh size callback)."""
        u = min(max((theta - self.theta[0]) / GRID_STEP, 0.0), len(self.theta) - 1.000001)
        v = min(max((phi - self.phi[0]) / GRID_STEP, 0.0), len(self.phi) - 1.000001)
        i, j = int(u), int(v)
        u, v = u - i, v - j
        row0, row1 = self._table[i], self._table[i + 1]
        value = ((1 - u) * ((1 - v) * row0[j] + v * row0[j + 1])
                 + u * ((1 - v) * row1[j] + v * row1[j + 1]))
        return self.scale * value


def _blend(distance: np.ndarray, refinement: Refinement) -> np.ndarray:
    """Size factor: refinement.factor at distance 0, back to 1 at refinement.radius (smoothstep)."""
    x = np.clip(distance / refinement.radius, 0.0, 1.0)
    return refinement.factor + (1.0 - refinement.factor) * x * x * (3.0 - 2.0 * x)


def mesh_parameter_domain(description: Description, openings: tuple[Opening, ...],
                          sites: np.ndarray, target_triangles: int) -> PlanarMesh:
    """Triangulate the domain with about ``target_triangles`` triangles (gmsh, one thread)."""
    import gmsh  # imported here: gmsh changes the process' SIGINT handling while imported

    size = SizeField(description, openings, sites)
    size.scale = np.sqrt(size.density_integral() / target_triangles)
    gmsh.initialize()
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.option.setNumber("General.NumThreads", 1)
        gmsh.model.add("face_domain")
        curve_names = _add_geometry(gmsh, description, openings)
        gmsh.option.setNumber("Mesh.Algorithm", 6)  # frontal-Delaunay: well-shaped triangles
        for option in ("MeshSizeFromPoints", "MeshSizeFromCurvature", "MeshSizeExtendFromBoundary"):
            gmsh.option.setNumber(f"Mesh.{option}", 0)
        gmsh.model.mesh.setSizeCallback(size)
        for _ in range(3):
            gmsh.model.mesh.clear()
            gmsh.model.mesh.generate(2)
            count = len(gmsh.model.mesh.getElementsByType(2)[0])
            if abs(count / target_triangles - 1.0) < COUNT_TOLERANCE:
                break
            size.scale *= np.sqrt(count / target_triangles)
        return _extract(gmsh, curve_names)
    finally:
        gmsh.finalize()


def _add_geometry(gmsh, description: Description, openings: tuple[Opening, ...]) -> dict[int, str]:
    """The planar surface with holes; returns {curve tag: name} for the boundary curves."""
    occ = gmsh.model.occ
    (t0, t1), (p0, p1) = description.theta_range, description.phi_range
    corners = [occ.addPoint(t, p, 0.0) for t, p in ((t0, p0), (t1, p0), (t1, p1), (t0, p1))]
    outer = [occ.addLine(corners[i], corners[(i + 1) % 4]) for i in range(4)]
    names = dict(zip(outer, OUTER_EDGES))
    loops = [occ.addCurveLoop(outer)]
    for opening in openings:
        upper_points = [occ.addPoint(t, p, 0.0) for t, p in opening.upper]
        inner_lower = [occ.addPoint(t, p, 0.0) for t, p in opening.lower[1:-1]]
        lower_points = [upper_points[0], *inner_lower, upper_points[-1]]
        upper = occ.addSpline(upper_points)
        lower = occ.addSpline(lower_points[::-1])  # from the second corner back to the first
        names[upper], names[lower] = f"{opening.name}_upper", f"{opening.name}_lower"
        loops.append(occ.addCurveLoop([upper, lower]))
    occ.addPlaneSurface(loops)
    occ.synchronize()
    return names


def _extract(gmsh, curve_names: dict[int, str]) -> PlanarMesh:
    tags, coordinates, _ = gmsh.model.mesh.getNodes()
    position = np.zeros((int(tags.max()) + 1, 2))
    position[tags.astype(np.int64)] = coordinates.reshape(-1, 3)[:, :2]
    # Number only the nodes of triangles (the spline through-points are nodes of their own).
    triangle_tags = gmsh.model.mesh.getElementsByType(2)[1].astype(np.int64)
    used = np.unique(triangle_tags)
    index = np.full(len(position), -1, dtype=np.int64)
    index[used] = np.arange(len(used))
    points = position[used]
    triangles = index[triangle_tags].reshape(-1, 3)
    # gmsh orients by the surface normal; make every triangle counter-clockwise in (theta, phi).
    a, b, c = points[triangles[:, 0]], points[triangles[:, 1]], points[triangles[:, 2]]
    clockwise = np.cross(b - a, c - a) < 0
    triangles[clockwise] = triangles[clockwise][:, [0, 2, 1]]

    names = tuple(sorted(set(curve_names.values())))
    edges, labels = [], []
    for tag, name in curve_names.items():
        _, _, node_tags = gmsh.model.mesh.getElements(1, tag)
        for nodes in node_tags:
            segments = index[nodes.astype(np.int64)].reshape(-1, 2)
            edges.append(segments)
            labels.append(np.full(len(segments), names.index(name)))
    return PlanarMesh(points, triangles, np.concatenate(edges), np.concatenate(labels), names)
