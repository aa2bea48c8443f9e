"""Embedding the muscles in the flesh mesh: a volume fraction and a fiber direction per tet.

As in sifakis2005 section 3, the muscles are bodies of their own, not parts of the mesh. Each is
a geometric region (a tapered tube along a path, a sheet over a surface polygon between two
depths, or an elliptic band around an opening). A tet's fraction of a muscle is the share of a
fixed set of sample points of the tet that lie inside the region (every point stands for the
same volume); its fiber is the muscle direction at the tet's centroid: the path tangent for a
tube, the sheet's direction, the tangent of the concentric ellipses for a sphincter.

Only tets near a muscle are sampled (a cheap centroid/bounding test first), which keeps the
whole embedding at a few seconds for 400K tets.
"""
import numpy as np
from matplotlib.path import Path as Polygon

from .description import DescriptionError, MuscleSpec
from .shape import FaceShape
from face_dolfinx.model.folder import Muscle

SAMPLES_PER_TET = 27
PATH_SEGMENTS_PER_PIECE = 8   # a linear muscle's path is refined on the curved surface


def tet_sample_points(count: int = SAMPLES_PER_TET) -> np.ndarray:
    """(count, 4) barycentric coordinates spread uniformly over a tet (deterministic).

    Halton points fill the unit cube evenly; the gaps between the sorted coordinates of a
    uniform point of the cube are uniform barycentric coordinates of the tet.
    """
    cube = np.column_stack([_halton(count, base) for base in (2, 3, 5)])
    s = np.sort(cube, axis=1)
    return np.column_stack([s[:, 0], s[:, 1] - s[:, 0], s[:, 2] - s[:, 1], 1.0 - s[:, 2]])


def _halton(count: int, base: int) -> np.ndarray:
    values = np.zeros(count)
    for i in range(count):
        f, n, x = 1.0, i + 1, 0.0
        while n:
            f /= base
            x += f * (n % base)
            n //= base
        values[i] = x
    return values


