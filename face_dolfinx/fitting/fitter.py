"""Gauss-Newton fitting of activations and bone motion to markers (sifakis2005 sections 5-9).

Per frame, from the previous frame's equilibrium and controls:
  1. factorise the tangent once, solve for dX/dc (activations, jaw) and add the analytic cranium
     columns: the marker Jacobian J = W dX/dc;
  2. the Gauss-Newton step minimises |r + J dc|^2 (r = simulated - captured markers present in
     this frame) under the mode's constraints;
  3. solve the equilibrium at the new controls from the linear prediction X + dX/dc dc; accept the
     step when the objective drops, otherwise golden-section search along it (each trial starting
     from the linear interpolation of the two shapes, as the paper does);
  4. repeat until the relative decrease or the step is small.

Two formulations share this driver:
  ``exact``: activations with hard bounds [0, 1] (bounded linear least squares), the head a rigid
    motion updated on the rotation group, the jaw its 3 TMJ degrees of freedom with hard bounds;
  ``paper``: 32 activations + 12 affine cranium + 12 affine jaw numbers, with the nested penalty
    schedule of section 7 (rho grows by 5 % per step) for the bounds, rigidity and TMJ terms.
"""
from dataclasses import dataclass, field
import logging
import math
import time

import numpy as np
from scipy.optimize import lsq_linear

from . import penalties
from face_dolfinx.model.bones import AffineMap, jaw_pose, rotation
from face_dolfinx.physics.points import PointEvaluator
from face_dolfinx.sensitivities.columns import EquilibriumSensitivity, bone_position_derivatives, frame_columns
from face_dolfinx.equilibrium.solver import EquilibriumError

log = logging.getLogger(__name__)

GOLDEN = (math.sqrt(5.0) - 1.0) / 2.0
MIN_TRUST_RADIUS = 0.01
TMJ_STEP = 1e-6  # central-difference step of the closed-form jaw pose (rad, mm)
# An under-determined frame names the controls whose weight in the weak directions is at least
# this share of the largest: the ones that make up those directions, not every small contributor.
WEAK_SHARE = 0.5


@dataclass
class FitSettings:
    mode: str = "exact"                 # "exact" or "paper"
    max_gn_steps: int = 3               # per frame, warm-started
    first_frame_gn_steps: int = 8       # from a remote initial guess
    relative_decrease: float = 1e-3     # stop when the objective drops by less than this
    min_step: float = 1e-5              # stop when the control step is smaller than this
    marker_tolerance: float = 1e-4      # mm: stop when the marker RMS error is below this
    trial_halvings: int = 3             # a trial point whose continuation needs steps under 2^-3 is rejected
    line_search_depth: int = 6          # golden-section evaluations when the full step fails
    line_search: bool = True            # False: pure Gauss-Newton, every full step taken (stability study)
    line_search_every_step: bool = False  # the paper's loop: golden section on every step, the full step one candidate
    temporal_smoothness: float = 0.0    # weight (mm^2 per unit activation^2) towards the last frame
    fit_head: bool = True
    fit_jaw: bool = True
    unreachable_rms: float = 3.0        # mm: a frame fitted worse than this is flagged
    # A frame is flagged under-determined when some combination of controls moves its visible
    # markers by less than this fraction of what a complete frame shows (``observability``;
    # chosen from the damage study's gaps, docs/fitting.md).
    observability_threshold: float = 0.1
    reuse_jacobian: bool = True         # first step of a frame: the last frame's J, turned with the head
    # Exact Jacobians per frame after that first step (None: one per step); later steps reuse the
    # newest, turned with the head, or an approximate one. An inexact J whose step fails is
    # always replaced by an exact one.
    max_fresh_jacobians: int | None = None
    # mm: a fresh Jacobian may use the newest factor of the equilibrium solve if it was made at a
    # state this close to the equilibrium (an approximate tangent: the step's direction, not the
    # fit's optimum, depends on it) instead of factorising again. 0: always the exact tangent.
    approximate_jacobian_within: float = 0.0
    # Exact mode: trust region on the activation step (max |da|), adapted within a frame by how
    # well the linear prediction matched (doubles on agreement, halves otherwise). Noise in
    # poorly identified muscle combinations otherwise moves activations by 0.5 in one step, and
    # each such step then costs 10+ Newton iterations at equilibrium (docs/fitting.md: 0.1 was
    # faster but under-fitted fast takes in 3 steps).
    activation_trust_radius: float = 0.25
    penalty_growth: float = 1.05        # paper mode: rho_{i+1} = 1.05 rho_i
    penalty_final_ratio: float = 1e6    # ... until rho = 1e6 phi(c)


