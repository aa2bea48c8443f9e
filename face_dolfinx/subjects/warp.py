"""Subject adaptation: warping the template face onto a subject with radial basis functions.

sifakis2005 section 3 morphs its template (bones, muscles, flesh) onto the subject through point
correspondences and radial basis functions. ``RBFWarp.fit(source, target)`` builds the smooth map
x -> x + d(x) of 3-space whose displacement d interpolates target - source at the control points:
an affine part plus a sum of kernels phi(|x - c_i|),

    "thin_plate": phi(r) = r^2 log r   (thin-plate spline)
    "biharmonic": phi(r) = r           (the biharmonic kernel of 3-D space: the smoothest interpolant)

Everything in the template then moves with the warp: node positions by ``apply``, muscle fiber
directions by the warp's Jacobian (``fiber_transform``), and ``inverted_tets`` says whether the
warped flesh mesh is still valid.
"""
from __future__ import annotations

import numpy as np
from scipy.interpolate import RBFInterpolator

# Our kernel names -> scipy's. scipy's "linear" is -r: the sign is absorbed by the weights.
KERNELS = {"thin_plate": "thin_plate_spline", "biharmonic": "linear"}
# Central-difference step for fiber_transform, as a fraction of the control points' extent.
RELATIVE_STEP = 1e-4


class RBFWarp:
    """A radial-basis-function warp of 3-space; make one with ``RBFWarp.fit``."""

    def __init__(self, source_points, target_points, kernel, smoothing, affine, displacement):
        self.source_points = source_points
        self.target_points = target_points
        self.kernel = kernel
        self.smoothing = smoothing
        self.affine = affine
        self._displacement = displacement

    @classmethod
    def fit(cls, source_points, target_points, kernel="thin_plate", smoothing=0.0, affine=True) -> RBFWarp:
        """The warp taking ``source_points`` (n, 3) to ``target_points`` (n, 3).

        With ``smoothing`` 0 it interpolates: the control points land exactly on their targets.
        A positive ``smoothing`` trades that for a smoother warp (a least-squares fit, for noisy
        correspondences). With ``affine`` the polynomial part is affine, so an affine map is
        reproduced exactly; without it only a constant shift, which only the "biharmonic" kernel
        allows (the thin-plate spline needs the affine part to be well posed).
        """
        if kernel not in KERNELS:
            raise ValueError(f"unknown kernel {kernel!r}; use one of {', '.join(KERNELS)}")
        if not affine and kernel == "thin_plate":
            raise ValueError('the "thin_plate" kernel needs the affine part (affine=True)')
        source = _as_points(source_points, "source_points")
        target = _as_points(target_points, "target_points")
        if source.shape != target.shape:
            raise ValueError(f"source and target points must have the same shape, "
                             f"not {source.shape} and {target.shape}")
        if len(source) < 4:
            raise ValueError(f"an RBF warp needs at least 4 control points, got {len(source)}")
        if not smoothing >= 0:
            raise ValueError(f"smoothing must be >= 0, not {smoothing!r}")
        _, first, counts = np.unique(source, axis=0, return_index=True, return_counts=True)
        if np.any(counts > 1):
            repeated = sorted(first[counts > 1])
            raise ValueError(f"repeated source points (first at rows {repeated}): each control point must be distinct")
        # The displacement is interpolated, not the position: away from the control points the
        # warp tends to (an affine map close to) the identity rather than to the polynomial part.
        try:
            displacement = RBFInterpolator(source, target - source, kernel=KERNELS[kernel],
                                           smoothing=smoothing, degree=1 if affine else 0)
        except np.linalg.LinAlgError as error:
            raise ValueError(f"the RBF system is singular ({error}); are the control points coplanar?") from None
        return cls(source, target, kernel, float(smoothing), affine, displacement)

    def apply(self, points) -> np.ndarray:
        """Warped points, (n, 3) or (3,) like the input.

        scipy evaluates in chunks under a fixed memory budget, so half a million nodes against a
        thousand control points need no more than some tens of MB.
        """
        points = np.asarray(points, dtype=np.float64)
        flat = points.reshape(-1, 3)
        return (flat + self._displacement(flat)).reshape(points.shape)


def warp_residual(warp: RBFWarp, source_points, target_points) -> np.ndarray:
    """|warp(source) - target| per point: zero at the control points of an interpolating warp;
    on held-out correspondences, a measure of how well the warp predicts the subject."""
    source = _as_points(source_points, "source_points")
    target = _as_points(target_points, "target_points")
    return np.linalg.norm(warp.apply(source) - target, axis=1)


def fiber_transform(warp: RBFWarp, points, fibers) -> np.ndarray:
    """Unit fiber directions (n, 3) at ``points`` (n, 3), carried through the warp.

    A fiber is a material line element, so it maps by the warp's Jacobian, J f, then is
    re-normalised. J f is the derivative of the warp along f, taken by central differences
    (exact for an affine warp up to rounding, O(h^2) otherwise).
    """
    points = _as_points(points, "points")
    fibers = _as_points(fibers, "fibers")
    if fibers.shape != points.shape:
        raise ValueError(f"points and fibers must have the same shape, not {points.shape} and {fibers.shape}")
    length = np.linalg.norm(fibers, axis=1)
    if np.any(length == 0):
        raise ValueError(f"zero fiber directions at rows {np.flatnonzero(length == 0)[:10]}")
    direction = fibers / length[:, None]
    extent = np.ptp(warp.source_points, axis=0).max()
    step = RELATIVE_STEP * extent
    pushed = (warp.apply(points + step * direction) - warp.apply(points - step * direction)) / (2 * step)
    pushed_length = np.linalg.norm(pushed, axis=1)
    degenerate = pushed_length <= 1e-12
    if np.any(degenerate):
        raise ValueError(f"the warp squashes fibers to nothing at rows {np.flatnonzero(degenerate)[:10]} "
                         "(singular Jacobian: the warp folds there)")
    return pushed / pushed_length[:, None]


def signed_volumes(points, tets) -> np.ndarray:
    """Signed volumes (m,) of tetrahedra ``tets`` (m, 4): positive when (b-a, c-a, d-a) is right-handed."""
    points = _as_points(points, "points")
    tets = np.asarray(tets)
    if tets.ndim != 2 or tets.shape[1] != 4:
        raise ValueError(f"tets must have shape (m, 4), not {tets.shape}")
    a, b, c, d = (points[tets[:, k]] for k in range(4))
    return np.einsum("ij,ij->i", np.cross(b - a, c - a), d - a) / 6.0


def inverted_tets(points_after, tets, reference_points=None) -> np.ndarray:
    """Indices of the tetrahedra that a warp inverted (or flattened).

    Without ``reference_points`` every tet is taken to be positively oriented, and those with a
    non-positive signed volume in ``points_after`` are returned. With them (the mesh before the
    warp), those whose signed volume changed sign or became zero: use this for a mesh whose tets
    are not consistently oriented.
    """
    after = signed_volumes(points_after, tets)
    if reference_points is None:
        return np.flatnonzero(after <= 0)
    before = signed_volumes(reference_points, tets)
    return np.flatnonzero(np.sign(after) != np.sign(before))


def _as_points(points, name) -> np.ndarray:
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"{name} must have shape (n, 3), not {points.shape}")
    if not np.all(np.isfinite(points)):
        raise ValueError(f"{name} must be finite")
    return points
