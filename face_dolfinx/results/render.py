"""Offscreen PNG pictures of the skin surface (matplotlib, Agg backend).

mplot3d's Poly3DCollection re-sorts and re-projects its polygons in Python on every draw and
becomes slow beyond ~10K triangles. A fixed orthographic camera needs none of that: we project
once, shade each triangle, sort back to front (painter's algorithm) and draw one flat 2D
PolyCollection. A 50K triangle skin renders in about a second.

Shading: a Lambert light from the upper left on normals smoothed across the mesh (but not across
sharp creases), times a facing term (surfaces seen at a grazing angle darken). Lighting is
two-sided; smoothing needs consistently oriented triangles (``FaceModel.skin_surface`` orients
them outwards). The walls of openings are shaded as the cavities they are, so the mouth slit and
the eye fissures read dark: a wall is the smooth patch (bounded by creases) that touches a hole
of the surface, i.e. a boundary loop other than the longest one (the outer rim).
Markers hidden behind the surface (e.g. the far cheek in a three-quarter view) are not drawn.
Rigid objects touching the face (a sphere pressed into the cheek, a mesh from a file) are drawn
as surfaces of their own colour, sorted back to front together with the skin's triangles.
"""
import math
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402  (after choosing the backend)
import numpy as np  # noqa: E402
import scipy.sparse as sp  # noqa: E402
from matplotlib.collections import PolyCollection  # noqa: E402
from scipy.sparse.csgraph import connected_components  # noqa: E402

# Camera directions as (azimuth, elevation) in degrees: azimuth turns the camera from straight
# ahead (+z) towards the subject's left (+x), elevation raises it.
VIEWS = {"front": (0.0, 0.0), "three_quarter": (35.0, 10.0), "side": (90.0, 0.0)}
SKIN_COLOUR = np.array([0.93, 0.76, 0.65])
OBJECT_COLOUR = np.array([0.55, 0.68, 0.85])  # rigid objects: a cool grey-blue, apart from any skin tone
LIGHT = np.array([-0.35, 0.6, 1.0])  # in camera coordinates: from the upper left, behind the viewer
AMBIENT = 0.2
FACING_POWER = 0.4   # brightness *= |normal . view| ** FACING_POWER
CREASE_ANGLE = 70.0  # degrees: sharper edges stay sharp in the shading
WALL_ANGLE = 40.0    # degrees: a fold this sharp bounds the wall of an opening
CAVITY_SHADE = 0.3   # brightness factor inside openings
LARGEST_WALL = 0.2   # a "wall" covering more of the surface than this is no wall


def camera_rotation(view: str) -> np.ndarray:
    """Rotation taking model coordinates to camera coordinates (x right, y up, z to the viewer)."""
    if view not in VIEWS:
        raise ValueError(f"unknown view {view!r}; choose one of {', '.join(VIEWS)}")
    azimuth, elevation = np.radians(VIEWS[view])
    ca, sa, ce, se = np.cos(azimuth), np.sin(azimuth), np.cos(elevation), np.sin(elevation)
    turn = np.array([[ca, 0.0, -sa], [0.0, 1.0, 0.0], [sa, 0.0, ca]])   # about y
    tilt = np.array([[1.0, 0.0, 0.0], [0.0, ce, -se], [0.0, se, ce]])   # about x
    return tilt @ turn


def render_skin(points, triangles, path, scalars=None, markers=None, other_markers=None,
                title=None, view="front", *, cmap="viridis", size=(5.0, 6.0), dpi=150, objects=()) -> Path:
    """Write a shaded picture of a triangulated surface to ``path`` (PNG) and return the path.

    points (n, 3), triangles (m, 3): the surface (e.g. ``FaceModel.skin_surface()``).
    scalars: optional values per point (n,) or per triangle (m,), shown with ``cmap``.
    markers / other_markers: optional (k, 3) points (or {name: point} dicts) drawn red / green,
    e.g. captured and simulated marker positions; rows with NaN (capture gaps) are skipped.
    view: "front", "three_quarter" or "side".
    objects: surfaces (points (k, 3), triangles (l, 3)) of rigid objects at their poses, in the
    skin's coordinates, drawn in OBJECT_COLOUR (e.g. a contact sphere's ``surface()`` moved by
    its pose).
    """
    figure = draw_skin(points, triangles, scalars, markers, other_markers, title, view, cmap=cmap,
                       size=size, dpi=dpi, objects=objects)
    path = Path(path)
    figure.savefig(path, facecolor="white")
    plt.close(figure)
    return path


