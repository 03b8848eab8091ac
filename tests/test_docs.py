"""Every command in README.md and docs/*.md: it parses into a valid configuration (fast), and it
runs as written in the folder the documents assume (slow).

The documents' examples run in a folder where ``dvpmvs demo out=dvpmvs_demo`` (``make demo``) has
left the embedded scene. Commands that cannot run here are listed in ``NOT_RUN`` with the reason;
commands that need the reference tools (``$PEERS``) or the Strecha photos (``DVPMVS_FOUNTAIN``, the
folder holding ``fountain-P11``) run only where those are given. The benchmark commands render
800x600 scenes and run for hours: here they run on 160x120 scenes of 4 views and one scene per
sweep (``_shrunk``), the same command otherwise. README.md's examples are run by test_readme.py.
"""

from __future__ import annotations

import os
import re
import shlex
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]

# A documented command that matches one of these is not run here, for the reason given.
NOT_RUN = {
    r"^make ": "sets the checkout up: what .ci/run does on a clean clone",
    r"pip install": "installs packages",
    r"^(apt-get|git clone|mkdir|cmake) ": "builds the reference tools outside the repository",
    r"^dask (scheduler|worker) ": "starts a cluster's daemons",
    r"executor\.scheduler_file=/shared/": "needs a running Dask cluster",
    r"hydra/launcher=submitit_slurm": "needs a SLURM cluster",
    r"^dvpmvs compare ": "builds other commits, each in its own environment "
                        "(tests/evaluation/test_compare.py runs the command on this checkout)",
    r"metric=tanks": "needs a Tanks and Temples scene (downloaded)",
}
# Run only where what they need is given.
NEEDS_PEERS = r"\$PEERS/"                  # OpenMVS, the official ETH3D evaluator: $PEERS
NEEDS_FOUNTAIN = r"fountain-P11|fountain_ws|fountain_project/dense"   # the Strecha photos: $DVPMVS_FOUNTAIN


def code_blocks(doc: Path, language: str = "bash") -> list[str]:
    """The text of a document's fenced blocks of ``language``, in order."""
    return re.findall(rf"^```{language}\n(.*?)^```", doc.read_text(), re.M | re.S)


def block_commands(block: str) -> list[str]:
    """The shell commands of a block: continuation lines joined, comments and blank lines dropped."""
    commands = []
    for line in block.replace("\\\n", " ").splitlines():
        words = shlex.split(line, comments=True)
        if words:
            commands.append(_join(words))
    return commands


def documented_commands(doc: Path) -> list[str]:
    """The shell commands of a document's ``bash`` blocks."""
    return [command for block in code_blocks(doc) for command in block_commands(block)]


def _join(words: list[str]) -> str:
    """A command line from its words, quoted where the shell needs it; variables (``$PEERS``),
    globs (``multirun/bench-*``) and ``&&`` / ``&`` are left for the shell, as the documents mean."""
    return " ".join(word if word in ("&&", "&") or re.fullmatch(r"[\w@%+=:,./$*-]+", word) else shlex.quote(word)
                    for word in words)


def _not_run_reason(command: str) -> str | None:
    return next((reason for pattern, reason in NOT_RUN.items() if re.search(pattern, command)), None)


def test_every_documented_command_is_one_this_test_knows():
    """A command is run here (a dvpmvs, dvpmvs module or COLMAP command), or listed with why not."""
    for doc in DOCS:
        for command in documented_commands(doc):
            if _not_run_reason(command):
                continue
            words = shlex.split(command)
            assert words[0] in ("dvpmvs", "colmap") or words[:3] == ["python", "-m", words[2]] \
                and words[2].startswith("dvpmvs."), f"{doc.name}: {command}"


# -- the configurations --------------------------------------------------------------------------

HYDRA_SUBCOMMANDS = ("dense", "fuse", "reconstruct", "mesh", "eval", "bench", "synth", "import", "submit", "demo")


