"""The levels of an alignment (face_dolfinx.alignment.placement.place_capture): good, doubtful,
wrong; a wrong one refused with its culprits named unless accepted; bad correspondence files named
in the message."""
import json

import numpy as np
import pytest

from face_dolfinx.alignment.placement import place_capture
from face_dolfinx.alignment.similarity import AlignmentError
from face_dolfinx.capture import Capture
from test_align import SKIN, correspondence_setup, swap_sides


def setup_capture(neutral, names, source="session.trc"):
    """Two frames, both the neutral one."""
    return Capture(names, np.stack([neutral, neutral]), 60.0, source=source)


def place(neutral, names, landmarks, correspondence, **options):
    return place_capture(setup_capture(neutral, names), 0, SKIN, {}, landmarks, correspondence, **options)


def test_good_and_doubtful_alignments_are_placed():
    truth, neutral, names, landmarks, correspondence, _ = correspondence_setup()
    good = place(neutral, names, landmarks, correspondence)
    assert good.method == "correspondence" and good.quality.level == "good" and not good.doubtful
    assert good.details["pairs_standing_out_mm"] == {}
    assert good.details["mirrored_assignment"]["landmark_rms_mm"] > 10.0
    moved = {**landmarks, "chin": landmarks["chin"] + [0.0, 20.0, 0.0]}
    doubtful = place(neutral, names, moved, correspondence)
    assert doubtful.quality.level == "doubtful" and doubtful.doubtful
    assert list(doubtful.details["pairs_standing_out_mm"]) == ["M_chin"]
    assert "accepted" not in doubtful.details


def test_a_wrong_alignment_is_refused_naming_its_culprits():
    truth, neutral, names, landmarks, correspondence, _ = correspondence_setup()
    with pytest.raises(AlignmentError) as error:
        place(neutral, names, landmarks, swap_sides(correspondence, landmarks))
    message = str(error.value)
    assert message.startswith("session.trc: the alignment by correspondence to the model is wrong; nothing is "
                              "fitted:\n  left and right look swapped: with each left landmark exchanged for its "
                              "right partner and vice versa, the landmarks fit with RMS ")
    assert message.endswith("check the correspondences, or pass accept_alignment=True (--accept-alignment on "
                            "the command line) to fit with this alignment anyway")

    moved = {**landmarks, "chin": landmarks["chin"] + [0.0, 40.0, 0.0]}
    with pytest.raises(AlignmentError, match=r"is wrong; nothing is fitted:\n  pair 'M_chin' -> 'chin' stands out: "
                                             r"the other pairs put 'M_chin' 4\d\.\d mm from 'chin'\n"):
        place(neutral, names, moved, correspondence)


def test_an_accepted_wrong_alignment_is_kept_and_recorded():
    truth, neutral, names, landmarks, correspondence, _ = correspondence_setup()
    swapped = swap_sides(correspondence, landmarks)
    placement = place(neutral, names, landmarks, swapped, accept_wrong=True)
    assert placement.quality.wrong and placement.doubtful
    record = json.loads(json.dumps(placement.to_json()))
    assert record["verdict"].startswith("wrong: left and right look swapped")
    assert record["accepted"] == "the wrong alignment was accepted by the user (accept_alignment)"
    assert record["correspondence_residuals_mm"].keys() == swapped.keys()
    assert placement.summary().count("wrong: left and right look swapped") == 1


def test_correspondence_file_problems_name_both_files(tmp_path):
    truth, neutral, names, landmarks, correspondence, _ = correspondence_setup()

    def problem(text, suffix=".csv"):
        path = tmp_path / f"pairs{suffix}"
        path.write_text(text)
        with pytest.raises(AlignmentError) as error:
            place(neutral, names, landmarks, path)
        return str(error.value)

    rows = "".join(f"{marker},{landmark}\n" for marker, landmark in correspondence.items())
    assert problem(rows + "M_typo,chin\n") == (f"{tmp_path / 'pairs.csv'}, line 9: landmark 'chin' is already used "
                                              f"({tmp_path / 'pairs.csv'}, line 7)")
    assert problem(rows + "M_typo,ear\n").startswith(
        f"session.trc with {tmp_path / 'pairs.csv'}: cannot align the capture by correspondences:\n"
        "  capture marker 'M_typo' (for landmark 'ear') does not exist in the capture\n"
        "  landmark 'ear' (for capture marker 'M_typo') is not a landmark of the model")
    assert problem("".join(rows.splitlines(keepends=True)[:5])).endswith(
        "only 5 usable correspondences; at least 6 are needed")
    assert problem("[correspondence]\nM_chin = \"chin\"\nM_chin = \"menton\"\n", ".toml").startswith(
        f"{tmp_path / 'pairs.toml'}: ")
    # A file that is right places the capture.
    path = tmp_path / "pairs.csv"
    path.write_text(rows)
    assert place(neutral, names, landmarks, path).quality.good
