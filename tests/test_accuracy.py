"""Accuracy without a truth (face_dolfinx.results.accuracy): non-rigid motion, the fraction a fit
explains, muscles pinned at their bound; and marker setups (face_dolfinx.tracking.markers)."""
import numpy as np
import pytest

from face_dolfinx.model.bones import rigid_map, rotation
from face_dolfinx.results.accuracy import MotionMeasures, pinned_stretches, rigid_prediction, summary, summary_lines
from face_dolfinx.tracking import MarkerSetup, MarkerSetupError
from face_dolfinx.tracking.markers import spread_out

RNG = np.random.default_rng(3)
NEUTRAL = RNG.uniform(-50, 50, size=(20, 3))
MOVED = np.array([2, 5, 11, 17])               # markers that move beyond the head's motion
SHIFT = np.array([[0.0, -3.0, 1.0], [1.0, 2.0, 0.0], [0.0, 0.0, 4.0], [-2.0, 0.0, 0.0]])


def take(frames=5):
    """Each frame: the neutral markers under a rigid head motion, four of them also displaced."""
    captured = []
    for frame in range(frames):
        head = rigid_map(rotation([0.3, 1.0, 0.2], 0.05 * frame), [0.0, 0.0, 0.0], [frame, -frame, 0.5 * frame])
        markers = head.apply(NEUTRAL)
        markers[MOVED] += (frame / frames) * SHIFT @ head.matrix.T
        captured.append(markers)
    return np.array(captured)


def test_non_rigid_motion_is_what_the_head_motion_leaves():
    captured = take()
    measures = MotionMeasures.of(NEUTRAL, captured, captured)
    expected = np.zeros((5, 20))
    expected[:, MOVED] = np.outer(np.arange(5) / 5, np.linalg.norm(SHIFT, axis=1))
    assert np.abs(measures.non_rigid - expected).max() < 1e-9
    rigid = rigid_prediction(NEUTRAL, captured)
    assert np.abs(np.delete(rigid - captured, MOVED, axis=1)).max() < 1e-9


def test_explained_fraction():
    captured = take()
    everything = np.ones(20, dtype=bool)
    perfect = MotionMeasures.of(NEUTRAL, captured, captured)
    assert perfect.pooled(everything)["explained"] == 1.0
    rigid_only = MotionMeasures.of(NEUTRAL, captured, rigid_prediction(NEUTRAL, captured))
    assert abs(rigid_only.pooled(everything)["explained"]) < 1e-12
    half_way = MotionMeasures.of(NEUTRAL, captured, 0.5 * (captured + rigid_prediction(NEUTRAL, captured)))
    assert half_way.pooled(everything)["explained"] == pytest.approx(0.75, abs=1e-9)
    per_frame = half_way.per_frame(everything)
    assert per_frame["non_rigid_mm"][0] < 1e-12    # the neutral frame itself: nothing to explain
    assert np.allclose(per_frame["explained"][1:], 0.75)


def test_gaps_and_a_marker_worse_than_rigid_motion():
    captured = take()
    captured[2, 7] = np.nan
    simulated = rigid_prediction(NEUTRAL, captured).copy()
    simulated[:, MOVED] = captured[:, MOVED]
    simulated[:, 0] += [0.0, 0.0, 3.0]  # a marker the fit puts 3 mm off though it moves rigidly
    measures = MotionMeasures.of(NEUTRAL, captured, simulated)
    assert np.isnan(measures.error[2, 7]) and np.isnan(measures.non_rigid[2, 7])
    roles = ["validation" if i in (0, 2) else "fitted" for i in range(20)]
    record = summary(measures, [f"m{i}" for i in range(20)], roles, ["lips" if i in MOVED else None for i in range(20)])
    assert record["worse_than_rigid"] == {"fitted": [], "validation": ["m0"]}
    assert record["markers"]["m2"]["explained"] == pytest.approx(1.0)
    assert record["groups"]["lips"]["markers"] == 4 and record["groups"]["lips"]["explained"] == pytest.approx(1.0)
    record["pinned_muscles"] = [dict(muscle="mentalis_left", start_s=1.0, end_s=2.5, seconds=1.5)]
    lines = summary_lines(record)
    assert len(lines) == 4 and "2 validation markers" in lines[1] and "(m0)" in lines[1]
    assert lines[2].startswith("by group: lips (4)") and lines[3].endswith("mentalis_left 1.5 s")


def test_pinned_muscles():
    times = np.arange(120) / 60.0
    activations = np.zeros((120, 3))
    activations[10:70, 0] = 1.0        # 59 frame intervals: 0.98 s at the bound
    activations[80:95, 1] = 1.0        # 0.23 s: too short to report
    activations[:, 2] = 0.9
    stretches = pinned_stretches(activations, times, ["a", "b", "c"])
    assert [s["muscle"] for s in stretches] == ["a"]
    assert stretches[0]["seconds"] == pytest.approx(59 / 60) and stretches[0]["start_s"] == pytest.approx(10 / 60)


def test_spread_out_starts_at_the_extremes():
    points = np.column_stack([np.arange(11.0), np.zeros(11), np.zeros(11)])
    points[4] = np.nan
    picked = spread_out(points, 3, np.arange(11) + 100)
    assert picked[:2] in ([100, 110], [110, 100]) and picked[2] in (105, 106)


def test_marker_setup_file(tmp_path):
    file = tmp_path / "setup.toml"
    file.write_text('validation = ["m4"]\n[groups]\neyelids = ["m1", "m2"]\n[weights]\neyelids = 0\nm2 = 3.0\nm5 = 0.5\n')
    setup = MarkerSetup.read(file)
    names = [f"m{i}" for i in range(8)]
    weights, roles, groups = setup.resolve(names, NEUTRAL[:8])
    assert weights.tolist() == [1, 0, 3, 1, 0, 0.5, 1, 1]
    assert roles == ["fitted", "ignored", "fitted", "fitted", "validation", "fitted", "fitted", "fitted"]
    assert groups == [None, "eyelids", "eyelids", None, None, None, None, None]
    counted = setup.with_validation(2).resolve(names, NEUTRAL[:8])
    assert counted[1].count("validation") == 2 and all(counted[0][i] == 0 for i, r in enumerate(counted[1])
                                                      if r == "validation")


@pytest.mark.parametrize("text, message", [
    ('[groups]\ng = ["m1", "nowhere"]\n', "group 'g' names marker 'nowhere'"),
    ('[weights]\nnowhere = 2\n', r"\[weights\] names marker 'nowhere'"),
    ('validation = ["m1", "x9"]\n', "validation names marker 'x9'"),
    ('validation = 8\n', "8 validation markers would leave 0 to fit"),
    ('[weights]\nm1 = -1\n', "weights must be numbers, 0 or more"),
    ('[groups]\na = ["m1"]\nb = ["m1"]\n', "marker 'm1' is in groups 'a' and 'b'"),
    ('markers = 3\n', "unknown entries markers"),
    ('[weights\n', "not a TOML marker setup file"),
])
def test_bad_marker_setups_are_named(tmp_path, text, message):
    file = tmp_path / "setup.toml"
    file.write_text(text)
    with pytest.raises(MarkerSetupError, match=f"setup.toml: .*{message}"):
        MarkerSetup.read(file).resolve([f"m{i}" for i in range(8)], NEUTRAL[:8])
