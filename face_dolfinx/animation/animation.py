"""An animation: muscle activations, head and jaw motion over time (sifakis2005 section 9).

``Animation`` holds the controls of the face at a sequence of times: each muscle's activation
(by name, so that it applies to any model carrying muscles of those names), the cranium frame
(``AffineMap``, world frame), the jaw (relative to the cranium) as its frame and/or its three TMJ
values (opening in radians, right and left condyle slides in mm), and optionally the intraoral
pressure (kPa). It comes from a fit folder (``from_fit_folder``), a CSV table or a TOML file of
keyframes (``read``; docs/animation.md), or the edits of ``face_dolfinx.animation.editing``, and
``controls_at(t, model)`` gives the ``Controls`` of a model at any time of its span.

Between its samples every control moves on its own space, so that every in-between is a pose the
face can take (sifakis2005 figure 10): activations linearly (they stay in [0, 1]), the cranium
by its matrix on SO(3) (``AffineMap.geodesic`` of the matrices: a rotation stays a rotation,
turning about one axis at a steady rate) and its translation linearly, the jaw by its TMJ values
linearly (within their bounds, as the bounds are an interval) when it has them, else its frame as
the cranium's.

The jaw: ``tmj`` (n, 3), where known, is what drives the model's jaw (``bones.jaw_pose`` on the
model's own jaw geometry, which is what carries a motion from one model to another); ``jaw``
(frames relative to the cranium) is then the frames of the model the animation came from, or
None. An animation whose jaw is given by frames only (a fit of the paper's affine formulation)
has ``tmj`` None. ``jaw_frames(model)`` gives the frames for a model in either case.
"""
from __future__ import annotations

import csv
import math
import pathlib
import tomllib
from dataclasses import dataclass

import numpy as np

from face_dolfinx.model.bones import AffineMap, jaw_pose, rotation, tmj_upper_limits
from face_dolfinx.physics.problem import Controls

# Column names of the CSV form (docs/animation.md). The first four groups are what ``write``
# writes (every number exactly); the hand-written forms below them are read too.
TIME = "time_s"
CRANIUM_MATRIX = tuple(f"cranium_M{i}{j}" for i in range(3) for j in range(3))
CRANIUM_TRANSLATION = ("cranium_tx", "cranium_ty", "cranium_tz")
JAW_MATRIX = tuple(f"jaw_M{i}{j}" for i in range(3) for j in range(3))
JAW_TRANSLATION = ("jaw_tx", "jaw_ty", "jaw_tz")
TMJ = ("jaw_opening_rad", "jaw_slide_right_mm", "jaw_slide_left_mm")
PRESSURE = "intraoral_pressure_kpa"
HEAD_ROTATION = ("head_rx_deg", "head_ry_deg", "head_rz_deg")  # a rotation vector about the model origin
HEAD_TRANSLATION = ("head_tx_mm", "head_ty_mm", "head_tz_mm")
JAW_OPENING_DEG = "jaw_opening_deg"
IGNORED = ("frame",)  # the frame number of a fit's tables
KINEMATIC = frozenset((TIME, *CRANIUM_MATRIX, *CRANIUM_TRANSLATION, *JAW_MATRIX, *JAW_TRANSLATION, *TMJ,
                       PRESSURE, *HEAD_ROTATION, *HEAD_TRANSLATION, JAW_OPENING_DEG, *IGNORED))
TIME_SLACK = 1e-9  # s: a time this far outside the span counts as its end (round-off of a caller's clock)
BOUND_SLACK = 1e-9  # TMJ values this far outside their bounds are round-off of a bounded fit


class AnimationError(ValueError):
    """An animation that cannot drive a face: a bad file, or a mismatch with the model."""


