"""PointEvaluator reproduces fields its space contains exactly, at any point, on any rank count."""
import numpy as np
import pytest
from dolfinx import fem

from face_dolfinx.physics.points import PointEvaluator
from slab import slab_model

POINTS = np.array([[0.0, 0.0, 0.0], [40.0, 20.0, 10.0], [13.3, 7.7, 10.0], [21.1, 0.0, 4.4],
                   [5.0, 5.0, 5.0], [39.99, 19.5, 0.01]])


def polynomial(x, degree):
    """A vector field of total degree ``degree`` (exact in P``degree``)."""
    if degree == 1:
        return np.stack([0.2 * x[0] + 0.1 * x[1], 0.3 * x[2] - 1.0, 0.01 * x[1]])
    return np.stack([0.01 * x[0] ** 2 + 0.1 * x[1], 0.3 * x[2] * x[1], 0.001 * x[0] * x[1]])


@pytest.mark.parametrize("degree", [1, 2])
def test_exact_for_polynomials_in_the_space(degree):
    domain = slab_model().mesh
    V = fem.VectorFunctionSpace(domain, ("CG", degree))
    u = fem.Function(V)
    u.interpolate(lambda x: polynomial(x, degree))
    values = PointEvaluator(V, POINTS).values(u.x.array)
    assert np.abs(values - polynomial(POINTS.T, degree).T).max() < 1e-12
    many = PointEvaluator(V, POINTS).values_many(np.stack([u.x.array, 2 * u.x.array]))
    assert np.allclose(many[1], 2 * values, atol=1e-12)


def test_point_outside_is_an_error():
    V = fem.VectorFunctionSpace(slab_model().mesh, ("CG", 1))
    with pytest.raises(ValueError, match="outside the mesh"):
        PointEvaluator(V, np.array([[100.0, 0.0, 0.0]]))
