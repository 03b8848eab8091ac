import shutil
import sys
import tempfile
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent))

from scenes import make_workspace  # noqa: E402


@pytest.fixture
def workspace_dir(tmp_path):
    """A 5-view binary-model workspace with `__auto__, 2` sources; returns (path, ground truth)."""
    root = tmp_path / "ws"
    truth = make_workspace(root)
    return root, truth


def _free_space() -> str:
    folder = tempfile.gettempdir()
    return f"free space in {folder}: {shutil.disk_usage(folder).free / 1e9:.1f} GB"


def pytest_report_header(config):
    return _free_space()


def pytest_terminal_summary(terminalreporter, exitstatus, config):
    # Printed last, where CI's kept tail shows it: a run that failed for want of disk says so.
    terminalreporter.write_line(_free_space() + " (at the end of the run)")
