"""The built-in face generator: resolution, element quality, tags, muscles, sites, jaw, cache.

Checks run on the files of the small built-in face (meshes/small_face/, tests/conftest.py), read
with h5py, so they are the same on every rank; checks of the distributed mesh live in test_model.py.
"""
import json
import os
import tomllib

import h5py
import numpy as np
import pytest
from mpi4py import MPI

from face_dolfinx.model.anatomy import build_builtin_face, builder
from face_dolfinx.model.anatomy.builder import SMALL_FACE_TETS
from face_dolfinx.model.anatomy.description import load_description
from face_dolfinx.model.folder import tet_volumes_and_quality
from face_dolfinx.model.surface_file import read_triangle_surface
from face_dolfinx.alignment.surface import SkinSurface

PAIRED_MUSCLES = [
    "frontalis", "corrugator", "orbicularis_oculi", "levator_labii_superioris_alaeque_nasi",
    "levator_labii_superioris", "zygomaticus_minor", "zygomaticus_major", "levator_anguli_oris",
    "risorius", "buccinator", "depressor_anguli_oris", "depressor_labii_inferioris", "mentalis",
    "orbicularis_oris_upper", "orbicularis_oris_lower", "platysma"]
LANDMARKS = ["nose_tip", "nasion", "subnasale", "glabella", "mouth_corner_left", "mouth_corner_right",
             "upper_lip_center", "lower_lip_center", "chin", "menton", "eye_inner_corner_left",
             "eye_inner_corner_right", "eye_outer_corner_left", "eye_outer_corner_right",
             "brow_center_left", "brow_center_right", "cheekbone_left", "cheekbone_right",
             "jaw_angle_left", "jaw_angle_right"]


class FaceFiles:
    """The arrays of a model folder, as written."""

    def __init__(self, folder):
        self.meta = tomllib.loads((folder / "model.toml").read_text())
        with h5py.File(folder / "mesh.h5") as h5:
            self.points = h5["Mesh/flesh/geometry"][:]
            self.tets = h5["Mesh/flesh/topology"][:]
            self.facets = h5["MeshTags/boundaries/topology"][:]
            self.values = h5["MeshTags/boundaries/Values"][:].ravel()
        archive = np.load(folder / "muscles.npz")
        self.muscles = {m["name"]: {part: archive[f"{m['name']}/{part}"] for part in ("cells", "fraction", "fiber")}
                        for m in self.meta["muscles"]}

    def tagged(self, name):
        return self.facets[self.values == self.meta["boundaries"][name]]

    def outward_normals(self, facets):
        """Unit normals of boundary triangles, pointing away from the tet they bound."""
        faces = np.concatenate([self.tets[:, [1, 2, 3]], self.tets[:, [0, 2, 3]],
                                self.tets[:, [0, 1, 3]], self.tets[:, [0, 1, 2]]])
        apex = self.tets.T.reshape(-1)            # the vertex each face above leaves out
        key_faces, key_facets = (np.sort(f, axis=1) @ np.array([1, 2**20, 2**40]) for f in (faces, facets))
        order = np.argsort(key_faces)
        where = order[np.searchsorted(key_faces[order], key_facets)]
        assert np.array_equal(key_faces[where], key_facets), "a tagged facet is not a tet face"
        a, b, c = (self.points[facets[:, k]] for k in range(3))
        normal = np.cross(b - a, c - a)
        normal[np.einsum("ij,ij->i", normal, self.points[apex[where]] - a) > 0] *= -1
        return normal / np.linalg.norm(normal, axis=1, keepdims=True)


@pytest.fixture(scope="module")
def face(builtin_model_path):
    return FaceFiles(builtin_model_path)


def test_tet_count_near_target(face):
    count = len(face.tets)
    assert SMALL_FACE_TETS / 1.5 < count < SMALL_FACE_TETS * 1.5
    assert face.meta["generator"]["tets"] == count


