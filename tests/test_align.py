"""Aligning a capture to the model: similarity fits, correspondences, their files, ICP (face_dolfinx.alignment.similarity)."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from face_dolfinx.alignment.similarity import (AlignmentError, Similarity, align_by_correspondences, align_by_icp,
                                               check_pairs, read_correspondence_file, similarity_transform)
from face_dolfinx.alignment.surface import SkinSurface


def face_surface(n_theta=60, n_phi=50):
    """A face-like mask (mm, Y up, +Z out of the face): a radial graph with a nose, cheekbones, a
    brow and eye sockets, so that no rotation or sliding maps it onto itself."""
    theta, phi = np.meshgrid(np.linspace(-1.2, 1.2, n_theta), np.linspace(-0.9, 0.9, n_phi))
    radius = (100
              + 25 * np.exp(-(theta / 0.12) ** 2 - ((phi + 0.05) / 0.25) ** 2)                  # nose
              + 6 * np.exp(-((np.abs(theta) - 0.45) / 0.2) ** 2 - ((phi + 0.1) / 0.2) ** 2)     # cheekbones
              + 5 * np.exp(-(theta / 0.5) ** 2 - ((phi - 0.5) / 0.12) ** 2)                     # brow
              - 8 * np.exp(-((np.abs(theta) - 0.35) / 0.15) ** 2 - ((phi - 0.25) / 0.1) ** 2))  # eye sockets
    points = np.stack([0.8 * radius * np.cos(phi) * np.sin(theta), 1.2 * radius * np.sin(phi),
                       radius * np.cos(phi) * np.cos(theta)], axis=-1).reshape(-1, 3)
    index = np.arange(n_theta * n_phi).reshape(n_phi, n_theta)
    lower = np.column_stack([index[:-1, :-1].ravel(), index[:-1, 1:].ravel(), index[1:, :-1].ravel()])
    upper = np.column_stack([index[1:, :-1].ravel(), index[:-1, 1:].ravel(), index[1:, 1:].ravel()])
    return points, np.concatenate([lower, upper])


POINTS, TRIANGLES = face_surface()
SKIN = SkinSurface(POINTS, TRIANGLES)


def skin_samples(n, seed, lift=0.0):
    """Points spread uniformly over the skin, optionally lifted off it along the normal."""
    rng = np.random.default_rng(seed)
    pick = rng.choice(len(TRIANGLES), n, p=SKIN.areas / SKIN.areas.sum())
    weights = rng.dirichlet([2, 2, 2], n)
    return np.einsum("nk,nkd->nd", weights, POINTS[TRIANGLES[pick]]) + lift * SKIN.triangle_normals[pick]


def random_similarity(seed, angle_degrees=30.0, scale_range=(0.9, 1.1), shift_mm=20.0):
    rng = np.random.default_rng(seed)
    axis = rng.normal(size=3)
    rotation = Rotation.from_rotvec(np.radians(angle_degrees) * axis / np.linalg.norm(axis)).as_matrix()
    direction = rng.normal(size=3)
    return Similarity(rng.uniform(*scale_range), rotation, shift_mm * direction / np.linalg.norm(direction))


def max_error(found, truth, points):
    return np.max(np.linalg.norm(found.apply(points) - truth.apply(points), axis=1))


# --- similarity_transform ---------------------------------------------------------------------

def test_similarity_recovers_an_exact_transform():
    source = np.random.default_rng(0).uniform(-100, 100, (20, 3))
    truth = random_similarity(1, angle_degrees=140.0, scale_range=(0.5, 2.0))
    found = similarity_transform(source, truth.apply(source))
    assert found.scale == pytest.approx(truth.scale, rel=1e-12)
    np.testing.assert_allclose(found.rotation, truth.rotation, atol=1e-12)
    np.testing.assert_allclose(found.translation, truth.translation, atol=1e-10)
    assert found.rms < 1e-10
    back = found.inverse()
    np.testing.assert_allclose(back.apply(found.apply(source)), source, atol=1e-10)
    np.testing.assert_allclose((back @ found).apply(source), source, atol=1e-10)


def test_similarity_with_noise_is_within_the_noise_statistics():
    rng = np.random.default_rng(2)
    source = rng.uniform(-100, 100, (200, 3))
    truth = random_similarity(3)
    sigma = 0.5
    found = similarity_transform(source, truth.apply(source) + rng.normal(0, sigma, source.shape))
    # The residual of a 7-parameter fit to 3n noisy coordinates: sigma sqrt(3 - 7/n) per point.
    assert found.rms == pytest.approx(sigma * np.sqrt(3 - 7 / 200), rel=0.1)
    # The fitted transform is off by about sigma / sqrt(n) (plus lever-arm terms): far below sigma.
    assert max_error(found, truth, source) < 0.2
    assert found.scale == pytest.approx(truth.scale, abs=2e-3)


def test_rigid_fit_keeps_unit_scale():
    source = np.random.default_rng(4).uniform(-100, 100, (10, 3))
    truth = Similarity(1.0, random_similarity(5).rotation, [5.0, -3.0, 2.0])
    found = similarity_transform(source, truth.apply(source) * 1.001, allow_scale=False)
    assert found.scale == 1.0
    assert max_error(found, truth, source) < 0.3


@pytest.mark.parametrize("seed", range(5))
def test_mirror_image_data_gives_a_proper_rotation(seed):
    rng = np.random.default_rng(seed)
    source = rng.uniform(-100, 100, (8, 3))
    mirrored = source * [-1, 1, 1] + rng.normal(0, 0.5, source.shape)
    found = similarity_transform(source, mirrored)
    assert np.linalg.det(found.rotation) == pytest.approx(1.0, abs=1e-12)
    np.testing.assert_allclose(found.rotation @ found.rotation.T, np.eye(3), atol=1e-12)


def test_nan_rows_and_zero_weights_are_ignored():
    rng = np.random.default_rng(6)
    source = rng.uniform(-100, 100, (12, 3))
    target = random_similarity(7).apply(source)
    reference = similarity_transform(source[3:], target[3:])
    holes_source, holes_target = source.copy(), target.copy()
    holes_source[0, 1] = np.nan
    holes_target[1] = np.nan
    for found in (similarity_transform(holes_source, holes_target, weights=[1, 1, 0] + [1] * 9),
                  similarity_transform(source, target * 1, weights=[0, 0, 0] + [1] * 9)):
        np.testing.assert_allclose(found.rotation, reference.rotation, atol=1e-12)
        np.testing.assert_allclose(found.translation, reference.translation, atol=1e-9)


def test_weights_weigh_the_fit():
    source = np.random.default_rng(8).uniform(-100, 100, (10, 3))
    target = source.copy()
    target[0] += 30.0  # one bad pair
    light = similarity_transform(source, target, weights=[1e-9] + [1] * 9)
    heavy = similarity_transform(source, target)
    assert max_error(light, Similarity.identity(), source) < 1e-6 < max_error(heavy, Similarity.identity(), source)


def test_too_few_or_collinear_points_are_refused():
    line = np.outer(np.arange(5.0), [1.0, 2.0, 3.0])
    with pytest.raises(AlignmentError, match="at least 3"):
        similarity_transform(np.eye(3)[:2], np.eye(3)[:2])
    with pytest.raises(AlignmentError, match="at least 3"):
        similarity_transform(np.eye(3), np.array([[0, 0, 0], [np.nan, 0, 0], [1, 1, 1.0]]))
    with pytest.raises(AlignmentError, match="source points are collinear"):
        similarity_transform(line, np.random.default_rng(9).normal(size=(5, 3)))
    with pytest.raises(AlignmentError, match="target points are collinear"):
        similarity_transform(np.random.default_rng(9).normal(size=(5, 3)), line)
    with pytest.raises(AlignmentError, match="same shape"):
        similarity_transform(np.eye(3), np.eye(4)[:, :3])


# --- align_by_correspondences -----------------------------------------------------------------

LANDMARK_NAMES = ["nose_tip", "brow_mid", "cheek_left", "cheek_right", "eye_left", "eye_right", "chin", "jaw_left"]


def correspondence_setup(seed=10, lift=1.5):
    """Model landmarks on the skin; a capture with a marker over each and a few more, all lifted
    off the skin by a marker radius and seen through a known similarity."""
    landmarks = dict(zip(LANDMARK_NAMES, skin_samples(len(LANDMARK_NAMES), seed)))
    capture_names = [f"M_{name}" for name in LANDMARK_NAMES] + ["extra_1", "extra_2", "extra_3"]
    lifted = np.vstack([skin_samples(len(LANDMARK_NAMES), seed, lift), skin_samples(3, seed + 1, lift)])
    truth = random_similarity(seed)
    correspondence = {f"M_{name}": name for name in LANDMARK_NAMES}
    return truth, truth.inverse().apply(lifted), capture_names, landmarks, correspondence, lifted


def test_correspondences_recover_the_transform_and_embed_every_marker():
    truth, neutral, names, landmarks, correspondence, lifted = correspondence_setup()
    result = align_by_correspondences(neutral, names, landmarks, correspondence, SKIN)
    # Markers sit 1.5 mm off the skin while landmarks lie on it: the fit absorbs that as a slightly
    # larger scale, by about 1.5 mm over the face's radius.
    assert max_error(result.transform, truth, neutral) < 3.0
    assert set(result.residuals) == set(correspondence)
    assert max(result.residuals.values()) < 2.0
    embedding = result.embedding
    assert embedding.names == tuple(names)
    # Every marker is embedded where the transform puts it, offsets kept.
    np.testing.assert_allclose(embedding.positions(POINTS), result.transform.apply(neutral), atol=1e-10)
    assert result.quality.good, result.quality.verdict


def test_exact_correspondences_give_an_exact_fit():
    truth, neutral, names, landmarks, correspondence, lifted = correspondence_setup(lift=0.0)
    result = align_by_correspondences(neutral, names, landmarks, correspondence, SKIN)
    assert max_error(result.transform, truth, neutral) < 1e-9
    assert result.quality.rms < 1e-9 and result.quality.good


def test_each_correspondence_problem_is_named():
    truth, neutral, names, landmarks, correspondence, _ = correspondence_setup()

    def problem(neutral=neutral, landmarks=landmarks, correspondence=correspondence):
        with pytest.raises(AlignmentError) as error:
            align_by_correspondences(neutral, names, landmarks, correspondence, SKIN)
        return str(error.value)

    assert "'M_typo' (for landmark 'chin') does not exist in the capture" in problem(
        correspondence={**correspondence, "M_typo": "chin"})
    assert "landmark 'ear_left' (for capture marker 'extra_1') is not a landmark of the model" in problem(
        correspondence={**correspondence, "extra_1": "ear_left"})
    occluded = neutral.copy()
    occluded[names.index("M_chin")] = np.nan
    assert "'M_chin' (for landmark 'chin') is missing (NaN) in the neutral frame" in problem(neutral=occluded)
    occluded = neutral.copy()
    occluded[names.index("extra_2")] = np.nan
    assert "cannot be embedded in the skin: extra_2" in problem(neutral=occluded)
    few = dict(list(correspondence.items())[:5])
    assert "only 5 usable correspondences; at least 6" in problem(correspondence=few)
    # Several problems are reported together.
    message = problem(correspondence={**few, "M_typo": "ear_left"})
    assert "M_typo" in message and "ear_left" in message and "only 5" in message
    bad_landmarks = {**landmarks, "chin": [0.0, np.nan, 1.0]}
    assert "landmark 'chin' is not a finite 3-vector" in problem(landmarks=bad_landmarks)
    twice = {**correspondence, "extra_3": "chin"}
    assert "landmark 'chin' is paired with more than one capture marker: 'M_chin', 'extra_3'" in problem(
        correspondence=twice)
    with pytest.raises(AlignmentError, match="unique"):
        align_by_correspondences(neutral, names[:-1] + [names[0]], landmarks, correspondence, SKIN)


def test_a_misplaced_landmark_makes_the_alignment_doubtful():
    truth, neutral, names, landmarks, correspondence, _ = correspondence_setup()
    moved = {**landmarks, "chin": landmarks["chin"] + [0.0, 20.0, 0.0]}
    result = align_by_correspondences(neutral, names, moved, correspondence, SKIN)
    assert result.quality.level == "doubtful" and not result.quality.good and not result.quality.wrong
    assert "the landmarks fit with RMS" in result.quality.verdict and "'M_chin'" in result.quality.verdict
    # The pair is named: the other pairs put its marker 20 mm (plus the 1.5 mm lift) from its landmark.
    assert list(result.pairs.standing_out) == ["M_chin"]
    assert result.pairs.standing_out["M_chin"] == pytest.approx(20.0, abs=2.0)
    assert result.quality.reasons[0].startswith("pair 'M_chin' -> 'chin' stands out: the other pairs put 'M_chin' ")


def test_a_pair_far_from_where_the_others_put_it_makes_the_alignment_wrong():
    truth, neutral, names, landmarks, correspondence, _ = correspondence_setup()
    # Both kinds of mistake: a landmark given to the wrong marker, and a landmark far off.
    wrong_marker = {**{m: lm for m, lm in correspondence.items() if m != "M_brow_mid"}, "extra_2": "brow_mid"}
    far_extra = np.linalg.norm(neutral[names.index("extra_2")] - neutral[names.index("M_brow_mid")])
    assert far_extra * truth.scale > 30.0
    moved = {**landmarks, "chin": landmarks["chin"] + [0.0, 40.0, 0.0]}
    for culprit, landmark, result in (
            ("extra_2", "brow_mid", align_by_correspondences(neutral, names, landmarks, wrong_marker, SKIN)),
            ("M_chin", "chin", align_by_correspondences(neutral, names, moved, correspondence, SKIN))):
        assert result.quality.level == "wrong", result.quality.verdict
        assert list(result.pairs.standing_out) == [culprit]
        assert result.quality.reasons[0].startswith(f"pair {culprit!r} -> {landmark!r} stands out")
    # Without the culprit the rest is good: the pair is what is wrong.
    rest = {m: lm for m, lm in correspondence.items() if m != "M_chin"}
    assert align_by_correspondences(neutral, names, moved, rest, SKIN).quality.good


def swap_sides(correspondence, landmarks):
    """Each landmark named *_left given to the marker of its *_right partner and vice versa."""
    def mirror(name):
        other = name.replace("_left", "_RIGHT").replace("_right", "_left").replace("_RIGHT", "_right")
        return other if other in landmarks else name
    return {marker: mirror(landmark) for marker, landmark in correspondence.items()}


def test_left_and_right_swapped_is_wrong_and_named():
    truth, neutral, names, landmarks, correspondence, _ = correspondence_setup()
    correct = align_by_correspondences(neutral, names, landmarks, correspondence, SKIN)
    swapped = align_by_correspondences(neutral, names, landmarks, swap_sides(correspondence, landmarks), SKIN)
    assert correct.quality.good and correct.pairs.mirrored_rms > 10 * correct.transform.rms
    assert swapped.quality.wrong
    assert swapped.quality.reasons[0].startswith("left and right look swapped")
    # The mirrored assignment of the swapped file is the correct one.
    assert swapped.pairs.mirrored_rms == pytest.approx(correct.transform.rms, rel=1e-9)
    assert swapped.pairs.mirrored_scale == pytest.approx(correct.transform.scale, rel=1e-9)
    # Without landmarks that have a partner of the other side there is nothing to mirror.
    markers = list(correspondence)
    source = neutral[[names.index(marker) for marker in markers]]
    target = np.array([landmarks[correspondence[marker]] for marker in markers])
    unsided = [f"point {i}" for i in range(len(markers))]
    assert check_pairs(source, target, markers, unsided, dict(zip(unsided, target))).mirrored_rms is None
    alone = ["jaw_left", *unsided[1:]]  # no jaw_right
    assert check_pairs(source, target, markers, alone, dict(zip(alone, target))).mirrored_rms is None


def test_a_scale_from_wrong_units_is_wrong():
    truth, neutral, names, landmarks, correspondence, _ = correspondence_setup()
    for factor in (2.54, 1 / 2.54, 10.0):  # inches taken for cm and back, cm for mm
        result = align_by_correspondences(neutral * factor, names, landmarks, correspondence, SKIN)
        assert result.quality.wrong and result.quality.reasons == (
            f"scale {result.transform.scale:.3f} is far outside a face's range [0.5, 2]: wrong units, or "
            "markers that are not on this face",)


# --- read_correspondence_file -----------------------------------------------------------------

def test_correspondence_file_formats(tmp_path):
    toml = tmp_path / "pairs.toml"
    toml.write_text('title = "session 3"\n\n[correspondence]\nM_nose = "nose_tip"  # tip\n'
                    '"M brow" = "brow_mid"\n\n[other]\nx = 1\n')
    assert read_correspondence_file(toml) == {"M_nose": "nose_tip", "M brow": "brow_mid"}
    csv = tmp_path / "pairs.CSV"
    csv.write_text("# made by hand\ncapture_marker,model_landmark\n\nM_nose, nose_tip\n\"M brow\",brow_mid\n")
    assert read_correspondence_file(csv) == {"M_nose": "nose_tip", "M brow": "brow_mid"}
    bare = tmp_path / "bare.csv"
    bare.write_text("M_nose,nose_tip\n")
    assert read_correspondence_file(bare) == {"M_nose": "nose_tip"}


@pytest.mark.parametrize("name, text, message", [
    ("syntax.toml", "[correspondence]\nM_nose = nose_tip\n", r"syntax.toml: .*line 2"),
    ("no_table.toml", "[pairs]\nM_nose = \"nose_tip\"\n", r"no_table.toml: no \[correspondence\] table"),
    ("number.toml", "[correspondence]\nM_nose = \"nose_tip\"\nM_chin = 3\n", r"number.toml, line 3: .*'M_chin' = 3"),
    ("twice.toml", "[correspondence]\nA = \"chin\"\nB = \"chin\"\n",
     r"twice.toml, line 3: landmark 'chin' is already used \(.*twice.toml, line 2\)"),
    ("empty.toml", "[correspondence]\n", r"empty.toml: no correspondences"),
    ("columns.csv", "capture_marker,model_landmark\nA,chin\nB,nose,extra\n",
     r"columns.csv, line 3: expected two names"),
    ("blank.csv", "A,chin\nB,\n", r"blank.csv, line 2: expected two names"),
    ("twice.csv", "A,chin\nB,nose\nA,brow\n",
     r"twice.csv, line 3: capture marker 'A' is already used \(.*twice.csv, line 1\)"),
    ("pairs.txt", "A,chin\n", r"pairs.txt: unknown correspondence file type"),
])
def test_correspondence_file_errors_name_the_file_and_line(tmp_path, name, text, message):
    path = tmp_path / name
    path.write_text(text)
    with pytest.raises(AlignmentError, match=message):
        read_correspondence_file(path)


def test_missing_correspondence_file(tmp_path):
    with pytest.raises(AlignmentError, match="absent.csv: no such file"):
        read_correspondence_file(tmp_path / "absent.csv")


# --- align_by_icp ---------------------------------------------------------------------------

@pytest.mark.parametrize("seed", [0, 1, 2])
def test_icp_recovers_a_similarity(seed):
    markers = skin_samples(70, seed=100 + seed)
    truth = random_similarity(seed)
    neutral = truth.inverse().apply(markers)
    result = align_by_icp(neutral, SKIN)
    assert max_error(result.transform, truth, neutral) < 0.1
    assert result.converged and result.quality.verdict == "good"
    assert result.quality.rms < 0.01


def test_rigid_icp_from_a_given_pose_ignores_missing_markers_and_outliers():
    markers = skin_samples(70, seed=200)
    truth = Similarity(1.0, random_similarity(4).rotation, [10.0, -20.0, 5.0])
    neutral = truth.inverse().apply(markers)
    neutral[3] = np.nan
    neutral[[10, 20, 30]] += [0.0, 0.0, 25.0]  # markers off the face, e.g. on a head band
    result = align_by_icp(neutral, SKIN, initial=Similarity.identity(), allow_scale=False)
    clean = np.setdiff1d(np.arange(70), [3, 10, 20, 30])
    assert result.transform.scale == 1.0
    assert max_error(result.transform, truth, neutral[clean]) < 0.1
    assert np.isnan(result.quality.distances[3])
    # The outliers are trimmed from the fit but not from the report.
    assert not result.quality.good and "marker #" in result.quality.verdict
    np.testing.assert_allclose(result.quality.near_fraction, 66 / 69)


def test_icp_on_garbage_is_wrong():
    garbage = np.random.default_rng(5).uniform(-120, 120, (60, 3))
    result = align_by_icp(garbage, SKIN)
    assert result.quality.level == "wrong" and result.quality.wrong and not result.quality.good
    assert result.quality.verdict.startswith("wrong: markers are ")
    assert "from the skin, more than 20 mm" in result.quality.reasons[0]


def test_icp_needs_enough_markers():
    with pytest.raises(AlignmentError, match="at least 7 markers"):
        align_by_icp(skin_samples(6, seed=6), SKIN)
