import sys
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
