"""The import contract (pyproject.toml, [tool.importlinter]) holds: import-linter on the package
as installed, ``evaluation/`` and ``conf/`` inside ``dvpmvs``, the plugins beside it."""

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
# Where each importable package's sources are (pyproject.toml's package-dir).
PACKAGE_DIRS = {"dvpmvs": "dvpmvs", "dvpmvs/evaluation": "evaluation", "dvpmvs/conf": "conf",
                "dvpmvs_classic": "plugins/classic/dvpmvs_classic", "dvpmvs_onnx": "plugins/onnx/dvpmvs_onnx"}


def installed_layout(target: Path) -> Path:
    """The packages as installed, made of links to the sources (so that import-linter, which reads
    a package's folder, sees ``dvpmvs.evaluation``)."""
    for package, source in PACKAGE_DIRS.items():
        folder = target / package
        folder.mkdir(parents=True, exist_ok=True)
        for entry in (ROOT / source).iterdir():
            if entry.name != "__pycache__" and not (folder / entry.name).exists():
                (folder / entry.name).symlink_to(entry)
    return target


def lint_imports(tmp_path: Path, config: Path = ROOT / "pyproject.toml") -> subprocess.CompletedProcess:
    linter = shutil.which("lint-imports", path=str(Path(sys.executable).parent))
    if linter is None:
        pytest.fail("import-linter is not installed (it is in the test extra: pip install -e '.[test]')")
    env = {**os.environ, "PYTHONPATH": str(installed_layout(tmp_path / "site"))}
    return subprocess.run([linter, str(config), "--no-cache"], capture_output=True, text=True, env=env,
                          cwd=tmp_path)


def test_the_layers_hold(tmp_path):
    done = lint_imports(tmp_path)
    assert done.returncode == 0, done.stdout + done.stderr
    assert "Contracts: 3 kept, 0 broken." in done.stdout


def test_an_import_from_a_higher_layer_breaks_the_contract(tmp_path):
    # The same contract on a copy of the sources in which the maps (layer 2) import the pipeline.
    site = installed_layout(tmp_path / "site")
    maps = site / "dvpmvs" / "maps.py"
    text = maps.read_text()
    maps.unlink()
    maps.write_text(text + "\n\ndef _uses_the_pipeline():\n    from dvpmvs import pipeline  # noqa: F401\n")
    env = {**os.environ, "PYTHONPATH": str(site)}
    linter = shutil.which("lint-imports", path=str(Path(sys.executable).parent))
    done = subprocess.run([linter, str(ROOT / "pyproject.toml"), "--no-cache"], capture_output=True,
                          text=True, env=env, cwd=tmp_path)
    assert done.returncode != 0
    assert "dvpmvs.maps -> dvpmvs.pipeline" in done.stdout
