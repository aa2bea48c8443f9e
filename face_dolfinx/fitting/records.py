"""What a fit gives back per frame (``FrameResult``) and what resumes it (``FitCheckpoint``)."""
from dataclasses import dataclass, field
import math

import numpy as np

from face_dolfinx.model.bones import AffineMap
from .formulations import ControlState


@dataclass
class FrameResult:
    frame: int
    activations: np.ndarray
    cranium: AffineMap
    jaw: AffineMap
    jaw_tmj: np.ndarray | None          # opening (rad), right and left slides (mm); exact mode
    marker_errors: np.ndarray           # per marker (mm), NaN where missing
    rms_error: float
    max_error: float
    gn_steps: int
    seconds: float
    phases: dict = field(default_factory=dict)
    flag: str = ""                      # why this frame is doubtful or skipped ("" = fine)
    initial_rms: float = math.nan       # marker RMS error of the warm start, before fitting
    observability: float = math.nan     # how well the visible markers determine the controls (1: as all do)
    unobservable: list[str] = field(default_factory=list)  # controls they cannot determine
    pressure: float = 0.0               # intraoral pressure (kPa; 0 unless fitted)


@dataclass
class FitCheckpoint:
    """The warm-start state of a sequence fit after a frame (``FaceFitter.checkpoint``).

    Arrays over dofs are local (owned + ghost dofs of this rank's part of the mesh).
    """
    state: ControlState                      # the fitted controls
    previous_activations: np.ndarray | None  # the temporal smoothness term's reference
    frames_done: int                         # 0: the next frame gets the first-frame step budget
    displacement: np.ndarray                 # the equilibrium the next frame starts from
    problem_controls: object                 # FaceProblem.controls at that equilibrium
    jacobian_state: ControlState | None      # the Jacobian the next first step reuses: the
    jacobian_dofs: np.ndarray | None         # controls it was computed at, dX/dc (k, dofs)
    jacobian_markers: np.ndarray | None      # and the marker Jacobian (k, markers, 3)
