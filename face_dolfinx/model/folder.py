"""The face model folder (docs/model_format.md): the one place that reads and writes it.

``load_model`` reads a folder on any number of MPI ranks (the mesh is distributed by DOLFINx)
and checks every part, raising ``ModelError`` with the file and the problem named. It is
collective: every check that depends on the distributed mesh is reduced over the ranks, so all
ranks raise together. ``read_model_arrays`` reads a folder serially as plain arrays in the
file's numbering (``ModelArrays``), for work on the whole model in one process (subject
adaptation, the fit report). ``write_model`` writes a folder from plain arrays (serially); the
built-in face generator (``face_dolfinx.model.anatomy``) uses it, and so can a user converting
their own model. ``skin_triangles`` is the one extraction of the skin surface.
"""

import difflib
import math
import re
import tomllib
from dataclasses import dataclass, field, fields, replace
from functools import cached_property
from pathlib import Path

import h5py
import numpy as np
from mpi4py import MPI
# Imported with the module, on every rank: importing DOLFINx initialises PETSc, which is collective
# over COMM_WORLD, so it must not first happen inside rank-0-only work (the face generator loads
# the model it built on rank 0 alone while the other ranks wait).
from dolfinx import cpp as dolfinx_cpp, io as dolfinx_io, mesh as dolfinx_mesh
import scipy.sparse as sp
from scipy.sparse.csgraph import reverse_cuthill_mckee
import ufl

from face_dolfinx.alignment.surface import SkinSurface
from face_dolfinx.model.surface_file import read_triangle_surface, write_triangle_surface
from face_dolfinx.parallel import on_rank_0

MODEL_FILE, MESH_FILE, HEAVY_FILE, MUSCLES_FILE = "model.toml", "mesh.xdmf", "mesh.h5", "muscles.npz"
MESH_NAME, TAGS_NAME = "flesh", "boundaries"
BOUNDARY_NAMES = ("cranium", "mandible", "skin", "free")
# Optional tags: "oral", the free inner surface that faces the mouth's air (intraoral pressure).
OPTIONAL_BOUNDARY_NAMES = ("oral",)
MATERIAL_KEYS = ("mu10", "mu01", "kappa", "fiber_stress")
# Optional rigid teeth (closed triangle surfaces), one per bone frame they move with.
TEETH_BONES = ("cranium", "mandible")
MUSCLE_KINDS = ("linear", "sphincter")
UNIT_TOLERANCE = 1e-6        # |fiber| must be 1 to this
MARKER_TOLERANCE = 1.0       # mm: markers must lie this close to the skin
# Faces of a tet as local node triples; face k is opposite node k.
TET_FACES = np.array([[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]])
# Tet quality 6 sqrt(2) V / l_rms^3: 1 for the regular tet, 0 for a flat one. Below this a tet is
# called degenerate: its stiffness would be meaningless and its Jacobian ill-conditioned.
DEGENERATE_QUALITY = 1e-3


class ModelError(ValueError):
    """A model folder is missing, malformed or inconsistent. The message names file and problem."""


@dataclass
class Muscle:
    name: str
    kind: str                 # "linear" or "sphincter"
    peak_stress: float | None  # sigma_max in kPa; None means the model's material.fiber_stress
    cells: np.ndarray         # (k,) int32 LOCAL cell indices (owned and ghost) on this rank
    fraction: np.ndarray      # (k,) volume fraction in (0, 1]
    fiber: np.ndarray         # (k, 3) unit rest fiber direction
    # Optional points from model.toml for documentation and rendering (mm): origin/insertion
    # of a linear muscle, center/axis of a sphincter.
    geometry: dict[str, np.ndarray] = field(default_factory=dict)


@dataclass(frozen=True)
class JawGeometry:
    """Temporomandibular joint in the cranium frame at rest (sifakis2005 section 8)."""

    condyle_right: np.ndarray
    condyle_left: np.ndarray
    u: np.ndarray                 # right -> left condyle, unit
    v: np.ndarray                 # sliding direction, back to front, unit, orthogonal to u
    w: np.ndarray                 # v x u
    midpoint: np.ndarray          # m
    condyle_distance: float       # l
    track_length: float           # d (mm)
    max_opening_sine: float       # s

    @classmethod
    def from_condyles(cls, condyle_right, condyle_left, slide_direction, track_length: float,
                      max_opening_sine: float) -> "JawGeometry":
        """Derive u, v, w, m, l. The slide direction loses any component along u."""
        right, left = np.asarray(condyle_right, float), np.asarray(condyle_left, float)
        axis = left - right
        distance = float(np.linalg.norm(axis))
        if distance == 0:
            raise ValueError("the two condyles coincide")
        u = axis / distance
        v = np.asarray(slide_direction, float)
        v = v - (v @ u) * u
        if np.linalg.norm(v) < 1e-9:
            raise ValueError("slide_direction is parallel to the condyle axis")
        if not track_length > 0 or not 0 < max_opening_sine <= 1:
            raise ValueError("track_length must be > 0 and max_opening_sine in (0, 1]")
        v = v / np.linalg.norm(v)
        return cls(right, left, u, v, np.cross(v, u), 0.5 * (right + left), distance,
                   float(track_length), float(max_opening_sine))