def test_no_inverted_or_degenerate_tets(face):
    volume, quality = tet_volumes_and_quality(face.points[face.tets])
    assert volume.min() > 0
    assert quality.min() > 0.05, f"worst tet quality {quality.min():.3g}"
    assert len(np.unique(face.tets)) == len(face.points), "every node belongs to a tet"


def test_face_dimensions(face):
    """Head ~150 mm wide, nasion to menton ~120 mm, facing +z."""
    landmarks = {k: np.array(v) for k, v in face.meta["landmarks"].items()}
    width = np.ptp(face.points[:, 0])
    assert 130 < width < 170
    assert 105 < landmarks["nasion"][1] - landmarks["menton"][1] < 135
    assert landmarks["nose_tip"][2] > landmarks["nasion"][2] + 15   # the nose sticks out forwards
    assert landmarks["eye_outer_corner_left"][0] > landmarks["eye_inner_corner_left"][0] > 0


def test_boundary_tags(face):
    counts = {name: len(face.tagged(name)) for name in ("cranium", "mandible", "skin", "free")}
    assert all(counts.values()), counts
    # Every exterior facet is tagged, every tagged facet is exterior.
    faces = np.sort(np.concatenate([face.tets[:, [1, 2, 3]], face.tets[:, [0, 2, 3]],
                                    face.tets[:, [0, 1, 3]], face.tets[:, [0, 1, 2]]]), axis=1)
    unique, multiplicity = np.unique(faces, axis=0, return_counts=True)
    exterior = {tuple(f) for f in unique[multiplicity == 1]}
    assert exterior == {tuple(f) for f in np.sort(face.facets, axis=1)}


def test_bones_do_not_share_nodes(face):
    """A free band separates cranium from mandible: no node is pulled by both bones."""
    shared = np.intersect1d(face.tagged("cranium"), face.tagged("mandible"))
    assert shared.size == 0


def test_mouth_slit_separates_the_lips(face):
    """The lip surfaces facing each other inside the slit are skin, and no tet bridges them."""
    landmarks = {k: np.array(v) for k, v in face.meta["landmarks"].items()}
    skin = face.tagged("skin")
    normal = face.outward_normals(skin)
    centre = face.points[skin].mean(axis=1)
    upper, lower = landmarks["upper_lip_center"], landmarks["lower_lip_center"]
    # Between the two lip centres on the skin, inside the corners, behind the lips' front.
    mouth = ((np.abs(centre[:, 0]) < 0.8 * landmarks["mouth_corner_left"][0])
             & (centre[:, 1] < upper[1]) & (centre[:, 1] > lower[1])
             & (centre[:, 2] < max(upper[2], lower[2])))
    upper_lip = np.unique(skin[mouth & (normal[:, 1] < -0.8)])   # facing down into the slit
    lower_lip = np.unique(skin[mouth & (normal[:, 1] > 0.8)])    # facing up
    commissure = np.intersect1d(upper_lip, lower_lip)
    upper_lip, lower_lip = np.setdiff1d(upper_lip, commissure), np.setdiff1d(lower_lip, commissure)
    assert len(upper_lip) >= 5 and len(lower_lip) >= 5
    bridging = np.isin(face.tets, upper_lip).any(axis=1) & np.isin(face.tets, lower_lip).any(axis=1)
    assert not bridging.any(), f"{bridging.sum()} tets connect the upper and the lower lip"


def test_all_32_muscles(face):
    expected = [f"{name}_{side}" for name in PAIRED_MUSCLES for side in ("left", "right")]
    assert sorted(face.muscles) == sorted(expected)
    for name, muscle in face.muscles.items():
        assert len(muscle["cells"]) > 0, name
        assert np.all((muscle["fraction"] > 0) & (muscle["fraction"] <= 1)), name
        assert np.allclose(np.linalg.norm(muscle["fiber"], axis=1), 1.0, atol=1e-12), name
        assert muscle["cells"].max() < len(face.tets)


