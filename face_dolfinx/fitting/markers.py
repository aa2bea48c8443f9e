"""Markers as material points of the face, evaluated on the displacement field."""
import numpy as np

from face_dolfinx.model.bones import AffineMap
from face_dolfinx.physics.points import PointEvaluator


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
