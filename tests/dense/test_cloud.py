"""The fused cloud (``dvpmvs.dense.cloud``, ``dvpmvs.fusion``): its record, our fusion of true maps,
COLMAP's fusion and programs reading our maps and cloud, and a fusion without maps."""

import shutil
import subprocess
from dataclasses import replace

import numpy as np
import open3d as o3d
import pytest

from dvpmvs.dense import (
    DenseOptions,
    cloud_record_path,
    run_dense,
)
from dvpmvs.evaluation.commands import eth3d_parameters_for
from dvpmvs.evaluation.eth3d_metric import evaluate_eth3d
from dvpmvs.evaluation.pointclouds import read_meshlab_project, read_points
from dvpmvs.evaluation.synthetic import SynthOptions, generate
from dvpmvs.fusion import (
    FusionError,
    FusionOptions,
    fuse,
    fuse_with_colmap,
    read_visibility,
    visibility_path,
    write_fused_cloud,
)
from dvpmvs.maps import (
    Pass,
    map_path,
    read_depth_map,
    read_normal_map,
    write_depth_map,
    write_normal_map,
)
from dvpmvs.provenance import read_record
from dvpmvs.workspace import Workspace
from tests.dense.tabletop import SMALL, copy_workspace, eth3d_scores, file_times


def test_a_fusion_option_reruns_only_fusion(dense_scene, tmp_path):
    root, first = dense_scene
    workspace = Workspace.open(copy_workspace(root, tmp_path))
    maps_before = file_times(workspace.stereo_dir)
    options = replace(DenseOptions(), fusion=FusionOptions(max_depth_error=0.005))
    summary = run_dense(workspace, options, progress=False)
    assert {r.action for r in summary.reports} == {"reused"} and not summary.fusion_reused
    assert file_times(workspace.stereo_dir) == maps_before
    assert 0 < summary.num_points < first.num_points
    record = read_record(cloud_record_path(summary.output))
    assert record.complete and record.inputs["fusion"]["max_depth_error"] == 0.005
    # Thread counts and the map cache's size change no output: nothing to redo.
    again = run_dense(
        workspace,
        replace(options, fusion=replace(options.fusion, num_threads=1, cache_views=8)),
        progress=False,
    )
    assert again.fusion_reused
    # The cloud's visibility file is part of it: without it the cloud is made again.
    visibility_path(summary.output).unlink()
    again = run_dense(workspace, options, progress=False)
    assert not again.fusion_reused and visibility_path(summary.output).is_file()


def test_colmap_fusion_reads_our_maps(dense_scene, tmp_path):
    root, summary = dense_scene
    workspace = Workspace.open(copy_workspace(root, tmp_path))
    out = tmp_path / "colmap.ply"
    count = fuse_with_colmap(workspace, out, FusionOptions())
    ours = eth3d_scores(root, summary.output)
    theirs = eth3d_scores(root, out)
    # COLMAP merges ~2 px clusters into one point: measured 1,108-1,109 of our 2,972 (its threads
    # make the count vary by one), accuracy 99.9 %, F1 at 2 cm 38.3 against our 42.1.
    assert count == len(read_points(out)) > 1_000
    assert theirs.accuracy[0] > 0.97
    assert abs(theirs.f1[0] - ours.f1[0]) < 0.05


def test_fusion_of_true_maps_is_accurate_and_needs_agreement(dense_scene, tmp_path):
    root, _ = dense_scene
    workspace = Workspace.open(copy_workspace(root, tmp_path))
    truth = workspace.root / "ground_truth"
    for view in workspace.reference_views():
        write_depth_map(
            map_path(workspace.stereo_dir, view.name, "depth", Pass.GEOMETRIC),
            read_depth_map(truth / "depth_maps" / f"{view.name}.bin"),
        )
        write_normal_map(
            map_path(workspace.stereo_dir, view.name, "normal", Pass.GEOMETRIC),
            read_normal_map(truth / "normal_maps" / f"{view.name}.bin"),
        )
    cloud = fuse(workspace, FusionOptions())
    mlp = truth / "scan_alignment.mlp"
    result = evaluate_eth3d(
        cloud.points, read_meshlab_project(mlp), (0.01,), eth3d_parameters_for(mlp)
    )
    assert result.accuracy[0] > 0.99
    assert len(cloud) > SMALL[0] * SMALL[1]  # 8,026 measured: 4 views of 6,912 pixels
    assert np.allclose(np.linalg.norm(cloud.normals, axis=1), 1, atol=1e-4)
    stricter = fuse(workspace, FusionOptions(min_consistent_views=3))
    assert 0 < len(stricter) < len(cloud)
    # The same maps, one thread or two: the same cloud.
    single = fuse(workspace, FusionOptions(num_threads=1))
    assert np.array_equal(single.points, cloud.points)


def _share_seen_as_stated(workspace, points, visibility, truth):
    """The share of (point, supporting image) pairs where the point projects into the image at
    its true depth (within 1 %): an image index that names the wrong image fails this."""
    names = {i: name for name, i in workspace.colmap_image_indices.items()}
    hits = total = 0
    for point, images in zip(points, visibility):
        for index in images:
            view = workspace[names[int(index)]]
            x = view.R @ point + view.t
            u, v = np.round((view.K @ (x / x[2]))[:2]).astype(int)
            depth = truth[view.name]
            total += 1
            hits += bool(
                0 <= u < view.width
                and 0 <= v < view.height
                and abs(depth[v, u] - x[2]) < 0.01 * x[2]
            )
    return hits / total


