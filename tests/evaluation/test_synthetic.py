"""The synthetic scene generator: determinism, consistent ground truth, a loadable workspace."""

import json

import cv2
import numpy as np
import pycolmap
import pytest

from dvpmvs.errors import DvpmvsError
from dvpmvs.evaluation.eth3d_metric import ETH3DParameters, evaluate_eth3d
from dvpmvs.evaluation.pointclouds import read_meshlab_project
from dvpmvs.evaluation.synthetic import SynthOptions, generate
from dvpmvs.maps import read_depth_map, read_normal_map
from dvpmvs.workspace import Workspace


@pytest.fixture(scope="module")
def room(tmp_path_factory):
    out = tmp_path_factory.mktemp("room")
    stats = generate(out, SynthOptions(scene="room", views=4, width=160, seed=3))
    return out, stats


def files_of(root):
    """Every file but the writer lock (it names its last holder: not the scene)."""
    from dvpmvs.writer_lock import LOCK_NAME

    return {
        p.relative_to(root): p.read_bytes()
        for p in sorted(root.rglob("*"))
        if p.is_file() and p.name != LOCK_NAME
    }


def test_same_seed_same_bytes_other_seed_other_scene(tmp_path):
    opts = SynthOptions(scene="tabletop", views=3, width=64, seed=7)
    generate(tmp_path / "a", opts)
    generate(tmp_path / "b", opts)
    a, b = files_of(tmp_path / "a"), files_of(tmp_path / "b")
    assert a.keys() == b.keys() and len(a) > 20
    assert [k for k in a if a[k] != b[k]] == []
    generate(tmp_path / "c", SynthOptions(scene="tabletop", views=3, width=64, seed=8))
    c = files_of(tmp_path / "c")
    assert (
        c[next(k for k in c if k.suffix == ".png")] != a[next(k for k in a if k.suffix == ".png")]
    )


# Per family: the share of the first view with a surface (the rest is sky) and the sparse points
# of 3 views at 96x72, as measured; the bounds are a few per cent around them.
FAMILIES = {
    "room": (1.0, 218),
    "facade": (0.868, 440),
    "tabletop": (1.0, 191),
    "street": (0.97, 336),
    "courtyard": (0.663, 225),
}


@pytest.mark.parametrize("scene", sorted(FAMILIES))
def test_every_family_renders_valid_ground_truth(scene, tmp_path):
    stats = generate(tmp_path, SynthOptions(scene=scene, views=3, width=96, seed=0, priors=False))
    depth = read_depth_map(tmp_path / "ground_truth" / "depth_maps" / "0000.png.bin")
    normal = read_normal_map(tmp_path / "ground_truth" / "normal_maps" / "0000.png.bin")
    assert depth.shape == (72, 96) and normal.shape == (72, 96, 3)
    valid = depth > 0
    surface, sparse = FAMILIES[scene]
    assert surface - 0.03 <= valid.mean() <= surface + 0.01
    assert np.allclose(np.linalg.norm(normal[valid], axis=1), 1, atol=1e-4)
    K = np.array(stats["intrinsics"]["params"])
    rows, cols = np.nonzero(valid)
    rays = np.stack([(cols - K[2]) / K[0], (rows - K[3]) / K[1], np.ones(len(rows))], 1)
    assert np.all(np.sum(normal[valid] * rays, axis=1) < 1e-6)  # normals face the camera
    assert 0.85 * sparse < stats["sparse_points"] < 1.15 * sparse
    image = cv2.imread(str(tmp_path / "images" / "0000.png"))
    assert image.shape == (72, 96, 3) and image.std() > 10


def test_ground_truth_depth_warps_one_view_onto_another(room):
    out, _ = room
    recon = pycolmap.Reconstruction(str(out / "sparse"))
    images = {im.name: im for im in recon.images.values()}
    cam = recon.cameras[1]
    K = cam.calibration_matrix()
    ref, src = images["0001.png"], images["0002.png"]
    ref_img = cv2.imread(str(out / "images" / ref.name)).astype(np.float32) / 255
    src_img = cv2.imread(str(out / "images" / src.name)).astype(np.float32) / 255
    depth = read_depth_map(out / "ground_truth" / "depth_maps" / f"{ref.name}.bin")
    src_depth = read_depth_map(out / "ground_truth" / "depth_maps" / f"{src.name}.bin")

    def warp_error(depth_scale):
        rows, cols = np.nonzero(depth > 0)
        z = depth[rows, cols] * depth_scale
        cam_pts = np.stack([(cols - K[0, 2]) / K[0, 0] * z, (rows - K[1, 2]) / K[1, 1] * z, z], 1)
        ref_pose, src_pose = ref.cam_from_world().matrix(), src.cam_from_world().matrix()
        world = (cam_pts - ref_pose[:, 3]) @ ref_pose[:, :3]
        pc = world @ src_pose[:, :3].T + src_pose[:, 3]
        x = K[0, 0] * pc[:, 0] / pc[:, 2] + K[0, 2]
        y = K[1, 1] * pc[:, 1] / pc[:, 2] + K[1, 2]
        h, w = depth.shape
        inside = (x > 1) & (x < w - 2) & (y > 1) & (y < h - 2)
        # Visible in the source: its own ground-truth depth agrees (not occluded).
        seen = np.zeros_like(inside)
        seen[inside] = (
            np.abs(
                src_depth[np.round(y[inside]).astype(int), np.round(x[inside]).astype(int)]
                - pc[inside, 2]
            )
            < 0.01 * pc[inside, 2]
        )
        sampled = cv2.remap(
            src_img,
            x[seen].astype(np.float32)[None],
            y[seen].astype(np.float32)[None],
            cv2.INTER_LINEAR,
        )[0]
        return np.abs(sampled - ref_img[rows[seen], cols[seen]]).mean(), seen.mean()

    error, overlap = warp_error(1.0)
    assert overlap > 0.5
    assert error < 0.035  # sensor noise (1 %), shading differences and highlights
    wrong, _ = warp_error(1.03)
    assert wrong > 1.5 * error