@dataclass
class FaceModel:
    path: Path
    name: str
    mesh: object                      # dolfinx.mesh.Mesh, distributed over comm
    facet_tags: object                # dolfinx MeshTags on facets
    boundary_ids: dict[str, int]
    muscles: list[Muscle]
    jaw: JawGeometry
    markers: dict[str, np.ndarray]
    landmarks: dict[str, np.ndarray]
    material: dict[str, float]
    expressions: dict[str, dict]
    # Regional material overrides (``with_material``, ``face_dolfinx.model.regions``), in order.
    material_overrides: tuple = ()
    # {bone: (points (n, 3) mm, outward triangles (m, 3))} in the bone's rest frame, on every rank.
    teeth: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)

    @property
    def muscle_names(self) -> list[str]:
        return [m.name for m in self.muscles]

    def muscle_index(self, name: str) -> int:
        names = self.muscle_names
        if name in names:
            return names.index(name)
        close = difflib.get_close_matches(name, names, n=4, cutoff=0.5)
        hint = f"; did you mean {', '.join(close)}?" if close else f"; known: {', '.join(names)}"
        raise ModelError(f"{self.path}: unknown muscle {name!r}{hint}")

    def peak_stress(self, index: int) -> float:
        """sigma_max of muscle ``index`` (kPa): its own value or the model's default fiber stress."""
        own = self.muscles[index].peak_stress
        return own if own is not None else self.material.get("fiber_stress", 300.0)

    def with_strength(self, scales: dict[str, float]) -> "FaceModel":
        """This model with muscles' peak stresses scaled, i.e. their force-length curves: how
        sifakis2005 section 9 exaggerates an expression beyond the physical range, never by an
        activation above 1. ``scales``: {muscle name: factor}, the key "all" for every muscle
        (factors multiply); each factor > 0."""
        factors = np.ones(len(self.muscles))
        for name, factor in scales.items():
            if not (np.isfinite(factor) and factor > 0):
                raise ModelError(f"{self.path}: strength of {name} must be a positive number, not {factor!r}")
            if name == "all":
                factors *= factor
            else:
                factors[self.muscle_index(name)] *= factor
        muscles = [replace(muscle, peak_stress=factor * self.peak_stress(index))
                   for index, (muscle, factor) in enumerate(zip(self.muscles, factors))]
        return replace(self, muscles=muscles)

    def with_material(self, overrides) -> "FaceModel":
        """This model with regional material overrides (``face_dolfinx.model.regions``) after its
        own: softer or stiffer flesh in a muscle's cells, a sphere or a box. Collective: a region
        naming an unknown muscle, or holding no cell of the mesh, raises ModelError here, before
        any solve."""
        overrides = tuple(overrides)
        midpoints = cell_midpoints(self.mesh)
        for override in overrides:
            region = override.region
            if region.kind == "muscle":
                self.muscle_index(region.name)
            owned = region.cells(self, midpoints)
            owned = owned[owned < self.mesh.topology.index_map(3).size_local]
            if self.mesh.comm.allreduce(len(owned), op=MPI.SUM) == 0:
                raise ModelError(f"{self.path}: material region {region.describe()} holds no cell of the model")
        return replace(self, material_overrides=self.material_overrides + overrides)

    def skin_surface(self) -> tuple[np.ndarray, np.ndarray]:
        """Points (n, 3) and triangles (m, 3) of the facets tagged skin, on EVERY rank.

        Collective. Triangles are oriented with outward normals (away from their tet); points
        are the skin's mesh nodes in the order of the mesh file. Rank 0 reads them from the
        model files (``ModelArrays.skin_surface``), so they do not depend on the distribution.
        """
        return on_rank_0(lambda: read_model_arrays(self.path, check=False).skin_surface(), self.mesh.comm)


def cell_midpoints(mesh) -> np.ndarray:
    """Midpoints (mm) of the rank's owned and ghost cells, in local cell order."""
    index_map = mesh.topology.index_map(mesh.topology.dim)
    cells = np.arange(index_map.size_local + index_map.num_ghosts, dtype=np.int32)
    return dolfinx_mesh.compute_midpoints(mesh, mesh.topology.dim, cells)


