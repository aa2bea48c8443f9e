"""A small slab of flesh with three crossing muscles: a stand-in face for fast solver tests.

The slab [0, 40] x [0, 20] x [0, 10] mm is attached to the "cranium" at x = 0 and to the
"mandible" at x = 40; two linear muscles run along x and along y, a third diagonally, and they
overlap in the middle so cells carry up to three muscle slots.
"""
from types import SimpleNamespace

from mpi4py import MPI
import numpy as np
from dolfinx import mesh as dmesh

from face_dolfinx.model.bones import AffineMap  # noqa: F401  (re-exported for tests)

CRANIUM, MANDIBLE = 1, 2


def slab_model(cells=(8, 4, 2), comm=MPI.COMM_WORLD):
    domain = dmesh.create_box(comm, [np.zeros(3), np.array([40.0, 20.0, 10.0])], list(cells),
                              dmesh.CellType.tetrahedron, ghost_mode=dmesh.GhostMode.shared_facet)
    tdim = domain.topology.dim
    domain.topology.create_connectivity(tdim - 1, tdim)
    left = dmesh.locate_entities_boundary(domain, tdim - 1, lambda x: np.isclose(x[0], 0.0))
    right = dmesh.locate_entities_boundary(domain, tdim - 1, lambda x: np.isclose(x[0], 40.0))
    facets = np.concatenate([left, right])
    values = np.concatenate([np.full(len(left), CRANIUM), np.full(len(right), MANDIBLE)]).astype(np.int32)
    order = np.argsort(facets)
    tags = dmesh.meshtags(domain, tdim - 1, facets[order], values[order])

    num_cells = domain.topology.index_map(tdim).size_local + domain.topology.index_map(tdim).num_ghosts
    midpoints = dmesh.compute_midpoints(domain, tdim, np.arange(num_cells, dtype=np.int32))

    def muscle(name, inside, direction, fraction):
        cells = np.flatnonzero(inside(midpoints))
        fiber = np.tile(np.asarray(direction, float) / np.linalg.norm(direction), (len(cells), 1))
        return SimpleNamespace(name=name, kind="linear", peak_stress=None, cells=cells,
                               fraction=np.full(len(cells), fraction), fiber=fiber)

    muscles = [
        # Inserting in free flesh short of the far end: a muscle clamped at both ends would pull
        # against the bones only, leaving no visible motion (its activation unobservable).
        muscle("long", lambda x: (np.abs(x[:, 1] - 10) < 6) & (x[:, 0] < 28), [1, 0, 0], 0.8),
        muscle("across", lambda x: np.abs(x[:, 0] - 20) < 8, [0, 1, 0], 0.6),
        muscle("diagonal", lambda x: np.abs(x[:, 0] - x[:, 1] - 10) < 6, [1, 1, 0.2], 0.5),
    ]
    names = [m.name for m in muscles]

    def muscle_index(name):
        if name not in names:
            raise KeyError(f"unknown muscle {name!r}; known: {', '.join(names)}")
        return names.index(name)

    # A TMJ for the slab: condyles on the far end's edge, sliding along +x; w = v x u = +z and
    # opening turns the end towards -w.
    jaw = SimpleNamespace(u=np.array([0.0, 1.0, 0.0]), v=np.array([1.0, 0.0, 0.0]),
                          w=np.array([0.0, 0.0, 1.0]), midpoint=np.array([40.0, 10.0, 5.0]),
                          condyle_distance=20.0, track_length=5.0, max_opening_sine=0.5)
    material = {"mu10": 6.0, "mu01": 2.0, "kappa": 60.0, "fiber_stress": 30.0}

    def peak_stress(index):  # as FaceModel.peak_stress
        own = muscles[index].peak_stress
        return own if own is not None else material["fiber_stress"]

    return SimpleNamespace(
        path="<slab>", jaw=jaw, name="slab", mesh=domain, facet_tags=tags,
        boundary_ids={"cranium": CRANIUM, "mandible": MANDIBLE}, muscles=muscles, material=material,
        material_overrides=(), muscle_names=names, muscle_index=muscle_index, peak_stress=peak_stress)
