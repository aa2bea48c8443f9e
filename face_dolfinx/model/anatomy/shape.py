"""The face as a thick mask: skin and inner (bone) surfaces as radial graphs over two angles.

Every point of the flesh has surface coordinates (theta, phi, t): theta is the azimuth about the
vertical axis (0 = straight ahead, positive towards the subject's left, +x), phi the elevation
(positive up) of a ray from the projection centre, and t in [0, 1] the depth fraction from the
inner surface (t = 0, bone, eyeballs or teeth) to the skin (t = 1). The point is

    x(theta, phi, t) = c + (r_inner + t T) d(theta, phi),   T = r_skin - r_inner > 0,

with d the unit ray direction. Because both surfaces are graphs over the same rays and T > 0,
the map is one-to-one: meshing the (theta, phi) domain and stacking layers in t can never fold.

The skin radius is a smooth base head (a horizontal superellipse blended with vertical caps)
plus named features; the tissue thickness T is a base value plus thickness features. A feature
has a layer: "bone" moves skin and inner surface together (brow ridges, cheekbones, chin),
"flesh" adds soft tissue on a fixed bone (nose, lips, cheek fat), "thickness" moves only the
inner surface (thin forehead skin, thin eyelids over the eyeball). Angles are in degrees.
"""
from dataclasses import dataclass

import numpy as np
from scipy.interpolate import PchipInterpolator

from . import libm

LAYERS = ("bone", "flesh", "thickness")


@dataclass(frozen=True)
class Feature:
    """A smooth bump along a segment of the (theta, phi) plane.

    The value at a point is amplitude(s) * exp(-0.5 * (rho / width(s))**power), where s in [0, 1]
    is the position of the closest point of the segment start -> end, rho the distance to it in
    degrees after dividing the theta and phi offsets by ``stretch``, and amplitude and width vary
    smoothly (smoothstep in s) along the segment. A single point (start == end) gives an
    elliptic bump.
    """

    name: str
    layer: str
    start: tuple[float, float]
    end: tuple[float, float]
    amplitude: tuple[float, float]  # mm at start and end
    width: tuple[float, float]      # degrees at start and end
    stretch: tuple[float, float] = (1.0, 1.0)
    power: float = 2.0
    mirror: bool = False            # also place the mirror image theta -> -theta

    def value(self, theta: np.ndarray, phi: np.ndarray) -> np.ndarray:
        total = self._one_side(theta, phi)
        if self.mirror:
            total = total + self._one_side(-theta, phi)
        return total

    def _one_side(self, theta, phi):
        sx, sy = self.stretch
        a = np.array(self.start) / (sx, sy)
        b = np.array(self.end) / (sx, sy)
        px, py = theta / sx, phi / sy
        ab = b - a
        length2 = float(ab @ ab)
        if length2 > 0:
            s = np.clip(((px - a[0]) * ab[0] + (py - a[1]) * ab[1]) / length2, 0.0, 1.0)
        else:
            s = np.zeros_like(px)
        rho = np.hypot(px - (a[0] + s * ab[0]), py - (a[1] + s * ab[1]))
        # Smoothstep blending: a linear blend would crease the surface where s stops at the ends.
        blend = s * s * (3.0 - 2.0 * s)
        amplitude = self.amplitude[0] + blend * (self.amplitude[1] - self.amplitude[0])
        width = self.width[0] + blend * (self.width[1] - self.width[0])
        return amplitude * libm.exp(-0.5 * libm.power(rho / width, self.power))


@dataclass(frozen=True)
class Table:
    """A smooth (C1, shape-preserving cubic) function of one variable, constant beyond its ends.

    Piecewise linear tables would crease the skin along every breakpoint.
    """

    x: tuple[float, ...]
    y: tuple[float, ...]

    def __call__(self, at):
        at = np.clip(at, self.x[0], self.x[-1])
        return PchipInterpolator(self.x, self.y)(at)


@dataclass(frozen=True)
class FaceShape:
    center: np.ndarray          # projection centre (mm)
    half_breadth: Table         # a(phi): horizontal superellipse semi-axis along x (mm)
    front_depth: Table          # c(phi): horizontal superellipse semi-axis along z (mm)
    breadth_exponent: float     # superellipse exponent in the horizontal plane
    top: float                  # vertical semi-axis above the centre (mm)
    bottom: float               # vertical semi-axis below the centre (mm)
    vertical_exponent: float
    base_thickness: float       # mm
    min_thickness: float        # mm: thickness is softly clamped above this
    features: tuple[Feature, ...]

    @staticmethod
    def direction(theta, phi) -> np.ndarray:
        """Unit ray directions, shape (..., 3), for angles in degrees."""
        th, ph = np.radians(theta), np.radians(phi)
        return np.stack([libm.cos(ph) * libm.sin(th), libm.sin(ph), libm.cos(ph) * libm.cos(th)], axis=-1)

    def base_radius(self, theta, phi):
        th, ph = np.radians(theta), np.radians(phi)
        n, m = self.breadth_exponent, self.vertical_exponent
        a, c = self.half_breadth(phi), self.front_depth(phi)
        horizontal = libm.power(libm.power(np.abs(libm.sin(th) / a), n) + libm.power(np.abs(libm.cos(th) / c), n), -1.0 / n)
        cap = np.where(ph > 0, self.top, self.bottom)
        return libm.power(libm.power(libm.cos(ph) / horizontal, m) + libm.power(np.abs(libm.sin(ph)) / cap, m), -1.0 / m)

    def radii(self, theta, phi) -> tuple[np.ndarray, np.ndarray]:
        """Inner-surface and skin radii along the rays (theta, phi)."""
        theta, phi = np.asarray(theta, float), np.asarray(phi, float)
        sums = {layer: np.zeros(np.broadcast(theta, phi).shape) for layer in LAYERS}
        for feature in self.features:
            sums[feature.layer] = sums[feature.layer] + feature.value(theta, phi)
        skin = self.base_radius(theta, phi) + sums["bone"] + sums["flesh"]
        thickness = _soft_floor(self.base_thickness + sums["flesh"] + sums["thickness"],
                                self.min_thickness)
        return skin - thickness, skin

    def thickness(self, theta, phi) -> np.ndarray:
        inner, skin = self.radii(theta, phi)
        return skin - inner

    def point(self, theta, phi, t) -> np.ndarray:
        """Physical points (..., 3) at surface coordinates (degrees, degrees, depth fraction)."""
        inner, skin = self.radii(theta, phi)
        radius = inner + np.asarray(t, float) * (skin - inner)
        return self.center + radius[..., None] * self.direction(theta, phi)

    def tangents(self, theta, phi, t, step: float = 1e-3) -> tuple[np.ndarray, np.ndarray]:
        """dx/dtheta and dx/dphi (mm per degree) by central differences."""
        d_theta = (self.point(theta + step, phi, t) - self.point(theta - step, phi, t)) / (2 * step)
        d_phi = (self.point(theta, phi + step, t) - self.point(theta, phi - step, t)) / (2 * step)
        return d_theta, d_phi


def _soft_floor(value, floor, softness: float = 1.0):
    """max(value, floor) with the corner rounded over ``softness`` mm (keeps the surfaces smooth)."""
    return floor + softness * np.logaddexp(0.0, (value - floor) / softness)
