"""Regional material overrides: flesh parameters scaled or replaced in a part of the model.

A surgeon-planner softens the nose cartilage or stiffens a scar; an animator softens the cheeks to
see them swing. An override names a region, a muscle's cells (``muscle:NAME``), a sphere
(``sphere:X,Y,Z,R``) or a box (``box:X0,Y0,Z0,X1,Y1,Z1``) in model coordinates (mm; a cell
belongs to a sphere or box when its midpoint does), and what happens to the flesh there:

- ``scale``: factors (> 0) of ``mu10``, ``mu01`` (Mooney-Rivlin, kPa), ``kappa`` (volumetric,
  kPa) and ``passive`` (the passive fibre curves of the muscles in the region); ``all`` scales
  the four together, which keeps the Poisson ratio;
- ``value``: new values (> 0, kPa) of ``mu10``, ``mu01``, ``kappa``.

Overrides apply in order (a later one acts on what the earlier ones left). ``FaceModel.with_material``
attaches them to a model; ``FaceProblem`` turns them into the cellwise (DG0) material fields of its
forms, so a uniform model and an overridden one compile the same kernels.

On the command line an override is ``REGION:PARAM=FACTOR[,PARAM=FACTOR...]`` (scales), e.g.
``sphere:0,95,20,12:all=0.3``; a TOML file holds a list of them (``read_material_file``)::

    [[region]]
    sphere = [0.0, 95.0, 20.0, 12.0]
    scale = { all = 0.3 }

    [[region]]
    muscle = "mentalis_left"
    value = { mu10 = 120.0 }
"""
from dataclasses import dataclass, field
import math
from pathlib import Path
import tomllib

import numpy as np

SCALED_PARAMETERS = ("mu10", "mu01", "kappa", "passive")
VALUED_PARAMETERS = ("mu10", "mu01", "kappa")
REGION_KINDS = ("muscle", "sphere", "box")


class MaterialError(ValueError):
    """A material override is malformed or names what the model does not have."""


@dataclass(frozen=True)
class Region:
    """Cells of the model: a muscle's (``name``), or those whose midpoint lies in a sphere
    (``numbers`` = centre, radius) or a box (``numbers`` = lower corner, upper corner)."""

    kind: str
    name: str = ""
    numbers: tuple = ()

    def __post_init__(self):
        if self.kind not in REGION_KINDS:
            raise MaterialError(f"region {self.kind!r}: give one of {', '.join(REGION_KINDS)}")
        counts = {"muscle": 0, "sphere": 4, "box": 6}
        if len(self.numbers) != counts[self.kind] or not all(math.isfinite(x) for x in self.numbers):
            shape = {"muscle": "muscle:NAME", "sphere": "sphere:X,Y,Z,R", "box": "box:X0,Y0,Z0,X1,Y1,Z1"}
            raise MaterialError(f"region {self.describe()}: give {shape[self.kind]} (finite numbers, mm)")
        if self.kind == "muscle" and not self.name:
            raise MaterialError("region muscle: give muscle:NAME")
        if self.kind == "sphere" and not self.numbers[3] > 0:
            raise MaterialError(f"region {self.describe()}: the radius must be positive")
        if self.kind == "box" and not all(a < b for a, b in zip(self.numbers[:3], self.numbers[3:])):
            raise MaterialError(f"region {self.describe()}: each lower corner coordinate must lie below the upper one")

    def describe(self) -> str:
        if self.kind == "muscle":
            return f"muscle:{self.name}"
        return f"{self.kind}:" + ",".join(f"{x:g}" for x in self.numbers)

    def cells(self, model, midpoints: np.ndarray) -> np.ndarray:
        """Local cells (indices into ``midpoints``, the midpoints of the rank's owned and ghost
        cells) in the region."""
        if self.kind == "muscle":
            muscle = model.muscles[model.muscle_index(self.name)]
            return np.asarray(muscle.cells, dtype=np.int64)[np.asarray(muscle.fraction) > 0]
        numbers = np.asarray(self.numbers)
        if self.kind == "sphere":
            inside = np.linalg.norm(midpoints - numbers[:3], axis=1) <= numbers[3]
        else:
            inside = np.all((midpoints >= numbers[:3]) & (midpoints <= numbers[3:]), axis=1)
        return np.flatnonzero(inside)


