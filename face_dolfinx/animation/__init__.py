"""Animations of the face: activations, head and jaw motion over time, read from fits and files,
edited, and played back by ``run.py simulate --animation`` (docs/animation.md)."""
from .animation import Animation, AnimationError, concatenate, frame_between, keyframe_curve

__all__ = ["Animation", "AnimationError", "concatenate", "frame_between", "keyframe_curve"]
