"""The `dvpmvs` command as a user types it (run in a subprocess, as from a shell)."""

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from tests.helpers import dvpmvs
from tests.scenes import make_workspace


def test_console_script_is_installed():
    # pip puts console scripts beside the interpreter of the environment it installs into.
    beside = Path(sys.executable).parent / "dvpmvs"
    exe = str(beside) if beside.exists() else shutil.which("dvpmvs")
    assert exe is not None, "the console script `dvpmvs` is not installed"
    result = subprocess.run([exe, "--version"], capture_output=True, text=True)
    assert result.returncode == 0 and result.stdout.startswith("dvpmvs ")


_OPENBLAS_THREADS = """
import ctypes
import dvpmvs.cli, numpy, scipy.spatial
counts = set()
for path in {line.split()[-1] for line in open("/proc/self/maps") if "openblas" in line.lower()}:
    library = ctypes.CDLL(path)
    for name in ("scipy_openblas_get_num_threads64_", "scipy_openblas_get_num_threads",
                 "openblas_get_num_threads64_", "openblas_get_num_threads"):
        if hasattr(library, name):
            counts.add(getattr(library, name)())
print(sorted(counts))
"""


@pytest.mark.skipif(
    not Path("/proc/self/maps").is_file(), reason="reads the loaded libraries from /proc"
)
def test_the_command_leaves_the_cores_to_the_kernels_unless_the_user_sets_openblas_threads(
    tmp_path,
):
    # numpy's and SciPy's OpenBLAS would start a thread per core beside the kernels' threads.
    env = {
        k: v for k, v in os.environ.items() if k not in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS")
    }
    ran = subprocess.run(
        [sys.executable, "-c", _OPENBLAS_THREADS],
        capture_output=True,
        text=True,
        cwd=tmp_path,
        env=env,
    )
    assert ran.returncode == 0 and ran.stdout.split() == ["[1]"], ran.stderr
    ran = subprocess.run(
        [sys.executable, "-c", _OPENBLAS_THREADS],
        capture_output=True,
        text=True,
        cwd=tmp_path,
        env={**env, "OPENBLAS_NUM_THREADS": "2"},
    )
    assert ran.returncode == 0 and ran.stdout.split() == ["[2]"], ran.stderr


def test_help_lists_the_subcommands(tmp_path):
    result = dvpmvs("--help", cwd=tmp_path)
    assert result.returncode == 0
    for sub in ("dense", "fuse", "eval", "demo", "plugins"):
        assert f"\n  {sub} " in result.stdout


