"""Synthetic takes with known truth: the accuracy yardstick of the fitting.

A take is a set of control curves over frames (activations, TMJ jaw degrees of freedom, head
motion). Solving the face at every frame and sampling the model's marker sites gives exact marker
trajectories; Gaussian noise, outliers (markers jumping for a few frames) and gaps (markers
missing for stretches) are then added. The truth is returned next to the capture so that a fit can
be scored against it.

Noise is given as the RMS of the 3D error per marker (per-coordinate sigma = noise / sqrt(3)), so
"marker RMS error <= 1.1 x noise" compares like with like.

Each frame's solve starts from the last frame's equilibrium. Where that fails (Newton through a jaw
motion with the lips pressed on each other and on the teeth, say), the frame is solved from rest:
an equilibrium at the frame's true controls reached along another path, which with contact need
not be the one the take's history would reach (``TakeTruth.solved_from_rest`` lists those frames).
"""
from dataclasses import dataclass
import logging
import math
from pathlib import Path

import numpy as np

from face_dolfinx.model.bones import AffineMap, jaw_pose, rigid_map, rotation
from face_dolfinx.capture import Capture
from face_dolfinx.equilibrium.solver import EquilibriumError
from face_dolfinx.physics.contact import TEETH_STIFFNESS, ContactSettings
from face_dolfinx.physics.self_contact import LipContactSettings

log = logging.getLogger(__name__)

SCENARIOS = ("smile", "jaw", "brow", "speech", "mixed", "training", "bilabial")
# What touches what in a truth solved with contact: the lips each other, and the lining of the lips
# and cheeks the model's teeth too.
TRUTH_CONTACTS = ("lips", "lips+teeth")


@dataclass
class TakeTruth:
    activations: np.ndarray   # (frames, muscles)
    tmj: np.ndarray           # (frames, 3): opening (rad), right slide, left slide (mm)
    head: list                # per frame AffineMap of the cranium
    clean_positions: np.ndarray  # (frames, markers, 3) before noise, outliers and gaps
    solved_from_rest: tuple = ()  # frames whose solve from the last frame's equilibrium failed

    def select(self, frames) -> "TakeTruth":
        """The truth of some frames only (indices into this take's frames)."""
        frames = np.asarray(frames, dtype=int)
        from_rest = tuple(int(i) for i, f in enumerate(frames) if f in self.solved_from_rest)
        return TakeTruth(self.activations[frames], self.tmj[frames], [self.head[f] for f in frames],
                         self.clean_positions[frames], from_rest)


def _smooth_pulse(t: np.ndarray, start: float, peak: float, end: float) -> np.ndarray:
    """0 before ``start``, rising smoothly to 1 at ``peak``, back to 0 at ``end``."""
    rise = np.clip((t - start) / max(peak - start, 1e-9), 0.0, 1.0)
    fall = np.clip((end - t) / max(end - peak, 1e-9), 0.0, 1.0)
    shape = np.where(t < peak, rise, fall)
    return 0.5 - 0.5 * np.cos(math.pi * shape)


