"""Aligning a capture's neutral frame to the face model, and embedding its markers in the skin.

The capture and the model each have their own frame (the capture's origin and facing direction
are arbitrary). A similarity transform (scale, proper rotation, translation) maps capture
coordinates into model coordinates. It is found either from named correspondences (capture
marker -> model landmark; Umeyama's closed form) or, without names, by ICP of the markers against
the skin. Either way the markers are then embedded in the skin at their closest points, keeping
their offsets (sifakis2005 section 5), and the alignment is judged: how far the aligned markers
are from the skin and, by names, how well the pairs agree, whether one pair disagrees with the
others and whether the mirrored (left/right swapped) assignment fits much better. The verdict is
"good", "doubtful: <reasons>" (fit, but warn) or "wrong: <reasons>" (clearly wrong: refuse). See
docs/alignment.md.
"""
from __future__ import annotations

import csv
import itertools
import re
import tomllib
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from .surface import MarkerEmbedding, SkinSurface

# Correspondences needed for an alignment by names: 7 unknowns, and a margin for a misplaced one.
MIN_CORRESPONDENCES = 6
# Centred points whose second singular value is below this fraction of the first are collinear:
# a rotation about their line is undetermined.
COLLINEAR_RATIO = 1e-9
# The 24 proper rotations that map principal axes onto principal axes, in any order and direction
# (signed permutation matrices, det +1). Any order, not only largest variance onto largest: markers
# cover the face, the skin also its sides and neck, so their axes need not rank alike; on the
# built-in face the skin is about as wide as it is tall, and the markers much taller than wide.
PROPER_AXIS_MAPS = tuple(np.diag(signs)[list(order)] for order in itertools.permutations(range(3))
                         for signs in itertools.product((1, -1), repeat=3)
                         if np.linalg.det(np.diag(signs)[list(order)]) > 0)
# The rigid warm-up of a similarity ICP ends once an iteration lowers the objective by less than this.
WARM_UP_DECREASE = 1e-3
# Fractions of a point-to-plane step tried, in turn, until one lowers the objective.
STEP_FRACTIONS = (1.0, 0.5, 0.25)


class AlignmentError(ValueError):
    """Alignment inputs that can't be used; the message says what is missing or wrong."""


@dataclass(frozen=True, eq=False)
class Similarity:
    """x -> scale * rotation @ x + translation, with a proper rotation (det +1).

    ``rms`` is the root-mean-square residual of the fit that produced it, in target units (NaN for
    a transform that was not fitted).
    """

    scale: float
    rotation: np.ndarray     # (3, 3)
    translation: np.ndarray  # (3,)
    rms: float = float("nan")

    def __post_init__(self):
        for name, shape in (("rotation", (3, 3)), ("translation", (3,))):
            value = np.array(getattr(self, name), dtype=np.float64)
            if value.shape != shape:
                raise ValueError(f"{name} must have shape {shape}, not {value.shape}")
            value.flags.writeable = False
            object.__setattr__(self, name, value)
        object.__setattr__(self, "scale", float(self.scale))
        object.__setattr__(self, "rms", float(self.rms))

    @classmethod
    def identity(cls) -> Similarity:
        return cls(1.0, np.eye(3), np.zeros(3))

    def apply(self, points) -> np.ndarray:
        """Transformed points, (n, 3) or (3,) like the input; NaN rows stay NaN."""
        points = np.asarray(points, dtype=np.float64)
        return self.scale * points @ self.rotation.T + self.translation

    def inverse(self) -> Similarity:
        # Residuals map back scaled by 1/scale, so the fit's RMS does too.
        rotation = self.rotation.T
        return Similarity(1.0 / self.scale, rotation, -(rotation @ self.translation) / self.scale,
                          self.rms / self.scale)

    def __matmul__(self, first: Similarity) -> Similarity:
        """self @ first: apply ``first``, then ``self``."""
        return Similarity(self.scale * first.scale, self.rotation @ first.rotation,
                          self.scale * self.rotation @ first.translation + self.translation)