def test_sparse_tracks_reproject_within_a_pixel_and_the_workspace_opens(room):
    out, stats = room
    recon = pycolmap.Reconstruction(str(out / "sparse"))
    assert recon.num_points3D() == stats["sparse_points"] > 100
    errors = []
    for point in recon.points3D.values():
        assert point.track.length() >= 2
        for el in point.track.elements:
            image = recon.images[el.image_id]
            xy = recon.cameras[image.camera_id].img_from_cam(image.cam_from_world() * point.xyz)
            errors.append(np.linalg.norm(xy - image.points2D[el.point2D_idx].xy))
    assert max(errors) < 1.0
    ws = Workspace.open(out)
    assert sorted(ws.views) == ["0000.png", "0001.png", "0002.png", "0003.png"]
    lo, hi = ws.views["0001.png"].depth_range
    gt = read_depth_map(out / "ground_truth" / "depth_maps" / "0001.png.bin")
    assert lo <= np.percentile(gt[gt > 0], 5) and hi >= np.percentile(gt[gt > 0], 95)


def test_eth3d_ground_truth_scores_itself_perfectly_and_a_shifted_copy_not(room):
    out, stats = room
    scans = read_meshlab_project(out / "ground_truth" / "scan_alignment.mlp")
    params = ETH3DParameters(
        **json.loads((out / "ground_truth" / "eth3d_parameters.json").read_text())
    )
    assert len(scans) == 4 and sum(len(s.points) for s in scans) == stats["scan_points"]
    points = np.concatenate([s.global_points() for s in scans])
    perfect = evaluate_eth3d(points, scans, [0.01, 0.02], params)
    assert perfect.f1 == pytest.approx([1.0, 1.0])
    # Each scan's points lie on that camera's rays: moving them 3 cm towards their camera puts
    # them in observed free space.
    moved = []
    for s in scans:
        p = s.points * (1 - 0.03 / np.linalg.norm(s.points, axis=1, keepdims=True))
        moved.append(
            p @ s.global_T_scan[:3, :3].T.astype(np.float32)
            + s.global_T_scan[:3, 3].astype(np.float32)
        )
    shifted = evaluate_eth3d(np.concatenate(moved).astype(np.float32), scans, [0.01, 0.02], params)
    assert shifted.accuracy[0] < 0.2 and shifted.completeness[0] < 0.2


def test_simulated_priors_are_close_but_not_equal_to_the_truth(room):
    out, _ = room
    gt = read_depth_map(out / "ground_truth" / "depth_maps" / "0000.png.bin")
    prior = read_depth_map(out / "simulated_priors" / "depth" / "0000.png.bin")
    assert np.all(prior > 0)  # defined everywhere, like a network's output
    valid = gt > 0
    ratio = prior[valid] / gt[valid]
    assert 0.5 < np.median(ratio) < 1.5 and ratio.std() > 0.005
    n_gt = read_normal_map(out / "ground_truth" / "normal_maps" / "0000.png.bin")
    n_prior = read_normal_map(out / "simulated_priors" / "normal" / "0000.png.bin")
    cos = np.sum(n_gt[valid] * n_prior[valid], axis=1)
    assert 0.8 < np.median(cos) < 0.99999
    assert "SIMULATED" in (out / "simulated_priors" / "README.txt").read_text()


def test_bad_options_are_refused():
    with pytest.raises(DvpmvsError, match="unknown scene"):
        SynthOptions(scene="castle")
    with pytest.raises(DvpmvsError, match="at least 2"):
        SynthOptions(views=1)
    # Typed as the core's options: "no" is not false, "4" not 4.
    with pytest.raises(ValueError, match="priors must be true or false, got 'no'"):
        SynthOptions(priors="no")
    with pytest.raises(ValueError, match="views must be an integer"):
        SynthOptions(views="4")