def test_the_cloud_names_its_supporting_views_as_colmap_does(dense_scene, tmp_path):
    root, _ = dense_scene
    workspace = Workspace.open(copy_workspace(root, tmp_path))
    truth = {}
    for view in workspace.reference_views():
        truth[view.name] = read_depth_map(
            workspace.root / "ground_truth" / "depth_maps" / f"{view.name}.bin"
        )
        write_depth_map(
            map_path(workspace.stereo_dir, view.name, "depth", Pass.GEOMETRIC), truth[view.name]
        )
        write_normal_map(
            map_path(workspace.stereo_dir, view.name, "normal", Pass.GEOMETRIC),
            read_normal_map(workspace.root / "ground_truth" / "normal_maps" / f"{view.name}.bin"),
        )
    cloud = fuse(workspace, FusionOptions())
    ours = tmp_path / "ours.ply"
    write_fused_cloud(ours, cloud)
    visibility = read_visibility(visibility_path(ours))
    assert len(visibility) == len(read_points(ours)) == len(cloud)
    assert min(len(images) for images in visibility) >= 3  # the reference and >= 2 agreeing views
    rng = np.random.default_rng(0)
    sample = rng.choice(len(cloud), 500, replace=False)
    assert (
        _share_seen_as_stated(
            workspace, cloud.points[sample], [visibility[i] for i in sample], truth
        )
        > 0.99
    )
    # COLMAP's fusion numbers the images the same way: its points are seen where it says too.
    theirs = tmp_path / "colmap.ply"
    fuse_with_colmap(workspace, theirs, FusionOptions())
    their_points, their_visibility = read_points(theirs), read_visibility(visibility_path(theirs))
    sample = rng.choice(len(their_points), 500, replace=False)
    assert (
        _share_seen_as_stated(
            workspace,
            their_points[sample].astype(np.float64),
            [their_visibility[i] for i in sample],
            truth,
        )
        > 0.99
    )


def _colmap(*args, cwd):
    """COLMAP's own command-line program (Debian's ``colmap``), or a skip saying why not."""
    if shutil.which("colmap") is None:
        pytest.skip(
            "COLMAP's command-line program is not installed (`make test` installs Debian's `colmap` "
            "where apt-get can be used)"
        )
    return subprocess.run(["colmap", *args], cwd=cwd, capture_output=True, text=True, timeout=600)


def test_colmap_program_fuses_our_maps(dense_scene, tmp_path):
    root, summary = dense_scene
    ws = copy_workspace(root, tmp_path)
    run = _colmap(
        "stereo_fusion",
        "--workspace_path",
        ws,
        "--workspace_format",
        "COLMAP",
        "--input_type",
        "geometric",
        "--output_path",
        ws / "colmap_cli.ply",
        cwd=tmp_path,
    )
    assert run.returncode == 0, run.stderr[-2000:]
    points = read_points(ws / "colmap_cli.ply")
    assert len(points) > 450  # 504 measured (COLMAP's 2 px default merges ~2 px clusters)
    assert eth3d_scores(root, ws / "colmap_cli.ply").accuracy[0] > 0.9
    assert len(read_visibility(ws / "colmap_cli.ply.vis")) == len(points)


@pytest.mark.slow
def test_colmap_program_meshes_our_cloud(dense_scene, tmp_path):
    root, summary = dense_scene
    ws = copy_workspace(root, tmp_path)
    assert visibility_path(ws / "fused.ply").is_file()
    # COLMAP's Poisson mesher reads the cloud; its Delaunay mesher also reads fused.ply.vis.
    # (COLMAP's default trim, 10, removes every vertex of a cloud this small: 3k points.)
    run = _colmap(
        "poisson_mesher",
        "--input_path",
        ws / "fused.ply",
        "--output_path",
        ws / "poisson.ply",
        "--PoissonMeshing.trim",
        "5",
        cwd=tmp_path,
    )
    assert run.returncode == 0, run.stderr[-2000:]
    assert (
        len(o3d.io.read_triangle_mesh(str(ws / "poisson.ply")).triangles) > 8_000
    )  # 11,511 measured
    run = _colmap(
        "delaunay_mesher",
        "--input_path",
        ws,
        "--input_type",
        "dense",
        "--output_path",
        ws / "delaunay.ply",
        cwd=tmp_path,
    )
    if "requires CGAL" in run.stdout + run.stderr:
        pytest.skip(
            "this COLMAP was built without CGAL (Debian 12's colmap 3.8 is), so its delaunay_mesher "
            "cannot run; the .vis layout and image numbering are checked against COLMAP's fusion instead"
        )
    assert run.returncode == 0, run.stderr[-2000:]
    assert len(o3d.io.read_triangle_mesh(str(ws / "delaunay.ply")).triangles) > 1_000


def test_fusion_without_maps_says_what_to_run(tmp_path):
    root = tmp_path / "ws"
    generate(root, SynthOptions(scene="tabletop", views=3, width=64, priors=False))
    workspace = Workspace.open(root)
    with pytest.raises(FusionError, match="dvpmvs dense"):
        fuse(workspace)
    with pytest.raises(FusionError, match="dvpmvs dense"):
        fuse_with_colmap(workspace, tmp_path / "x.ply")
