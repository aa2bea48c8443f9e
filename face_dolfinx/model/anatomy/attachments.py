"""Facet tags of the built-in face: where the flesh is attached to bone and where it is free.

Inner surface (t = 0), by the (theta, phi) polygons of [attachments] (left half, mirrored):
  cranium   forehead, temples, nose, maxilla and cheekbones, and the lateral edges of the mask
            above the ear lobe (they continue into the scalp);
  mandible  the lower face from below the lower lip's vestibule to the mandible's lower border,
            out to the jaw angles and up the ramus: it rotates with the jaw;
  free      everything else: the gap between the two bones (oral vestibule behind the lips,
            buccal gap between the dental arches, masseter between zygomatic arch and ramus),
            so the lips and mouth corners can move and no node is pulled by both bones; the
            flesh behind the ramus; the submental region and neck; and the eyelids, within
            eye_margin degrees of the eye openings (they rest on the eyeball);
  oral      the free inner surface inside the [attachments] ``oral`` polygon: the lining of the
            vestibule and of the cheeks, which faces the air of the mouth (the intraoral
            pressure acts there, ``FaceProblem(intraoral_pressure=True)``).
Side walls of the mask: the mouth and eye walls are skin (lip and eyelid surfaces); the other
edges get the region at their position (cranium at the top and upper lateral edges, free at the
neck cut). The outer surface is skin.
"""
import numpy as np
from matplotlib.path import Path as Polygon
from scipy.spatial import cKDTree

from .description import Attachments
from .domain import PlanarMesh
from .extrude import LayeredMesh
from .openings import Opening

BOUNDARY_IDS = {"cranium": 1, "mandible": 2, "skin": 3, "free": 4, "oral": 5}


def bone_region(centres: np.ndarray, attachments: Attachments, openings: tuple[Opening, ...]) -> np.ndarray:
    """Tag value (cranium, mandible, oral or free) of inner-surface points (theta, phi)."""
    mirrored = np.column_stack([np.abs(centres[:, 0]), centres[:, 1]])
    values = np.full(len(centres), BOUNDARY_IDS["free"], dtype=np.int32)
    values[Polygon(attachments.oral).contains_points(mirrored)] = BOUNDARY_IDS["oral"]
    values[Polygon(attachments.cranium).contains_points(mirrored)] = BOUNDARY_IDS["cranium"]
    values[Polygon(attachments.mandible).contains_points(mirrored)] = BOUNDARY_IDS["mandible"]
    eyes = np.concatenate([_densify(o.outline()) for o in openings if o.name.startswith("eye")])
    values[cKDTree(eyes).query(centres)[0] < attachments.eye_margin] = BOUNDARY_IDS["free"]
    return values


def facet_tags(layered: LayeredMesh, planar: PlanarMesh, attachments: Attachments,
               openings: tuple[Opening, ...]) -> tuple[np.ndarray, np.ndarray]:
    """All tagged boundary triangles (k, 3) and their tag values (k,)."""
    opening_curves = [i for i, name in enumerate(planar.curve_names)
                      if name.startswith(tuple(o.name for o in openings))]
    wall_values = bone_region(layered.wall_centres, attachments, openings)
    wall_values[np.isin(layered.wall_curve, opening_curves)] = BOUNDARY_IDS["skin"]
    facets = np.concatenate([layered.inner, layered.outer, layered.walls])
    values = np.concatenate([bone_region(layered.inner_centres, attachments, openings),
                             np.full(len(layered.outer), BOUNDARY_IDS["skin"], dtype=np.int32),
                             wall_values])
    return facets, values


def _densify(polygon: np.ndarray, step: float = 0.25) -> np.ndarray:
    """Points every ``step`` degrees along a closed polygon (for distance queries)."""
    closed = np.vstack([polygon, polygon[:1]])
    pieces = []
    for start, end in zip(closed[:-1], closed[1:]):
        count = max(1, int(np.ceil(np.linalg.norm(end - start) / step)))
        pieces.append(start + np.linspace(0.0, 1.0, count, endpoint=False)[:, None] * (end - start))
    return np.concatenate(pieces)