def test_muscles_are_mirror_images(face):
    """Left and right muscles embed the same volume (the mesh is nearly symmetric)."""
    volume, _ = tet_volumes_and_quality(face.points[face.tets])
    for name in PAIRED_MUSCLES:
        left, right = (face.muscles[f"{name}_{side}"] for side in ("left", "right"))
        v_left, v_right = ((m["fraction"] * volume[m["cells"]]).sum() for m in (left, right))
        assert abs(v_left - v_right) < 0.15 * v_left, name
        centroid_x = face.points[face.tets[left["cells"]]].mean(axis=1)[:, 0]
        assert np.average(centroid_x, weights=left["fraction"]) > 0, f"{name}_left is on the +x side"


def test_sphincter_fibers_circulate(face):
    """Sphincter fibers run around their centre: consistently oriented, within 60 degrees of the
    circumferential direction axis x (x - centre) and close to it on average. (They follow the
    elliptic opening, so they are not exactly circular.)"""
    sphincters = [m for m in face.meta["muscles"] if m["kind"] == "sphincter"]
    assert {m["name"] for m in sphincters} >= {f"orbicularis_oris_{p}_{s}" for p in ("upper", "lower")
                                                for s in ("left", "right")}
    mouth = (np.array(face.meta["landmarks"]["mouth_corner_left"])
             + np.array(face.meta["landmarks"]["mouth_corner_right"])) / 2
    for entry in sphincters:
        centre, axis = np.array(entry["center"]), np.array(entry["axis"])
        muscle = face.muscles[entry["name"]]
        radial = face.points[face.tets[muscle["cells"]]].mean(axis=1) - centre
        radial -= np.outer(radial @ axis, axis)
        radial /= np.linalg.norm(radial, axis=1, keepdims=True)
        circumferential = np.einsum("ij,ij->i", muscle["fiber"], np.cross(axis, radial))
        assert circumferential.min() > 0.5, entry["name"]
        assert np.average(circumferential, weights=muscle["fraction"]) > 0.8, entry["name"]
        if entry["name"].startswith("orbicularis_oris"):
            assert np.linalg.norm(centre - mouth) < 15.0


def test_markers_and_landmarks_on_the_skin(face):
    markers, landmarks = face.meta["markers"], face.meta["landmarks"]
    assert len(markers) == 79
    assert set(LANDMARKS) <= set(landmarks) and len(landmarks) >= 20
    for name in ("mouth_corner_left", "upper_lip_1", "chin_3", "cheek_left_2", "jaw_left_4",
                 "brow_left_2", "forehead_3", "nose_tip"):
        assert name in markers
    skin = SkinSurface(face.points, face.tagged("skin"))
    for sites in (markers, landmarks):
        distance = skin.closest(np.array(list(sites.values())))[3]
        assert distance.max() < 1e-6
    # Dense around the mouth and jaw, as in the paper's capture.
    lower_face = sum(1 for p in markers.values() if p[1] < markers["nose_tip"][1])
    assert lower_face > 0.6 * len(markers)


def test_jaw_geometry(face):
    jaw = face.meta["jaw"]
    right, left = np.array(jaw["condyle_right"]), np.array(jaw["condyle_left"])
    assert np.allclose(right * [-1, 1, 1], left)                     # symmetric
    assert 80 < np.linalg.norm(left - right) < 120                   # intercondylar distance
    v = np.array(jaw["slide_direction"])
    assert v[2] > 0.9 and -0.5 < v[1] < 0                           # forwards, slightly down
    assert 5 <= jaw["track_length"] <= 15 and 0.15 <= jaw["max_opening_sine"] <= 0.5
    # Opening about the condyle axis swings the chin down and back.
    angle = np.arcsin(jaw["max_opening_sine"])
    chin = np.array(face.meta["landmarks"]["menton"]) - (left + right) / 2
    opened = np.array([chin[0], chin[1] * np.cos(angle) - chin[2] * np.sin(angle),
                       chin[1] * np.sin(angle) + chin[2] * np.cos(angle)])
    assert opened[1] < chin[1] - 20
    # The mandible-attached flesh lies below the condyles and in front of the ear.
    mandible_nodes = face.points[np.unique(face.tagged("mandible"))]
    assert mandible_nodes[:, 1].max() < left[1]


