"""The bilabial take's truth solved with contact (capture/synthetic.py, ``truth_contact_options``):
the surfaces ``fit --contact`` models by default, and a truth with the teeth in which the lips
neither pass through each other nor the lining into the teeth, frame after frame (5K face); a
frame whose solve from the last frame's equilibrium fails is solved from rest."""
import dataclasses
import re
from types import SimpleNamespace

import numpy as np
import pytest

from face_dolfinx.capture.synthetic import (TRUTH_CONTACTS, control_curves, load_truth, save_truth, synthesize_take,
                                            truth_contact_options)
from face_dolfinx.equilibrium.solver import EquilibriumError
from face_dolfinx.fitting import MarkerSet
from face_dolfinx.model.bones import tmj_values
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
    refusal = "--truth-contact 'teeth': choose from " + ", ".join(TRUTH_CONTACTS)
    with pytest.raises(ValueError, match=re.escape(refusal)):
        truth_contact_options(model, "teeth", where="--truth-contact")
    toothless = dataclasses.replace(model, teeth={})
    with pytest.raises(ValueError, match=re.escape(f"truth_contact lips+teeth: model {model.path} has no teeth")):
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


class _OneFailingSolve:
    """A problem whose solve from the last equilibrium fails at one frame (a Newton that gives up):
    the state after a solve is the controls' jaw opening; from rest the solve succeeds."""

    def __init__(self, model, failing_opening):
        self.comm, self.jaw, self.failing_opening = model.mesh.comm, model.jaw, failing_opening
        self.opening, self.resets = 0.0, 0
        self.u = SimpleNamespace(x=SimpleNamespace(array=np.zeros(0)))  # the state is ``opening``

    def solve(self, activations, cranium, jaw):
        opening = float(tmj_values(self.jaw, jaw)[0])
        if self.opening != 0.0 and np.isclose(opening, self.failing_opening):
            raise EquilibriumError("no equilibrium beyond 0.5 of the way to the target controls")
        self.opening = opening

    def reset_to_rest(self):
        self.opening, self.resets = 0.0, self.resets + 1


class _OpeningMarker:
    reference = np.zeros((1, 3))
    names = ["opening"]

    def __init__(self, problem):
        self.problem = problem

    def positions(self, displacement, cranium):
        return np.full((1, 3), self.problem.opening)


def test_a_frame_whose_warm_solve_fails_is_solved_from_rest(model, tmp_path):
    """The take goes on from rest at that frame, the truth lists it, and the list survives
    ``select`` and the truth file."""
    _, tmj, _ = control_curves(model, "bilabial", 12, head_motion=False)
    failing = 4  # the jaw closing from a vowel onto the next closure
    problem = _OneFailingSolve(model, tmj[failing, 0])
    capture, truth = synthesize_take(problem, _OpeningMarker(problem), model, "bilabial", n_frames=12, noise=0.0,
                                     head_motion=False, marker_names=["opening"])
    assert truth.solved_from_rest == (failing,) and problem.resets == 1
    np.testing.assert_allclose(truth.clean_positions[:, 0, 0], tmj[:, 0], atol=1e-7)
    assert truth.select([2, 4, 5]).solved_from_rest == (1,) and truth.select([5, 6]).solved_from_rest == ()
    save_truth(tmp_path / "take.truth.npz", truth, model.muscle_names)
    assert load_truth(tmp_path / "take.truth.npz").solved_from_rest == (failing,)
