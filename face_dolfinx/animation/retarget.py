"""Retargeting: a take's muscle activations, head and jaw motion carried onto another face model
(Choe & Ko 2001: "we can synthesize expressions by applying the analyzed muscle contractions to any
computer model with an equivalent muscle structure"). No markers are needed on the target.

- **Muscles** map by name: every model adapted from a template carries the template's muscles by
  name. Muscles of the source the target lacks are dropped (with the largest activation they had);
  muscles of the target the source lacks stay at rest. No shared muscle is an error.
- **Head**: the cranium frame is a motion in model coordinates, so it is carried through the
  similarity ``S`` (scale, rotation, translation) that best maps the source's head onto the
  target's: the landmarks both models name and both condyles (Umeyama's least squares). The
  target's frame is ``S o C o S^-1``: the same rotation, turned into the target's axes, about the
  corresponding pivot, and translations scaled by the ratio of the head sizes. A uniformly scaled
  copy of a face thereby moves as the scaled copy of its motion.
- **Jaw**: the TMJ values carry over, not the mandible's affine frame (which moves points of the
  source's geometry): the opening angle as it is, clamped to the target's maximal opening, each
  condyle slide as the same fraction of the condylar track (in [0, 1] of the target's track).
  A target without mandible facets takes no jaw motion: an error if the take moves the jaw.
- **Intraoral pressure** (kPa) carries over as it is; a target without an ``oral`` surface takes
  none: an error if the take uses it.

``retarget`` takes an ``Animation`` on the source model and returns the ``Animation`` of the target
(the shared muscles by name, the cranium frames, the TMJ values, the pressure) and a record of what
was mapped, dropped and clamped, which the ``retarget`` command writes beside the animation.
"""
from __future__ import annotations

import json
import logging
import math
import pathlib

import numpy as np

from face_dolfinx.animation.animation import Animation
from face_dolfinx.alignment.similarity import AlignmentError, Similarity, similarity_transform
from face_dolfinx.model.bones import AffineMap, tmj_upper_limits, tmj_values
from face_dolfinx.model.folder import ModelArrays

log = logging.getLogger(__name__)

CONDYLES = ("condyle_right", "condyle_left")


class RetargetError(ValueError):
    """A take cannot be carried onto a model; the message names the model and the problem."""


def source_model_path(animation_path) -> pathlib.Path | None:
    """The model a fit or simulation folder was made on (its run.json), None for an animation file."""
    run = pathlib.Path(animation_path) / "run.json"
    if not run.is_file():
        return None
    model = json.loads(run.read_text()).get("model")
    return pathlib.Path(model) if model else None


def has_surface(model: ModelArrays, name: str) -> bool:
    """Whether some facet of ``model`` is tagged ``name``."""
    tag = model.boundary_ids.get(name)
    return tag is not None and bool(np.any(model.facet_values == tag))


def head_similarity(source: ModelArrays, target: ModelArrays) -> tuple[Similarity, list[str]]:
    """The similarity mapping the source's head onto the target's, fitted to the landmarks both
    name and both condyles, and the names of those points."""
    names = [name for name in source.landmarks if name in target.landmarks]

    def points(model):
        return np.array([model.landmarks[n] for n in names] + [model.jaw.condyle_right, model.jaw.condyle_left])
    try:
        return similarity_transform(points(source), points(target)), names + list(CONDYLES)
    except AlignmentError as error:
        raise RetargetError(f"models {source.name} and {target.name}: no head frame from their {len(names)} "
                            f"shared landmarks and the condyles ({error})") from None


def carry_head(cranium: AffineMap, similarity: Similarity) -> AffineMap:
    """The cranium frame ``S o C o S^-1`` of the target for the source's ``C``."""
    S = AffineMap(similarity.scale * similarity.rotation, similarity.translation)
    return S.compose(cranium).compose(S.inverse())


def carry_tmj(tmj: np.ndarray, source_jaw, target_jaw) -> tuple[np.ndarray, dict]:
    """The target's TMJ values (frames, 3) for the source's: opening angle as it is, slides as the
    same fraction of the track, each clamped to the target's bounds; and how many frames each
    clamp changed, with the source's largest values."""
    tmj = np.asarray(tmj, dtype=float).reshape(-1, 3)
    carried = tmj * np.array([1.0, target_jaw.track_length / source_jaw.track_length,
                              target_jaw.track_length / source_jaw.track_length])
    upper = tmj_upper_limits(target_jaw)
    clamped = np.clip(carried, 0.0, upper)
    changed = np.abs(clamped - carried) > 1e-12 * np.maximum(upper, 1.0)
    record = dict(
        slides="the same fraction of the condylar track",
        track_length_mm=dict(source=source_jaw.track_length, target=target_jaw.track_length),
        max_opening_deg=dict(source_take=math.degrees(float(tmj[:, 0].max(initial=0.0))),
                             target_limit=math.degrees(upper[0])),
        clamped_frames=dict(opening=int(changed[:, 0].sum()), slide_right=int(changed[:, 1].sum()),
                            slide_left=int(changed[:, 2].sum())))
    return clamped, record


