"""Strecha import end to end (pycolmap SIFT, matching, triangulation with fixed poses).

The scene is a synthetic one written in Strecha's layout, so that the recovered poses and the
reprojection errors can be checked against exact ground truth.
"""

import numpy as np
import pycolmap
import pytest

from dvpmvs.errors import DvpmvsError
from dvpmvs.evaluation.strecha import import_strecha, read_strecha_camera, write_strecha_camera
from dvpmvs.evaluation.synthetic import SynthOptions, generate
from dvpmvs.workspace import Workspace


@pytest.fixture(scope="module")
def strecha_scene(tmp_path_factory):
    root = tmp_path_factory.mktemp("strecha")
    synth = root / "synth"
    generate(synth, SynthOptions(scene="room", views=4, width=480, seed=1, priors=False))
    recon = pycolmap.Reconstruction(str(synth / "sparse"))
    scene = root / "scene"
    (scene / "images").mkdir(parents=True)
    (scene / "gt_dense_cameras").mkdir()
    poses = {}
    for image in recon.images.values():
        (scene / "images" / image.name).write_bytes((synth / "images" / image.name).read_bytes())
        cam = recon.cameras[image.camera_id]
        pose = image.cam_from_world().matrix()
        poses[image.name] = pose
        write_strecha_camera(
            scene / "gt_dense_cameras" / f"{image.name}.camera",
            cam.calibration_matrix(),
            pose[:, :3],
            pose[:, 3],
            cam.width,
            cam.height,
        )
    return scene, poses


def test_camera_file_round_trip(tmp_path):
    R = np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]])
    K = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])
    write_strecha_camera(tmp_path / "a.camera", K, R, np.array([1.0, 2, 3]), 640, 480)
    cam = read_strecha_camera(tmp_path / "a.camera")
    assert (
        np.allclose(cam.R, R)
        and np.allclose(cam.t, [1, 2, 3])
        and (cam.width, cam.height) == (640, 480)
    )
    (tmp_path / "b.camera").write_text("1 2 3\n")
    with pytest.raises(DvpmvsError, match="26 numbers"):
        read_strecha_camera(tmp_path / "b.camera")


@pytest.mark.slow
def test_import_keeps_the_poses_and_triangulates_sub_pixel_points(strecha_scene, tmp_path):
    scene, poses = strecha_scene
    stats = import_strecha(scene, tmp_path / "ws", max_image_size=480, num_sources=3)
    assert stats["images"] == 4
    # Measured: 112 points from 300 observations, 0.26 px mean reprojection error.
    assert 90 < stats["points3D"] < 135
    assert stats["mean_reprojection_error_px"] < 0.4
    recon = pycolmap.Reconstruction(str(tmp_path / "ws" / "sparse"))
    for image in recon.images.values():
        assert np.allclose(image.cam_from_world().matrix(), poses[image.name], atol=1e-6)
    ws = Workspace.open(tmp_path / "ws")
    assert len(ws.references) == 4 and all(len(v.sources) == 3 for v in ws.reference_views())


def test_missing_images_are_named(strecha_scene, tmp_path):
    scene, _ = strecha_scene
    broken = tmp_path / "broken"
    (broken / "images").mkdir(parents=True)
    (broken / "gt_dense_cameras").mkdir()
    for f in (scene / "gt_dense_cameras").iterdir():
        (broken / "gt_dense_cameras" / f.name).write_bytes(f.read_bytes())
    with pytest.raises(DvpmvsError, match="missing"):
        import_strecha(broken, tmp_path / "ws")
