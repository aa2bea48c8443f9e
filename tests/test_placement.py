"""Placing a capture on the model (face_dolfinx.alignment.placement): markers at the model's
sites, moved into a lab frame by a known similarity, are placed back exactly by correspondences
and closely by ICP; marker-site names keep the capture as it is; a neutral frame with a gap is
refused with frames to choose from."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from face_dolfinx.alignment.placement import place_capture
from face_dolfinx.alignment.similarity import AlignmentError, Similarity
from face_dolfinx.alignment.surface import SkinSurface
from face_dolfinx.capture import Capture
from user_capture import user_sites

# The lab frame of a "user's" capture: turned, moved far from the model's origin, 10 % larger.
LAB = Similarity(1.1, Rotation.from_euler("xyz", [20.0, -35.0, 10.0], degrees=True).as_matrix(),
                 [400.0, -250.0, 900.0])


@pytest.fixture(scope="module")
def face(model):
    names, sites, correspondence = user_sites(model)
    return SkinSurface(*model.skin_surface()), model, names, sites, correspondence


def lab_take(names, sites, frames=3):
    """The sites, still, for a few frames, seen in the LAB frame."""
    return Capture(names, LAB.apply(np.stack([sites] * frames)), 60.0)


def test_correspondences_place_the_capture_back_exactly(face):
    skin, model, names, sites, correspondence = face
    capture = lab_take(names, sites)
    placement = place_capture(capture, 0, skin, model.markers, model.landmarks, correspondence)
    assert placement.method == "correspondence" and not placement.doubtful
    back = LAB.inverse()
    assert placement.transform.scale == pytest.approx(back.scale, rel=1e-12)
    np.testing.assert_allclose(placement.transform.rotation, back.rotation, atol=1e-12)
    np.testing.assert_allclose(placement.transform.translation, back.translation, atol=1e-9)
    np.testing.assert_allclose(placement.aligned(capture).positions, np.stack([sites] * 3), atol=1e-9)
    # Every site is on the skin: each marker is its site with no offset.
    np.testing.assert_allclose(placement.surface_points, sites, atol=1e-9)
    np.testing.assert_allclose(placement.offsets, 0.0, atol=1e-9)
    assert max(placement.residuals.values()) < 1e-9 and len(placement.residuals) == len(correspondence)
    record = placement.to_json()
    assert record["method"] == "correspondence" and record["transform"]["direction"] == "capture -> model"
    assert set(record["markers"]) == set(names)


def test_icp_places_a_capture_without_correspondences(face):
    """No names to go by: the similarity ICP finds the pose from the skin alone, to a fraction
    of a millimetre (the markers may slide along the skin), and judges it good."""
    skin, model, names, sites, _ = face
    capture = lab_take(names, sites)
    placement = place_capture(capture, 1, skin, model.markers, model.landmarks)
    assert placement.method == "icp" and placement.neutral_frame == 1
    assert not placement.doubtful and placement.details["converged"]
    assert placement.transform.scale == pytest.approx(1 / 1.1, rel=1e-3)
    aligned = placement.aligned(capture).positions[1]
    assert np.sqrt(np.mean(np.sum((aligned - sites) ** 2, axis=1))) < 0.5
    assert np.abs(placement.offsets).max() < 0.1  # on the skin after the alignment


def test_model_site_names_keep_the_capture_where_it_is(face):
    skin, model, _, _, _ = face
    names = list(model.markers)
    sites = np.array(list(model.markers.values()))
    placement = place_capture(Capture(names, np.stack([sites, sites + 1.0]), 60.0), 0, skin,
                              model.markers, model.landmarks)
    assert placement.method == "model_sites" and not placement.doubtful
    assert placement.transform.scale == 1.0 and np.array_equal(placement.transform.rotation, np.eye(3))
    assert np.array_equal(placement.surface_points, sites) and not placement.offsets.any()
    far = place_capture(Capture(names, np.stack([sites + 50.0]), 60.0), 0, skin, model.markers, model.landmarks)
    assert far.doubtful and "does not look like it is in model coordinates" in far.details["warning"]
    assert far.details["neutral_to_sites_rms_mm"] == pytest.approx(50.0 * np.sqrt(3.0))


def test_a_neutral_frame_with_a_gap_is_refused_naming_frames_to_choose(face):
    skin, model, names, sites, _ = face
    positions = LAB.apply(np.stack([sites] * 4))
    positions[0, 5] = np.nan
    positions[2, 7] = np.nan
    with pytest.raises(AlignmentError, match=rf"neutral frame 0 lacks markers {names[5]}; choose a neutral "
                                             r"frame where every marker is present \(frames 1, 3\)"):
        place_capture(Capture(names, positions, 60.0), 0, skin, model.markers, model.landmarks)
