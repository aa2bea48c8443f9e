"""Loading model folders (face_dolfinx.model.folder): distributed loading and every ModelError.

The error cases corrupt a private copy of the small face and load it on COMM_SELF, so under
``mpirun -n 2`` each rank checks them independently in its own temporary folder.
"""
import re
import shutil
import tomllib

import h5py
import numpy as np
import pytest
from mpi4py import MPI

from face_dolfinx.model.folder import (ModelError, toml_value, load_model, read_mesh_arrays, read_model_arrays, skin_triangles,
                                      tet_volumes_and_quality)


@pytest.fixture(scope="module")
def serial_model(builtin_model_path):
    return load_model(builtin_model_path, MPI.COMM_SELF)


def owned_volumes(model):
    owned = model.mesh.topology.index_map(3).size_local
    nodes = model.mesh.geometry.dofmap.array.reshape(-1, 4)[:owned]
    return tet_volumes_and_quality(model.mesh.geometry.x[nodes])[0]


def test_model_contents(model):
    assert model.name == "builtin-face"
    assert len(model.muscles) == 32 and len(model.muscle_names) == 32
    assert model.muscle_index("zygomaticus_major_left") == model.muscle_names.index("zygomaticus_major_left")
    assert set(model.boundary_ids) == {"cranium", "mandible", "skin", "free", "oral"}
    assert model.material["kappa"] > model.material["mu10"] > 0
    assert {"smile", "jaw_open"} <= set(model.expressions)
    jaw = model.jaw
    assert np.allclose(np.cross(jaw.v, jaw.u), jaw.w) and np.isclose(np.linalg.norm(jaw.w), 1.0)
    assert np.isclose(jaw.u @ jaw.v, 0.0) and np.isclose(jaw.condyle_distance,
                                                         np.linalg.norm(jaw.condyle_left - jaw.condyle_right))
    num_local = model.mesh.topology.index_map(3).size_local + model.mesh.topology.index_map(3).num_ghosts
    for muscle in model.muscles:
        assert muscle.cells.size == 0 or (muscle.cells.min() >= 0 and muscle.cells.max() < num_local)


def test_unknown_muscle_names_close_matches(model):
    with pytest.raises(ModelError, match="zygomaticus_major_left"):
        model.muscle_index("zygomaticus_majr_left")


def test_distributed_load_matches_serial(model, serial_model):
    """Same total volume and same volume-weighted muscle fractions on any number of ranks."""
    comm = model.mesh.comm

    def totals(m, comm):
        volume = owned_volumes(m)
        owned = m.mesh.topology.index_map(3).size_local
        per_muscle = np.array([np.sum(volume[mu.cells[mu.cells < owned]] * mu.fraction[mu.cells < owned])
                               for mu in m.muscles])
        return comm.allreduce(volume.sum(), op=MPI.SUM), comm.allreduce(per_muscle, op=MPI.SUM)

    volume, muscles = totals(model, comm)
    volume_serial, muscles_serial = totals(serial_model, MPI.COMM_SELF)
    assert abs(volume - volume_serial) <= 1e-12 * volume_serial
    assert np.all(np.abs(muscles - muscles_serial) <= 1e-12 * muscles_serial)
    assert np.all(muscles > 0)


def test_muscle_cells_are_the_file_cells(model, builtin_model_path):
    """Local cell indices map back (original_cell_index) to the file's cells, each once."""
    archive = np.load(builtin_model_path / "muscles.npz")
    original = np.asarray(model.mesh.topology.original_cell_index)
    owned = model.mesh.topology.index_map(3).size_local
    for muscle in model.muscles:
        mine = original[muscle.cells[muscle.cells < owned]]
        everyone = np.sort(np.concatenate(model.mesh.comm.allgather(mine)))
        assert np.array_equal(everyone, np.sort(archive[f"{muscle.name}/cells"]))


