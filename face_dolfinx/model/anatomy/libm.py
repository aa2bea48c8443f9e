"""sin, cos, exp and power of float arrays by the C library, one call per element.

numpy picks its float64 kernels for these by the CPU: its own SIMD code where the CPU has AVX-512,
the C library's elsewhere, and the two differ in the last bit. gmsh's triangulation of the face's
parameter plane turns such bits into another mesh (5 064 against 5 136 tets for the 5K face). With
these the generator built the same faces, bit for bit, on CPUs with and without AVX-512
(docs/builtin_face.md).
"""
import math

import numpy as np

_sin, _cos, _exp = (np.frompyfunc(f, 1, 1) for f in (math.sin, math.cos, math.exp))
_pow = np.frompyfunc(math.pow, 2, 1)


def sin(x) -> np.ndarray:
    return np.asarray(_sin(x), dtype=float)


def cos(x) -> np.ndarray:
    return np.asarray(_cos(x), dtype=float)


def exp(x) -> np.ndarray:
    return np.asarray(_exp(x), dtype=float)


def power(x, y) -> np.ndarray:
    return np.asarray(_pow(x, y), dtype=float)
