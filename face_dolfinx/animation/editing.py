"""Edits in activation space (sifakis2005 section 9): pure functions from animations to animations.

Every edit keeps each control on its own space, so that whatever it returns is a pose the face
can take: activations stay in [0, 1] (convex combinations, or clamping where an edit scales),
rotations stay rotations (``frame_between``), TMJ values stay within the bounds their inputs
respect (convex combinations of them, or clamping to the inputs' range).

  between     in-betweens of two poses (fitted frames or expressions; sifakis2005 figure 10)
  scaled      activations exaggerated or toned down about neutral or a reference pose, clamped
  segment     a time range of an animation, sped up or slowed down, optionally resampled
  splice      segments one after another, with in-betweens across each seam
  with_keyframes  one muscle's curve replaced by keyframes, blended in and out of the original
  smoothed    curves smoothed in time (Gaussian or Savitzky-Golay with a time constant), clamped

Exaggerating beyond the physical range is not an edit of activations (they never exceed 1): it
is the model's strength override (``FaceModel.with_strength``, ``--strength``; sifakis2005
figure 8), which ``simulate --animation`` honours.
"""
from __future__ import annotations

import math

import numpy as np

from face_dolfinx.model.bones import AffineMap
from .animation import Animation, AnimationError, concatenate, frame_between, keyframe_curve

SMOOTHING_METHODS = ("gaussian", "savgol")


def _pose(animation: Animation, where: str) -> Animation:
    if animation.n_frames != 1:
        raise AnimationError(f"{where}: a pose is one frame; {animation.source} has {animation.n_frames} "
                             f"(take one with Animation.at(t))")
    return animation


def pose_between(first: Animation, second: Animation, s: float, time: float = 0.0) -> Animation:
    """The pose a fraction ``s`` in [0, 1] of the way from pose ``first`` to pose ``second``
    (one-frame animations): activations linearly (by muscle name, 0 where one pose does not name
    a muscle), bone frames by ``frame_between``, TMJ values and pressure linearly."""
    first, second = _pose(first, "between"), _pose(second, "between")
    if not 0.0 <= s <= 1.0:
        raise AnimationError(f"fraction {s:g}: give a number in [0, 1] (scaled exaggerates)")
    # One set of muscle names, jaw and pressure for the two (times made distinct to join them).
    both = concatenate([_with(first, times=[0.0]), _with(second, times=[1.0])])
    activations = np.clip((1 - s) * both.activations[0] + s * both.activations[1], 0.0, 1.0)
    cranium = frame_between(both.cranium[0], both.cranium[1], s)
    tmj = None if both.tmj is None else ((1 - s) * both.tmj[0] + s * both.tmj[1])[None]
    jaw = None if both.jaw is None or tmj is not None else [frame_between(both.jaw[0], both.jaw[1], s)]
    pressure = None if both.pressure is None else [(1 - s) * both.pressure[0] + s * both.pressure[1]]
    return Animation([time], both.muscle_names, activations[None], [cranium], jaw, pressure, tmj,
                     source=f"{first.source} -> {second.source}")


def between(first: Animation, second: Animation, frames: int, duration: float) -> Animation:
    """``frames`` (>= 2) poses evenly from ``first`` (at time 0) to ``second`` (at ``duration``)."""
    if frames < 2:
        raise AnimationError(f"{frames} frames: an interpolation needs 2 or more")
    if not duration > 0:
        raise AnimationError(f"duration {duration:g} s: must be positive")
    fractions = np.linspace(0.0, 1.0, frames)
    return concatenate([pose_between(first, second, float(s), float(s * duration)) for s in fractions],
                       source=f"{first.source} -> {second.source}")


def scaled(animation: Animation, factor: float, about: Animation | None = None) -> Animation:
    """Activations moved ``factor`` times as far from ``about`` (a pose; default neutral, all 0):
    > 1 exaggerates, < 1 tones down; clamped to [0, 1]. Head and jaw stay as they are."""
    if not (math.isfinite(factor) and factor >= 0):
        raise AnimationError(f"scale factor {factor!r}: give a number 0 or more")
    reference = np.zeros(len(animation.muscle_names))
    if about is not None:
        about = _pose(about, "scale about")
        reference = np.array([about.activation(name)[0] for name in animation.muscle_names])
    activations = np.clip(reference + factor * (animation.activations - reference), 0.0, 1.0)
    return _with(animation, activations=activations, source=f"{animation.source} scaled by {factor:g}")