@dataclass
class FrameResult:
    frame: int
    activations: np.ndarray
    cranium: AffineMap
    jaw: AffineMap
    jaw_tmj: np.ndarray | None          # opening (rad), right and left slides (mm); exact mode
    marker_errors: np.ndarray           # per marker (mm), NaN where missing
    rms_error: float
    max_error: float
    gn_steps: int
    seconds: float
    phases: dict = field(default_factory=dict)
    flag: str = ""                      # why this frame is doubtful or skipped ("" = fine)
    initial_rms: float = math.nan       # marker RMS error of the warm start, before fitting
    observability: float = math.nan     # how well the visible markers determine the controls (1: as all do)
    unobservable: list[str] = field(default_factory=list)  # controls they cannot determine


class MarkerSet:
    """Markers at fixed material points of the face (plus an offset that turns with the head)."""

    def __init__(self, problem, surface_points: np.ndarray, offsets: np.ndarray | None = None,
                 names: list[str] | None = None):
        self.reference = np.asarray(surface_points, dtype=float).reshape(-1, 3)
        self.offsets = np.zeros_like(self.reference) if offsets is None else np.asarray(offsets, float)
        self.names = names or [f"marker_{i}" for i in range(len(self.reference))]
        self.evaluator = PointEvaluator(problem.V, self.reference)

    def positions(self, displacement: np.ndarray, cranium: AffineMap) -> np.ndarray:
        return self.reference + self.evaluator.values(displacement) + self.offsets @ cranium.matrix.T


class ControlState:
    """The controls of one formulation with their Jacobian columns, steps and bounds."""

    def __init__(self, mode: str, activations, cranium: AffineMap, jaw: AffineMap, tmj=None):
        self.mode = mode
        self.activations = np.asarray(activations, dtype=float).copy()
        self.cranium = cranium
        self.jaw = jaw
        self.tmj = None if tmj is None else np.asarray(tmj, dtype=float).copy()

    def copy(self):
        return ControlState(self.mode, self.activations, self.cranium, self.jaw, self.tmj)


