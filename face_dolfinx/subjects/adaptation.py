"""Subject adaptation: a template face model warped onto one subject (sifakis2005 section 3).

The template (the built-in face, or any model folder) is carried onto the subject by one smooth
map of 3-space, a radial-basis-function warp (``warp.RBFWarp``): flesh nodes, and with them the
skin, the bone attachment surfaces and the muscles' cells, move by it; fiber directions by its
Jacobian; the jaw's condyles, the marker sites and the landmarks likewise. Two kinds of subject:

``adapt_to_markers``  the neutral frame of the subject's capture plus correspondences (>= 6 capture
    markers named by template landmark). The warp takes each template landmark to its marker and
    every other marker's closest template skin point to that marker, so the new skin passes
    through all of them. Which template point is "closest" depends on the warp, so the two are
    found together: warp by the landmarks, match each marker to its closest point on the warped
    skin and pull it back to the template, warp again, until the matches settle.
``adapt_to_surface``  a scan of the subject's face (triangles) plus landmark positions on it. The
    same iteration with the template's skin nodes as the points matched, to their closest points
    on the scan; matches on the scan's open border are dropped (the scan may end before the
    template's skin does, and border matches would drag the skin along the edge).

The subject is first moved rigidly (no scaling: the subject keeps its size) onto the template's
landmarks, so the new model is in the template's frame: Y up, the same origin and facing. The
result is refused (SubjectError) if the warp inverts or flattens any tetrahedron.

Everything works on plain arrays (``face_dolfinx.model.folder.ModelArrays``, read by
``read_model_arrays``); ``write_adapted_model`` writes the result.
"""
from __future__ import annotations

import csv
import json
import tomllib
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from mpi4py import MPI

from face_dolfinx.files import atomic_directory
from face_dolfinx.model import folder as model_format
from face_dolfinx.alignment.similarity import AlignmentError, Similarity, align_by_correspondences, read_pair_file, similarity_transform
from face_dolfinx.model.folder import JawGeometry, ModelArrays
from face_dolfinx.alignment.surface import SkinSurface
from .warp import RBFWarp, fiber_transform, inverted_tets


MIN_LANDMARKS = 6              # as for aligning a capture: 7 unknowns and a margin
# A subject this much smaller or larger than the template (scale of the landmarks' best
# similarity) is a unit mistake, not a face.
SUBJECT_SCALE_RANGE = (0.5, 2.0)
MAX_ITERATIONS = 10            # closest-point matching rounds
SETTLED_MM = 0.01              # matches moving less than this have settled
MAX_SURFACE_CONTROLS = 1000    # template skin nodes matched to a scan (RBF solve cost ~ n^3)
# The thin-plate spline is smooth (C1) at its control points; the biharmonic kernel r has a cone
# there, which the flat skin triangles between warped nodes cut off: on the 5K face it left the
# skin twice as far from a subject's markers (0.41 against 0.22 mm for a 3 mm cheek bump).
WARP_KERNEL = "thin_plate"
SURFACE_SUFFIXES = (".obj", ".stl", ".ply", ".off", ".vtk", ".vtu")
MM_PER_UNIT = {"mm": 1.0, "cm": 10.0, "m": 1000.0}


class SubjectError(ValueError):
    """Subject inputs that can't be used, or a warp that would break the mesh; the message says which."""


@dataclass
class Adaptation:
    """A warped model and how well it fits the subject."""

    model: ModelArrays
    warp: RBFWarp
    to_template: Similarity               # rigid: subject input frame -> template (and new model) frame
    distances: dict[str, float]           # subject point -> new skin (mm), by name
    iterations: int
    record: dict                          # what subject.json holds

    @property
    def rms(self) -> float:
        return float(np.sqrt(np.mean(np.square(list(self.distances.values())))))

    @property
    def max(self) -> float:
        return float(max(self.distances.values()))