def test_skin_surface_on_every_rank(model, serial_model):
    points, triangles = model.skin_surface()
    serial_points, serial_triangles = serial_model.skin_surface()
    assert points.shape == serial_points.shape and triangles.shape == serial_triangles.shape
    assert np.array_equal(points, serial_points)
    assert np.array_equal(np.sort(np.sort(triangles, axis=1), axis=0),
                          np.sort(np.sort(serial_triangles, axis=1), axis=0))
    gathered = model.mesh.comm.allgather(triangles)
    assert all(np.array_equal(g, gathered[0]) for g in gathered)
    # Outward orientation: on the face's front (nose tip) the normal points forward (+z).
    a, b, c = (points[triangles[:, k]] for k in range(3))
    normals = np.cross(b - a, c - a)
    front = np.linalg.norm(a - model.landmarks["nose_tip"], axis=1) < 5.0
    assert np.all(normals[front, 2] > 0)


def test_skin_triangles_face_away_from_their_tet_in_the_distributed_mesh(model, builtin_model_path):
    """Checked against DOLFINx's own facet-to-cell connectivity on each rank: the tet behind every
    skin facet lies on the inner side of the triangle skin_surface gives for it."""
    points, triangles = model.skin_surface()
    skin_nodes = read_model_arrays(builtin_model_path, check=False).skin_nodes
    normal_of = {tuple(sorted(skin_nodes[t])): np.cross(points[t[1]] - points[t[0]], points[t[2]] - points[t[0]])
                 for t in triangles}
    mesh, topology = model.mesh, model.mesh.topology
    topology.create_connectivity(2, 3)
    topology.create_connectivity(2, 0)
    facets = model.facet_tags.find(model.boundary_ids["skin"])
    cell_nodes = mesh.geometry.dofmap.array.reshape(-1, 4)
    file_node = np.asarray(mesh.geometry.input_global_indices)
    facet_cells, cell_vertices = topology.connectivity(2, 3), topology.connectivity(3, 0).array.reshape(-1, 4)
    checked = 0
    for facet in facets:
        cell = facet_cells.links(facet)[0]
        on_facet = np.isin(cell_vertices[cell], topology.connectivity(2, 0).links(facet))
        corners = mesh.geometry.x[cell_nodes[cell]]
        normal = normal_of[tuple(sorted(file_node[cell_nodes[cell][on_facet]]))]
        assert normal @ (corners[~on_facet][0] - corners[on_facet][0]) < 0
        checked += 1
    assert model.mesh.comm.allreduce(checked) >= len(triangles)


def test_skin_triangles_of_two_tets():
    """Each facet turned, where needed, so that its normal points away from the tet it bounds."""
    points = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1]])
    cells = np.array([[0, 1, 2, 3], [1, 2, 3, 4]])
    assert np.all(tet_volumes_and_quality(points[cells])[0] > 0)
    facets = np.array([[0, 1, 2], [2, 1, 0], [4, 3, 2], [2, 3, 4]])
    # z = 0 face of the first tet: outward is -z; face (2, 3, 4) of the second: outward is (1, 1, 1).
    assert np.array_equal(skin_triangles(points, cells, facets), [[0, 2, 1], [2, 1, 0], [4, 2, 3], [2, 3, 4]])
    with pytest.raises(ModelError, match=r"here: 1 facets that are no face of a tetrahedron, e.g. nodes \[0, 1, 4\]"):
        skin_triangles(points, cells, np.array([[0, 1, 2], [0, 1, 4]]), "here")


def test_arrays_written_and_read_back_are_the_same(builtin_model_path, tmp_path):
    """read_model_arrays and ModelArrays.write (write_model) are each other's inverse."""
    model = read_model_arrays(builtin_model_path)
    again = read_model_arrays(model.write(tmp_path / "copy"))
    for name in ("points", "cells", "facets", "facet_values", "skin_triangles"):
        assert np.array_equal(getattr(again, name), getattr(model, name)), name
    for before, after in zip(model.muscles, again.muscles):
        assert (before.name, before.kind, before.peak_stress) == (after.name, after.kind, after.peak_stress)
        for part in ("cells", "fraction", "fiber"):
            assert np.array_equal(getattr(before, part), getattr(after, part))
    for name in ("markers", "landmarks", "geometry"):
        pairs = [(model.markers, again.markers), (model.landmarks, again.landmarks)] if name != "geometry" else \
            [(b.geometry, a.geometry) for b, a in zip(model.muscles, again.muscles)]
        for before, after in pairs:
            assert list(before) == list(after) and all(np.array_equal(before[k], after[k]) for k in before)
    assert (again.name, again.boundary_ids, again.material, again.expressions, again.info) == \
        (model.name, model.boundary_ids, model.material, model.expressions, model.info)
    assert again.info["tets"] == len(model.cells)
    assert np.array_equal(again.jaw.v, model.jaw.v) and again.jaw.track_length == model.jaw.track_length


