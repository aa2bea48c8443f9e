"""Subject adaptation (face_dolfinx.subjects.adaptation, `build --subject` and `build --surface`): the built-in
5K face warped onto synthetic subjects whose true shape is known."""
import json

import meshio
from mpi4py import MPI
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from face_dolfinx.alignment.similarity import Similarity
from face_dolfinx.capture import Capture, write_capture
from face_dolfinx.cli.main import main
from face_dolfinx.model.folder import load_model
from face_dolfinx.subjects.adaptation import SubjectError, adapt_to_markers
from face_dolfinx.alignment.surface import SkinSurface
from face_dolfinx.subjects.warp import inverted_tets
from user_capture import user_sites, write_correspondence
from conftest import on_rank_0

# The subject: the template stretched, sheared and moved (an affine map, which the warp's affine
# part reproduces exactly), in a lab frame of its own.
STRETCH = np.array([[1.08, 0.06, 0.0], [0.0, 0.94, 0.07], [0.04, 0.0, 1.03]])
LAB = Similarity(1.0, Rotation.from_euler("xyz", [-15.0, 30.0, 5.0], degrees=True).as_matrix(), [-300.0, 50.0, 700.0])
# A 3 mm puff of the left cheek (sigma 15 mm) on top, for the scan: a shape no affine map gives.
PUFF_MM, PUFF_CENTRE, PUFF_SIGMA = 3.0, np.array([35.0, -10.0, 95.0]), 15.0


def affine_subject(points):
    return LAB.apply(points @ STRETCH.T)


def puffed_subject(points):
    puff = PUFF_MM * np.exp(-np.sum((points - PUFF_CENTRE) ** 2, axis=-1) / (2 * PUFF_SIGMA ** 2))
    return affine_subject(points + puff[..., None] * np.array([0.5, 0.0, 1.0]) / np.sqrt(1.25))




def to_template(folder) -> Similarity:
    """The rigid map from the subject's frame to the adapted model's, as subject.json records it."""
    record = json.loads((folder / "subject.json").read_text())["to_template"]
    return Similarity(record["scale"], record["rotation"], record["translation"])


def fibers_of(folder, model):
    archive = np.load(folder / "muscles.npz")
    return {name: (archive[f"{name}/cells"], archive[f"{name}/fiber"]) for name in model.muscle_names}


def check_is_a_valid_model(folder, template):
    """Loads; same cells and tags; unit fibers; no tet inverted."""
    model = load_model(folder)
    assert model.muscle_names == [m.name for m in template.muscles]
    with __import__("h5py").File(folder / "mesh.h5", "r") as h5:
        points, cells = h5["Mesh/flesh/geometry"][...], h5["Mesh/flesh/topology"][...]
    np.testing.assert_array_equal(cells, template.cells)
    assert inverted_tets(points, cells).size == 0
    for _, fiber in fibers_of(folder, model).values():
        np.testing.assert_allclose(np.linalg.norm(fiber, axis=1), 1.0, atol=1e-12)
    return model, points


def test_the_template_own_markers_give_the_template_back(template):
    """Markers at the template's own sites, seen in a lab frame: the rigid alignment removes the
    frame and the warp has nothing left to do, so the adapted model is the template."""
    names, sites, correspondence = user_sites(template)
    adaptation = adapt_to_markers(template, LAB.apply(sites), names, correspondence, name="same")
    np.testing.assert_allclose(adaptation.to_template.apply(LAB.apply(sites)), sites, atol=1e-9)
    np.testing.assert_allclose(adaptation.model.points, template.points, atol=1e-6)
    assert adaptation.max < 1e-6 and set(adaptation.distances) == set(names)
    assert adaptation.model.name == "same" and np.array_equal(adaptation.model.cells, template.cells)


def test_a_marker_missing_in_the_neutral_frame_is_named(template):
    names, sites, correspondence = user_sites(template)
    sites[3] = np.nan
    with pytest.raises(SubjectError, match=f"markers missing in the neutral frame: {names[3]}; every marker"):
        adapt_to_markers(template, sites, names, correspondence, name="gap")