class FaceFitter:
    """Fits frames of marker targets with a ``FaceProblem``; keeps the last equilibrium."""

    def __init__(self, problem, markers: MarkerSet, settings: FitSettings | None = None):
        self.problem = problem
        self.markers = markers
        self.settings = settings or FitSettings()
        if self.settings.mode not in ("exact", "paper"):
            raise ValueError(f"unknown fitting mode {self.settings.mode!r}: use 'exact' or 'paper'")
        self.sensitivity = EquilibriumSensitivity(problem)
        self.jaw_geometry = problem.model.jaw
        n = problem.num_muscles
        tmj = np.zeros(3) if self.settings.mode == "exact" else None
        self.state = ControlState(self.settings.mode, np.zeros(n), AffineMap(), AffineMap(), tmj)
        self.previous_activations = None
        self.frames_done = 0
        self._cached_jacobian = None  # (state, dof columns, marker columns) of the last GN step

    # -- controls <-> problem -----------------------------------------------------------------
    def _jaw_of(self, state: ControlState) -> AffineMap:
        if state.mode == "exact":
            return jaw_pose(self.jaw_geometry, *state.tmj)
        return state.jaw

    def _equilibrium(self, state: ControlState, guess: np.ndarray | None, trial: bool = False) -> None:
        """Equilibrium at ``state``. A trial point (a Gauss-Newton candidate or a line-search
        point) that needs deep continuation is a bad step: it is rejected early, not forced."""
        self.problem.solve(activations=np.clip(state.activations, 0.0, 1.0),
                           cranium=state.cranium, jaw=self._jaw_of(state), guess=guess,
                           max_halvings=self.settings.trial_halvings if trial else 10)

    def _objective(self, state: ControlState, targets, present) -> tuple[float, np.ndarray]:
        simulated = self.markers.positions(self.problem.u.x.array, state.cranium)
        residual = (simulated - targets)[present]
        value = float(np.sum(residual**2))
        if self.settings.temporal_smoothness and self.previous_activations is not None:
            value += self.settings.temporal_smoothness * float(
                np.sum((state.activations - self.previous_activations) ** 2))
        if state.mode == "paper":
            value += self._rho_final * self._penalty(state).value
        return value, simulated

    # -- Jacobian -----------------------------------------------------------------------------
    def _columns(self, state: ControlState, approximate_within: float) -> tuple[np.ndarray, np.ndarray, float, bool]:
        """dX/dc as dof arrays (k, ndofs), the marker Jacobian (k, markers, 3), the time and
        whether it is exact (from the tangent at this state, not at one ``approximate_within`` mm
        away)."""
        start = time.perf_counter()
        exact_jacobian = self.sensitivity.factor(reuse_within=approximate_within) == 0.0
        columns = [self.sensitivity.activation_columns()]
        cranium_marker_columns = None
        if self.settings.fit_head:
            cranium_dofs = self.sensitivity.cranium_columns()
            cranium_marker = self._cranium_marker_columns(state)
            if state.mode == "exact":
                combine = _exact_head_combination(state.cranium)
                cranium_dofs = combine @ cranium_dofs
                cranium_marker = np.tensordot(combine, cranium_marker, axes=1)
            columns.append(cranium_dofs)
            cranium_marker_columns = cranium_marker
        if self.settings.fit_jaw:
            if state.mode == "exact":
                pose = lambda p: (state.cranium, jaw_pose(self.jaw_geometry, *p))  # noqa: E731
                derivatives = bone_position_derivatives(self.problem, pose, state.tmj, TMJ_STEP)
            else:
                params = np.concatenate([state.jaw.matrix.reshape(-1), state.jaw.translation])
                pose = lambda p: (state.cranium, AffineMap(p[:9], p[9:]))  # noqa: E731
                derivatives = bone_position_derivatives(self.problem, pose, params, 1.0)
            columns.append(self.sensitivity.boundary_columns(derivatives))
        dofs = np.concatenate(columns)
        marker = self.markers.evaluator.values_many(dofs)
        if cranium_marker_columns is not None:
            n = self.problem.num_muscles
            marker[n:n + len(cranium_marker_columns)] = cranium_marker_columns
        return dofs, marker, time.perf_counter() - start, exact_jacobian

    def _close_factor(self) -> bool:
        """The newest factor may serve a fresh Jacobian (``approximate_jacobian_within``)."""
        within = self.settings.approximate_jacobian_within
        return within > 0.0 and self.problem.solver.factor_distance() <= within

    def _reused_columns(self, state: ControlState):
        """The cached Jacobian turned by the change of the head's rotation since it was computed
        (the paper's warm start), with fresh analytic cranium columns."""
        start = time.perf_counter()
        cached_state, dofs, marker = self._cached_jacobian
        turn = state.cranium.matrix @ np.linalg.inv(cached_state.cranium.matrix)
        dofs = (dofs.reshape(len(dofs), -1, 3) @ turn.T).reshape(len(dofs), -1)
        marker = marker @ turn.T
        if self.settings.fit_head:
            n, head, _ = self._layout()
            cranium = self._cranium_marker_columns(state)
            cranium_dofs = self.sensitivity.cranium_columns()
            if state.mode == "exact":
                combine = _exact_head_combination(state.cranium)
                cranium, cranium_dofs = np.tensordot(combine, cranium, axes=1), combine @ cranium_dofs
            marker[n:n + head] = cranium
            dofs[n:n + head] = cranium_dofs
        return dofs, marker, time.perf_counter() - start

    def _cranium_marker_columns(self, state: ControlState) -> np.ndarray:
        """d(marker)/d(M_c, t_c) (12, markers, 3): the whole face, offsets included, moves
        with the cranium frame."""
        return frame_columns(self.markers.positions(self.problem.u.x.array, state.cranium), state.cranium)

    # -- steps --------------------------------------------------------------------------------
    def _layout(self):
        n = self.problem.num_muscles
        head = (6 if self.settings.mode == "exact" else 12) if self.settings.fit_head else 0
        jaw = (3 if self.settings.mode == "exact" else 12) if self.settings.fit_jaw else 0
        return n, head, jaw

    def _gn_step(self, state: ControlState, jacobian: np.ndarray, residual: np.ndarray) -> np.ndarray:
        """The control step: bounded least squares (exact) or the nested penalty loop (paper)."""
        n, head, jaw = self._layout()
        A = jacobian.reshape(len(jacobian), -1).T  # (3 markers, controls)
        b = -residual.reshape(-1)
        w = self.settings.temporal_smoothness
        if w and self.previous_activations is not None:
            rows = np.zeros((n, A.shape[1]))
            rows[:, :n] = math.sqrt(w) * np.eye(n)
            A = np.vstack([A, rows])
            b = np.concatenate([b, -math.sqrt(w) * (state.activations - self.previous_activations)])
        if state.mode == "exact":
            lower = np.full(A.shape[1], -np.inf)
            upper = np.full(A.shape[1], np.inf)
            lower[:n] = np.maximum(-state.activations, -self.trust_radius)
            upper[:n] = np.minimum(1.0 - state.activations, self.trust_radius)
            if jaw:
                geometry = self.jaw_geometry
                limits_low = np.array([0.0, 0.0, 0.0])
                limits_high = np.array([math.asin(geometry.max_opening_sine), geometry.track_length,
                                        geometry.track_length])
                lower[n + head:] = limits_low - state.tmj
                upper[n + head:] = limits_high - state.tmj
            # Round-off can put a control a hair outside its bounds; the step may not be infeasible.
            upper = np.maximum(upper, lower)
            scale = np.maximum(np.linalg.norm(A, axis=0), 1e-12)  # column scaling: mm vs rad vs 1
            result = lsq_linear(A / scale, b, bounds=(lower * scale, upper * scale),
                                method="bvls", tol=1e-12)
            return result.x / scale
        return self._nested_penalty_step(state, A, b)

    def _paper_vector(self, state: ControlState) -> np.ndarray:
        n, head, jaw = self._layout()
        parts = [state.activations]
        if head:
            parts += [state.cranium.matrix.reshape(-1), state.cranium.translation]
        if jaw:
            parts += [state.jaw.matrix.reshape(-1), state.jaw.translation]
        return np.concatenate(parts)

    def _penalty(self, state: ControlState) -> penalties.PenaltyValue:
        """phi_p on the fitted controls (fixed frames contribute nothing)."""
        n, head, jaw = self._layout()
        full = np.concatenate([state.activations, state.cranium.matrix.reshape(-1),
                               state.cranium.translation, state.jaw.matrix.reshape(-1),
                               state.jaw.translation])
        value = penalties.kinematic_and_bounds(full, n, self.jaw_geometry)
        keep = np.concatenate([np.arange(n), np.arange(n, n + 12) if head else [],
                               np.arange(n + 12, n + 24) if jaw else []]).astype(int)
        return penalties.PenaltyValue(value.value, value.gradient[keep],
                                      value.hessian[np.ix_(keep, keep)])

    def _state_from_paper_vector(self, template: ControlState, c: np.ndarray) -> ControlState:
        n, head, jaw = self._layout()
        state = template.copy()
        state.activations = c[:n].copy()
        offset = n
        if head:
            state.cranium = AffineMap(c[offset:offset + 9], c[offset + 9:offset + 12])
            offset += 12
        if jaw:
            state.jaw = AffineMap(c[offset:offset + 9], c[offset + 9:offset + 12])
        return state

    def _nested_penalty_step(self, state: ControlState, A: np.ndarray, b: np.ndarray) -> np.ndarray:
        """Section 7: minimise |A dc - b|^2 + rho_i phi_p(c + dc) for growing rho_i (Newton)."""
        c0 = self._paper_vector(state)
        phi = float(b @ b)
        rho = max(self._rho_start, 1e-12)
        rho_final = max(self.settings.penalty_final_ratio * phi, rho)
        self._rho_final = rho_final
        AtA, Atb = A.T @ A, A.T @ b
        dc = np.zeros_like(c0)
        while True:
            p = self._penalty(self._state_from_paper_vector(state, c0 + dc))
            gradient = 2.0 * (AtA @ dc - Atb) + rho * p.gradient
            hessian = 2.0 * AtA + rho * p.hessian
            dc -= np.linalg.lstsq(hessian, gradient, rcond=1e-12)[0]
            if rho >= rho_final:
                return dc
            rho = min(rho * self.settings.penalty_growth, rho_final)

    def _retract(self, state: ControlState, step: np.ndarray) -> ControlState:
        if state.mode == "paper":
            return self._state_from_paper_vector(state, self._paper_vector(state) + step)
        n, head, jaw = self._layout()
        new = state.copy()
        new.activations = np.clip(state.activations + step[:n], 0.0, 1.0)
        if head:
            spin = rotation(step[n:n + 3], np.linalg.norm(step[n:n + 3])) if np.any(step[n:n + 3]) else np.eye(3)
            new.cranium = AffineMap(spin @ state.cranium.matrix,
                                    spin @ state.cranium.translation + step[n + 3:n + 6])
        if jaw:
            new.tmj = state.tmj + step[n + head:n + head + 3]
        return new

    def _interpolate(self, a: ControlState, b: ControlState, t: float) -> ControlState:
        new = a.copy()
        new.activations = (1 - t) * a.activations + t * b.activations
        new.jaw = a.jaw.interpolate(b.jaw, t)
        if a.mode == "exact":
            new.tmj = (1 - t) * a.tmj + t * b.tmj
            relative = b.cranium.matrix @ a.cranium.matrix.T
            axis, angle = _axis_angle(relative)
            spin = rotation(axis, t * angle) if angle else np.eye(3)
            new.cranium = AffineMap(spin @ a.cranium.matrix,
                                    (1 - t) * a.cranium.translation + t * b.cranium.translation)
        else:
            new.cranium = a.cranium.interpolate(b.cranium, t)
        return new

    # -- one frame ----------------------------------------------------------------------------
    def fit_frame(self, targets: np.ndarray, frame: int = 0, max_steps: int | None = None) -> FrameResult:
        """Fit one frame of targets (markers, 3) with NaN rows for missing markers."""
        start = time.perf_counter()
        settings = self.settings
        targets = np.asarray(targets, dtype=float)
        present = np.all(np.isfinite(targets), axis=1)
        if max_steps is None:
            max_steps = settings.first_frame_gn_steps if self.frames_done == 0 else settings.max_gn_steps
        phases = dict(sensitivities=0.0, gn_solve=0.0, equilibrium=0.0, line_search=0.0)
        flag = self._frame_flag(present)
        if flag:
            return self._result(frame, targets, present, 0, start, phases, flag)

        state = self.state
        # From rest (the first frame) the activations have far to go.
        self.trust_radius = settings.activation_trust_radius if self.frames_done else 1.0
        if state.mode == "paper":
            spread = np.nanstd(targets[present]) if present.any() else 1.0
            self._rho_start = 1e-6 * spread**2
            self._rho_final = self._rho_start
        objective, simulated = self._objective(state, targets, present)
        initial_rms = float(np.sqrt(np.mean(np.sum((simulated - targets)[present] ** 2, axis=1))))
        fresh = not (settings.reuse_jacobian and self._cached_jacobian is not None)
        fresh_jacobians = 0      # exact ones so far
        retry_exact = False      # a step from an inexact Jacobian failed
        converged_objective = settings.marker_tolerance**2 * max(1, int(present.sum()))
        steps = 0
        marker_columns = None
        while steps < max_steps and objective > converged_objective:
            steps += 1
            base_u, base_controls = self.problem.u.x.array.copy(), self.problem.controls.copy()
            if fresh or self._close_factor():
                within = 0.0 if retry_exact else settings.approximate_jacobian_within
                dofs, marker_columns, seconds, exact_jacobian = self._columns(state, within)
                self._cached_jacobian = (state.copy(), dofs, marker_columns)
                fresh_jacobians += int(exact_jacobian)
                jacobian_kind = "exact" if exact_jacobian else "approximate"
            else:
                dofs, marker_columns, seconds = self._reused_columns(state)
                exact_jacobian, jacobian_kind = False, "reused"
            phases["sensitivities"] += seconds
            t0 = time.perf_counter()
            simulated = self.markers.positions(base_u, state.cranium)
            residual = np.where(present[:, None], simulated - np.nan_to_num(targets), 0.0)
            jac = marker_columns * present[None, :, None]
            step = self._gn_step(state, jac, residual)
            phases["gn_solve"] += time.perf_counter() - t0
            if state.mode == "paper":
                objective, _ = self._objective(state, targets, present)  # rho changed
            candidate = self._retract(state, step)
            t0 = time.perf_counter()
            guess = base_u + step @ dofs[:len(step)]
            try:
                self._equilibrium(candidate, guess, trial=True)
                candidate_objective, _ = self._objective(candidate, targets, present)
            except EquilibriumError:
                candidate_objective = math.inf
            phases["equilibrium"] += time.perf_counter() - t0
            if state.mode == "exact":
                predicted = np.sum(residual**2) - np.sum((residual + np.tensordot(step, jac, axes=1))**2)
                self._adapt_trust_radius(step, objective - candidate_objective, predicted)
            full_step_good = candidate_objective < objective or (
                not settings.line_search and math.isfinite(candidate_objective))
            if self.problem.comm.rank == 0:
                log.debug("frame %d step %d: %s Jacobian, max |da| %.3f (trust %.3f), objective %.4g -> %.4g",
                          frame, steps, jacobian_kind, np.abs(step[:self.problem.num_muscles]).max(),
                          self.trust_radius, objective, candidate_objective)
            if full_step_good and not (settings.line_search and settings.line_search_every_step):
                accepted, new_objective = candidate, candidate_objective
            else:
                t0 = time.perf_counter()
                accepted, new_objective = self._line_search(state, candidate, base_u, targets, present,
                                                            objective, candidate_objective)
                phases["line_search"] += time.perf_counter() - t0
            if accepted is None:  # no decrease along the step: converged, stuck, or an inexact J
                self.problem.adopt(base_controls, base_u)
                if not exact_jacobian:
                    fresh = retry_exact = True
                    continue
                break
            retry_exact = False
            decrease = (objective - new_objective) / max(objective, 1e-300)
            state, objective = accepted, new_objective
            limit = settings.max_fresh_jacobians if self.frames_done else None  # not from rest
            fresh = limit is None or fresh_jacobians < limit
            if abs(decrease) < settings.relative_decrease or np.linalg.norm(step) < settings.min_step:
                break
        self.state = state
        self.previous_activations = state.activations.copy()
        self.frames_done += 1
        result = self._result(frame, targets, present, steps, start, phases, "")
        result.initial_rms = initial_rms
        if result.rms_error > settings.unreachable_rms:
            result.flag = (f"targets not reachable: marker RMS {result.rms_error:.2f} mm after "
                           f"{steps} Gauss-Newton steps (threshold {settings.unreachable_rms} mm)")
        if marker_columns is None and self._cached_jacobian is not None:  # on target before any step
            marker_columns = self._reused_columns(state)[1]
        if marker_columns is not None:
            self._flag_unobservable(result, marker_columns, present)
        return result

    def _flag_unobservable(self, result: FrameResult, marker_columns: np.ndarray, present: np.ndarray) -> None:
        """Name the controls the frame's visible markers cannot determine, in the result's flag
        and a warning; the fitted controls are kept. ``marker_columns`` holds every marker on
        every rank (``PointEvaluator`` sums them over the ranks), so all ranks agree."""
        threshold = self.settings.observability_threshold
        result.observability, weights = observability(marker_columns, present, threshold)
        if not weights.any():
            return
        result.unobservable = [name for name, weight in zip(self._control_names(), weights)
                               if weight >= WEAK_SHARE * weights.max()]
        message = (f"under-determined: the {int(present.sum())} visible markers cannot determine "
                   f"{', '.join(result.unobservable)} (observability {result.observability:.3g}, "
                   f"threshold {threshold:g}); the fitted values are kept")
        result.flag = f"{result.flag}; {message}" if result.flag else message
        if self.problem.comm.rank == 0:
            log.warning("frame %d: %s", result.frame, message)

    def _control_names(self) -> list[str]:
        """Names of the Jacobian's columns, in order."""
        n, head, jaw = self._layout()
        names = [muscle.name for muscle in self.problem.model.muscles]
        if head:
            names += ([f"head_rotation_{axis}" for axis in "xyz"] + [f"head_translation_{axis}" for axis in "xyz"]
                      if head == 6 else [f"head_M{i}{j}" for i in range(3) for j in range(3)]
                      + [f"head_t{axis}" for axis in "xyz"])
        if jaw:
            names += (["jaw_opening", "jaw_slide_right", "jaw_slide_left"] if jaw == 3 else
                      [f"jaw_M{i}{j}" for i in range(3) for j in range(3)] + [f"jaw_t{axis}" for axis in "xyz"])
        return names

    def _adapt_trust_radius(self, step, actual_decrease, predicted_decrease) -> None:
        n = self.problem.num_muscles
        agreement = actual_decrease / predicted_decrease if predicted_decrease > 0 else -math.inf
        if agreement > 0.75 and np.abs(step[:n]).max(initial=0.0) >= 0.99 * self.trust_radius:
            self.trust_radius = min(2.0 * self.trust_radius, 1.0)
        elif agreement < 0.25:
            self.trust_radius = max(0.5 * self.trust_radius, MIN_TRUST_RADIUS)

    def _line_search(self, state, candidate, base_u, targets, present, objective,
                     candidate_objective=math.inf):
        """Golden-section search for t in (0, 1) along the step, the full step (at the problem's
        current equilibrium, objective ``candidate_objective``) competing; None if nothing improves."""
        if not self.settings.line_search:  # pure Gauss-Newton: a full step without equilibrium ends the frame
            return None, objective
        candidate_u = self.problem.u.x.array.copy()
        best = (objective, None, None)
        if candidate_objective < objective:
            best = (candidate_objective, candidate, (self.problem.controls.copy(), candidate_u))

        def evaluate(t):
            nonlocal best
            trial = self._interpolate(state, candidate, t)
            guess = (1 - t) * base_u + t * candidate_u
            try:
                self._equilibrium(trial, guess, trial=True)
            except EquilibriumError:
                return math.inf
            value, _ = self._objective(trial, targets, present)
            if value < best[0]:
                best = (value, trial, (self.problem.controls.copy(), self.problem.u.x.array.copy()))
            return value

        low, high = 0.0, 1.0
        x1, x2 = high - GOLDEN * (high - low), low + GOLDEN * (high - low)
        f1, f2 = evaluate(x1), evaluate(x2)
        for _ in range(max(0, self.settings.line_search_depth - 2)):
            if f1 < f2:
                high, x2, f2 = x2, x1, f1
                x1 = high - GOLDEN * (high - low)
                f1 = evaluate(x1)
            else:
                low, x1, f1 = x1, x2, f2
                x2 = low + GOLDEN * (high - low)
                f2 = evaluate(x2)
        value, trial, equilibrium = best
        if trial is None:
            return None, objective
        self.problem.adopt(*equilibrium)
        return trial, value

    def _frame_flag(self, present: np.ndarray) -> str:
        usable = int(present.sum())
        if usable == 0:
            return "every marker is missing in this frame"
        if self.settings.fit_head and usable < 3:
            return f"only {usable} marker(s) present: fewer than the 3 a rigid head motion needs"
        return ""

    def _result(self, frame, targets, present, steps, start, phases, flag) -> FrameResult:
        state = self.state
        simulated = self.markers.positions(self.problem.u.x.array, state.cranium)
        errors = np.where(present, np.linalg.norm(simulated - np.nan_to_num(targets), axis=1), np.nan)
        rms = float(np.sqrt(np.nanmean(errors**2))) if present.any() else math.nan
        worst = float(np.nanmax(errors)) if present.any() else math.nan
        return FrameResult(frame, state.activations.copy(), state.cranium, self._jaw_of(state),
                           None if state.tmj is None else state.tmj.copy(), errors, rms, worst, steps,
                           time.perf_counter() - start, phases, flag)

    # -- checkpoint: what the next frame starts from ------------------------------------------
    def checkpoint(self) -> "FitCheckpoint":
        """Everything the next ``fit_frame`` depends on, copied: a fitter restored from it fits
        the following frames bit for bit as this one would (same mesh distribution)."""
        cached = self._cached_jacobian
        return FitCheckpoint(
            state=self.state.copy(),
            previous_activations=None if self.previous_activations is None else self.previous_activations.copy(),
            frames_done=self.frames_done,
            displacement=self.problem.u.x.array.copy(),
            problem_controls=self.problem.controls.copy(),
            jacobian_state=None if cached is None else cached[0].copy(),
            jacobian_dofs=None if cached is None else cached[1].copy(),
            jacobian_markers=None if cached is None else cached[2].copy())

    def restore(self, checkpoint: "FitCheckpoint") -> None:
        """Continue from ``checkpoint``: controls, equilibrium and the Jacobian to reuse. The
        equilibrium is put back as it was, not re-solved: one more Newton step would change it
        at round-off level and the frames after it with it."""
        if checkpoint.state.mode != self.settings.mode:
            raise ValueError(f"checkpoint of a {checkpoint.state.mode!r} fit, this fitter is {self.settings.mode!r}")
        self.state = checkpoint.state.copy()
        self.previous_activations = (None if checkpoint.previous_activations is None
                                     else checkpoint.previous_activations.copy())
        self.frames_done = checkpoint.frames_done
        self.problem.adopt(checkpoint.problem_controls, checkpoint.displacement)
        self._cached_jacobian = None if checkpoint.jacobian_state is None else (
            checkpoint.jacobian_state.copy(), checkpoint.jacobian_dofs.copy(),
            checkpoint.jacobian_markers.copy())