def test_the_courtyard_shows_a_plain_wall_and_open_sky(tmp_path):
    generate(tmp_path, SynthOptions(scene="courtyard", views=3, width=160, seed=0, priors=False))
    for name in ("0000.png", "0002.png"):
        depth = read_depth_map(tmp_path / "ground_truth" / "depth_maps" / f"{name}.bin")
        plain = (
            cv2.imread(str(tmp_path / "ground_truth" / "textureless" / name), cv2.IMREAD_GRAYSCALE)
            > 127
        )
        image = cv2.imread(str(tmp_path / "images" / name), cv2.IMREAD_GRAYSCALE).astype(np.float32)
        sky = depth <= 0
        assert 0.25 <= plain.mean() <= 0.40  # the wall: a third of each view (measured 0.34)
        assert 0.2 <= sky.mean() <= 0.4 and not (plain & sky).any()
        # The sky brighter than the wall; the wall's pixel-to-pixel differences near those of the
        # noise alone (2.55 grey levels: 3.6 rms; 4.8-5.5 measured at this size), the textured
        # surfaces' four times as large.
        assert image[sky].mean() > image[plain].mean() + 10
        step = np.abs(np.diff(image, axis=1))
        inner = plain[:, 1:] & plain[:, :-1]
        textured = ~plain[:, 1:] & ~plain[:, :-1] & ~sky[:, 1:] & ~sky[:, :-1]
        assert np.sqrt(np.mean(step[inner] ** 2)) < 6.0 < np.sqrt(np.mean(step[textured] ** 2)) / 3


def test_sky_points_are_those_no_view_can_hold(tmp_path):
    from dvpmvs.evaluation.depth_metrics import sky_point_share
    from dvpmvs.evaluation.depth_scans import backproject

    generate(tmp_path, SynthOptions(scene="courtyard", views=3, width=96, seed=0, priors=False))
    workspace = Workspace.open(tmp_path)
    views = workspace.reference_views()
    truths = [
        read_depth_map(tmp_path / "ground_truth" / "depth_maps" / f"{v.name}.bin") for v in views
    ]
    view, truth = views[0], truths[0]
    rows, cols = np.nonzero(truth > 0)
    surface = backproject(truth, view.K, view.R, view.t, rows, cols)
    cameras = [(v.K, v.R, v.t) for v in views]
    assert (
        sky_point_share(surface, cameras, truths) < 0.01
    )  # silhouettes within the 2 px margin only
    # Points 10 m along the rays of the first view's sky pixels, far from its border.
    sky = cv2.erode((truth <= 0).astype(np.uint8), np.ones((9, 9), np.uint8)) > 0
    rows, cols = np.nonzero(sky)
    ten = backproject(np.full(truth.shape, 10.0, np.float32), view.K, view.R, view.t, rows, cols)
    share = sky_point_share(np.concatenate([surface, ten]), cameras, truths)
    assert abs(share - len(ten) / (len(ten) + len(surface))) < 0.01
    assert sky_point_share(np.zeros((0, 3)), cameras, truths) == 0.0


def test_synth_replaces_its_scene_whole_and_keeps_folders_it_did_not_write(tmp_path):
    import threading

    from dvpmvs.writer_lock import FolderLockedError, writer_lock

    out = tmp_path / "ws"
    generate(out, SynthOptions(scene="tabletop", views=3, width=64, seed=1, priors=False))
    # A rerun with fewer views leaves exactly the scene it names, not the old views.
    generate(out, SynthOptions(scene="tabletop", views=2, width=64, seed=1, priors=False))
    assert sorted(p.name for p in (out / "images").iterdir()) == ["0000.png", "0001.png"]
    assert len(list((out / "ground_truth" / "depth_maps").iterdir())) == 2
    assert [p.name for p in out.iterdir() if p.name.startswith(".synth")] == []
    # A folder of the user's: refused, untouched; replaced only with overwrite.
    mine = tmp_path / "mine"
    (mine / "images").mkdir(parents=True)
    (mine / "images" / "holiday.png").write_bytes(b"not ours")
    (mine / "scene.json").write_text('{"my": "scene"}')
    options = SynthOptions(scene="tabletop", views=2, width=64, seed=1, priors=False)
    with pytest.raises(DvpmvsError, match="synth did not write"):
        generate(mine, options)
    assert (mine / "images" / "holiday.png").read_bytes() == b"not ours"
    generate(mine, options, overwrite=True)
    assert sorted(p.name for p in (mine / "images").iterdir()) == ["0000.png", "0001.png"]
    assert "intrinsics" in json.loads((mine / "scene.json").read_text())
    # Two synths into one folder: the second stops, naming the first.
    failed = []
    with writer_lock(out):

        def other():
            try:
                generate(out, options)
            except FolderLockedError as exc:
                failed.append(exc)

        thread = threading.Thread(target=other)
        thread.start()
        thread.join()
    assert len(failed) == 1