# ---------------------------------------------------------------------------------------------
# Subject from a capture's neutral frame
# ---------------------------------------------------------------------------------------------
def adapt_to_markers(template: ModelArrays, neutral, names, correspondence: dict[str, str], *,
                     name: str) -> Adaptation:
    """The template warped so that its skin passes through every marker of the neutral frame.

    ``neutral`` (n, 3) and ``names`` (n,) are the subject's markers (every one present: each
    becomes a control point); ``correspondence`` maps capture markers to template landmarks.
    """
    neutral = np.asarray(neutral, dtype=np.float64)
    names = [str(n) for n in names]
    skin = template.skin()
    missing = [n for n, row in zip(names, neutral) if not np.all(np.isfinite(row))]
    if missing:
        raise SubjectError(f"markers missing in the neutral frame: {', '.join(missing)}; every marker shapes "
                           f"the subject, so choose a neutral frame where all are present")
    try:  # checks every name; rigid, so that the subject keeps its size
        rigid = align_by_correspondences(neutral, names, template.landmarks, correspondence, skin,
                                         allow_scale=False).transform
    except AlignmentError as error:
        raise SubjectError(str(error)) from None
    pairs = list(correspondence.items())
    row = {n: i for i, n in enumerate(names)}
    landmark_rows = [row[marker] for marker, _ in pairs]
    _check_scale(neutral[landmark_rows], np.array([template.landmarks[lm] for _, lm in pairs]), "capture")
    subject = rigid.apply(neutral)

    # Landmarks are fixed pairs; every other marker is matched to the template skin.
    fixed_template = np.array([template.landmarks[landmark] for _, landmark in pairs])
    fixed_subject = subject[landmark_rows]
    free = [i for i in range(len(names)) if i not in set(landmark_rows)]
    warp, iterations, settled = _match_and_warp(
        template, fixed_template, fixed_subject,
        match=lambda warped_skin: _pull_back(template, warped_skin, subject[free]))
    new = warp_model(template, warp, name=name)
    distances = new.skin().closest(subject)[3]
    record = dict(method="capture markers", correspondence=dict(correspondence), to_template=_similarity_json(rigid),
                  iterations=iterations, settled=settled,
                  markers={n: dict(subject=subject[i].tolist(), skin_distance_mm=float(distances[i]))
                           for i, n in enumerate(names)})
    return Adaptation(new, warp, rigid, dict(zip(names, distances.tolist())), iterations, record)


def _pull_back(template: ModelArrays, warped_skin: SkinSurface, subject_points):
    """Template skin points whose warped images are closest to ``subject_points``, and those targets."""
    triangle, barycentric, _, _ = warped_skin.closest(subject_points)
    corners = template.points[warped_skin.triangles[triangle]]
    return np.einsum("nk,nkd->nd", barycentric, corners), subject_points


# ---------------------------------------------------------------------------------------------
# Subject from a surface scan
# ---------------------------------------------------------------------------------------------
def adapt_to_surface(template: ModelArrays, scan: SurfaceScan, landmarks: dict[str, np.ndarray], *,
                     name: str) -> Adaptation:
    """The template warped so that its skin lies on a subject's face surface.

    ``landmarks`` maps template landmark names to points of the surface (its frame, mm).
    """
    unknown = [lm for lm in landmarks if lm not in template.landmarks]
    problems = []
    if unknown:
        problems.append(f"not landmarks of model {template.name}: {', '.join(unknown)} (it has: "
                        f"{', '.join(template.landmarks)})")
    known = [lm for lm in landmarks if lm in template.landmarks]
    if len(known) < MIN_LANDMARKS:
        problems.append(f"only {len(known)} usable landmarks; at least {MIN_LANDMARKS} are needed")
    if problems:
        raise SubjectError("; ".join(problems))
    subject_landmarks = np.array([landmarks[lm] for lm in known], dtype=np.float64)
    template_landmarks = np.array([template.landmarks[lm] for lm in known])
    _check_scale(subject_landmarks, template_landmarks, "surface")
    rigid = similarity_transform(subject_landmarks, template_landmarks, allow_scale=False)
    surface = SkinSurface(rigid.apply(scan.points), scan.triangles)
    border = _border_nodes(scan.triangles)
    fixed_subject = rigid.apply(subject_landmarks)
    controls = _surface_controls(template, template_landmarks)

    def within(points):
        """Closest scan points of ``points`` and which of them are inside the scan, not on its border."""
        triangle, barycentric, closest, distance = surface.closest(points)
        # Closest at a border node or on a border edge: the point is beyond where the scan ends.
        on_edge = barycentric <= 1e-9
        at_border = on_edge.any(axis=1) & np.all(np.isin(scan.triangles[triangle], border) | on_edge, axis=1)
        return closest, distance, ~at_border

    def match(warped_skin):
        closest, _, inside = within(warped_skin.points[controls])
        return template.points[controls[inside]], closest[inside]

    warp, iterations, settled = _match_and_warp(template, template_landmarks, fixed_subject, match)
    new = warp_model(template, warp, name=name)
    skin_nodes = template.skin_nodes
    _, distances, covered = within(new.points[skin_nodes])
    names = [f"skin_node_{n}" for n in skin_nodes[covered]]
    landmark_distances = np.linalg.norm(warp.apply(template_landmarks) - fixed_subject, axis=1)
    record = dict(method="surface", to_template=_similarity_json(rigid), iterations=iterations, settled=settled,
                  skin_nodes_matched=int(covered.sum()), skin_nodes=len(skin_nodes),
                  landmarks={lm: dict(subject=p.tolist(), residual_mm=float(d))
                             for lm, p, d in zip(known, fixed_subject, landmark_distances)})
    return Adaptation(new, warp, rigid, dict(zip(names, distances[covered].tolist())), iterations, record)


