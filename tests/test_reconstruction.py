"""From photos to a mesh: structure from motion on the embedded scene's images alone (its poses
discarded), the recovered poses against the true ones, resuming, known intrinsics, a given sparse
model, and bad input."""

import shutil

import open3d as o3d
import pycolmap
import pytest

import dvpmvs
from dvpmvs.cli import main
from dvpmvs.evaluation.embedded import EMBEDDED_SCENE
from dvpmvs.evaluation.poses import pose_errors
from dvpmvs.fusion import read_visibility
from dvpmvs.maps import read_depth_map
from dvpmvs.reconstruction import ReconstructionError, SfmOptions, run_structure_from_motion
from tests.test_report import CHROMIUM

PHOTOS = EMBEDDED_SCENE / "images"
TRUTH = EMBEDDED_SCENE / "sparse"
# The dense stage at half the photos' size (SfM sees them whole): what is checked here does not
# depend on the maps' size.
DENSE = ["quality=fast", "previews=false", "max_image_size=160"]
FAST = [*DENSE, "meshing.depth=9"]


@pytest.fixture(scope="module")
def project(tmp_path_factory):
    out = tmp_path_factory.mktemp("reconstruct") / "project"
    assert main(["reconstruct", f"images={PHOTOS}", f"out={out}", *FAST]) == 0
    return out


@pytest.mark.slow
def test_photos_alone_give_a_workspace_maps_a_cloud_and_a_mesh(project):
    assert (project / "database.db").is_file()
    dense = project / "dense"
    for name in ("0000.png", "0001.png", "0002.png", "0003.png", "0004.png"):
        depth = read_depth_map(dense / "stereo" / "depth_maps" / f"{name}.geometric.bin")
        assert (depth > 0).mean() > 0.5
    cloud = o3d.io.read_point_cloud(str(dense / "fused.ply"))
    assert len(cloud.points) > 14_000  # 17,367 measured
    assert len(read_visibility(dense / "fused.ply.vis")) == len(cloud.points)
    assert (
        len(o3d.io.read_triangle_mesh(str(dense / "meshed-poisson.ply")).triangles) > 50_000
    )  # 79,789
    # its report: the cloud, a link to the mesh, and the mesh drawn in 3D
    page = (dense / "report.html").read_text()
    assert 'href="meshed-poisson.ply"' in page and (dense / "report_files" / "cloud.js").is_file()
    assert "; the mesh, " in page and " triangles, drawn with the points" in page


@pytest.mark.slow
@pytest.mark.skipif(CHROMIUM is None, reason="no Chromium (scripts/system-deps.sh --test)")
def test_the_reports_viewer_draws_the_mesh(project, tmp_path):
    from tests.test_report import _drawn_fraction, _open_in_chromium

    page = project / "dense" / "report.html"
    shots = {}
    for show in ("points", "mesh"):
        problems, outside, pictures, _ = _open_in_chromium(
            page,
            tmp_path / f"{show}.png",
            "#cloud .viewer canvas",
            script=f"window.dvpmvsReport.viewers[0].show('{show}')",
        )
        assert problems == [] and outside == [] and len(pictures) == 1
        shots[show] = pictures[0]
    # The mesh alone covers far more of the view than the points (a surface, not samples):
    # measured 0.36 against 0.085.
    assert _drawn_fraction(shots["mesh"]) > 0.28 and _drawn_fraction(shots["points"]) > 0.05
    assert _drawn_fraction(shots["mesh"]) > 3 * _drawn_fraction(shots["points"])
    assert shots["mesh"].reshape(-1, 3).std(axis=0).min() > 20


@pytest.mark.slow
def test_recovered_poses_agree_with_the_true_ones(project):
    # Five 320x240 renders of a room with bare walls give the mapper ~110 points: the poses are
    # good to a few degrees (5.2 deg and 5.1 % of the camera extent at most, measured), not more.
    errors = pose_errors(
        pycolmap.Reconstruction(str(project / "sparse" / "0")), pycolmap.Reconstruction(str(TRUTH))
    )
    assert len(errors.names) == 5
    assert errors.rotation.max() < 6.0
    assert errors.centre.max() < 0.06 * errors.extent


@pytest.mark.slow
def test_a_rerun_skips_every_finished_stage(project):
    mtimes = {p: p.stat().st_mtime_ns for p in project.rglob("*") if p.is_file()}
    summary = dvpmvs.reconstruct(PHOTOS, project, overrides=FAST)
    assert [s.name for s in summary.stages] == [
        "features",
        "matching",
        "mapping",
        "undistortion",
        "dense",
        "mesh",
    ]
    assert all(s.reused for s in summary.stages)
    changed = [
        p for p, t in mtimes.items() if p.stat().st_mtime_ns != t and not p.name.endswith(".lock")
    ]
    assert not changed
    # Another matching option: matching and everything after it run again, not the features.
    summary = dvpmvs.reconstruct(PHOTOS, project, overrides=[*FAST, "sfm.matching=sequential"])
    assert [s.reused for s in summary.stages] == [True, False, False, False, False, False]