def control_curves(model, scenario: str, n_frames: int, head_motion: bool = True, seed: int = 0):
    """Activations (frames, muscles), TMJ (frames, 3) and head frames for a scenario."""
    if scenario not in SCENARIOS:
        raise ValueError(f"unknown scenario {scenario!r}; choose from {', '.join(SCENARIOS)}")
    rng = np.random.default_rng(seed)
    t = np.linspace(0.0, 1.0, n_frames)
    names = [m.name for m in model.muscles]
    activations = np.zeros((n_frames, len(names)))
    tmj = np.zeros((n_frames, 3))
    max_opening = math.asin(model.jaw.max_opening_sine)

    def drive(expression: str, curve: np.ndarray):
        for name, value in model.expressions.get(expression, {}).items():
            if name == "jaw_opening_deg":
                tmj[:, 0] = np.maximum(tmj[:, 0], min(math.radians(value), max_opening) * curve)
            else:
                i = names.index(name)
                activations[:, i] = np.maximum(activations[:, i], value * curve)

    if scenario == "smile":
        drive("smile", _smooth_pulse(t, 0.1, 0.5, 0.9))
    elif scenario == "jaw":
        tmj[:, 0] = 0.7 * max_opening * _smooth_pulse(t, 0.05, 0.5, 0.95)
        tmj[:, 1:] = (0.3 * model.jaw.track_length * _smooth_pulse(t, 0.05, 0.5, 0.95))[:, None]
    elif scenario == "brow":
        drive("brow_raise", _smooth_pulse(t, 0.1, 0.4, 0.8))
    elif scenario in ("speech", "mixed"):
        # Several mouth muscles with incommensurate frequencies and random phases, and the jaw
        # opening with the syllables, like the paper's narration sequence.
        mouth = [i for i, n in enumerate(names) if any(k in n for k in (
            "orbicularis_oris", "zygomaticus", "risorius", "depressor", "levator", "mentalis"))]
        for k, i in enumerate(mouth):
            frequency = 1.5 + 0.7 * k
            phase = rng.uniform(0, 2 * math.pi)
            activations[:, i] = 0.35 * (1 - np.cos(2 * math.pi * frequency * t + phase)) * rng.uniform(0.5, 1.0)
        tmj[:, 0] = 0.4 * max_opening * (0.5 - 0.5 * np.cos(2 * math.pi * 3.0 * t))
        if scenario == "mixed":
            drive("smile", _smooth_pulse(t, 0.2, 0.5, 0.8))
            drive("brow_raise", _smooth_pulse(t, 0.5, 0.7, 0.95))
    elif scenario == "training":
        _training_curves(model, n_frames, activations, tmj, drive)
    elif scenario == "bilabial":
        # "ma ba pa": three lip closures (the orbicularis oris at 0.9 presses the lips together,
        # the jaw closed), each followed by an open vowel (jaw opening, lower lip drawn down).
        closures = sum(_smooth_pulse(t, peak - 0.1, peak, peak + 0.1) for peak in (0.15, 0.45, 0.75))
        vowels = sum(_smooth_pulse(t, peak - 0.1, peak, peak + 0.1) for peak in (0.3, 0.6, 0.9))
        for i, name in enumerate(names):
            if name.startswith("orbicularis_oris"):
                activations[:, i] = 0.9 * closures
            elif name.startswith("depressor_labii_inferioris"):
                activations[:, i] = 0.4 * vowels
        tmj[:, 0] = 0.3 * max_opening * vowels
    activations = np.clip(activations, 0.0, 1.0)

    head = []
    for s in t:
        if head_motion:
            # A slow nod and turn (a few degrees) and a drift of a few millimetres.
            R = rotation([1.0, 0.0, 0.0], math.radians(4.0) * math.sin(2 * math.pi * s)) @ \
                rotation([0.0, 1.0, 0.0], math.radians(6.0) * math.sin(math.pi * s))
            head.append(rigid_map(R, np.zeros(3), np.array([2.0 * s, -1.5 * s, 1.0 * math.sin(math.pi * s)])))
        else:
            head.append(AffineMap())
    return activations, tmj, head


def training_segments(model) -> list[tuple[str, object]]:
    """The segments of the "training" take, in order: ("muscle", index) for every muscle fully
    contracted on its own, ("tmj", limits) for each jaw degree of freedom at its limit (opening,
    either condyle slide, both slides: protrusion), ("expression", name) for the model's named
    expressions (compound actuation)."""
    max_opening = math.asin(model.jaw.max_opening_sine)
    track = model.jaw.track_length
    jaw_limits = [(max_opening, 0.0, 0.0), (0.0, track, 0.0), (0.0, 0.0, track), (0.0, track, track)]
    return ([("muscle", i) for i in range(len(model.muscles))]
            + [("tmj", np.array(limits)) for limits in jaw_limits]
            + [("expression", name) for name, spec in model.expressions.items() if spec])


