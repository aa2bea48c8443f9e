"""Control penalties: gradients by central differences, convex Hessians, and the TMJ geometry.

A jaw pose built from the three TMJ degrees of freedom (bones.jaw_pose) must satisfy psi_1..3
exactly and put psi_4, psi_5, psi_6 at the slides and -sin(opening): then the penalty vanishes
inside the limits and grows outside them.
"""
from types import SimpleNamespace

import numpy as np
import pytest

from face_dolfinx.model.bones import jaw_pose
from face_dolfinx.fitting import penalties

JAW = SimpleNamespace(u=np.array([1.0, 0.0, 0.0]), v=np.array([0.0, -0.2, 1.0]) / np.hypot(0.2, 1.0),
                      condyle_distance=100.0, track_length=10.0, max_opening_sine=0.4)
JAW.w = np.cross(JAW.v, JAW.u)
JAW.midpoint = np.array([0.0, -10.0, -40.0])


def numeric_gradient(f, x, h=1e-6):
    g = np.zeros_like(x)
    for i in range(len(x)):
        e = np.zeros_like(x)
        e[i] = h
        g[i] = (f(x + e) - f(x - e)) / (2 * h)
    return g


def test_activation_bounds():
    a = np.array([-0.2, 0.0, 0.5, 1.0, 1.3])
    p = penalties.activation_bounds(a)
    assert p.value == pytest.approx(0.2**2 + 0.3**2)
    # At the kinks a = 0, 1 central differences are off by h/2: compare to that accuracy.
    assert np.allclose(p.gradient, numeric_gradient(lambda x: penalties.activation_bounds(x).value, a),
                       atol=1e-6)
    assert np.allclose(np.diag(p.hessian), [2, 0, 0, 0, 2])


def test_rigidity_gradient_and_psd_hessian():
    rng = np.random.default_rng(0)
    M = np.eye(3) + 0.3 * rng.normal(size=(3, 3))
    p = penalties.rigidity(M)
    assert np.allclose(p.gradient, numeric_gradient(lambda x: penalties.rigidity(x).value, M.reshape(-1)),
                       atol=1e-6)
    assert np.linalg.eigvalsh(p.hessian).min() >= -1e-12
    # Rotations cost nothing: the penalty only sees the symmetric stretch (polar decomposition).
    c, s = np.cos(0.8), np.sin(0.8)
    assert penalties.rigidity(np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])).value < 1e-28
    # Near a rotation the exact Hessian is already PSD: the projection must not change it there.
    exact = penalties.rigidity(np.eye(3))
    assert np.allclose(exact.hessian, exact.hessian.T)


@pytest.mark.parametrize("opening, right, left", [(0.0, 0.0, 0.0), (0.3, 2.0, 7.0), (0.41, 0.0, 10.0)])
def test_tmj_pose_satisfies_constraints(opening, right, left):
    pose = jaw_pose(JAW, opening, right, left)
    M, t = pose.matrix, pose.translation
    m, u, v, w, half = JAW.midpoint, JAW.u, JAW.v, JAW.w, 50.0
    psi = [w @ M @ u, w @ (M @ m + t - m), u @ (M @ m + t - m),
           v @ (M @ (m - half * u) + t - m), v @ (M @ (m + half * u) + t - m), w @ M @ v]
    assert np.allclose(psi, [0, 0, 0, right, left, -np.sin(opening)], atol=1e-12)
    assert np.allclose(M.T @ M, np.eye(3), atol=1e-12)
    inside = penalties.tmj(M, t, JAW)
    assert inside.value < 1e-24 or opening > np.arcsin(JAW.max_opening_sine)


def test_tmj_outside_limits_and_gradient():
    pose = jaw_pose(JAW, 0.6, -1.0, 12.0)  # too wide open, right condyle behind, left beyond
    params = np.concatenate([pose.matrix.reshape(-1), pose.translation])
    value = penalties.tmj(pose.matrix, pose.translation, JAW)
    expected = (np.sin(0.6) - 0.4) ** 2 + 1.0**2 + 2.0**2
    assert value.value == pytest.approx(expected, rel=1e-10)
    f = lambda x: penalties.tmj(x[:9], x[9:], JAW).value  # noqa: E731
    assert np.allclose(value.gradient, numeric_gradient(f, params), atol=1e-6)
    eigenvalues = np.linalg.eigvalsh(value.hessian)
    assert eigenvalues.min() >= -1e-14 * np.abs(eigenvalues).max()  # PSD up to round-off of its norm


def test_combined_layout():
    n = 4
    # Away from the kinks of every term (a jaw pose strictly inside its limits, but not rigid).
    jaw = jaw_pose(JAW, 0.1, 2.0, 3.0)
    c = np.concatenate([[0.5, -0.1, 1.2, 0.3], np.eye(3).reshape(-1) * 1.1, [0, 0, 0],
                        (1.05 * jaw.matrix).reshape(-1), jaw.translation + [0.0, 0.5, 0.0]])
    p = penalties.kinematic_and_bounds(c, n, JAW)
    f = lambda x: penalties.kinematic_and_bounds(x, n, JAW).value  # noqa: E731
    assert np.allclose(p.gradient, numeric_gradient(f, c), atol=1e-5)
    assert np.linalg.eigvalsh(p.hessian).min() >= -1e-10
