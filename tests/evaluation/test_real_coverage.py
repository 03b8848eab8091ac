"""Coverage of a view by a cloud, per band of rows (evaluation/experiments/real_coverage.py)."""

from types import SimpleNamespace

import numpy as np

from dvpmvs.evaluation.experiments.real_coverage import coverage, render


def _view(width=40, height=30):
    K = np.array([[30.0, 0, (width - 1) / 2], [0, 30.0, (height - 1) / 2], [0, 0, 1]])
    return SimpleNamespace(K=K, R=np.eye(3), t=np.zeros(3), width=width, height=height)


def _points_at(view, pixels, depth):
    """World points (camera = world) seen at ``pixels`` ((N, 2) col, row) at ``depth``."""
    homogeneous = np.concatenate([pixels, np.ones((len(pixels), 1))], axis=1)
    return depth * homogeneous @ np.linalg.inv(view.K).T


def test_coverage_counts_the_pixels_points_fall_in_closing_one_pixel_gaps_per_band():
    view = _view()
    # Every other column of the bottom 6 rows (the bottom fifth): the closing fills the gaps.
    cols, rows = np.meshgrid(np.arange(0, 40, 2), np.arange(24, 30))
    points = _points_at(view, np.stack([cols.ravel(), rows.ravel()], 1).astype(float), 5.0)
    shares = coverage(points, view)
    # The closing spreads nothing past the band's edge (row 23 stays empty) and closes the gap
    # at the image border (column 39) as any other.
    np.testing.assert_allclose(shares, [0, 0, 0, 0, 100, 20])
    # Points behind the camera or outside the image cover nothing.
    assert not coverage(-points, view).any()
    assert not coverage(points + [100, 0, 0], view).any()


def test_render_keeps_the_nearest_point_of_a_pixel():
    view = _view()
    pixel = np.array([[10.0, 12.0]])
    points = np.concatenate([_points_at(view, pixel, 3.0), _points_at(view, pixel, 6.0)])
    colours = np.array([[1.0, 0, 0], [0, 0, 1.0]])  # near red, far blue
    image = render(points, colours, view)
    assert image[12, 10].tolist() == [0, 0, 255]  # BGR: red
    assert image.sum() == 255