def test_subject_from_a_capture(template, builtin_model_path, shared_dir):
    """The subject's markers are the template's sites and landmarks under an affine map. The warp
    reproduces an affine map exactly, so everything (nodes, skin through the markers, fibers, jaw)
    must match the map to what the TRC file keeps of it: 10 significant digits, 1e-5 mm here."""
    names, sites, correspondence = user_sites(template)
    take = shared_dir / "subject.trc"
    on_rank_0(lambda: write_capture(Capture(names, np.stack([affine_subject(sites)] * 2), 60.0), take))
    pairs = write_correspondence(shared_dir / "subject.toml", correspondence)
    out = shared_dir / "subject_model"
    assert main(["build", "--subject", str(take), "--correspondence", str(pairs), "--model",
                 str(builtin_model_path), "--out", str(out)]) == 0

    model, points = check_is_a_valid_model(out, template)
    frame = to_template(out)
    assert frame.scale == 1.0  # rigid: the subject keeps its size
    truth = frame @ LAB  # template points -> STRETCH -> new model's frame

    def expected(x):
        return truth.apply(x @ STRETCH.T)
    np.testing.assert_allclose(points, expected(template.points), rtol=0, atol=1e-4)
    skin = SkinSurface(*model.skin_surface())
    markers = frame.apply(affine_subject(sites))
    assert skin.closest(markers)[3].max() < 1e-4
    for name, (_, fiber) in fibers_of(out, model).items():
        index = [m.name for m in template.muscles].index(name)
        stretched = template.muscles[index].fiber @ (truth.rotation @ STRETCH).T
        np.testing.assert_allclose(fiber, stretched / np.linalg.norm(stretched, axis=1)[:, None], atol=1e-6)
    np.testing.assert_allclose(model.jaw.condyle_left, expected(template.jaw.condyle_left), atol=1e-4)
    np.testing.assert_allclose(model.landmarks["nose_tip"], expected(template.landmarks["nose_tip"]), atol=1e-4)
    assert list(model.markers) == list(template.markers)  # the template's sites, carried along
    info = __import__("tomllib").loads((out / "model.toml").read_text())["generator"]
    assert info["residual_max_mm"] < 1e-4 and info["subject_capture"] == str(take.resolve())


def pushed_capture(template, shared_dir, name, marker, depth):
    """The template's sites with one marker moved ``depth`` mm into the face (along the skin's
    inward normal; negative: out of it), as a capture, with its correspondence file."""
    names, sites, correspondence = user_sites(template)
    skin = template.skin()
    triangle = skin.closest(sites)[0]
    index = names.index(marker)
    pushed = sites.copy()
    pushed[index] -= depth * skin.triangle_normals[triangle[index]]
    take = shared_dir / f"{name}.trc"
    on_rank_0(lambda: write_capture(Capture(names, pushed[None], 60.0), take))
    return take, write_correspondence(shared_dir / f"{name}.toml", correspondence), pushed[index]


def test_a_landmark_deep_inside_the_face_gives_a_valid_model(template, builtin_model_path, shared_dir):
    """The upper lip's landmark 20 mm inside the face: the skin follows it there (a free-space
    warp inverted tets here), the flesh is carried along without inverting a tet."""
    take, pairs, target = pushed_capture(template, shared_dir, "pushed", "M05", 20.0)
    out = shared_dir / "pushed_model"
    assert main(["build", "--subject", str(take), "--correspondence", str(pairs), "--model",
                 str(builtin_model_path), "--out", str(out)]) == 0
    model, _ = check_is_a_valid_model(out, template)
    record = json.loads((out / "subject.json").read_text())
    assert record["markers"]["M05"]["skin_distance_mm"] < 1.0
    assert np.linalg.norm(model.landmarks["upper_lip_center"] - to_template(out).apply(target)) < 1.0
    assert record["min_quality_after"] > 0.01


def test_a_marker_off_the_face_is_refused(template, builtin_model_path, shared_dir):
    """A marker 60 mm in front of the skin cannot be matched: refused, naming it, nothing written."""
    take, pairs, _ = pushed_capture(template, shared_dir, "stray", "M20", -60.0)
    out = shared_dir / "stray_model"
    with pytest.raises(SystemExit, match=r"stray\.trc: markers that cannot be matched to the skin: M20 \(\d+\.\d mm\)"):
        main(["build", "--subject", str(take), "--correspondence", str(pairs), "--model",
              str(builtin_model_path), "--out", str(out)])
    MPI.COMM_WORLD.barrier()
    assert not [p for p in shared_dir.iterdir() if "stray_model" in p.name]


def write_scan(template, path, subject, units_per_mm=1.0):
    """The template's skin triangles under ``subject`` as a surface file, the landmarks' subject
    positions appended as extra (unconnected) vertices; and a landmark file naming half of them by
    vertex id and half by coordinates."""
    skin = template.skin()
    nodes = template.skin_nodes
    index = np.full(len(template.points), -1)
    index[nodes] = np.arange(len(nodes))
    landmarks = subject(np.array(list(template.landmarks.values()))) * units_per_mm
    points = np.vstack([subject(template.points[nodes]) * units_per_mm, landmarks])
    lines = ["[landmarks]"]
    for k, name in enumerate(template.landmarks):
        lines.append(f"{name} = {len(nodes) + k}" if k % 2 else f"{name} = {landmarks[k].tolist()}")

    def write():
        meshio.write(path, meshio.Mesh(points, [("triangle", index[skin.triangles].astype(np.int32))]))
        path.with_suffix(".toml").write_text("\n".join(lines) + "\n")
    on_rank_0(write)
    return path, path.with_suffix(".toml")


