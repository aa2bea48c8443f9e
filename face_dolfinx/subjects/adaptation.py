"""Subject adaptation: a template face model carried onto one subject (sifakis2005 section 3).

Three steps, each with its own module:

1. The subject is moved rigidly (no scaling: the subject keeps its size) onto the template's
   landmarks, so the new model is in the template's frame: Y up, the same origin and facing.
2. The template's skin is registered onto the subject (``registration.register_skin``): a global
   affine map, then a smooth non-rigid displacement, landmarks held to their subject points and
   the other subject points matched to the closest skin, round after round.
3. Everything else follows the skin by a pseudo-elastic solve on the template mesh with the
   registered skin prescribed (``elastic.PseudoElasticCarry``, ``carry_model``): flesh nodes and
   with them the bone attachment surfaces and the muscles' cells; fibers by each cell's
   deformation gradient; landmarks and marker sites at their places on the skin triangles; the
   jaw's condyles and the muscles' geometry points by a smooth map fitted to the nodes' motion.
   The result is refused (SubjectError) if a tetrahedron inverts or flattens.

Two kinds of subject:

``adapt_to_markers``  the neutral frame of the subject's capture plus correspondences (>= 6 capture
    markers named by template landmark). Every other marker is matched to its closest skin
    point, except where that point is on the rim of an opening of the skin (a marker on an
    eyelid over the template's eye opening): such a marker shapes nothing and is reported as
    over an opening.
``adapt_to_surface``  a scan of the subject's face (triangles) plus landmark positions on it. Each
    template skin node is matched to its closest scan point; matches on the scan's open border
    are dropped (the scan may end before the template's skin does, and border matches would drag
    the skin along the edge), and so are matches farther than MAX_SURFACE_MATCH_MM.

Everything works on plain arrays (``face_dolfinx.model.folder.ModelArrays``, read by
``read_model_arrays``) on one process; ``write_adapted_model`` writes the result.
"""
from __future__ import annotations

import csv
import json
import tomllib
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree
from mpi4py import MPI

from face_dolfinx.files import atomic_directory
from face_dolfinx.model import folder as model_format
from face_dolfinx.alignment.similarity import AlignmentError, Similarity, align_by_correspondences, read_pair_file, similarity_transform
from face_dolfinx.model.folder import JawGeometry, ModelArrays
from face_dolfinx.alignment.surface import SkinSurface
from face_dolfinx.equilibrium.solver import EquilibriumError
from .elastic import PseudoElasticCarry, deformation_gradients
from .registration import FIXED_WEIGHT, Pairs, SkinRegistration, barycentric_rows, register_skin
from .warp import RBFWarp, fiber_transform, inverted_tets


MIN_LANDMARKS = 6              # as for aligning a capture: 7 unknowns and a margin
# A subject this much smaller or larger than the template (scale of the landmarks' best
# similarity) is a unit mistake, not a face.
SUBJECT_SCALE_RANGE = (0.5, 2.0)
# mm: a marker farther than this from the registered skin is not on this face (a stray marker,
# a marker of another subject, wrong units of one column): refused with its name.
MAX_MARKER_DISTANCE_MM = 10.0
# mm: a skin node's closest scan point farther than this is not its counterpart (the scan is
# another part of the head there); such a match is dropped.
MAX_SURFACE_MATCH_MM = 20.0
# Flesh nodes whose motion defines the smooth map for points off the mesh (the jaw's condyles,
# muscle geometry): enough to follow the elastic solve's large-scale motion, cheap to fit.
FAR_FIELD_NODES = 400
# Teeth: they follow a smooth map fitted to the motion of the flesh nodes within this distance (mm)
# of them (the lining they rest on), at most this many, so that the lining's clearance is kept.
TEETH_NEIGHBOURHOOD_MM = 10.0
TEETH_NODES = 600
# Stiffer registrations tried when the flesh cannot follow the softest one.
MAX_STIFFER_STEPS = 3
# The thin-plate spline reproduces an affine motion exactly, and its fitted map is smooth (C1)
# at its control points.
WARP_KERNEL = "thin_plate"
SURFACE_SUFFIXES = (".obj", ".stl", ".ply", ".off", ".vtk", ".vtu")
MM_PER_UNIT = {"mm": 1.0, "cm": 10.0, "m": 1000.0}


