"""The intraoral pressure control on the small built-in face: a follower load on the lining of the
lips and cheeks (the model's ``oral`` facets).

- Positive pressure pushes the lips out, suction draws them in; the skull does not move.
- dX/dp, by a solve with the equilibrium's (LU-factorised, non-symmetric) tangent, against central
  differences of the nonlinear solve, with muscles active and the jaw open.
- A fit with the control recovers a known pressure (exact and paper mode), and one without it
  cannot reach those markers.
- A model without an oral surface, or a fit asking for the control on a problem without it, is
  refused with a message that says so.
Also under mpirun -n 2.
"""
import dataclasses

import numpy as np
import pytest

from face_dolfinx.fitting import FaceFitter, FitSettings, MarkerSet
from face_dolfinx.model.bones import jaw_pose
from face_dolfinx.physics.problem import FaceProblem
from face_dolfinx.sensitivities.columns import EquilibriumSensitivity


@pytest.fixture(scope="module")
def sites(model):
    return np.array(list(model.markers.values()))


@pytest.fixture(scope="module")
def lower_lip(model):
    return list(model.markers).index("lower_lip_4")  # the centre of the lower lip


def test_pressure_pushes_the_lips_out_and_suction_draws_them_in(model, sites, lower_lip):
    problem = FaceProblem(model, intraoral_pressure=True)
    markers = MarkerSet(problem, sites)
    moved = {}
    for pressure in (30.0, -30.0):
        report = problem.solve(pressure=pressure)
        assert report.converged
        moved[pressure] = markers.positions(problem.u.x.array, problem.controls.cranium) - sites
        bones = problem.u.x.array.reshape(-1, 3)[problem.bone_blocks]
        assert np.abs(bones).max() < 1e-12  # the bones stay in their rest frames
    # +z points out of the face: out with pressure, in with suction, by millimetres.
    assert moved[30.0][lower_lip, 2] > 2.0
    assert moved[-30.0][lower_lip, 2] < -2.0
    forehead = [i for i, name in enumerate(model.markers) if name.startswith("forehead")]
    assert np.abs(moved[30.0][forehead]).max() < 0.05 * moved[30.0][lower_lip, 2]


def test_pressure_column_matches_finite_differences(model, sites):
    problem = FaceProblem(model, intraoral_pressure=True)
    activations = np.full(problem.num_muscles, 0.2)
    jaw = jaw_pose(model.jaw, 0.1, 1.0, 2.0)
    pressure = 20.0
    problem.solve(activations=activations, jaw=jaw, pressure=pressure)
    markers = MarkerSet(problem, sites)
    sensitivity = EquilibriumSensitivity(problem)
    sensitivity.factor()
    analytic = markers.evaluator.values_many(sensitivity.pressure_columns())[0]
    base = problem.u.x.array.copy()

    def positions(p):
        problem.u.x.array[:] = base
        problem.solve(pressure=p, guess=base)
        return markers.positions(problem.u.x.array, problem.controls.cranium)

    h = 1e-3
    fd = (positions(pressure + h) - positions(pressure - h)) / (2 * h)
    assert np.abs(fd).max() > 0.05  # mm per kPa: a column worth checking
    assert np.abs(analytic - fd).max() <= 1e-5 * np.abs(fd).max()


@pytest.mark.parametrize("mode", ["exact", "paper"])
def test_fit_recovers_a_known_pressure(model, sites, mode):
    problem = FaceProblem(model, intraoral_pressure=True)
    truth = np.zeros(problem.num_muscles)
    truth[model.muscle_index("zygomaticus_major_left")] = 0.4
    problem.solve(activations=truth, pressure=40.0)
    markers = MarkerSet(problem, sites)
    targets = markers.positions(problem.u.x.array, problem.controls.cranium)
    problem.reset_to_rest()

    settings = dict(mode=mode, fit_head=False, fit_jaw=False, first_frame_gn_steps=12)
    fitter = FaceFitter(problem, markers, FitSettings(fit_pressure=True, **settings))
    result = fitter.fit_frame(targets)
    assert abs(result.pressure - 40.0) < 1.0
    assert result.rms_error < 0.05
    assert np.abs(result.activations - truth).max() < 0.05

    # Without the control the same markers are out of reach of the muscles by far.
    without = FaceProblem(model)
    unfitted = FaceFitter(without, MarkerSet(without, sites), FitSettings(**settings)).fit_frame(targets)
    assert unfitted.rms_error > 10 * result.rms_error


def test_a_model_without_an_oral_surface_has_no_pressure_control(model):
    ids = {name: tag for name, tag in model.boundary_ids.items() if name != "oral"}
    with pytest.raises(ValueError, match="no facets tagged 'oral'"):
        FaceProblem(dataclasses.replace(model, boundary_ids=ids), intraoral_pressure=True)
    problem = FaceProblem(model)
    with pytest.raises(ValueError, match="intraoral pressure"):
        problem.solve(pressure=10.0)
    with pytest.raises(ValueError, match="fit_pressure"):
        FaceFitter(problem, MarkerSet(problem, np.array(list(model.markers.values()))),
                   FitSettings(fit_pressure=True))
