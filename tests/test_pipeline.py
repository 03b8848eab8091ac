"""The dense stage end to end on a small rendered scene (4 views, 200x150), resume, and fusion."""

import shutil
from dataclasses import replace

import numpy as np
import pycolmap
import pytest

from dvpmvs.evaluation.commands import eth3d_parameters_for
from dvpmvs.evaluation.depth_metrics import evaluate_depth_maps
from dvpmvs.evaluation.eth3d_metric import evaluate_eth3d
from dvpmvs.evaluation.pointclouds import read_meshlab_project, read_points
from dvpmvs.evaluation.synthetic import SynthOptions, generate
from dvpmvs.fusion import FusionError, FusionOptions, fuse, fuse_with_colmap
from dvpmvs.maps import Pass, map_path, read_depth_map, read_extra_map, read_normal_map, write_depth_map, \
    write_normal_map
from dvpmvs.pipeline import DenseOptions, maps_complete, run_dense
from dvpmvs.workspace import Workspace


@pytest.fixture(scope="module")
def dense_scene(tmp_path_factory):
    """The tabletop scene, 4 views of 200x150, with the whole dense stage run once."""
    root = tmp_path_factory.mktemp("dense") / "tabletop"
    generate(root, SynthOptions(scene="tabletop", views=4, width=200, priors=False))
    summary = run_dense(Workspace.open(root), DenseOptions(), progress=False)
    return root, summary


def _copy(root, tmp_path):
    target = tmp_path / "ws"
    shutil.copytree(root, target)
    return target


def _eth3d(root, cloud_path):
    mlp = root / "ground_truth" / "scan_alignment.mlp"
    return evaluate_eth3d(read_points(cloud_path), read_meshlab_project(mlp), (0.02, 0.1), eth3d_parameters_for(mlp))


def test_small_scene_reaches_the_stated_depth_accuracy(dense_scene):
    root, summary = dense_scene
    views = evaluate_depth_maps(root / "stereo" / "depth_maps", root / "ground_truth" / "depth_maps")
    assert len(views) == 4
    for view in views:
        # Stated accuracy of this scene (measured 45-65 % of the pixels estimated, 73-74 % of
        # them and 33-48 % of all pixels within 1 %; matching images as they are,
        # `image_sigma=0`: 40-52 %, 89-91 % and 36-47 %: the smoothed walls add estimates that
        # are rougher at this size, and fusion drops the ones the views disagree on):
        assert view.estimated > 0.4, view
        assert view.within_1_percent / view.estimated > 0.65, view
        assert view.within_1_percent > 0.3, view
        assert view.normal_median_deg < 3.0
    result = _eth3d(root, summary.output)
    assert summary.num_points > 10_000  # measured 18,500
    assert result.accuracy[0] > 0.9 and result.f1[1] > 0.6  # measured 98.1 % and 71 (as they are: 99.8 %, 66)


def test_maps_are_complete_and_in_colmap_format(dense_scene):
    root, summary = dense_scene
    workspace = Workspace.open(root)
    for view in workspace.reference_views():
        for pass_ in Pass:
            assert maps_complete(workspace, view, pass_)
            depth = pycolmap.DepthMap()
            depth.read(str(map_path(workspace.stereo_dir, view.name, "depth", pass_)))
            assert (depth.width, depth.height) == (200, 150)
            normal = read_normal_map(map_path(workspace.stereo_dir, view.name, "normal", pass_))
            valid = read_depth_map(map_path(workspace.stereo_dir, view.name, "depth", pass_)) > 0
            assert np.allclose(np.linalg.norm(normal[valid], axis=-1), 1, atol=1e-4)
            visibility = read_extra_map(map_path(workspace.stereo_dir, view.name, "visibility", pass_))
            assert visibility.shape == (150, 200, len(view.sources))
            assert np.allclose(visibility[valid].sum(-1), 1, atol=1e-5)  # weights of selected views
            assert (workspace.stereo_dir / "previews" / f"{view.name}.{pass_.value}.depth.png").is_file()
        # The aligned prior's regions (default providers: coarse_mvs, from_depth, roberts).
        labels = read_extra_map(map_path(workspace.stereo_dir, view.name, "labels", Pass.PHOTOMETRIC))
        assert labels.shape == (150, 200) and labels.max() >= 2 and (labels == np.round(labels)).all()
        assert (workspace.stereo_dir / "previews" / f"{view.name}.labels.png").is_file()
    assert len(summary.computed(Pass.GEOMETRIC)) == 4
    assert all(r.prior_seconds > 0 for r in summary.computed(Pass.PHOTOMETRIC))


def test_rerun_recomputes_only_the_view_whose_map_was_deleted(dense_scene, tmp_path):
    root, _ = dense_scene
    ws_root = _copy(root, tmp_path)
    workspace = Workspace.open(ws_root)
    stereo = workspace.stereo_dir
    victim = workspace.reference_views()[2].name
    original = map_path(stereo, victim, "depth", Pass.GEOMETRIC).read_bytes()
    map_path(stereo, victim, "depth", Pass.GEOMETRIC).unlink()
    others = {p: p.stat().st_mtime_ns for p in (stereo / "depth_maps").iterdir()}
    summary = run_dense(workspace, DenseOptions(fuse=False), progress=False)
    assert summary.computed(Pass.PHOTOMETRIC) == []
    assert [r.name for r in summary.computed(Pass.GEOMETRIC)] == [victim]
    assert all(p.stat().st_mtime_ns == t for p, t in others.items())
    # Same seed, same inputs: the recomputed map is the same, byte for byte.
    assert map_path(stereo, victim, "depth", Pass.GEOMETRIC).read_bytes() == original