# -- ModelError cases ---------------------------------------------------------------------------
@pytest.fixture
def copy(builtin_model_path, tmp_path):
    folder = tmp_path / "face"
    shutil.copytree(builtin_model_path, folder)
    return folder


def load(folder):
    return load_model(folder, MPI.COMM_SELF)


def edit_toml(folder, old, new):
    path = folder / "model.toml"
    text = path.read_text()
    assert re.search(old, text, flags=re.M), old
    path.write_text(re.sub(old, new, text, count=1, flags=re.M))


def test_missing_folder(tmp_path):
    with pytest.raises(ModelError, match="no such model folder"):
        load(tmp_path / "nowhere")


@pytest.mark.parametrize("name", ["model.toml", "mesh.xdmf", "mesh.h5", "muscles.npz"])
def test_missing_file(copy, name):
    (copy / name).unlink()
    with pytest.raises(ModelError, match=f"{name}: missing file"):
        load(copy)


def test_malformed_toml(copy):
    with open(copy / "model.toml", "a") as f:
        f.write("\nthis is = not = toml\n")
    with pytest.raises(ModelError, match=r"model\.toml: malformed TOML"):
        load(copy)


@pytest.mark.parametrize("key, table", [("mu10", "material"), ("track_length", "jaw"), ("skin", "boundaries")])
def test_missing_key(copy, key, table):
    edit_toml(copy, rf"^{key} = .*$", "")
    with pytest.raises(ModelError, match=rf"model\.toml: missing key {table}\.{key}"):
        load(copy)


def rewrite_muscles(folder, change):
    arrays = dict(np.load(folder / "muscles.npz"))
    change(arrays)
    np.savez(folder / "muscles.npz", **arrays)


def test_unknown_muscle_in_npz(copy):
    def add(arrays):
        for part in ("cells", "fraction", "fiber"):
            arrays[f"nosuchmuscle/{part}"] = arrays[f"risorius_left/{part}"]
    rewrite_muscles(copy, add)
    with pytest.raises(ModelError, match=r"muscles\.npz: muscles not listed in model\.toml: nosuchmuscle"):
        load(copy)


@pytest.mark.parametrize("bad", [0.0, 1.5, -0.2, np.nan])
def test_fraction_outside_unit_interval(copy, bad):
    def spoil(arrays):
        arrays["mentalis_left/fraction"] = arrays["mentalis_left/fraction"].copy()
        arrays["mentalis_left/fraction"][0] = bad
    rewrite_muscles(copy, spoil)
    with pytest.raises(ModelError, match=r"muscles\.npz: mentalis_left/fraction has 1 values outside \(0, 1\]"):
        load(copy)


def test_non_unit_fiber(copy):
    def spoil(arrays):
        arrays["buccinator_right/fiber"] = arrays["buccinator_right/fiber"] * 1.01
    rewrite_muscles(copy, spoil)
    with pytest.raises(ModelError, match=r"muscles\.npz: buccinator_right/fiber has \d+ vectors that are not unit"):
        load(copy)


def add_tet(folder, corners):
    """Append a detached tet with four new nodes (the rest of the mesh stays valid)."""
    with h5py.File(folder / "mesh.h5", "r+") as h5:
        points, tets = h5["Mesh/flesh/geometry"][:], h5["Mesh/flesh/topology"][:]
        del h5["Mesh/flesh/geometry"], h5["Mesh/flesh/topology"]
        h5["Mesh/flesh/geometry"] = np.vstack([points, corners])
        h5["Mesh/flesh/topology"] = np.vstack([tets, len(points) + np.arange(4)])
    xdmf = folder / "mesh.xdmf"
    text = xdmf.read_text()
    text = text.replace(f'NumberOfElements="{len(tets)}"', f'NumberOfElements="{len(tets) + 1}"')
    text = text.replace(f'Dimensions="{len(tets)} 4"', f'Dimensions="{len(tets) + 1} 4"')
    xdmf.write_text(text.replace(f'Dimensions="{len(points)} 3"', f'Dimensions="{len(points) + 4} 3"'))
    return len(tets)


