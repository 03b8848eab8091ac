"""The ONNX Runtime priors (plugins/onnx) with tiny networks built here with the onnx helper API."""

import numpy as np
import pytest

from dvpmvs import registry
from dvpmvs.maps import read_extra_map
from dvpmvs.priors import PriorContext, PriorError, PriorProviders, compute_priors
from tests.helpers import dvpmvs
from tests.onnx_models import (
    IMAGENET_MEAN,
    IMAGENET_STD,
    affine_red_model,
    constant_normal_model,
    highlight_model,
    nan_model,
)
from tests.prior_scenes import H, K, W, plane_depth
from tests.scenes import make_workspace

# Also run on the other Pythons `make test` checks (scripts/other_pythons.py).
pytestmark = pytest.mark.smoke


def _ctx(tmp_path, depth):
    """A view whose red channel is its inverse depth mapped to [0, 1] (what the tiny networks
    'see'), with sparse points sampled from the true depth."""
    inverse = 1.0 / depth
    red = ((inverse - inverse.min()) / (inverse.max() - inverse.min())).astype(np.float32)
    rgb = np.stack([red, np.full_like(red, 0.5), np.full_like(red, 0.25)], axis=2)
    rng = np.random.default_rng(0)
    cols, rows = rng.integers(0, W, 150), rng.integers(0, H, 150)
    sparse = np.stack([cols, rows, depth[rows, cols]], axis=1).astype(np.float64)
    return PriorContext(
        "im.png", rgb.mean(axis=2), K, (2.0, 8.0), sparse, rgb_loader=lambda: rgb, root=tmp_path
    )


def test_onnx_providers_are_registered_with_their_presets():
    assert "onnx" in registry.available("depth_prior") and "onnx" in registry.available(
        "normal_prior"
    )
    from dvpmvs_onnx import PRESETS

    assert {"depthpro", "depth_anything_v2", "metric3dv2"} <= set(PRESETS)


def test_relative_inverse_depth_round_trip_is_aligned_to_the_sparse_points(tmp_path):
    # The preset's ImageNet normalisation is undone by the network (a = 7 std, b = 7 mean + 3), so
    # it outputs 7 * red + 3: inverse depth up to an unknown scale and shift.
    model = affine_red_model(tmp_path / "da2.onnx", 7 * IMAGENET_STD[0], 7 * IMAGENET_MEAN[0] + 3)
    truth = plane_depth()
    providers = PriorProviders.from_configs(
        {"depth_prior": {"name": "onnx", "preset": "depth_anything_v2", "model": str(model)}}
    )
    priors = compute_priors(_ctx(tmp_path, truth), providers)
    error = np.abs(priors.depth - truth) / truth
    assert priors.depth_valid.all()
    assert np.median(error) < 1e-4 and error.max() < 1e-3  # measured 0 and 9e-5
    # Read as depth instead of inverse depth, the output runs against the sparse depths: a clear
    # error, not a silently inverted prior.
    providers = PriorProviders.from_configs(
        {
            "depth_prior": {
                "name": "onnx",
                "preset": "depth_anything_v2",
                "model": str(model),
                "output": "depth",
            }
        }
    )
    with pytest.raises(PriorError, match="correlates negatively"):
        compute_priors(_ctx(tmp_path, truth), providers)


def test_padded_input_is_cropped_back_to_the_image(tmp_path):
    # 60x80 into a 64x64 input: the image fills 48 rows, 8 rows of padding above and below, whose
    # output (a = 7 / 255 on a zero pad gives 3) must not leak into the prior.
    model = affine_red_model(tmp_path / "pad.onnx", 7 / 255, 3.0)
    truth = plane_depth()
    providers = PriorProviders.from_configs(
        {
            "depth_prior": {
                "name": "onnx",
                "model": str(model),
                "input_size": [64, 64],
                "resize": "pad",
                "scale": 255.0,
                "output": "inverse_depth",
                "metric": False,
            }
        }
    )
    priors = compute_priors(_ctx(tmp_path, truth), providers)
    error = np.abs(priors.depth - truth) / truth
    # Through a 48x64 network image and back: measured 9e-5 median, 7e-4 at worst.
    assert np.median(error) < 1e-3 and error.max() < 5e-3