def similarity_transform(source, target, weights=None, allow_scale=True) -> Similarity:
    """The least-squares similarity mapping ``source`` (n, 3) onto ``target`` (n, 3) (Umeyama 1991).

    Rows with a non-finite coordinate in either array, or a zero weight, are ignored. The rotation
    is always proper: mirror-image data gets the best rotation, never a reflection. Without
    ``allow_scale`` the scale is 1 (a rigid transform). ``rms`` is the weighted RMS residual.
    Raises AlignmentError with fewer than 3 usable rows, or when those are collinear.
    """
    source = _as_points(source, "source")
    target = _as_points(target, "target")
    if source.shape != target.shape:
        raise AlignmentError(f"source and target must have the same shape, not {source.shape} and {target.shape}")
    if weights is None:
        weights = np.ones(len(source))
    weights = np.asarray(weights, dtype=np.float64)
    if weights.shape != (len(source),) or not np.all(np.isfinite(weights)) or np.any(weights < 0):
        raise AlignmentError(f"weights must be {len(source)} finite non-negative numbers")
    usable = _finite_rows(source) & _finite_rows(target) & (weights > 0)
    if usable.sum() < 3:
        raise AlignmentError(f"a similarity transform needs at least 3 usable point pairs, got {usable.sum()}")
    source, target, weights = source[usable], target[usable], weights[usable] / weights[usable].sum()

    source_mean, target_mean = weights @ source, weights @ target
    source_centred, target_centred = source - source_mean, target - target_mean
    for name, centred in (("source", source_centred), ("target", target_centred)):
        spread = np.linalg.svd(centred * np.sqrt(weights)[:, None], compute_uv=False)
        if spread[1] <= COLLINEAR_RATIO * spread[0]:
            raise AlignmentError(f"the usable {name} points are collinear (or coincide): "
                                 "the rotation about their line is undetermined")
    covariance = (target_centred * weights[:, None]).T @ source_centred
    u, singular, vt = np.linalg.svd(covariance)
    # Umeyama's S: flip the weakest axis when the best orthogonal map would be a reflection.
    signs = np.array([1.0, 1.0, -1.0 if np.linalg.det(u) * np.linalg.det(vt) < 0 else 1.0])
    rotation = (u * signs) @ vt
    scale = (singular @ signs) / (weights @ np.sum(source_centred ** 2, axis=1)) if allow_scale else 1.0
    translation = target_mean - scale * rotation @ source_mean
    residual = scale * source @ rotation.T + translation - target
    rms = np.sqrt(weights @ np.sum(residual ** 2, axis=1))
    return Similarity(scale, rotation, translation, rms)


@dataclass(frozen=True)
class QualityThresholds:
    """When an alignment is "good" (every test of the first group passes) and when it is "wrong"
    (a test of the second group fails). Distances in mm. The second group was chosen by
    measurement on synthetic and real captures (docs/alignment.md): a real face of other
    proportions than the template's, correctly paired, stays clear of every one of them."""

    rms_mm: float = 2.0          # RMS distance of the aligned markers to the skin
    max_mm: float = 5.0          # distance of the worst marker
    near_mm: float = 2.0         # a marker this close to the skin is "near" it ...
    min_near_fraction: float = 0.9   # ... and at least this fraction of markers must be
    scale_range: tuple[float, float] = (0.8, 1.25)  # plausible capture-to-model size ratios
    landmark_rms_mm: float = 5.0     # RMS of correspondence residuals (alignment by names)
    rival_ratio: float = 1.5         # ICP: another pose whose trimmed RMS is within this factor is a rival
    # A pair stands out when the other pairs put its marker more than stand_out_ratio times their
    # own residual (per coordinate, degrees of freedom counted) and more than stand_out_mm from
    # its landmark; it makes the alignment wrong beyond wrong_pair_mm, given at least
    # wrong_pair_min_pairs pairs (fewer fit a real face of other proportions too loosely to tell).
    stand_out_ratio: float = 6.0
    stand_out_mm: float = 10.0
    wrong_pair_mm: float = 30.0
    wrong_pair_min_pairs: int = 8
    # Left and right are swapped when the mirrored assignment fits with less than this fraction of
    # the landmark RMS, that RMS being above landmark_rms_mm.
    swap_ratio: float = 2.0 / 3.0
    wrong_scale_range: tuple[float, float] = (0.5, 2.0)  # beyond: wrong units, or not this face
    wrong_landmark_rms_mm: float = 20.0
    wrong_rms_mm: float = 20.0       # markers to skin


