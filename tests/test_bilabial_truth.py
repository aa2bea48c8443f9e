"""The bilabial take's truth solved with contact (capture/synthetic.py, ``truth_contact_options``):
the surfaces ``fit --contact`` models by default, and a truth with the teeth in which the lips
neither pass through each other nor the lining into the teeth, frame after frame. 5K face."""
import dataclasses

import numpy as np
import pytest

from face_dolfinx.capture.synthetic import TRUTH_CONTACTS, control_curves, synthesize_take, truth_contact_options
from face_dolfinx.fitting import MarkerSet
from face_dolfinx.physics.problem import FaceProblem
from face_dolfinx.tracking import TrackingSettings

# Frames 2-6 of the 24-frame take: the lips pressed by the orbicularis oris (0.27, then 0.82, then
# 0.78), released, then the jaw opening 5 degrees.
TAKE_FRAMES, FRAMES = 24, range(2, 7)


def test_the_default_truth_is_what_fit_contact_models(model):
    """Without a choice the truth touches what ``fit --contact`` makes touch, with its settings."""
    fit = TrackingSettings(contact=True).problem_options(model)
    truth = truth_contact_options(model)
    assert model.teeth and truth["contact"] is not None and truth["lip_contact"] is not None
    for name in ("lip_contact", "contact"):
        assert dataclasses.replace(truth[name], where="") == dataclasses.replace(fit[name], where=""), name
    assert truth_contact_options(model, "lips")["contact"] is None


def test_bad_truth_contact_is_refused_naming_the_option(model):
    with pytest.raises(ValueError, match="--truth-contact 'teeth': choose from " + ", ".join(TRUTH_CONTACTS)):
        truth_contact_options(model, "teeth", where="--truth-contact")
    toothless = dataclasses.replace(model, teeth={})
    with pytest.raises(ValueError, match=f"truth_contact lips\\+teeth: model {model.path} has no teeth"):
        truth_contact_options(toothless, "lips+teeth")
    assert truth_contact_options(toothless)["contact"] is None  # the default follows the model


def test_bilabial_truth_with_the_teeth_keeps_lips_and_lining_apart(model):
    problem = FaceProblem(model, **truth_contact_options(model, "lips+teeth"))
    names = list(model.markers)
    markers = MarkerSet(problem, np.array([model.markers[n] for n in names]), names=names)
    seen = []

    def check(frame):
        u = problem.u.x.array
        seen.append((problem.lips.penetration(u), problem.lips.min_distance(u), problem.teeth_contact.min_gap(u),
                     problem.teeth_contact.contact_nodes(u)))
    capture, truth = synthesize_take(problem, markers, model, "bilabial", n_frames=TAKE_FRAMES, noise=0.0,
                                     head_motion=False, frames=FRAMES, progress=check)
    activations, tmj, _ = control_curves(model, "bilabial", TAKE_FRAMES, head_motion=False)
    assert np.array_equal(truth.activations, activations[FRAMES]) and np.array_equal(truth.tmj, tmj[FRAMES])
    sphincter = [i for i, m in enumerate(model.muscles) if m.name.startswith("orbicularis_oris")]
    assert truth.activations[:, sphincter].max() > 0.8 and np.degrees(truth.tmj[:, 0].max()) > 4.0
    penetration, distance, teeth_gap, teeth_nodes = map(np.array, zip(*seen))
    assert len(seen) == len(FRAMES)
    assert np.all(penetration == 0.0)
    assert np.all(teeth_gap > 0.0)  # no lining node inside the teeth
    pressed = truth.activations[:, sphincter].max(axis=1) > 0.5
    assert np.all(distance[pressed] < 0.01) and np.all(distance[~pressed] > 0.0)  # touching, not passing
    assert np.all(teeth_nodes[pressed] > 0)  # the pressed lips rest on the teeth
    assert np.array_equal(capture.positions, truth.clean_positions)