def test_known_intrinsics_are_held_and_help(tmp_path):
    reports = []
    options = SfmOptions(
        camera_model="PINHOLE", camera_params="224,224,160,120", single_camera=True
    )
    model_dir, _, _ = run_structure_from_motion(PHOTOS, tmp_path, options, True, reports)
    model = pycolmap.Reconstruction(str(model_dir))
    assert [list(c.params) for c in model.cameras.values()] == [[224.0, 224.0, 160.0, 120.0]]
    errors = pose_errors(model, pycolmap.Reconstruction(str(TRUTH)))
    assert (
        len(errors.names) == 5 and errors.rotation.max() < 4.0
    )  # 3.6 deg measured (5.2 estimated)
    # The same photos and seed: the same model, bit for bit.
    again = tmp_path / "again"
    run_structure_from_motion(PHOTOS, again, options, True, [])
    for name in ("cameras.bin", "images.bin", "points3D.bin"):
        assert (again / "sparse" / "0" / name).read_bytes() == (model_dir / name).read_bytes()


def test_each_structure_from_motion_stage_says_why_it_runs_and_how_far_it_is(
    tmp_path, monkeypatch, caplog
):
    # COLMAP's calls say nothing until they return: the stages' lines come from their counts
    # (the database's rows, the photos the mapper tries), here at every poll. Read often while
    # COLMAP writes: a reader that took SQLite's locks made COLMAP abort the process.
    import logging

    import dvpmvs.stage_progress as stage_progress

    monkeypatch.setattr(stage_progress, "HEARTBEAT_SECONDS", 0.0)
    monkeypatch.setattr(stage_progress, "POLL_SECONDS", 0.01)
    with caplog.at_level(logging.INFO, logger="dvpmvs"):
        run_structure_from_motion(PHOTOS, tmp_path, SfmOptions(), True, [])
    said = [r.getMessage() for r in caplog.records]
    for stage in ("features", "matching", "mapping"):
        assert f"{stage}: computing (" in "\n".join(said), said
    assert "features: computing (not computed yet)" in said
    assert "matching: computing (the stage before it was computed again)" in said
    counts = [line for line in said if " of 5 photos (" in line or " of 10 pairs (" in line]
    assert counts, said
    assert any(line.startswith("mapping: ") and " photos tried in " in line for line in said)


@pytest.mark.slow
def test_a_given_sparse_model_skips_structure_from_motion(tmp_path):
    summary = dvpmvs.reconstruct(
        PHOTOS,
        tmp_path / "project",
        overrides=[*FAST, "mesh=false", "geometric=false"],
        sparse_path=TRUTH,
    )
    assert [s.name for s in summary.stages] == ["undistortion", "dense"]
    assert not (tmp_path / "project" / "database.db").exists()
    model = pycolmap.Reconstruction(str(tmp_path / "project" / "dense" / "sparse"))
    errors = pose_errors(model, pycolmap.Reconstruction(str(TRUTH)))
    assert errors.rotation.max() < 1e-6 and errors.centre.max() < 1e-9 and summary.mesh is None


def test_bad_input_says_what_to_do(tmp_path, capsys):
    photos = tmp_path / "photos"
    photos.mkdir()
    shutil.copy(PHOTOS / "0000.png", photos)
    with pytest.raises(ReconstructionError, match="1 photo.*at least 2"):
        dvpmvs.reconstruct(photos, tmp_path / "out")
    with pytest.raises(SystemExit, match="1"):
        main(["reconstruct", f"images={tmp_path / 'none'}", f"out={tmp_path / 'out'}"])
    assert "is not a folder of photos" in capsys.readouterr().err
    with pytest.raises(ValueError, match="has 3 values; PINHOLE takes 4"):
        SfmOptions(camera_model="PINHOLE", camera_params="1,2,3")
    with pytest.raises(ValueError, match="not a COLMAP camera model"):
        SfmOptions(camera_model="FISHEYE9")
    with pytest.raises(SystemExit, match="1"):
        main(["reconstruct", f"images={photos}", f"out={tmp_path / 'out'}", "sfm.matching=vocab"])
    assert "sfm.matching must be one of" in capsys.readouterr().err


