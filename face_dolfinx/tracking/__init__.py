"""Tracking a take: the frame loop (``Tracker``, ``track``) and its settings (``TrackingSettings``,
the presets ``PRESETS["default"]`` and ``PRESETS["fast"]``)."""
from .markers import MarkerSetup, MarkerSetupError
from .settings import PRESETS, RECORD_FIELDS, SettingError, TrackingSettings
from .tracker import Tracker, TrackingRun, finish, track

__all__ = ["MarkerSetup", "MarkerSetupError", "PRESETS", "RECORD_FIELDS", "SettingError", "Tracker", "TrackingRun", "TrackingSettings", "finish", "track"]