def _surface_controls(template: ModelArrays, landmark_points) -> np.ndarray:
    """Template skin nodes to match to the scan: evenly spread, at most MAX_SURFACE_CONTROLS, none
    on top of a landmark (two control points that close with different targets would fold the warp)."""
    nodes = template.skin_nodes
    edges = template.skin().triangles[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    spacing = np.median(np.linalg.norm(template.points[edges[:, 0]] - template.points[edges[:, 1]], axis=1))
    near = np.min(np.linalg.norm(template.points[nodes][:, None] - landmark_points[None], axis=2), axis=1)
    nodes = nodes[near > 0.5 * spacing]
    if len(nodes) <= MAX_SURFACE_CONTROLS:
        return nodes
    # Farthest-point sampling: each pick is the node farthest from all earlier picks.
    points = template.points[nodes]
    chosen = [0]
    distance = np.linalg.norm(points - points[0], axis=1)
    for _ in range(MAX_SURFACE_CONTROLS - 1):
        chosen.append(int(np.argmax(distance)))
        distance = np.minimum(distance, np.linalg.norm(points - points[chosen[-1]], axis=1))
    return nodes[np.sort(chosen)]


def _border_nodes(triangles) -> np.ndarray:
    """Nodes on edges used by one triangle only (the scan's open border)."""
    edges = np.sort(triangles[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    unique, counts = np.unique(edges, axis=0, return_counts=True)
    return np.unique(unique[counts == 1])


# ---------------------------------------------------------------------------------------------
# The warp and the warped model
# ---------------------------------------------------------------------------------------------
def _match_and_warp(template: ModelArrays, fixed_template, fixed_subject, match):
    """Alternate matching and warping until the matches settle.

    ``match(warped_skin)`` returns (template points, subject targets) for the current warp; the
    fixed pairs (landmarks) are always controls. The matches have settled when no template point
    and no target moves by SETTLED_MM; the rounds are capped at MAX_ITERATIONS, as sliding along
    the skin can settle slowly while the surface itself no longer changes. Returns the warp, the
    number of rounds and whether the matches settled.
    """
    skin_nodes = template.skin_nodes
    warp = RBFWarp.fit(fixed_template, fixed_subject, kernel=WARP_KERNEL)
    previous = None
    for iteration in range(1, MAX_ITERATIONS + 1):
        warped = np.zeros_like(template.points)
        warped[skin_nodes] = warp.apply(template.points[skin_nodes])
        pairs = np.hstack(match(template.skin(warped)))
        if previous is not None and previous.shape == pairs.shape and \
                np.max(np.linalg.norm((pairs - previous).reshape(-1, 3), axis=1), initial=0.0) < SETTLED_MM:
            return warp, iteration, True
        previous = pairs
        try:
            warp = RBFWarp.fit(np.vstack([fixed_template, pairs[:, :3]]), np.vstack([fixed_subject, pairs[:, 3:]]),
                               kernel=WARP_KERNEL)
        except ValueError as error:  # repeated template points: two subject points claim one spot
            raise SubjectError(f"two subject points map onto the same template point ({error}); are two "
                               f"markers at the same place, or a marker far off the face?") from None
    return warp, MAX_ITERATIONS, False


def warp_model(template: ModelArrays, warp: RBFWarp, *, name: str) -> ModelArrays:
    """Everything in the template carried through ``warp``; SubjectError if a tet inverts or flattens."""
    points = warp.apply(template.points)
    bad = inverted_tets(points, template.cells)
    if bad.size:
        raise SubjectError(f"the warp inverts {bad.size} of {len(template.cells)} tetrahedra (e.g. cell {bad[0]}): "
                           f"the subject points pull the template too far or cross over; check the "
                           f"correspondences and that the markers are on this face")
    _, quality = model_format.tet_volumes_and_quality(points[template.cells])
    if quality.min() < model_format.DEGENERATE_QUALITY:
        raise SubjectError(f"the warp flattens {np.sum(quality < model_format.DEGENERATE_QUALITY)} tetrahedra "
                           f"(quality {quality.min():.2g} < {model_format.DEGENERATE_QUALITY:g}, cell "
                           f"{int(np.argmin(quality))}); the subject points pull the template too far")
    centres = template.points[template.cells].mean(axis=1)
    muscles = []
    for muscle in template.muscles:
        geometry = {}
        for key, value in muscle.geometry.items():
            if key == "axis":  # a direction at the sphincter's centre, its length kept
                at = muscle.geometry.get("center", centres[muscle.cells].mean(axis=0))
                geometry[key] = np.linalg.norm(value) * fiber_transform(warp, at[None], value[None])[0]
            else:
                geometry[key] = warp.apply(value)
        fiber = fiber_transform(warp, centres[muscle.cells], muscle.fiber) if len(muscle.cells) else muscle.fiber
        muscles.append(replace(muscle, fiber=fiber, geometry=geometry))
    jaw = template.jaw
    slide = fiber_transform(warp, jaw.midpoint[None], jaw.v[None])[0]
    stretch = _stretch(warp, jaw.midpoint, jaw.v)
    new_jaw = JawGeometry.from_condyles(warp.apply(jaw.condyle_right), warp.apply(jaw.condyle_left), slide,
                                        jaw.track_length * stretch, jaw.max_opening_sine)
    new = replace(template, name=name, points=points, muscles=muscles, jaw=new_jaw, info={})
    skin = new.skin()
    new.markers = _onto(skin, warp, template.markers)
    new.landmarks = _onto(skin, warp, template.landmarks)
    return new


def _onto(skin: SkinSurface, warp: RBFWarp, sites: dict) -> dict:
    """Sites carried by the warp and put back on the skin: the warped skin is the flat triangles
    between warped nodes, a warped skin point is off them by the warp's curvature."""
    if not sites:
        return {}
    closest = skin.closest(warp.apply(np.array(list(sites.values()))))[2]
    return dict(zip(sites, closest))


def _stretch(warp: RBFWarp, point, direction) -> float:
    """|J d| / |d|: how much the warp lengthens a line element along ``direction`` at ``point``."""
    step = 1e-4 * np.ptp(warp.source_points, axis=0).max()
    unit = direction / np.linalg.norm(direction)
    return float(np.linalg.norm(warp.apply(point + step * unit) - warp.apply(point - step * unit)) / (2 * step))


def _check_scale(subject_points, template_points, what: str) -> None:
    scale = similarity_transform(subject_points, template_points).scale
    low, high = SUBJECT_SCALE_RANGE
    if not low <= 1.0 / scale <= high:
        units = [unit for unit, mm in MM_PER_UNIT.items() if low <= mm / scale <= high and mm != 1.0]
        hint = f"; looks like {units[0]}: pass --units {units[0]}" if units else ""
        raise SubjectError(f"the {what}'s landmarks span {1 / scale:.3g} times the template's: not a face in "
                           f"mm, likely a unit mistake{hint}")


def _similarity_json(transform: Similarity) -> dict:
    return dict(scale=transform.scale, rotation=transform.rotation.tolist(), translation=transform.translation.tolist())


# ---------------------------------------------------------------------------------------------
# Files
# ---------------------------------------------------------------------------------------------
def write_adapted_model(adaptation: Adaptation, out, *, info: dict, overwrite: bool = False) -> Path:
    """Write the adapted model folder plus subject.json; staged and checked by loading, then renamed
    into place, so a failure never leaves a folder that looks like a model."""
    with atomic_directory(out, MPI.COMM_SELF, overwrite=overwrite) as staging:
        replace(adaptation.model, info=info).write(staging)
        (staging / "subject.json").write_text(json.dumps(dict(info, **adaptation.record), indent=2))
        model_format.load_model(staging, MPI.COMM_SELF)
    return Path(out)


@dataclass(frozen=True, eq=False)
class SurfaceScan:
    """A subject's face surface: ``points`` (n, 3) mm with coincident points merged, ``triangles``
    (m, 3) into them, and ``point_of_vertex`` mapping the file's vertex ids to rows of ``points``."""

    path: Path
    points: np.ndarray
    triangles: np.ndarray
    point_of_vertex: np.ndarray


def read_surface(path, units: str = "mm") -> SurfaceScan:
    """A surface file (OBJ, STL, PLY, ...) read with meshio, in mm.

    Quads are split in two; other cells (lines, points) are ignored. Coincident points are merged
    (STL repeats every corner), so that neighbouring triangles share their edges and the scan's
    open border can be found.
    """
    import meshio
    path = Path(path)
    if path.suffix.lower() not in SURFACE_SUFFIXES:
        raise SubjectError(f"{path}: unknown surface format {path.suffix or '(no suffix)'!r}: expected "
                           f"{', '.join(SURFACE_SUFFIXES)}")
    if not path.is_file():
        raise SubjectError(f"{path}: file not found")
    try:
        mesh = meshio.read(path)
    except Exception as error:  # meshio raises assorted types for malformed files
        raise SubjectError(f"{path}: not a readable surface: {error}") from None
    triangles = [block.data for block in mesh.cells if block.type == "triangle"]
    triangles += [block.data[:, [0, 1, 2, 0, 2, 3]].reshape(-1, 3) for block in mesh.cells if block.type == "quad"]
    if not triangles:
        raise SubjectError(f"{path}: no triangles (cell types: {', '.join(b.type for b in mesh.cells) or 'none'})")
    points = np.asarray(mesh.points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3 or not np.all(np.isfinite(points)):
        raise SubjectError(f"{path}: points must be finite 3-D coordinates")
    unique, inverse = np.unique(points * _mm_per(units, path), axis=0, return_inverse=True)
    inverse = inverse.reshape(-1)
    return SurfaceScan(path, unique, inverse[np.concatenate(triangles)], inverse)


def read_landmark_file(path, scan: SurfaceScan, units: str = "mm") -> dict[str, np.ndarray]:
    """Template landmark name -> point of the subject surface, from TOML or CSV (by suffix).

    Each landmark is a vertex id of the surface file (0-based) or coordinates in the surface's
    ``units``. TOML: a ``[landmarks]`` table, ``nose_tip = 1234`` or ``nose_tip = [x, y, z]``.
    CSV: rows ``name,vertex`` or ``name,x,y,z`` (an optional header row, # comments).
    """
    path, suffix, text = read_pair_file(path, "landmark", SubjectError)
    if suffix == ".toml":
        try:
            table = tomllib.loads(text).get("landmarks")
        except tomllib.TOMLDecodeError as error:
            raise SubjectError(f"{path}: {error}") from None
        if not isinstance(table, dict) or not table:
            raise SubjectError(f"{path}: no [landmarks] table")
        entries = list(table.items())
    else:
        entries = []
        for row in csv.reader(line for line in text.splitlines() if not line.lstrip().startswith("#")):
            cells = [c.strip() for c in row]
            if not any(cells) or (not entries and cells[0].lower() in ("landmark", "name")):
                continue
            values = []
            for cell in cells[1:]:
                try:
                    values.append(int(cell) if cell.lstrip("-").isdigit() else float(cell))
                except ValueError:
                    raise SubjectError(f"{path}: {cells[0]}: {cell!r} is not a number") from None
            entries.append((cells[0], values[0] if len(values) == 1 else values))
    mm = _mm_per(units, path)
    landmarks = {}
    for name, value in entries:
        if name in landmarks:
            raise SubjectError(f"{path}: landmark {name!r} given twice")
        if isinstance(value, int) and not isinstance(value, bool):
            if not 0 <= value < len(scan.point_of_vertex):
                raise SubjectError(f"{path}: {name} = {value}: the vertex ids of {scan.path.name} run from 0 "
                                   f"to {len(scan.point_of_vertex) - 1}")
            landmarks[name] = scan.points[scan.point_of_vertex[value]].copy()
        elif isinstance(value, list) and len(value) == 3 and all(
                isinstance(v, (int, float)) and not isinstance(v, bool) and np.isfinite(v) for v in value):
            landmarks[name] = np.array(value, dtype=np.float64) * mm
        else:
            raise SubjectError(f"{path}: {name} must be a vertex id or [x, y, z], not {value!r}")
    return landmarks


def _mm_per(units: str, path: Path) -> float:
    if units not in MM_PER_UNIT:
        raise SubjectError(f"{path}: unknown units {units!r}: expected mm, cm or m")
    return MM_PER_UNIT[units]