def segment(animation: Animation, start: float | None = None, stop: float | None = None, speed: float = 1.0,
            frame_rate: float | None = None) -> Animation:
    """The part of ``animation`` from ``start`` to ``stop`` (its own times; default: all of it),
    played ``speed`` times as fast, its times from 0: its own samples in that range, or with
    ``frame_rate`` (Hz) resampled at that rate (controls on their own spaces)."""
    first, last = animation.times[0], animation.times[-1]
    start = first if start is None else float(start)
    stop = last if stop is None else float(stop)
    where = f"{animation.source} [{start:g}, {stop:g}] s"
    if not (math.isfinite(speed) and speed > 0):
        raise AnimationError(f"{where}: speed {speed!r} must be positive")
    if not first <= start <= stop <= last:
        raise AnimationError(f"{where}: the range must lie within the animation's [{first:g}, {last:g}] s, "
                             f"start before stop")
    if frame_rate is not None:
        if not (math.isfinite(frame_rate) and frame_rate > 0):
            raise AnimationError(f"{where}: frame rate {frame_rate!r} must be positive")
        count = int(math.floor((stop - start) / speed * frame_rate + 1e-9)) + 1
        played = np.arange(count) / frame_rate
        part = animation.resampled(start + speed * played)
    else:
        inside = (animation.times >= start) & (animation.times <= stop)
        if not inside.any():
            raise AnimationError(f"{where}: no frame in that range (give a frame rate to resample)")
        part = _select(animation, np.flatnonzero(inside))
        played = (part.times - start) / speed
    return _with(part, times=played, source=where + (f" x{speed:g}" if speed != 1.0 else ""))


def splice(parts: list[Animation], transition: float | None = None) -> Animation:
    """``parts`` one after another. Each seam lasts ``transition`` seconds (default: one frame
    spacing of the part before), filled with in-betweens of the last pose before it and the first
    after it at that part's frame spacing, so the face does not jump."""
    if not parts:
        raise AnimationError("splice: no parts")
    pieces, end = [], None
    for index, part in enumerate(parts):
        if end is None:
            pieces.append(part)
            end = part.times[-1]
            continue
        before = parts[index - 1]
        spacing = _spacing(before) or _spacing(part) or 1.0
        seam = spacing if transition is None else float(transition)
        if not (math.isfinite(seam) and seam > 0):
            raise AnimationError(f"splice: transition {transition!r} s must be positive")
        steps = max(1, int(round(seam / spacing)))
        last_pose = _select(before, [before.n_frames - 1])
        first_pose = _select(part, [0])
        for k in range(1, steps):
            pieces.append(pose_between(last_pose, first_pose, k / steps, end + k * seam / steps))
        shifted = _with(part, times=part.times - part.times[0] + end + seam)
        pieces.append(shifted)
        end = shifted.times[-1]
    return concatenate(pieces, source=" + ".join(part.source for part in parts))


def with_keyframes(animation: Animation, muscle: str, key_times, key_values, blend: float = 0.1,
                   interpolation: str = "smooth") -> Animation:
    """``muscle``'s activation replaced by the curve through keyframes (``key_times`` in the
    animation's time, ``key_values`` in [0, 1]) from the first key to the last, blended in over
    ``blend`` seconds before the first key and out over ``blend`` seconds after the last (eased),
    the original curve (0 for a muscle the animation does not name) elsewhere."""
    key_times = np.asarray(key_times, dtype=float).reshape(-1)
    key_values = np.asarray(key_values, dtype=float).reshape(-1)
    where = f"keyframes of {muscle}"
    if not len(key_times) or key_times.shape != key_values.shape:
        raise AnimationError(f"{where}: give as many values as times (one or more)")
    if np.any(np.diff(key_times) <= 0):
        raise AnimationError(f"{where}: key times must increase")
    if not np.all((key_values >= 0) & (key_values <= 1)):
        raise AnimationError(f"{where}: activations must lie in [0, 1]")
    if not (math.isfinite(blend) and blend >= 0):
        raise AnimationError(f"{where}: blend {blend!r} s must be 0 or more")
    t = animation.times
    override = keyframe_curve(key_times, key_values, t, interpolation)
    if blend > 0:
        weight = np.minimum(keyframe_curve([key_times[0] - blend, key_times[0]], [0.0, 1.0], t, "smooth"),
                            keyframe_curve([key_times[-1], key_times[-1] + blend], [1.0, 0.0], t, "smooth"))
    else:
        weight = ((t >= key_times[0]) & (t <= key_times[-1])).astype(float)
    names = list(animation.muscle_names)
    activations = animation.activations
    if muscle not in names:
        names.append(muscle)
        activations = np.column_stack([activations, np.zeros(len(t))])
    activations = activations.copy()
    k = names.index(muscle)
    activations[:, k] = np.clip((1 - weight) * activations[:, k] + weight * override, 0.0, 1.0)
    return _with(animation, muscle_names=names, activations=activations, source=f"{animation.source} + {where}")


