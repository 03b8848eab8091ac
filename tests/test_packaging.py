"""`pip install dvpmvs` alone gives a working default; the [onnx] extra adds the learned presets.

A fresh virtual environment gets the wheel built from this tree (what `pip install .` installs),
without the plugins folder on any path and without the extras: the demo runs end to end. The
same wheel with [onnx] adds ONNX Runtime, and with it the learned presets.
"""

import subprocess
import sys
import venv
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _run(args, cwd, timeout=1800):
    run = subprocess.run([str(a) for a in args], cwd=cwd, capture_output=True, text=True, timeout=timeout)
    assert run.returncode == 0, f"{' '.join(map(str, args))}\n{run.stdout[-3000:]}\n{run.stderr[-3000:]}"
    return run


def test_every_package_of_the_tree_is_in_the_wheels_package_list():
    # pyproject.toml lists the packages by hand (the harness and the configs are installed under
    # dvpmvs.*): a new subpackage missing from the list installs as an import error.
    try:
        import tomllib
    except ModuleNotFoundError:  # Python 3.10
        pytest.skip("tomllib is Python 3.11's")
    setuptools = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    found = set()
    for name, folder in setuptools["package-dir"].items():
        for init in (ROOT / folder).rglob("__init__.py"):
            found.add(".".join([name, *init.parent.relative_to(ROOT / folder).parts]))
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
    assert {"dvpmvs.patchmatch._patchmatch", "dvpmvs._fusion", "dvpmvs.evaluation._accuracy",
            "dvpmvs.evaluation.experiments.scale", "dvpmvs_onnx.providers"} <= set(names)


@pytest.mark.slow
def test_the_core_alone_runs_the_demo_and_the_onnx_extra_adds_the_learned_presets(tmp_path):
    wheels = tmp_path / "wheels"
    _run([sys.executable, "-m", "pip", "wheel", "--quiet", "--no-deps", "--wheel-dir", wheels, ROOT], cwd=tmp_path)
    (wheel,) = wheels.glob("dvpmvs-*.whl")
    env = tmp_path / "venv"
    venv.create(env, with_pip=True)
    python = env / "bin" / "python"
    constraints = ["-c", ROOT / "constraints.txt"] if sys.version_info[:2] == (3, 11) else []
    _run([python, "-m", "pip", "install", "--quiet", *constraints, wheel], cwd=tmp_path)
    freeze = _run([python, "-m", "pip", "list", "--format=freeze"], cwd=tmp_path).stdout.lower().split()
    installed = {line.split("==")[0] for line in freeze}
    assert not installed & {"onnxruntime", "matplotlib", "dvpmvs-classic", "dvpmvs-onnx"}, sorted(installed)
    # Run outside the source tree, so that nothing is imported from it.
    # The fast preset: each stage of the demo; the default's figures are the main suite's to check.
    demo = _run([env / "bin" / "dvpmvs", "demo", f"out={tmp_path / 'demo'}", "quality=fast"], cwd=tmp_path)
    assert (tmp_path / "demo" / "fused.ply").is_file() and (tmp_path / "demo" / "fused.ply.vis").is_file()
    # the report's scripts are package data: the page works from the installed package's copy
    assert (tmp_path / "demo" / "report.html").is_file()
    assert all((tmp_path / "demo" / "report_files" / name).is_file()
               for name in ("three.bundle.js", "LICENSE.three.txt", "viewer.js", "report.css", "cloud.js"))
    assert "fused cloud" in demo.stderr + demo.stdout and "pip install 'dvpmvs[eval]'" in demo.stderr + demo.stdout
    plugins = _run([env / "bin" / "dvpmvs", "plugins"], cwd=tmp_path).stdout
    assert "coarse_mvs" in plugins and "colmap_cfg" in plugins
    presets = [env / "bin" / "dvpmvs", "dense", "workspace=x", "depth_prior=depth_anything_v2",
               "normal_prior=metric3dv2", "--cfg", "job"]
    missing = subprocess.run([str(a) for a in presets], cwd=tmp_path, capture_output=True, text=True)
    assert missing.returncode != 0 and "Could not find" in missing.stderr
    _run([python, "-m", "pip", "install", "--quiet", *constraints, f"{wheel}[onnx]"], cwd=tmp_path)
    config = _run(presets, cwd=tmp_path).stdout
    assert "preset: depth_anything_v2" in config and "preset: metric3dv2" in config


def _other_pythons_script():
    """scripts/other_pythons.py as a module (a script, not part of the package)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("other_pythons", ROOT / "scripts" / "other_pythons.py")
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
    assert not other_pythons.run([sys.executable, "-m", "pip", "install", "--no-index", "--quiet",
                                  "dvpmvs-no-such-package"], log)
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
    assert (copy / "pkg" / "a.py").read_text() == "a = 1\n" and not (copy / "pkg" / "_kernel.so").exists()
    (copy / "pkg" / "_kernel.cpython-310.so").write_text("built in the copy")
    (root / "pkg" / "a.py").write_text("a = 22\n")
    (root / "pkg" / "b.py").unlink()
    other_pythons.sync_copy(copy, root)
    assert (copy / "pkg" / "a.py").read_text() == "a = 22\n" and not (copy / "pkg" / "b.py").exists()
    assert (copy / "pkg" / "_kernel.cpython-310.so").read_text() == "built in the copy"
    # In a git checkout, the files git sees: tracked and untracked ones, not the ignored ones.
    names = {str(name) for name in other_pythons.source_files(ROOT)}
    assert "scripts/other_pythons.py" in names and "pyproject.toml" in names
    assert not any(name.startswith((".venv", "build/")) or name.endswith(".so") for name in names)