@dataclass(frozen=True, eq=False)
class AlignmentQuality:
    """How well the aligned markers sit on the skin, and the verdict on the alignment."""

    distances: np.ndarray  # (n,) mm from each aligned marker to the skin; NaN for a missing marker
    rms: float
    max: float
    near_mm: float
    near_fraction: float   # fraction of the present markers within near_mm of the skin
    level: str             # "good", "doubtful" (fit, but warn) or "wrong" (refuse)
    reasons: tuple[str, ...] = ()   # why not good: what makes it wrong first, then what makes it doubtful

    @property
    def verdict(self) -> str:
        """"good", "doubtful: <reasons>" or "wrong: <reasons>"."""
        return self.level if not self.reasons else f"{self.level}: " + "; ".join(self.reasons)

    @property
    def good(self) -> bool:
        return self.level == "good"

    @property
    def wrong(self) -> bool:
        return self.level == "wrong"

    def __str__(self):
        return (f"{self.verdict} (markers to skin: RMS {self.rms:.2f} mm, max {self.max:.2f} mm, "
                f"{100 * self.near_fraction:.0f}% within {self.near_mm:g} mm)")


@dataclass(frozen=True, eq=False)
class PairCheck:
    """How the correspondences agree with each other (``check_pairs``)."""

    # capture marker -> distance (mm) from its landmark at which the other pairs put it, for the
    # pairs that stand out, worst first
    standing_out: dict[str, float]
    # the same fit with every left/right landmark swapped for its mirror partner: its landmark RMS
    # and scale; None when no pair has a mirror partner among the model's landmarks
    mirrored_rms: float | None
    mirrored_scale: float | None


@dataclass(frozen=True, eq=False)
class CorrespondenceAlignment:
    transform: Similarity          # capture -> model coordinates
    residuals: dict[str, float]    # capture marker -> |transform(marker) - landmark|, mm
    embedding: MarkerEmbedding     # every capture marker, named, in capture order
    quality: AlignmentQuality
    pairs: PairCheck


@dataclass(frozen=True, eq=False)
class IcpAlignment:
    transform: Similarity          # capture -> model coordinates
    quality: AlignmentQuality
    iterations: int
    converged: bool


