"""The estimator's contract (dvpmvs/patchmatch/problem.py): views and problems checked on construction, work counts."""

import numpy as np
import pytest

from dvpmvs.patchmatch.problem import LevelWork, Problem, ViewData, pooled_work

pytestmark = pytest.mark.smoke


def _view(name="v", shape=(4, 5), **maps):
    return ViewData(name, np.zeros(shape), np.eye(3), np.eye(3), np.zeros(3), **maps)


def test_a_views_maps_are_normalised_unknown_depth_to_zero_unknown_cost_to_infinity():
    depth = np.array([[1.0, np.nan, -2.0, np.inf, 0.5]] * 4)
    cost = np.array([[0.1, np.nan, np.inf, 0.3, 2.0]] * 4)
    view = _view(depth=depth, cost=cost)
    assert view.shape == (4, 5) and view.image.dtype == np.float32
    assert view.depth[0].tolist() == [1.0, 0.0, 0.0, 0.0, 0.5] and view.depth.dtype == np.float32
    assert np.isinf(view.cost[0, 1]) and view.cost[0, 4] == pytest.approx(2.0)


@pytest.mark.parametrize(
    "maps,message",
    [
        (
            {"depth": np.ones((3, 5))},
            r"view v: depth map \(3, 5\) does not match the image \(4, 5\)",
        ),
        ({"cost": np.ones((4, 4))}, "cost map"),
        (
            {"corrected": np.full((4, 5), np.nan)},
            "the corrected image .* must match the image .* and be finite",
        ),
        ({"highlight": np.ones((5, 4), bool)}, "the highlight mask"),
    ],
)
def test_a_map_of_another_size_is_named_with_its_view(maps, message):
    with pytest.raises(ValueError, match=message):
        _view(**maps)


def test_an_image_that_is_not_a_finite_grey_image_is_refused():
    with pytest.raises(ValueError, match="expected a grey"):
        ViewData("v", np.zeros((4, 5, 3)), np.eye(3), np.eye(3), np.zeros(3))
    with pytest.raises(ValueError, match="NaN or infinite"):
        ViewData("v", np.full((4, 5), np.inf), np.eye(3), np.eye(3), np.zeros(3))


@pytest.mark.parametrize(
    "change,message",
    [
        ({"sources": []}, "view ref has no source views"),
        ({"depth_range": (3.0, 2.0)}, "invalid depth range"),
        ({"depth_range": (0.0, 2.0)}, "invalid depth range"),
        ({"initial": (np.ones((4, 5)), np.ones((4, 5, 2)))}, "the initial maps"),
        ({"labels": np.ones((4, 4))}, "the region labels"),
        ({"mask": np.ones((5, 5))}, "the mask"),
        ({"sparse_points": np.ones((3, 2))}, r"sparse points must be \(N, 3\)"),
    ],
)
def test_a_problem_names_what_does_not_fit_its_reference(change, message):
    arguments = {"sources": [_view("s")], "depth_range": (1.0, 2.0), **change}
    with pytest.raises(ValueError, match=message):
        Problem(_view("ref"), **arguments)


def test_a_problem_keeps_only_the_finite_sparse_points_and_typed_labels():
    points = np.array([[0.0, 0.0, 1.0], [np.nan, 0.0, 1.0], [1.0, 2.0, 3.0]])
    problem = Problem(
        _view("ref"), [_view("s")], (1, 2), labels=np.ones((4, 5)), sparse_points=points
    )
    assert problem.sparse_points.tolist() == [[0.0, 0.0, 1.0], [1.0, 2.0, 3.0]]
    assert problem.labels.dtype == np.int32 and problem.depth_range == (1.0, 2.0)


def test_work_is_counted_per_pixel_and_pooled_per_level_over_views():
    level = LevelWork(0, 10, 5, hypotheses=100, windows=400, samples=4000)
    assert level.per_pixel() == {"hypotheses": 2.0, "windows": 8.0, "samples": 80.0}
    views = [
        dict(level=0, width=10, height=5, hypotheses=100, windows=400, samples=4000),
        dict(level=0, width=10, height=5, hypotheses=300, windows=0, samples=0),
        dict(level=1, width=5, height=2, hypotheses=10, windows=10, samples=10),
    ]
    pooled = pooled_work(views)
    assert [p["level"] for p in pooled] == [0, 1] and pooled[0]["size"] == [10, 5]
    assert (
        pooled[0]["hypotheses"] == 4.0
        and pooled[0]["samples"] == 40.0
        and pooled[1]["windows"] == 1.0
    )
