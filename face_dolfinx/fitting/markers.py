"""Markers as material points of the face, evaluated on the displacement field."""
import numpy as np

from face_dolfinx.model.bones import AffineMap
from face_dolfinx.physics.points import PointEvaluator


class MarkerSet:
    """Markers at fixed material points of the face (plus an offset that turns with the head).

    ``weights`` (default 1) weigh each marker's squared distance in the fit's objective; a marker
    of weight 0 is followed and reported but not fitted (a validation marker, or one whose motion
    the model cannot make).
    """

    def __init__(self, problem, surface_points: np.ndarray, offsets: np.ndarray | None = None,
                 names: list[str] | None = None, weights: np.ndarray | None = None):
        self.reference = np.asarray(surface_points, dtype=float).reshape(-1, 3)
        self.offsets = np.zeros_like(self.reference) if offsets is None else np.asarray(offsets, float)
        self.names = names or [f"marker_{i}" for i in range(len(self.reference))]
        self.weights = np.ones(len(self.reference)) if weights is None else np.asarray(weights, dtype=float)
        if self.weights.shape != (len(self.reference),) or not np.all(self.weights >= 0):
            raise ValueError(f"marker weights must be {len(self.reference)} numbers, 0 or more")
        self.evaluator = PointEvaluator(problem.V, self.reference)

    def positions(self, displacement: np.ndarray, cranium: AffineMap) -> np.ndarray:
        return self.reference + self.evaluator.values(displacement) + self.offsets @ cranium.matrix.T