def _jobs(overrides: list[str]) -> list[list[str]]:
    """Jobs of a sweep that together take every swept value (the i-th job the i-th value of each
    sweep, cycling): each value is checked with the command's other overrides, without the whole
    cartesian product (the values of different sweeps do not depend on each other)."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    parsed = OverridesParser.create().parse_overrides(overrides)
    choices = []
    for text, override in zip(overrides, parsed):
        if override.is_sweep_override():
            key = override.get_key_element()
            choices.append([f"{key}={value}" for value in override.sweep_string_iterator()])
        else:
            choices.append([text])
    return [[values[i % len(values)] for values in choices] for i in range(max(map(len, choices), default=1))]


def _hydra_commands() -> list[tuple[str, str, list[str]]]:
    found = []
    for doc in DOCS:
        for command in documented_commands(doc):
            words = shlex.split(command)
            if words[0] == "dvpmvs" and len(words) > 1 and words[1] in HYDRA_SUBCOMMANDS:
                # Hydra's own settings (launchers, folders) are Hydra's to check when it runs.
                overrides = [w for w in words[2:] if w not in ("-m", "--multirun", "--help", "-h")
                             and not w.startswith(("hydra/", "hydra."))]
                found.append((doc.name, words[1], overrides))
    return found


def test_every_documented_dvpmvs_command_composes_into_valid_options():
    """Each job of each documented command: its overrides name existing keys and groups, and the
    options objects the subcommand builds accept their values (a renamed or retired option in a
    document fails here)."""
    from hydra import compose, initialize_config_module
    from hydra.core.global_hydra import GlobalHydra

    from dvpmvs import config, registry

    checked = set()
    GlobalHydra.instance().clear()
    with initialize_config_module(config_module="dvpmvs.conf", version_base=None):
        for doc, subcommand, overrides in _hydra_commands():
            for job in _jobs(overrides):
                if (subcommand, tuple(job)) in checked:
                    continue
                checked.add((subcommand, tuple(job)))
                try:
                    cfg = compose(config_name=subcommand, overrides=[*registry.plugin_search_path(), *job])
                    if subcommand in ("dense", "bench", "demo", "reconstruct"):
                        config.dense_options(cfg)
                        config.executor_options(cfg)
                    if subcommand in ("dense", "bench", "reconstruct"):
                        config.workspace_options(cfg)
                    if subcommand == "reconstruct":
                        config.sfm_options(cfg)
                    if subcommand in ("reconstruct", "mesh"):
                        config.meshing_options(cfg)
                    if subcommand == "fuse":
                        config.fusion_options(cfg, str(cfg.input_type))
                except Exception as exc:  # noqa: BLE001 - the message names the document and the job
                    pytest.fail(f"{doc}: dvpmvs {subcommand} {' '.join(job)}\n{exc}")
    GlobalHydra.instance().clear()
    assert len(checked) > 50


# -- running them --------------------------------------------------------------------------------

SHRUNK_WIDTH, SHRUNK_VIEWS = 160, 4


def _shrunk(command: str) -> str:
    """A benchmark command at a size that runs in seconds: 160x120 scenes of 4 views, one scene per
    sweep, two estimator seeds instead of three (still folded into a mean and a spread), one where
    the sweep has three or more values of another option (each value is a code path to run; a
    second seed of each adds nothing), and the folders named after that size; the experiments'
    scripts on small grids."""
    words = shlex.split(command)
    if words[:2] in (["dvpmvs", "bench"], ["dvpmvs", "synth"]):
        words = [re.sub(r"^width=\d+$", f"width={SHRUNK_WIDTH}", w) for w in words]
        words = [re.sub(r"^views=\d+$", f"views={SHRUNK_VIEWS}", w) for w in words]
        if not any(w.startswith("hydra.sweep.dir=") for w in words):  # else a later command names its jobs
            words = [re.sub(r"^scene=room,facade,tabletop$", "scene=room", w) for w in words]
        many = any(w.count(",") >= 2 and not w.startswith(("seed=", "scene=")) for w in words)
        words = [re.sub(r"^seed=0,1,2$", "seed=0" if many else "seed=0,1", w) for w in words]
        if words[1] == "bench" and not any(w.startswith("views=") for w in words):
            words.append(f"views={SHRUNK_VIEWS}")
    if words[:3] == ["python", "-m", "dvpmvs.evaluation.experiments.mesh_quality"]:
        # One configuration per mesher, sampled every 2 cm: the ten at 5 mm took a quarter of the run.
        words += ["--depths", "9", "--trim-quantiles", "0.05", "--colmap-trims", "7", "--spacing", "0.02"]
    if words[:3] == ["python", "-m", "dvpmvs.evaluation.experiments.scale"]:
        words += ["--views", "6", "--width", "96"]
    if words[:3] == ["python", "-m", "dvpmvs.evaluation.experiments.openmvs_suite"]:
        words += ["--width", str(SHRUNK_WIDTH), "--views", str(SHRUNK_VIEWS), "--scenes", "room"]
    words = [re.sub(r"_8v_800_", f"_{SHRUNK_VIEWS}v_{SHRUNK_WIDTH}_", w) for w in words]
    return _join(words)


@pytest.fixture(scope="module")
def demo_folder(tmp_path_factory):
    """The embedded scene as `make demo` leaves it, and the tiny ONNX networks the documents'
    learned-prior examples name (models/*.onnx: the interfaces of the real ones, not their weights)."""
    from onnx_models import IMAGENET_MEAN, IMAGENET_STD, affine_red_model, constant_normal_model, highlight_model

    folder = tmp_path_factory.mktemp("demo")
    subprocess.run([sys.executable, "-m", "dvpmvs.cli", "demo", "out=dvpmvs_demo", "progress=false"], cwd=folder,
                   check=True, capture_output=True)
    models = folder / "models"
    models.mkdir()
    # Metric depth inside the demo's depth range; a relative one that rises with depth there.
    affine_red_model(models / "da2_vits.onnx", 0.01 * IMAGENET_STD[0], 4.0 + 0.01 * IMAGENET_MEAN[0])
    affine_red_model(models / "net.onnx", -IMAGENET_STD[0], 5.0 - IMAGENET_MEAN[0])
    constant_normal_model(models / "metric3d_vit_small.onnx", [0.0, 0.0, -1.0])
    highlight_model(models / "jshdr.onnx")
    return folder


def _playground(demo_folder: Path, path: Path) -> Path:
    """A folder for one document's commands: the demo's copy, the models, and what the document
    says to bring (the tutorial's photos: the demo's five images, as it suggests; its COLMAP
    project's photos and sparse model; its ground-truth scan)."""
    shutil.copytree(demo_folder, path, symlinks=True)
    (path / "fountain").mkdir()
    (path / "fountain" / "images").symlink_to(path / "dvpmvs_demo" / "images")
    (path / "photos").symlink_to(path / "dvpmvs_demo" / "images")
    (path / "sparse").mkdir()
    (path / "sparse" / "0").symlink_to(path / "dvpmvs_demo" / "sparse")
    for entry in (path / "dvpmvs_demo" / "ground_truth").iterdir():
        if entry.name in ("scan_alignment.mlp", "scans", "eth3d_parameters.json"):
            (path / entry.name).symlink_to(entry)
    fountain = os.environ.get("DVPMVS_FOUNTAIN")
    if fountain:
        (path / "fountain-P11").symlink_to(Path(fountain).resolve() / "fountain-P11")
        (path / "docs" / "images").mkdir(parents=True)
    return path


def _skip_reason(command: str) -> str | None:
    reason = _not_run_reason(command)
    if reason:
        return reason
    if re.search(NEEDS_PEERS, command) and not os.environ.get("PEERS"):
        return "needs the reference tools ($PEERS)"
    if re.search(NEEDS_FOUNTAIN, command) and not os.environ.get("DVPMVS_FOUNTAIN"):
        return "needs the Strecha fountain-P11 photos ($DVPMVS_FOUNTAIN)"
    if command.startswith("colmap ") and shutil.which("colmap") is None:
        return "COLMAP's own program is not installed (make test installs it where apt can)"
    return None


@pytest.mark.slow
@pytest.mark.parametrize("doc", [d.name for d in DOCS if d.name != "README.md" and documented_commands(d)])
def test_every_command_of_the_document_runs(doc, demo_folder, tmp_path):
    folder = _playground(demo_folder, tmp_path / "play")
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}", "CI": "true"}
    ran, skipped = [], []
    for command in documented_commands(ROOT / "docs" / doc):
        reason = _skip_reason(command)
        if reason:
            skipped.append(f"{command[:60]}: {reason}")
            continue
        command = _shrunk(command)
        start = time.perf_counter()
        done = subprocess.run(["bash", "-c", command], cwd=folder, env=env, capture_output=True, text=True)
        assert done.returncode == 0, f"{doc}: {command}\n{done.stdout[-2000:]}\n{done.stderr[-4000:]}"
        ran.append(f"{time.perf_counter() - start:6.1f} s  {command[:100]}")
    # Each command's seconds, so that the longest test's time can be traced to its commands.
    print(f"{doc}: {len(ran)} ran, {len(skipped)} not run", *ran, *skipped, sep="\n  ")
