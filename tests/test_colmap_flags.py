"""COLMAP's flags of patch_match_stereo and stereo_fusion, read as dvpmvs's options."""

import pytest

from dvpmvs.colmap_flags import ColmapFlagError, translate_colmap_flags


def test_flags_that_mean_the_same_become_our_options():
    argv, notes = translate_colmap_flags(
        "dense",
        [
            "--workspace_path",
            "/data/my ws",
            "--PatchMatchStereo.max_image_size=1600",
            "--PatchMatchStereo.geom_consistency",
            "0",
            "--PatchMatchStereo.filter_min_ncc",
            "0.1",
            "--StereoFusion.min_num_pixels",
            "5",
            "--StereoFusion.max_normal_error",
            "10",
            "quality=fast",
        ],
    )
    assert argv == [
        "workspace='/data/my ws'",
        "max_image_size=1600",
        "geometric=false",
        "patch_match.filter_max_cost=0.9",  # our cost is 1 - NCC
        "fusion_options.min_consistent_views=4",  # COLMAP counts the reference pixel
        "fusion_options.max_normal_error=10",
        "quality=fast",
    ]
    assert notes == []


def test_fuse_takes_stereo_fusions_flags():
    argv, _ = translate_colmap_flags(
        "fuse",
        ["--workspace_path", "ws", "--input_type", "photometric", "--output_path", "out.ply"]
        + ["--StereoFusion.mask_path", "masks", "--StereoFusion.max_reproj_error", "1"],
    )
    assert argv == [
        "workspace=ws",
        "input_type=photometric",
        "output=out.ply",
        "mask.path=masks",
        "mask=files",  # COLMAP's masks: <image name>.png, 0 masked
        "mask.layout=colmap",
        "fusion_options.max_reproj_error=1",
    ]
    # COLMAP's own fusion is handed the reprojection bound of its own key.
    argv, _ = translate_colmap_flags(
        "fuse", ["fusion=colmap", "--StereoFusion.max_reproj_error", "1"]
    )
    assert argv == ["fusion=colmap", "fusion_options.colmap_max_reproj_error=1"]


def test_flags_that_tune_colmaps_gpu_or_cache_are_noted_and_ignored():
    argv, notes = translate_colmap_flags(
        "dense",
        ["--PatchMatchStereo.gpu_index", "0", "--workspace_format", "COLMAP", "workspace=ws"],
    )
    assert argv == ["workspace=ws"]
    assert len(notes) == 1 and "runs on the CPU" in notes[0]


@pytest.mark.parametrize(
    "argv,needle",
    [
        (["--PatchMatchStereo.num_iterations", "5"], "patch_match.num_iterations counts"),
        (["--PatchMatchStereo.depth_min", "1"], "depth_range=[MIN,MAX]"),
        (["--PatchMatchStereo.filter_min_num_consistent", "2"], "min_consistent_views"),
        (["--workspace_format", "PMVS"], "COLMAP workspaces only"),
        (["--PatchMatchStereo.window_radiu", "5"], "did you mean --PatchMatchStereo.window_radius"),
        (["--StereoFusion.min_num_pixels", "1"], "at least 2"),
        (["--PatchMatchStereo.geom_consistency", "maybe"], "takes 1 or 0"),
        (["--workspace_path"], "needs a value"),
    ],
)
def test_flags_whose_meaning_differs_name_what_to_write(argv, needle):
    with pytest.raises(ColmapFlagError, match=None) as error:
        translate_colmap_flags("dense", argv)
    assert needle in str(error.value)


def test_other_subcommands_and_our_own_options_are_left_alone():
    argv = ["--workspace_path", "x", "scene=room", "--cfg", "job"]
    assert translate_colmap_flags("bench", argv) == (argv, [])
    assert translate_colmap_flags("dense", ["workspace=x", "-m"]) == (["workspace=x", "-m"], [])
