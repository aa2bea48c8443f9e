"""Fitting activations and bone motion to marker frames (sifakis2005 sections 5-9).

``FaceFitter`` (``fitter``) runs the Gauss-Newton loop per frame on a ``FaceProblem``, with the
markers of a ``MarkerSet`` and the options of ``FitSettings``; ``FitSettings.mode`` chooses the
formulation (``formulations``: ``exact`` or ``paper``). Each frame gives a ``FrameResult``;
``FaceFitter.checkpoint`` gives a ``FitCheckpoint`` to resume from. ``penalties`` holds the paper
formulation's constraint terms, ``baselines`` the linear models of the ladder (Choe & Ko).
"""
from .fitter import FaceFitter
from .formulations import ControlState, ExactFormulation, Formulation, PaperFormulation
from .markers import MarkerSet
from .observability import observability
from .records import FitCheckpoint, FrameResult
from .settings import FitSettings

__all__ = ["FaceFitter", "FitSettings", "MarkerSet", "FrameResult", "FitCheckpoint", "ControlState",
           "Formulation", "ExactFormulation", "PaperFormulation", "observability"]