FAR = np.array([0.0, 0.0, -300.0])
UNIT_TET = np.array([[0.0, 0, 0], [10, 0, 0], [0, 10, 0], [0, 0, 10]])


def test_inverted_tet(copy):
    cell = add_tet(copy, FAR + UNIT_TET[[0, 2, 1, 3]])
    with pytest.raises(ModelError, match=rf"mesh\.h5: inverted tetrahedra: 1 .*worst: cell {cell} with volume -167"):
        load(copy)


def test_degenerate_tet(copy):
    sliver = UNIT_TET * [1, 1, 1e-4]
    cell = add_tet(copy, FAR + sliver)
    with pytest.raises(ModelError, match=rf"mesh\.h5: degenerate tetrahedra: 1 .*worst: cell {cell} with quality"):
        load(copy)


def test_the_oral_surface_is_optional(copy):
    edit_toml(copy, r"^oral = \d+$", "")
    assert "oral" not in load(copy).boundary_ids


def test_the_oral_surface_lines_the_mouth(model):
    """The oral facets face the mouth: on the inner surface behind the lips, between the corners."""
    points, _, facets, values = read_mesh_arrays(model.path)
    centres = points[facets[values == model.boundary_ids["oral"]]].mean(axis=1)
    lips = np.array([model.markers[name] for name in ("upper_lip_4", "lower_lip_4")])
    corners = np.array([model.markers[name] for name in ("mouth_corner_left", "mouth_corner_right")])
    assert len(centres) > 50
    # Behind the lips' skin, no higher than the nose and no lower than the chin.
    assert np.all(centres[:, 2] < lips[:, 2].min())
    assert np.all(centres[:, 1] < model.markers["nose_tip"][1])
    assert np.all(centres[:, 1] > model.markers["chin_5"][1])
    # Both sides, past the mouth corners (the cheeks' lining).
    assert centres[:, 0].min() < corners[:, 0].min() and centres[:, 0].max() > corners[:, 0].max()


def test_no_cranium_facets(copy):
    edit_toml(copy, r"^cranium = \d+$", "cranium = 99")
    with pytest.raises(ModelError, match=r"mesh\.xdmf: no facets tagged cranium"):
        load(copy)


def test_marker_off_the_skin(copy):
    marker = tomllib.loads((copy / "model.toml").read_text())["markers"]["chin_2"]
    edit_toml(copy, r"^chin_2 = .*$", f"chin_2 = {toml_value(np.array(marker) + [0, 0, 5.0])}")
    with pytest.raises(ModelError, match=r"model\.toml: markers farther than 1.0 mm from the skin \(1 of 79\): chin_2 \([45]\."):
        load(copy)


def test_expression_with_unknown_muscle(copy):
    edit_toml(copy, r"^\[expressions\.smile\]$", "[expressions.smile]\nzygomaticus_mayor_left = 0.5")
    with pytest.raises(ModelError, match="did you mean zygomaticus_major_left"):
        load(copy)


def test_mesh_partition_is_reproducible(builtin_model_path):
    """Two loads give every rank the same cells (DOLFINx's SCOTCH partition did not), with ghost
    cells across the cut, and the cells add up to the whole mesh."""
    from mpi4py import MPI
    from face_dolfinx.model.folder import load_model

    def owned_cells():
        mesh = load_model(builtin_model_path, MPI.COMM_WORLD).mesh
        cells = mesh.topology.index_map(3)
        return np.sort(np.asarray(mesh.topology.original_cell_index[:cells.size_local])), cells

    first, cells = owned_cells()
    second, _ = owned_cells()
    assert np.array_equal(first, second)
    assert MPI.COMM_WORLD.allreduce(len(first)) == cells.size_global
    if MPI.COMM_WORLD.size > 1:
        assert cells.num_ghosts > 0