@dataclass(frozen=True, eq=False)
class Animation:
    """Controls of a face at ``times`` (s, strictly increasing).

    ``muscle_names`` (m,) name the columns of ``activations`` (n, m), each in [0, 1]; muscles of
    a model the animation does not name stay at 0. ``cranium``: n frames (world); ``jaw``: n
    frames relative to the cranium, or None when ``tmj`` gives the jaw; ``pressure`` (n,) kPa or
    None; ``tmj`` (n, 3): opening (rad), right and left slide (mm), or None. ``source`` names
    where it came from, for messages.
    """

    times: np.ndarray
    muscle_names: tuple
    activations: np.ndarray
    cranium: tuple
    jaw: tuple | None
    pressure: np.ndarray | None = None
    tmj: np.ndarray | None = None
    source: str = "the animation"

    def __post_init__(self):
        def put(name, value):
            object.__setattr__(self, name, value)

        where = self.source
        times = np.asarray(self.times, dtype=float).reshape(-1)
        n = len(times)
        if n == 0:
            raise AnimationError(f"{where}: no frames")
        if not np.all(np.isfinite(times)):
            raise AnimationError(f"{where}: times must be finite numbers")
        steps = np.flatnonzero(np.diff(times) <= 0)
        if steps.size:
            i = steps[0] + 1
            raise AnimationError(f"{where}: times must increase; frame {i} is at {times[i]:g} s, "
                                 f"frame {i - 1} at {times[i - 1]:g} s")
        names = tuple(str(name) for name in self.muscle_names)
        repeated = sorted({name for name in names if names.count(name) > 1})
        if repeated:
            raise AnimationError(f"{where}: muscles named more than once: {', '.join(repeated)}")
        activations = np.asarray(self.activations, dtype=float).reshape(n, len(names))
        outside = np.argwhere(~((activations >= 0.0) & (activations <= 1.0)))
        if outside.size:
            frame, muscle = outside[0]
            raise AnimationError(f"{where}: activations must lie in [0, 1]; {names[muscle]} is "
                                 f"{activations[frame, muscle]:g} at {times[frame]:g} s"
                                 f" ({len(outside)} value(s) outside)")
        cranium = tuple(self.cranium)
        if len(cranium) != n:
            raise AnimationError(f"{where}: {len(cranium)} cranium frames for {n} times")
        tmj = None if self.tmj is None else np.asarray(self.tmj, dtype=float).reshape(n, 3)
        if tmj is not None and not np.all(np.isfinite(tmj)):
            raise AnimationError(f"{where}: TMJ values must be finite numbers")
        jaw = None if self.jaw is None else tuple(self.jaw)
        if jaw is None and tmj is None:
            raise AnimationError(f"{where}: give the jaw as frames or as TMJ values")
        if jaw is not None and len(jaw) != n:
            raise AnimationError(f"{where}: {len(jaw)} jaw frames for {n} times")
        pressure = None if self.pressure is None else np.asarray(self.pressure, dtype=float).reshape(n)
        if pressure is not None and not np.all(np.isfinite(pressure)):
            raise AnimationError(f"{where}: intraoral pressures must be finite numbers")
        for name, value in (("times", times), ("muscle_names", names), ("activations", activations),
                            ("cranium", cranium), ("jaw", jaw), ("pressure", pressure), ("tmj", tmj)):
            put(name, value)

    # -- what it is ----------------------------------------------------------------------------
    @property
    def n_frames(self) -> int:
        return len(self.times)

    @property
    def has_pressure(self) -> bool:
        """Whether it presses the mouth (a problem with the intraoral pressure control needed)."""
        return self.pressure is not None and bool(np.any(self.pressure != 0.0))

    def activation(self, name: str) -> np.ndarray:
        """The activation curve (n,) of muscle ``name`` (zeros if the animation does not name it)."""
        return (self.activations[:, self.muscle_names.index(name)] if name in self.muscle_names
                else np.zeros(self.n_frames))

    def check(self, model) -> None:
        """Raise AnimationError unless every muscle it names is the model's and its TMJ values are
        within the model's bounds."""
        unknown = [name for name in self.muscle_names if name not in model.muscle_names]
        if unknown:
            raise AnimationError(f"{self.source}: muscle(s) unknown to the model {model.path}: {', '.join(unknown)}; "
                                 f"the model's muscles: {', '.join(model.muscle_names)}")
        if self.tmj is not None:
            upper = tmj_upper_limits(model.jaw)
            outside = np.argwhere((self.tmj < -BOUND_SLACK) | (self.tmj > upper + BOUND_SLACK))
            if outside.size:
                frame, k = outside[0]
                raise AnimationError(f"{self.source}: {TMJ[k]} = {self.tmj[frame, k]:g} at {self.times[frame]:g} s "
                                     f"is outside the model's TMJ bounds [0, {upper[k]:g}]")

    def model_activations(self, model) -> np.ndarray:
        """Activations (n, the model's muscles) in the model's order, 0 for muscles not named."""
        self.check(model)
        columns = np.zeros((self.n_frames, len(model.muscle_names)))
        for k, name in enumerate(self.muscle_names):
            columns[:, model.muscle_names.index(name)] = self.activations[:, k]
        return columns

    def jaw_frames(self, model) -> list[AffineMap]:
        """The jaw frames (relative to the cranium) that drive ``model``: from the TMJ values on
        the model's jaw geometry where known, else the animation's frames."""
        if self.tmj is not None:
            return [jaw_pose(model.jaw, *values) for values in self.tmj]
        return list(self.jaw)

    # -- in between ----------------------------------------------------------------------------
    def segment(self, t: float) -> tuple[int, float]:
        """(i, s): time ``t`` is the fraction s in [0, 1] of the way from sample i to sample i + 1
        (i = n - 1, s = 0 at the last sample and for a single-frame animation)."""
        first, last = self.times[0], self.times[-1]
        slack = TIME_SLACK * max(1.0, last - first)
        if not first - slack <= t <= last + slack:
            raise AnimationError(f"{self.source}: time {t:g} s is outside the animation's span "
                                 f"[{first:g}, {last:g}] s")
        t = min(max(t, first), last)
        i = int(np.searchsorted(self.times, t, side="right")) - 1
        if i >= self.n_frames - 1:
            return self.n_frames - 1, 0.0
        return i, float((t - self.times[i]) / (self.times[i + 1] - self.times[i]))

    def at(self, t: float) -> "Animation":
        """The one-frame animation of the controls at time ``t`` (see the module docstring)."""
        i, s = self.segment(t)
        j = min(i + 1, self.n_frames - 1)
        activations = np.clip((1 - s) * self.activations[i] + s * self.activations[j], 0.0, 1.0)
        cranium = frame_between(self.cranium[i], self.cranium[j], s)
        tmj = None if self.tmj is None else (1 - s) * self.tmj[i] + s * self.tmj[j]
        # With TMJ values those drive the jaw; frames in between would only be a second opinion.
        jaw = None if self.jaw is None or (tmj is not None and s != 0.0) else [frame_between(self.jaw[i], self.jaw[j], s)]
        pressure = None if self.pressure is None else [(1 - s) * self.pressure[i] + s * self.pressure[j]]
        return Animation([t], self.muscle_names, activations[None], [cranium], jaw, pressure,
                         None if tmj is None else tmj[None], self.source)

    def resampled(self, times) -> "Animation":
        """The animation at ``times`` (each within the span), controls moved on their own spaces."""
        frames = [self.at(float(t)) for t in np.asarray(times, dtype=float).reshape(-1)]
        return concatenate(frames, self.source)

    def controls_at(self, t: float, model) -> Controls:
        """The ``Controls`` of ``model`` at time ``t``: activations by muscle name in the model's
        order, the cranium frame, the jaw frame for the model (``jaw_frames``), the pressure."""
        frame = self.at(t)
        return Controls(frame.model_activations(model)[0], frame.cranium[0], frame.jaw_frames(model)[0],
                        0.0 if frame.pressure is None else float(frame.pressure[0]))

    def frame_controls(self, frame: int, model) -> Controls:
        """The ``Controls`` of ``model`` at sample ``frame`` (exactly the stored values)."""
        return self.controls_at(float(self.times[frame]), model)

    # -- files ---------------------------------------------------------------------------------
    @classmethod
    def read(cls, path) -> "Animation":
        """An animation from a CSV table, a TOML file of keyframes, or a results folder of a fit
        or a simulation (``from_fit_folder``). Errors name the file (and line)."""
        path = pathlib.Path(path)
        if path.is_dir():
            return cls.from_fit_folder(path)
        if not path.is_file():
            raise AnimationError(f"{path}: no such animation file or results folder")
        suffix = path.suffix.lower()
        if suffix == ".csv":
            return _read_csv(path)
        if suffix == ".toml":
            return _read_toml(path)
        raise AnimationError(f"{path}: an animation is a .csv table, a .toml file of keyframes or a results "
                             f"folder, not {suffix or 'a file without suffix'}")

    @classmethod
    def from_fit_folder(cls, path) -> "Animation":
        """The fitted controls of the finished frames of a fit (or simulation) results folder, at
        the frames' times: every number as the frame records hold it."""
        from face_dolfinx.results.folder import FitFolder
        try:
            folder = FitFolder(path)
        except FileNotFoundError as error:
            raise AnimationError(str(error)) from None
        results = [result for _, result in sorted(folder.finished_frames().items())]
        if not results:
            raise AnimationError(f"{folder.path}: no finished frame")
        exact = all(r.jaw_tmj is not None for r in results)
        return cls(folder.times[[r.frame for r in results]], folder.muscle_names,
                   np.array([r.activations for r in results]), [r.cranium for r in results],
                   [r.jaw for r in results], np.array([r.pressure for r in results]),
                   np.array([r.jaw_tmj for r in results]) if exact else None, source=str(folder.path))

    @classmethod
    def from_expression(cls, model, name: str, time: float = 0.0) -> "Animation":
        """A one-frame animation of the model's named expression (head at rest)."""
        if name not in model.expressions:
            raise AnimationError(f"unknown expression {name!r}; the model {model.path} defines: "
                                 f"{', '.join(sorted(model.expressions))}")
        spec = dict(model.expressions[name])
        opening = math.radians(spec.pop("jaw_opening_deg", 0.0))
        names = list(spec)
        return cls([time], names, np.array([[spec[n] for n in names]]), [AffineMap()], None, None,
                   np.array([[opening, 0.0, 0.0]]), source=f"expression {name}")

    def write(self, path) -> pathlib.Path:
        """Write the CSV form (every number exactly: ``read`` gives the same animation back)."""
        path = pathlib.Path(path)
        if path.suffix.lower() != ".csv":
            raise AnimationError(f"{path}: animations are written as .csv tables")
        from face_dolfinx.files import atomic_write
        path.parent.mkdir(parents=True, exist_ok=True)
        atomic_write(path, self.csv_text())
        return path

    def csv_text(self) -> str:
        header = [TIME, *self.muscle_names, *CRANIUM_MATRIX, *CRANIUM_TRANSLATION]
        if self.jaw is not None:
            header += [*JAW_MATRIX, *JAW_TRANSLATION]
        if self.tmj is not None:
            header += list(TMJ)
        if self.pressure is not None:
            header.append(PRESSURE)
        lines = [",".join(header)]
        for i in range(self.n_frames):
            row = [self.times[i], *self.activations[i], *self.cranium[i].matrix.reshape(-1),
                   *self.cranium[i].translation]
            if self.jaw is not None:
                row += [*self.jaw[i].matrix.reshape(-1), *self.jaw[i].translation]
            if self.tmj is not None:
                row += list(self.tmj[i])
            if self.pressure is not None:
                row.append(self.pressure[i])
            lines.append(",".join(repr(float(v)) for v in row))
        return "\n".join(lines) + "\n"