class SubjectError(ValueError):
    """Subject inputs that can't be used, or an adaptation that would break the mesh; the message says which."""


class CarryError(SubjectError):
    """The flesh cannot be carried onto a registered skin (no equilibrium)."""


@dataclass
class Adaptation:
    """An adapted model and how well it fits the subject."""

    model: ModelArrays
    registration: SkinRegistration
    to_template: Similarity               # rigid: subject input frame -> template (and new model) frame
    distances: dict[str, float]           # subject point -> new skin (mm), by name; the residual
    record: dict                          # what subject.json holds

    @property
    def iterations(self) -> int:
        return self.registration.rounds

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
    """The template carried onto the subject so that its skin passes through the markers of the
    neutral frame (those over an opening of the skin excepted).

    ``neutral`` (n, 3) and ``names`` (n,) are the subject's markers (every one present: each
    shapes the subject); ``correspondence`` maps capture markers to template landmarks.
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

    skin_points, triangles = template.skin_surface()
    template_skin = SkinSurface(skin_points, triangles)
    openings = _opening_edges(triangles)
    fixed = _landmark_pairs(template_skin, np.array([template.landmarks[lm] for _, lm in pairs]),
                            subject[landmark_rows])
    free = np.array([i for i in range(len(names)) if i not in set(landmark_rows)], dtype=int)

    def match(current: SkinSurface) -> Pairs:
        triangle, barycentric, over_opening = _closest_or_opening(current, openings, subject[free])
        on_skin = ~over_opening
        return Pairs(barycentric_rows(triangles, triangle[on_skin], barycentric[on_skin], len(skin_points)),
                     subject[free][on_skin])

    registration = _register(skin_points, triangles, fixed, match)
    new, measures, registration = _carry(template, registration, name)
    new_skin = SkinSurface(new.points[template.skin_nodes], triangles)
    distances = new_skin.closest(subject)[3]
    over_opening = _closest_or_opening(new_skin, openings, subject)[2]
    over_opening[landmark_rows] = False
    far = [f"{names[i]} ({distances[i]:.1f} mm)" for i in np.flatnonzero(distances > MAX_MARKER_DISTANCE_MM)]
    if far:
        raise SubjectError(f"markers that cannot be matched to the skin: {', '.join(far)} from the adapted "
                           f"skin (more than {MAX_MARKER_DISTANCE_MM:g} mm): are they on this face, and "
                           f"are the correspondences right?")
    offsets = skin.closest(subject)[3]
    on_skin = [n for i, n in enumerate(names) if not over_opening[i]]
    record = dict(method="capture markers", correspondence=dict(correspondence), to_template=_similarity_json(rigid),
                  iterations=registration.rounds, settled=registration.settled, **measures,
                  markers_over_openings=[n for i, n in enumerate(names) if over_opening[i]],
                  markers={n: dict(subject=subject[i].tolist(), skin_distance_mm=float(distances[i]),
                                   template_skin_distance_mm=float(offsets[i]), over_opening=bool(over_opening[i]))
                           for i, n in enumerate(names)})
    return Adaptation(new, registration, rigid, {n: float(distances[row[n]]) for n in on_skin}, record)


# ---------------------------------------------------------------------------------------------
# Subject from a surface scan
# ---------------------------------------------------------------------------------------------
def adapt_to_surface(template: ModelArrays, scan: SurfaceScan, landmarks: dict[str, np.ndarray], *,
                     name: str) -> Adaptation:
    """The template carried onto the subject so that its skin lies on the subject's face surface.

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
    scan_border = _border_nodes(scan.triangles)
    fixed_subject = rigid.apply(subject_landmarks)
    skin_points, triangles = template.skin_surface()
    fixed = _landmark_pairs(SkinSurface(skin_points, triangles), template_landmarks, fixed_subject)
    node_rows = sp.identity(len(skin_points), format="csr")  # a pair per skin node

    def within(points):
        """Closest scan points of ``points``, their distances, and which are inside the scan."""
        triangle, barycentric, closest, distance = surface.closest(points)
        inside = ~_at_border(scan.triangles, scan_border, triangle, barycentric)
        return closest, distance, inside

    def match(current: SkinSurface) -> Pairs:
        closest, distance, inside = within(current.points)
        keep = inside & (distance <= MAX_SURFACE_MATCH_MM)
        return Pairs(node_rows[np.flatnonzero(keep)], closest[keep])

    registration = _register(skin_points, triangles, fixed, match)
    new, measures, registration = _carry(template, registration, name)
    skin_nodes = template.skin_nodes
    _, distances, covered = within(new.points[skin_nodes])
    covered &= distances <= MAX_SURFACE_MATCH_MM
    names = [f"skin_node_{n}" for n in skin_nodes[covered]]
    landmark_distances = np.linalg.norm(np.array([new.landmarks[lm] for lm in known]) - fixed_subject, axis=1)
    record = dict(method="surface", to_template=_similarity_json(rigid), iterations=registration.rounds,
                  settled=registration.settled, **measures,
                  skin_nodes_matched=int(covered.sum()), skin_nodes=len(skin_nodes),
                  landmarks={lm: dict(subject=p.tolist(), residual_mm=float(d))
                             for lm, p, d in zip(known, fixed_subject, landmark_distances)})
    return Adaptation(new, registration, rigid, dict(zip(names, distances[covered].tolist())), record)


