"""The tree keeps its style (pyproject.toml: [tool.ruff], [tool.cython-lint]): ruff's lint rules
and its formatting on the Python sources, cython-lint on the kernels."""

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def tool(name: str) -> str:
    found = shutil.which(name, path=str(Path(sys.executable).parent))
    if found is None:
        pytest.fail(f"{name} is not installed (it is in the test extra: pip install -e '.[test]')")
    return found


def run(*args: str) -> subprocess.CompletedProcess:
    # cython-lint runs pycodestyle, installed beside it
    env = {"PATH": str(Path(sys.executable).parent) + ":/usr/bin:/bin"}
    return subprocess.run(args, capture_output=True, text=True, cwd=ROOT, env=env)


def test_ruff_finds_nothing():
    done = run(tool("ruff"), "check", "--no-cache", ".")
    assert done.returncode == 0, done.stdout + done.stderr


def test_the_python_sources_are_formatted():
    done = run(tool("ruff"), "format", "--check", "--no-cache", ".")
    assert done.returncode == 0, done.stdout + done.stderr


def test_cython_lint_finds_nothing():
    kernels = sorted(
        str(p.relative_to(ROOT))
        for folder in ("dvpmvs", "evaluation", "plugins")
        for p in (ROOT / folder).rglob("*.p[yx][xd]")
    )
    assert "dvpmvs/patchmatch/_patchmatch.pyx" in kernels
    assert "dvpmvs/patchmatch/_window_cost.pxd" in kernels
    done = run(tool("cython-lint"), *kernels)
    assert done.returncode == 0, done.stdout + done.stderr
