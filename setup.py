"""Build the private Cython kernels (everything else lives in pyproject.toml).

Every ``dvpmvs/**/_*.pyx`` and ``evaluation/_*.pyx`` (installed as ``dvpmvs.evaluation``)
becomes an extension compiled with ``-O3`` and OpenMP, carrying the digest of its source (see
``dvpmvs/_kernel_sources.py``).
Set ``DVPMVS_NO_OPENMP=1`` to build single-threaded kernels on a compiler without OpenMP, and
``DVPMVS_NATIVE=1`` to compile for the build machine's own vector units (see ``_native_flags``).
"""

import importlib.util
import os
import sys
from pathlib import Path

import numpy as np
from Cython.Build import cythonize
from setuptools import Extension, setup

HERE = Path(__file__).parent.resolve()


def _kernel_sources():
    """dvpmvs/_kernel_sources.py, loaded by path: the package itself is not importable yet."""
    spec = importlib.util.spec_from_file_location(
        "_kernel_sources", HERE / "dvpmvs" / "_kernel_sources.py"
    )
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _openmp_flags():
    if os.environ.get("DVPMVS_NO_OPENMP"):
        return [], []
    if sys.platform == "darwin":  # Apple clang needs libomp from Homebrew.
        return ["-Xpreprocessor", "-fopenmp"], ["-lomp"]
    if sys.platform == "win32":
        return ["/openmp"], []
    return ["-fopenmp"], ["-fopenmp"]


def _native_flags():
    """``DVPMVS_NATIVE=1``: -march=native, so that the compiler's own vectorised loops use the
    build machine's widest vector units (AVX2, AVX-512); with -ffp-contract=off (always on) the
    maps stay the same, bit for bit, as a portable build's. Measured on
    the 800x600 room (docs/benchmarks.md): the estimator 10 % faster. Off by default: such a
    build stops with "illegal instruction" on a CPU without those units (a wheel or a container
    image built on a newer machine)."""
    if not os.environ.get("DVPMVS_NATIVE") or sys.platform == "win32":
        return []
    return ["-march=native"]


def _extensions():
    compile_omp, link_omp = _openmp_flags()
    # -fno-math-errno lets sqrt/exp inline; NaN and infinity semantics are kept (no -ffast-math).
    # -ffp-contract=off: the compiler fuses no multiply and add of its own, so that every vector path
    # rounds as the portable one does; the kernels fuse theirs explicitly (fmaf and FMA instructions
    # in _window_cost_simd.h), which rounds the same on every path.
    optimise = (
        ["/O2"]
        if sys.platform == "win32"
        else ["-O3", "-fno-math-errno", "-ffp-contract=off", *_native_flags()]
    )
    extensions = []
    digest = _kernel_sources().source_digest
    sources = sorted(HERE.glob("dvpmvs/**/_*.pyx")) + sorted(HERE.glob("evaluation/_*.pyx"))
    for pyx in sources:
        rel = pyx.relative_to(HERE)
        parts = rel.with_suffix("").parts
        if parts[0] == "evaluation":  # see package-dir in pyproject.toml
            parts = ("dvpmvs",) + parts
        extensions.append(
            Extension(
                ".".join(parts),
                [str(rel)],
                include_dirs=[np.get_include()],
                extra_compile_args=optimise + compile_omp,
                extra_link_args=link_omp,
                # The source's digest goes into the binary, so that a stale build is refused.
                define_macros=[
                    ("NPY_NO_DEPRECATED_API", "NPY_1_7_API_VERSION"),
                    ("DVPMVS_SOURCE_DIGEST", f'"{digest(pyx)}"'),
                ],
            )
        )
    return cythonize(
        extensions,
        nthreads=_build_jobs(),
        language_level=3,
        compiler_directives={
            "boundscheck": False,
            "wraparound": False,
            "cdivision": True,
            "initializedcheck": False,
        },
    )


def _build_jobs() -> int:
    """The kernels are translated and compiled side by side, one per core: pip gives setuptools no
    ``-j``, and `make setup`, the packaging test and each Python `make test` checks build them
    anew. ``DVPMVS_BUILD_JOBS=N`` sets another count."""
    return int(os.environ.get("DVPMVS_BUILD_JOBS", 0)) or os.cpu_count() or 1


setup(ext_modules=_extensions(), options={"build_ext": {"parallel": _build_jobs()}})
