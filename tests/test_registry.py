"""Plugin discovery: built-in plugins, errors, and a plugin from a separate distribution."""

import os
import subprocess
import sys
import textwrap

import pytest

from dvpmvs import registry
from dvpmvs.registry import PluginNotFoundError
from tests.scenes import make_workspace

# Also run on the other Pythons `make test` checks (scripts/other_pythons.py).
pytestmark = pytest.mark.smoke


def test_builtin_view_selectors_are_registered():
    assert {"colmap_cfg", "sparse_score"} <= set(registry.available("view_selector"))
    selector = registry.create("view_selector", {"name": "sparse_score", "theta0": 4.0})
    assert selector.theta0 == 4.0


def test_unknown_name_lists_the_installed_ones():
    with pytest.raises(
        PluginNotFoundError,
        match=r"no view_selector plugin named 'magic'.*installed: colmap_cfg, sparse_score",
    ):
        registry.load_factory("view_selector", "magic")
    with pytest.raises(ValueError, match="unknown plugin kind"):
        registry.available("teleporter")


def test_bad_parameters_name_the_plugin():
    with pytest.raises(registry.PluginError, match="'colmap_cfg' rejected its parameters"):
        registry.create("view_selector", {"name": "colmap_cfg", "min_triangulation_angle": 120.0})


@pytest.mark.parametrize("value", ["no", "maybe", 1, "true"])
def test_a_plugin_option_of_a_declared_type_takes_only_that_type(value):
    # FileMasks declares allow_missing: bool; "no" must not count as true (a view without a
    # mask would be left unmasked, silently).
    config = {"name": "files", "path": "masks", "allow_missing": value}
    with pytest.raises(registry.PluginError, match=r"mask\.allow_missing must be true or false"):
        registry.create("mask", config)
    assert registry.create("mask", {**config, "allow_missing": False}).allow_missing is False
    # An integer where a number is declared is that number, as for the core's options.
    selector = registry.create("view_selector", {"name": "sparse_score", "theta0": 4})
    assert isinstance(selector.theta0, float)
    with pytest.raises(registry.PluginError, match=r"view_selector\.theta0 must be a number"):
        registry.create("view_selector", {"name": "sparse_score", "theta0": "4"})


THIRD_PARTY_PYPROJECT = """
[build-system]
requires = ["setuptools>=64"]
build-backend = "setuptools.build_meta"

[project]
name = "acme-dvpmvs-selector"
version = "1.0"

[project.entry-points."dvpmvs.view_selectors"]
nearest_centres = "acme_selector:make"

[project.entry-points."dvpmvs.configs"]
acme = "acme_selector.conf"

[tool.setuptools]
packages = ["acme_selector", "acme_selector.conf"]

[tool.setuptools.package-data]
"acme_selector.conf" = ["view_selector/*.yaml"]
"""

THIRD_PARTY_MODULE = '''
"""Ranks source views by the distance between camera centres (closest first)."""
import numpy as np


class NearestCentres:
    def __init__(self, power):
        self.power = power

    def __call__(self, workspace, reference, max_sources):
        centre = workspace[reference].center
        scores = {name: 1.0 / np.linalg.norm(view.center - centre) ** self.power
                  for name, view in workspace.views.items() if name != reference}
        return sorted(scores.items(), key=lambda kv: -kv[1])[:max_sources]


def make(params):
    return NearestCentres(**params)
'''


@pytest.fixture(scope="module")
def third_party_site(tmp_path_factory):
    """A plugin distribution of its own, pip-installed into a separate folder."""
    src = tmp_path_factory.mktemp("acme_src")
    (src / "pyproject.toml").write_text(THIRD_PARTY_PYPROJECT)
    package = src / "acme_selector"
    (package / "conf" / "view_selector").mkdir(parents=True)
    (package / "__init__.py").write_text(THIRD_PARTY_MODULE)
    (package / "conf" / "__init__.py").write_text("")
    (package / "conf" / "view_selector" / "nearest_centres.yaml").write_text(
        "name: nearest_centres\npower: 1.0\n"
    )
    site = tmp_path_factory.mktemp("acme_site")
    subprocess.run(
        [
            sys.executable,
            "-m",
            "pip",
            "install",
            "--quiet",
            "--no-deps",
            "--no-build-isolation",
            "--no-index",
            "--target",
            str(site),
            str(src),
        ],
        check=True,
    )
    return site


def _run(site, *args):
    env = dict(
        os.environ,
        PYTHONPATH=os.pathsep.join(filter(None, [str(site), os.environ.get("PYTHONPATH")])),
    )
    # Run outside the repository so that the installed dvpmvs is used, not the source tree.
    return subprocess.run(args, env=env, capture_output=True, text=True, cwd=site)


def test_third_party_plugin_is_discovered_without_touching_the_core(third_party_site):
    result = _run(
        third_party_site,
        sys.executable,
        "-c",
        "from dvpmvs import registry; print(registry.available('view_selector'))",
    )
    assert result.returncode == 0, result.stderr
    assert "nearest_centres" in result.stdout


def test_third_party_plugin_drives_the_workspace(third_party_site, tmp_path):
    root = tmp_path / "ws"
    make_workspace(root, num_auto=2)
    code = textwrap.dedent(f"""
        from dvpmvs.workspace import Workspace, WorkspaceOptions
        ws = Workspace.open({str(root)!r}, WorkspaceOptions(view_selector={{"name": "nearest_centres", "power": 2.0}}))
        print(sorted(ws["view_02.png"].sources))
    """)
    result = _run(third_party_site, sys.executable, "-c", code)
    assert result.returncode == 0, result.stderr
    # Cameras sit on an arc: the neighbours of the middle camera are the closest centres.
    # (Both are equally far: their order is a floating-point tie, so compare them sorted.)
    assert result.stdout.strip() == "['view_01.png', 'view_03.png']"


@pytest.mark.slow
def test_third_party_config_group_is_selectable_on_the_command_line(third_party_site, tmp_path):
    root = tmp_path / "ws"
    make_workspace(root, num_auto=2)
    result = _run(
        third_party_site,
        sys.executable,
        "-m",
        "dvpmvs.cli",
        "dense",
        f"workspace={root}",
        "view_selector=nearest_centres",
        "view_selector.power=3",
    )
    # The dense stage reads the workspace with the sources the plugin chose, then runs.
    assert (
        "view_01.png, view_03.png" in result.stderr or "view_03.png, view_01.png" in result.stderr
    ), result.stderr
    assert result.returncode == 0, result.stderr