def _landmark_pairs(skin: SkinSurface, template_points, targets) -> Pairs:
    """Landmark pairs: template points (at their closest skin points) to their subject ``targets``."""
    triangle, barycentric, _, _ = skin.closest(template_points)
    rows = barycentric_rows(skin.triangles, triangle, barycentric, len(skin.points))
    return Pairs(rows, np.asarray(targets, dtype=np.float64), weight=FIXED_WEIGHT)


def _register(skin_points, triangles, fixed: Pairs, match) -> SkinRegistration:
    registration = register_skin(skin_points, triangles, fixed, match)
    if registration.folded.size:
        raise SubjectError(f"registering the skin onto the subject folds {registration.folded.size} skin "
                           f"triangles over: the subject points cross over; check the correspondences "
                           f"and that the points are on this face")
    return registration


def _carry(template: ModelArrays, registration: SkinRegistration, name: str):
    """``carry_model`` of the registered skin; where the flesh cannot follow it (no equilibrium:
    the skin squeezes a cell between two of its layers, at a lip), of the registration's stiffer
    steps, up to MAX_STIFFER_STEPS, the latest first. Returns the model, its measures and the
    registration used."""
    candidates = [(registration.stiffness, registration.positions)] + registration.stiffer[:MAX_STIFFER_STEPS]
    for attempt, (stiffness, positions) in enumerate(candidates):
        try:
            new, measures = carry_model(template, positions, name=name)
        except CarryError:
            if attempt == len(candidates) - 1:
                raise
            continue
        measures["skin_stiffness_mm2"] = stiffness
        return new, measures, replace(registration, positions=positions, stiffness=stiffness)


def _at_border(triangles, border, triangle, barycentric) -> np.ndarray:
    """Closest points on a border edge or border node of a surface: beyond where it ends."""
    on_edge = barycentric <= 1e-9
    return on_edge.any(axis=1) & np.all(np.isin(triangles[triangle], border) | on_edge, axis=1)


