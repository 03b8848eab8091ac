"""The previews people look at: depth, normals and cost as 8-bit images, written atomically."""

import cv2
import numpy as np
import pytest

from dvpmvs.preview import colorize_cost, colorize_depth, colorize_normals, write_png


def test_depth_runs_through_the_colour_map_between_the_given_bounds_and_is_black_where_missing():
    depth = np.tile(np.arange(255) + 0.5, (2, 1))  # level k of 255 between the bounds 0 and 255
    depth[0, :10] = 0
    bgr = colorize_depth(depth, 0.0, 255.0)
    turbo = cv2.applyColorMap(np.arange(255, dtype=np.uint8)[None], cv2.COLORMAP_TURBO)[0]
    assert bgr.dtype == np.uint8 and np.array_equal(bgr[1], turbo)
    assert not bgr[0, :10].any() and np.array_equal(bgr[0, 10:], turbo[10:])
    assert not colorize_depth(np.zeros((3, 4), np.float32)).any()
    # Without bounds, the 1st and 99th percentiles of the valid depths.
    far = depth[1:] * 2 + 7
    assert np.array_equal(
        colorize_depth(far), colorize_depth(far, np.percentile(far, 1), np.percentile(far, 99))
    )


def test_normals_map_to_colours_and_a_missing_normal_is_black():
    normal = np.zeros((1, 3, 3), np.float32)
    normal[0, 0] = (0, 0, -1)  # facing the camera
    normal[0, 1] = (1, 0, 0)
    bgr = colorize_normals(normal)
    assert bgr[0, 0].tolist() == [0, 127, 127] and bgr[0, 1].tolist() == [127, 127, 255]
    assert bgr[0, 2].tolist() == [0, 0, 0]


def test_cost_is_grey_from_certain_to_the_bound_and_nan_is_the_worst():
    cost = np.array([[0.0, 0.5, 2.0, np.nan]], np.float32)
    assert colorize_cost(cost).tolist() == [[0, 127, 255, 255]]


def test_a_png_is_written_whole_or_not_at_all(tmp_path):
    image = np.random.default_rng(0).integers(0, 255, (8, 9, 3), dtype=np.uint8)
    path = write_png(tmp_path / "previews" / "v.png", image)
    assert np.array_equal(cv2.imread(str(path)), image)
    with pytest.raises(cv2.error):  # OpenCV refuses an empty image
        write_png(tmp_path / "previews" / "w.png", np.zeros((0, 0, 3), np.uint8))
    assert sorted(p.name for p in (tmp_path / "previews").iterdir()) == ["v.png"]
