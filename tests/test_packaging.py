"""The package's contents, and the script that installs it on the other Pythons `make test` checks.

The wheel itself (built from this tree, installed alone into a fresh environment, the demo run
outside the source tree, then its extras and the smoke tests against it) is checked by
scripts/other_pythons.py, the last stage of `make test`, on the newest Python it finds.
"""

import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def test_every_folder_of_the_tree_is_in_the_wheels_package_list():
    # pyproject.toml lists the packages by hand (the harness and the configs are installed under
    # dvpmvs.*): a new subpackage missing from the list installs as an import error, and a folder
    # of data (a config group) missing from it is one of setuptools' "Package would be ignored"
    # warnings at every install.
    import subprocess

    try:
        import tomllib
    except ModuleNotFoundError:  # Python 3.10
        pytest.skip("tomllib is Python 3.11's")
    setuptools = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    tracked = subprocess.run(
        ["git", "ls-files"], cwd=ROOT, capture_output=True, text=True, check=True
    ).stdout.split()
    if not tracked:
        pytest.skip("not a git checkout")
    found = set()
    for name, folder in setuptools["package-dir"].items():
        for path in tracked:
            parent = Path(path).parent
            if parent == Path(folder) or Path(folder) in parent.parents:
                found.add(".".join([name, *parent.relative_to(folder).parts]))
    assert found == set(setuptools["packages"])


@pytest.mark.smoke
def test_every_module_of_the_installed_packages_imports():
    # Each module, the compiled kernels included, on this Python and its wheels of the libraries:
    # what a Python the main suite did not run on breaks first.
    import importlib
    import pkgutil

    names = []
    # dvpmvs.evaluation by its own name: an editable install maps it from another folder.
    for package in ("dvpmvs", "dvpmvs.evaluation", "dvpmvs_classic", "dvpmvs_onnx"):
        root = importlib.import_module(package)
        names += [package, *(m.name for m in pkgutil.walk_packages(root.__path__, f"{package}."))]
    for name in names:
        importlib.import_module(name)
    assert {
        "dvpmvs.patchmatch._patchmatch",
        "dvpmvs._fusion",
        "dvpmvs.evaluation._accuracy",
        "dvpmvs.evaluation.experiments.scale",
        "dvpmvs_onnx.providers",
    } <= set(names)


def _other_pythons_script():
    """scripts/other_pythons.py as a module (a script, not part of the package)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location(
        "other_pythons", ROOT / "scripts" / "other_pythons.py"
    )
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_an_install_that_fails_on_another_python_says_why_in_what_ci_keeps(tmp_path):
    # scripts/other_pythons.py keeps pip's output in a log on the machine that ran it; what CI
    # keeps is what it prints, so a failed install must print pip's own error and the free space.
    other_pythons = _other_pythons_script()
    log = tmp_path / "install.log"
    log.write_text("")
    assert other_pythons.run([sys.executable, "-m", "pip", "--version"], log)
    assert not other_pythons.run(
        [sys.executable, "-m", "pip", "install", "--no-index", "--quiet", "dvpmvs-no-such-package"],
        log,
    )
    text = log.read_text()
    said = other_pythons._last_messages(text)
    assert "No matching distribution found for dvpmvs-no-such-package" in said
    assert " from " not in said  # the last command's lines only, not pip's version line
    assert other_pythons.failing_package(text) == "dvpmvs-no-such-package"
    assert "GiB" in other_pythons._free_space()


def test_each_other_python_gets_a_copy_that_follows_the_checkout_and_keeps_its_build(tmp_path):
    # scripts/other_pythons.py builds each version in its own copy, so that two editable installs
    # never write into one tree; the copy must follow the checkout's edits and deletions.
    other_pythons = _other_pythons_script()
    root, copy = tmp_path / "checkout", tmp_path / "copy"
    (root / "pkg").mkdir(parents=True)
    (root / "pkg" / "a.py").write_text("a = 1\n")
    (root / "pkg" / "b.py").write_text("b = 1\n")
    (root / "pkg" / "_kernel.so").write_text("built here")  # ignored: not a source file
    other_pythons.sync_copy(copy, root)
    assert (copy / "pkg" / "a.py").read_text() == "a = 1\n" and not (
        copy / "pkg" / "_kernel.so"
    ).exists()
    (copy / "pkg" / "_kernel.cpython-310.so").write_text("built in the copy")
    (root / "pkg" / "a.py").write_text("a = 22\n")
    (root / "pkg" / "b.py").unlink()
    other_pythons.sync_copy(copy, root)
    assert (copy / "pkg" / "a.py").read_text() == "a = 22\n" and not (
        copy / "pkg" / "b.py"
    ).exists()
    assert (copy / "pkg" / "_kernel.cpython-310.so").read_text() == "built in the copy"
    # In a git checkout, the files git sees: tracked and untracked ones, not the ignored ones.
    names = {str(name) for name in other_pythons.source_files(ROOT)}
    assert "scripts/other_pythons.py" in names and "pyproject.toml" in names
    assert not any(name.startswith((".venv", "build/")) or name.endswith(".so") for name in names)


def test_the_newest_other_python_checks_the_wheel_and_this_one_does_where_none_is_found():
    other_pythons = _other_pythons_script()
    found = {"3.13": Path("/py313"), "3.10": Path("/py310")}
    lanes = other_pythons.choose_lanes(found)
    assert lanes["3.13"] == (Path("/py313"), other_pythons.check_wheel)
    assert lanes["3.10"] == (Path("/py310"), other_pythons.check)
    assert (
        other_pythons.choose_lanes({"3.10": Path("/py310")})["3.10"][1] is other_pythons.check_wheel
    )
    assert other_pythons.choose_lanes({}) == {
        "wheel": (Path(sys.executable), other_pythons.check_wheel)
    }