def observability(marker_columns: np.ndarray, present: np.ndarray, threshold: float) -> tuple[float, np.ndarray]:
    """How well the visible markers determine the controls, from the marker Jacobian.

    ``marker_columns`` (controls, markers, 3): d(marker)/dc at every marker; ``present``: the
    visible markers. Each column is scaled by its norm over all markers, so that every control
    counts with the marker motion it causes in a complete frame. Combinations that move no marker
    even in a complete frame (a muscle no marker sees, redundant affine numbers) are the model's
    limit, not the frame's, and are left out. Returns

    - the smallest singular value of the scaled visible Jacobian over that of the scaled complete
      one: the least any combination of controls moves the visible markers, relative to the least
      a complete frame would show (1 with every marker present, 0 when some combination moves no
      visible marker);
    - per control, its weight in the weak directions, the right singular vectors of the scaled
      visible Jacobian whose singular value is below ``threshold`` times the complete frame's
      smallest: ||P_weak e_i||^2, 0 with no weak direction, 1 for a control lying in them.
    Both catch a control whose markers are missing and controls whose visible effects coincide.
    """
    count = len(marker_columns)
    response = np.linalg.norm(marker_columns.reshape(count, -1), axis=1)
    scale = np.where(response > 1e-12 * response.max(), response, np.inf)[:, None, None]
    scaled = marker_columns / scale
    _, values, directions = np.linalg.svd(scaled.reshape(count, -1).T, full_matrices=False)
    directions = directions[values > 1e-8 * values[0]]  # the combinations a complete frame sees
    floor = values[len(directions) - 1]
    visible = scaled[:, present].reshape(count, -1).T @ directions.T
    _, visible_values, visible_directions = np.linalg.svd(visible, full_matrices=True)
    visible_values = np.concatenate([visible_values,  # fewer visible rows than combinations
                                     np.zeros(len(directions) - len(visible_values))])
    weak = directions.T @ visible_directions[visible_values < threshold * floor].T
    return float(visible_values[-1] / floor), np.sum(weak**2, axis=1)


def _exact_head_combination(cranium: AffineMap) -> np.ndarray:
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


@dataclass
class FitCheckpoint:
    """The warm-start state of a sequence fit after a frame (``FaceFitter.checkpoint``).

    Arrays over dofs are local (owned + ghost dofs of this rank's part of the mesh).
    """
    state: ControlState                      # the fitted controls
    previous_activations: np.ndarray | None  # the temporal smoothness term's reference
    frames_done: int                         # 0: the next frame gets the first-frame step budget
    displacement: np.ndarray                 # the equilibrium the next frame starts from
    problem_controls: object                 # FaceProblem.controls at that equilibrium
    jacobian_state: ControlState | None      # the Jacobian the next first step reuses: the
    jacobian_dofs: np.ndarray | None         # controls it was computed at, dX/dc (k, dofs)
    jacobian_markers: np.ndarray | None      # and the marker Jacobian (k, markers, 3)