# ---------------------------------------------------------------------------------------------
# Loading
# ---------------------------------------------------------------------------------------------
def _read_mesh_reproducibly(xdmf, name: str) -> dolfinx_mesh.Mesh:
    """``XDMFFile.read_mesh``, but with a partition that is the same on every launch.

    The SCOTCH partitioner of the Debian packages gives a different partition on each run of the
    same command (measured: different owned cells on 2 ranks, the same dual graph), so results
    differed at round-off between runs and a resumed fit was not bit-identical to an uninterrupted
    one. Here the cell dual graph is ordered by reverse Cuthill-McKee on rank 0 and cut into equal
    contiguous pieces: deterministic slabs, as compact as a graph partition for the few ranks of a
    workstation (MUMPS orders the assembled matrix itself, whatever the partition).
    """
    shape, degree = xdmf.read_cell_type(name)
    cells = xdmf.read_topology_data(name)
    x = xdmf.read_geometry_data(name)
    cmap = dolfinx_cpp.fem.CoordinateElement(shape, degree)
    mesh = dolfinx_cpp.mesh.create_mesh(
        xdmf.comm(), dolfinx_cpp.graph.AdjacencyList_int64(cells), cmap, x,
        dolfinx_mesh.GhostMode.shared_facet, dolfinx_cpp.mesh.create_cell_partitioner(_slab_partition))
    mesh.name = name
    cell = ufl.Cell(shape.name, geometric_dimension=x.shape[1])
    return dolfinx_mesh.Mesh(mesh, ufl.Mesh(ufl.VectorElement("Lagrange", cell, degree)))


