import logging
import math
import shutil

import numpy as np
import pytest

from dvpmvs.image import ImageReadError
from dvpmvs.workspace import Workspace, WorkspaceError, WorkspaceOptions, parse_patch_match_cfg
from tests.scenes import make_workspace

# Also run on the other Pythons `make test` checks (scripts/other_pythons.py).
pytestmark = pytest.mark.smoke


def expected_depth_range(points, R, t, margin=0.25):
    depths = np.sort(points @ R[2] + t[2])
    depths = depths[depths > 0]
    lo = depths[int(depths.size * 0.01)]
    hi = depths[int(depths.size * 0.99)]
    return lo * (1 - margin), hi * (1 + margin)


def observed_points(truth, image_id):
    reconstruction = truth["reconstruction"]
    return np.array(
        [
            p.xyz
            for p in reconstruction.points3D.values()
            if any(e.image_id == image_id for e in p.track.elements)
        ]
    )


def test_loads_calibration_poses_and_depth_ranges(workspace_dir):
    root, truth = workspace_dir
    ws = Workspace.open(root)
    assert sorted(ws.views) == truth["names"]
    assert ws.references == truth["names"]
    for index, name in enumerate(truth["names"]):
        view = ws[name]
        R, t = truth["poses"][index]
        np.testing.assert_allclose(view.K, truth["K"])
        np.testing.assert_allclose(view.R, R, atol=1e-12)
        np.testing.assert_allclose(view.t, t, atol=1e-12)
        # The projection of a world point through (K, R, t) lands where the test put it.
        X = truth["points"][0]
        uv = view.P @ np.append(X, 1.0)
        ref = truth["K"] @ (R @ X + t)
        np.testing.assert_allclose(uv[:2] / uv[2], ref[:2] / ref[2], atol=1e-9)
        lo, hi = expected_depth_range(observed_points(truth, view.image_id), R, t)
        assert view.depth_range == pytest.approx((lo, hi), rel=1e-6)
        assert not view.depth_range_is_fallback
        assert view.width == 64 and view.height == 48


def test_auto_sources_come_from_the_view_selector(workspace_dir):
    root, truth = workspace_dir
    ws = Workspace.open(root)
    for name in truth["names"]:
        view = ws[name]
        assert len(view.sources) == 2 and name not in view.sources
        # colmap_cfg ranks by the number of shared sparse points.
        shared = {other: angles.size for other, angles in ws.covisibility[name].items()}
        best = sorted(shared.items(), key=lambda kv: (-kv[1], kv[0]))[:2]
        assert list(view.sources) == [other for other, _ in best]
        assert list(view.source_scores) == [float(count) for _, count in best]


def test_sparse_score_selector_prefers_useful_baselines(tmp_path):
    root = tmp_path / "ws"
    truth = make_workspace(root, num_views=5, num_auto=4)
    ws = Workspace.open(
        root, WorkspaceOptions(view_selector={"name": "sparse_score", "theta0": 5.0})
    )
    view = ws[truth["names"][2]]
    assert len(view.sources) == 4
    assert list(view.source_scores) == sorted(view.source_scores, reverse=True)


def test_explicit_and_all_source_lists(tmp_path):
    root = tmp_path / "ws"
    cfg = "view_00.png\nview_03.png, view_01.png\n# a comment\n\nview_02.png\n__all__\n"
    make_workspace(root, patch_match_cfg=cfg)
    ws = Workspace.open(root)
    assert ws.references == ["view_00.png", "view_02.png"]
    assert ws["view_00.png"].sources == ("view_03.png", "view_01.png")
    assert ws["view_02.png"].sources == ("view_00.png", "view_01.png", "view_03.png", "view_04.png")
    assert all(math.isnan(s) for s in ws["view_02.png"].source_scores)


def test_text_model_and_sparse_0_layout_load_the_same(tmp_path, workspace_dir):
    root, _ = workspace_dir
    reference = Workspace.open(root)
    other = tmp_path / "text"
    make_workspace(other, text=True, layout_subdir="0")
    assert not (other / "sparse" / "cameras.txt").exists()
    ws = Workspace.open(other)
    for name, view in reference.views.items():
        np.testing.assert_allclose(ws[name].K, view.K)
        np.testing.assert_allclose(ws[name].R, view.R, atol=1e-9)
        assert ws[name].depth_range == pytest.approx(view.depth_range, rel=1e-5)
        assert ws[name].sources == view.sources


