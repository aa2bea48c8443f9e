"""Linear baselines of the model ladder (issue 5): Choe & Ko's actuation basis and the FE model
linearised at rest.

Both are linear marker models. In the cranium frame the markers sit at

    y(x) = E0 + sum_k x_k B_k,    0 <= x_k <= 1                         (Choe & Ko 2001, eq. 1)

with E0 the markers at rest and one column B_k per muscle and per jaw (TMJ) degree of freedom; a
rigid head motion (R, t) carries them into the capture, p = R y(x) + t. ``LinearFitter`` finds x,
R and t per frame and returns the ``FrameResult`` records of ``FaceFitter``, so the same reports
work. The two models differ in their columns only:

``ActuationBasis`` (choe_ko2001, sections 3-4): B_i is the FE model's marker displacement with
    muscle i fully on and every other control at rest: the artist who sculpts the basis in the
    paper is replaced by the FE model, as the issue asks. Choe & Ko treat the jaw as one more
    basis element ("jaw rotate", fig. 5), the shape at a full rotation. The FE fitter has three
    TMJ degrees of freedom, so the basis has three jaw elements, each the FE shape at that
    degree's limit: the opening at asin(s), each condyle slid by the track length d. A jaw
    coefficient x then stands for the TMJ value x * limit, and its bounds [0, 1] are the FE
    fitter's TMJ bounds. The basis interpolates the chord of the opening rotation, not the arc:
    at half the widest opening the chin is off by about r (1 - cos(asin(s) / 2)), 2.4 mm at
    r = 100 mm; this is one place where the baseline must break.
``LinearizedModel``: the tangent of the FE model at rest, B = W dX/dc for the activations and
    the TMJ degrees of freedom (``EquilibriumSensitivity``, sifakis2005 eqs. 5-6), the TMJ
    columns scaled by their limits so that the coefficients share the [0, 1] bounds.

Head motion. Choe & Ko align the capture to the model once (first frame) and take the head's
gross motion from their capture system; synthetic takes have no head-mounted markers, so
``LinearFitter`` offers two stand-ins: ``head="joint"`` (default) minimises the same objective
over x, R and t together (Gauss-Newton on the rotation group, bounded least squares in x), and
``head="kabsch"`` removes the head motion first by the best rigid map of E0 onto the frame's
markers (Kabsch on every marker, blind to the expression), then solves for x alone, as a capture
system's gross head motion would be used.

Contractions (section 4.1.2, eqs. 2-3): bounded linear least squares (BVLS on column-scaled
columns); QP (3) is the same convex problem, so it has the same minimiser as the paper's active
set method. The paper's regions: with ``split_regions`` the contractions of Frontalis,
Corrugator and Orbicularis oculi see only the upper-face markers and every other element (the
jaw included) only the lower-face markers. A marker is in the upper region when the upper
muscles' basis displacements there are larger in sum than the lower elements'; the paper drew
the line by hand (fig. 2). The head, shared by both regions, is fitted to every marker.

Basis refinement (section 4.2): ``ActuationBasis.refined`` alternates the analysis of a training
take with a least-squares update of the basis, marker by marker, until the total analysis error
saturates. Deviations: (1) where the training contractions leave a combination of elements
unexcited, the least-squares problem for that marker is singular and the paper does not say
which solution to take; the update is the smallest correction of the current basis (singular
values below ``rcond`` times the largest are dropped), so an unexcited element keeps its shape;
(2) the final radial basis function step, which carries the refined marker displacements to the
whole face mesh for rendering, is not needed for the analysis and is left out.
"""
from dataclasses import dataclass, replace
import math
import time

import numpy as np
from scipy.optimize import lsq_linear

from face_dolfinx.alignment.similarity import similarity_transform
from face_dolfinx.model.bones import AffineMap, jaw_pose, rotation, tmj_upper_limits
from .formulations import TMJ_STEP
from .records import FrameResult
from face_dolfinx.sensitivities.columns import EquilibriumSensitivity, bone_position_derivatives

UPPER_FACE_MUSCLES = ("frontalis", "corrugator", "orbicularis_oculi")  # choe_ko2001 section 4.1.2


