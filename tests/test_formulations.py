"""The exact and paper formulations of the fit (``face_dolfinx.fitting.formulations``) on the slab.

- Layout: one name per Jacobian column, for every choice of fitted bones.
- The head's Jacobian columns are the derivatives of the controls' update (``retract``), so a
  Gauss-Newton step moves the head as its linear model predicts.
- Steps keep their constraints where the unconstrained least-squares step breaks them: exact
  mode's hard bounds (activations in [0, 1] and the trust region, TMJ limits), paper mode's
  penalties at their final weight (activation bounds, rigid cranium and jaw).
- Interpolation between two sets of controls ends at both.
"""
import numpy as np
import pytest

from face_dolfinx.fitting import FitSettings
from face_dolfinx.fitting.formulations import make_formulation
from face_dolfinx.model.bones import AffineMap, jaw_pose, rigid_map, rotation
from face_dolfinx.physics.problem import FaceProblem
from slab import slab_model

HEAD = rigid_map(rotation([0.2, 1.0, 0.1], 0.1), [20, 10, 5], [1.0, -0.5, 0.3])
TMJ = np.array([0.1, 1.0, 2.0])


@pytest.fixture(scope="module")
def problem():
    return FaceProblem(slab_model())


def posed_state(formulation):
    """Controls away from rest: some activations near their bounds, the head turned, the jaw open."""
    state = formulation.initial_state()
    state.activations = np.linspace(0.05, 0.95, formulation.num_muscles)
    state.cranium = HEAD
    if state.tmj is not None:
        state.tmj = TMJ.copy()
    state.jaw = jaw_pose(formulation.problem.model.jaw, *TMJ)
    return state


def affine_numbers(frame: AffineMap) -> np.ndarray:
    return np.concatenate([frame.matrix.reshape(-1), frame.translation])


@pytest.mark.parametrize("mode", ["exact", "paper"])
@pytest.mark.parametrize("fit_head, fit_jaw", [(True, True), (False, True), (True, False)])
def test_one_name_per_control(problem, mode, fit_head, fit_jaw):
    formulation = make_formulation(problem, FitSettings(mode=mode, fit_head=fit_head, fit_jaw=fit_jaw))
    names = formulation.control_names()
    assert len(set(names)) == len(names) == problem.num_muscles + formulation.head_size + formulation.jaw_size
    assert formulation.head_size == (formulation.head_controls if fit_head else 0)
    assert len(formulation.retract(posed_state(formulation), np.zeros(len(names))).activations) == problem.num_muscles


def test_unknown_mode_is_refused(problem):
    with pytest.raises(ValueError, match="unknown fitting mode"):
        make_formulation(problem, FitSettings(mode="affine"))


@pytest.mark.parametrize("mode", ["exact", "paper"])
def test_head_columns_are_derivatives_of_the_update(problem, mode):
    formulation = make_formulation(problem, FitSettings(mode=mode))
    state = posed_state(formulation)
    n, head = formulation.num_muscles, formulation.head_size
    columns, _ = formulation.head_columns(state, np.eye(12), np.zeros((12, 4, 3)))
    assert columns.shape == (head, 12)
    h = 1e-6
    for k in range(head):
        step = np.zeros(n + head + formulation.jaw_size)
        step[n + k] = h
        forward = affine_numbers(formulation.retract(state, step).cranium)
        backward = affine_numbers(formulation.retract(state, -step).cranium)
        assert np.allclose((forward - backward) / (2 * h), columns[k], atol=1e-7), k


def pushing_system(formulation, state, seed=0):
    """A least-squares system whose unconstrained solution drives the activations out of [0, 1]
    (and, in exact mode, the TMJ values past their limits)."""
    rng = np.random.default_rng(seed)
    size = formulation.num_muscles + formulation.head_size + formulation.jaw_size
    A = rng.normal(size=(3 * size, size))
    free = np.zeros(size)
    free[:formulation.num_muscles] = np.where(state.activations > 0.5, 1.5, -1.5)
    free[formulation.num_muscles:] = rng.normal(scale=0.5, size=size - formulation.num_muscles)
    if state.tmj is not None:
        free[-3:] = [1.0, -5.0, 20.0]
    return A, A @ free, free


def test_exact_step_keeps_the_hard_bounds(problem):
    formulation = make_formulation(problem, FitSettings(mode="exact"))
    formulation.trust_radius = 0.25
    state = posed_state(formulation)
    A, b, free = pushing_system(formulation, state)
    assert np.allclose(np.linalg.lstsq(A, b, rcond=None)[0], free)  # unconstrained: out of bounds
    step = formulation.step(state, A, b)
    n = formulation.num_muscles
    activations = state.activations + step[:n]
    assert np.all(activations >= -1e-12) and np.all(activations <= 1.0 + 1e-12)
    assert np.abs(step[:n]).max() <= 0.25 + 1e-12
    assert np.abs(step[:n]).max() == pytest.approx(0.25)  # the far target pulls to the edge
    low, high = formulation.tmj_limits()
    tmj = state.tmj + step[-3:]
    assert np.all(tmj >= low - 1e-12) and np.all(tmj <= high + 1e-12)
    assert np.isclose(tmj[1], low[1]) and np.isclose(tmj[2], high[2])  # both slides at a limit


def test_paper_step_ends_on_its_penalties(problem):
    formulation = make_formulation(problem, FitSettings(mode="paper"))
    state = posed_state(formulation)
    A, b, free = pushing_system(formulation, state)
    formulation.start_frame(np.zeros((4, 3)), np.ones(4, bool), warm=True)
    moved = formulation.retract(state, formulation.step(state, A, b))
    assert formulation.rho_final == pytest.approx(formulation.settings.penalty_final_ratio * float(b @ b))
    free_activations = state.activations + free[:formulation.num_muscles]
    assert np.abs(np.clip(free_activations, 0, 1) - free_activations).max() > 0.4
    assert np.abs(np.clip(moved.activations, 0, 1) - moved.activations).max() < 1e-3
    for frame in (moved.cranium, moved.jaw):
        assert np.abs(frame.matrix.T @ frame.matrix - np.eye(3)).max() < 1e-3
    assert formulation.constraint_penalty(moved).value < 1e-5 * formulation.constraint_penalty(
        formulation.retract(state, free)).value


@pytest.mark.parametrize("mode", ["exact", "paper"])
def test_interpolation_ends_at_both_states(problem, mode):
    formulation = make_formulation(problem, FitSettings(mode=mode))
    a = posed_state(formulation)
    step = np.random.default_rng(1).normal(scale=0.05, size=len(formulation.control_names()))
    b = formulation.retract(a, step)
    for t, end in ((0.0, a), (1.0, b)):
        between = formulation.interpolate(a, b, t)
        assert np.allclose(between.activations, end.activations, atol=1e-12)
        assert np.allclose(affine_numbers(between.cranium), affine_numbers(end.cranium), atol=1e-12)
        assert np.allclose(affine_numbers(formulation.jaw(between)), affine_numbers(formulation.jaw(end)),
                           atol=1e-12)
