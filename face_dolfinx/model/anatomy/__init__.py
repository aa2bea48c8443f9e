"""The built-in procedural face: a thick mask of flesh over the skull with 32 embedded muscles.

``build_builtin_face(target_tets)`` returns a model folder (docs/model_format.md) to load with
``face_dolfinx.model.folder.load_model``. The geometry lives in meshes/builtin_face.toml and is
explained in docs/builtin_face.md.
"""
from .builder import build_builtin_face

__all__ = ["build_builtin_face"]
