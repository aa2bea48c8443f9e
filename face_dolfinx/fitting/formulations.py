"""The two formulations of the fit: which controls, how they step, and their constraints.

A formulation owns everything in which the fits differ: the layout and names of the controls,
the jaw pose they give, their Jacobian columns for the head and jaw, the Gauss-Newton step under
their constraints, the update of the controls by a step and the interpolation between two sets of
controls. ``FaceFitter`` drives either through this interface.

``exact`` (``ExactFormulation``): activations with hard bounds [0, 1] in a trust region (bounded
  linear least squares), the head a rigid motion updated on the rotation group (3 rotation + 3
  translation controls), the jaw its 3 TMJ degrees of freedom with hard bounds;
``paper`` (``PaperFormulation``, sifakis2005 section 7): activations + 12 affine cranium + 12
  affine jaw numbers, bounds, rigidity and TMJ constraints as penalties (``penalties``) whose
  weight rho grows by ``penalty_growth`` per Newton step of the nested schedule.
Both may add the intraoral pressure (``FitSettings.fit_pressure``), one control in kPa within
+-``pressure_limit`` (a hard bound in exact mode, a penalty in paper mode).
"""
from abc import ABC, abstractmethod
import math

import numpy as np
from scipy.optimize import lsq_linear

from . import penalties
from face_dolfinx.model.bones import AffineMap, jaw_pose, rotation, tmj_upper_limits
from face_dolfinx.sensitivities.columns import bone_position_derivatives, teeth_pose_derivatives

MIN_TRUST_RADIUS = 0.01
TMJ_STEP = 1e-6  # central-difference step of the closed-form jaw pose (rad, mm)


class ControlState:
    """The controls of one formulation (``mode``): activations, cranium and jaw frames, the TMJ
    values in exact mode (the jaw frame then follows from them) and the intraoral pressure (kPa)."""

    def __init__(self, mode: str, activations, cranium: AffineMap, jaw: AffineMap, tmj=None,
                 pressure: float = 0.0):
        self.mode = mode
        self.activations = np.asarray(activations, dtype=float).copy()
        self.cranium = cranium
        self.jaw = jaw
        self.tmj = None if tmj is None else np.asarray(tmj, dtype=float).copy()
        self.pressure = float(pressure)

    def copy(self):
        return ControlState(self.mode, self.activations, self.cranium, self.jaw, self.tmj, self.pressure)