def frame_between(first: AffineMap, second: AffineMap, s: float) -> AffineMap:
    """The bone frame a fraction ``s`` of the way from ``first`` to ``second``: the matrix along
    the geodesic of SO(3) (``AffineMap.geodesic`` of the matrices alone; a general matrix, as the
    paper's affine frames, along that of GL(3)), the translation linearly. ``s`` = 0 and 1 give
    the frames themselves, exactly."""
    if s == 0.0:
        return first
    if s == 1.0:
        return second
    matrix = AffineMap(first.matrix).geodesic(AffineMap(second.matrix), s).matrix
    return AffineMap(matrix, (1 - s) * first.translation + s * second.translation)


def concatenate(parts: list[Animation], source: str | None = None) -> Animation:
    """The frames of ``parts`` one after another (times must keep increasing). Muscles are the
    union of theirs (0 where a part does not name one); the jaw by TMJ values if every part has
    them, by frames if every part has those; the pressure where any part has one (0 elsewhere)."""
    if not parts:
        raise AnimationError("nothing to concatenate")
    names = list(parts[0].muscle_names)
    for part in parts[1:]:
        names += [name for name in part.muscle_names if name not in names]
    activations = np.vstack([np.column_stack([part.activation(name) for name in names]) if names
                             else np.zeros((part.n_frames, 0)) for part in parts])
    tmj = np.vstack([part.tmj for part in parts]) if all(p.tmj is not None for p in parts) else None
    jaw = [f for part in parts for f in part.jaw] if all(p.jaw is not None for p in parts) else None
    if tmj is None and jaw is None:
        missing = next(p for p in parts if p.jaw is None)
        raise AnimationError(f"{missing.source} gives its jaw by TMJ values only, another part by frames only: "
                             f"they cannot be joined without a model (Animation.jaw_frames)")
    pressure = (np.concatenate([p.pressure if p.pressure is not None else np.zeros(p.n_frames) for p in parts])
                if any(p.pressure is not None for p in parts) else None)
    return Animation(np.concatenate([p.times for p in parts]), names, activations,
                     [f for p in parts for f in p.cranium], jaw, pressure, tmj,
                     source if source is not None else parts[0].source)