def draw_skin(points, triangles, scalars=None, markers=None, other_markers=None, title=None,
              view="front", *, cmap="viridis", size=(5.0, 6.0), dpi=150, box=None, objects=()):
    """The figure ``render_skin`` saves (the caller closes it). ``box`` ((x0, x1), (y0, y1)) in
    the view's camera coordinates fixes what is shown, e.g. the same for every frame of a video;
    by default the drawn skin fills the picture (objects beyond it are cut off)."""
    points = np.asarray(points, dtype=float)
    triangles = np.asarray(triangles, dtype=np.int64)
    rotation = camera_rotation(view)
    corners, keep, flat, brightness = _lit_triangles(points, triangles, rotation)
    triangles = triangles[keep]
    brightness[_opening_walls(triangles, flat)] *= CAVITY_SHADE

    if scalars is None:
        base = np.tile(SKIN_COLOUR, (len(triangles), 1))
    else:
        values = np.asarray(scalars, dtype=float)
        per_triangle = values[triangles].mean(axis=1) if len(values) == len(points) else values[keep]
        low, high = np.nanmin(per_triangle), np.nanmax(per_triangle)
        base = plt.get_cmap(cmap)((per_triangle - low) / (high - low if high > low else 1.0))[:, :3]
    colours = np.clip(base * brightness[:, None], 0.0, 1.0)
    skin_corners = corners
    for object_points, object_triangles in objects:
        object_corners, _, _, object_brightness = _lit_triangles(object_points, object_triangles, rotation)
        corners = np.concatenate([corners, object_corners])
        colours = np.concatenate([colours, np.clip(OBJECT_COLOUR * object_brightness[:, None], 0.0, 1.0)])

    order = np.argsort(corners[:, :, 2].mean(axis=1))             # far first
    figure, axes = plt.subplots(figsize=size, dpi=dpi)
    axes.add_collection(PolyCollection(corners[order, :, :2], facecolors=colours[order],
                                       edgecolors=colours[order], linewidths=0.15,
                                       antialiaseds=False))
    # The green set is drawn smaller, on top: where the two nearly coincide (a good fit) the red
    # one still shows as a ring around it.
    for marker_set, colour, area in ((markers, "red", 16), (other_markers, "limegreen", 6)):
        if marker_set is None:
            continue
        xyz = np.asarray(list(marker_set.values()) if isinstance(marker_set, dict) else marker_set,
                         dtype=float).reshape(-1, 3) @ rotation.T
        xyz = xyz[np.all(np.isfinite(xyz), axis=1)]
        xyz = xyz[_visible(xyz, skin_corners)]
        axes.scatter(xyz[:, 0], xyz[:, 1], s=area, c=colour, edgecolors="black", linewidths=0.3,
                     zorder=3)
    if box is None:
        drawn = skin_corners[:, :, :2].reshape(-1, 2)  # frame the drawn skin, not unused points
        box = view_box(drawn)
    axes.set_xlim(*box[0])
    axes.set_ylim(*box[1])
    axes.set_aspect("equal")
    axes.axis("off")
    if title:
        axes.set_title(title, fontsize=10)
    figure.tight_layout()
    return figure


def marker_caption(rms_error: float) -> str:
    """The caption's marker line: the error to the capture, or, for a simulation without one,
    that only the simulated markers are drawn."""
    if math.isfinite(rms_error):
        return f"marker RMS {rms_error:.2f} mm\nred: captured, green: simulated"
    return "simulated markers green (no capture)"


def view_box(camera_xy: np.ndarray, margin: float = 0.04) -> tuple[tuple[float, float], tuple[float, float]]:
    """((x0, x1), (y0, y1)) around camera-plane points (k, 2), with a margin of ``margin`` times the
    larger extent."""
    low, high = camera_xy.min(axis=0), camera_xy.max(axis=0)
    pad = margin * (high - low).max()
    return (low[0] - pad, high[0] + pad), (low[1] - pad, high[1] + pad)


def _lit_triangles(points, triangles, rotation: np.ndarray):
    """A surface in camera space, lit: the corners (l, 3, 3) of its triangles of nonzero area,
    which ones those are (a mask of ``triangles``), their unit normals and their brightness."""
    camera = np.asarray(points, dtype=float) @ rotation.T
    triangles = np.asarray(triangles, dtype=np.int64)
    corners = camera[triangles]
    normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    lengths = np.linalg.norm(normals, axis=1)
    keep = lengths > 0
    smooth = _smoothed_normals(triangles[keep], normals[keep], len(camera))
    light = LIGHT / np.linalg.norm(LIGHT)
    brightness = ((AMBIENT + (1.0 - AMBIENT) * np.abs(smooth @ light))
                  * np.abs(smooth[:, 2]) ** FACING_POWER)
    return corners[keep], keep, normals[keep] / lengths[keep, None], brightness


