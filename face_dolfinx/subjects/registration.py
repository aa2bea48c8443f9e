"""Registration of the template's skin onto a subject: a global affine map, then a smooth non-rigid one.

The skin is a triangle surface over the template's skin nodes X; the subject is a set of points
(the markers of a capture's neutral frame, or points of a scan) of which some are fixed pairs
(landmarks: a template skin point and the subject point it must go to) and the others are matched,
round after round, to the closest point of the current skin (or the other way round for a scan:
the skin nodes matched to the scan). Two stages, as in Amberg et al. 2007 ("Optimal step nonrigid
ICP"):

1. Global affine ICP: the best affine map of all pairs, re-matched until the pairs settle. A
   subject that is an affine image of the template is reproduced exactly here.
2. Non-rigid: node displacements D on top of the affine image Y0 = A X + b minimising

       sum_pairs w |B (Y0 + D) - target|^2  +  stiffness * int |Laplace D|^2  +  stiffness / decay^4 * int |D|^2

   (B: the barycentric rows of the template points paired; the Laplacian is the umbrella
   operator scaled to the local edge length, the integrals are lumped over node areas), a sparse
   linear solve per round. The bending term keeps the displacement smooth (it is the thin-plate
   energy of the skin, so it neither cusps at a marker nor folds a small feature); the weak tether
   makes it die out over ``decay`` mm where the subject says nothing (the back of the head, skin
   beyond a scan's border). The stiffness steps down over STIFFNESS_SCHEDULE, re-matching at each
   step, so that the skin first follows the subject's large-scale shape and then its details.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from face_dolfinx.alignment.similarity import similarity_transform
from face_dolfinx.alignment.surface import SkinSurface

# mm^2: bending stiffness of the displacement, from the shape of a whole face down to the size of
# a lip. Measured on the real 41-marker sample (docs/subjects.md): the last step leaves the
# markers 0.2-0.3 mm RMS from the skin without folding a triangle.
STIFFNESS_SCHEDULE = (1e4, 3e3, 1e3, 300.0, 100.0, 30.0, 10.0, 3.0, 1.0)
DECAY_MM = 40.0              # the displacement dies out over this distance where no data pulls it
FIXED_WEIGHT = 10.0          # landmarks pull ten times as hard as a matched point
AFFINE_ROUNDS = 50
ROUNDS_PER_STIFFNESS = 3
FINAL_ROUNDS = 30            # the softest stiffness: until the matches settle
FOLD_BISECTIONS = 3
SETTLED_MM = 0.01            # mm: pairs moving less than this have settled
# The affine stage settles further: an affine subject must come out exact, not nearly so.
AFFINE_SETTLED_MM = 1e-4
# An affine map stretching one direction this much more than another is not a face's proportions
# but a poorly spread set of pairs: the global stage then keeps a similarity.
MAX_AFFINE_ANISOTROPY = 1.25


@dataclass
class Pairs:
    """Template skin points (sparse rows of barycentric weights over the skin nodes) and the
    subject points they go to."""

    rows: sp.csr_matrix         # (k, n_nodes)
    targets: np.ndarray         # (k, 3)
    weight: float = 1.0


@dataclass
class SkinRegistration:
    positions: np.ndarray       # (n_nodes, 3) registered skin nodes
    affine: np.ndarray          # (3, 4) the global stage's map [A | b]
    rounds: int                 # matching rounds in all
    settled: bool               # the last stiffness's matches settled
    stiffness: float            # the softest stiffness taken (mm^2): softer ones would fold the skin
    stiffer: list               # (stiffness, positions) of the steps before, the latest first
    folded: np.ndarray          # skin triangles whose orientation the registration reversed


def barycentric_rows(triangles: np.ndarray, triangle: np.ndarray, barycentric: np.ndarray, num_nodes: int):
    """Sparse rows (k, num_nodes) evaluating points given by triangle and barycentric coordinates."""
    k = len(triangle)
    return sp.csr_matrix((np.asarray(barycentric).ravel(), (np.repeat(np.arange(k), 3),
                                                            triangles[triangle].ravel())), shape=(k, num_nodes))


def register_skin(points: np.ndarray, triangles: np.ndarray, fixed: Pairs,
                  match: Callable[[SkinSurface], Pairs], *, schedule=STIFFNESS_SCHEDULE,
                  decay: float = DECAY_MM) -> SkinRegistration:
    """Register the skin (nodes ``points``, ``triangles`` into them) onto the subject.

    ``fixed`` are the landmark pairs; ``match(skin)`` returns the pairs for the skin as it is now
    (rows on the template's nodes, as ``barycentric_rows`` builds them).
    """
    points = np.asarray(points, dtype=np.float64)
    rounds = 0

    def pairs_now(current):
        matched = match(SkinSurface(current, triangles))
        return [fixed, matched]

    # 1. Global affine ICP.
    affine = np.hstack([np.eye(3), np.zeros((3, 1))])
    previous = None
    for _ in range(AFFINE_ROUNDS):
        rounds += 1
        current = points @ affine[:, :3].T + affine[:, 3]
        pairs = pairs_now(current)
        stacked = _pair_points(points, pairs)
        if previous is not None and previous.shape == stacked.shape and \
                np.max(np.abs(stacked - previous), initial=0.0) < AFFINE_SETTLED_MM:
            break
        previous = stacked
        affine = _weighted_affine(points, pairs)
    rest = points @ affine[:, :3].T + affine[:, 3]

    # 2. Non-rigid, stiff to soft; a step that would fold the skin is not taken, but up to
    # FOLD_BISECTIONS stiffnesses between the last one taken and the folding one are tried.
    bending, area = _bending_operator(rest, triangles)
    displacement = np.zeros_like(points)
    settled, stiffness_reached, taken = False, None, []
    levels, level, bisections = list(schedule), 0, 0
    while level < len(levels):
        stiffness = levels[level]
        regulariser = stiffness * (bending + (1.0 / decay ** 4) * sp.diags(area))
        trial, previous, trial_settled = displacement, None, False
        for _ in range(FINAL_ROUNDS if level == len(levels) - 1 else ROUNDS_PER_STIFFNESS):
            rounds += 1
            pairs = pairs_now(rest + trial)
            stacked = _pair_points(points, pairs)
            if previous is not None and previous.shape == stacked.shape and \
                    np.max(np.abs(stacked - previous), initial=0.0) < SETTLED_MM:
                trial_settled = True
                break
            previous = stacked
            matrix, rhs = regulariser.copy(), np.zeros_like(points)
            for p in pairs:
                matrix = matrix + p.weight * (p.rows.T @ p.rows)
                rhs += p.weight * (p.rows.T @ (p.targets - p.rows @ rest))
            solve = spla.factorized(sp.csc_matrix(matrix))
            trial = np.column_stack([solve(rhs[:, d]) for d in range(3)])
        if stiffness_reached is not None and _folded(rest, rest + trial, triangles).size:
            if bisections == FOLD_BISECTIONS:
                break
            bisections += 1
            levels = levels[:level] + [float(np.sqrt(stiffness_reached * stiffness))]
            continue
        if stiffness_reached is not None:
            taken.insert(0, (stiffness_reached, rest + displacement))
        displacement, settled, stiffness_reached = trial, trial_settled, stiffness
        level += 1
    positions = rest + displacement
    return SkinRegistration(positions, affine, rounds, settled, stiffness_reached, taken,
                            _folded(rest, positions, triangles))


def _pair_points(points, pairs: list[Pairs]) -> np.ndarray:
    """The template points and the targets of ``pairs``, side by side: what settles."""
    return np.vstack([np.hstack([p.rows @ points, p.targets]) for p in pairs])


def _weighted_affine(points, pairs: list[Pairs]) -> np.ndarray:
    """Best affine [A | b] of the template points of ``pairs`` onto their targets (weighted least
    squares); a similarity where the pairs leave an affine map ill-determined."""
    source = np.vstack([p.rows @ points for p in pairs])
    target = np.vstack([p.targets for p in pairs])
    weight = np.concatenate([np.full(len(p.targets), p.weight) for p in pairs])
    homogeneous = np.hstack([source, np.ones((len(source), 1))]) * np.sqrt(weight)[:, None]
    affine = np.linalg.lstsq(homogeneous, target * np.sqrt(weight)[:, None], rcond=None)[0].T
    singular = np.linalg.svd(affine[:, :3], compute_uv=False)
    if np.linalg.det(affine[:, :3]) > 0 and singular[0] <= MAX_AFFINE_ANISOTROPY * singular[-1]:
        return affine
    similarity = similarity_transform(source, target, weight)
    return np.hstack([similarity.scale * similarity.rotation, similarity.translation[:, None]])


def _bending_operator(points, triangles) -> tuple[sp.csr_matrix, np.ndarray]:
    """(L^T M L) approximating int |Laplace D|^2 over the skin, and the lumped node areas M.

    L is the umbrella operator (neighbour mean minus the node) times 4 / h^2 (h: the node's mean
    edge length), the Laplacian of a regular triangulation."""
    n = len(points)
    edges = np.unique(np.sort(triangles[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1), axis=0)
    i, j = np.concatenate([edges[:, 0], edges[:, 1]]), np.concatenate([edges[:, 1], edges[:, 0]])
    adjacency = sp.csr_matrix((np.ones(len(i)), (i, j)), shape=(n, n))
    degree = np.asarray(adjacency.sum(axis=1)).ravel()
    length = np.linalg.norm(points[edges[:, 0]] - points[edges[:, 1]], axis=1)
    mean_length = np.bincount(i, weights=np.concatenate([length, length]), minlength=n) / np.maximum(degree, 1)
    umbrella = sp.diags(1.0 / np.maximum(degree, 1)) @ adjacency - sp.identity(n)
    laplacian = sp.diags(4.0 / np.maximum(mean_length, 1e-12) ** 2) @ umbrella
    a, b, c = (points[triangles[:, k]] for k in range(3))
    triangle_area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    area = np.bincount(triangles.ravel(), weights=np.repeat(triangle_area / 3.0, 3), minlength=n)
    return (laplacian.T @ sp.diags(area) @ laplacian).tocsr(), area


def _folded(before, after, triangles) -> np.ndarray:
    """Triangles whose normal turned by more than 90 degrees."""
    def normals(p):
        return np.cross(p[triangles[:, 1]] - p[triangles[:, 0]], p[triangles[:, 2]] - p[triangles[:, 0]])
    return np.flatnonzero(np.einsum("ij,ij->i", normals(before), normals(after)) <= 0)
