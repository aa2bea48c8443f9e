"""Gauss-Newton fitting of activations and bone motion to markers (sifakis2005 sections 5-9).

Per frame, from the previous frame's equilibrium and controls:
  1. factorise the tangent once, solve for dX/dc (activations, jaw; the jaw's with the teeth's
     mixed term when the teeth's contact is on) and add the analytic cranium columns: the marker
     Jacobian J = W dX/dc;
  2. the Gauss-Newton step minimises |r + J dc|^2 (r = simulated - captured markers present in
     this frame) under the mode's constraints;
  3. solve the equilibrium at the new controls from the linear prediction X + dX/dc dc; accept the
     step when the objective drops, otherwise golden-section search along it (each trial starting
     from the linear interpolation of the two shapes, as the paper does);
  4. repeat until the relative decrease or the step is small.

Two formulations share this driver (``formulations``, chosen by ``FitSettings.mode``):
  ``exact``: activations with hard bounds [0, 1] (bounded linear least squares), the head a rigid
    motion updated on the rotation group, the jaw its 3 TMJ degrees of freedom with hard bounds;
  ``paper``: 32 activations + 12 affine cranium + 12 affine jaw numbers, with the nested penalty
    schedule of section 7 (rho grows by 5 % per step) for the bounds, rigidity and TMJ terms.
Either may add the intraoral pressure (``FitSettings.fit_pressure``): one more column, dX/dp.
"""
import logging
import math
import time

from mpi4py import MPI
import numpy as np

from face_dolfinx.equilibrium.solver import EquilibriumError
from face_dolfinx.sensitivities.columns import EquilibriumSensitivity, frame_columns
from .formulations import ControlState, Formulation, make_formulation
from .markers import MarkerSet
from .observability import WEAK_SHARE, observability
from .records import FitCheckpoint, FrameResult
from .settings import FitSettings

log = logging.getLogger(__name__)

GOLDEN = (math.sqrt(5.0) - 1.0) / 2.0


