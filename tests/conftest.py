"""The suite's shared fixtures and what it prints about the machine's disk."""

from __future__ import annotations

import json
import shutil
import subprocess
import tempfile
from pathlib import Path

import pytest

from tests.helpers import built_once, dvpmvs
from tests.scenes import make_workspace


@pytest.fixture
def workspace_dir(tmp_path):
    """A 5-view binary-model workspace with `__auto__, 2` sources; returns (path, ground truth)."""
    root = tmp_path / "ws"
    truth = make_workspace(root)
    return root, truth


class _DemoRun(subprocess.CompletedProcess):
    """The demo's command, its output, and the folder it ran in (``cwd``)."""

    def __init__(self, cwd: Path, returncode: int, stdout: str, stderr: str):
        super().__init__(["dvpmvs", "demo", "out=dvpmvs_demo"], returncode, stdout, stderr)
        self.cwd = cwd


@pytest.fixture(scope="session")
def demo_run(tmp_path_factory) -> _DemoRun:
    """``dvpmvs demo out=dvpmvs_demo`` as `make demo` runs it, once for the whole run (the workers
    of pytest-xdist share it); its ``cwd`` is the folder holding ``dvpmvs_demo/``. The tests that
    use it only read that folder: one that changes it works on a copy."""

    def build(folder: Path) -> None:
        result = dvpmvs("demo", "out=dvpmvs_demo", cwd=folder)
        (folder / "said.json").write_text(
            json.dumps(
                {"returncode": result.returncode, "stdout": result.stdout, "stderr": result.stderr}
            )
        )

    folder = built_once(tmp_path_factory, "demo_run", build)
    return _DemoRun(folder, **json.loads((folder / "said.json").read_text()))


def _free_space() -> str:
    folder = tempfile.gettempdir()
    return f"free space in {folder}: {shutil.disk_usage(folder).free / 1e9:.1f} GB"


def pytest_report_header(config):
    return _free_space()


def pytest_terminal_summary(terminalreporter, exitstatus, config):
    # Printed last, where CI's kept tail shows it: a run that failed for want of disk says so.
    terminalreporter.write_line(_free_space() + " (at the end of the run)")
