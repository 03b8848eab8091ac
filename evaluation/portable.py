"""The scene generator's arithmetic, with the same bits on every machine.

A scene is its digest (docs/benchmarks.md), so the generator must write the same bytes wherever
it runs. Two parts of numpy do not: matrix products go to OpenBLAS, whose kernels are chosen
per CPU (Haswell, SkylakeX, Sandybridge...) and sum and fuse in different orders; and
transcendental functions go to SIMD variants per vector extension (SVML on AVX-512) that
differ in the last bits. The generator's products and powers are computed here instead:
products as fixed chains of fused multiply-adds (C's ``fma`` rounds once, exactly, on every
platform) or of plain operations, powers through libm. The orders are those OpenBLAS's AVX2
kernels use for the same calls, and libm is what numpy calls on AVX2, so that scenes rendered
before this module existed keep their bits. Elementwise numpy arithmetic (``+ - * /``,
``sqrt``) is correctly rounded on every path and is used as it is.
"""

from __future__ import annotations

import numpy as np

from dvpmvs._kernel_sources import require_current
from dvpmvs.evaluation import _portable

require_current(_portable)

__all__ = ["matmul", "matvec", "transposed_matvec", "norm", "inverse_intrinsics", "power"]


def matmul(rows: np.ndarray, matrix: np.ndarray) -> np.ndarray:
    """``rows @ matrix`` for rows (..., K) and a (K, M) matrix, in float64."""
    rows = np.asarray(rows, np.float64)
    flat = np.ascontiguousarray(rows.reshape(-1, rows.shape[-1]))
    out = np.empty((len(flat), matrix.shape[1]))
    _portable.rows_times(flat, np.ascontiguousarray(matrix, np.float64), out)
    return out.reshape(*rows.shape[:-1], matrix.shape[1])


def matvec(matrix: np.ndarray, vector: np.ndarray) -> np.ndarray:
    """``matrix @ vector`` for a (M, 3) matrix and a 3-vector, in float64."""
    out = np.empty(len(matrix))
    _portable.matrix_times_vector(
        np.ascontiguousarray(matrix, np.float64), np.ascontiguousarray(vector, np.float64), out
    )
    return out


def transposed_matvec(matrix: np.ndarray, vector: np.ndarray) -> np.ndarray:
    """``matrix.T @ vector`` for a (3, M) matrix and a 3-vector: rows summed left to right onto 0."""
    m, v = np.asarray(matrix, np.float64), np.asarray(vector, np.float64)
    return ((0.0 + m[0] * v[0]) + m[1] * v[1]) + m[2] * v[2]


def norm(vector) -> float:
    """The length of a 3-vector, its squares summed left to right."""
    v = np.asarray(vector, np.float64)
    return float(np.sqrt((v[0] * v[0] + v[1] * v[1]) + v[2] * v[2]))


def inverse_intrinsics(K: np.ndarray) -> np.ndarray:
    """The inverse of a PINHOLE matrix [[fx, 0, cx], [0, fy, cy], [0, 0, 1]], rounded as
    LAPACK's inversion of it rounds."""
    fx, fy, cx, cy = float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])
    if K[0, 1] != 0 or K[1, 0] != 0 or K[2, 0] != 0 or K[2, 1] != 0 or K[2, 2] != 1:
        raise ValueError(f"not a PINHOLE intrinsics matrix: {K.tolist()}")
    return np.array(
        [[1 / fx, 0.0, -((1 / fx) * cx)], [0.0, 1 / fy, -((1 / fy) * cy)], [0.0, 0.0, 1.0]]
    )


def power(base, exponent) -> np.ndarray:
    """``base ** exponent`` element by element (broadcast), in float64, through libm's ``pow``."""
    base, exponent = np.broadcast_arrays(
        np.asarray(base, np.float64), np.asarray(exponent, np.float64)
    )
    out = np.empty(base.shape)
    _portable.power(
        np.ascontiguousarray(base).reshape(-1),
        np.ascontiguousarray(exponent).reshape(-1),
        out.reshape(-1),
    )
    return out