class MuscleEmbedder:
    """Holds the mesh once and embeds muscle after muscle."""

    def __init__(self, shape: FaceShape, coordinates: np.ndarray, points: np.ndarray, tets: np.ndarray):
        self.shape = shape
        self.tets = tets
        self.coordinates = coordinates            # (theta, phi, t) per node
        self.points = points                      # physical per node
        corners = points[tets]
        self.centroids = corners.mean(axis=1)
        self.reach = np.linalg.norm(corners - self.centroids[:, None], axis=2).max(axis=1)
        surface = coordinates[tets]
        self.coord_low, self.coord_high = surface.min(axis=1), surface.max(axis=1)
        self.coord_centroids = surface.mean(axis=1)
        self.barycentric = tet_sample_points()

    def embed(self, spec: MuscleSpec) -> list[Muscle]:
        """The muscle (left side as described) and, if mirrored, its right-side image."""
        sides = [("left", 1.0), ("right", -1.0)] if spec.mirror else [(None, 1.0)]
        muscles = []
        for side, sign in sides:
            suffix = f"_{side}" if side else ""
            if spec.kind == "linear":
                muscles.append(self._tube(spec, spec.name + suffix, sign))
            elif spec.kind == "sheet":
                muscles.append(self._sheet(spec, spec.name + suffix, sign))
            else:
                muscles.extend(self._sphincter(spec, spec.name + suffix, sign))
        empty = [m.name for m in muscles if len(m.cells) == 0]
        if empty:
            raise DescriptionError(f"muscles {empty} contain no sample point: the mesh is too coarse "
                                   "or the muscle lies outside the flesh")
        return muscles

    # -- sampling ---------------------------------------------------------------------------
    def _samples(self, cells: np.ndarray, values: np.ndarray) -> np.ndarray:
        """Values (per node, (n, d)) at the sample points of ``cells``: (cells, samples, d)."""
        return np.einsum("sv,cvd->csd", self.barycentric, values[self.tets[cells]])

    def _result(self, name, kind, cells, inside, fiber, geometry, spec) -> Muscle:
        fraction = inside.mean(axis=1)
        keep = fraction > 0
        return Muscle(name, kind, spec.peak_stress, cells[keep], fraction[keep], fiber[keep], geometry)

    def _surface_direction(self, coords: np.ndarray, direction: np.ndarray) -> np.ndarray:
        """Unit physical directions of (d theta, d phi) per point at surface coordinates."""
        d_theta, d_phi = self.shape.tangents(coords[:, 0], coords[:, 1], coords[:, 2])
        vector = direction[:, :1] * d_theta + direction[:, 1:2] * d_phi
        return vector / np.linalg.norm(vector, axis=1, keepdims=True)

    # -- the three kinds --------------------------------------------------------------------
    def _tube(self, spec: MuscleSpec, name: str, sign: float) -> Muscle:
        path = spec.path * (sign, 1.0, 1.0)
        # Refine the path in surface coordinates so the tube follows the face's curvature.
        s = np.linspace(0.0, 1.0, PATH_SEGMENTS_PER_PIECE, endpoint=False)
        fine = np.concatenate([a + s[:, None] * (b - a) for a, b in zip(path[:-1], path[1:])] + [path[-1:]])
        knots = self.shape.point(fine[:, 0], fine[:, 1], fine[:, 2])
        length = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(knots, axis=0), axis=1))])
        radius_at = np.interp(length / length[-1], [0.0, 1.0], spec.radius)

        # Candidates: tets that can reach the tube; a bounding box first, the exact test after.
        margin = radius_at.max() + self.reach.max()
        boxed = np.flatnonzero(np.all((self.centroids >= knots.min(axis=0) - margin)
                                      & (self.centroids <= knots.max(axis=0) + margin), axis=1))
        distance, segment = _distance_to_tube(self.centroids[boxed], knots, radius_at)
        near = distance < self.reach[boxed]
        cells, segment = boxed[near], segment[near]
        samples = self._samples(cells, self.points)
        inside_distance, _ = _distance_to_tube(samples.reshape(-1, 3), knots, radius_at)
        inside = (inside_distance <= 0).reshape(len(cells), -1)
        tangents = np.diff(knots, axis=0)
        fiber = tangents[segment] / np.linalg.norm(tangents[segment], axis=1, keepdims=True)
        geometry = {"origin": knots[0], "insertion": knots[-1]}
        return self._result(name, "linear", cells, inside, fiber, geometry, spec)

    def _sheet(self, spec: MuscleSpec, name: str, sign: float) -> Muscle:
        polygon = spec.polygon * (sign, 1.0)
        region = Polygon(polygon)
        low, high = polygon.min(axis=0), polygon.max(axis=0)
        cells = np.flatnonzero(np.all(self.coord_high[:, :2] >= low, axis=1)
                               & np.all(self.coord_low[:, :2] <= high, axis=1)
                               & (self.coord_high[:, 2] >= spec.depth[0])
                               & (self.coord_low[:, 2] <= spec.depth[1]))
        samples = self._samples(cells, self.coordinates).reshape(-1, 3)
        inside = (region.contains_points(samples[:, :2])
                  & (samples[:, 2] >= spec.depth[0]) & (samples[:, 2] <= spec.depth[1]))
        direction = np.array(spec.direction) * (sign, 1.0)
        fiber = self._surface_direction(self.coord_centroids[cells], np.tile(direction, (len(cells), 1)))
        geometry = self._sheet_ends(region, polygon, direction, np.mean(spec.depth))
        return self._result(name, "linear", cells, inside.reshape(len(cells), -1), fiber, geometry, spec)

    def _sheet_ends(self, region: Polygon, polygon, direction, depth) -> dict:
        """Origin and insertion of a sheet: where the line through its centre along the fiber
        direction leaves the polygon, behind and ahead."""
        centre = polygon.mean(axis=0)
        step = direction / np.linalg.norm(direction)
        reach = np.linspace(0.0, np.ptp(polygon, axis=0).max(), 400)
        ends = {}
        for key, sense in (("origin", -1.0), ("insertion", 1.0)):
            line = centre + sense * reach[:, None] * step
            last = line[region.contains_points(line)][-1]
            ends[key] = self.shape.point(last[0], last[1], depth)
        return ends

    def _sphincter(self, spec: MuscleSpec, name: str, sign: float) -> list[Muscle]:
        theta0, phi0 = spec.center[0] * sign, spec.center[1]
        a, b = spec.semi_axes
        cells = np.flatnonzero((self.coord_high[:, 0] >= theta0 - a) & (self.coord_low[:, 0] <= theta0 + a)
                               & (self.coord_high[:, 1] >= phi0 - b) & (self.coord_low[:, 1] <= phi0 + b)
                               & (self.coord_high[:, 2] >= spec.depth[0])
                               & (self.coord_low[:, 2] <= spec.depth[1]))
        samples = self._samples(cells, self.coordinates)
        d_theta, d_phi = samples[..., 0] - theta0, samples[..., 1] - phi0
        in_band = (((d_theta / a) ** 2 + (d_phi / b) ** 2 <= 1.0)
                   & (samples[..., 2] >= spec.depth[0]) & (samples[..., 2] <= spec.depth[1]))
        centre = self.coord_centroids[cells]
        c_theta, c_phi = centre[:, 0] - theta0, centre[:, 1] - phi0
        # Tangent of the ellipse (theta/a)^2 + (phi/b)^2 = const through the centroid.
        fiber = self._surface_direction(centre, np.column_stack([-c_phi * a / b, c_theta * b / a]))
        mid_depth = np.mean(spec.depth)
        d_th, d_ph = self.shape.tangents(theta0, phi0, mid_depth)
        axis = np.cross(d_th, d_ph)
        geometry = {"center": self.shape.point(theta0, phi0, mid_depth), "axis": axis / np.linalg.norm(axis)}
        halves = {"upper": d_phi >= 0, "lower": d_phi < 0, "left": d_theta >= 0, "right": d_theta < 0}
        labels = ["upper", "lower"] if {"upper", "lower"} <= set(spec.split) else [""]
        if {"left", "right"} <= set(spec.split):
            labels = [f"{label}_{side}" if label else side for label in labels for side in ("left", "right")]
        parts = []
        for label in labels:
            mask = in_band.copy()
            for half in filter(None, label.split("_")):
                mask &= halves[half]
            parts.append(self._result(f"{name}_{label}" if label else name, "sphincter", cells, mask,
                                      fiber, geometry, spec))
        return parts


def _distance_to_tube(points: np.ndarray, knots: np.ndarray, radius: np.ndarray):
    """Signed distance (negative inside) from points to a tapered tube along the polyline
    ``knots`` with radius ``radius`` at the knots, and the index of the closest segment."""
    start, vector = knots[:-1], np.diff(knots, axis=0)
    best = np.full(len(points), np.inf)
    segment = np.zeros(len(points), dtype=np.int64)
    for j in range(len(vector)):
        offset = points - start[j]
        s = np.clip(offset @ vector[j] / (vector[j] @ vector[j]), 0.0, 1.0)
        away = offset - s[:, None] * vector[j]
        gap = np.sqrt(np.einsum("ij,ij->i", away, away)) - (radius[j] + s * (radius[j + 1] - radius[j]))
        closer = gap < best
        best[closer], segment[closer] = gap[closer], j
    return best, segment