def test_normals_pick_the_three_channel_output_and_face_the_camera(tmp_path):
    n = np.array([0.3, -0.2, -1.0])
    model = constant_normal_model(tmp_path / "m3d.onnx", n)
    ctx = _ctx(tmp_path, plane_depth())
    for flip, expected in ((False, n), (True, -n * [1, -1, -1])):
        provider = registry.create(
            "normal_prior",
            {"name": "onnx", "preset": "metric3dv2", "model": str(model), "flip_y_z": flip},
        )
        normal = provider(ctx, None)
        assert normal.shape == (H, W, 3)
        assert np.allclose(normal, expected / np.linalg.norm(expected), atol=1e-5)


def test_model_errors_name_the_config_key(tmp_path):
    ctx = _ctx(tmp_path, plane_depth())

    def run(config):
        compute_priors(ctx, PriorProviders.from_configs({"depth_prior": config}))

    with pytest.raises(PriorError, match=r"set depth_prior.model=/path/to/model.onnx"):
        run({"name": "onnx", "preset": "depthpro"})
    with pytest.raises(
        PriorError, match=r"depth_prior.model: ONNX model file not found: .*nowhere.onnx"
    ):
        run({"name": "onnx", "preset": "depthpro", "model": str(tmp_path / "nowhere.onnx")})
    (tmp_path / "garbage.onnx").write_bytes(b"not a model")
    with pytest.raises(PriorError, match=r"depth_prior.model: ONNX Runtime cannot load"):
        run({"name": "onnx", "preset": "depthpro", "model": str(tmp_path / "garbage.onnx")})
    fixed = affine_red_model(tmp_path / "fixed.onnx", 1.0, 1.0, input_shape=(1, 3, 32, 32))
    with pytest.raises(
        PriorError, match=r"depth_prior.input_size is \[518, 518\] but .* fixed at \[32, 32\]"
    ):
        run({"name": "onnx", "preset": "depth_anything_v2", "model": str(fixed)})
    dynamic = affine_red_model(tmp_path / "dynamic.onnx", 1.0, 1.0)
    with pytest.raises(
        PriorError, match=r"depth_prior.input_size: the model's input size is dynamic"
    ):
        run({"name": "onnx", "model": str(dynamic)})
    with pytest.raises(PriorError, match=r"depth_prior.model returned .* NaN"):
        run(
            {
                "name": "onnx",
                "preset": "depthpro",
                "model": str(nan_model(tmp_path / "nan.onnx")),
                "input_size": [16, 16],
            }
        )
    with pytest.raises(registry.PluginError, match=r"'metric3dv2' is a normal_prior preset"):
        run({"name": "onnx", "preset": "metric3dv2", "model": str(dynamic)})
    with pytest.raises(
        registry.PluginError, match=r"unknown depth_prior option\(s\) for the onnx provider: colour"
    ):
        run({"name": "onnx", "colour": "blue"})


def test_dense_runs_end_to_end_with_onnx_priors_from_the_presets(tmp_path):
    """`dvpmvs dense` with the plugin's own config groups: depth_prior=depth_anything_v2 read as
    metric depth (the tiny network outputs 4 + 0.01 * red, inside the scene's slab) and
    normal_prior=metric3dv2; the aligned prior's labels come out of the run."""
    root = tmp_path / "ws"
    make_workspace(root)
    depth_model = affine_red_model(
        tmp_path / "da2.onnx", 0.01 * IMAGENET_STD[0], 4.0 + 0.01 * IMAGENET_MEAN[0]
    )
    normal_model = constant_normal_model(tmp_path / "m3d.onnx", [0.0, 0.0, -1.0])
    result = dvpmvs(
        "dense",
        f"workspace={root}",
        "max_image_size=32",
        "view_selector=sparse_score",
        "patch_match.num_scales=1",
        "geometric=false",
        "fuse=false",
        "depth_prior=depth_anything_v2",
        f"depth_prior.model={depth_model}",
        "depth_prior.output=depth",
        "depth_prior.metric=true",
        "normal_prior=metric3dv2",
        f"normal_prior.model={normal_model}",
        cwd=tmp_path,
    )
    assert result.returncode == 0, result.stderr
    for name in sorted(p.name for p in (root / "images").iterdir()):
        labels = read_extra_map(root / "stereo" / "label_maps" / f"{name}.photometric.bin")
        assert labels.shape == (24, 32) and labels.max() >= 1
        assert (root / "stereo" / "previews" / f"{name}.normal_prior.png").is_file()
        assert (root / "stereo" / "depth_maps" / f"{name}.photometric.bin").is_file()
    missing = dvpmvs(
        "dense",
        f"workspace={root}",
        "overwrite=true",
        "depth_prior=depthpro",
        "depth_prior.model=/no/such/depth_pro.onnx",
        cwd=tmp_path,
    )
    assert missing.returncode == 1
    assert "depth_prior.model: ONNX model file not found: /no/such/depth_pro.onnx" in missing.stderr
    assert "Traceback" not in missing.stderr