# -- the CSV form ------------------------------------------------------------------------------
def _read_csv(path: pathlib.Path) -> Animation:
    try:
        with open(path, newline="") as handle:
            rows = list(csv.reader(handle))
    except (OSError, UnicodeDecodeError, csv.Error) as error:
        raise AnimationError(f"{path}: cannot be read as a CSV table ({error})") from None
    numbered = [(line, row) for line, row in enumerate(rows, start=1) if row and any(c.strip() for c in row)
                and not row[0].lstrip().startswith("#")]
    if not numbered:
        raise AnimationError(f"{path}: empty; the first line names the columns ({TIME}, muscles, ...)")
    header_line, header = numbered[0]
    header = [name.strip() for name in header]
    if TIME not in header:
        raise AnimationError(f"{path}:{header_line}: no {TIME} column (the header names the columns)")
    if not all(header):
        raise AnimationError(f"{path}:{header_line}: column {header.index('') + 1} has no name")
    repeated = sorted({name for name in header if header.count(name) > 1})
    if repeated:
        raise AnimationError(f"{path}:{header_line}: columns named more than once: {', '.join(repeated)}")
    groups = {"cranium": CRANIUM_MATRIX + CRANIUM_TRANSLATION, "head": HEAD_ROTATION + HEAD_TRANSLATION,
              "jaw frame": JAW_MATRIX + JAW_TRANSLATION}
    for group, columns in groups.items():
        present = [c for c in columns if c in header]
        if group != "head" and present and len(present) < len(columns):
            missing = [c for c in columns if c not in header]
            raise AnimationError(f"{path}:{header_line}: the {group} needs all of its columns; missing "
                                 f"{', '.join(missing)}")
    if any(c in header for c in groups["cranium"]) and any(c in header for c in groups["head"]):
        raise AnimationError(f"{path}:{header_line}: give the head as cranium_M*/cranium_t* or as "
                             f"head_r*_deg/head_t*_mm, not both")
    if JAW_OPENING_DEG in header and TMJ[0] in header:
        raise AnimationError(f"{path}:{header_line}: give the jaw opening in {JAW_OPENING_DEG} or {TMJ[0]}, not both")
    muscles = [name for name in header if name not in KINEMATIC]

    values = np.empty((len(numbered) - 1, len(header)))
    for r, (line, row) in enumerate(numbered[1:]):
        if len(row) != len(header):
            raise AnimationError(f"{path}:{line}: {len(row)} fields, the header (line {header_line}) has {len(header)}")
        for c, text in enumerate(row):
            try:
                values[r, c] = float(text)
            except ValueError:
                raise AnimationError(f"{path}:{line}: column {header[c]}: {text.strip()!r} is not a number") from None
            if not math.isfinite(values[r, c]):
                raise AnimationError(f"{path}:{line}: column {header[c]}: {text.strip()!r} is not a finite number")
    if not len(values):
        raise AnimationError(f"{path}: no rows after the header")
    lines = [line for line, _ in numbered[1:]]
    column = {name: values[:, k] for k, name in enumerate(header)}
    times = column[TIME]
    for r in range(1, len(times)):
        if times[r] <= times[r - 1]:
            raise AnimationError(f"{path}:{lines[r]}: time {times[r]:g} s is not after the previous row's "
                                 f"{times[r - 1]:g} s (times must increase)")
    activations = np.column_stack([column[name] for name in muscles]) if muscles else np.zeros((len(times), 0))
    for r, c in np.argwhere(~((activations >= 0.0) & (activations <= 1.0))):
        raise AnimationError(f"{path}:{lines[r]}: activation of {muscles[c]} is {activations[r, c]:g}, "
                             f"outside [0, 1]")

    def stack(names):
        return np.column_stack([column[name] if name in column else np.zeros(len(times)) for name in names])

    if CRANIUM_MATRIX[0] in column:
        matrices, translations = stack(CRANIUM_MATRIX).reshape(-1, 3, 3), stack(CRANIUM_TRANSLATION)
        cranium = [AffineMap(m, t) for m, t in zip(matrices, translations)]
    else:
        cranium = [AffineMap(_rotation_from_vector(r), t)
                   for r, t in zip(stack(HEAD_ROTATION), stack(HEAD_TRANSLATION))]
    jaw = None
    if JAW_MATRIX[0] in column:
        jaw = [AffineMap(m, t) for m, t in zip(stack(JAW_MATRIX).reshape(-1, 3, 3), stack(JAW_TRANSLATION))]
    tmj = None
    if any(name in column for name in (*TMJ, JAW_OPENING_DEG)):
        tmj = stack(TMJ)
        if JAW_OPENING_DEG in column:
            tmj[:, 0] = np.radians(column[JAW_OPENING_DEG])
    elif jaw is None:
        tmj = np.zeros((len(times), 3))  # no jaw columns: the jaw stays closed
    pressure = column.get(PRESSURE)
    return Animation(times, muscles, activations, cranium, jaw, pressure, tmj, source=str(path))


