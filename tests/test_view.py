"""One view of a workspace: its camera centre and projection, and its image read at its size."""

import cv2
import numpy as np
import pytest

from dvpmvs.image import ImageReadError
from dvpmvs.workspace import Workspace, WorkspaceOptions


def test_the_centre_projects_nowhere_and_points_project_through_k_r_t(workspace_dir):
    root, truth = workspace_dir
    view = Workspace.open(root)["view_03.png"]
    R, t = truth["poses"][3]
    assert np.allclose(view.R @ view.center + view.t, 0)
    X = truth["points"][7]
    uv = view.P @ np.append(X, 1.0)
    assert np.allclose(uv[:2] / uv[2], (truth["K"] @ (R @ X + t))[:2] / (R @ X + t)[2])


def test_a_downscaled_view_reads_its_image_at_its_size(workspace_dir):
    root, _ = workspace_dir
    view = Workspace.open(root, WorkspaceOptions(max_image_size=32))["view_01.png"]
    assert view.scale == (0.5, 0.5) and view.original_size == (64, 48)
    full = cv2.imread(str(view.path))[..., ::-1].astype(np.float32) / 255
    expected = cv2.resize(full, (32, 24), interpolation=cv2.INTER_AREA)
    assert np.allclose(view.load_rgb(), expected, atol=1e-6)


def test_images_load_lazily_as_rgb_and_grey(workspace_dir):
    root, _ = workspace_dir
    view = Workspace.open(root)["view_00.png"]
    rgb = view.load_rgb()
    grey = view.load_grey()
    assert rgb.shape == (48, 64, 3) and grey.shape == (48, 64)
    expected = 0.299 * rgb[..., 0] + 0.587 * rgb[..., 1] + 0.114 * rgb[..., 2]
    np.testing.assert_allclose(grey, expected, atol=1e-3)


def test_image_size_differs_from_camera(workspace_dir):
    root, _ = workspace_dir
    cv2.imwrite(str(root / "images" / "view_02.png"), np.zeros((10, 10, 3), np.uint8))
    with pytest.raises(ImageReadError, match="10x10 but its camera"):
        Workspace.open(root)["view_02.png"].load_rgb()