def _smoothed_normals(triangles: np.ndarray, area_normals: np.ndarray, num_points: int):
    """Per-triangle normals averaged over the triangle's corners, each corner taking the
    area-weighted normal of the triangles around its vertex. Flat shading of the raw normals
    makes irregular meshes look crumpled. Vertices on a crease (some triangle around them turned
    more than CREASE_ANGLE / 2 from their mean normal: the lips' edge at the mouth slit, the
    eyelid margins) are not smoothed."""
    flat = area_normals / np.linalg.norm(area_normals, axis=1, keepdims=True)
    corners = triangles.ravel()

    def vertex_mean(normals):
        summed = np.column_stack([np.bincount(corners, np.repeat(normals[:, k], 3), num_points)
                                  for k in range(3)])
        return summed / np.maximum(np.linalg.norm(summed, axis=1, keepdims=True), np.finfo(float).tiny)

    agreement = np.ones(num_points)
    np.minimum.at(agreement, corners, np.einsum("md,mcd->mc", flat, vertex_mean(flat)[triangles]).ravel())
    on_crease = agreement < np.cos(np.radians(CREASE_ANGLE / 2))
    corner = vertex_mean(area_normals)[triangles]                 # (m, 3, 3)
    creased = on_crease[triangles]
    corner[creased] = np.repeat(flat[:, None], 3, axis=1)[creased]
    smooth = corner.sum(axis=1)
    return smooth / np.linalg.norm(smooth, axis=1, keepdims=True)


def _opening_walls(triangles: np.ndarray, flat_normals: np.ndarray) -> np.ndarray:
    """Which triangles line an opening of the surface (mouth slit, eye fissures).

    The surface's boundary edges form loops; the longest is the outer rim, the others are holes.
    The triangles reachable from a hole's edge without crossing a fold sharper than WALL_ANGLE are
    its wall. Should a hole's wall leak onto the open skin (no fold), it would be huge: walls
    larger than LARGEST_WALL of the surface are dropped.
    """
    count = len(triangles)
    edges = np.sort(triangles[:, [[0, 1], [1, 2], [2, 0]]].reshape(-1, 2), axis=1)
    owner = np.repeat(np.arange(count), 3)
    _, edge_id, uses = np.unique(edges, axis=0, return_inverse=True, return_counts=True)
    edge_id = edge_id.reshape(-1)
    on_boundary = uses[edge_id] == 1
    if not on_boundary.any():
        return np.zeros(count, dtype=bool)
    # Boundary loops: connected components of the boundary edges' vertices.
    rim = edges[on_boundary]
    num_points = triangles.max() + 1
    _, loop_of_vertex = connected_components(
        sp.coo_matrix((np.ones(len(rim)), (rim[:, 0], rim[:, 1])), shape=(num_points, num_points)),
        directed=False)
    loop = loop_of_vertex[rim[:, 0]]
    outer = np.argmax(np.bincount(loop))
    seeds = np.unique(owner[on_boundary][loop != outer])
    # Patches: triangles joined across their shared edges where the surface does not fold.
    order = np.argsort(edge_id, kind="stable")
    shared = np.flatnonzero(uses[edge_id[order]] == 2)[::2]
    first, second = owner[order][shared], owner[order][shared + 1]
    smooth = np.abs(np.einsum("ij,ij->i", flat_normals[first], flat_normals[second])) > np.cos(np.radians(WALL_ANGLE))
    _, patch = connected_components(
        sp.coo_matrix((np.ones(smooth.sum()), (first[smooth], second[smooth])), shape=(count, count)),
        directed=False)
    sizes = np.bincount(patch)
    walls = np.unique(patch[seeds])
    walls = walls[sizes[walls] <= LARGEST_WALL * count]
    return np.isin(patch, walls)


def _visible(points: np.ndarray, corners: np.ndarray, tolerance: float = 2.0) -> np.ndarray:
    """Points (camera coordinates) not hidden behind a triangle (corners (m, 3, 3)) by more than
    ``tolerance`` mm, so that points on the surface stay visible, and so do captured markers,
    which lie off the skin by their noise (0.5 mm and more); the far cheek is tens of mm behind."""
    a, b, c = corners[:, 0], corners[:, 1], corners[:, 2]
    low, high = corners[:, :, :2].min(axis=1), corners[:, :, :2].max(axis=1)
    e1, e2 = (b - a)[:, :2], (c - a)[:, :2]
    determinant = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
    visible = np.ones(len(points), dtype=bool)
    for i, p in enumerate(points):
        near = np.flatnonzero(np.all(low <= p[:2], axis=1) & np.all(high >= p[:2], axis=1)
                              & (determinant != 0))
        d = p[:2] - a[near, :2]
        s = (d[:, 0] * e2[near, 1] - d[:, 1] * e2[near, 0]) / determinant[near]
        t = (e1[near, 0] * d[:, 1] - e1[near, 1] * d[:, 0]) / determinant[near]
        inside = (s >= 0) & (t >= 0) & (s + t <= 1)
        depth = (a[near, 2] + s * (b[near, 2] - a[near, 2]) + t * (c[near, 2] - a[near, 2]))[inside]
        visible[i] = not np.any(depth > p[2] + tolerance)
    return visible