class FaceFitter:
    """Fits frames of marker targets with a ``FaceProblem``; keeps the last equilibrium."""

    def __init__(self, problem, markers: MarkerSet, settings: FitSettings | None = None):
        self.problem = problem
        self.markers = markers
        self.settings = settings or FitSettings()
        self.formulation: Formulation = make_formulation(problem, self.settings)
        self.sensitivity = EquilibriumSensitivity(problem)
        self.state = self.formulation.initial_state()
        self.previous_activations = None
        self.frames_done = 0
        self._cached_jacobian = None  # (state, dof columns, marker columns) of the last GN step
        self._jacobian_displacement = None  # the displacement it was computed for (for the log)
        self._root_weights = np.sqrt(markers.weights)

    # -- controls <-> problem -----------------------------------------------------------------
    def _equilibrium(self, state: ControlState, guess: np.ndarray | None, trial: bool = False) -> None:
        """Equilibrium at ``state``. A trial point (a Gauss-Newton candidate or a line-search
        point) that needs deep continuation is a bad step: it is rejected early, not forced."""
        self.problem.solve(activations=np.clip(state.activations, 0.0, 1.0),
                           cranium=state.cranium, jaw=self.formulation.jaw(state), guess=guess,
                           max_halvings=self.settings.trial_halvings if trial else 10,
                           pressure=state.pressure)

    def _objective(self, state: ControlState, targets, present) -> tuple[float, np.ndarray]:
        """sum w_i |x_i - target_i|^2 over the fitted markers, plus the regularisation terms."""
        simulated = self.markers.positions(self.problem.u.x.array, state.cranium)
        residual = (simulated - targets)[present] * self._root_weights[present, None]
        value = float(np.sum(residual**2))
        if self.settings.temporal_smoothness and self.previous_activations is not None:
            value += self.settings.temporal_smoothness * float(
                np.sum((state.activations - self.previous_activations) ** 2))
        if self.settings.effort:
            value += self.settings.effort * float(np.sum(state.activations**2))
        value += self.formulation.penalty(state)
        return value, simulated

    # -- Jacobian -----------------------------------------------------------------------------
    def _columns(self, state: ControlState, approximate_within: float) -> tuple[np.ndarray, np.ndarray, float, bool]:
        """dX/dc as dof arrays (k, ndofs), the marker Jacobian (k, markers, 3), the time and
        whether it is exact (from the exact tangent at this state, not from Newton's or from one
        at a state up to ``approximate_within`` mm away)."""
        start = time.perf_counter()
        distance = self.sensitivity.factor(reuse_within=approximate_within,
                                           newton_tangent=self.settings.fresh_jacobian_from_newton_tangent)
        exact_jacobian = distance == 0.0 and self.problem.solver.factor_is_exact
        columns = [self.sensitivity.activation_columns()]
        cranium_marker_columns = None
        if self.settings.fit_head:
            cranium_dofs = self.sensitivity.cranium_columns()
            cranium_dofs, cranium_marker_columns = self.formulation.head_columns(
                state, cranium_dofs, self._cranium_marker_columns(state))
            columns.append(cranium_dofs)
        if self.settings.fit_jaw:
            derivatives = self.formulation.jaw_position_derivatives(state)
            teeth = (self.formulation.jaw_teeth_derivatives(state)
                     if self.problem.teeth_contact is not None else None)
            columns.append(self.sensitivity.boundary_columns(derivatives, teeth))
        if self.settings.fit_pressure:
            columns.append(self.sensitivity.pressure_columns())
        dofs = np.concatenate(columns)
        marker = self.markers.evaluator.values_many(dofs)
        if cranium_marker_columns is not None:
            n = self.problem.num_muscles
            marker[n:n + len(cranium_marker_columns)] = cranium_marker_columns
        return dofs, marker, time.perf_counter() - start, exact_jacobian

    def _close_factor(self) -> bool:
        """The newest factor may serve a fresh Jacobian (``approximate_jacobian_within``)."""
        within = self.settings.approximate_jacobian_within
        return within > 0.0 and self.problem.solver.factor_distance(exact=False) <= within

    def _distance_from(self, displacement: np.ndarray | None) -> float:
        """Largest distance of a dof of the current displacement from ``displacement`` (NaN:
        not known, as after ``restore``), over all ranks. Collective."""
        if displacement is None:
            return math.nan
        local = float(np.abs(self.problem.u.x.array - displacement).max(initial=0.0))
        return self.problem.comm.allreduce(local, op=MPI.MAX)

    def _reused_columns(self, state: ControlState):
        """The cached Jacobian turned by the change of the head's rotation since it was computed
        (the paper's warm start), with fresh analytic cranium columns."""
        start = time.perf_counter()
        cached_state, dofs, marker = self._cached_jacobian
        turn = state.cranium.matrix @ np.linalg.inv(cached_state.cranium.matrix)
        dofs = (dofs.reshape(len(dofs), -1, 3) @ turn.T).reshape(len(dofs), -1)
        marker = marker @ turn.T
        if self.settings.fit_head:
            n, head = self.formulation.num_muscles, self.formulation.head_size
            cranium_dofs, cranium = self.formulation.head_columns(
                state, self.sensitivity.cranium_columns(), self._cranium_marker_columns(state))
            marker[n:n + head] = cranium
            dofs[n:n + head] = cranium_dofs
        return dofs, marker, time.perf_counter() - start

    def _cranium_marker_columns(self, state: ControlState) -> np.ndarray:
        """d(marker)/d(M_c, t_c) (12, markers, 3): the whole face, offsets included, moves
        with the cranium frame."""
        return frame_columns(self.markers.positions(self.problem.u.x.array, state.cranium), state.cranium)

    # -- steps --------------------------------------------------------------------------------
    def _gn_step(self, state: ControlState, jacobian: np.ndarray, residual: np.ndarray) -> np.ndarray:
        """The control step of the formulation on the linearised objective |r + J dc|^2 (with the
        rows of the temporal smoothness and effort terms)."""
        n = self.problem.num_muscles
        A = jacobian.reshape(len(jacobian), -1).T  # (3 markers, controls)
        b = -residual.reshape(-1)
        terms = [(self.settings.temporal_smoothness, self.previous_activations),
                 (self.settings.effort, np.zeros(n))]
        for weight, reference in terms:
            if weight and reference is not None:
                rows = np.zeros((n, A.shape[1]))
                rows[:, :n] = math.sqrt(weight) * np.eye(n)
                A = np.vstack([A, rows])
                b = np.concatenate([b, -math.sqrt(weight) * (state.activations - reference)])
        return self.formulation.step(state, A, b)

    # -- one frame ----------------------------------------------------------------------------
    def fit_frame(self, targets: np.ndarray, frame: int = 0, max_steps: int | None = None) -> FrameResult:
        """Fit one frame of targets (markers, 3) with NaN rows for missing markers."""
        start = time.perf_counter()
        settings = self.settings
        targets = np.asarray(targets, dtype=float)
        seen = np.all(np.isfinite(targets), axis=1)
        present = seen & (self.markers.weights > 0)  # the markers fitted in this frame
        if max_steps is None:
            max_steps = settings.first_frame_gn_steps if self.frames_done == 0 else settings.max_gn_steps
        phases = dict(sensitivities=0.0, gn_solve=0.0, equilibrium=0.0, line_search=0.0)
        flag = self._frame_flag(present)
        if flag:
            return self._result(frame, targets, seen, present, 0, start, phases, flag)

        state = self.state
        formulation = self.formulation
        formulation.start_frame(targets, present, warm=self.frames_done > 0)
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
                self._jacobian_displacement = base_u
                fresh_jacobians += int(exact_jacobian)
                jacobian_kind = "exact" if exact_jacobian else "approximate"
                jacobian_distance = self.problem.solver.factor_distance(exact=False)
            else:
                dofs, marker_columns, seconds = self._reused_columns(state)
                exact_jacobian, jacobian_kind = False, "reused"
                jacobian_distance = self._distance_from(self._jacobian_displacement)
            phases["sensitivities"] += seconds
            t0 = time.perf_counter()
            simulated = self.markers.positions(base_u, state.cranium)
            weight = np.where(present, self._root_weights, 0.0)
            residual = (simulated - np.nan_to_num(targets)) * weight[:, None]
            jac = marker_columns * weight[None, :, None]
            step = self._gn_step(state, jac, residual)
            phases["gn_solve"] += time.perf_counter() - t0
            if formulation.step_changes_objective:
                objective, _ = self._objective(state, targets, present)
            candidate = formulation.retract(state, step)
            t0 = time.perf_counter()
            guess = base_u + step @ dofs[:len(step)]
            try:
                self._equilibrium(candidate, guess, trial=True)
                candidate_objective, _ = self._objective(candidate, targets, present)
            except EquilibriumError:
                candidate_objective = math.inf
            phases["equilibrium"] += time.perf_counter() - t0
            formulation.judge_step(step, residual, jac, objective - candidate_objective)
            full_step_good = candidate_objective < objective or (
                not settings.line_search and math.isfinite(candidate_objective))
            if self.problem.comm.rank == 0:
                log.debug("frame %d step %d: %s Jacobian (from a state %.3g mm away), max |da| %.3f (%s), "
                          "objective %.4g -> %.4g", frame, steps, jacobian_kind, jacobian_distance,
                          np.abs(step[:self.problem.num_muscles]).max(),
                          formulation.summary(), objective, candidate_objective)
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
        result = self._result(frame, targets, seen, present, steps, start, phases, "")
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
        result.unobservable = [name for name, weight in zip(self.formulation.control_names(), weights)
                               if weight >= WEAK_SHARE * weights.max()]
        message = (f"under-determined: the {int(present.sum())} visible markers cannot determine "
                   f"{', '.join(result.unobservable)} (observability {result.observability:.3g}, "
                   f"threshold {threshold:g}); the fitted values are kept")
        result.flag = f"{result.flag}; {message}" if result.flag else message
        if self.problem.comm.rank == 0:
            log.warning("frame %d: %s", result.frame, message)

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
            trial = self.formulation.interpolate(state, candidate, t)
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

    def _result(self, frame, targets, seen, present, steps, start, phases, flag) -> FrameResult:
        """The frame's result: errors of every marker seen, RMS and largest over the fitted ones."""
        state = self.state
        simulated = self.markers.positions(self.problem.u.x.array, state.cranium)
        errors = np.where(seen, np.linalg.norm(simulated - np.nan_to_num(targets), axis=1), np.nan)
        rms = float(np.sqrt(np.mean(errors[present]**2))) if present.any() else math.nan
        worst = float(np.max(errors[present])) if present.any() else math.nan
        return FrameResult(frame, state.activations.copy(), state.cranium, self.formulation.jaw(state),
                           None if state.tmj is None else state.tmj.copy(), errors, rms, worst, steps,
                           time.perf_counter() - start, phases, flag, pressure=state.pressure)

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
        if checkpoint.state.mode != self.formulation.name:
            raise ValueError(f"checkpoint of a {checkpoint.state.mode!r} fit, this fitter is {self.formulation.name!r}")
        self.state = checkpoint.state.copy()
        self.previous_activations = (None if checkpoint.previous_activations is None
                                     else checkpoint.previous_activations.copy())
        self.frames_done = checkpoint.frames_done
        self.problem.adopt(checkpoint.problem_controls, checkpoint.displacement)
        self._cached_jacobian = None if checkpoint.jacobian_state is None else (
            checkpoint.jacobian_state.copy(), checkpoint.jacobian_dofs.copy(),
            checkpoint.jacobian_markers.copy())
        self._jacobian_displacement = None
