"""Reading the face description (meshes/builtin_face.toml) into typed, checked objects.

The file holds every number of the built-in face; this module only gives them names and checks
their types, so that a typo fails here with the file and key named instead of deep inside the
generator. Angles are degrees, lengths mm, as in the file.
"""
import tomllib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .shape import LAYERS, FaceShape, Feature, Table

MUSCLE_KINDS = ("linear", "sheet", "sphincter")
ANCHORS = ("mouth_corner", "eye_inner_corner", "eye_outer_corner")


class DescriptionError(ValueError):
    """The face description file is missing, malformed or inconsistent."""


@dataclass(frozen=True)
class Refinement:
    factor: float   # relative element size at the refined feature
    radius: float   # mm over which the size blends back to the global size


@dataclass(frozen=True)
class MeshSettings:
    refine_mouth: Refinement
    refine_eyes: Refinement
    refine_markers: Refinement
    layers_per_cube_root_ktets: float
    min_layers: int
    max_layers: int

    def layers(self, target_tets: int) -> int:
        """Number of tetrahedron layers through the thickness for a target tet count."""
        layers = round(self.layers_per_cube_root_ktets * (target_tets / 1000.0) ** (1.0 / 3.0))
        return int(np.clip(layers, self.min_layers, self.max_layers))


@dataclass(frozen=True)
class Mouth:
    center: tuple[float, float]
    half_width: float   # degrees
    opening: float      # mm on the skin at the centre


@dataclass(frozen=True)
class Eye:
    inner_corner: tuple[float, float]
    outer_corner: tuple[float, float]
    upper_height: float
    lower_height: float


@dataclass(frozen=True)
class Attachments:
    cranium: np.ndarray     # (k, 2) polygons in (theta, phi), left half
    mandible: np.ndarray
    oral: np.ndarray        # the free inner surface inside it faces the mouth's air
    eye_margin: float       # degrees


@dataclass(frozen=True)
class Jaw:
    condyle_left: np.ndarray
    slide_direction: np.ndarray
    track_length: float
    max_opening_sine: float


@dataclass(frozen=True)
class DentalArch:
    """The teeth and gum of one jaw: a curved plate over a (theta, phi) window behind the lips."""

    theta: tuple[float, float]   # degrees
    phi: tuple[float, float]     # degrees


@dataclass(frozen=True)
class Teeth:
    upper: DentalArch            # on the cranium
    lower: DentalArch            # on the mandible
    clearance: float             # mm from the inner surface of the flesh, along the rays
    depth: float                 # mm, the plates' thickness along the rays
    spacing: float               # mm, the triangles' size


@dataclass(frozen=True)
class MuscleSpec:
    """One muscle of the description (before mirroring and splitting)."""

    name: str
    kind: str
    mirror: bool
    path: np.ndarray | None = None          # linear: (k, 3) (theta, phi, t)
    radius: tuple[float, float] | None = None
    polygon: np.ndarray | None = None       # sheet: (k, 2)
    direction: tuple[float, float] | None = None
    center: tuple[float, float] | None = None   # sphincter
    semi_axes: tuple[float, float] | None = None
    depth: tuple[float, float] | None = None    # sheet, sphincter
    split: tuple[str, ...] = ()
    peak_stress: float | None = None


@dataclass(frozen=True)
class SiteGroup:
    """Named skin sites: explicit (theta, phi) points or anchors, optionally mirrored."""

    name: str
    mirror: bool
    at: tuple   # of (theta, phi) tuples or anchor names

    def named_sites(self) -> list[tuple[str, object, bool]]:
        """(name, location, mirrored) in file order: left before right for mirrored groups."""
        single = len(self.at) == 1
        sites = []
        for side, mirrored in ((("left", False), ("right", True)) if self.mirror else ((None, False),)):
            for i, location in enumerate(self.at, start=1):
                parts = [self.name] + ([side] if side else []) + ([] if single else [str(i)])
                sites.append(("_".join(parts), location, mirrored))
        return sites


@dataclass(frozen=True)
class Description:
    path: Path
    text: bytes          # the raw file, for the cache key
    shape: FaceShape
    theta_range: tuple[float, float]
    phi_range: tuple[float, float]
    mouth: Mouth
    eye: Eye
    mesh: MeshSettings
    attachments: Attachments
    jaw: Jaw
    teeth: Teeth
    material: dict[str, float]
    muscles: tuple[MuscleSpec, ...]
    markers: tuple[SiteGroup, ...]
    landmarks: tuple[SiteGroup, ...]
    expressions: dict[str, dict[str, float]]