class Formulation(ABC):
    """The interface of a formulation; ``name`` is its ``FitSettings.mode``.

    The control vector c, whose columns make the marker Jacobian, is laid out as
    activations (``num_muscles``), head (``head_size``, 0 unless ``fit_head``), jaw (``jaw_size``, 0
    unless ``fit_jaw``), intraoral pressure (``pressure_size``, 0 unless ``fit_pressure``).
    """
    name = ""
    head_controls = 0
    jaw_controls = 0
    # True when a step changes the objective's penalty term at the same controls (its weight).
    step_changes_objective = False

    def __init__(self, problem, settings):
        self.problem = problem
        self.settings = settings
        self.jaw_geometry = problem.model.jaw
        self.num_muscles = problem.num_muscles
        self.head_size = self.head_controls if settings.fit_head else 0
        self.jaw_size = self.jaw_controls if settings.fit_jaw else 0
        self.pressure_size = 1 if settings.fit_pressure else 0
        self.pressure_index = self.num_muscles + self.head_size + self.jaw_size
        if settings.fit_pressure and not problem.has_pressure:
            raise ValueError("fit_pressure needs a FaceProblem with the intraoral pressure control")

    @abstractmethod
    def initial_state(self) -> ControlState:
        """Rest: no activation, bones in place."""

    def control_names(self) -> list[str]:
        """Names of the Jacobian's columns, in order."""
        names = [muscle.name for muscle in self.problem.model.muscles]
        if self.head_size:
            names += self.head_names()
        if self.jaw_size:
            names += self.jaw_names()
        if self.pressure_size:
            names.append("intraoral_pressure")
        return names

    @abstractmethod
    def jaw(self, state: ControlState) -> AffineMap:
        """The jaw frame of ``state``."""

    @abstractmethod
    def head_columns(self, state: ControlState, dofs: np.ndarray, markers: np.ndarray):
        """The head's columns from those of the 12 affine cranium numbers, d/d(M_c, t_c) of the
        dofs (12, dofs) and the markers (12, markers, 3)."""

    @abstractmethod
    def jaw_parameters(self, state: ControlState) -> tuple:
        """(pose_of, values, step): the bone frames (cranium, jaw) as a function of the jaw
        controls, their values at ``state`` and the central-difference step of their derivatives."""

    def jaw_position_derivatives(self, state: ControlState):
        """d(jaw boundary positions)/d(jaw controls) at ``state``, for the jaw's columns."""
        return bone_position_derivatives(self.problem, *self.jaw_parameters(state))

    def jaw_teeth_derivatives(self, state: ControlState):
        """d(teeth poses)/d(jaw controls) at ``state`` (``teeth_pose_derivatives``), for the jaw's
        columns of a problem with teeth contact: the lower teeth move with the mandible."""
        return teeth_pose_derivatives(self.problem, *self.jaw_parameters(state))

    def start_frame(self, targets: np.ndarray, present: np.ndarray, warm: bool) -> None:
        """Per-frame settings, before its first objective; ``warm``: not the first frame."""

    def penalty(self, state: ControlState) -> float:
        """The objective's term beyond the marker residual and temporal smoothness."""
        return 0.0

    @abstractmethod
    def step(self, state: ControlState, A: np.ndarray, b: np.ndarray) -> np.ndarray:
        """The control step dc minimising |A dc - b|^2 under the formulation's constraints."""

    def judge_step(self, step, residual, jacobian, actual_decrease: float) -> None:
        """Learn from the objective's ``actual_decrease`` at the full step, against the decrease
        |r|^2 - |r + J dc|^2 the linear model predicted."""

    @abstractmethod
    def retract(self, state: ControlState, step: np.ndarray) -> ControlState:
        """The controls at ``state`` moved by ``step``."""

    @abstractmethod
    def interpolate(self, a: ControlState, b: ControlState, t: float) -> ControlState:
        """The controls a fraction ``t`` of the way from ``a`` to ``b``."""

    def summary(self) -> str:
        """The step's adaptive parameter, for the log."""
        return ""

    @abstractmethod
    def head_names(self) -> list[str]:
        """Names of the head's controls."""

    @abstractmethod
    def jaw_names(self) -> list[str]:
        """Names of the jaw's controls."""


