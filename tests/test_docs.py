"""Every command in README.md and docs/*.md: it parses into a valid configuration (fast), and it
runs as written in the folder the documents assume (slow).

The documents' examples run in a folder where ``dvpmvs demo out=dvpmvs_demo`` (``make demo``) has
left the embedded scene. Commands that cannot run here are listed in ``NOT_RUN`` with the reason;
commands that need the reference tools (``$PEERS``) or the Strecha photos (``DVPMVS_FOUNTAIN``, the
folder holding ``fountain-P11``) run only where those are given. The benchmark commands render
800x600 scenes and run for hours: here they run on 64x48 scenes of 3 views and one scene per sweep,
and the commands on the demo at 64 px (``_shrunk``), the same command otherwise. The demo
is run once for the whole suite (the ``demo_run`` fixture) and copied into each document's folder.
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

from dvpmvs.options import MIN_IMAGE_SIZE
from tests.helpers import (
    DOCS,
    README,
    ROOT,
    block_commands,
    code_blocks,
    documented_commands,
    join_words,
    shell,
)

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
    r"^gcc .*scripts/kernel_layouts\.c": "compiles the kernel layouts' timing program "
    "(tests/patchmatch/test_kernel_layouts.py builds and runs it)",
}
# Run only where what they need is given.
NEEDS_PEERS = r"\$PEERS/"  # OpenMVS, the official ETH3D evaluator: $PEERS
# the Strecha photos: $DVPMVS_FOUNTAIN
NEEDS_FOUNTAIN = r"fountain-P11|fountain_ws|fountain_project/dense"
# a 7-Scenes sequence: the shared redkitchen frames, where this checkout has ../shared beside it
NEEDS_KITCHEN = r"7scenes-redkitchen|kitchen_ws"
KITCHEN = Path(__file__).resolve().parents[2] / "shared" / "data" / "7scenes-redkitchen"


def _not_run_reason(command: str) -> str | None:
    return next(
        (reason for pattern, reason in NOT_RUN.items() if re.search(pattern, command)), None
    )


def test_every_documented_command_is_one_this_test_knows():
    """A command is run here (a dvpmvs, dvpmvs module or COLMAP command), or listed with why not."""
    for doc in DOCS:
        for command in documented_commands(doc):
            if _not_run_reason(command):
                continue
            words = shlex.split(command)
            assert (
                words[0] in ("dvpmvs", "colmap")
                or words[:3] == ["python", "-m", words[2]]
                and words[2].startswith("dvpmvs.")
            ), f"{doc.name}: {command}"


# -- the configurations --------------------------------------------------------------------------

HYDRA_SUBCOMMANDS = (
    "dense",
    "fuse",
    "reconstruct",
    "mesh",
    "eval",
    "bench",
    "synth",
    "import",
    "submit",
    "demo",
)


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
    return [
        [values[i % len(values)] for values in choices]
        for i in range(max(map(len, choices), default=1))
    ]


def _hydra_commands() -> list[tuple[str, str, list[str]]]:
    found = []
    for doc in DOCS:
        for command in documented_commands(doc):
            words = shlex.split(command)
            if words[0] == "dvpmvs" and len(words) > 1 and words[1] in HYDRA_SUBCOMMANDS:
                # Hydra's own settings (launchers, folders) are Hydra's to check when it runs.
                overrides = [
                    w
                    for w in words[2:]
                    if w not in ("-m", "--multirun", "--help", "-h")
                    and not w.startswith(("hydra/", "hydra."))
                ]
                found.append((doc.name, words[1], overrides))
    return found


@pytest.mark.slow
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
                    cfg = compose(
                        config_name=subcommand, overrides=[*registry.plugin_search_path(), *job]
                    )
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

SHRUNK_WIDTH, SHRUNK_VIEWS = 64, 3
# The demo's 320x240 views are matched at this size by the commands on its workspace or photos
# (the documents' photo folders are the demo's images in their folders: _playground; ``ws`` is
# the tutorial's workspace undistorted from them).
DEMO_SIZE, DEMO_MATCH_SIZE = 320, 64
SHRUNK_MESH_DEPTH = 8
DEMO_PHOTOS = ("dvpmvs_demo/images", "fountain/images", "photos")
DEMO_WORKSPACES = ("dvpmvs_demo", "ws")


def _matched(sizes: list[int]) -> list[int]:
    """The longest sides the demo is matched at for those a command asks: scaled as the demo's, at
    least the smallest size accepted, and still distinct (a sweep over sizes stays one)."""
    matched = []
    for size in sizes:
        scaled = max(MIN_IMAGE_SIZE, min(size, DEMO_SIZE) * DEMO_MATCH_SIZE // DEMO_SIZE)
        matched.append(max([scaled] + [m + 8 for m in matched]))
    return matched


def _extremes(word: str) -> str:
    """A sweep over three or more numbers of one option, or over three or more methods: its first
    and last (every number runs the same code; each method is a preset of switches that other
    tests run, and the composition test checks each value)."""
    key, _, values = word.partition("=")
    items = values.split(",")
    numbers = all(re.fullmatch(r"-?[\d.]+", v) for v in items) and key not in ("seed", "scene_seed")
    if len(items) > 2 and (numbers or key == "method"):
        return f"{key}={items[0]},{items[-1]}"
    return word


def _shrunk(command: str) -> str:
    """A command at a size that runs in seconds, the same command otherwise.

    Benchmark commands: 64x48 scenes of 3 views (a sweep over sizes on 64, 72, ... px), one scene
    per sweep, a sweep over three or more numbers of an option or over three or more methods on its
    first and last (``_extremes``), two estimator seeds instead of three (still folded into a mean
    and a spread) where the sweep has one job per seed and one seed where it has more (each job is
    a code path to run; a second seed of each adds nothing), and the folders named after that size;
    the experiments' scripts on small grids (the metric's speed benchmark on 100,000 points of a
    128 px scene, the workspace's on a tenth of its views and points). Commands on the demo's
    workspace or photos match at 64 px (``max_image_size=64``, or each size the command gives
    scaled as 320 to 64, see ``_matched``), and their meshes are Poisson's of depth 8 at most."""
    words = shlex.split(command)
    if words[:2] in (["dvpmvs", "bench"], ["dvpmvs", "synth"]):
        # a sweep over sizes stays one, over distinct small sizes
        words = [
            re.sub(
                r"^width=[\d,]+$",
                lambda m: (
                    "width="
                    + ",".join(str(SHRUNK_WIDTH + 8 * i) for i in range(m.group(0).count(",") + 1))
                ),
                w,
            )
            for w in words
        ]
        words = [re.sub(r"^views=\d+$", f"views={SHRUNK_VIEWS}", w) for w in words]
        if not any(
            w.startswith("hydra.sweep.dir=") for w in words
        ):  # else a later command names its jobs
            words = [re.sub(r"^scene=room,facade,tabletop$", "scene=room", w) for w in words]
        words = [_extremes(w) for w in words]
        words = [
            re.sub(r"^seed=0,1(,2)?$", "seed=0" if _other_jobs(words) > 1 else "seed=0,1", w)
            for w in words
        ]
        if words[1] == "bench" and not any(w.startswith("views=") for w in words):
            words.append(f"views={SHRUNK_VIEWS}")
    on_the_demo = any(
        w in [f"workspace={p}" for p in DEMO_WORKSPACES]
        or w in [f"images={p}" for p in DEMO_PHOTOS]
        for w in words
    )
    if words[:2] == ["dvpmvs", "dense"]:
        words = [_extremes(w) if w.startswith("method=") else w for w in words]
    if (
        words[:2] in (["dvpmvs", "dense"], ["dvpmvs", "fuse"], ["dvpmvs", "reconstruct"])
        and on_the_demo
    ):
        sizes = [w for w in words if w.startswith("max_image_size=")]
        if sizes:
            matched = ",".join(
                map(str, _matched([int(v) for v in sizes[0].split("=")[1].split(",")]))
            )
            words = [f"max_image_size={matched}" if w == sizes[0] else w for w in words]
        else:
            words.append(f"max_image_size={DEMO_MATCH_SIZE}")
    if words[:2] in (["dvpmvs", "mesh"], ["dvpmvs", "reconstruct"]):
        # Poisson's octree at most 8 deep: the documents' clouds come from the demo matched small
        given = [int(w.split("=")[1]) for w in words if w.startswith("meshing.depth=")]
        words = [w for w in words if not w.startswith("meshing.depth=")]
        words.append(f"meshing.depth={min(given + [SHRUNK_MESH_DEPTH])}")
    if words[:3] == ["python", "-m", "dvpmvs.evaluation.bench_metric"]:
        words[3] = str(
            min(int(words[3]), 100_000)
        )  # its points: the speed of 1 M is a figure, not a check
        words += ["--width", str(SHRUNK_WIDTH * 2)]
    if words[:3] == ["python", "-m", "dvpmvs.evaluation.experiments.mesh_quality"]:
        # One configuration per mesher, sampled every 2 cm: the ten at 5 mm took a quarter of the run.
        words += [
            "--depths",
            "8",
            "--trim-quantiles",
            "0.05",
            "--colmap-trims",
            "7",
            "--spacing",
            "0.02",
        ]
    if words[:3] == ["python", "-m", "dvpmvs.evaluation.experiments.scale"]:
        words += ["--views", "4", "--width", str(SHRUNK_WIDTH)]
    if words[:3] == ["python", "-m", "dvpmvs.evaluation.bench_workspace"]:
        # a speed benchmark of opening a workspace: a tenth of its views and points show it runs
        words = [
            str(max(1, int(w) // 10)) if i and words[i - 1] in ("--views", "--points") else w
            for i, w in enumerate(words)
        ]
    if words[:3] == ["python", "-m", "dvpmvs.evaluation.experiments.rgbd_clips"]:
        # one clip, one seed, the fast preset beside OpenMVS: the script's path, not its figures
        words += ["--starts", "0", "--seeds", "0", "--configs", "quality=fast"]
    if words[:3] == ["python", "-m", "dvpmvs.evaluation.experiments.openmvs_suite"]:
        words += ["--width", str(SHRUNK_WIDTH), "--views", str(SHRUNK_VIEWS), "--scenes", "room"]
    words = [re.sub(r"_8v_800_", f"_{SHRUNK_VIEWS}v_{SHRUNK_WIDTH}_", w) for w in words]
    return join_words(words)


def _other_jobs(words: list[str]) -> int:
    """The jobs of a sweep per estimator seed: the product of the other overrides' value counts."""
    jobs = 1
    for word in words[2:]:
        if "=" in word and not word.startswith(("seed=", "hydra.")):
            jobs *= word.count(",") + 1
    return jobs


def _shrunk_python(block: str) -> str:
    """A Python example at the size the commands on the demo match at (``_shrunk``): the API's
    dense and fusion calls get ``max_image_size`` in their overrides (fusion reads the maps at the
    size they were computed at)."""
    size = f'"max_image_size={DEMO_MATCH_SIZE}"'
    shrunk = block.replace("overrides=[", f"overrides=[{size}, ")
    shrunk = re.sub(
        r"(dvpmvs\.(?:patch_match_stereo|stereo_fusion)\((?:(?!overrides=)[^()])*)\)",
        rf"\1, overrides=[{size}])",
        shrunk,
    )
    assert "max_image_size" in shrunk, (
        "the example calls neither patch_match_stereo nor stereo_fusion"
    )
    return shrunk


@pytest.fixture(scope="session")
def demo_folder(demo_run, tmp_path_factory):
    """The embedded scene as `make demo` leaves it, and the tiny ONNX networks the documents'
    learned-prior examples name (models/*.onnx: the interfaces of the real ones, not their weights)."""
    from tests.onnx_models import constant_normal_model, highlight_model, row_ramp_model

    assert demo_run.returncode == 0, demo_run.stderr[-3000:]
    folder = tmp_path_factory.mktemp("demo")
    shutil.copytree(demo_run.cwd / "dvpmvs_demo", folder / "dvpmvs_demo", symlinks=True)
    models = folder / "models"
    models.mkdir()
    # Relative inverse depth at the preset's input size and a relative depth at the documented
    # command's, each following the demo's rooms (far at the top, the floor near at the bottom).
    row_ramp_model(models / "da2_vits.onnx", 518, 518, 0.2, 0.6)
    row_ramp_model(models / "net.onnx", 384, 512, 3.0, 1.0)
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
    if KITCHEN.is_dir():
        (path / "7scenes-redkitchen").symlink_to(KITCHEN)
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
    if re.search(NEEDS_KITCHEN, command) and not KITCHEN.is_dir():
        return f"needs the 7-Scenes redkitchen frames ({KITCHEN})"
    if command.startswith("colmap ") and shutil.which("colmap") is None:
        return "COLMAP's own program is not installed (make test installs it where apt can)"
    return None


def _document_env() -> dict:
    return {
        **os.environ,
        "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}",
        "CI": "true",
    }


def _run_documented(doc: str, command: str, folder: Path, env: dict) -> str:
    """Run one command (shrunk) in ``folder`` as a shell would; its seconds and text."""
    command = _shrunk(command)
    start = time.perf_counter()
    done = shell(command, folder, env)
    assert done.returncode == 0, f"{doc}: {command}\n{done.stdout[-2000:]}\n{done.stderr[-4000:]}"
    return f"{time.perf_counter() - start:6.1f} s  {command[:100]}"


@pytest.mark.slow
@pytest.mark.parametrize(
    "doc", [d.name for d in DOCS if d.name != "README.md" and documented_commands(d)]
)
def test_every_command_of_the_document_runs(doc, demo_folder, tmp_path):
    folder = _playground(demo_folder, tmp_path / "play")
    env = _document_env()
    ran, skipped = [], []
    for command in documented_commands(ROOT / "docs" / doc):
        reason = _skip_reason(command)
        if reason:
            skipped.append(f"{command[:60]}: {reason}")
            continue
        ran.append(_run_documented(doc, command, folder, env))
    # Each command's seconds, so that the longest test's time can be traced to its commands.
    print(f"{doc}: {len(ran)} ran, {len(skipped)} not run", *ran, *skipped, sep="\n  ")


# -- README.md -------------------------------------------------------------------------------------


def test_the_readme_names_its_two_commands_first():
    first = block_commands(code_blocks(README)[0])
    assert [shlex.split(c, comments=True) for c in first] == [["make", "demo"], ["make", "test"]]


@pytest.mark.slow
def test_every_readme_example_runs_as_written(demo_folder, tmp_path):
    """Each example after the two commands, in the folder `make demo` leaves, and its Python."""
    folder = _playground(demo_folder, tmp_path / "play")
    env = _document_env()
    ran = []
    for block in code_blocks(README)[1:]:
        for command in block_commands(block):
            reason = _skip_reason(command)
            if reason:
                assert command.startswith("colmap "), (
                    command
                )  # an optional client; the rest always runs
                continue
            assert shlex.split(command)[0] in ("dvpmvs", "colmap"), command
            _run_documented("README.md", command, folder, env)
            ran.append(shlex.split(command)[:2])
    for number, block in enumerate(code_blocks(README, "python")):
        # Saved as a script, as a reader would run it: a child process re-runs a script's file
        # (multiprocessing's spawn), which ``python -c`` does not have.
        script = folder / f"readme_example_{number}.py"
        script.write_text(_shrunk_python(block))
        done = subprocess.run(
            [sys.executable, str(script)],
            cwd=folder,
            env=env,
            capture_output=True,
            text=True,
        )
        assert done.returncode == 0, f"{block}\n{done.stderr[-3000:]}"
        assert "maps;" in done.stdout and "triangles" in done.stdout
    assert ["dvpmvs", "reconstruct"] in ran and ["dvpmvs", "bench"] in ran
    assert (folder / "runs" / "fast" / "fused.ply").is_file()
    assert (folder / "runs" / "project" / "dense" / "meshed-poisson.ply").is_file()
    assert (
        (folder / "runs" / "submission" / "high_res_multi_view" / "courtyard.txt")
        .read_text()
        .startswith("runtime")
    )