def align_by_correspondences(capture_neutral, capture_names, model_landmarks, correspondence, skin: SkinSurface,
                             *, allow_scale=True, thresholds=QualityThresholds()) -> CorrespondenceAlignment:
    """Align a capture's neutral frame to the model by named correspondences, then embed every marker.

    capture_neutral (n, 3) and capture_names (n,) are the capture's neutral frame and marker names;
    model_landmarks maps landmark names to model points; correspondence maps capture marker names
    to landmark names. Every capture marker must be present (finite) in the neutral frame, since
    each is embedded in the skin; choose a complete frame (``frames_with_gaps``) or leave the
    marker out. All problems are reported together in one AlignmentError.
    """
    markers = _as_points(capture_neutral, "capture_neutral")
    names = [str(name) for name in capture_names]
    if len(names) != len(markers):
        raise AlignmentError(f"{len(names)} capture names for {len(markers)} markers")
    repeated = sorted({name for name in names if names.count(name) > 1})
    if repeated:
        raise AlignmentError(f"capture marker names must be unique; repeated: {', '.join(repeated)}")
    row_of = {name: row for row, name in enumerate(names)}
    present = _finite_rows(markers)

    problems = []
    for marker, landmark in correspondence.items():
        if marker not in row_of:
            problems.append(f"capture marker {marker!r} (for landmark {landmark!r}) does not exist in the capture")
        elif not present[row_of[marker]]:
            problems.append(f"capture marker {marker!r} (for landmark {landmark!r}) is missing (NaN) "
                            "in the neutral frame")
        if landmark not in model_landmarks:
            problems.append(f"landmark {landmark!r} (for capture marker {marker!r}) is not a landmark of the model")
        elif not (np.shape(model_landmarks[landmark]) == (3,) and np.all(np.isfinite(model_landmarks[landmark]))):
            problems.append(f"landmark {landmark!r} is not a finite 3-vector: {model_landmarks[landmark]!r}")
    markers_of = {}
    for marker, landmark in correspondence.items():
        markers_of.setdefault(landmark, []).append(marker)
    for landmark, markers_at in markers_of.items():
        if len(markers_at) > 1:
            problems.append(f"landmark {landmark!r} is paired with more than one capture marker: "
                            f"{', '.join(map(repr, markers_at))}")
    usable = [(marker, landmark) for marker, landmark in correspondence.items()
              if marker in row_of and present[row_of[marker]] and landmark in model_landmarks]
    if len(usable) < MIN_CORRESPONDENCES:
        problems.append(f"only {len(usable)} usable correspondences; at least {MIN_CORRESPONDENCES} are needed")
    unplaced = [name for name in names if not present[row_of[name]] and name not in correspondence]
    if unplaced:
        problems.append(f"capture markers missing (NaN) in the neutral frame cannot be embedded in the skin: "
                        f"{', '.join(unplaced)}")
    if problems:
        raise AlignmentError("cannot align the capture by correspondences:\n  " + "\n  ".join(problems))

    source = markers[[row_of[marker] for marker, _ in usable]]
    target = np.array([model_landmarks[landmark] for _, landmark in usable], dtype=np.float64)
    transform = similarity_transform(source, target, allow_scale=allow_scale)
    residuals = dict(zip((marker for marker, _ in usable),
                         np.linalg.norm(transform.apply(source) - target, axis=1).tolist()))
    embedding = skin.embed(transform.apply(markers), names)

    check = check_pairs(source, target, [marker for marker, _ in usable], [landmark for _, landmark in usable],
                        model_landmarks, allow_scale=allow_scale, thresholds=thresholds)
    landmark_rms = float(np.sqrt(np.mean(np.square(list(residuals.values())))))
    wrong, extra = [], []
    swapped = (check.mirrored_rms is not None and landmark_rms > thresholds.landmark_rms_mm
               and check.mirrored_rms < thresholds.swap_ratio * landmark_rms)
    if swapped:
        wrong.append(f"left and right look swapped: with each left landmark exchanged for its right partner "
                     f"and vice versa, the landmarks fit with RMS {check.mirrored_rms:.1f} mm instead of "
                     f"{landmark_rms:.1f} mm, at scale {check.mirrored_scale:.3f} instead of {transform.scale:.3f} "
                     "(pair left markers with left landmarks; if they are, the capture's frame is mirrored)")
    else:
        landmark_of = dict(usable)
        for marker, distance in check.standing_out.items():
            far = distance > thresholds.wrong_pair_mm and len(usable) >= thresholds.wrong_pair_min_pairs
            (wrong if far else extra).append(
                f"pair {marker!r} -> {landmark_of[marker]!r} stands out: the other pairs put {marker!r} "
                f"{distance:.1f} mm from {landmark_of[marker]!r}")
        worst = max(residuals, key=residuals.get)
        for limit, reasons in ((thresholds.wrong_landmark_rms_mm, wrong), (thresholds.landmark_rms_mm, extra)):
            if landmark_rms > limit:
                reasons.append(f"the landmarks fit with RMS {landmark_rms:.1f} mm > {limit:g} mm "
                               f"(worst: {worst!r}, {residuals[worst]:.1f} mm)")
                break
    quality = _assess(np.linalg.norm(embedding.offsets, axis=1), transform.scale, thresholds, names, extra, wrong)
    return CorrespondenceAlignment(transform, residuals, embedding, quality, check)


def check_pairs(source, target, markers, landmarks, model_landmarks, *, allow_scale=True,
                thresholds=QualityThresholds()) -> PairCheck:
    """How correspondences agree: pairs that stand out, and the fit of the mirrored assignment.

    source (k, 3) are the capture markers ``markers``, target (k, 3) their landmarks ``landmarks``.
    A pair stands out when the similarity fitted to the other pairs puts its marker more than
    ``stand_out_mm`` and more than ``stand_out_ratio`` times the others' residual from its
    landmark; that residual, per coordinate, is counted with the fit's degrees of freedom, so that
    few pairs, which a similarity fits closely, do not make every left-out pair look far. The worst
    such pair is set aside and the rest checked again, while the pairs left for a fit are at
    least MIN_CORRESPONDENCES - 1. The mirrored assignment exchanges every landmark named on one
    side (``*_left``, ``left_*``, ``*_L``, ...) for its partner of the other side, when the model
    has that partner.
    """
    keep = list(range(len(source)))
    standing_out = {}
    while len(keep) >= MIN_CORRESPONDENCES:
        distances, spreads = _left_out_errors(source[keep], target[keep], allow_scale)
        worst = int(np.argmax(distances / np.maximum(spreads, np.finfo(float).tiny)))
        if not (distances[worst] > thresholds.stand_out_mm
                and distances[worst] > thresholds.stand_out_ratio * spreads[worst]):
            break
        standing_out[markers[keep[worst]]] = float(distances[worst])
        del keep[worst]
    mirrored = [_mirror_name(landmark) for landmark in landmarks]
    mirrored = [other if other in model_landmarks else landmark for other, landmark in zip(mirrored, landmarks)]
    if mirrored == list(landmarks):
        return PairCheck(standing_out, None, None)
    fit = similarity_transform(source, np.array([model_landmarks[name] for name in mirrored], dtype=np.float64),
                               allow_scale=allow_scale)
    return PairCheck(standing_out, fit.rms, fit.scale)