class ExactFormulation(Formulation):
    """Hard bounds, the head on the rotation group, the jaw by its TMJ values.

    The activation step lies in a trust region (max |da| <= ``trust_radius``), adapted within a
    frame by how well the linear prediction matched (``FitSettings.activation_trust_radius``).
    """
    name = "exact"
    head_controls = 6
    jaw_controls = 3

    def __init__(self, problem, settings):
        super().__init__(problem, settings)
        self.trust_radius = settings.activation_trust_radius

    def initial_state(self) -> ControlState:
        return ControlState(self.name, np.zeros(self.num_muscles), AffineMap(), AffineMap(), np.zeros(3))

    def head_names(self):
        return [f"head_rotation_{axis}" for axis in "xyz"] + [f"head_translation_{axis}" for axis in "xyz"]

    def jaw_names(self):
        return ["jaw_opening", "jaw_slide_right", "jaw_slide_left"]

    def jaw(self, state):
        return jaw_pose(self.jaw_geometry, *state.tmj)

    def head_columns(self, state, dofs, markers):
        combine = head_combination(state.cranium)
        return combine @ dofs, np.tensordot(combine, markers, axes=1)

    def jaw_parameters(self, state):
        pose = lambda p: (state.cranium, jaw_pose(self.jaw_geometry, *p))  # noqa: E731
        return pose, state.tmj, TMJ_STEP

    def tmj_limits(self) -> tuple[np.ndarray, np.ndarray]:
        """Lower and upper bounds of the TMJ values: opening (rad), right and left slides (mm)."""
        return np.zeros(3), tmj_upper_limits(self.jaw_geometry)

    def start_frame(self, targets, present, warm):
        # From rest (the first frame) the activations have far to go.
        self.trust_radius = self.settings.activation_trust_radius if warm else 1.0

    def step(self, state, A, b):
        """Bounded linear least squares: activations in [0, 1] and the trust region, TMJ values
        and the pressure within their limits."""
        n, head = self.num_muscles, self.head_size
        lower = np.full(A.shape[1], -np.inf)
        upper = np.full(A.shape[1], np.inf)
        lower[:n] = np.maximum(-state.activations, -self.trust_radius)
        upper[:n] = np.minimum(1.0 - state.activations, self.trust_radius)
        if self.jaw_size:
            limits_low, limits_high = self.tmj_limits()
            lower[n + head:n + head + 3] = limits_low - state.tmj
            upper[n + head:n + head + 3] = limits_high - state.tmj
        if self.pressure_size:
            limit = self.settings.pressure_limit
            lower[self.pressure_index] = -limit - state.pressure
            upper[self.pressure_index] = limit - state.pressure
        # Round-off can put a control a hair outside its bounds; the step may not be infeasible.
        upper = np.maximum(upper, lower)
        scale = np.maximum(np.linalg.norm(A, axis=0), 1e-12)  # column scaling: mm vs rad vs 1
        result = lsq_linear(A / scale, b, bounds=(lower * scale, upper * scale), method="bvls", tol=1e-12)
        return result.x / scale

    def judge_step(self, step, residual, jacobian, actual_decrease):
        """The trust radius doubles when the prediction held at a step on its edge, halves when
        it did not."""
        predicted = np.sum(residual**2) - np.sum((residual + np.tensordot(step, jacobian, axes=1))**2)
        agreement = actual_decrease / predicted if predicted > 0 else -math.inf
        if agreement > 0.75 and np.abs(step[:self.num_muscles]).max(initial=0.0) >= 0.99 * self.trust_radius:
            self.trust_radius = min(2.0 * self.trust_radius, 1.0)
        elif agreement < 0.25:
            self.trust_radius = max(0.5 * self.trust_radius, MIN_TRUST_RADIUS)

    def retract(self, state, step):
        n, head = self.num_muscles, self.head_size
        new = state.copy()
        new.activations = np.clip(state.activations + step[:n], 0.0, 1.0)
        if head:
            spin = rotation(step[n:n + 3], np.linalg.norm(step[n:n + 3])) if np.any(step[n:n + 3]) else np.eye(3)
            new.cranium = AffineMap(spin @ state.cranium.matrix,
                                    spin @ state.cranium.translation + step[n + 3:n + 6])
        if self.jaw_size:
            new.tmj = state.tmj + step[n + head:n + head + 3]
        if self.pressure_size:
            limit = self.settings.pressure_limit
            new.pressure = float(np.clip(state.pressure + step[self.pressure_index], -limit, limit))
        return new

    def interpolate(self, a, b, t):
        """Activations, TMJ values and pressure linearly, the head's rotation along the geodesic."""
        new = a.copy()
        new.activations = (1 - t) * a.activations + t * b.activations
        new.pressure = (1 - t) * a.pressure + t * b.pressure
        new.jaw = a.jaw.interpolate(b.jaw, t)
        new.tmj = (1 - t) * a.tmj + t * b.tmj
        axis, angle = _axis_angle(b.cranium.matrix @ a.cranium.matrix.T)
        spin = rotation(axis, t * angle) if angle else np.eye(3)
        new.cranium = AffineMap(spin @ a.cranium.matrix,
                                (1 - t) * a.cranium.translation + t * b.cranium.translation)
        return new

    def summary(self):
        return f"trust {self.trust_radius:.3f}"


