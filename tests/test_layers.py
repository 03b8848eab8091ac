"""The import contract (pyproject.toml, [tool.importlinter]) holds: import-linter in the source
checkout, where the harness is its folder ``evaluation``, and on the packages as installed,
``evaluation/`` and ``conf/`` inside ``dvpmvs``, the plugins beside it."""

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
# Where each importable package's sources are (pyproject.toml's package-dir), and the harness's
# folder under the name the source checkout gives it.
PACKAGE_DIRS = {
    "dvpmvs": "dvpmvs",
    "dvpmvs/evaluation": "evaluation",
    "dvpmvs/conf": "conf",
    "dvpmvs_classic": "plugins/classic/dvpmvs_classic",
    "dvpmvs_onnx": "plugins/onnx/dvpmvs_onnx",
    "evaluation": "evaluation",
}


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


def lint_imports(cwd: Path, site: Path | None = None) -> subprocess.CompletedProcess:
    """``lint-imports`` on pyproject.toml's contracts, run in ``cwd`` (which it puts first on the
    path), with ``site`` on the path if given."""
    linter = shutil.which("lint-imports", path=str(Path(sys.executable).parent))
    if linter is None:
        pytest.fail(
            "import-linter is not installed (it is in the test extra: pip install -e '.[test]')"
        )
    env = {**os.environ, **({"PYTHONPATH": str(site)} if site is not None else {})}
    return subprocess.run(
        [linter, "--config", str(ROOT / "pyproject.toml"), "--no-cache"],
        capture_output=True,
        text=True,
        env=env,
        cwd=cwd,
    )


def test_the_layers_hold_in_the_source_checkout():
    done = lint_imports(ROOT)
    assert done.returncode == 0, done.stdout + done.stderr
    assert "Contracts: 4 kept, 0 broken." in done.stdout


def test_the_layers_hold_as_installed(tmp_path):
    done = lint_imports(tmp_path, installed_layout(tmp_path / "site"))
    assert done.returncode == 0, done.stdout + done.stderr
    assert "Contracts: 4 kept, 0 broken." in done.stdout


@pytest.mark.parametrize(
    "module, statement, broken",
    [
        ("dvpmvs/maps.py", "from dvpmvs import dense", "dvpmvs.maps -> dvpmvs.dense"),
        (
            "dvpmvs/maps.py",
            "from dvpmvs.evaluation import runs",
            "dvpmvs.maps -> dvpmvs.evaluation.runs",
        ),
        (
            "dvpmvs/evaluation/report.py",
            "from dvpmvs import cli",
            "dvpmvs.evaluation.report -> dvpmvs.cli",
        ),
    ],
)
def test_an_import_from_a_higher_layer_breaks_the_contract(tmp_path, module, statement, broken):
    # The same contracts on a copy of the sources in which a module imports a higher layer.
    site = installed_layout(tmp_path / "site")
    path = site / module
    text = path.read_text()
    path.unlink()
    path.write_text(text + f"\n\ndef _uses_a_higher_layer():\n    {statement}  # noqa: F401\n")
    done = lint_imports(tmp_path, site)
    assert done.returncode != 0
    assert broken in done.stdout