def retarget(animation: Animation, source: ModelArrays, target: ModelArrays, *,
             target_label: str | None = None) -> tuple[Animation, dict]:
    """``animation`` of ``source`` carried onto ``target`` (module docstring), and the record of
    what was mapped, dropped, held at rest and clamped, and of the head similarity."""
    target_label = target_label or target.name
    target_names = [m.name for m in target.muscles]
    names = list(animation.muscle_names)
    shared = [name for name in names if name in target_names]
    if not shared:
        raise RetargetError(f"target model {target_label} shares no muscle with {animation.source} (its muscles: "
                            f"{', '.join(names[:4])}{', ...' if len(names) > 4 else ''}; the target's: "
                            f"{', '.join(target_names[:4])}, ...)")
    tmj = (animation.tmj if animation.tmj is not None
           else np.array([tmj_values(source.jaw, frame) for frame in animation.jaw]))
    opening, slides = tmj[:, 0].max(initial=0.0), np.abs(tmj[:, 1:]).max(initial=0.0)
    if not has_surface(target, "mandible") and (opening > 0 or slides > 0):
        raise RetargetError(f"target model {target_label} has no jaw (no facets tagged mandible), and "
                            f"{animation.source} moves the jaw (opening up to {math.degrees(opening):.3g} deg, "
                            f"slides up to {slides:.3g} mm)")
    pressure = np.abs(animation.pressure).max(initial=0.0) if animation.pressure is not None else 0.0
    if pressure > 0 and not has_surface(target, "oral"):
        raise RetargetError(f"target model {target_label} has no oral surface (no facets tagged oral) for the "
                            f"intraoral pressure of {animation.source} (up to {pressure:.3g} kPa)")

    dropped = {name: float(animation.activation(name).max(initial=0.0)) for name in names if name not in shared}
    at_rest = [name for name in target_names if name not in names]
    similarity, head_points = head_similarity(source, target)
    cranium = [carry_head(frame, similarity) for frame in animation.cranium]
    carried_tmj, jaw_record = carry_tmj(tmj, source.jaw, target.jaw)
    if dropped:
        log.warning("retarget onto %s drops %d muscles it lacks: %s", target_label, len(dropped),
                    ", ".join(f"{name} (up to {value:.3g})" for name, value in dropped.items()))
    if at_rest:
        log.info("retarget onto %s holds %d muscles the animation lacks at rest: %s", target_label,
                 len(at_rest), ", ".join(at_rest))
    if any(jaw_record["clamped_frames"].values()):
        log.warning("retarget onto %s clamps the jaw to its bounds in some frames: %s", target_label,
                    jaw_record["clamped_frames"])
    record = dict(
        source=animation.source, source_model=source.name, target_model=target_label,
        frames=animation.n_frames, muscles=dict(mapped=shared, dropped=dropped, held_at_rest=at_rest),
        head=dict(points=head_points, scale=similarity.scale, rotation=similarity.rotation.tolist(),
                  translation_mm=similarity.translation.tolist(), rms_mm=similarity.rms),
        jaw=jaw_record, intraoral_pressure_kpa_max=float(pressure))
    activations = np.column_stack([animation.activation(name) for name in shared])
    moved = Animation(animation.times, shared, activations, cranium, None,
                      None if animation.pressure is None else animation.pressure.copy(), carried_tmj,
                      source=f"{animation.source} retargeted to {target_label}")
    return moved, record


def record_path(animation_file) -> pathlib.Path:
    """Where the record of a retargeted animation is kept: beside it, ``NAME.retarget.json``."""
    path = pathlib.Path(animation_file)
    return path.with_name(path.stem + ".retarget.json")


def write_record(animation_file, record: dict) -> pathlib.Path:
    from face_dolfinx.files import atomic_write
    path = record_path(animation_file)
    atomic_write(path, json.dumps(record, indent=2))
    return path