@pytest.mark.parametrize(
    "sub,option",
    [
        ("dense", "max_image_size: -1"),
        ("fuse", "input_type: geometric"),
        ("eval", "tolerances:"),
        ("demo", "out: dvpmvs_demo"),
    ],
)
def test_subcommand_help_shows_its_options(sub, option, tmp_path):
    result = dvpmvs(sub, "--help", cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    assert f"dvpmvs {sub}:" in result.stdout
    assert option in result.stdout


def test_dense_help_shows_the_config_groups(tmp_path):
    out = dvpmvs("dense", "--help", cwd=tmp_path).stdout
    assert "view_selector: colmap_cfg, sparse_score" in out
    assert "depth_prior: coarse_mvs" in out
    assert "method: baseline, default, paper, w_o_agn, w_o_dep" in out
    assert "patch_match.anchor_visibility" in out  # the table of the paper's components


def test_unknown_subcommand(tmp_path):
    result = dvpmvs("densify", cwd=tmp_path)
    assert result.returncode == 1 and "unknown subcommand 'densify'" in result.stderr


def test_a_misspelt_option_names_the_right_one(tmp_path):
    for given, meant in (
        ("max_imge_size=1200", "max_image_size"),
        ("patch_match.num_iteration=2", "patch_match.num_iterations"),
        ("planar_prior=false", "patch_match.planar_prior"),  # a section left out
        ("depth_prior.max_siz=100", "depth_prior.max_size"),  # a plugin's options
    ):
        result = dvpmvs("dense", f"workspace={tmp_path}", given, cwd=tmp_path)
        assert result.returncode == 1
        key = given.partition("=")[0]
        assert f"unknown option {key} (did you mean {meant}?)" in result.stderr, result.stderr
        assert "Traceback" not in result.stderr and "+" + key not in result.stderr
    # In a sweep too, whichever presets it crosses.
    result = dvpmvs(
        "dense",
        "-m",
        f"workspace={tmp_path}",
        "method=default,paper",
        "patch_match.windw_radius=3",
        cwd=tmp_path,
    )
    assert "unknown option patch_match.windw_radius (did you mean patch_match.window_radius?)" in (
        result.stderr
    )
    assert list(tmp_path.iterdir()) == []  # nothing written into the current folder
    result = dvpmvs("dense", f"workspace={tmp_path}", "--workspace", "x", cwd=tmp_path)
    assert result.returncode == 1 and "unknown flag --workspace" in result.stderr
    assert "takes its options as key=value" in result.stderr


def test_colmaps_flags_are_read_as_our_options(tmp_path):
    result = dvpmvs(
        "dense",
        "--workspace_path",
        str(tmp_path),
        "--PatchMatchStereo.max_image_size",
        "800",
        "--PatchMatchStereo.geom_consistency",
        "false",
        "--StereoFusion.min_num_pixels",
        "3",
        "--PatchMatchStereo.gpu_index",
        "0",
        "--cfg",
        "job",
        cwd=tmp_path,
    )
    assert result.returncode == 0, result.stderr
    for line in (f"workspace: {tmp_path}", "max_image_size: 800", "geometric: false"):
        assert line in result.stdout
    assert "min_consistent_views: 2" in result.stdout
    assert "--PatchMatchStereo.gpu_index 0: ignored, dvpmvs runs on the CPU" in result.stderr
    result = dvpmvs(
        "dense", "--workspace_path", str(tmp_path), "--PatchMatchStereo.filter", "1", cwd=tmp_path
    )
    assert result.returncode == 1
    assert "dvpmvs always filters its maps (patch_match.filter_max_cost" in result.stderr


def test_unknown_group_option_lists_the_available_ones(tmp_path):
    result = dvpmvs("dense", f"workspace={tmp_path}", "view_selector=magic", cwd=tmp_path)
    assert result.returncode == 1
    assert (
        "Could not find 'view_selector/magic'" in result.stderr and "sparse_score" in result.stderr
    )


def test_hydra_flags_follow_overrides_that_use_a_plugins_config_group(tmp_path):
    # `depth_prior=depth_anything_v2` lives in the onnx plugin's config package; Hydra's own
    # flags after the overrides print the composed job without running it.
    result = dvpmvs(
        "dense",
        f"workspace={tmp_path}",
        "depth_prior=depth_anything_v2",
        "--cfg",
        "job",
        cwd=tmp_path,
    )
    assert result.returncode == 0, result.stderr
    assert (
        "preset: depth_anything_v2" in result.stdout and f"workspace: {tmp_path}" in result.stdout
    )
    assert list(tmp_path.iterdir()) == []  # printed, not run
    result = dvpmvs("dense", f"workspace={tmp_path}", "--info", "searchpath", cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    assert "pkg://dvpmvs_onnx.conf" in result.stdout


def test_compose_api_sees_the_plugins_config_groups_through_the_registry():
    # Python users and notebooks compose configs without the CLI; the registry names the plugins'
    # config packages for them.
    from hydra import compose, initialize_config_module

    from dvpmvs.registry import plugin_search_path

    assert plugin_search_path() == [
        "hydra.searchpath=[pkg://dvpmvs_classic.conf,pkg://dvpmvs.evaluation.conf,"
        "pkg://dvpmvs_onnx.conf]"
    ]
    with initialize_config_module(config_module="dvpmvs.conf", version_base=None):
        cfg = compose(
            "dense",
            overrides=[*plugin_search_path(), "workspace=unused", "normal_prior=metric3dv2"],
        )
        # The harness's options come with its config package; the core's dense has none.
        bare = compose(
            "dense",
            overrides=["hydra.searchpath=[pkg://dvpmvs_classic.conf]", "workspace=unused"],
        )
    assert cfg.normal_prior.name == "onnx" and cfg.normal_prior.preset == "metric3dv2"
    assert cfg.evaluate.ground_truth == "auto" and "evaluate" not in bare


def test_missing_workspace_option_and_bad_path_are_clear_errors(tmp_path):
    result = dvpmvs("dense", cwd=tmp_path)
    assert result.returncode == 1 and "missing required option workspace=" in result.stderr
    result = dvpmvs("dense", f"workspace={tmp_path / 'nope'}", cwd=tmp_path)
    assert result.returncode == 1 and "workspace folder not found" in result.stderr
    assert "Traceback" not in result.stderr


def test_dense_writes_maps_and_the_fused_cloud(tmp_path):
    root = tmp_path / "ws"
    make_workspace(root)
    # Spelled as COLMAP's patch_match_stereo takes it, where ours means the same.
    result = dvpmvs(
        "dense",
        "--workspace_path",
        str(root),
        "--PatchMatchStereo.max_image_size",
        "32",
        "view_selector=sparse_score",
        "patch_match.num_scales=1",
        cwd=tmp_path,
    )
    assert result.returncode == 0, result.stderr
    assert "32x24" in result.stderr  # the workspace summary of the downscaled views
    assert "dvpmvs dense" in result.stderr and "fused cloud:" in result.stderr  # the closing table
    names = sorted(p.name for p in (root / "images").iterdir())
    for name in names:
        for pass_ in ("photometric", "geometric"):
            assert (root / "stereo" / "depth_maps" / f"{name}.{pass_}.bin").is_file()
            assert (root / "stereo" / "normal_maps" / f"{name}.{pass_}.bin").is_file()
    assert (root / "fused.ply").is_file()
    # The manifest's command runs it again as typed, in our spelling (the report shows it).
    manifest = json.loads((root / "dvpmvs_run.json").read_text())
    assert manifest["command"] == [
        "dvpmvs",
        "dense",
        f"workspace={root}",
        "max_image_size=32",
        "view_selector=sparse_score",
        "patch_match.num_scales=1",
    ]
    # A rerun finds every view finished and recomputes nothing.
    again = dvpmvs(
        "dense",
        f"workspace={root}",
        "max_image_size=32",
        "view_selector=sparse_score",
        "patch_match.num_scales=1",
        "fuse=false",
        cwd=tmp_path,
    )
    assert again.returncode == 0, again.stderr
    table = again.stderr.replace("┃", "│")
    assert "photometric │        0 │      5" in table and "geometric │        0 │      5" in table
    assert "the maps of all 5 views are current" in again.stdout


def test_dense_option_errors_are_clear(tmp_path):
    root = tmp_path / "ws"
    make_workspace(root)
    result = dvpmvs("dense", f"workspace={root}", "patch_match.window_step=0", cwd=tmp_path)
    assert result.returncode == 1 and "invalid patch_match option: window_step" in result.stderr
    result = dvpmvs("dense", f"workspace={root}", "fusion=openmvs", cwd=tmp_path)
    assert result.returncode == 1 and "unknown fusion backend" in result.stderr
    assert "Traceback" not in result.stderr


@pytest.mark.slow
def test_multirun_sweep_runs_every_job(tmp_path):
    root = tmp_path / "ws"
    make_workspace(root)
    result = dvpmvs(
        "dense",
        "-m",
        f"workspace={root}",
        "max_image_size=32,48",
        "fuse=false",
        "patch_match.num_scales=1",
        "geometric=false",
        cwd=tmp_path,
    )
    assert "32x24" in result.stderr and "48x36" in result.stderr
    assert result.returncode == 0, result.stderr


@pytest.mark.slow
def test_fuse_subcommand_runs_both_fusions(tmp_path):
    root = tmp_path / "ws"
    make_workspace(root)
    result = dvpmvs("fuse", f"workspace={root}", cwd=tmp_path)
    assert result.returncode == 1 and "run `dvpmvs dense" in result.stderr
    assert (
        dvpmvs(
            "dense", f"workspace={root}", "patch_match.num_scales=1", "fuse=false", cwd=tmp_path
        ).returncode
        == 0
    )
    for fusion in ("dvpmvs", "colmap"):
        out = tmp_path / f"{fusion}.ply"
        result = dvpmvs(
            "fuse", f"workspace={root}", f"fusion={fusion}", f"output={out}", cwd=tmp_path
        )
        assert result.returncode == 0, result.stderr
        assert out.is_file() and "points ->" in result.stderr
    # The cloud `fuse` writes carries its record: a later dense run on the workspace keeps it.
    assert dvpmvs("fuse", f"workspace={root}", cwd=tmp_path).returncode == 0
    again = dvpmvs("dense", f"workspace={root}", "patch_match.num_scales=1", cwd=tmp_path)
    assert again.returncode == 0, again.stderr
    assert "is current (same maps and fusion options): reused" in again.stdout


def test_plugins_subcommand_lists_entry_points_and_marks_the_defaults(tmp_path):
    result = dvpmvs("plugins", cwd=tmp_path)
    assert result.returncode == 0
    assert "view_selector" in result.stdout and "colmap_cfg*, sparse_score" in result.stdout
    assert "mask           (dvpmvs.masks): files, onnx, none*" in result.stdout
    assert "quality=fast | high* | low | medium" in result.stdout
    assert "method=baseline | default* | paper | w_o_agn" in result.stdout


def test_the_presets_marked_default_are_the_default():
    from omegaconf import OmegaConf

    from dvpmvs.cli import DEFAULT_PRESETS
    from dvpmvs.config import compose

    plain = OmegaConf.to_container(compose("dense", ["workspace=w"]))
    for group, option in DEFAULT_PRESETS.items():
        assert (
            OmegaConf.to_container(compose("dense", ["workspace=w", f"{group}={option}"])) == plain
        )
    fast = OmegaConf.to_container(compose("dense", ["workspace=w", "quality=fast"]))
    assert fast != plain  # a preset that is not the default changes something


def test_fast_preset_matches_at_half_size_with_a_floor(tmp_path):
    # quality=fast halves the views (resolution_level=1) down to min_resolution: the 64x48
    # workspace stays whole under the preset's 160 px floor, and is halved with a 32 px one.
    from dvpmvs.config import compose

    cfg = compose("dense", ["workspace=unused", "quality=fast"])
    assert (cfg.resolution_level, cfg.min_resolution) == (1, 160)
    root = tmp_path / "ws"
    make_workspace(root)
    result = dvpmvs(
        "dense",
        f"workspace={root}",
        "quality=fast",
        "min_resolution=32",
        "view_selector=sparse_score",
        "patch_match.num_scales=1",
        "fuse=false",
        cwd=tmp_path,
    )
    assert result.returncode == 0, result.stderr
    assert "32x24" in result.stderr
    from dvpmvs.maps import read_depth_map

    assert read_depth_map(root / "stereo" / "depth_maps" / "view_00.png.geometric.bin").shape == (
        24,
        32,
    )


def test_the_demo_names_a_workspace_it_would_not_read(tmp_path):
    # The demo writes and reads its workspace at out=; a workspace= beside it would be ignored.
    result = dvpmvs(
        "demo", f"workspace={tmp_path / 'mine'}", f"out={tmp_path / 'demo'}", cwd=tmp_path
    )
    assert result.returncode != 0
    assert "writes its workspace to out=" in result.stderr and "give out= instead" in result.stderr
    assert not (tmp_path / "demo").exists()