def test_truncated_map_counts_as_unfinished(dense_scene, tmp_path):
    root, _ = dense_scene
    workspace = Workspace.open(_copy(root, tmp_path))
    view = workspace.reference_views()[0]
    path = map_path(workspace.stereo_dir, view.name, "cost", Pass.PHOTOMETRIC)
    path.write_bytes(path.read_bytes()[:1000])
    assert not maps_complete(workspace, view, Pass.PHOTOMETRIC)
    summary = run_dense(workspace, DenseOptions(geometric=False, fuse=False), progress=False)
    assert [r.name for r in summary.computed(Pass.PHOTOMETRIC)] == [view.name]


def test_geometric_problem_carries_the_sources_costs_for_the_visibility_restoration(dense_scene, tmp_path):
    from dvpmvs.maps import MapFormatError
    from dvpmvs.patchmatch.options import PatchMatchOptions
    from dvpmvs.pipeline import _problem
    root, _ = dense_scene
    workspace = Workspace.open(_copy(root, tmp_path))
    view = workspace.reference_views()[0]
    restoring = PatchMatchOptions(anchor_visibility=True)
    problem = _problem(workspace, view, Pass.GEOMETRIC, restoring)
    for src in problem.sources:
        stored = read_extra_map(map_path(workspace.stereo_dir, src.name, "cost", Pass.PHOTOMETRIC))
        assert np.array_equal(src.cost, stored.reshape(src.shape))
    # Loaded only where they are used.
    assert all(src.cost is None for src in _problem(workspace, view, Pass.GEOMETRIC, PatchMatchOptions()).sources)
    assert all(src.cost is None for src in _problem(
        workspace, view, Pass.GEOMETRIC, replace(restoring, visibility_restore_radius=0)).sources)
    # A missing cost map is unknown (the kernel then keeps the source's own depths); a corrupt
    # one is an error, not a silent fallback.
    path = map_path(workspace.stereo_dir, problem.sources[0].name, "cost", Pass.PHOTOMETRIC)
    data = path.read_bytes()
    path.unlink()
    assert np.isinf(_problem(workspace, view, Pass.GEOMETRIC, restoring).sources[0].cost).all()
    path.write_bytes(data[:1000])
    with pytest.raises(MapFormatError):
        _problem(workspace, view, Pass.GEOMETRIC, restoring)


def test_colmap_fusion_reads_our_maps(dense_scene, tmp_path):
    root, summary = dense_scene
    workspace = Workspace.open(_copy(root, tmp_path))
    out = tmp_path / "colmap.ply"
    count = fuse_with_colmap(workspace, out, FusionOptions())
    ours = _eth3d(root, summary.output)
    theirs = _eth3d(root, out)
    assert count == len(read_points(out)) > 3_000  # COLMAP merges ~2 px clusters into one point
    assert theirs.accuracy[0] > 0.9
    assert abs(theirs.f1[0] - ours.f1[0]) < 0.1


def test_fusion_of_true_maps_is_accurate_and_needs_agreement(dense_scene, tmp_path):
    root, _ = dense_scene
    workspace = Workspace.open(_copy(root, tmp_path))
    truth = workspace.root / "ground_truth"
    for view in workspace.reference_views():
        write_depth_map(map_path(workspace.stereo_dir, view.name, "depth", Pass.GEOMETRIC),
                        read_depth_map(truth / "depth_maps" / f"{view.name}.bin"))
        write_normal_map(map_path(workspace.stereo_dir, view.name, "normal", Pass.GEOMETRIC),
                         read_normal_map(truth / "normal_maps" / f"{view.name}.bin"))
    cloud = fuse(workspace, FusionOptions())
    mlp = truth / "scan_alignment.mlp"
    result = evaluate_eth3d(cloud.points, read_meshlab_project(mlp), (0.01,), eth3d_parameters_for(mlp))
    assert result.accuracy[0] > 0.99
    assert len(cloud) > 0.5 * 200 * 150
    assert np.allclose(np.linalg.norm(cloud.normals, axis=1), 1, atol=1e-4)
    stricter = fuse(workspace, FusionOptions(min_consistent_views=3))
    assert 0 < len(stricter) < len(cloud)
    # The same maps, one thread or two: the same cloud.
    single = fuse(workspace, FusionOptions(num_threads=1))
    assert np.array_equal(single.points, cloud.points)


def test_fusion_without_maps_says_what_to_run(tmp_path):
    root = tmp_path / "ws"
    generate(root, SynthOptions(scene="tabletop", views=3, width=64, priors=False))
    workspace = Workspace.open(root)
    with pytest.raises(FusionError, match="dvpmvs dense"):
        fuse(workspace)
    with pytest.raises(FusionError, match="dvpmvs dense"):
        fuse_with_colmap(workspace, tmp_path / "x.ply")


def test_dense_options_validate():
    with pytest.raises(ValueError, match="fusion backend"):
        DenseOptions(fusion_backend="openmvs")
    with pytest.raises(ValueError):
        FusionOptions(max_normal_error=0)
    with pytest.raises(ValueError):
        FusionOptions(input_type="final")
    assert replace(DenseOptions(), geometric=False).final_pass is Pass.PHOTOMETRIC