class PaperFormulation(Formulation):
    """Affine bone frames with the nested penalty schedule of sifakis2005 section 7.

    Per frame, rho starts at 1e-6 times the targets' spread squared; each step minimises
    |A dc - b|^2 + rho_i phi_p(c + dc) by Newton steps while rho_{i+1} = ``penalty_growth`` rho_i,
    up to ``penalty_final_ratio`` times the step's residual |b|^2. The objective weighs phi_p with
    the last step's final rho.
    """
    name = "paper"
    head_controls = 12
    jaw_controls = 12
    step_changes_objective = True

    def __init__(self, problem, settings):
        super().__init__(problem, settings)
        check_contact(problem, settings)
        self.rho_start = self.rho_final = 0.0

    def initial_state(self) -> ControlState:
        return ControlState(self.name, np.zeros(self.num_muscles), AffineMap(), AffineMap())

    def head_names(self):
        return [f"head_M{i}{j}" for i in range(3) for j in range(3)] + [f"head_t{axis}" for axis in "xyz"]

    def jaw_names(self):
        return [f"jaw_M{i}{j}" for i in range(3) for j in range(3)] + [f"jaw_t{axis}" for axis in "xyz"]

    def jaw(self, state):
        return state.jaw

    def head_columns(self, state, dofs, markers):
        return dofs, markers

    def jaw_parameters(self, state):
        params = np.concatenate([state.jaw.matrix.reshape(-1), state.jaw.translation])
        pose = lambda p: (state.cranium, AffineMap(p[:9], p[9:]))  # noqa: E731
        return pose, params, 1.0

    def start_frame(self, targets, present, warm):
        spread = np.nanstd(targets[present]) if present.any() else 1.0
        self.rho_start = 1e-6 * spread**2
        self.rho_final = self.rho_start

    def penalty(self, state):
        return self.rho_final * self.constraint_penalty(state).value

    def constraint_penalty(self, state: ControlState) -> penalties.PenaltyValue:
        """phi_p on the fitted controls (fixed frames contribute nothing)."""
        n = self.num_muscles
        full = np.concatenate([state.activations, state.cranium.matrix.reshape(-1),
                               state.cranium.translation, state.jaw.matrix.reshape(-1),
                               state.jaw.translation])
        value = penalties.kinematic_and_bounds(full, n, self.jaw_geometry)
        keep = np.concatenate([np.arange(n), np.arange(n, n + 12) if self.head_size else [],
                               np.arange(n + 12, n + 24) if self.jaw_size else []]).astype(int)
        fitted = penalties.PenaltyValue(value.value, value.gradient[keep], value.hessian[np.ix_(keep, keep)])
        if not self.pressure_size:
            return fitted
        bound = penalties.symmetric_bound(state.pressure, self.settings.pressure_limit)
        size = len(keep) + 1
        gradient, hessian = np.zeros(size), np.zeros((size, size))
        gradient[:-1], hessian[:-1, :-1] = fitted.gradient, fitted.hessian
        gradient[-1], hessian[-1, -1] = bound.gradient[0], bound.hessian[0, 0]
        return penalties.PenaltyValue(fitted.value + bound.value, gradient, hessian)

    def vector(self, state: ControlState) -> np.ndarray:
        """The fitted controls as one vector c."""
        parts = [state.activations]
        if self.head_size:
            parts += [state.cranium.matrix.reshape(-1), state.cranium.translation]
        if self.jaw_size:
            parts += [state.jaw.matrix.reshape(-1), state.jaw.translation]
        if self.pressure_size:
            parts.append([state.pressure])
        return np.concatenate(parts)

    def state_from_vector(self, template: ControlState, c: np.ndarray) -> ControlState:
        """``template`` with the fitted controls of ``c``."""
        n = self.num_muscles
        state = template.copy()
        state.activations = c[:n].copy()
        offset = n
        if self.head_size:
            state.cranium = AffineMap(c[offset:offset + 9], c[offset + 9:offset + 12])
            offset += 12
        if self.jaw_size:
            state.jaw = AffineMap(c[offset:offset + 9], c[offset + 9:offset + 12])
        if self.pressure_size:
            state.pressure = float(c[self.pressure_index])
        return state

    def step(self, state, A, b):
        """Section 7: minimise |A dc - b|^2 + rho_i phi_p(c + dc) for growing rho_i (Newton)."""
        c0 = self.vector(state)
        phi = float(b @ b)
        rho = max(self.rho_start, 1e-12)
        rho_final = max(self.settings.penalty_final_ratio * phi, rho)
        self.rho_final = rho_final
        AtA, Atb = A.T @ A, A.T @ b
        dc = np.zeros_like(c0)
        while True:
            p = self.constraint_penalty(self.state_from_vector(state, c0 + dc))
            gradient = 2.0 * (AtA @ dc - Atb) + rho * p.gradient
            hessian = 2.0 * AtA + rho * p.hessian
            dc -= np.linalg.lstsq(hessian, gradient, rcond=1e-12)[0]
            if rho >= rho_final:
                return dc
            rho = min(rho * self.settings.penalty_growth, rho_final)

    def retract(self, state, step):
        return self.state_from_vector(state, self.vector(state) + step)

    def interpolate(self, a, b, t):
        new = a.copy()
        new.activations = (1 - t) * a.activations + t * b.activations
        new.jaw = a.jaw.interpolate(b.jaw, t)
        new.cranium = a.cranium.interpolate(b.cranium, t)
        new.pressure = (1 - t) * a.pressure + t * b.pressure
        return new

    def summary(self):
        return f"rho {self.rho_final:.3g}"


