"""Queries of the sparse model: the points each view observes, depth ranges as COLMAP computes
them, the points two views share with their triangulation angles, and overlap."""

import numpy as np
import pytest

from dvpmvs.model import NoDepthRangeError
from dvpmvs.workspace import Workspace
from tests.scenes import make_workspace


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    root = tmp_path_factory.mktemp("model") / "ws"
    truth = make_workspace(root)
    return Workspace.open(root), truth


def _tracks(truth):
    """point -> the image ids observing it, from the reconstruction the test wrote."""
    return {
        pid: {e.image_id for e in p.track.elements}
        for pid, p in truth["reconstruction"].points3D.items()
    }


def test_each_view_observes_the_points_of_its_tracks(scene):
    ws, truth = scene
    tracks, points = _tracks(truth), truth["reconstruction"].points3D
    for name, view in ws.views.items():
        expected = np.array(
            sorted(
                points[pid].xyz.tolist() for pid, seen in tracks.items() if view.image_id in seen
            )
        )
        assert np.array_equal(np.array(sorted(ws.model.observed_points(name).tolist())), expected)


def test_depth_ranges_are_computed_for_the_views_and_leave_them_alone(scene):
    # COLMAP's Model::ComputeDepthRanges: the views keep theirs; a given range is every view's.
    ws, _ = scene
    before = {name: view.depth_range for name, view in ws.views.items()}
    wider = ws.model.depth_ranges((0.01, 0.99), 0.5, 3)
    assert {name: view.depth_range for name, view in ws.views.items()} == before
    for name, found in wider.items():
        assert (
            found.range[0] < before[name][0]
            and found.range[1] > before[name][1]
            and found.num_points > 3
        )
    assert all(
        r.range == (1.0, 2.0) and r.num_points == 0
        for r in ws.model.depth_ranges((0.01, 0.99), 0.5, 3, (1.0, 2.0)).values()
    )
    with pytest.raises(NoDepthRangeError, match="observes at least 100000 sparse points"):
        ws.model.depth_ranges((0.01, 0.99), 0.25, 100_000)


def test_shared_points_carry_the_triangulation_angle_of_each_point(scene):
    ws, truth = scene
    tracks, points = _tracks(truth), truth["reconstruction"].points3D
    names = list(ws.views)
    reference = ws.views[names[0]]
    shared = ws.model.covisibility[reference.name]
    assert set(shared) <= set(names[1:]) and len(ws.model.covisibility) == len(names)
    for other_name, angles in shared.items():
        other = ws.views[other_name]
        both = [pid for pid, seen in tracks.items() if {reference.image_id, other.image_id} <= seen]
        expected = []
        for pid in both:
            a, b = reference.center - points[pid].xyz, other.center - points[pid].xyz
            expected.append(np.degrees(np.arccos(a @ b / np.linalg.norm(a) / np.linalg.norm(b))))
        assert np.allclose(np.sort(angles), np.sort(expected))
    with pytest.raises(KeyError):
        ws.model.covisibility["not_a_view.png"]


def test_a_view_overlaps_a_source_that_shares_a_point(scene):
    ws, _ = scene
    assert all(ws.model.overlaps(view) for view in ws.reference_views())