def _rotation_from_vector(vector_deg: np.ndarray) -> np.ndarray:
    angle = float(np.linalg.norm(vector_deg))
    return rotation(vector_deg, math.radians(angle)) if angle > 0.0 else np.eye(3)


# -- the TOML keyframe form --------------------------------------------------------------------
INTERPOLATIONS = ("linear", "smooth")


def keyframe_curve(key_times, key_values, times, interpolation: str = "linear") -> np.ndarray:
    """Values at ``times`` of the curve through keyframes (``key_times`` increasing): linear, or
    ``smooth`` (each stretch eased in and out, 3s^2 - 2s^3, so the curve is flat at every key);
    the first value before the first key, the last after the last. Both stay between the values
    of the two keys around a time, so activations in [0, 1] stay there."""
    key_times = np.asarray(key_times, dtype=float)
    key_values = np.asarray(key_values, dtype=float)
    times = np.asarray(times, dtype=float)
    if interpolation not in INTERPOLATIONS:
        raise AnimationError(f"interpolation {interpolation!r}: give one of {', '.join(INTERPOLATIONS)}")
    if len(key_times) == 1:
        return np.broadcast_to(key_values[0], times.shape + key_values.shape[1:]).copy()
    i = np.clip(np.searchsorted(key_times, times, side="right") - 1, 0, len(key_times) - 2)
    s = np.clip((times - key_times[i]) / (key_times[i + 1] - key_times[i]), 0.0, 1.0)
    if interpolation == "smooth":
        s = s * s * (3.0 - 2.0 * s)
    s = s.reshape(s.shape + (1,) * (key_values.ndim - 1))
    return (1 - s) * key_values[i] + s * key_values[i + 1]


