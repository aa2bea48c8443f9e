"""Penalties on the controls (sifakis2005 sections 7-8): value, gradient and convex Hessian.

These act on the low-dimensional control vector, not on fields, so they are numpy, not UFL; they
are kept here beside the other terms of the objective and free of solver code. Paper-mode layout
of the control vector c: activations (n), cranium M_c (9, row-major), t_c (3), jaw M_m (9), t_m (3).
"""
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class PenaltyValue:
    value: float
    gradient: np.ndarray
    hessian: np.ndarray  # positive semi-definite


def _psd(matrix: np.ndarray) -> np.ndarray:
    """Projection of a symmetric matrix onto the positive semi-definite cone."""
    sym = 0.5 * (matrix + matrix.T)
    eigenvalues, eigenvectors = np.linalg.eigh(sym)
    return (eigenvectors * np.clip(eigenvalues, 0.0, None)) @ eigenvectors.T


def activation_bounds(a: np.ndarray) -> PenaltyValue:
    """sum_i min{0, a_i, 1 - a_i}^2: zero inside [0, 1], C1 and convex."""
    below = np.minimum(a, 0.0)
    above = np.minimum(1.0 - a, 0.0)
    value = float(np.sum(below**2 + above**2))
    gradient = 2.0 * below - 2.0 * above
    hessian = np.diag(2.0 * ((a < 0.0) | (a > 1.0)))
    return PenaltyValue(value, gradient, hessian)


def symmetric_bound(x: float, limit: float) -> PenaltyValue:
    """((|x| - limit) / limit)^2 outside [-limit, limit], 0 inside: ``activation_bounds`` of
    (x + limit) / (2 limit), scaled back to x (value 4x that of the scaled variable)."""
    scaled = activation_bounds(np.array([(x + limit) / (2.0 * limit)]))
    return PenaltyValue(4.0 * scaled.value, 2.0 * scaled.gradient / limit, scaled.hessian / limit**2)


def rigidity(M: np.ndarray) -> PenaltyValue:
    """||M^T M - I||_F^2 on the 9 entries of M (row-major); Hessian projected PSD."""
    M = np.asarray(M, dtype=float).reshape(3, 3)
    E = M.T @ M - np.eye(3)
    value = float(np.sum(E**2))
    gradient = (4.0 * M @ E).reshape(-1)
    hessian = np.zeros((9, 9))
    for k in range(9):
        dM = np.zeros(9)
        dM[k] = 1.0
        dM = dM.reshape(3, 3)
        dE = dM.T @ M + M.T @ dM
        hessian[:, k] = (4.0 * (dM @ E + M @ dE)).reshape(-1)
    return PenaltyValue(value, gradient, _psd(hessian))


def _outside(x: float, low: float, high: float) -> float:
    """min{0, x - low, high - x} up to sign: the signed distance outside [low, high]."""
    return min(0.0, x - low) - min(0.0, high - x)


def tmj(M_m: np.ndarray, t_m: np.ndarray, jaw) -> PenaltyValue:
    """The jaw-joint terms of phi_kin on the 12 jaw numbers (M_m row-major, t_m).

    psi_1..psi_3 must vanish; psi_4, psi_5 in [0, d] (condyle slides); psi_6 in [-s, 0] (opening).
    Every psi is linear in (M_m, t_m), so each squared term is convex with Hessian 2 g g^T.
    """
    u, v, w, m = jaw.u, jaw.v, jaw.w, jaw.midpoint
    half_axis = 0.5 * jaw.condyle_distance * u
    d, s = jaw.track_length, jaw.max_opening_sine

    def linear(a, b, c):
        """psi = a^T M_m b + c^T t_m + const, as (gradient over the 12 numbers)."""
        return np.concatenate([np.outer(a, b).reshape(-1), c])

    params = np.concatenate([np.asarray(M_m, float).reshape(-1), np.asarray(t_m, float)])
    # (gradient, constant, allowed interval) per psi; psi = gradient . params + constant.
    terms = [
        (linear(w, u, np.zeros(3)), 0.0, (0.0, 0.0)),
        (linear(w, m, w), -w @ m, (0.0, 0.0)),
        (linear(u, m, u), -u @ m, (0.0, 0.0)),
        (linear(v, m - half_axis, v), -v @ m, (0.0, d)),
        (linear(v, m + half_axis, v), -v @ m, (0.0, d)),
        (linear(w, v, np.zeros(3)), 0.0, (-s, 0.0)),
    ]
    value, gradient, hessian = 0.0, np.zeros(12), np.zeros((12, 12))
    for g, constant, (low, high) in terms:
        distance = _outside(g @ params + constant, low, high)
        if distance != 0.0:
            value += distance**2
            gradient += 2.0 * distance * g
            hessian += 2.0 * np.outer(g, g)
    return PenaltyValue(value, gradient, hessian)


def kinematic_and_bounds(c: np.ndarray, num_muscles: int, jaw) -> PenaltyValue:
    """phi_p of the paper mode: activation bounds + rigidity of both frames + TMJ."""
    n = num_muscles
    parts = [(slice(0, n), activation_bounds(c[:n])),
             (slice(n, n + 9), rigidity(c[n:n + 9])),
             (slice(n + 12, n + 21), rigidity(c[n + 12:n + 21])),
             (slice(n + 12, n + 24), tmj(c[n + 12:n + 21], c[n + 21:n + 24], jaw))]
    value, gradient, hessian = 0.0, np.zeros(len(c)), np.zeros((len(c), len(c)))
    for where, part in parts:
        value += part.value
        gradient[where] += part.gradient
        hessian[where, where] += part.hessian
    return PenaltyValue(value, gradient, hessian)