def load_description(path: Path) -> Description:
    path = Path(path)
    try:
        text = path.read_bytes()
        data = tomllib.loads(text.decode())
    except (OSError, tomllib.TOMLDecodeError, UnicodeDecodeError) as error:
        raise DescriptionError(f"{path}: {error}") from error
    read = _Reader(path)
    head, thickness = read.table(data, "head"), read.table(data, "thickness")
    shape = FaceShape(
        center=read.vector(head, "center", 3),
        half_breadth=read.curve(head, "half_breadth"),
        front_depth=read.curve(head, "front_depth"),
        breadth_exponent=read.number(head, "breadth_exponent"),
        top=read.number(head, "top"),
        bottom=read.number(head, "bottom"),
        vertical_exponent=read.number(head, "vertical_exponent"),
        base_thickness=read.number(thickness, "base"),
        min_thickness=read.number(thickness, "min"),
        features=tuple(read.feature(f) for f in read.sequence(data, "features")))
    domain, mouth, eye = read.table(data, "domain"), read.table(data, "mouth"), read.table(data, "eye")
    mesh, attachments, jaw = read.table(data, "mesh"), read.table(data, "attachments"), read.table(data, "jaw")
    return Description(
        path=path, text=text, shape=shape,
        theta_range=tuple(read.vector(domain, "theta", 2)),
        phi_range=tuple(read.vector(domain, "phi", 2)),
        mouth=Mouth(tuple(read.vector(mouth, "center", 2)), read.number(mouth, "half_width"),
                    read.number(mouth, "opening")),
        eye=Eye(tuple(read.vector(eye, "inner_corner", 2)), tuple(read.vector(eye, "outer_corner", 2)),
                read.number(eye, "upper_height"), read.number(eye, "lower_height")),
        mesh=MeshSettings(
            **{key: read.refinement(mesh, key) for key in ("refine_mouth", "refine_eyes", "refine_markers")},
            layers_per_cube_root_ktets=read.number(mesh, "layers_per_cube_root_ktets"),
            min_layers=int(read.number(mesh, "min_layers")), max_layers=int(read.number(mesh, "max_layers"))),
        attachments=Attachments(read.points(attachments, "cranium", 2), read.points(attachments, "mandible", 2),
                                read.points(attachments, "oral", 2), read.number(attachments, "eye_margin")),
        jaw=Jaw(read.vector(jaw, "condyle_left", 3), read.vector(jaw, "slide_direction", 3),
                read.number(jaw, "track_length"), read.number(jaw, "max_opening_sine")),
        teeth=read.teeth(read.table(data, "teeth")),
        material={key: read.number(read.table(data, "material"), key) for key in read.table(data, "material")},
        muscles=tuple(read.muscle(m) for m in read.sequence(data, "muscles")),
        markers=read.sites(data, "markers"),
        landmarks=read.sites(data, "landmarks"),
        expressions={name: {key: read.number(table, key) for key in table}
                     for name, table in read.table(data, "expressions").items()})