def _read_toml(path: pathlib.Path) -> Animation:
    try:
        data = tomllib.loads(path.read_text())
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as error:
        raise AnimationError(f"{path}: cannot be read as TOML ({error})") from None

    def fail(message):
        raise AnimationError(f"{path}: {message}")

    known = {"frame_rate", "duration", "interpolation", "muscles", "head", "jaw", "pressure"}
    unknown = sorted(set(data) - known)
    if unknown:
        fail(f"unknown key(s) {', '.join(unknown)}; an animation has {', '.join(sorted(known))}")
    interpolation = data.get("interpolation", "linear")
    if interpolation not in INTERPOLATIONS:
        fail(f"interpolation = {interpolation!r}: give one of {', '.join(INTERPOLATIONS)}")

    def number(value, where, positive=False):
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            fail(f"{where} must be a number, got {value!r}")
        if positive and value <= 0:
            fail(f"{where} = {value}: must be positive")
        return float(value)

    def keys(table, where, channels: dict[str, int]):
        """(times, {channel: values (k,) or (k, width)}) of a keyframe table."""
        if not isinstance(table, dict):
            fail(f"[{where}] must be a table with times and values")
        extra = sorted(set(table) - {"times", *channels})
        if extra:
            fail(f"[{where}]: unknown key(s) {', '.join(extra)}; give times and {', '.join(channels)}")
        if "times" not in table:
            fail(f"[{where}]: no times")
        raw = table["times"]
        if not isinstance(raw, list) or not raw:
            fail(f"[{where}].times must be a list of numbers")
        key_times = np.array([number(t, f"[{where}].times") for t in raw])
        back = np.flatnonzero(np.diff(key_times) <= 0)
        if back.size:
            fail(f"[{where}].times must increase: {key_times[back[0] + 1]:g} s follows {key_times[back[0]]:g} s")
        found = {}
        for channel, width in channels.items():
            if channel not in table:
                continue
            values = table[channel]
            if not isinstance(values, list) or len(values) != len(key_times):
                fail(f"[{where}].{channel} must be a list of {len(key_times)} values, one per time")
            if width == 1:
                found[channel] = np.array([number(v, f"[{where}].{channel}") for v in values])
            else:
                if not all(isinstance(v, list) and len(v) == width for v in values):
                    fail(f"[{where}].{channel} must be a list of [x, y, z] values")
                found[channel] = np.array([[number(c, f"[{where}].{channel}") for c in v] for v in values])
        if not found:
            fail(f"[{where}]: give {' and/or '.join(channels)}")
        return key_times, found

    muscles = data.get("muscles", {})
    if not isinstance(muscles, dict):
        fail("[muscles] must be a table of muscles, each with times and values")
    curves = {name: keys(table, f"muscles.{name}", {"values": 1}) for name, table in muscles.items()}
    for name, (_, found) in curves.items():
        if "values" not in found:
            fail(f"[muscles.{name}]: no values")
        bad = found["values"][~((found["values"] >= 0) & (found["values"] <= 1))]
        if bad.size:
            fail(f"[muscles.{name}].values: activation {bad[0]:g} is outside [0, 1]")
    tables = {}
    for name, channels in (("head", {"rotation_deg": 3, "translation_mm": 3}),
                           ("jaw", {"opening_deg": 1, "slide_right_mm": 1, "slide_left_mm": 1}),
                           ("pressure", {"kpa": 1})):
        if name in data:
            tables[name] = keys(data[name], name, channels)
    last_key = max([t[-1] for t, _ in [*curves.values(), *tables.values()]], default=0.0)
    frame_rate = number(data["frame_rate"], "frame_rate", positive=True) if "frame_rate" in data else None
    if frame_rate is None:
        fail("no frame_rate (Hz): the rate of the frames to simulate")
    duration = number(data.get("duration", last_key), "duration")
    if duration < 0:
        fail(f"duration = {duration}: must be 0 or more")
    times = np.arange(int(math.floor(duration * frame_rate + 1e-9)) + 1) / frame_rate

    names = list(curves)
    activations = (np.column_stack([keyframe_curve(curves[n][0], curves[n][1]["values"], times, interpolation)
                                    for n in names]) if names else np.zeros((len(times), 0)))
    cranium = [AffineMap()] * len(times)
    if "head" in tables:
        key_times, found = tables["head"]
        rotations = found.get("rotation_deg", np.zeros((len(key_times), 3)))
        shifts = found.get("translation_mm", np.zeros((len(key_times), 3)))
        keys_maps = Animation(key_times, [], np.zeros((len(key_times), 0)),
                              [AffineMap(_rotation_from_vector(r), t) for r, t in zip(rotations, shifts)],
                              None, None, np.zeros((len(key_times), 3)), source=f"{path} [head]")
        # Rotations along SO(3) between keys, translations linearly; eased like the other curves.
        eased = keyframe_curve(key_times, key_times, times, interpolation)
        cranium = [keys_maps.at(float(t)).cranium[0] for t in eased]
    tmj = np.zeros((len(times), 3))
    if "jaw" in tables:
        key_times, found = tables["jaw"]
        for k, channel in enumerate(("opening_deg", "slide_right_mm", "slide_left_mm")):
            if channel in found:
                values = np.radians(found[channel]) if k == 0 else found[channel]
                tmj[:, k] = keyframe_curve(key_times, values, times, interpolation)
    pressure = None
    if "pressure" in tables:
        key_times, found = tables["pressure"]
        pressure = keyframe_curve(key_times, found["kpa"], times, interpolation)
    return Animation(times, names, activations, cranium, None, pressure, tmj, source=str(path))