@dataclass
class LinearMarkerModel:
    """Markers y(x) = E0 + sum_k x_k B_k in the cranium frame, 0 <= x_k <= 1."""

    rest: np.ndarray           # (markers, 3) E0
    columns: np.ndarray        # (elements, markers, 3) B_k, zero outside the element's region
    control_scale: np.ndarray  # (elements,) control value at x_k = 1 (1 for a muscle; rad, mm)
    num_muscles: int
    region: np.ndarray         # (elements, markers) bool: markers that element k is fitted to
    build_seconds: float = 0.0

    @property
    def num_elements(self) -> int:
        return len(self.columns)

    def markers(self, coefficients: np.ndarray) -> np.ndarray:
        return self.rest + np.tensordot(coefficients, self.columns, axes=1)

    def controls(self, coefficients: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Activations and TMJ degrees of freedom (opening, right slide, left slide)."""
        values = coefficients * self.control_scale
        return values[:self.num_muscles], values[self.num_muscles:]


def upper_face_regions(model, columns: np.ndarray) -> np.ndarray:
    """choe_ko2001's split (section 4.1.2): (elements, markers) bool, True where the element is
    fitted. Upper muscles (``UPPER_FACE_MUSCLES``) get the markers where they move the face more
    than all other elements together; the other elements (jaw included) get the rest."""
    upper = np.zeros(len(columns), dtype=bool)
    upper[:len(model.muscles)] = [name.startswith(UPPER_FACE_MUSCLES) for name in model.muscle_names]
    reach = np.linalg.norm(columns, axis=2)  # (elements, markers)
    upper_markers = reach[upper].sum(axis=0) > reach[~upper].sum(axis=0)
    return np.where(upper[:, None], upper_markers[None, :], ~upper_markers[None, :])


class ActuationBasis(LinearMarkerModel):
    """Choe & Ko's actuation basis from the FE model (see the module docstring)."""

    @classmethod
    def from_face(cls, problem, markers, split_regions: bool = True) -> "ActuationBasis":
        """Basis elements: the FE equilibrium with one muscle fully on, then one TMJ degree of
        freedom at its limit, each from rest with the head fixed. Leaves ``problem`` at rest."""
        start = time.perf_counter()
        model = problem.model
        n = problem.num_muscles
        rest_controls = dict(activations=np.zeros(n), cranium=AffineMap(), jaw=AffineMap())
        problem.solve(**rest_controls)
        rest_u = problem.u.x.array.copy()
        rest = markers.positions(rest_u, AffineMap())
        limits = tmj_upper_limits(model.jaw)
        columns = []
        for element in range(n + 3):
            activations, tmj = np.zeros(n), np.zeros(3)
            if element < n:
                activations[element] = 1.0
            else:
                tmj[element - n] = limits[element - n]
            # Newton straight from rest; the solver falls back to continuation if it must.
            problem.solve(activations=activations, cranium=AffineMap(), jaw=jaw_pose(model.jaw, *tmj),
                          guess=rest_u)
            columns.append(markers.positions(problem.u.x.array, AffineMap()) - rest)
        problem.solve(**rest_controls)
        columns = np.array(columns)
        region = upper_face_regions(model, columns) if split_regions else np.ones(columns.shape[:2], bool)
        return cls(rest, columns * region[:, :, None], np.concatenate([np.ones(n), limits]), n, region,
                   time.perf_counter() - start)

    def refined(self, positions: np.ndarray, head: str = "joint", max_iterations: int = 20,
                saturation: float = 1e-3, rcond: float = 1e-3) -> tuple["ActuationBasis", list[float]]:
        """Section 4.2 on a training take ``positions`` (frames, markers, 3), NaN = missing.

        Each iteration analyses every frame with the current basis (contractions x^(t) and head
        motion), then, for every marker j, solves X D_j = D^_j in the least-squares sense for the
        marker's displacements D_j in the basis elements (X the frames' contractions, D^_j the
        marker's observed displacements in the cranium frame). Stops when the total analysis error
        drops by less than ``saturation`` (relative) or after ``max_iterations`` updates. Returns
        the basis with the lowest error and the total analysis error (mm^2) of each basis tried,
        the initial one first.
        """
        start = time.perf_counter()
        positions = np.asarray(positions, dtype=float)
        basis, history = self, []
        best = (math.inf, self)
        for iteration in range(max_iterations + 1):
            fitter = LinearFitter(basis, head=head)
            fits = [fitter.solve(frame) for frame in positions]
            error = float(sum(fit.objective for fit in fits))
            history.append(error)
            if error < best[0]:
                best = (error, basis)
            saturated = len(history) > 1 and history[-2] - error < saturation * history[-2]
            if saturated or iteration == max_iterations:
                break
            basis = basis._updated(fits, positions, rcond)
        refined = best[1]
        return replace(refined, build_seconds=self.build_seconds + time.perf_counter() - start), history

    def _updated(self, fits, positions, rcond) -> "ActuationBasis":
        contractions = np.array([fit.coefficients for fit in fits])  # (frames, elements)
        # Observed displacements in the cranium frame: R^T (p - t) - E0.
        observed = np.array([(p - fit.translation) @ fit.rotation for p, fit in zip(positions, fits)])
        observed -= self.rest
        columns = self.columns.copy()
        for j in range(len(self.rest)):
            frames = np.all(np.isfinite(observed[:, j]), axis=1)
            elements = self.region[:, j]
            X = contractions[np.ix_(frames, elements)]
            if not X.size:
                continue
            current = columns[elements, j]  # (active elements, 3)
            correction = np.linalg.lstsq(X, observed[frames, j] - X @ current, rcond=rcond)[0]
            columns[elements, j] = current + correction
        return replace(self, columns=columns)


class LinearizedModel(LinearMarkerModel):
    """The FE model linearised at rest: B = W dX/dc there (see the module docstring)."""

    @classmethod
    def from_face(cls, problem, markers) -> "LinearizedModel":
        """Tangent columns at rest (one factorisation). Leaves ``problem`` at rest."""
        start = time.perf_counter()
        model = problem.model
        n = problem.num_muscles
        problem.solve(activations=np.zeros(n), cranium=AffineMap(), jaw=AffineMap())
        rest = markers.positions(problem.u.x.array, AffineMap())
        sensitivity = EquilibriumSensitivity(problem)
        sensitivity.factor()
        muscle_columns = markers.evaluator.values_many(sensitivity.activation_columns())
        pose = lambda tmj: (AffineMap(), jaw_pose(model.jaw, *tmj))  # noqa: E731
        jaw_dofs = sensitivity.boundary_columns(bone_position_derivatives(problem, pose, np.zeros(3), TMJ_STEP))
        limits = tmj_upper_limits(model.jaw)
        jaw_columns = markers.evaluator.values_many(jaw_dofs) * limits[:, None, None]
        columns = np.concatenate([muscle_columns, jaw_columns])
        return cls(rest, columns, np.concatenate([np.ones(n), limits]), n,
                   np.ones(columns.shape[:2], dtype=bool), time.perf_counter() - start)


@dataclass
class LinearFit:
    """One frame fitted by a linear marker model."""

    coefficients: np.ndarray
    rotation: np.ndarray
    translation: np.ndarray
    predicted: np.ndarray   # (markers, 3) model markers in the capture frame
    objective: float        # sum of squared marker errors over the present markers (mm^2)
    iterations: int


class LinearFitter:
    """Fits frames with a ``LinearMarkerModel``, each warm-started from the last; the same
    ``fit_frame`` as ``FaceFitter``, so ``face_dolfinx.tracking.track`` drives it."""

    def __init__(self, model: LinearMarkerModel, jaw_geometry=None, head: str = "joint",
                 max_iterations: int = 30, step_tolerance: float = 1e-10, unreachable_rms: float = 3.0):
        if head not in ("joint", "kabsch"):
            raise ValueError(f"unknown head treatment {head!r}: use 'joint' or 'kabsch'")
        self.model = model
        self.jaw_geometry = jaw_geometry
        self.head = head
        self.max_iterations = max_iterations
        self.step_tolerance = step_tolerance
        self.unreachable_rms = unreachable_rms
        self.coefficients = np.zeros(model.num_elements)
        self.rotation, self.translation = None, None  # set by the first frame

    def solve(self, targets: np.ndarray) -> LinearFit:
        """Contractions and head motion of one frame (markers, 3), NaN rows missing; updates the
        warm start."""
        targets = np.asarray(targets, dtype=float)
        present = np.all(np.isfinite(targets), axis=1)
        if self.head == "kabsch" or self.rotation is None:
            head = similarity_transform(self.model.rest, targets, allow_scale=False)
            self.rotation, self.translation = head.rotation.copy(), head.translation.copy()
        if self.head == "kabsch":
            fit = self._contractions_only(targets, present)
        else:
            fit = self._joint(targets, present)
        self.coefficients, self.rotation, self.translation = fit.coefficients, fit.rotation, fit.translation
        return fit

    def _fit(self, coefficients, rotation, translation, targets, present, iterations) -> LinearFit:
        predicted = self.model.markers(coefficients) @ rotation.T + translation
        objective = float(np.sum((predicted - targets)[present] ** 2))
        return LinearFit(coefficients, rotation, translation, predicted, objective, iterations)

    def _contractions_only(self, targets, present) -> LinearFit:
        R, t = self.rotation, self.translation
        observed = (targets - t) @ R - self.model.rest  # displacements in the cranium frame
        A = self.model.columns[:, present].reshape(self.model.num_elements, -1).T
        x = _bounded_least_squares(A, observed[present].reshape(-1), np.zeros(A.shape[1]),
                                   np.ones(A.shape[1]))
        return self._fit(x, R, t, targets, present, 1)

    def _joint(self, targets, present) -> LinearFit:
        """Gauss-Newton on (x, R, t): x exact (the model is linear in x), the rotation linearised
        about the markers' centroid and retracted on the rotation group."""
        model = self.model
        k = model.num_elements
        fit = self._fit(self.coefficients, self.rotation, self.translation, targets, present, 0)
        for iteration in range(1, self.max_iterations + 1):
            predicted = fit.predicted[present]
            centre = predicted.mean(axis=0)
            coefficient_columns = model.columns[:, present] @ fit.rotation.T
            rotation_columns = np.cross(np.eye(3)[:, None, :], (predicted - centre)[None, :, :])
            translation_columns = np.broadcast_to(np.eye(3)[:, None, :], (3,) + predicted.shape)
            A = np.concatenate([coefficient_columns, rotation_columns, translation_columns]).reshape(k + 6, -1).T
            lower = np.concatenate([-fit.coefficients, np.full(6, -np.inf)])
            upper = np.concatenate([1.0 - fit.coefficients, np.full(6, np.inf)])
            step = _bounded_least_squares(A, (targets[present] - predicted).reshape(-1), lower, upper)
            # The rotation makes the step approximate: halve it until the objective drops.
            for halving in range(6):
                trial = self._stepped(fit, step * 0.5**halving, centre, targets, present, iteration)
                if trial.objective <= fit.objective:
                    break
            else:
                return fit
            fit = trial
            if np.linalg.norm(step) < self.step_tolerance:
                break
        return fit

    def _stepped(self, fit, step, centre, targets, present, iteration) -> LinearFit:
        k = self.model.num_elements
        x = np.clip(fit.coefficients + step[:k], 0.0, 1.0)
        spin = step[k:k + 3]
        turn = rotation(spin, np.linalg.norm(spin)) if np.any(spin) else np.eye(3)
        # p -> turn (p - c) + c + dt, applied to p = R y + t.
        R = turn @ fit.rotation
        t = turn @ (fit.translation - centre) + centre + step[k + 3:]
        return self._fit(x, R, t, targets, present, iteration)

    def fit_frame(self, targets: np.ndarray, frame: int = 0) -> FrameResult:
        start = time.perf_counter()
        targets = np.asarray(targets, dtype=float)
        present = np.all(np.isfinite(targets), axis=1)
        if present.sum() < 3:
            return self._result(frame, targets, present, self._warm_start_fit(targets, present),
                                start, 0.0, f"only {present.sum()} marker(s) present: fewer than the "
                                "3 a rigid head motion needs")
        initial_rms = (math.sqrt(self._warm_start_fit(targets, present).objective / present.sum())
                       if self.rotation is not None else math.nan)
        fit = self.solve(targets)
        result = self._result(frame, targets, present, fit, start, initial_rms, "")
        if result.rms_error > self.unreachable_rms:
            result.flag = (f"targets not reachable: marker RMS {result.rms_error:.2f} mm "
                           f"(threshold {self.unreachable_rms} mm)")
        return result

    def _warm_start_fit(self, targets, present) -> LinearFit:
        R = np.eye(3) if self.rotation is None else self.rotation
        t = np.zeros(3) if self.translation is None else self.translation
        return self._fit(self.coefficients, R, t, targets, present, 0)

    def _result(self, frame, targets, present, fit, start, initial_rms, flag) -> FrameResult:
        activations, tmj = self.model.controls(fit.coefficients)
        errors = np.where(present, np.linalg.norm(fit.predicted - np.nan_to_num(targets), axis=1), np.nan)
        rms = float(np.sqrt(np.nanmean(errors**2))) if present.any() else math.nan
        worst = float(np.nanmax(errors)) if present.any() else math.nan
        jaw = jaw_pose(self.jaw_geometry, *tmj) if self.jaw_geometry is not None else AffineMap()
        seconds = time.perf_counter() - start
        return FrameResult(frame, activations.copy(), AffineMap(fit.rotation, fit.translation), jaw,
                           tmj.copy(), errors, rms, worst, fit.iterations, seconds,
                           dict(gn_solve=seconds), flag, initial_rms)


def _bounded_least_squares(A: np.ndarray, b: np.ndarray, lower: np.ndarray, upper: np.ndarray) -> np.ndarray:
    """min |A x - b| subject to lower <= x <= upper, with the columns scaled to unit norm (mm,
    rad and contraction columns differ by orders of magnitude)."""
    scale = np.maximum(np.linalg.norm(A, axis=0), 1e-12)
    upper = np.maximum(upper, lower)  # round-off may put a coefficient a hair outside its bounds
    result = lsq_linear(A / scale, b, bounds=(lower * scale, upper * scale), method="bvls", tol=1e-12)
    return result.x / scale