class _Reader:
    """Typed access to the parsed TOML that names the file and key on error."""

    def __init__(self, path: Path):
        self.path = path

    def fail(self, message: str):
        raise DescriptionError(f"{self.path}: {message}")

    def get(self, table: dict, key: str):
        if key not in table:
            self.fail(f"missing key {key!r}")
        return table[key]

    def table(self, table: dict, key: str) -> dict:
        value = self.get(table, key)
        if not isinstance(value, dict):
            self.fail(f"{key!r} must be a table")
        return value

    def sequence(self, table: dict, key: str) -> list:
        value = self.get(table, key)
        if not isinstance(value, list):
            self.fail(f"{key!r} must be an array")
        return value

    def number(self, table: dict, key: str) -> float:
        value = self.get(table, key)
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            self.fail(f"{key!r} must be a number, got {value!r}")
        return float(value)

    def points(self, table: dict, key: str, dim: int) -> np.ndarray:
        try:
            value = np.asarray(self.get(table, key), dtype=float)
        except (TypeError, ValueError):
            self.fail(f"{key!r} must be numbers")
        if value.ndim != 2 or value.shape[1] != dim:
            self.fail(f"{key!r} must be a list of {dim}-vectors")
        return value

    def vector(self, table: dict, key: str, dim: int) -> np.ndarray:
        return self.points({key: [self.get(table, key)]}, key, dim)[0]

    def curve(self, table: dict, key: str) -> Table:
        curve = self.table(table, key)
        try:
            x = np.asarray(self.get(curve, "phi"), dtype=float)
            y = np.asarray(self.get(curve, "value"), dtype=float)
        except (TypeError, ValueError):
            self.fail(f"{key!r}: phi and value must be numbers")
        if x.shape != y.shape or x.ndim != 1 or np.any(np.diff(x) <= 0):
            self.fail(f"{key!r}: phi must increase and match value in length")
        return Table(tuple(x), tuple(y))

    def teeth(self, table: dict) -> Teeth:
        arches = {}
        for key in ("upper", "lower"):
            arch = self.table(table, key)
            theta, phi = tuple(self.vector(arch, "theta", 2)), tuple(self.vector(arch, "phi", 2))
            if not (theta[0] < theta[1] and phi[0] < phi[1]):
                self.fail(f"teeth.{key}: theta and phi must be increasing ranges")
            arches[key] = DentalArch(theta, phi)
        sizes = {key: self.number(table, key) for key in ("clearance", "depth", "spacing")}
        if min(sizes.values()) <= 0.0:
            self.fail(f"teeth: clearance, depth and spacing must be positive, got {sizes}")
        return Teeth(**arches, **sizes)

    def refinement(self, table: dict, key: str) -> Refinement:
        entry = self.table(table, key)
        return Refinement(self.number(entry, "factor"), self.number(entry, "radius"))

    def feature(self, entry: dict) -> Feature:
        name = self.get(entry, "name")
        layer = self.get(entry, "layer")
        if layer not in LAYERS:
            self.fail(f"feature {name!r}: layer must be one of {LAYERS}, got {layer!r}")
        return Feature(name=name, layer=layer,
                       start=tuple(self.vector(entry, "start", 2)), end=tuple(self.vector(entry, "end", 2)),
                       amplitude=tuple(self.vector(entry, "amplitude", 2)),
                       width=tuple(self.vector(entry, "width", 2)),
                       stretch=tuple(self.vector(entry, "stretch", 2)) if "stretch" in entry else (1.0, 1.0),
                       power=self.number(entry, "power") if "power" in entry else 2.0,
                       mirror=bool(entry.get("mirror", False)))

    def muscle(self, entry: dict) -> MuscleSpec:
        name, kind = self.get(entry, "name"), self.get(entry, "kind")
        if kind not in MUSCLE_KINDS:
            self.fail(f"muscle {name!r}: kind must be one of {MUSCLE_KINDS}, got {kind!r}")
        common = dict(name=name, kind=kind, mirror=bool(entry.get("mirror", False)),
                      peak_stress=self.number(entry, "peak_stress") if "peak_stress" in entry else None)
        if kind == "linear":
            path = self.points(entry, "path", 3)
            if len(path) < 2:
                self.fail(f"muscle {name!r}: path needs an origin and an insertion")
            return MuscleSpec(**common, path=path, radius=tuple(self.vector(entry, "radius", 2)))
        depth = tuple(self.vector(entry, "depth", 2))
        if kind == "sheet":
            return MuscleSpec(**common, polygon=self.points(entry, "polygon", 2), depth=depth,
                              direction=tuple(self.vector(entry, "direction", 2)))
        split = tuple(entry.get("split", ()))
        pairs = ({"upper", "lower"}, {"left", "right"})
        if not set(split) <= set.union(*pairs) or any(len(pair & set(split)) == 1 for pair in pairs):
            self.fail(f"muscle {name!r}: split may only name the pairs upper, lower and left, right")
        return MuscleSpec(**common, center=tuple(self.vector(entry, "center", 2)),
                          semi_axes=tuple(self.vector(entry, "semi_axes", 2)), depth=depth, split=split)

    def sites(self, data: dict, key: str) -> tuple[SiteGroup, ...]:
        groups = []
        for name, entry in self.table(data, key).items():
            at = []
            for location in self.sequence(entry, "at"):
                if isinstance(location, str):
                    if location not in ANCHORS:
                        self.fail(f"{key}.{name}: unknown anchor {location!r}; known: {ANCHORS}")
                    at.append(location)
                else:
                    at.append(tuple(self.vector({"at": location}, "at", 2)))
            groups.append(SiteGroup(name, bool(entry.get("mirror", False)), tuple(at)))
        return tuple(groups)
