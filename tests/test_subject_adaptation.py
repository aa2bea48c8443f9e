"""Subject adaptation on subjects that stress it (face_dolfinx.subjects: registration, elastic, adaptation):
proportions unlike the template's, markers over the eye openings, a scan with an open border and
another extent, in centimetres; and bad input refused with one message, nothing left behind."""
import json

import meshio
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from face_dolfinx.alignment.similarity import Similarity
from face_dolfinx.alignment.surface import SkinSurface
from face_dolfinx.capture import Capture, write_capture
from face_dolfinx.cli.main import main
from face_dolfinx.model.folder import load_model, tet_volumes_and_quality
from face_dolfinx.subjects.elastic import PseudoElasticCarry
from face_dolfinx.subjects.warp import inverted_tets
from user_capture import user_sites, write_correspondence
from conftest import on_rank_0

LAB = Similarity(1.0, Rotation.from_euler("xyz", [10.0, -20.0, 4.0], degrees=True).as_matrix(), [120.0, -40.0, 900.0])
CHANGE = 0.2   # the subject's mouth 20 % wider, eyes 16 % narrower (corner to corner)
CHIN_CHANGE = 0.28  # lower lip to menton 20 % longer




class Proportions:
    """A smooth map of space giving the template a subject's proportions: the mouth region
    widened, everything below the lower lip lengthened, each eye region narrowed. Widening and
    narrowing are uniform within a plateau (the mouth and eye corners inside it) and fade out
    beyond it over a Gaussian; the map's Jacobian stays positive."""

    def __init__(self, template):
        lm = template.landmarks
        self.mouth = 0.5 * (lm["mouth_corner_left"] + lm["mouth_corner_right"])
        self.lip = lm["lower_lip_center"][1]
        self.eyes = [0.5 * (lm[f"eye_inner_corner_{s}"] + lm[f"eye_outer_corner_{s}"]) for s in ("left", "right")]

    @staticmethod
    def plateau(points, centre, radius, sigma):
        beyond = np.maximum(np.linalg.norm(points - centre, axis=-1) - radius, 0.0)
        return np.exp(-beyond ** 2 / (2 * sigma ** 2))

    def __call__(self, points):
        points = np.asarray(points, dtype=float)
        moved = points.copy()
        moved[..., 0] += CHANGE * (points[..., 0] - self.mouth[0]) * self.plateau(points, self.mouth, 28.0, 12.0)
        below = 5.0 * np.logaddexp(0.0, (self.lip - points[..., 1]) / 5.0)  # smooth max(0, lip - y)
        moved[..., 1] -= CHIN_CHANGE * below
        for eye in self.eyes:
            moved[..., 0] -= CHANGE * (points[..., 0] - eye[0]) * self.plateau(points, eye, 18.0, 10.0)
        return moved