def test_highlight_preset_round_trip_over_tiles(tmp_path):
    from dvpmvs.image import to_grey

    model = highlight_model(tmp_path / "jshdr.onnx")
    rng = np.random.default_rng(0)
    rgb = rng.random((230, 310, 3)).astype(np.float32)  # not a whole number of 200x200 tiles
    ctx = PriorContext("im.png", to_grey(rgb), K, (2.0, 8.0), rgb_loader=lambda: rgb, root=tmp_path)
    provider = registry.create(
        "highlight", {"name": "onnx", "preset": "jshdr", "model": str(model)}
    )
    assert provider.tile and provider.model.options.input_size == (200, 200)
    corrected, mask = provider(ctx)
    np.testing.assert_array_equal(mask, rgb.mean(axis=2) >= 0.5)
    assert np.abs(corrected - to_grey(rgb * 0.5)).max() < 1e-5
    # By name, as logits, without tiles (the view resized to 200x200 and back: blurred, not equal).
    provider = registry.create(
        "highlight",
        {
            "name": "onnx",
            "preset": "jshdr",
            "model": str(model),
            "tile": False,
            "mask_output": "mask",
            "corrected_output": "diffuse",
            "mask_logits": True,
            "mask_threshold": 0.6,
        },
    )
    corrected, mask = provider(ctx)
    # The resized view's mean is about 0.5 everywhere: sigmoid(0.5) = 0.62 >= 0.6, while read as a
    # probability it would be under the threshold.
    assert mask.shape == (230, 310) and mask.mean() > 0.9
    assert np.abs(corrected - to_grey(rgb * 0.5)).mean() < 0.1
    provider.mask_logits = False
    assert provider(ctx)[1].mean() < 0.1
    assert [p.name for p in provider.input_files("im.png", tmp_path)] == ["jshdr.onnx"]


def test_a_view_smaller_than_one_tile_is_padded_to_it(tmp_path):
    from dvpmvs.image import to_grey

    model = highlight_model(tmp_path / "jshdr.onnx")
    rgb = (
        np.random.default_rng(1).random((120, 160, 3)).astype(np.float32)
    )  # under 200x200 both ways
    ctx = PriorContext("im.png", to_grey(rgb), K, (2.0, 8.0), rgb_loader=lambda: rgb, root=tmp_path)
    corrected, mask = registry.create(
        "highlight", {"name": "onnx", "preset": "jshdr", "model": str(model)}
    )(ctx)
    assert mask.shape == (120, 160)
    np.testing.assert_array_equal(mask, rgb.mean(axis=2) >= 0.5)
    assert np.abs(corrected - to_grey(rgb * 0.5)).max() < 1e-5


def test_highlight_network_with_the_wrong_outputs_is_a_clear_error(tmp_path):
    model = highlight_model(tmp_path / "m.onnx")
    rgb = np.full((50, 60, 3), 0.5, np.float32)
    ctx = PriorContext(
        "im.png", rgb.mean(axis=2), K, (2.0, 8.0), rgb_loader=lambda: rgb, root=tmp_path
    )
    for params, message in (
        ({"mask_output": 1}, "not a one-channel map"),
        ({"corrected_output": "colour"}, "no output 'colour'"),
        ({"corrected_output": 7}, "no output number 7"),
    ):
        provider = registry.create(
            "highlight", {"name": "onnx", "model": str(model), "input_size": [50, 60], **params}
        )
        with pytest.raises(PriorError, match=message):
            provider(ctx)
    nan = nan_model(tmp_path / "nan.onnx")
    provider = registry.create(
        "highlight",
        {"name": "onnx", "model": str(nan), "input_size": [50, 60], "corrected_output": 0},
    )
    with pytest.raises(PriorError, match="NaN"):
        provider(ctx)
    with pytest.raises(registry.PluginError, match="a highlight preset|is a highlight preset"):
        registry.create("depth_prior", {"name": "onnx", "preset": "jshdr", "model": str(model)})