def _left_out_errors(source, target, allow_scale):
    """For each pair: the distance of its transformed source from its target under the fit to the
    other pairs, and those pairs' residual per coordinate (root of the squared residuals' sum over
    the degrees of freedom left: 3 per point less 7, or 6 without scale)."""
    count = len(source)
    parameters = 7 if allow_scale else 6
    distances, spreads = np.empty(count), np.empty(count)
    for pair in range(count):
        others = np.arange(count) != pair
        fit = similarity_transform(source[others], target[others], allow_scale=allow_scale)
        squares = np.sum((fit.apply(source[others]) - target[others]) ** 2)
        distances[pair] = np.linalg.norm(fit.apply(source[pair]) - target[pair])
        spreads[pair] = np.sqrt(squares / max(3 * (count - 1) - parameters, 1))
    return distances, spreads


# One side of the face in a name: a word of its own (between separators such as _ - . or a space).
_SIDE = re.compile(r"(?<![A-Za-z0-9])(left|right|l|r)(?![A-Za-z0-9])", re.IGNORECASE)
_OTHER_SIDE = {"left": "right", "right": "left", "l": "r", "r": "l"}


def _mirror_name(name: str) -> str:
    """``name`` with left and right exchanged (case kept): mouth_corner_left -> mouth_corner_right,
    Cheek_L -> Cheek_R; unchanged without a side."""
    def other(match):
        word = match.group(0)
        swapped = _OTHER_SIDE[word.lower()]
        return swapped.upper() if word.isupper() else swapped.capitalize() if word[0].isupper() else swapped
    return _SIDE.sub(other, name)


def align_by_icp(capture_neutral, skin: SkinSurface, initial: Similarity | None = None, allow_scale=True,
                 *, trim_fraction=0.1, max_iterations=100, tolerance_mm=1e-4,
                 thresholds=QualityThresholds()) -> IcpAlignment:
    """Align a capture's neutral frame to the skin without names: similarity ICP.

    Gauss-Newton (point-to-plane) steps on the markers' distances to the skin, missing markers
    ignored, each step leaving out the worst ``trim_fraction`` of them as outliers (markers off the
    modelled skin, e.g. on a head band); scale is freed once a rigid fit has settled. Without
    ``initial`` the start is the rough pose that matches centroids and principal axes, tried with
    each of the 24 proper rotations mapping axes onto axes; the best fit wins, and another
    orientation fitting about as well makes the verdict doubtful. Iterations stop when no marker
    moves more than ``tolerance_mm``. The quality covers every present marker, trimmed or not.
    """
    markers = _as_points(capture_neutral, "capture_neutral")
    present = _finite_rows(markers)
    points = markers[present]
    n_kept = int(np.ceil((1.0 - trim_fraction) * len(points)))
    if n_kept < 7:
        raise AlignmentError(f"ICP needs at least 7 markers after trimming; {len(points)} are present "
                             f"in the neutral frame and {n_kept} would be kept")

    settings = dict(n_kept=n_kept, max_iterations=max_iterations, tolerance_mm=tolerance_mm,
                    scale_range=thresholds.scale_range)

    def fit_from(start):
        # Freeing the scale from a rough start would collapse the markers (shrunk onto one skin
        # point, every distance is zero). Near the right pose the true scale is a local minimum
        # the steps find, so the fit is rigid first and only then scaled.
        rigid = _icp(points, skin, start, scaled=False, warm_up=allow_scale, **settings)
        if not allow_scale:
            return rigid
        scaled = _icp(points, skin, rigid.transform, scaled=True, warm_up=False, **settings)
        return replace(scaled, iterations=rigid.iterations + scaled.iterations)

    starts = [initial] if initial is not None else _principal_axes_starts(points, skin)
    runs = [fit_from(start) for start in starts]
    low, high = thresholds.scale_range
    candidates = [run for run in runs if low <= run.transform.scale <= high] or runs
    best = min(candidates, key=lambda run: run.trimmed_rms)

    problems = [] if best.converged else ["ICP did not converge"]
    for run in candidates:
        other_pose = np.max(np.linalg.norm(run.transform.apply(points) - best.transform.apply(points), axis=1))
        if other_pose > thresholds.near_mm and run.trimmed_rms <= thresholds.rival_ratio * best.trimmed_rms:
            problems.append(f"a pose {other_pose:.0f} mm away fits about as well (trimmed RMS "
                            f"{run.trimmed_rms:.2f} mm against {best.trimmed_rms:.2f} mm): give an initial pose")
            break

    distances = np.full(len(markers), np.nan)
    distances[present] = skin.closest(best.transform.apply(points))[3]
    quality = _assess(distances, best.transform.scale, thresholds, None, problems)
    return IcpAlignment(best.transform, quality, best.iterations, best.converged)