def _opening_edges(triangles) -> list[np.ndarray]:
    """The border edges (k, 2) of each opening of a surface (eyes, mouth): every border loop but
    the longest, which is the surface's outer edge."""
    edges = np.sort(triangles[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    unique, counts = np.unique(edges, axis=0, return_counts=True)
    border = unique[counts == 1]
    if not len(border):
        return []
    nodes, local = np.unique(border, return_inverse=True)
    graph = sp.csr_matrix((np.ones(len(border)), (local.reshape(-1, 2)[:, 0], local.reshape(-1, 2)[:, 1])),
                          shape=(len(nodes), len(nodes)))
    _, loop_of_node = connected_components(graph, directed=False)
    loop_of_edge = loop_of_node[local.reshape(-1, 2)[:, 0]]
    loops = [border[loop_of_edge == k] for k in range(loop_of_node.max() + 1)]
    loops.sort(key=len)
    return loops[:-1]


def _closest_or_opening(skin: SkinSurface, openings: list[np.ndarray], query):
    """Closest skin triangles and barycentric coordinates of ``query``, and which of the points
    are over an opening instead: closer to the opening's cap (a fan of triangles from the rim to
    its centroid, a stand-in for a closed eyelid or closed lips) than to any skin triangle."""
    triangle, barycentric, _, distance = skin.closest(query)
    over = np.zeros(len(query), dtype=bool)
    for rim in openings:
        centre = skin.points[np.unique(rim)].mean(axis=0)
        cap = SkinSurface(np.vstack([skin.points, centre]),
                          np.column_stack([rim, np.full(len(rim), len(skin.points))]))
        over |= cap.closest(query)[3] < distance
    return triangle, barycentric, over


def _border_nodes(triangles) -> np.ndarray:
    """Nodes on edges used by one triangle only (the scan's open border)."""
    edges = np.sort(triangles[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    unique, counts = np.unique(edges, axis=0, return_counts=True)
    return np.unique(unique[counts == 1])


# ---------------------------------------------------------------------------------------------
# The template carried along
# ---------------------------------------------------------------------------------------------
def carry_model(template: ModelArrays, skin_targets: np.ndarray, *, name: str) -> tuple[ModelArrays, dict]:
    """Everything in the template carried along with its skin moved to ``skin_targets`` (positions
    of ``template.skin_nodes``), and the measures of what that did to the mesh.

    The best affine map of the skin moves every node first (the reference of the elastic solve);
    the rest of the skin's motion is spread into the flesh by the pseudo-elastic solve
    (``elastic.PseudoElasticCarry``). Fibers follow each cell's deformation gradient; landmarks and
    marker sites stay at their places on the skin triangles; points off the mesh (muscle
    geometry, the jaw's condyles) follow a smooth map fitted to the flesh nodes' motion; the teeth
    one fitted to the motion of the flesh around them (``_carry_teeth``).
    SubjectError if no equilibrium is found or a tet inverts or flattens.
    """
    skin_nodes = template.skin_nodes
    affine = _affine_fit(template.points[skin_nodes], skin_targets)
    if np.linalg.det(affine[:, :3]) <= 0:
        raise SubjectError("the subject points turn the template's skin inside out (the best affine map "
                           "of the skin is a reflection): check the correspondences (left and right?)")
    reference = template.points @ affine[:, :3].T + affine[:, 3]
    carry = PseudoElasticCarry(reference, template.cells, skin_nodes)
    try:
        points, report = carry.solve(skin_targets - reference[skin_nodes])
    except EquilibriumError as error:
        raise CarryError(f"the template cannot be carried onto the registered skin ({error}): the skin "
                           f"registration folds or pulls the skin through the flesh; check the "
                           f"correspondences and that the markers are on this face") from None
    bad = inverted_tets(points, template.cells)
    if bad.size:
        raise SubjectError(f"carrying the template inverts {bad.size} of {len(template.cells)} tetrahedra (e.g. "
                           f"cell {bad[0]}): the subject points pull the template too far or cross over; "
                           f"check the correspondences and that the markers are on this face")
    _, quality_before = model_format.tet_volumes_and_quality(template.points[template.cells])
    _, quality = model_format.tet_volumes_and_quality(points[template.cells])
    if quality.min() < model_format.DEGENERATE_QUALITY:
        raise SubjectError(f"carrying the template flattens {np.sum(quality < model_format.DEGENERATE_QUALITY)} "
                           f"tetrahedra (quality {quality.min():.2g} < {model_format.DEGENERATE_QUALITY:g}, cell "
                           f"{int(np.argmin(quality))}); the subject points pull the template too far")
    gradients = deformation_gradients(template.points, points, template.cells)
    far_field = RBFWarp.fit(*(p[_spread_nodes(template.points, FAR_FIELD_NODES)] for p in (template.points, points)),
                            kernel=WARP_KERNEL)
    volumes_before = _muscle_volumes(template, template.points)
    muscles = []
    for muscle in template.muscles:
        geometry = {}
        for key, value in muscle.geometry.items():
            if key == "axis":  # a direction at the sphincter's centre, its length kept
                centres = template.points[template.cells[muscle.cells]].mean(axis=1)
                at = muscle.geometry.get("center", centres.mean(axis=0))
                geometry[key] = np.linalg.norm(value) * fiber_transform(far_field, at[None], value[None])[0]
            else:
                geometry[key] = far_field.apply(value)
        fiber = np.einsum("nij,nj->ni", gradients[muscle.cells], muscle.fiber) if len(muscle.cells) else muscle.fiber
        if len(muscle.cells):
            fiber = fiber / np.linalg.norm(fiber, axis=1, keepdims=True)
        muscles.append(replace(muscle, fiber=fiber, geometry=geometry))
    jaw = template.jaw
    slide = fiber_transform(far_field, jaw.midpoint[None], jaw.v[None])[0]
    stretch = _stretch(far_field, jaw.midpoint, jaw.v)
    new_jaw = JawGeometry.from_condyles(far_field.apply(jaw.condyle_right), far_field.apply(jaw.condyle_left), slide,
                                        jaw.track_length * stretch, jaw.max_opening_sine)
    new = replace(template, name=name, points=points, muscles=muscles, jaw=new_jaw, info={},
                  teeth=_carry_teeth(template, points))
    new.markers = _on_skin(template, points, template.markers)
    new.landmarks = _on_skin(template, points, template.landmarks)
    volumes_after = _muscle_volumes(new, points)
    measures = dict(
        min_quality_before=float(quality_before.min()), min_quality_after=float(quality.min()),
        muscle_volume_mm3={m.name: dict(before=volumes_before[i], after=volumes_after[i])
                           for i, m in enumerate(template.muscles)},
        elastic_newton_iterations=report.newton_iterations, elastic_load_steps=report.load_steps)
    return new, measures


def _carry_teeth(template: ModelArrays, points: np.ndarray) -> dict:
    """The template's teeth moved by a thin-plate warp interpolating the motion of the flesh
    nodes near them (the lining they rest on moves the same way, so the clearance is kept)."""
    teeth = {}
    for bone, (teeth_points, triangles) in template.teeth.items():
        near = np.flatnonzero(cKDTree(teeth_points).query(template.points)[0] <= TEETH_NEIGHBOURHOOD_MM)
        if len(near) < 4:
            near = _spread_nodes(template.points, FAR_FIELD_NODES)
        near = near[_spread_nodes(template.points[near], TEETH_NODES)]
        warp = RBFWarp.fit(template.points[near], points[near], kernel=WARP_KERNEL)
        teeth[bone] = (warp.apply(teeth_points), triangles)
    return teeth


def _affine_fit(source, target) -> np.ndarray:
    """The (3, 4) affine map [A | b] taking ``source`` closest to ``target`` (least squares)."""
    homogeneous = np.hstack([source, np.ones((len(source), 1))])
    return np.linalg.lstsq(homogeneous, target, rcond=None)[0].T


def _spread_nodes(points, count: int) -> np.ndarray:
    """``count`` rows of ``points`` spread over them (farthest-point sampling), or all."""
    if len(points) <= count:
        return np.arange(len(points))
    chosen = [0]
    distance = np.linalg.norm(points - points[0], axis=1)
    for _ in range(count - 1):
        chosen.append(int(np.argmax(distance)))
        distance = np.minimum(distance, np.linalg.norm(points - points[chosen[-1]], axis=1))
    return np.sort(chosen)


def _muscle_volumes(model: ModelArrays, points) -> list[float]:
    """Each muscle's volume (mm^3): its cells' volumes times the fraction of each it fills."""
    volumes, _ = model_format.tet_volumes_and_quality(points[model.cells])
    return [float(np.sum(volumes[m.cells] * m.fraction)) for m in model.muscles]


def _on_skin(template: ModelArrays, points, sites: dict) -> dict:
    """Sites at the same place on the skin triangles (barycentric) over the moved ``points``."""
    if not sites:
        return {}
    skin = template.skin()
    triangle, barycentric, _, _ = skin.closest(np.array(list(sites.values())))
    moved = np.einsum("nk,nkd->nd", barycentric, points[skin.triangles[triangle]])
    return dict(zip(sites, moved))


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


def summary(adaptation: Adaptation, subject: str, template_name: str) -> str:
    """What an adaptation did, in a few lines: residual, mesh quality, muscle volumes, markers
    over openings and those farthest from the template's skin (marker offsets)."""
    record = adaptation.record
    worst = max(adaptation.distances, key=adaptation.distances.get)
    what = "markers" if record["method"] == "capture markers" else "skin nodes inside the scan"
    volumes = record["muscle_volume_mm3"]
    ratio = {name: v["after"] / v["before"] for name, v in volumes.items() if v["before"] > 0}
    smallest, largest = min(ratio, key=ratio.get), max(ratio, key=ratio.get)
    settling = "" if adaptation.registration.settled else " (matches still sliding along the skin)"
    lines = [(f"adapted {template_name} to {subject}: the skin is RMS {adaptation.rms:.3f} mm, max "
              f"{adaptation.max:.3f} mm ({worst}) from the subject's {len(adaptation.distances)} {what}; "
              f"{adaptation.iterations} matching rounds, skin stiffness down to "
              f"{adaptation.registration.stiffness:g} mm^2{settling}"),
             (f"  elements: min quality {record['min_quality_before']:.3g} -> {record['min_quality_after']:.3g}, "
              f"none inverted; pseudo-elastic carry in {record['elastic_load_steps']} load steps, "
              f"{record['elastic_newton_iterations']} Newton iterations"),
             f"  muscle volumes x{ratio[smallest]:.2f} ({smallest}) to x{ratio[largest]:.2f} ({largest})"]
    if record.get("markers_over_openings"):
        lines.append(f"  over an opening of the skin (shape nothing): {', '.join(record['markers_over_openings'])}")
    if "markers" in record:
        offsets = {n: m["template_skin_distance_mm"] for n, m in record["markers"].items()}
        farthest = sorted(offsets, key=offsets.get, reverse=True)[:3]
        lines.append("  marker offsets from the template's skin (aligned rigidly): RMS "
                     f"{np.sqrt(np.mean(np.square(list(offsets.values())))):.1f} mm, largest "
                     + ", ".join(f"{n} {offsets[n]:.1f} mm" for n in farthest))
    return "\n".join(lines)


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
    if points.ndim != 2 or points.shape[1] != 3:
        raise SubjectError(f"{path}: points must be 3-D coordinates, not of shape {points.shape}")
    not_finite = np.flatnonzero(~np.all(np.isfinite(points), axis=1))
    if not_finite.size:
        raise SubjectError(f"{path}: {not_finite.size} vertices are not finite (first: vertex {not_finite[0]})")
    unique, inverse = np.unique(points * _mm_per(units, path), axis=0, return_inverse=True)
    inverse = inverse.reshape(-1)
    merged = inverse[np.concatenate(triangles)]
    collapsed = np.flatnonzero((merged[:, 0] == merged[:, 1]) | (merged[:, 1] == merged[:, 2])
                               | (merged[:, 2] == merged[:, 0]))
    if collapsed.size:
        raise SubjectError(f"{path}: {collapsed.size} triangles have two corners at the same point (duplicate "
                           f"vertices; first: triangle {collapsed[0]}): repair the surface (merge its vertices, "
                           f"drop the degenerate triangles)")
    return SurfaceScan(path, unique, merged, inverse)


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