@dataclass(frozen=True)
class MaterialOverride:
    """Flesh parameters scaled (``scale``) and/or replaced (``value``) in a region (module docstring)."""

    region: Region
    scale: dict = field(default_factory=dict)
    value: dict = field(default_factory=dict)

    def __post_init__(self):
        where = self.region.describe()
        if not self.scale and not self.value:
            raise MaterialError(f"material override of {where}: give at least one PARAM=FACTOR")
        for table, known in ((self.scale, SCALED_PARAMETERS + ("all",)), (self.value, VALUED_PARAMETERS)):
            for name, number in table.items():
                if name not in known:
                    raise MaterialError(f"material override of {where}: unknown parameter {name!r}; "
                                        f"known: {', '.join(known)}")
                if isinstance(number, bool) or not isinstance(number, (int, float)) or not (
                        math.isfinite(number) and number > 0):
                    raise MaterialError(f"material override of {where}: {name} must be a positive number, "
                                        f"not {number!r}")

    def factors(self) -> dict:
        """The scale factor of each of SCALED_PARAMETERS (``all`` expanded)."""
        every = self.scale.get("all", 1.0)
        return {name: every * self.scale.get(name, 1.0) for name in SCALED_PARAMETERS}

    def describe(self) -> dict:
        """For run.json and summary.json."""
        return dict(region=self.region.describe(), scale=dict(self.scale), value=dict(self.value))


def parse_region(text: str) -> Region:
    """``muscle:NAME``, ``sphere:X,Y,Z,R`` or ``box:X0,Y0,Z0,X1,Y1,Z1``."""
    kind, _, rest = text.strip().partition(":")
    if kind == "muscle":
        return Region("muscle", name=rest.strip())
    try:
        numbers = tuple(float(x) for x in rest.split(",")) if rest.strip() else ()
    except ValueError:
        raise MaterialError(f"region {text!r}: the coordinates must be numbers (mm)") from None
    return Region(kind, numbers=numbers)


def parse_material_option(text: str) -> MaterialOverride:
    """``REGION:PARAM=FACTOR[,PARAM=FACTOR...]`` (the ``--material`` option): scales."""
    region_text, _, changes = text.rpartition(":")
    if not region_text or "=" not in changes:
        raise MaterialError(f"--material {text!r}: give REGION:PARAM=FACTOR[,...], e.g. sphere:0,95,20,12:all=0.3 "
                            f"or muscle:mentalis_left:passive=2")
    scale = {}
    for item in filter(None, (part.strip() for part in changes.split(","))):
        name, _, number = item.partition("=")
        try:
            scale[name.strip()] = scale.get(name.strip(), 1.0) * float(number)
        except ValueError:
            raise MaterialError(f"--material {text!r}: {item!r} is not PARAM=FACTOR") from None
    return MaterialOverride(parse_region(region_text), scale)


def read_material_file(path) -> list[MaterialOverride]:
    """The ``[[region]]`` tables of a TOML file (module docstring)."""
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text())
    except OSError as error:
        raise MaterialError(f"{path}: cannot read: {error.strerror}") from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as error:
        raise MaterialError(f"{path}: malformed TOML: {error}") from None
    entries = data.get("region")
    if not isinstance(entries, list) or not entries or set(data) != {"region"}:
        raise MaterialError(f"{path}: give one or more [[region]] tables and nothing else")
    overrides = []
    for number, entry in enumerate(entries, start=1):
        where = f"{path}: region {number}"
        kinds = [kind for kind in REGION_KINDS if kind in entry]
        unknown = set(entry) - set(REGION_KINDS) - {"scale", "value"}
        if len(kinds) != 1 or unknown:
            raise MaterialError(f"{where}: give exactly one of {', '.join(REGION_KINDS)}, and scale and/or value"
                                + (f" (unknown keys: {', '.join(sorted(unknown))})" if unknown else ""))
        kind = kinds[0]
        try:
            if kind == "muscle":
                region = Region("muscle", name=str(entry["muscle"]))
            else:
                region = Region(kind, numbers=tuple(float(x) for x in entry[kind]))
            overrides.append(MaterialOverride(region, dict(entry.get("scale", {})), dict(entry.get("value", {}))))
        except (MaterialError, TypeError, ValueError) as error:
            raise MaterialError(f"{where}: {error}") from None
    return overrides


def material_fields(model, midpoints: np.ndarray) -> dict[str, np.ndarray]:
    """The cellwise material of ``model`` with its overrides: mu10, mu01, kappa (kPa) and the
    passive fibre scale per local cell (``midpoints``: the rank's owned and ghost cells). A
    region with no cell on any rank is checked by the caller (it needs the communicator)."""
    count = len(midpoints)
    fields = {name: np.full(count, float(model.material[name])) for name in VALUED_PARAMETERS}
    fields["passive"] = np.ones(count)
    for override in model.material_overrides:
        cells = override.region.cells(model, midpoints)
        for name, factor in override.factors().items():
            fields[name][cells] *= factor
        for name, number in override.value.items():
            fields[name][cells] = float(number)
    return fields
