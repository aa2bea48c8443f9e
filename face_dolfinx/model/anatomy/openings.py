"""The openings through the mask: the mouth slit and the two eye fissures, as curves in the
(theta, phi) plane.

Each opening is bounded by an upper and a lower curve that share their two corner points. The
curves are the walls of the opening once the mask is extruded: for the mouth, the surfaces of
the upper and the lower lip that touch (almost) at rest.
"""
from dataclasses import dataclass

import numpy as np

from . import libm
from .description import Description

# Anchors sit this far (degrees) outside an opening's corner, on the closed skin, so that a
# marker "at the mouth corner" is on tissue and not in the slit.
ANCHOR_OFFSET = 0.5


@dataclass(frozen=True)
class Opening:
    name: str            # "mouth", "eye_left", "eye_right"
    upper: np.ndarray    # (k, 2) from the first corner to the second
    lower: np.ndarray    # (k, 2) between the same corners, same direction

    @property
    def corners(self) -> tuple[np.ndarray, np.ndarray]:
        return self.upper[0], self.upper[-1]

    def outline(self) -> np.ndarray:
        """Closed polygon (upper curve, then the lower one backwards)."""
        return np.concatenate([self.upper, self.lower[-2:0:-1]])

    def anchor(self, corner: int) -> np.ndarray:
        """A point just outside corner 0 or 1, continuing the corner line outwards."""
        a, b = self.corners
        outward = (a - b) if corner == 0 else (b - a)
        return (a if corner == 0 else b) + ANCHOR_OFFSET * outward / np.linalg.norm(outward)


def mouth_opening(description: Description, samples: int = 41) -> Opening:
    """The lens-shaped slit between the lips: two parabolic arcs meeting at the corners.

    The opening at the centre is given in mm on the skin; the lens is drawn in degrees, so it is
    converted with the skin radius there.
    """
    mouth = description.mouth
    theta0, phi0 = mouth.center
    _, skin_radius = description.shape.radii(theta0, phi0)
    half_gap = 0.5 * np.degrees(mouth.opening / skin_radius)
    theta = theta0 + mouth.half_width * np.linspace(-1.0, 1.0, samples)
    bulge = half_gap * (1.0 - ((theta - theta0) / mouth.half_width) ** 2)
    return Opening("mouth", np.column_stack([theta, phi0 + bulge]), np.column_stack([theta, phi0 - bulge]))


def eye_openings(description: Description, samples: int = 31) -> tuple[Opening, Opening]:
    """The left eye's almond (lids as sine arcs over the corner line) and its mirror image."""
    eye = description.eye
    inner, outer = np.array(eye.inner_corner), np.array(eye.outer_corner)
    s = np.linspace(0.0, 1.0, samples)[:, None]
    along = outer - inner
    up = np.array([-along[1], along[0]]) / np.linalg.norm(along)
    if up[1] < 0:
        up = -up
    base = inner + s * along
    lid = libm.sin(np.pi * s)
    upper, lower = base + eye.upper_height * lid * up, base - eye.lower_height * lid * up
    left = Opening("eye_left", upper, lower)
    mirror = np.array([-1.0, 1.0])
    return left, Opening("eye_right", upper * mirror, lower * mirror)


def all_openings(description: Description) -> tuple[Opening, ...]:
    return (mouth_opening(description), *eye_openings(description))


def anchor_point(name: str, openings: tuple[Opening, ...]) -> np.ndarray:
    """The left-side (theta > 0) anchor named in the description (see description.ANCHORS)."""
    by_name = {opening.name: opening for opening in openings}
    if name == "mouth_corner":
        return by_name["mouth"].anchor(1)            # the corner at +theta
    eye = by_name["eye_left"]                        # corner 0 is the inner one
    return eye.anchor(0 if name == "eye_inner_corner" else 1)
