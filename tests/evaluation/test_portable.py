"""The generator's arithmetic: fixed fused chains and libm, the same bits whatever BLAS runs."""

import math
import os
import platform
import subprocess
import sys
from fractions import Fraction

import numpy as np
import pytest

from dvpmvs.evaluation.portable import (
    inverse_intrinsics,
    matmul,
    matvec,
    norm,
    power,
    transposed_matvec,
)
from dvpmvs.evaluation.scene_digest import cpu_features


def _fma(a: float, b: float, c: float) -> float:
    """a * b + c rounded once (exact rational arithmetic; IEEE's sign for an exact zero)."""
    exact = Fraction(a) * Fraction(b) + Fraction(c)
    if exact == 0:
        product_negative = math.copysign(1, a) * math.copysign(1, b) < 0
        both_negative_zero = (
            (a == 0 or b == 0) and c == 0 and product_negative and math.copysign(1, c) < 0
        )
        return -0.0 if both_negative_zero else 0.0
    return float(exact)


def _same_bits(a, b) -> bool:
    return np.array_equal(np.asarray(a).view(np.int64), np.asarray(b).view(np.int64))


def _values(rng, shape):
    """Random doubles with zeros of both signs among them (their signs are part of the bits)."""
    values = rng.normal(size=shape) * 10.0 ** rng.integers(-3, 4, size=shape)
    values[rng.random(shape) < 0.15] = 0.0
    values[rng.random(shape) < 0.1] = -0.0
    return values


def test_products_are_fused_chains_in_a_fixed_order():
    rng = np.random.default_rng(0)
    rows, matrix = _values(rng, (40, 3)), _values(rng, (3, 4))
    expected = np.empty((40, 4))
    for i in range(40):
        for j in range(4):
            acc = 0.0
            for k in range(3):
                acc = _fma(rows[i, k], matrix[k, j], acc)
            expected[i, j] = acc
    assert _same_bits(matmul(rows, matrix), expected)
    assert _same_bits(matmul(rows.reshape(5, 8, 3), matrix), expected.reshape(5, 8, 4))
    # Close to numpy's product, which rounds as its BLAS kernel does.
    np.testing.assert_allclose(matmul(rows, matrix), rows @ matrix, rtol=1e-12, atol=1e-12)

    R, v = _values(rng, (3, 3)), _values(rng, 3)
    assert _same_bits(
        matvec(R, v),
        [_fma(R[i, 2], v[2], _fma(R[i, 0], v[0], _fma(R[i, 1], v[1], 0.0))) for i in range(3)],
    )
    assert _same_bits(
        transposed_matvec(R, v),
        [((0.0 + R[0, j] * v[0]) + R[1, j] * v[1]) + R[2, j] * v[2] for j in range(3)],
    )
    assert norm([3.0, 4.0, 12.0]) == 13.0


def test_powers_are_libms_and_the_inverse_is_lapacks_rounding():
    rng = np.random.default_rng(1)
    base, exponent = rng.random(2000), rng.uniform(1, 120, 2000)
    assert _same_bits(power(base, exponent), [math.pow(b, e) for b, e in zip(base, exponent)])
    assert power(base[:, None], np.array([[2.0, -0.5]])).shape == (2000, 2)
    K = np.array([[689.5, 0.0, 400.0], [0.0, 689.5, 300.0], [0.0, 0.0, 1.0]])
    assert _same_bits(inverse_intrinsics(K), np.linalg.inv(K))
    with pytest.raises(ValueError, match="not a PINHOLE"):
        inverse_intrinsics(np.array([[1.0, 0.1, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]))


def _runs_haswell_kernels() -> bool:
    """OpenBLAS's Haswell kernels need x86-64 with AVX2 and FMA."""
    if platform.machine() not in ("x86_64", "AMD64"):
        return False
    features = cpu_features()
    return bool(features.get("AVX2") and features.get("FMA3"))


@pytest.mark.skipif(
    not _runs_haswell_kernels(), reason="OpenBLAS's Haswell kernels need x86-64 with AVX2 and FMA"
)
def test_the_same_bits_whichever_kernel_openblas_picks():
    # Sandybridge's kernels fuse no multiply-add and Haswell's do: numpy's own products differ
    # between them in the last bits; these do not.
    script = (
        "import numpy as np; from dvpmvs.evaluation.portable import matmul; "
        "rng = np.random.default_rng(2); a, b = rng.normal(size=(500, 3)), rng.normal(size=(3, 3)); "
        "print(matmul(a, b).tobytes().hex()[:4000], (a @ b).tobytes().hex()[:4000])"
    )
    outputs = [
        subprocess.run(
            [sys.executable, "-c", script],
            capture_output=True,
            text=True,
            check=True,
            env={**os.environ, "OPENBLAS_CORETYPE": core},
        ).stdout.split()
        for core in ("Haswell", "Sandybridge")
    ]
    assert outputs[0][0] == outputs[1][0]
    assert outputs[0][1] != outputs[1][1]  # the switch took effect: numpy's products did change