def test_subject_from_a_surface_scan(template, builtin_model_path, shared_dir):
    """An OBJ of the puffed subject's face. The registered skin lies on the scan wherever the scan
    goes on (nodes whose closest scan point is on the scan's open border are beyond it and not
    checked); the landmarks land on their subject points."""
    scan, landmarks = write_scan(template, shared_dir / "face.obj", puffed_subject)
    out = shared_dir / "scan_model"
    assert main(["build", "--surface", str(scan), "--landmarks", str(landmarks), "--model",
                 str(builtin_model_path), "--out", str(out)]) == 0
    model, points = check_is_a_valid_model(out, template)
    frame = to_template(out)
    surface = meshio.read(scan)
    triangles = surface.cells_dict["triangle"]
    scan_surface = SkinSurface(frame.apply(surface.points), triangles)
    skin_points, _ = model.skin_surface()
    triangle, barycentric, _, distance = scan_surface.closest(skin_points)
    edges, counts = np.unique(np.sort(triangles[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1), axis=0,
                              return_counts=True)
    border = np.unique(edges[counts == 1])
    on_edge = barycentric <= 1e-9
    inside = ~(on_edge.any(axis=1) & np.all(np.isin(triangles[triangle], border) | on_edge, axis=1))
    assert inside.mean() > 0.8
    assert distance[inside].max() < 0.1
    assert np.sqrt(np.mean(distance[inside] ** 2)) < 0.01
    for name, point in template.landmarks.items():
        assert np.linalg.norm(model.landmarks[name] - frame.apply(puffed_subject(point))) < 0.1
    record = json.loads((out / "subject.json").read_text())
    assert record["residual_max_mm"] < 0.1 and record["settled"]


def test_a_scan_in_centimetres(template, builtin_model_path, shared_dir):
    scan, landmarks = write_scan(template, shared_dir / "face_cm.ply", affine_subject, units_per_mm=0.1)
    out = shared_dir / "cm_model"
    arguments = ["build", "--surface", str(scan), "--landmarks", str(landmarks), "--model",
                 str(builtin_model_path), "--out", str(out)]
    with pytest.raises(SystemExit, match=r"face_cm\.ply: the surface's landmarks span 0\.10\d times the "
                                         r"template's: .* likely a unit mistake; looks like cm: pass --units cm"):
        main(arguments)
    MPI.COMM_WORLD.barrier()
    assert not out.exists()
    assert main(arguments + ["--units", "cm"]) == 0
    _, points = check_is_a_valid_model(out, template)
    # Matched to closest scan points, skin nodes may slide along the scan by what the matching
    # leaves unsettled (AFFINE_SETTLED_MM); everything else follows them.
    np.testing.assert_allclose(points, (to_template(out) @ LAB).apply(template.points @ STRETCH.T), atol=1e-2)


def test_surface_input_errors(template, builtin_model_path, shared_dir):
    scan, landmarks = write_scan(template, shared_dir / "errors.obj", affine_subject)
    model = ["--model", str(builtin_model_path), "--out", str(shared_dir / "never")]
    text = shared_dir / "face.txt"
    on_rank_0(lambda: text.write_text("not a mesh\n"))
    few = shared_dir / "few.toml"
    on_rank_0(lambda: few.write_text("[landmarks]\nnose_tip = 0\nnasion = 1\nchin = 2\nmenton = 3\nglabella = 4\n"))
    wrong = shared_dir / "wrong.csv"
    on_rank_0(lambda: wrong.write_text("landmark,vertex\nnose_tip,0\nnose_top,1\nchin,2\nmenton,3\n"
                                       "glabella,4\nnasion,5\nsubnasale,6\n"))
    far = shared_dir / "far.toml"
    on_rank_0(lambda: far.write_text("[landmarks]\nnose_tip = 100000\n"))
    for argv, message in [
        (["--surface", str(text), "--landmarks", str(landmarks)], r"face\.txt: unknown surface format '\.txt'"),
        (["--surface", str(shared_dir / "absent.stl"), "--landmarks", str(landmarks)], r"absent\.stl: file not found"),
        (["--surface", str(scan), "--landmarks", str(few)],
         r"errors\.obj: only 5 usable landmarks; at least 6 are needed"),
        (["--surface", str(scan), "--landmarks", str(wrong)],
         r"errors\.obj: not landmarks of model builtin-face: nose_top"),
        (["--surface", str(scan), "--landmarks", str(far)],
         r"far\.toml: nose_tip = 100000: the vertex ids of errors\.obj run from 0 to \d+"),
    ]:
        with pytest.raises(SystemExit, match=message):
            main(["build", *argv, *model])
    assert not (shared_dir / "never").exists()
    with pytest.raises(SystemExit) as usage:
        main(["build", "--surface", str(scan), *model])
    assert usage.value.code == 2  # --surface needs --landmarks: argparse's usage error