def test_simple_pinhole_camera(tmp_path):
    root = tmp_path / "ws"
    make_workspace(root, camera_model="SIMPLE_PINHOLE")
    K = Workspace.open(root)["view_00.png"].K
    assert K[0, 0] == K[1, 1] == 60.0


def test_downscaling_scales_intrinsics_and_images(workspace_dir):
    root, truth = workspace_dir
    ws = Workspace.open(root, WorkspaceOptions(max_image_size=32))
    view = ws["view_01.png"]
    assert (view.width, view.height) == (32, 24)
    np.testing.assert_allclose(view.K[0], truth["K"][0] * 0.5)
    np.testing.assert_allclose(view.K[1], truth["K"][1] * 0.5)
    rgb = view.load_rgb()
    assert rgb.shape == (24, 32, 3) and rgb.dtype == np.float32
    assert view.load_grey().shape == (24, 32)
    assert 0.0 <= rgb.min() and rgb.max() <= 1.0


def test_resolution_level_halves_the_largest_side_down_to_the_minimum(workspace_dir):
    root, _ = workspace_dir  # 64x48 images
    for level, minimum, limit, expected in [
        (1, 32, -1, (32, 24)),
        (2, 32, -1, (32, 24)),
        (1, 40, -1, (40, 30)),
        (1, 32, 40, (32, 24)),
        (2, 32, 48, (32, 24)),
        (1, 100, -1, (64, 48)),
        (0, 32, -1, (64, 48)),
    ]:
        ws = Workspace.open(
            root,
            WorkspaceOptions(resolution_level=level, min_resolution=minimum, max_image_size=limit),
        )
        view = ws["view_01.png"]
        assert (view.width, view.height) == expected, (level, minimum, limit)
        assert ws.max_image_size == (-1 if expected == (64, 48) and limit <= 0 else max(expected))
        # Sizes given for the images at level 0 (the depth prior's) shrink with the views.
        own = 64 if limit <= 0 else min(64, limit)
        assert ws.resolution_scale(view) == pytest.approx(max(expected) / own), (
            level,
            minimum,
            limit,
        )


def test_fixed_depth_range_option(workspace_dir):
    root, _ = workspace_dir
    ws = Workspace.open(root, WorkspaceOptions(depth_range=(1.0, 9.0)))
    assert all(view.depth_range == (1.0, 9.0) for view in ws.views.values())


def test_options_validate_themselves():
    with pytest.raises(ValueError, match="depth_quantiles"):
        WorkspaceOptions(depth_quantiles=(0.9, 0.1))
    with pytest.raises(ValueError, match="depth_range"):
        WorkspaceOptions(depth_range=(2.0, 1.0))
    with pytest.raises(ValueError, match="depth_margin"):
        WorkspaceOptions(depth_margin=1.5)
    with pytest.raises(ValueError, match="resolution_level"):
        WorkspaceOptions(resolution_level=-1)
    with pytest.raises(ValueError, match="min_resolution"):
        WorkspaceOptions(min_resolution=8)


# -- bad inputs: one clear error each -------------------------------------------------------------


@pytest.mark.parametrize("folder", ["images", "sparse"])
def test_missing_folder(workspace_dir, folder):
    root, _ = workspace_dir
    shutil.rmtree(root / folder)
    with pytest.raises(WorkspaceError, match=f"no {folder}/ folder"):
        Workspace.open(root)


def test_missing_workspace():
    with pytest.raises(WorkspaceError, match="workspace folder not found"):
        Workspace.open("/no/such/workspace")


def test_empty_sparse_folder(workspace_dir):
    root, _ = workspace_dir
    for f in (root / "sparse").iterdir():
        f.unlink()
    with pytest.raises(WorkspaceError, match="no COLMAP model"):
        Workspace.open(root)