def eye_opening_centres(template):
    """Points over the template's eye openings: the centroid of each eye opening's rim."""
    triangles = template.skin_triangles
    edges, counts = np.unique(np.sort(triangles[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1), axis=0,
                              return_counts=True)
    rim = np.unique(edges[counts == 1])
    centres = []
    for side in ("left", "right"):
        eye = 0.5 * (template.landmarks[f"eye_inner_corner_{side}"] + template.landmarks[f"eye_outer_corner_{side}"])
        near = rim[np.linalg.norm(template.points[rim] - eye, axis=1) < 25.0]
        centres.append(template.points[near].mean(axis=0))
    return np.array(centres)


def check_valid(folder, template):
    model = load_model(folder)
    with __import__("h5py").File(folder / "mesh.h5", "r") as h5:
        points, cells = h5["Mesh/flesh/geometry"][...], h5["Mesh/flesh/topology"][...]
    np.testing.assert_array_equal(cells, template.cells)
    assert inverted_tets(points, cells).size == 0
    _, quality = tet_volumes_and_quality(points[cells])
    return model, points, quality


def to_template(folder) -> Similarity:
    record = json.loads((folder / "subject.json").read_text())["to_template"]
    return Similarity(record["scale"], record["rotation"], record["translation"])


def test_a_homogeneous_skin_motion_moves_the_flesh_alike(template):
    """The pseudo-elastic solve with every boundary node moved by one affine map: a homogeneous
    deformation is the equilibrium, so the interior nodes must follow the same map to solver
    accuracy (with free inner surfaces it would not be: its stress would pull on them)."""
    boundary = np.unique(template.facets)
    matrix = np.array([[1.1, 0.05, 0.0], [0.0, 0.9, 0.1], [0.02, 0.0, 1.05]])
    carry = PseudoElasticCarry(template.points, template.cells, boundary)
    expected = template.points @ matrix.T + [3.0, -2.0, 1.0]
    moved, report = carry.solve(expected[boundary] - template.points[boundary])
    assert report.newton_iterations >= 1
    np.testing.assert_allclose(moved, expected, atol=1e-6)


def test_a_subject_with_other_proportions(template, builtin_model_path, shared_dir):
    """Mouth 20 % wider, chin 20 % longer, eyes 20 % narrower, two more markers over the eye
    openings (closed eyelids on a template with open eyes): a valid model (no tet inverted or
    flattened) whose skin passes within 1 mm RMS of the markers on the skin, its landmarks near
    the subject's, its mouth wider and its eyes narrower by about the subject's change; the eyelid
    markers are reported as over an opening."""
    subject_map = Proportions(template)
    names, sites, correspondence = user_sites(template)
    names += ["eyelid_left", "eyelid_right"]
    sites = np.vstack([sites, eye_opening_centres(template)])
    take = shared_dir / "proportions.trc"
    on_rank_0(lambda: write_capture(Capture(names, np.stack([LAB.apply(subject_map(sites))] * 2), 60.0), take))
    pairs = write_correspondence(shared_dir / "proportions.toml", correspondence)
    out = shared_dir / "proportions_model"
    assert main(["build", "--subject", str(take), "--correspondence", str(pairs), "--model",
                 str(builtin_model_path), "--out", str(out)]) == 0
    model, _, quality = check_valid(out, template)
    record = json.loads((out / "subject.json").read_text())
    assert record["markers_over_openings"] == ["eyelid_left", "eyelid_right"]
    assert record["residual_rms_mm"] <= 1.0
    assert quality.min() == pytest.approx(record["min_quality_after"]) and quality.min() > 0.01
    assert set(record["muscle_volume_mm3"]) == set(model.muscle_names)
    frame = to_template(out)
    truth = frame @ LAB
    for landmark, point in template.landmarks.items():
        assert np.linalg.norm(model.landmarks[landmark] - truth.apply(subject_map(point))) < 1.5, landmark

    for a, b, change in [("mouth_corner_left", "mouth_corner_right", 1.2),
                         ("eye_inner_corner_left", "eye_outer_corner_left", 0.84),
                         ("eye_inner_corner_right", "eye_outer_corner_right", 0.84),
                         ("lower_lip_center", "menton", 1.2)]:
        before = np.linalg.norm(template.landmarks[a] - template.landmarks[b])
        truth = np.linalg.norm(subject_map(template.landmarks[a]) - subject_map(template.landmarks[b])) / before
        assert truth == pytest.approx(change, abs=0.01)
        assert np.linalg.norm(model.landmarks[a] - model.landmarks[b]) / before == pytest.approx(truth, abs=0.03)


def subdivided_skin(template, subject_map, keep):
    """The template's skin split 1:4 (so the scan's vertices are not the template's nodes), under
    ``subject_map``, keeping the triangles whose centroid ``keep`` accepts: an open border."""
    points, triangles = template.skin_surface()
    edges = np.sort(triangles[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 3, 2), axis=2)
    unique, inverse = np.unique(edges.reshape(-1, 2), axis=0, return_inverse=True)
    middle = len(points) + inverse.reshape(-1, 3)
    fine_points = np.vstack([points, 0.5 * (points[unique[:, 0]] + points[unique[:, 1]])])
    a, b, c = triangles.T
    ab, bc, ca = middle.T
    fine = np.concatenate([np.stack(t, axis=1) for t in ((a, ab, ca), (ab, b, bc), (ca, bc, c), (ab, bc, ca))])
    fine = fine[keep(fine_points[fine].mean(axis=1))]
    used, fine = np.unique(fine, return_inverse=True)
    return subject_map(fine_points[used]), fine.reshape(-1, 3)


def test_a_scan_with_an_open_border_in_centimetres(template, builtin_model_path, shared_dir):
    """A finer scan of the subject with other proportions, cut off at the ears and the neck
    (an open border, less extent than the template's skin), in cm, landmarks by coordinates:
    the skin lies on the scan within 1.5 mm RMS inside it, and no tet inverts."""
    subject_map = Proportions(template)

    def front(centroids):
        return (centroids[:, 2] > 55.0) & (centroids[:, 1] > -90.0)
    points, triangles = subdivided_skin(template, subject_map, front)
    landmarks = {name: subject_map(p) for name, p in template.landmarks.items() if front(p[None])[0]}
    assert len(landmarks) >= 12
    scan, landmark_file = shared_dir / "front_cm.ply", shared_dir / "front_cm.toml"

    def write():
        meshio.write(scan, meshio.Mesh(LAB.apply(points) / 10.0, [("triangle", triangles.astype(np.int32))]))
        landmark_file.write_text("[landmarks]\n" + "".join(f"{name} = {(LAB.apply(p) / 10.0).tolist()}\n"
                                                           for name, p in landmarks.items()))
    on_rank_0(write)
    out = shared_dir / "front_model"
    assert main(["build", "--surface", str(scan), "--landmarks", str(landmark_file), "--units", "cm",
                 "--model", str(builtin_model_path), "--out", str(out)]) == 0
    model, _, quality = check_valid(out, template)
    record = json.loads((out / "subject.json").read_text())
    assert record["residual_rms_mm"] <= 1.5
    assert 0.3 * record["skin_nodes"] < record["skin_nodes_matched"] < record["skin_nodes"]
    frame = to_template(out)
    surface = SkinSurface(frame.apply(LAB.apply(points)), triangles)
    skin_points, _ = model.skin_surface()
    distance = surface.closest(skin_points)[3]
    inside = front(skin_points) & (distance < 5.0)
    assert np.sqrt(np.mean(distance[inside] ** 2)) <= 1.5
    assert quality.min() > 0.01


def test_bad_scans_are_refused_with_one_message(template, builtin_model_path, shared_dir):
    points, triangles = template.skin_surface()
    landmarks = shared_dir / "bad.toml"
    ids = {name: int(np.argmin(np.linalg.norm(points - p, axis=1))) for name, p in template.landmarks.items()}
    on_rank_0(lambda: landmarks.write_text("[landmarks]\n" + "".join(f"{n} = {i}\n" for n, i in ids.items())))
    nan_points = points.copy()
    nan_points[7] = np.nan
    duplicate_points = np.vstack([points, points[:1]])
    duplicate_triangles = np.vstack([triangles, [[0, len(points), 1]]])  # vertex 0 and its copy in one triangle
    cases = {
        "points_only.vtu": (meshio.Mesh(points, [("vertex", np.arange(len(points))[:, None])]),
                            r"points_only\.vtu: no triangles \(cell types: vertex\)"),
        "nan.ply": (meshio.Mesh(nan_points, [("triangle", triangles)]),
                    r"nan\.ply: 1 vertices are not finite \(first: vertex 7\)"),
        "duplicate.ply": (meshio.Mesh(duplicate_points, [("triangle", duplicate_triangles)]),
                          (r"duplicate\.ply: 1 triangles have two corners at the same point \(duplicate vertices; "
                           r"first: triangle \d+\)")),
    }

    def write():
        for name, (mesh, _) in cases.items():
            meshio.write(shared_dir / name, mesh)
    on_rank_0(write)
    for name, (_, message) in cases.items():
        with pytest.raises(SystemExit, match=message):
            main(["build", "--surface", str(shared_dir / name), "--landmarks", str(landmarks),
                  "--model", str(builtin_model_path), "--out", str(shared_dir / "never")])
    assert not (shared_dir / "never").exists()