def test_expressions(face):
    expressions = face.meta["expressions"]
    assert {"neutral", "smile", "jaw_open", "brow_raise", "frown", "pucker", "sneer"} <= set(expressions)
    for name, activations in expressions.items():
        for muscle, value in activations.items():
            if muscle == "jaw_opening_deg":
                assert 0 <= value <= np.degrees(np.arcsin(face.meta["jaw"]["max_opening_sine"]))
            else:
                assert muscle in face.muscles and 0 <= value <= 1, (name, muscle)
    assert expressions["jaw_open"]["jaw_opening_deg"] > 0


def test_second_build_is_a_cache_hit(monkeypatch):
    """The same description and size again: the cached folder, nothing generated."""
    first = build_builtin_face(target_tets=SMALL_FACE_TETS, comm=MPI.COMM_WORLD)

    def generates(description, target_tets, folder):
        raise AssertionError("the cached face was built again")

    monkeypatch.setattr(builder, "generate", generates)
    again = build_builtin_face(target_tets=SMALL_FACE_TETS, comm=MPI.COMM_WORLD)
    assert again == first


def test_the_committed_small_face_is_the_current_generators(builtin_model_path):
    """The tests' face (meshes/small_face/) was built from the current description and generator
    (the cache key covers both): after a change, ``python meshes/freeze_small_face.py``."""
    recorded = json.loads((builtin_model_path / "provenance.json").read_text())
    current = builder.cache_key(load_description(builder.DESCRIPTION_FILE), SMALL_FACE_TETS)
    assert recorded["cache_key"] == current, "meshes/small_face/ is stale: run python meshes/freeze_small_face.py"


def test_the_generator_builds_the_committed_small_face_bit_for_bit(builtin_model_path):
    """The same face on every machine: built here, the small face is the committed one to the bit
    (mesh, tags, muscles, teeth), whichever CPU built either (provenance.json says which). numpy's
    own sin, cos, exp and power differ in the last bit between CPUs with and without AVX-512, and
    gmsh made that another mesh (5 064 tets against 5 136): the generator takes them from the C
    library (model/anatomy/libm.py)."""
    built = build_builtin_face(target_tets=SMALL_FACE_TETS, comm=MPI.COMM_WORLD)

    def datasets(f):
        names = []
        f.visititems(lambda name, item: names.append(name) if isinstance(item, h5py.Dataset) else None)
        return sorted(names)

    with h5py.File(built / "mesh.h5", "r") as new, h5py.File(builtin_model_path / "mesh.h5", "r") as old:
        assert datasets(new) == datasets(old)
        for name in datasets(old):
            assert np.array_equal(new[name][()], old[name][()]), name
    with np.load(built / "muscles.npz") as new, np.load(builtin_model_path / "muscles.npz") as old:
        assert sorted(new.files) == sorted(old.files)
        for name in old.files:
            assert np.array_equal(new[name], old[name]), name
    for teeth in sorted(path.name for path in builtin_model_path.glob("teeth_*.ply")):
        for new, old in zip(read_triangle_surface(built / teeth), read_triangle_surface(builtin_model_path / teeth)):
            assert np.array_equal(new, old), teeth


def test_killed_build_leaves_nothing_that_looks_complete(tmp_path, monkeypatch):
    """A build that dies half way leaves neither the cache folder nor its temporary files."""
    def dies_half_way(description, target_tets, folder):
        (folder / "model.toml").write_text("name = 'half'\n")
        raise KeyboardInterrupt

    monkeypatch.setattr(builder, "generate", dies_half_way)
    with pytest.raises(KeyboardInterrupt):
        build_builtin_face(target_tets=SMALL_FACE_TETS, cache_dir=tmp_path, comm=MPI.COMM_SELF)
    assert os.listdir(tmp_path) == []
