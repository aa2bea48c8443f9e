"""Building the built-in face into a model folder, with a cache.

The pipeline (each step in its own module):
  description.py  read meshes/builtin_face.toml
  openings.py     mouth slit and eye fissures in the (theta, phi) plane
  domain.py       gmsh triangulation of the plane with holes, sized for the target tet count
  extrude.py      layers of tets through the thickness
  shape.py        map (theta, phi, t) to millimetres: skin, bone and the flesh between
  attachments.py  facet tags: cranium, mandible, skin, free
  muscles.py      volume fractions and fibers of the 32 muscles
  sites.py        markers and landmarks on the skin
  teeth.py        the rigid upper and lower teeth behind the lips
  libm.py         sin, cos, exp and power from the C library, for the same face on every CPU
and model.write_model writes the folder.

Models are cached under meshes/cache/<resolution>-<hash>/, the hash covering the description
file, the target tet count and the generator's source code, so any change rebuilds. A build
goes to a hidden temporary folder, is checked by loading it, and is renamed into place: a
killed build never leaves a folder that looks complete.

The tests run on the face at SMALL_FACE_TETS as committed in SMALL_FACE
(meshes/freeze_small_face.py writes it), so that a change of the generator changes their face only
when that copy is rebuilt.
"""
import hashlib
import logging
import time
from pathlib import Path

import numpy as np
from mpi4py import MPI

from face_dolfinx.files import atomic_directory
from face_dolfinx.model import folder as model_format
from .attachments import BOUNDARY_IDS, facet_tags
from .description import Description, DescriptionError, load_description
from .domain import mesh_parameter_domain
from .extrude import extrude
from .muscles import MuscleEmbedder
from .openings import all_openings
from .sites import place_on_skin, site_angles
from .teeth import dental_arch

log = logging.getLogger(__name__)

REPOSITORY = Path(__file__).resolve().parents[3]
DESCRIPTION_FILE = REPOSITORY / "meshes" / "builtin_face.toml"
DEFAULT_CACHE = REPOSITORY / "meshes" / "cache"
SMALL_FACE = REPOSITORY / "meshes" / "small_face"
SMALL_FACE_TETS = 5000
MODEL_NAME = "builtin-face"


def build_builtin_face(target_tets: int = 20000, cache_dir=None, comm=MPI.COMM_WORLD) -> Path:
    """The built-in face model folder at about ``target_tets`` tetrahedra (collective).

    Rank 0 builds (or finds it in the cache); the other ranks wait and get the same path.
    The actual tet count is logged and stored in model.toml [generator].
    """
    cache = Path(cache_dir) if cache_dir is not None else DEFAULT_CACHE
    folder, failure = None, None
    if comm.rank == 0:
        try:
            folder = _cached_build(int(target_tets), cache)
        except Exception as error:  # every rank must learn about it, or they would wait forever
            failure = error
    folder, message = comm.bcast((folder, failure and f"{type(failure).__name__}: {failure}"), root=0)
    if failure is not None:
        raise failure
    if message is not None:
        raise RuntimeError(f"building the built-in face failed on rank 0: {message}")
    return folder


def cache_key(description: Description, target_tets: int) -> str:
    digest = hashlib.sha256(description.text)
    digest.update(str(target_tets).encode())
    sources = sorted(Path(__file__).parent.glob("*.py")) + [Path(model_format.__file__)]
    for source in sources:
        digest.update(source.read_bytes())
    return f"{target_tets}-{digest.hexdigest()[:12]}"


def _cached_build(target_tets: int, cache: Path) -> Path:
    description = load_description(DESCRIPTION_FILE)
    folder = cache / cache_key(description, target_tets)
    if folder.is_dir():
        return folder
    try:
        with atomic_directory(folder, MPI.COMM_SELF) as staging:
            info = generate(description, target_tets, staging)
            model_format.load_model(staging, MPI.COMM_SELF)  # never cache a model that does not load
    except FileExistsError:
        if not folder.is_dir():  # not a concurrent build that finished first
            raise
        return folder
    log.info("built-in face: %d tets (target %d), %d layers, generated in %.1f s -> %s",
             info["tets"], target_tets, info["layers"], info["generation_seconds"], folder)
    return folder


def generate(description: Description, target_tets: int, folder: Path) -> dict:
    """Generate the face into ``folder`` (serial); returns the [generator] statistics."""
    if target_tets < 1000:
        raise ValueError(f"target_tets = {target_tets}: the face needs at least 1000 tets")
    start = time.perf_counter()
    shape = description.shape
    openings = all_openings(description)
    marker_angles = site_angles(description.markers, openings)
    landmark_angles = site_angles(description.landmarks, openings)

    layers = description.mesh.layers(target_tets)
    planar = mesh_parameter_domain(description, openings, np.array(list(marker_angles.values())),
                                   target_triangles=round(target_tets / (3 * layers)))
    layered = extrude(planar, layers)
    theta, phi, t = layered.coordinates.T
    points = shape.point(theta, phi, t)
    volume, quality = model_format.tet_volumes_and_quality(points[layered.tets])
    if volume.min() <= 0 or quality.min() < model_format.DEGENERATE_QUALITY:
        raise DescriptionError(f"{description.path}: the surfaces fold the mesh (min volume "
                               f"{volume.min():.3g} mm^3, min quality {quality.min():.3g})")
    facets, values = facet_tags(layered, planar, description.attachments, openings)

    embedder = MuscleEmbedder(shape, layered.coordinates, points, layered.tets)
    muscles = [m for spec in description.muscles for m in embedder.embed(spec)]
    names = {m.name for m in muscles}
    for expression, activations in description.expressions.items():
        unknown = sorted(set(activations) - names - {"jaw_opening_deg"})
        if unknown:
            raise DescriptionError(f"{description.path}: expression {expression!r} names unknown muscles {unknown}")

    skin_nodes = points[layers * len(planar.points):]   # the t = 1 layer
    jaw = description.jaw
    mirror = np.array([-1.0, 1.0, 1.0])
    info = dict(target_tets=target_tets, tets=len(layered.tets), nodes=len(points), layers=layers,
                min_quality=float(quality.min()), mean_quality=float(quality.mean()),
                volume_mm3=float(volume.sum()))
    info["generation_seconds"] = round(time.perf_counter() - start, 2)
    model_format.write_model(
        folder, name=MODEL_NAME, points=points, cells=layered.tets, facets=facets, facet_values=values,
        boundary_ids=BOUNDARY_IDS, muscles=muscles,
        jaw=model_format.JawGeometry.from_condyles(jaw.condyle_left * mirror, jaw.condyle_left,
                                                   jaw.slide_direction, jaw.track_length,
                                                   jaw.max_opening_sine),
        markers=place_on_skin(marker_angles, planar, skin_nodes),
        landmarks=place_on_skin(landmark_angles, planar, skin_nodes),
        material=description.material, expressions=description.expressions, info=info,
        teeth={"cranium": dental_arch(shape, description.teeth.upper, description.teeth),
               "mandible": dental_arch(shape, description.teeth.lower, description.teeth)})
    return info