def _training_curves(model, n_frames, activations, tmj, drive) -> None:
    """Choe & Ko's training data (2001, section 4.2): the frames are shared out over
    ``training_segments`` in order, and within a segment the level ramps up to full over its
    frames (two frames per segment: 0.5 and 1). Give a multiple of the segment count."""
    segments = training_segments(model)
    segment_of_frame = np.minimum(np.arange(n_frames) * len(segments) // n_frames, len(segments) - 1)
    for number, (kind, what) in enumerate(segments):
        frames = np.flatnonzero(segment_of_frame == number)
        level = np.zeros(n_frames)
        level[frames] = np.arange(1, len(frames) + 1) / max(len(frames), 1)
        if kind == "muscle":
            activations[:, what] = np.maximum(activations[:, what], level)
        elif kind == "tmj":
            tmj[:] = np.maximum(tmj, level[:, None] * what)
        else:
            drive(what, level)


def truth_contact_options(model, truth_contact: str | None = None, where: str = "truth_contact") -> dict:
    """The ``FaceProblem`` keywords (``lip_contact``, ``contact``) of a truth solved with contact.

    ``truth_contact``: ``"lips"`` (lip self-contact) or ``"lips+teeth"`` (the lips on each other and
    the lining on the teeth, with the settings ``fit --contact`` uses: ``TrackingSettings(contact=True)``);
    None: the surfaces ``fit --contact`` uses for ``model``, "lips+teeth" if it has teeth, else "lips",
    so that a fit with contact models the take as it was made. ``where`` names the option in errors.
    """
    if truth_contact is None:
        truth_contact = "lips+teeth" if model.teeth else "lips"
    if truth_contact not in TRUTH_CONTACTS:
        raise ValueError(f"{where} {truth_contact!r}: choose from {', '.join(TRUTH_CONTACTS)}")
    if truth_contact == "lips+teeth" and not model.teeth:
        raise ValueError(f"{where} {truth_contact}: model {model.path} has no teeth ([teeth] in its model.toml); "
                         "use lips")
    teeth = truth_contact == "lips+teeth"
    return dict(lip_contact=LipContactSettings(where=where),
                contact=ContactSettings(teeth=True, stiffness=TEETH_STIFFNESS, where=where) if teeth else None)


def synthesize_take(problem, markers, model, scenario: str = "speech", n_frames: int = 30,
                    frame_rate: float = 60.0, noise: float = 0.5, outliers: int = 0,
                    outlier_size: float = 10.0, gaps: int = 0, head_motion: bool = True,
                    seed: int = 0, marker_names: list[str] | None = None,
                    progress=None, frames: range | None = None) -> tuple[Capture, TakeTruth]:
    """Solve the face along a scenario and sample ``markers`` (a fitting.MarkerSet).

    ``frames`` (default all): solve and return only these frames of the ``n_frames``-long take,
    e.g. a stretch of a long take at its real frame spacing for a benchmark.
    """
    activations, tmj, head = control_curves(model, scenario, n_frames, head_motion, seed)
    if frames is not None:
        activations, tmj, head = activations[frames], tmj[frames], [head[f] for f in frames]
        n_frames = len(frames)
    clean = np.zeros((n_frames, len(markers.reference), 3))
    from_rest = []
    for frame in range(n_frames):
        controls = dict(activations=activations[frame], cranium=head[frame], jaw=jaw_pose(model.jaw, *tmj[frame]))
        try:
            problem.solve(**controls)
        except EquilibriumError as error:
            if problem.comm.rank == 0:
                log.warning("synthetic take, frame %d: %s; solving it from rest", frame, error)
            problem.reset_to_rest()
            problem.solve(**controls)
            from_rest.append(frame)
        clean[frame] = markers.positions(problem.u.x.array, head[frame])
        if progress is not None:
            progress(frame)
    rng = np.random.default_rng(seed + 1)
    noisy = clean + rng.normal(scale=noise / math.sqrt(3.0), size=clean.shape)
    n_markers = clean.shape[1]
    for _ in range(outliers):
        marker, start = rng.integers(n_markers), rng.integers(n_frames)
        direction = rng.normal(size=3)
        noisy[start:start + 3, marker] += outlier_size * direction / np.linalg.norm(direction)
    for _ in range(gaps):
        marker, start = rng.integers(n_markers), rng.integers(n_frames)
        noisy[start:start + max(2, n_frames // 10), marker] = np.nan
    names = marker_names or markers.names
    capture = Capture(names, noisy, frame_rate)
    return capture, TakeTruth(activations, tmj, head, clean, tuple(from_rest))


def truth_path(capture_path) -> Path:
    """Where the truth of a synthetic take is kept: beside the capture, ``NAME.truth.npz``."""
    capture_path = Path(capture_path)
    return capture_path.with_name(capture_path.stem + ".truth.npz")


def save_truth(path, truth: TakeTruth, muscle_names: list[str]) -> None:
    np.savez(path, activations=truth.activations, tmj=truth.tmj,
             head_matrices=np.array([h.matrix for h in truth.head]),
             head_translations=np.array([h.translation for h in truth.head]),
             clean_positions=truth.clean_positions, muscle_names=np.array(muscle_names),
             solved_from_rest=np.array(truth.solved_from_rest, dtype=int))


def load_truth(path) -> TakeTruth:
    with np.load(path) as data:
        head = [AffineMap(M, t) for M, t in zip(data["head_matrices"], data["head_translations"])]
        from_rest = tuple(int(f) for f in data["solved_from_rest"]) if "solved_from_rest" in data else ()
        return TakeTruth(data["activations"], data["tmj"], head, data["clean_positions"], from_rest)
