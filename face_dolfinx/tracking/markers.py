"""Which markers a fit follows, how strongly, in which groups, and which it leaves out to validate.

A marker setup file (TOML; ``run.py fit --marker-setup FILE``), after OpenSim's IK task sets:

    [groups]                      # named groups of capture markers (a marker in one group at most)
    eyelids = ["Leye_Up", "Leye_Down", "Reye_Up", "Reye_Down"]
    brows = ["Leyebrow_M", "Reyebrow_M"]

    [weights]                     # a marker or a group -> weight (default 1)
    eyelids = 0                   # 0: followed and reported, not fitted
    Chin = 2.0

    validation = ["NoseHead_L", "Chin_R2"]   # left out of the fit to measure prediction; or a count

A validation marker is embedded in the skin at the neutral frame like every other but has no weight
in the fit: its error measures how well the model predicts what it was not fitted to. A count picks
that many markers spread over the face (farthest-point order over the neutral frame, starting from
the marker farthest from the centroid), among those with a weight.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
import tomllib

import numpy as np


class MarkerSetupError(ValueError):
    """A marker setup that names unknown markers, or is malformed; the message names the file."""


@dataclass(frozen=True)
class MarkerSetup:
    weights: dict[str, float] = field(default_factory=dict)   # marker or group -> weight
    groups: dict[str, tuple[str, ...]] = field(default_factory=dict)
    validation: tuple[str, ...] | int = ()
    source: str = ""   # the file it came from, for messages

    @classmethod
    def read(cls, path) -> "MarkerSetup":
        path = Path(path)
        try:
            data = tomllib.loads(path.read_text())
        except FileNotFoundError:
            raise MarkerSetupError(f"{path}: no such marker setup file") from None
        except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as error:
            raise MarkerSetupError(f"{path}: not a TOML marker setup file ({error})") from None
        unknown = set(data) - {"groups", "weights", "validation"}
        if unknown:
            raise MarkerSetupError(f"{path}: unknown entries {', '.join(sorted(unknown))} "
                                   f"(a marker setup has [groups], [weights] and validation)")
        groups, weights, validation = data.get("groups", {}), data.get("weights", {}), data.get("validation", [])
        if not all(isinstance(members, list) and all(isinstance(m, str) for m in members)
                   for members in groups.values()):
            raise MarkerSetupError(f"{path}: each group must be a list of marker names")
        if not all(isinstance(w, (int, float)) and not isinstance(w, bool) and w >= 0 for w in weights.values()):
            raise MarkerSetupError(f"{path}: weights must be numbers, 0 or more")
        if not (isinstance(validation, int) and not isinstance(validation, bool) and validation >= 0
                or isinstance(validation, list) and all(isinstance(m, str) for m in validation)):
            raise MarkerSetupError(f"{path}: validation must be a list of marker names or a count")
        return cls({k: float(v) for k, v in weights.items()}, {k: tuple(v) for k, v in groups.items()},
                   validation if isinstance(validation, int) else tuple(validation), str(path))

    def with_validation(self, validation: tuple[str, ...] | int) -> "MarkerSetup":
        return MarkerSetup(self.weights, self.groups, validation, self.source)

    def record(self) -> dict:
        """What changes the fit, for the run record."""
        return dict(weights=self.weights, groups={k: list(v) for k, v in self.groups.items()},
                    validation=self.validation if isinstance(self.validation, int) else list(self.validation))

    def resolve(self, names: list[str], neutral: np.ndarray) -> tuple[np.ndarray, list[str], list[str | None]]:
        """Per marker of ``names``: its weight in the fit (0 for validation markers), its role
        (``results.accuracy.ROLES``) and its group. ``neutral`` (markers, 3) places a validation
        count over the face."""
        where = f"{self.source}: " if self.source else ""
        index = {name: i for i, name in enumerate(names)}
        group_of: list[str | None] = [None] * len(names)
        for group, members in self.groups.items():
            if group in index:
                raise MarkerSetupError(f"{where}group {group!r} has the name of a marker")
            for member in members:
                _check_known(member, index, where, f"group {group!r}")
                if group_of[index[member]] is not None:
                    raise MarkerSetupError(f"{where}marker {member!r} is in groups {group_of[index[member]]!r} "
                                           f"and {group!r}")
                group_of[index[member]] = group
        weights = np.ones(len(names))
        for key, weight in self.weights.items():
            if key in self.groups:
                weights[[index[m] for m in self.groups[key]]] = weight
        for key, weight in self.weights.items():  # a marker's own weight wins over its group's
            if key not in self.groups:
                _check_known(key, index, where, "[weights]")
                weights[index[key]] = weight
        if isinstance(self.validation, int):
            candidates = np.flatnonzero(weights > 0)
            if self.validation >= len(candidates):
                raise MarkerSetupError(f"{where}{self.validation} validation markers would leave "
                                       f"{len(candidates) - self.validation} to fit")
            validation = [names[i] for i in spread_out(neutral[candidates], self.validation, candidates)]
        else:
            validation = list(self.validation)
            for name in validation:
                _check_known(name, index, where, "validation")
        roles = ["fitted" if w > 0 else "ignored" for w in weights]
        for name in validation:
            roles[index[name]], weights[index[name]] = "validation", 0.0
        if not (weights > 0).any():
            raise MarkerSetupError(f"{where}no marker is left to fit")
        return weights, roles, group_of


def spread_out(points: np.ndarray, count: int, labels: np.ndarray) -> list[int]:
    """``count`` of ``labels`` whose ``points`` spread over the set: farthest-point order from the
    point farthest from the centroid; points with a NaN are never picked."""
    usable = np.all(np.isfinite(points), axis=1)
    if count == 0:
        return []

    def distance_to(point):
        return np.where(usable, np.linalg.norm(points - point, axis=1), -np.inf)
    picked = [int(np.argmax(distance_to(np.mean(points[usable], axis=0))))]
    distance = distance_to(points[picked[0]])
    for _ in range(count - 1):
        distance[picked] = -np.inf
        picked.append(int(np.argmax(distance)))
        distance = np.minimum(distance, distance_to(points[picked[-1]]))
    return [int(labels[i]) for i in picked]


def _check_known(name: str, index: dict, where: str, entry: str) -> None:
    if name not in index:
        raise MarkerSetupError(f"{where}{entry} names marker {name!r}, which the capture does not have")
