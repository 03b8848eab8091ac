"""The onnx mask provider: a segmentation network's classes masked, on tiny models built here."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest

pytest.importorskip("onnxruntime")

from dvpmvs.masks import MaskError, ViewMasks  # noqa: E402
from dvpmvs_onnx.masks import class_map  # noqa: E402
from tests.helpers import dvpmvs
from tests.onnx_models import (  # noqa: E402
    brightness_segmentation_model,
    highlight_model,
    nan_model,
    save_model,
)


@dataclass
class _View:
    name: str
    rgb: np.ndarray

    @property
    def height(self):
        return self.rgb.shape[0]

    @property
    def width(self):
        return self.rgb.shape[1]

    def load_rgb(self):
        return self.rgb


def _sky_view(height=60, width=80):
    """A dark ground with bright sky in the top third."""
    rgb = np.full((height, width, 3), 0.3, np.float32)
    rgb[: height // 3] = (0.8, 0.85, 0.95)
    return _View("0000.png", rgb)


def test_class_map_reads_labels_and_per_class_scores():
    labels = np.array([[0, 1], [2, 1]], np.int64)
    np.testing.assert_array_equal(class_map(labels[None, None], "nchw"), labels)
    np.testing.assert_array_equal(class_map(labels.astype(np.float32)[None], "nchw"), labels)
    scores = np.eye(3, dtype=np.float32)[labels]  # (2, 2, 3): channels last
    np.testing.assert_array_equal(class_map(scores[None], "nhwc"), labels)
    np.testing.assert_array_equal(class_map(scores.transpose(2, 0, 1)[None], "nchw"), labels)
    assert class_map(np.zeros((1, 3), np.float32), "nchw") is None  # no image
    assert class_map(np.zeros((2, 1, 4, 4), np.float32), "nchw") is None  # a batch of two


@pytest.mark.parametrize("scores", [False, True])
def test_the_excluded_class_is_masked_at_the_views_size(tmp_path, scores):
    model = brightness_segmentation_model(tmp_path / "sky.onnx", 0.6, scores=scores)
    masks = ViewMasks.from_config(
        {"name": "onnx", "model": str(model), "exclude": [1], "input_size": [30, 40]}
    )
    view = _sky_view()
    keep = masks.mask(view)
    assert keep.shape == (60, 80) and keep.dtype == bool
    np.testing.assert_array_equal(keep, view.rgb.mean(axis=2) <= 0.6)
    # The model's content is the mask's provenance.
    assert list(masks.provenance(view.name)["files"]) == [str(model)]


def test_a_model_without_a_class_map_is_named_with_its_outputs(tmp_path):
    from onnx import TensorProto, helper

    colour = save_model(
        tmp_path / "colour.onnx",
        [helper.make_node("ReduceMean", ["pixel_values"], ["colour"], axes=[2, 3], keepdims=0)],
        [helper.make_tensor_value_info("colour", TensorProto.FLOAT, [1, 3])],
        [],
    )
    masks = ViewMasks.from_config(
        {"name": "onnx", "model": str(colour), "exclude": [1], "input_size": [30, 40]}
    )
    with pytest.raises(MaskError, match=r"no output is a per-pixel class map.*colour \[1, 3\]"):
        masks.check([_sky_view()])
    # A named output that is no class map is named with its shape.
    masks = ViewMasks.from_config(
        {
            "name": "onnx",
            "model": str(highlight_model(tmp_path / "h.onnx")),
            "exclude": [1],
            "input_size": [30, 40],
            "output": "residue",
        }
    )
    masks.check([_sky_view()])  # three scores per pixel: a class map (argmax)
    masks = ViewMasks.from_config(
        {
            "name": "onnx",
            "model": str(colour),
            "exclude": [1],
            "input_size": [30, 40],
            "output": "colour",
        }
    )
    with pytest.raises(MaskError, match=r"output colour \[1, 3\] is not a per-pixel class map"):
        masks.check([_sky_view()])


@pytest.mark.parametrize(
    "params,needle",
    [
        ({"exclude": []}, "mask.exclude must list the class indices"),
        ({"exclude": ["sky"]}, "mask.exclude must list class indices"),
        ({"model": None, "exclude": [1]}, "needs a model file"),
    ],
)
def test_bad_onnx_mask_options_are_named(tmp_path, params, needle):
    config = {
        "name": "onnx",
        "model": str(brightness_segmentation_model(tmp_path / "s.onnx", 0.6)),
        **params,
    }
    with pytest.raises(Exception, match=needle):
        ViewMasks.from_config(config).check([_sky_view()])


@pytest.mark.slow
def test_a_brightness_segmenter_masks_the_courtyards_sky_as_its_ground_truth_does(tmp_path):
    """On the synthetic courtyard (open sky above a wall): a network's class "bright" masked agrees
    with the ground truth's sky (no surface) within a bound near the measured 0.6-1.0 % of pixels,
    and the maps computed with it have no depth in a masked pixel."""
    from dvpmvs.maps import map_path, read_depth_map
    from dvpmvs.workspace import Workspace

    ws = tmp_path / "courtyard"
    made = dvpmvs(
        "synth", f"out={ws}", "scene=courtyard", "views=4", "width=160", "seed=0", cwd=tmp_path
    )
    assert made.returncode == 0, made.stderr[-2000:]
    model = brightness_segmentation_model(tmp_path / "sky.onnx", 0.76)
    config = {"name": "onnx", "model": str(model), "exclude": [1], "input_size": [60, 80]}
    masks, workspace = ViewMasks.from_config(config), Workspace.open(ws)
    keeps = {}
    for view in workspace.reference_views():
        keeps[view.name] = keep = masks.mask(view, ws)
        sky = read_depth_map(ws / "ground_truth" / "depth_maps" / f"{view.name}.bin") <= 0
        assert 0.25 < sky.mean() < 0.4
        assert (keep == sky).mean() < 0.015  # pixels where the two disagree
        assert (~keep[sky]).mean() > 0.96
    run = dvpmvs(
        "dense",
        f"workspace={ws}",
        "quality=fast",
        "previews=false",
        "fuse=false",
        "evaluate.ground_truth=none",
        "num_threads=2",
        "mask=onnx",
        f"mask.model={model}",
        "mask.exclude=[1]",
        "mask.input_size=[60,80]",
        cwd=tmp_path,
    )
    assert run.returncode == 0, run.stderr[-2000:]
    for name, keep in keeps.items():
        depth = read_depth_map(map_path(ws / "stereo", name, "depth", "geometric"))
        assert not (depth[~keep] > 0).any()
        assert (depth[keep] > 0).mean() > 0.5


def test_a_bad_network_stops_dense_with_one_line_before_any_view(tmp_path):
    from onnx import TensorProto, helper

    ws = tmp_path / "ws"
    made = dvpmvs("synth", f"out={ws}", "scene=room", "views=3", "width=64", "seed=1", cwd=tmp_path)
    assert made.returncode == 0, made.stderr[-2000:]
    colour = save_model(
        tmp_path / "colour.onnx",
        [helper.make_node("ReduceMean", ["pixel_values"], ["colour"], axes=[2, 3], keepdims=0)],
        [helper.make_tensor_value_info("colour", TensorProto.FLOAT, [1, 3])],
        [],
    )
    run = dvpmvs(
        "dense",
        f"workspace={ws}",
        "quality=fast",
        "previews=false",
        "num_threads=1",
        "mask=onnx",
        f"mask.model={colour}",
        "mask.exclude=[1]",
        "mask.input_size=[32,32]",
        cwd=tmp_path,
    )
    assert run.returncode == 1 and "Traceback" not in run.stderr, run.stderr[-2000:]
    lines = [line for line in run.stderr.splitlines() if "class map" in line]
    assert len(lines) == 1 and "colour [1, 3]" in lines[0], run.stderr[-2000:]
    assert not list(ws.glob("stereo/depth_maps/*.bin")) and not (ws / "fused.ply").exists()


def test_the_network_runs_once_per_view_per_run(workspace_dir, tmp_path, monkeypatch):
    # The first view's mask is the check before any view; both passes and fusion read the stored
    # masks (a view reloaded into fusion's cache too); a rerun reuses them.
    import onnxruntime

    from dvpmvs.workspace import Workspace
    from tests.helpers import dvpmvs_here

    root, _ = workspace_dir
    model = brightness_segmentation_model(tmp_path / "bright.onnx", 0.6)
    runs = []
    run = onnxruntime.InferenceSession.run

    def counted(self, *args, **kwargs):
        runs.append(1)
        return run(self, *args, **kwargs)

    monkeypatch.setattr(onnxruntime.InferenceSession, "run", counted)
    command = (
        "dense",
        f"workspace={root}",
        "quality=fast",
        "previews=false",
        "num_threads=2",
        "fusion_options.cache_views=2",
        "mask=onnx",
        f"mask.model={model}",
        "mask.exclude=[1]",
        "mask.input_size=[30,40]",
    )
    first = dvpmvs_here(*command, cwd=tmp_path)
    assert first.returncode == 0, first.stderr[-2000:]
    views = [view.name for view in Workspace.open(root).reference_views()]
    assert len(runs) == len(views) == 5
    # Kept in COLMAP's layout beside the maps, with their records.
    assert sorted(p.name for p in (root / "stereo" / "mask_maps").glob("*.png")) == [
        f"{name}.png" for name in sorted(views)
    ]
    again = dvpmvs_here(*command, cwd=tmp_path)
    assert again.returncode == 0 and len(runs) == 5


@pytest.mark.parametrize(
    "key, value, wanted",
    [
        ("num_threads", "2", "an integer"),
        ("num_threads", 1.5, "an integer"),
        ("model", 3, "a string"),
    ],
)
def test_the_network_options_are_typed_as_the_cores(key, value, wanted):
    from dvpmvs.registry import PluginError

    with pytest.raises(PluginError, match=rf"mask\.{key} must be {wanted}"):
        ViewMasks.from_config({"name": "onnx", "model": "net.onnx", "exclude": [1], key: value})


@pytest.mark.parametrize("channels", [1, 3])
def test_a_network_returning_nan_masks_nothing_and_says_so(tmp_path, channels):
    # As labels (one channel) or as per-class scores (an argmax would call NaN class 0).
    model = nan_model(tmp_path / "nan.onnx", channels)
    masks = ViewMasks.from_config(
        {"name": "onnx", "model": str(model), "exclude": [0], "input_size": [30, 40]}
    )
    with pytest.raises(MaskError, match=r"returned \d+ NaN or infinite value"):
        masks.mask(_sky_view())