def test_image_listed_but_absent(workspace_dir):
    root, _ = workspace_dir
    (root / "images" / "view_03.png").unlink()
    with pytest.raises(WorkspaceError, match=r"missing from .*images: view_03\.png"):
        Workspace.open(root)


def test_unreadable_image(workspace_dir):
    root, _ = workspace_dir
    (root / "images" / "view_01.png").write_bytes(b"\x89PNG not really an image")
    # Found when the workspace opens, before any view is computed.
    with pytest.raises(ImageReadError, match=r"cannot decode image .*view_01\.png"):
        Workspace.open(root)


def test_distorted_camera_model(tmp_path):
    root = tmp_path / "ws"
    make_workspace(root, camera_model="OPENCV")
    with pytest.raises(WorkspaceError, match="model OPENCV.*image_undistorter"):
        Workspace.open(root)


def test_source_view_that_does_not_exist(tmp_path):
    root = tmp_path / "ws"
    make_workspace(root, patch_match_cfg="view_00.png\nview_01.png, view_99.png\n")
    with pytest.raises(WorkspaceError, match=r"patch-match\.cfg:2: source image 'view_99\.png'"):
        Workspace.open(root)


def test_reference_view_that_does_not_exist(tmp_path):
    root = tmp_path / "ws"
    make_workspace(root, patch_match_cfg="# header\nnope.png\n__auto__, 2\n")
    with pytest.raises(
        WorkspaceError,
        match=r"patch-match\.cfg:2: reference image 'nope\.png' is not a registered image",
    ):
        Workspace.open(root)


def test_malformed_patch_match_cfg(tmp_path):
    cfg = tmp_path / "patch-match.cfg"
    cfg.write_text("a.png\n__auto__, x\n")
    with pytest.raises(WorkspaceError, match="patch-match.cfg:2: expected `__auto__, N`"):
        parse_patch_match_cfg(cfg)
    cfg.write_text("a.png\n__auto__, 3\nb.png\n")
    with pytest.raises(
        WorkspaceError, match="patch-match.cfg:3: reference image 'b.png' has no line"
    ):
        parse_patch_match_cfg(cfg)


def test_missing_patch_match_cfg_falls_back_to_auto(tmp_path, caplog):
    root = tmp_path / "ws"
    truth = make_workspace(root, patch_match_cfg=None)
    with caplog.at_level(logging.WARNING, logger="dvpmvs.workspace"):
        ws = Workspace.open(root, WorkspaceOptions(default_num_sources=3))
    assert "patch-match.cfg not found" in caplog.text
    assert ws.references == truth["names"]
    assert all(len(view.sources) == 3 for view in ws.views.values())


def test_view_without_sparse_points_gets_fallback_range(workspace_dir, caplog):
    root, truth = workspace_dir
    import pycolmap

    reconstruction = pycolmap.Reconstruction(str(root / "sparse"))
    lonely = reconstruction.find_image_with_name("view_04.png").image_id
    for point_id in list(reconstruction.point3D_ids()):
        track = reconstruction.point3D(point_id).track
        if any(e.image_id == lonely for e in track.elements):
            if track.length() <= 2:
                reconstruction.delete_point3D(point_id)
            else:
                element = next(i for i, e in enumerate(track.elements) if e.image_id == lonely)
                reconstruction.delete_observation(lonely, track.elements[element].point2D_idx)
    reconstruction.write(str(root / "sparse"))
    with caplog.at_level(logging.WARNING, logger="dvpmvs.model"):
        ws = Workspace.open(root)
    view = ws["view_04.png"]
    assert view.num_sparse_points == 0 and view.depth_range_is_fallback
    others = [v.depth_range for n, v in ws.views.items() if n != "view_04.png"]
    assert view.depth_range == (min(r[0] for r in others), max(r[1] for r in others))
    assert "view_04.png observes 0 sparse point(s)" in caplog.text


def test_unknown_view_selector_lists_installed_ones(workspace_dir):
    root, _ = workspace_dir
    from dvpmvs.registry import PluginNotFoundError

    with pytest.raises(PluginNotFoundError, match="installed: .*colmap_cfg.*sparse_score"):
        Workspace.open(root, WorkspaceOptions(view_selector={"name": "nearest_magic"}))