@pytest.mark.slow
def test_dense_undistorts_a_distorted_project_on_request(project, tmp_path, capsys):
    colmap_project = (
        tmp_path / "colmap_project"
    )  # what `colmap mapper` leaves: images/ and sparse/0
    colmap_project.mkdir()
    (colmap_project / "images").symlink_to(PHOTOS, target_is_directory=True)
    shutil.copytree(project / "sparse", colmap_project / "sparse")
    assert {
        c.model.name
        for c in pycolmap.Reconstruction(str(colmap_project / "sparse" / "0")).cameras.values()
    } == {"SIMPLE_RADIAL"}
    with pytest.raises(SystemExit):
        main(["dense", f"workspace={colmap_project}", *DENSE])
    assert "undistort=true" in capsys.readouterr().err
    assert main(["dense", f"workspace={colmap_project}", "undistort=true", *DENSE]) == 0
    dense = colmap_project / "dense"
    assert (dense / "fused.ply").is_file() and len(
        list((dense / "stereo" / "depth_maps").glob("*.geometric.bin"))
    ) == 5
    assert {
        c.model.name for c in pycolmap.Reconstruction(str(dense / "sparse")).cameras.values()
    } == {"PINHOLE"}
    stamp = (dense / "sparse" / "cameras.bin").stat().st_mtime_ns
    assert main(["dense", f"workspace={colmap_project}", "undistort=true", *DENSE]) == 0
    assert (dense / "sparse" / "cameras.bin").stat().st_mtime_ns == stamp  # undistorted once
    # Masks of the distorted photos are undistorted with them, not laid over the new images.
    import cv2
    import numpy as np

    masks = colmap_project / "photo_masks"
    masks.mkdir()
    for photo in sorted(PHOTOS.glob("*.png")):
        height, width = cv2.imread(str(photo)).shape[:2]
        keep = np.full((height, width), 255, np.uint8)
        keep[:, int(0.8 * width) :] = 0  # the right 20 % of every photo
        cv2.imwrite(str(masks / f"{photo.name}.png"), keep)
    args = ["dense", f"workspace={colmap_project}", "undistort=true", *DENSE]
    assert main([*args, "mask=files", "mask.path=photo_masks"]) == 0  # relative: the project's
    for image in sorted((dense / "images").glob("*.png")):
        undistorted = cv2.imread(str(dense / "masks" / f"{image.name}.png"), cv2.IMREAD_GRAYSCALE)
        assert undistorted.shape == cv2.imread(str(image)).shape[:2]
        assert 0.15 < (undistorted == 0).mean() < 0.25
        kept = cv2.imread(str(dense / "stereo" / "mask_maps" / f"{image.name}.png"), 0) > 0
        depth = read_depth_map(dense / "stereo" / "depth_maps" / f"{image.name}.geometric.bin")
        assert kept.shape == depth.shape and not (depth[~kept] > 0).any()


@pytest.mark.slow
def test_masks_reach_feature_extraction_and_the_undistorted_workspace(tmp_path):
    """Masks given for the photos (OpenMVS's layout here): no feature extracted under a mask (read
    back from the database), the masks undistorted with the photos into dense/masks in COLMAP's
    layout, and no depth under them."""
    import cv2
    import numpy as np

    masks = tmp_path / "masks"
    masks.mkdir()
    for photo in sorted(PHOTOS.glob("*.png")):
        height, width = cv2.imread(str(photo)).shape[:2]
        labels = np.ones((height, width), np.uint16)
        labels[:, int(0.8 * width) :] = 4  # the right 20 % of every photo
        cv2.imwrite(str(masks / f"{photo.stem}.mask.png"), labels)
    project = tmp_path / "project"
    overrides = [
        *FAST,
        "mesh=false",
        "mask=files",
        f"mask.path={masks}",
        "mask.layout=openmvs",
        "mask.ignore_label=4",
    ]
    summary = dvpmvs.reconstruct(PHOTOS, project, overrides=overrides)
    assert [s.name for s in summary.stages] == [
        "masks",
        "features",
        "matching",
        "mapping",
        "undistortion",
        "dense",
    ]
    # A rerun reuses every stage (before pycolmap opens the database, which writes to it).
    again = dvpmvs.reconstruct(PHOTOS, project, overrides=overrides).stages
    assert all(s.reused for s in again), again
    with pycolmap.Database.open(project / "database.db") as db:
        images = db.read_all_images()
        assert len(images) == 5
        for image in images:
            width = db.read_camera(image.camera_id).width
            keypoints = db.read_keypoints(image.image_id)
            assert len(keypoints) > 100
            assert keypoints[:, 0].max() < 0.8 * width + 0.5, image.name
    dense = project / "dense"
    for image in sorted((dense / "images").glob("*.png")):
        keep = cv2.imread(str(dense / "masks" / f"{image.name}.png"), cv2.IMREAD_GRAYSCALE)
        assert keep.shape == cv2.imread(str(image)).shape[:2]
        assert set(np.unique(keep)) == {0, 255} and 0.15 < (keep == 0).mean() < 0.25
        depth = read_depth_map(dense / "stereo" / "depth_maps" / f"{image.name}.geometric.bin")
        assert not (depth[keep == 0] > 0).any() and (depth[keep > 0] > 0).mean() > 0.3