def read_correspondence_file(path) -> dict[str, str]:
    """Capture marker -> model landmark, from a TOML or a two-column CSV file (by suffix).

    TOML: a ``[correspondence]`` table of ``capture_name = "landmark_name"``.
    CSV: rows ``capture_marker,model_landmark``; an optional header row with exactly those
    names, blank lines and lines starting with ``#`` are skipped.
    A marker or a landmark used twice is an error. Errors name the file and, where known, the line.
    """
    path, suffix, text = read_pair_file(path, "correspondence", AlignmentError)
    pairs = _toml_pairs(path, text) if suffix == ".toml" else _csv_pairs(path, text)
    if not pairs:
        raise AlignmentError(f"{path}: no correspondences")
    correspondence, first_use = {}, {}
    for line, marker, landmark in pairs:
        for kind, name in (("capture marker", marker), ("landmark", landmark)):
            if (kind, name) in first_use:
                raise AlignmentError(f"{_where(path, line)}: {kind} {name!r} is already used "
                                     f"({_where(path, first_use[kind, name])})")
            first_use[kind, name] = line
        correspondence[marker] = landmark
    return correspondence


def read_pair_file(path, what: str, error: type[Exception]) -> tuple[Path, str, str]:
    """Path, suffix (.toml or .csv) and UTF-8 text of a small name-pairs file; ``error`` names it."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in (".toml", ".csv"):
        raise error(f"{path}: unknown {what} file type {path.suffix!r} (use .toml or .csv)")
    try:
        return path, suffix, path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise error(f"{path}: no such file") from None
    except UnicodeDecodeError:
        raise error(f"{path}: not UTF-8 text") from None


def _toml_pairs(path, text):
    """(line or None, marker, landmark) from the [correspondence] table of a TOML file."""
    try:
        table = tomllib.loads(text).get("correspondence")
    except tomllib.TOMLDecodeError as error:  # its message gives the line and column
        raise AlignmentError(f"{path}: {error}") from None
    if not isinstance(table, dict):
        raise AlignmentError(f"{path}: no [correspondence] table")
    pairs = []
    for marker, landmark in table.items():
        line = _toml_key_line(text, marker)
        if not isinstance(landmark, str) or not landmark.strip() or not marker.strip():
            raise AlignmentError(f"{_where(path, line)}: expected capture_name = \"landmark_name\", "
                                 f"got {marker!r} = {landmark!r}")
        pairs.append((line, marker.strip(), landmark.strip()))
    return pairs


def _toml_key_line(text, key):
    """The line of ``key = ...`` in the [correspondence] table (tomllib keeps no positions)."""
    in_table = False
    for number, line in enumerate(text.splitlines(), start=1):
        stripped = line.strip()
        if stripped.startswith("["):
            in_table = stripped.split("#")[0].strip() == "[correspondence]"
        elif in_table and "=" in stripped:
            if stripped.split("=", 1)[0].strip().strip("\"'") == key:
                return number
    return None


def _csv_pairs(path, text):
    """(line, marker, landmark) from a two-column CSV file."""
    pairs = []
    reader = csv.reader(text.splitlines())
    for row in reader:
        cells = [cell.strip() for cell in row]
        if not any(cells) or cells[0].startswith("#"):
            continue
        if not pairs and [cell.lower() for cell in cells] == ["capture_marker", "model_landmark"]:
            continue
        if len(cells) != 2 or not all(cells):
            raise AlignmentError(f"{_where(path, reader.line_num)}: expected two names, "
                                 f"capture_marker,model_landmark; got {row}")
        pairs.append((reader.line_num, cells[0], cells[1]))
    return pairs


def _where(path, line):
    return f"{path}" if line is None else f"{path}, line {line}"


@dataclass(frozen=True, eq=False)
class _IcpRun:
    transform: Similarity
    trimmed_rms: float
    iterations: int
    converged: bool


@dataclass(frozen=True, eq=False)
class _Match:
    """The markers under a transform, matched to their closest skin points, the worst trimmed."""

    transform: Similarity
    moved: np.ndarray
    closest: np.ndarray
    normals: np.ndarray    # unit gradients of the distance to the skin at the moved markers
    kept: np.ndarray       # indices of the markers closest to the skin
    objective: float       # mean squared distance of the kept markers

    @classmethod
    def of(cls, transform, points, skin, n_kept):
        moved = transform.apply(points)
        triangle, _, closest, distance = skin.closest(moved)
        kept = np.argsort(distance)[:n_kept]
        # Off the skin the distance grows along moved - closest: the face normal where the closest
        # point is inside a face, but not where it is on an edge or a vertex. On the skin, where
        # that direction is rounding noise, the face normal gives the signed distance's gradient.
        off_skin = distance > 1e-9 * np.max(np.abs(moved))
        normals = skin.triangle_normals[triangle]
        normals[off_skin] = (moved - closest)[off_skin] / distance[off_skin, None]
        return cls(transform, moved, closest, normals, kept, float(np.mean(distance[kept] ** 2)))


def _icp(points, skin, start, *, scaled, warm_up, n_kept, max_iterations, tolerance_mm, scale_range) -> _IcpRun:
    """ICP from ``start``: rigid, or with scale if ``scaled``.

    Each iteration tries a Gauss-Newton step on the kept markers' distances (point-to-plane where
    the closest point is inside a face), fast near the solution but liable to overshoot far from
    it, then fractions of it, and falls back to the point-to-point step (Umeyama on the matched
    points) when none lowers the trimmed objective. That step never raises it: the kept markers
    move closer to their matches, and re-matching and re-trimming only lower it further.
    Iterations stop when no marker moves more than ``tolerance_mm``; for a ``warm_up`` (rigid
    before a scaled fit) as soon as an iteration gains little; and, with no convergence, when the
    scale leaves ``scale_range``: the markers are collapsing.
    """
    match = _Match.of(start, points, skin, n_kept)
    converged, iterations = False, 0
    while not converged and iterations < max_iterations:
        iterations += 1
        kept = match.kept
        plane_step = _PlaneStep.solve(match.moved[kept], match.closest[kept], match.normals[kept], scaled)
        for fraction in STEP_FRACTIONS:
            candidate = _Match.of(plane_step.similarity(fraction) @ match.transform, points, skin, n_kept)
            if candidate.objective < match.objective:
                break
        else:
            step = similarity_transform(match.moved[kept], match.closest[kept], allow_scale=scaled)
            candidate = _Match.of(step @ match.transform, points, skin, n_kept)
        converged = (np.max(np.linalg.norm(candidate.moved - match.moved, axis=1)) < tolerance_mm
                     or warm_up and candidate.objective > (1 - WARM_UP_DECREASE) * match.objective)
        match = candidate
        if not scale_range[0] <= match.transform.scale <= scale_range[1]:
            break
    return _IcpRun(match.transform, float(np.sqrt(match.objective)), iterations, converged)


@dataclass(frozen=True)
class _PlaneStep:
    """The Gauss-Newton step minimising sum (n . (step(x) - q))^2 over small similarities.

    step(x) = exp(log_scale) R(rotation_vector) (x - centre) + centre + shift, linearised as
    x + rotation_vector x arm + log_scale arm + shift with arm = x - centre. The centre is the
    points' mean, so that rotation and translation decouple.
    """

    centre: np.ndarray
    rotation_vector: np.ndarray
    log_scale: float
    shift: np.ndarray

    @classmethod
    def solve(cls, moved, closest, normals, scaled) -> _PlaneStep:
        centre = moved.mean(axis=0)
        arm = moved - centre
        # Columns scaled by the points' spread, so that all unknowns are lengths (conditioning).
        spread = np.sqrt(np.mean(np.sum(arm ** 2, axis=1)))
        columns = [np.cross(arm, normals) / spread]
        if scaled:
            columns.append(_dot(normals, arm)[:, None] / spread)
        columns.append(normals)
        solution = np.linalg.lstsq(np.hstack(columns), -_dot(normals, moved - closest), rcond=None)[0]
        return cls(centre, solution[:3] / spread, solution[3] / spread if scaled else 0.0, solution[-3:])

    def similarity(self, fraction=1.0) -> Similarity:
        """The step, or the given fraction of it."""
        rotation = Rotation.from_rotvec(fraction * self.rotation_vector).as_matrix()
        scale = np.exp(fraction * self.log_scale)
        return Similarity(scale, rotation, self.centre + fraction * self.shift - scale * rotation @ self.centre)


def _principal_axes_starts(points, skin) -> list[Similarity]:
    """Rough poses matching the markers' centroid and principal axes to the skin's, one per proper
    map of axes onto axes."""
    marker_centroid, marker_axes = _principal_axes(points.mean(axis=0), np.cov(points.T, bias=True))
    skin_centroid, skin_axes = _principal_axes(*_surface_moments(skin))
    starts = []
    for axis_map in PROPER_AXIS_MAPS:
        rotation = skin_axes @ axis_map @ marker_axes.T
        starts.append(Similarity(1.0, rotation, skin_centroid - rotation @ marker_centroid))
    return starts


def _principal_axes(centroid, covariance):
    """The centroid and the principal axes as columns, largest variance first, right-handed."""
    _, axes = np.linalg.eigh(covariance)
    axes = axes[:, ::-1]
    if np.linalg.det(axes) < 0:
        axes[:, 2] *= -1
    return centroid, axes


def _surface_moments(skin):
    """Centroid and covariance of the skin as a uniform sheet (exact triangle moments)."""
    corners = skin.points[skin.triangles]  # (m, 3 corners, 3)
    areas = skin.areas
    total = areas.sum()
    centroid = areas @ corners.mean(axis=1) / total
    # Integral over a triangle of x x^T dA = area / 12 * (sum of v v^T over corners + s s^T), s = corner sum.
    corner_sum = corners.sum(axis=1)
    second = (np.einsum("m,mki,mkj->ij", areas, corners, corners)
              + np.einsum("m,mi,mj->ij", areas, corner_sum, corner_sum)) / (12.0 * total)
    return centroid, second - np.outer(centroid, centroid)


def _assess(distances, scale, thresholds, names, problems, wrong=()) -> AlignmentQuality:
    """Summarise marker-to-skin distances and give the verdict: ``wrong`` (reasons found by the
    caller) and the tests of ``thresholds`` decide "wrong", ``problems`` and the rest "doubtful"."""
    present = np.isfinite(distances)
    found = distances[present]
    rms = float(np.sqrt(np.mean(found ** 2)))
    worst = int(np.flatnonzero(present)[np.argmax(found)])
    near_fraction = float(np.mean(found <= thresholds.near_mm))
    wrong = list(wrong)
    low, high = thresholds.wrong_scale_range
    if not low <= scale <= high:
        wrong.append(f"scale {scale:.3f} is far outside a face's range [{low:g}, {high:g}]: wrong units, or "
                     "markers that are not on this face")
    if rms > thresholds.wrong_rms_mm:
        wrong.append(f"markers are {rms:.1f} mm (RMS) from the skin, more than {thresholds.wrong_rms_mm:g} mm")
    reasons = list(problems)
    if thresholds.rms_mm < rms <= thresholds.wrong_rms_mm:
        reasons.append(f"markers are {rms:.1f} mm (RMS) from the skin, more than {thresholds.rms_mm:g} mm")
    if distances[worst] > thresholds.max_mm:
        label = repr(names[worst]) if names is not None else f"#{worst}"
        reasons.append(f"marker {label} is {distances[worst]:.1f} mm from the skin, more than {thresholds.max_mm:g} mm")
    if near_fraction < thresholds.min_near_fraction:
        reasons.append(f"only {100 * near_fraction:.0f}% of the markers are within {thresholds.near_mm:g} mm "
                       f"of the skin (want {100 * thresholds.min_near_fraction:.0f}%)")
    low, high = thresholds.scale_range
    if not low <= scale <= high and thresholds.wrong_scale_range[0] <= scale <= thresholds.wrong_scale_range[1]:
        reasons.append(f"scale {scale:.3f} is outside the plausible range [{low:g}, {high:g}]")
    level = "wrong" if wrong else "doubtful" if reasons else "good"
    return AlignmentQuality(distances, rms, float(distances[worst]), thresholds.near_mm, near_fraction, level,
                            tuple(wrong + reasons))


def _as_points(points, name) -> np.ndarray:
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise AlignmentError(f"{name} must have shape (n, 3), not {points.shape}")
    return points


def _finite_rows(points) -> np.ndarray:
    return np.all(np.isfinite(points), axis=1)


def _dot(u, v):
    return np.einsum("ij,ij->i", u, v)