def _slab_partition(comm, parts: int, graph, ghosting: bool):
    """Destination ranks of each local cell: RCM order of the whole dual graph cut in ``parts``
    gives the owner; with ``ghosting``, the owners of its facet neighbours follow (ghost copies,
    as DOLFINx's own partitioners return them for GhostMode.shared_facet)."""
    offsets, links = np.asarray(graph.offsets), np.asarray(graph.array)
    degrees = comm.gather(np.diff(offsets), root=0)
    neighbours = comm.gather(links, root=0)
    pieces = None
    if comm.rank == 0:
        counts = np.concatenate(degrees)
        n = len(counts)
        rows = np.repeat(np.arange(n), counts)
        adjacency = sp.csr_matrix((np.ones(len(rows)), (rows, np.concatenate(neighbours))), shape=(n, n))
        order = reverse_cuthill_mckee(adjacency, symmetric_mode=True)
        owner = np.empty(n, dtype=np.int32)
        owner[order] = np.arange(n) * parts // n
        # Destinations as (cell, rank) pairs: the owner first, then (with ghosting) the other
        # owners among the cell's facet neighbours, each once.
        cell, rank = np.arange(n), owner
        if ghosting:
            row = np.repeat(np.arange(n), np.diff(adjacency.indptr))
            neighbour_owner = owner[adjacency.indices]
            foreign = neighbour_owner != owner[row]
            ghost = np.unique(row[foreign].astype(np.int64) * parts + neighbour_owner[foreign])
            cell = np.concatenate([cell, ghost // parts])
            rank = np.concatenate([rank, (ghost % parts).astype(np.int32)])
        by_cell = np.argsort(cell, kind="stable")  # owners stay ahead of ghosts
        cell, rank = cell[by_cell], rank[by_cell]
        starts = np.cumsum([0] + [len(d) for d in degrees])
        bounds = np.searchsorted(cell, starts)
        pieces = [(rank[lo:hi], cell[lo:hi] - first) for lo, hi, first in zip(bounds[:-1], bounds[1:], starts)]
    destinations, local_cell = comm.scatter(pieces, root=0)
    cell_offsets = np.searchsorted(local_cell, np.arange(len(offsets))).astype(np.int32)
    return dolfinx_cpp.graph.AdjacencyList_int32(destinations.astype(np.int32), cell_offsets)


def load_model(path, comm=MPI.COMM_WORLD) -> FaceModel:
    """Read and check a model folder; the mesh is distributed over ``comm`` (collective)."""
    folder = Path(path)
    if not folder.is_dir():
        raise ModelError(f"{folder}: no such model folder")
    for name in (MODEL_FILE, MESH_FILE, HEAVY_FILE, MUSCLES_FILE):
        if not (folder / name).is_file():
            raise ModelError(f"{folder / name}: missing file")
    meta = _read_metadata(folder / MODEL_FILE)
    muscle_data = _read_muscles(folder / MUSCLES_FILE, meta["muscles"])
    try:
        with dolfinx_io.XDMFFile(comm, str(folder / MESH_FILE), "r") as xdmf:
            domain = _read_mesh_reproducibly(xdmf, MESH_NAME)
            domain.topology.create_connectivity(2, 3)
            tags = xdmf.read_meshtags(domain, name=TAGS_NAME)
    except RuntimeError as error:
        raise ModelError(f"{folder / MESH_FILE}: cannot read mesh {MESH_NAME!r} and facet tags "
                         f"{TAGS_NAME!r}: {error}") from error
    num_cells = domain.topology.index_map(3).size_global
    _check_cells(domain, folder / HEAVY_FILE)
    boundary_ids = meta["boundaries"]
    for key in ("cranium", "skin"):
        count = comm.allreduce(len(tags.find(boundary_ids[key])), op=MPI.SUM)
        if count == 0:
            raise ModelError(f"{folder / MESH_FILE}: no facets tagged {key} (value {boundary_ids[key]})")
    _check_sites(folder, boundary_ids["skin"], meta["markers"], comm)

    # File cell index -> local cell index (owned and ghost), -1 where not on this rank.
    original = np.asarray(domain.topology.original_cell_index, dtype=np.int64)
    local_of_file = np.full(num_cells, -1, dtype=np.int32)
    local_of_file[original] = np.arange(len(original), dtype=np.int32)
    muscles = []
    for entry, (file_cells, fraction, fiber) in zip(meta["muscles"], muscle_data):
        if file_cells.size and (file_cells.min() < 0 or file_cells.max() >= num_cells):
            raise ModelError(f"{folder / MUSCLES_FILE}: {entry['name']}/cells outside [0, {num_cells})")
        local = local_of_file[file_cells]
        here = local >= 0
        muscles.append(Muscle(entry["name"], entry["kind"], entry["peak_stress"], local[here],
                              fraction[here], fiber[here], entry["geometry"]))
    teeth = on_rank_0(lambda: _read_teeth(folder, meta["teeth"]), comm)
    return FaceModel(folder, meta["name"], domain, tags, boundary_ids, muscles, meta["jaw"],
                     meta["markers"], meta["landmarks"], meta["material"], meta["expressions"], teeth=teeth)


def _read_teeth(folder: Path, files: dict[str, str]) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """The teeth surfaces listed in model.toml's [teeth], read and checked (closed, oriented)."""
    teeth = {}
    for bone, name in files.items():
        where = f"{folder / MODEL_FILE}: [teeth] {bone} = {name!r}"
        if not (folder / name).is_file():
            raise ModelError(f"{where}: no such file in the model folder")
        try:
            teeth[bone] = read_triangle_surface(folder / name)
        except ValueError as error:
            raise ModelError(f"{where}: {error}") from None
    return teeth


def _read_metadata(path: Path) -> dict:
    try:
        data = tomllib.loads(path.read_text())
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as error:
        raise ModelError(f"{path}: malformed TOML: {error}") from error

    def fail(message):
        raise ModelError(f"{path}: {message}")

    def need(table, key, where):
        if key not in table:
            fail(f"missing key {where}{key}")
        return table[key]

    def number(table, key, where):
        value = need(table, key, where)
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            fail(f"{where}{key} must be a finite number, got {value!r}")
        return float(value)

    def point(value, where):
        try:
            array = np.asarray(value, dtype=float)
        except (TypeError, ValueError):
            array = None
        if array is None or array.shape != (3,) or not np.all(np.isfinite(array)):
            fail(f"{where} must be three finite numbers [x, y, z], got {value!r}")
        return array

    def table(key):
        value = need(data, key, "")
        if not isinstance(value, dict):
            fail(f"[{key}] must be a table")
        return value

    name = need(data, "name", "")
    for key in MATERIAL_KEYS:
        need(table("material"), key, "material.")
    material = {key: number(table("material"), key, "material.") for key in table("material")}
    boundaries = {}
    for key in BOUNDARY_NAMES + OPTIONAL_BOUNDARY_NAMES:
        if key in OPTIONAL_BOUNDARY_NAMES and key not in table("boundaries"):
            continue
        value = need(table("boundaries"), key, "boundaries.")
        if isinstance(value, bool) or not isinstance(value, int):
            fail(f"boundaries.{key} must be an integer tag value, got {value!r}")
        boundaries[key] = value
    if len(set(boundaries.values())) != len(boundaries):
        fail(f"[boundaries] values must be distinct, got {boundaries}")

    entries = need(data, "muscles", "")
    if not isinstance(entries, list) or not entries:
        fail("[[muscles]] must list at least one muscle")
    muscles, seen = [], set()
    for i, entry in enumerate(entries):
        where = f"muscles[{i}]."
        muscle_name = need(entry, "name", where)
        if not isinstance(muscle_name, str) or not muscle_name or muscle_name in seen:
            fail(f"{where}name must be a unique non-empty string, got {muscle_name!r}")
        seen.add(muscle_name)
        kind = need(entry, "kind", where)
        if kind not in MUSCLE_KINDS:
            fail(f"muscle {muscle_name}: kind must be one of {MUSCLE_KINDS}, got {kind!r}")
        stress = number(entry, "peak_stress", where) if "peak_stress" in entry else None
        geometry = {key: point(entry[key], f"muscle {muscle_name}: {key}")
                    for key in ("origin", "insertion", "center", "axis") if key in entry}
        muscles.append(dict(name=muscle_name, kind=kind, peak_stress=stress, geometry=geometry))

    jaw_table = table("jaw")
    jaw_points = [point(need(jaw_table, key, "jaw."), f"jaw.{key}")
                  for key in ("condyle_right", "condyle_left", "slide_direction")]
    jaw_numbers = [number(jaw_table, key, "jaw.") for key in ("track_length", "max_opening_sine")]
    try:
        jaw = JawGeometry.from_condyles(*jaw_points, *jaw_numbers)
    except ValueError as error:
        fail(f"[jaw]: {error}")

    sites = {key: {site: point(value, f"{key}.{site}") for site, value in data.get(key, {}).items()}
             for key in ("markers", "landmarks")}
    names = [m["name"] for m in muscles]
    expressions = {}
    for expression, activations in data.get("expressions", {}).items():
        checked = {}
        for key, value in activations.items():
            where = f"expressions.{expression}.{key}"
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                fail(f"{where} must be a number, got {value!r}")
            if key != "jaw_opening_deg":
                if key not in names:
                    close = difflib.get_close_matches(key, names, n=3, cutoff=0.5)
                    fail(f"{where}: unknown muscle" + (f" (did you mean {', '.join(close)}?)" if close else ""))
                if not 0.0 <= value <= 1.0:
                    fail(f"{where} = {value}: activations must lie in [0, 1]")
            checked[key] = float(value)
        expressions[expression] = checked
    info = data.get("generator", {})
    if not isinstance(info, dict):
        fail("[generator] must be a table")
    teeth = data.get("teeth", {})
    if not isinstance(teeth, dict):
        fail("[teeth] must be a table of bone = file")
    for bone, file in teeth.items():
        if bone not in TEETH_BONES:
            fail(f"[teeth]: unknown bone {bone!r}; the teeth move with {' or '.join(TEETH_BONES)}")
        if not isinstance(file, str) or not file or Path(file).is_absolute():
            fail(f"[teeth] {bone} must name a triangle surface file in the model folder, got {file!r}")
    return dict(name=str(name), material=material, boundaries=boundaries, muscles=muscles, jaw=jaw,
                markers=sites["markers"], landmarks=sites["landmarks"], expressions=expressions, info=info,
                teeth=teeth)


def _read_muscles(path: Path, entries: list[dict]) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """(file cells, fraction, fiber) per muscle of model.toml, checked."""
    try:
        archive = np.load(path, allow_pickle=False)
        arrays = {key: archive[key] for key in archive.files}
    except (OSError, ValueError) as error:
        raise ModelError(f"{path}: cannot read: {error}") from error
    names = [entry["name"] for entry in entries]
    in_file = {key.rpartition("/")[0] for key in arrays}
    unknown = sorted(in_file - set(names))
    if unknown:
        raise ModelError(f"{path}: muscles not listed in {MODEL_FILE}: {', '.join(unknown)}")
    result = []
    for name in names:
        missing = [f"{name}/{part}" for part in ("cells", "fraction", "fiber") if f"{name}/{part}" not in arrays]
        if missing:
            raise ModelError(f"{path}: missing arrays {', '.join(missing)}")
        cells = arrays[f"{name}/cells"]
        fraction = np.asarray(arrays[f"{name}/fraction"], dtype=float)
        fiber = np.asarray(arrays[f"{name}/fiber"], dtype=float)
        if not np.issubdtype(cells.dtype, np.integer) or cells.ndim != 1:
            raise ModelError(f"{path}: {name}/cells must be a 1-d integer array")
        if fraction.shape != cells.shape or fiber.shape != (len(cells), 3):
            raise ModelError(f"{path}: {name}: cells {cells.shape}, fraction {fraction.shape} and "
                             f"fiber {fiber.shape} do not match (n,), (n,), (n, 3)")
        if len(np.unique(cells)) != len(cells):
            raise ModelError(f"{path}: {name}/cells lists a cell twice")
        bad = ~((fraction > 0) & (fraction <= 1))
        if bad.any():
            raise ModelError(f"{path}: {name}/fraction has {bad.sum()} values outside (0, 1], "
                             f"e.g. {fraction[bad][0]!r} at cell {cells[bad][0]}")
        norm = np.linalg.norm(fiber, axis=1)
        bad = ~(np.abs(norm - 1.0) <= UNIT_TOLERANCE)
        if bad.any():
            raise ModelError(f"{path}: {name}/fiber has {bad.sum()} vectors that are not unit, "
                             f"e.g. length {norm[bad][0]:.6g} at cell {cells[bad][0]}")
        result.append((cells.astype(np.int64), fraction, fiber))
    return result


def tet_volumes_and_quality(corners: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Signed volumes and the quality 6 sqrt(2) |V| / l_rms^3 of tets with corners (m, 4, 3)."""
    e1, e2, e3 = (corners[:, k] - corners[:, 0] for k in (1, 2, 3))
    volume = np.einsum("ij,ij->i", np.cross(e1, e2), e3) / 6.0
    edges = [corners[:, j] - corners[:, i] for i in range(4) for j in range(i + 1, 4)]
    rms = np.sqrt(sum(np.einsum("ij,ij->i", e, e) for e in edges) / 6.0)
    return volume, 6.0 * np.sqrt(2.0) * np.abs(volume) / np.maximum(rms, np.finfo(float).tiny) ** 3


def _check_cells(domain, path: Path) -> None:
    """No inverted (signed volume <= 0) or degenerate tets, counted over all ranks.

    DOLFINx keeps each tet's node order from the file (simplices are not reordered), so the sign
    of the volume is the file's orientation.
    """
    comm = domain.comm
    owned = domain.topology.index_map(3).size_local
    nodes = domain.geometry.dofmap.array.reshape(-1, 4)[:owned]
    volume, quality = tet_volumes_and_quality(domain.geometry.x[nodes])
    original = np.asarray(domain.topology.original_cell_index)[:owned]
    problems = []
    for label, bad, measure, rule in (("inverted", volume <= 0, volume, "signed volume <= 0"),
                                      ("degenerate", (volume > 0) & (quality < DEGENERATE_QUALITY),
                                       quality, f"quality < {DEGENERATE_QUALITY:g}")):
        count = comm.allreduce(int(bad.sum()), op=MPI.SUM)
        worst = (float(measure[bad].min()), int(original[bad][np.argmin(measure[bad])])) if bad.any() else (np.inf, -1)
        worst_value, worst_cell = comm.allreduce(worst, op=MPI.MINLOC)
        if count:
            what = "volume" if label == "inverted" else "quality"
            problems.append(f"{label} tetrahedra: {count} ({rule}; worst: cell {worst_cell} with "
                            f"{what} {worst_value:.3g})")
    if problems:
        raise ModelError(f"{path}: " + " and ".join(problems))


def _check_sites(folder: Path, skin_id: int, markers: dict[str, np.ndarray], comm) -> None:
    """Every marker within MARKER_TOLERANCE of the skin facets (rank 0 reads, all ranks raise)."""
    def far_markers() -> str | None:
        points, cells, facets, values = read_mesh_arrays(folder)
        skin = SkinSurface(points, skin_triangles(points, cells, facets[values == skin_id], folder / HEAVY_FILE))
        distance = skin.closest(np.array(list(markers.values())))[3]
        far = np.flatnonzero(distance > MARKER_TOLERANCE)
        if not far.size:
            return None
        names = list(markers)
        listed = ", ".join(f"{names[i]} ({distance[i]:.3g} mm)" for i in far[:5])
        return (f"{folder / MODEL_FILE}: markers farther than {MARKER_TOLERANCE} mm from the skin "
                f"({far.size} of {len(markers)}): {listed}")

    if not markers:
        return
    problem = on_rank_0(far_markers, comm)
    if problem:
        raise ModelError(problem)


# ---------------------------------------------------------------------------------------------
# The model as plain arrays (serial, the file's numbering)
# ---------------------------------------------------------------------------------------------
def read_mesh_arrays(path) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The mesh of the model folder ``path`` as mesh.h5 holds it: points (n, 3), cells (m, 4)
    int64, facets (k, 3) int64 and their tag values (k,)."""
    heavy = Path(path) / HEAVY_FILE
    try:
        with h5py.File(heavy, "r") as h5:
            mesh, tags = f"Mesh/{MESH_NAME}", f"MeshTags/{TAGS_NAME}"
            return (h5[f"{mesh}/geometry"][...], h5[f"{mesh}/topology"][...].astype(np.int64),
                    h5[f"{tags}/topology"][...].astype(np.int64), h5[f"{tags}/Values"][...].reshape(-1))
    except (OSError, KeyError) as error:
        raise ModelError(f"{heavy}: cannot read the mesh {MESH_NAME!r} and facet tags {TAGS_NAME!r}: "
                         f"{error}") from error


def skin_triangles(points: np.ndarray, cells: np.ndarray, facets: np.ndarray, where="the mesh") -> np.ndarray:
    """The boundary ``facets`` (k, 3) of the tets ``cells`` (m, 4), in their order, each oriented
    away from its tet (outward normal by the right-hand rule). ModelError (naming ``where``) if a
    facet is no face of a tet."""
    if not len(facets):
        return np.zeros((0, 3), dtype=np.int64)
    # Only tets with three nodes on the facets can own one; their nodes are numbered compactly so
    # that a sorted node triple is one int64 key.
    nodes = np.unique(facets)
    number = np.full(len(points), -1, dtype=np.int64)
    number[nodes] = np.arange(len(nodes))
    candidates = cells[np.count_nonzero(number[cells] >= 0, axis=1) >= 3]
    faces = number[candidates[:, TET_FACES].reshape(-1, 3)]
    complete = np.all(faces >= 0, axis=1)
    apex_of_face = candidates.reshape(-1)[complete]  # face k of a tet is opposite its node k

    def key(triples):
        ordered = np.sort(triples, axis=1)
        return (ordered[:, 0] * len(nodes) + ordered[:, 1]) * len(nodes) + ordered[:, 2]

    face_keys, facet_keys = key(faces[complete]), key(number[facets])
    order = np.argsort(face_keys)
    slot = np.searchsorted(face_keys[order], facet_keys)
    found = slot < len(order)
    found[found] = face_keys[order[slot[found]]] == facet_keys[found]
    if not found.all():
        bad = np.flatnonzero(~found)
        raise ModelError(f"{where}: {bad.size} facets that are no face of a tetrahedron, e.g. nodes "
                         f"{facets[bad[0]].tolist()}")
    triangles = np.array(facets, dtype=np.int64)
    a, b, c = (points[triangles[:, k]] for k in range(3))
    inward = np.einsum("ij,ij->i", np.cross(b - a, c - a), points[apex_of_face[order[slot]]] - a) > 0
    triangles[inward] = triangles[inward][:, [0, 2, 1]]
    return triangles


@dataclass
class ModelArrays:
    """A model folder as plain arrays, in the terms of ``write_model`` (muscle cells are file cells)."""

    name: str
    points: np.ndarray          # (n, 3) mm
    cells: np.ndarray           # (m, 4) positively oriented tets
    facets: np.ndarray          # (k, 3) node triples
    facet_values: np.ndarray    # (k,) tag values
    boundary_ids: dict[str, int]
    muscles: list[Muscle]
    jaw: JawGeometry
    markers: dict[str, np.ndarray]
    landmarks: dict[str, np.ndarray]
    material: dict[str, float]
    expressions: dict[str, dict]
    info: dict = field(default_factory=dict)   # the [generator] table
    teeth: dict = field(default_factory=dict)  # {bone: (points, triangles)}, as FaceModel.teeth

    @cached_property
    def skin_triangles(self) -> np.ndarray:
        """The facets tagged skin (file nodes, file order), oriented away from their tet."""
        return skin_triangles(self.points, self.cells,
                              self.facets[self.facet_values == self.boundary_ids["skin"]], self.name)

    @property
    def skin_nodes(self) -> np.ndarray:
        """The file nodes of the skin, ascending."""
        return np.unique(self.skin_triangles)

    def skin(self, points=None) -> SkinSurface:
        """The skin triangles over ``points`` (default: the model's own nodes)."""
        return SkinSurface(self.points if points is None else points, self.skin_triangles)

    def skin_surface(self) -> tuple[np.ndarray, np.ndarray]:
        """Points (n, 3) of the skin nodes (ascending file numbers) and the oriented skin
        triangles (m, 3) over them."""
        nodes = self.skin_nodes
        return self.points[nodes], np.searchsorted(nodes, self.skin_triangles)

    def write(self, path) -> Path:
        """Write the model folder ``path`` (``write_model``)."""
        return write_model(path, **{f.name: getattr(self, f.name) for f in fields(self)})


def read_model_arrays(path, *, check: bool = True) -> ModelArrays:
    """The model folder ``path`` as plain arrays (serial).

    With ``check`` it is first loaded on this process alone, and so checked in full; without,
    model.toml and muscles.npz are checked but not the mesh (for a folder known to load).
    """
    folder = Path(path)
    if check:
        load_model(folder, MPI.COMM_SELF)
    meta = _read_metadata(folder / MODEL_FILE)
    muscle_data = _read_muscles(folder / MUSCLES_FILE, meta["muscles"])
    points, cells, facets, values = read_mesh_arrays(folder)
    muscles = [Muscle(entry["name"], entry["kind"], entry["peak_stress"], file_cells, fraction, fiber,
                      entry["geometry"])
               for entry, (file_cells, fraction, fiber) in zip(meta["muscles"], muscle_data)]
    return ModelArrays(meta["name"], points, cells, facets, values, meta["boundaries"], muscles, meta["jaw"],
                       meta["markers"], meta["landmarks"], meta["material"], meta["expressions"], meta["info"],
                       _read_teeth(folder, meta["teeth"]))


# ---------------------------------------------------------------------------------------------
# Writing
# ---------------------------------------------------------------------------------------------
def write_model(path, *, name: str, points: np.ndarray, cells: np.ndarray, facets: np.ndarray,
                facet_values: np.ndarray, boundary_ids: dict[str, int], muscles: list[Muscle],
                jaw: JawGeometry, markers: dict[str, np.ndarray], landmarks: dict[str, np.ndarray],
                material: dict[str, float], expressions: dict[str, dict],
                info: dict | None = None, teeth: dict | None = None) -> Path:
    """Write a model folder (serial). ``muscles[i].cells`` are cell indices into ``cells``.

    points (n, 3) mm; cells (m, 4) positively oriented tets; facets (k, 3) node triples with
    tag values facet_values (k,); ``info`` is an optional [generator] table of plain values;
    ``teeth`` optional {bone: (points, triangles)} closed surfaces, written as teeth_<bone>.ply.
    """
    folder = Path(path)
    folder.mkdir(parents=True, exist_ok=True)
    _write_mesh(folder, np.asarray(points, float), np.asarray(cells, np.int64),
                np.asarray(facets, np.int64), np.asarray(facet_values, np.int32))
    np.savez(folder / MUSCLES_FILE, **{
        f"{m.name}/{part}": value for m in muscles
        for part, value in (("cells", np.asarray(m.cells, np.int64)),
                            ("fraction", np.asarray(m.fraction, float)),
                            ("fiber", np.asarray(m.fiber, float).reshape(-1, 3)))})
    teeth_files = {}
    for bone, (teeth_points, teeth_triangles) in (teeth or {}).items():
        if bone not in TEETH_BONES:
            raise ValueError(f"teeth on {bone!r}: the teeth move with {' or '.join(TEETH_BONES)}")
        teeth_files[bone] = f"teeth_{bone}.ply"
        write_triangle_surface(folder / teeth_files[bone], teeth_points, teeth_triangles)
    (folder / MODEL_FILE).write_text(_model_toml(name, boundary_ids, muscles, jaw, markers, landmarks,
                                                 material, expressions, info, teeth_files))
    return folder


def _write_mesh(folder: Path, points, cells, facets, values) -> None:
    """mesh.xdmf + mesh.h5 in the layout DOLFINx's XDMFFile writes and reads."""
    with h5py.File(folder / HEAVY_FILE, "w") as h5:
        h5[f"Mesh/{MESH_NAME}/geometry"] = points
        h5[f"Mesh/{MESH_NAME}/topology"] = cells
        h5[f"MeshTags/{TAGS_NAME}/topology"] = facets
        h5[f"MeshTags/{TAGS_NAME}/Values"] = values.reshape(-1, 1)
    heavy = HEAVY_FILE
    (folder / MESH_FILE).write_text(f"""<?xml version="1.0"?>
<!DOCTYPE Xdmf SYSTEM "Xdmf.dtd" []>
<Xdmf Version="3.0" xmlns:xi="http://www.w3.org/2001/XInclude">
  <Domain>
    <Grid Name="{MESH_NAME}" GridType="Uniform">
      <Topology TopologyType="Tetrahedron" NumberOfElements="{len(cells)}" NodesPerElement="4">
        <DataItem Dimensions="{len(cells)} 4" NumberType="Int" Format="HDF">{heavy}:/Mesh/{MESH_NAME}/topology</DataItem>
      </Topology>
      <Geometry GeometryType="XYZ">
        <DataItem Dimensions="{len(points)} 3" Format="HDF">{heavy}:/Mesh/{MESH_NAME}/geometry</DataItem>
      </Geometry>
    </Grid>
    <Grid Name="{TAGS_NAME}" GridType="Uniform">
      <xi:include xpointer="xpointer(/Xdmf/Domain/Grid[@Name='{MESH_NAME}']/Geometry)" />
      <Topology TopologyType="Triangle" NumberOfElements="{len(facets)}" NodesPerElement="3">
        <DataItem Dimensions="{len(facets)} 3" NumberType="Int" Format="HDF">{heavy}:/MeshTags/{TAGS_NAME}/topology</DataItem>
      </Topology>
      <Attribute Name="{TAGS_NAME}" AttributeType="Scalar" Center="Cell">
        <DataItem Dimensions="{len(facets)} 1" NumberType="Int" Format="HDF">{heavy}:/MeshTags/{TAGS_NAME}/Values</DataItem>
      </Attribute>
    </Grid>
  </Domain>
</Xdmf>
""")


def _model_toml(name, boundary_ids, muscles, jaw, markers, landmarks, material, expressions, info,
                teeth_files) -> str:
    lines = [f"name = {toml_value(name)}", 'units = { length = "mm", stress = "kPa" }', ""]
    if info:
        lines += ["[generator]"] + [f"{_key(k)} = {toml_value(v)}" for k, v in info.items()] + [""]
    lines += ["[material]"] + [f"{_key(k)} = {toml_value(v)}" for k, v in material.items()] + [""]
    lines += ["[boundaries]"] + [f"{_key(k)} = {int(v)}" for k, v in boundary_ids.items()] + [""]
    for muscle in muscles:
        lines += ["[[muscles]]", f"name = {toml_value(muscle.name)}", f"kind = {toml_value(muscle.kind)}"]
        if muscle.peak_stress is not None:
            lines.append(f"peak_stress = {toml_value(muscle.peak_stress)}")
        lines += [f"{key} = {toml_value(value)}" for key, value in muscle.geometry.items()] + [""]
    lines += ["[jaw]", f"condyle_right = {toml_value(jaw.condyle_right)}", f"condyle_left = {toml_value(jaw.condyle_left)}",
              f"slide_direction = {toml_value(jaw.v)}", f"track_length = {toml_value(jaw.track_length)}",
              f"max_opening_sine = {toml_value(jaw.max_opening_sine)}", ""]
    if teeth_files:
        lines += ["[teeth]"] + [f"{bone} = {toml_value(file)}" for bone, file in teeth_files.items()] + [""]
    for title, sites in (("markers", markers), ("landmarks", landmarks)):
        lines += [f"[{title}]"] + [f"{_key(k)} = {toml_value(v)}" for k, v in sites.items()] + [""]
    for expression, activations in expressions.items():
        lines += [f"[expressions.{_key(expression)}]"]
        lines += [f"{_key(k)} = {toml_value(v)}" for k, v in activations.items()] + [""]
    return "\n".join(lines)


def _key(key: str) -> str:
    return key if re.fullmatch(r"[A-Za-z0-9_-]+", key) else toml_value(key)


def toml_value(value) -> str:
    """A TOML literal for the plain values a model holds: strings, numbers, vectors."""
    if isinstance(value, str):
        return '"' + value.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(value, (bool, np.bool_)):
        return "true" if value else "false"
    if isinstance(value, (int, np.integer)):
        return str(int(value))
    if isinstance(value, (float, np.floating)):
        return repr(float(value))
    return "[" + ", ".join(toml_value(v) for v in np.asarray(value).tolist()) + "]"