FORMULATIONS = {formulation.name: formulation for formulation in (ExactFormulation, PaperFormulation)}


def check_contact(problem, settings) -> None:
    """Refuse, before any solve, a fit whose formulation cannot carry the contact of ``problem``:
    the paper mode fitting the head or the jaw with the teeth, which are rigid objects placed by
    the bone frames (an affine frame would shear them). ``PaperFormulation`` calls it, so every
    fitter meets it; the fit command calls it before it writes its folder."""
    if settings.mode == "paper" and problem.teeth_contact is not None and (settings.fit_head or settings.fit_jaw):
        raise ValueError("the paper mode (--mode paper) cannot fit with the teeth (--contact on a model with "
                         "teeth): its affine cranium and jaw frames would shear them; fit with contact in exact mode")


def make_formulation(problem, settings) -> Formulation:
    """The formulation named by ``settings.mode``."""
    try:
        return FORMULATIONS[settings.mode](problem, settings)
    except KeyError:
        raise ValueError(f"unknown fitting mode {settings.mode!r}: use 'exact' or 'paper'") from None


def head_combination(cranium: AffineMap) -> np.ndarray:
    """(6, 12): exact-mode head controls (rotation about the origin on the group,
    M <- exp([w]) M, t <- exp([w]) t, then translation) in terms of the 12 affine numbers."""
    combine = np.zeros((6, 12))
    for k, axis in enumerate(np.eye(3)):
        G = _cross_matrix(axis)
        combine[k, :9] = (G @ cranium.matrix).reshape(-1)
        combine[k, 9:] = G @ cranium.translation
    combine[3:, 9:] = np.eye(3)
    return combine


def _cross_matrix(axis: np.ndarray) -> np.ndarray:
    x, y, z = axis
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def _axis_angle(R: np.ndarray) -> tuple[np.ndarray, float]:
    angle = math.acos(max(-1.0, min(1.0, (np.trace(R) - 1.0) / 2.0)))
    if angle < 1e-14:
        return np.array([1.0, 0.0, 0.0]), 0.0
    axis = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    return axis / np.linalg.norm(axis), angle