def smoothed(animation: Animation, time_constant: float, method: str = "gaussian") -> Animation:
    """Curves smoothed in time: activations, TMJ values, pressure, the head's (and an affine
    jaw's) translation and matrix (rotations projected back onto SO(3)). ``gaussian``: a Gaussian
    kernel of standard deviation ``time_constant`` (a weighted mean: values stay within the range
    of the originals, on any time grid); ``savgol``: a Savitzky-Golay filter of degree 2 over a
    window of +- 2 time constants (keeps peaks better; needs evenly spaced frames). Each curve is
    clamped to its original range (activations thus to [0, 1])."""
    if method not in SMOOTHING_METHODS:
        raise AnimationError(f"smoothing {method!r}: give one of {', '.join(SMOOTHING_METHODS)}")
    if not (math.isfinite(time_constant) and time_constant > 0):
        raise AnimationError(f"time constant {time_constant!r} s must be positive")
    filter_ = _gaussian_filter(animation.times, time_constant) if method == "gaussian" else \
        _savgol_filter(animation.times, time_constant)

    def smooth(values):
        values = np.asarray(values, dtype=float)
        flat = values.reshape(len(values), -1)
        low, high = flat.min(axis=0), flat.max(axis=0)
        return np.clip(filter_(flat), low, high).reshape(values.shape)

    def frames(maps):
        matrices = smooth([m.matrix for m in maps])
        translations = smooth([m.translation for m in maps])
        rigid = all(np.allclose(m.matrix @ m.matrix.T, np.eye(3), atol=1e-9) and np.linalg.det(m.matrix) > 0
                    for m in maps)
        if rigid:
            matrices = [_nearest_rotation(m) for m in matrices]
        return [AffineMap(m, t) for m, t in zip(matrices, translations)]

    tmj = None if animation.tmj is None else smooth(animation.tmj)
    return _with(animation, activations=np.clip(smooth(animation.activations), 0.0, 1.0),
                 cranium=frames(animation.cranium),
                 jaw=None if animation.jaw is None or tmj is not None else frames(animation.jaw),
                 pressure=None if animation.pressure is None else smooth(animation.pressure), tmj=tmj,
                 source=f"{animation.source} smoothed ({method}, {time_constant:g} s)")


def roughness(values: np.ndarray, times: np.ndarray) -> float:
    """RMS of the second time derivative of a curve by finite differences (per s^2): what
    smoothing reduces."""
    values, times = np.asarray(values, dtype=float), np.asarray(times, dtype=float)
    if len(values) < 3:
        return 0.0
    h0, h1 = np.diff(times)[:-1], np.diff(times)[1:]
    second = 2 * (h0 * values[2:] - (h0 + h1) * values[1:-1] + h1 * values[:-2]) / (h0 * h1 * (h0 + h1))
    return float(np.sqrt(np.mean(second ** 2)))


# -- helpers -------------------------------------------------------------------------------------
def _with(animation: Animation, **changes) -> Animation:
    fields = dict(times=animation.times, muscle_names=animation.muscle_names, activations=animation.activations,
                  cranium=animation.cranium, jaw=animation.jaw, pressure=animation.pressure, tmj=animation.tmj,
                  source=animation.source)
    fields.update(changes)
    return Animation(**fields)


def _select(animation: Animation, frames) -> Animation:
    frames = list(frames)
    return _with(animation, times=animation.times[frames], activations=animation.activations[frames],
                 cranium=[animation.cranium[i] for i in frames],
                 jaw=None if animation.jaw is None else [animation.jaw[i] for i in frames],
                 pressure=None if animation.pressure is None else animation.pressure[frames],
                 tmj=None if animation.tmj is None else animation.tmj[frames])


def _spacing(animation: Animation) -> float | None:
    return float(np.median(np.diff(animation.times))) if animation.n_frames > 1 else None


def _nearest_rotation(matrix: np.ndarray) -> np.ndarray:
    u, _, vt = np.linalg.svd(matrix)
    d = np.sign(np.linalg.det(u @ vt))
    return u @ np.diag([1.0, 1.0, d]) @ vt


def _gaussian_filter(times: np.ndarray, sigma: float):
    weights = np.exp(-0.5 * ((times[:, None] - times[None, :]) / sigma) ** 2)
    weights /= weights.sum(axis=1, keepdims=True)
    return lambda values: weights @ values


def _savgol_filter(times: np.ndarray, time_constant: float):
    from scipy.signal import savgol_filter
    if len(times) > 2:
        spacing = np.diff(times)
        if np.ptp(spacing) > 1e-6 * spacing.mean():
            raise AnimationError("Savitzky-Golay smoothing needs evenly spaced frames (resample the animation, "
                                 "or smooth with the Gaussian)")
    spacing = float(np.mean(np.diff(times))) if len(times) > 1 else 1.0
    half = max(1, int(round(2 * time_constant / spacing)))
    window = min(2 * half + 1, len(times) if len(times) % 2 else len(times) - 1)
    if window < 3:
        return lambda values: values
    return lambda values: savgol_filter(values, window, min(2, window - 1), axis=0, mode="interp")
