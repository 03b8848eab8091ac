"""RGB-D sequences as benchmark scenes (dvpmvs/evaluation/rgbd.py): each layout read from a
fixture the tests write (a synthetic scene's renders, exact depth and poses in that layout's
files), the keyframe rule, the workspace's poses, sensor depth and ETH3D scans; and the shared
7-Scenes clip where ../shared is there."""

import json
from pathlib import Path

import cv2
import numpy as np
import pycolmap
import pytest

from dvpmvs.errors import DvpmvsError
from dvpmvs.evaluation.pointclouds import read_meshlab_project
from dvpmvs.evaluation.rgbd import RGBDOptions, import_rgbd, read_sequence, select_keyframes
from dvpmvs.evaluation.synthetic import SynthOptions, generate
from dvpmvs.maps import read_depth_map
from dvpmvs.workspace import Workspace

SHARED_KITCHEN = Path(__file__).resolve().parents[3] / "shared" / "data" / "7scenes-redkitchen"


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """A synthetic room of 8 views, 160x120: its renders, exact depth (mm) and camera-to-world
    poses, with its intrinsics."""
    out = tmp_path_factory.mktemp("room")
    generate(out, SynthOptions(scene="room", views=8, width=160, seed=3, priors=False))
    model = pycolmap.Reconstruction(str(out / "sparse"))
    frames = []
    for image in sorted(model.images.values(), key=lambda im: im.name):
        pose = np.eye(4)
        pose[:3] = image.cam_from_world().inverse().matrix()
        depth = read_depth_map(out / "ground_truth" / "depth_maps" / f"{image.name}.bin")
        frames.append(
            {
                "color": cv2.imread(str(out / "images" / image.name)),
                "depth": np.round(depth * 1000).astype(np.uint16),
                "pose": pose,
            }
        )
    K = next(iter(model.cameras.values())).calibration_matrix()
    return frames, K


def _seven_scenes(folder: Path, scene) -> Path:
    frames, K = scene
    folder.mkdir()
    for i, frame in enumerate(frames):
        cv2.imwrite(str(folder / f"frame-{i:06d}.color.png"), frame["color"])
        cv2.imwrite(str(folder / f"frame-{i:06d}.depth.png"), frame["depth"])
        np.savetxt(folder / f"frame-{i:06d}.pose.txt", frame["pose"])
    np.savetxt(folder / "camera-intrinsics.txt", K)
    return folder


def _quaternion(R: np.ndarray) -> tuple[float, float, float, float]:
    w = np.sqrt(max(0.0, 1 + np.trace(R))) / 2
    x = np.copysign(np.sqrt(max(0.0, 1 + R[0, 0] - R[1, 1] - R[2, 2])) / 2, R[2, 1] - R[1, 2])
    y = np.copysign(np.sqrt(max(0.0, 1 - R[0, 0] + R[1, 1] - R[2, 2])) / 2, R[0, 2] - R[2, 0])
    z = np.copysign(np.sqrt(max(0.0, 1 - R[0, 0] - R[1, 1] + R[2, 2])) / 2, R[1, 0] - R[0, 1])
    return x, y, z, w


def _tum(folder: Path, scene) -> Path:
    # Colour at 30 Hz, depth 5 ms later, poses at 100 Hz: associated by the nearest time.
    frames, _ = scene
    (folder / "rgb").mkdir(parents=True)
    (folder / "depth").mkdir()
    rgb, depth, truth = (
        ["# timestamp filename"],
        ["# timestamp filename"],
        ["# tx ty tz qx qy qz qw"],
    )
    for i, frame in enumerate(frames):
        t = 1305031102.0 + i / 30
        cv2.imwrite(str(folder / "rgb" / f"{t:.6f}.png"), frame["color"])
        depth_png = np.round(frame["depth"].astype(np.float64) * 5).astype(np.uint16)  # 1/5000 m
        cv2.imwrite(str(folder / "depth" / f"{t + 0.005:.6f}.png"), depth_png)
        rgb.append(f"{t:.6f} rgb/{t:.6f}.png")
        depth.append(f"{t + 0.005:.6f} depth/{t + 0.005:.6f}.png")
        for dt in (-0.01, 0.0, 0.01):
            x, y, z, w = _quaternion(frame["pose"][:3, :3])
            tx, ty, tz = frame["pose"][:3, 3]
            # Only the pose at the image's time is this frame's; the others are a wrong one.
            shift = 0.0 if dt == 0 else 5.0
            truth.append(f"{t + dt:.4f} {tx + shift} {ty} {tz} {x} {y} {z} {w}")
    for name, lines in (("rgb.txt", rgb), ("depth.txt", depth), ("groundtruth.txt", truth)):
        (folder / name).write_text("\n".join(lines) + "\n")
    return folder


def _scannet(folder: Path, scene) -> Path:
    # Colour twice the depth's size (as ScanNet's 1296x968 against 640x480), one lost frame.
    frames, K = scene
    for sub in ("color", "depth", "pose", "intrinsic"):
        (folder / sub).mkdir(parents=True)
    for i, frame in enumerate(frames):
        big = cv2.resize(frame["color"], None, fx=2, fy=2, interpolation=cv2.INTER_CUBIC)
        cv2.imwrite(str(folder / "color" / f"{i}.jpg"), big, [cv2.IMWRITE_JPEG_QUALITY, 98])
        cv2.imwrite(str(folder / "depth" / f"{i}.png"), frame["depth"])
        pose = np.full((4, 4), -np.inf) if i == 2 else frame["pose"]
        np.savetxt(folder / "pose" / f"{i}.txt", pose)
    K4 = np.eye(4)
    K4[:3, :3] = K
    np.savetxt(folder / "intrinsic" / "intrinsic_depth.txt", K4)
    return folder


def _plain(folder: Path, scene) -> Path:
    frames, K = scene
    (folder / "images").mkdir(parents=True)
    (folder / "depth").mkdir()
    lines = []
    for i, frame in enumerate(frames):
        cv2.imwrite(str(folder / "images" / f"v{i}.png"), frame["color"])
        cv2.imwrite(str(folder / "depth" / f"v{i}.png"), frame["depth"])
        lines.append(f"v{i}.png " + " ".join(f"{v:.17g}" for v in frame["pose"][:3].ravel()))
    (folder / "poses.txt").write_text("\n".join(lines) + "\n")
    (folder / "K.txt").write_text(" ".join(str(v) for v in (K[0, 0], K[1, 1], K[0, 2], K[1, 2])))
    return folder


WRITERS = {"7scenes": _seven_scenes, "tum": _tum, "scannet": _scannet, "rgbd": _plain}


@pytest.mark.parametrize("layout", sorted(WRITERS))
def test_each_layout_becomes_a_workspace_with_its_poses_and_sensor_depth(scene, tmp_path, layout):
    frames, K = scene
    source = WRITERS[layout](tmp_path / "sequence", scene)
    # TUM's intrinsics come from the Freiburg camera its folder names, or are given.
    intrinsics = [K[0, 0], K[1, 1], K[0, 2], K[1, 2]] if layout == "tum" else None
    options = RGBDOptions(
        views=4, min_baseline=0.1, min_overlap=0.3, intrinsics=intrinsics, calibrate_color=False
    )
    stats = import_rgbd(layout, source, tmp_path / "ws", options, max_image_size=160, num_sources=3)
    assert stats["keyframes"] == 4
    ws = Workspace.open(tmp_path / "ws")
    assert len(ws.views) == 4
    model = pycolmap.Reconstruction(str(tmp_path / "ws" / "sparse"))
    record = json.loads((tmp_path / "ws" / "rgbd.json").read_text())
    keys = record["keyframes"]
    assert [k["frame"] for k in keys] == sorted({k["frame"] for k in keys})
    kept = [i for i in range(len(frames)) if not (layout == "scannet" and i == 2)]
    for key in keys:
        frame = frames[kept[key["frame"]]]
        image = next(im for im in model.images.values() if im.name == key["image"])
        # The given pose, held fixed by the triangulation.
        assert np.allclose(
            image.cam_from_world().inverse().matrix(), frame["pose"][:3], atol=1e-6
        ), layout
        # The sensor's depth in metres, at the colour image's size (TUM's 1/5000 m read back).
        truth = read_depth_map(
            tmp_path / "ws" / "ground_truth" / "depth_maps" / f"{key['image']}.bin"
        )
        assert truth.shape == (120, 160)
        assert np.abs(truth - frame["depth"] / 1000.0).max() < 2e-4
        # Consecutive keyframes: the first at 10 cm or more, unless the overlap ended first.
        assert key["overlap"] >= 0.3
    assert all(k["baseline"] >= 0.1 or k["overlap"] < 1 for k in keys[1:])
    assert model.num_points3D() > 20
    assert np.allclose(next(iter(model.cameras.values())).calibration_matrix(), K, atol=1e-9)
    # ETH3D scans: one per keyframe, each point seen by another keyframe's sensor.
    scans = read_meshlab_project(tmp_path / "ws" / "ground_truth" / "scan_alignment.mlp")
    assert len(scans) == 4 and all(len(s.points) > 500 for s in scans)
    assert record["scan_points"] == sum(len(s.points) for s in scans)


def test_the_colour_camera_is_calibrated_against_the_poses(scene, tmp_path):
    # 7-Scenes gives the depth camera's intrinsics; its colour images have another focal length.
    # Told a focal length 10 % too long, the import finds the renders' own within 2 % (measured
    # 1.3 % at this fixture's 160x120; SIFT's points on small renders limit it).
    frames, K = scene
    source = _seven_scenes(tmp_path / "seq", scene)
    told = K.copy()
    told[0, 0] *= 1.1
    told[1, 1] *= 1.1
    np.savetxt(source / "camera-intrinsics.txt", told)
    # The given intrinsics are the depth camera's: its images are the renders' depth seen with them.
    from dvpmvs.evaluation.rgbd import _registered_depth

    for i, frame in enumerate(frames):
        seen = _registered_depth(frame["depth"].astype(np.float32), K, told)
        cv2.imwrite(str(source / f"frame-{i:06d}.depth.png"), seen.astype(np.uint16))
    options = RGBDOptions(views=6, min_baseline=0.1, min_overlap=0.3)
    import_rgbd("7scenes", source, tmp_path / "ws", options, max_image_size=160, num_sources=3)
    record = json.loads((tmp_path / "ws" / "rgbd.json").read_text())
    calibration = record["camera"]["color_calibration"]
    assert calibration["focal_given"] == pytest.approx(told[0, 0])
    assert calibration["focal"] == pytest.approx(K[0, 0], rel=0.02)
    assert calibration["principal_point"] == pytest.approx([K[0, 2], K[1, 2]], abs=1.5)
    assert calibration["reprojection_error_px"] < calibration["reprojection_error_px_before"]
    model = pycolmap.Reconstruction(str(tmp_path / "ws" / "sparse"))
    assert next(iter(model.cameras.values())).focal_length_x == pytest.approx(K[0, 0], rel=0.02)
    # The sensor's depth seen through the colour camera: the true depth, where the maps agree.
    first = record["keyframes"][0]
    truth = read_depth_map(
        tmp_path / "ws" / "ground_truth" / "depth_maps" / f"{first['image']}.bin"
    )
    exact = frames[first["frame"]]["depth"] / 1000.0
    both = (truth > 0) & (exact > 0)
    assert both.mean() > 0.6  # the depth camera's narrower view (measured 0.67)
    assert np.median(np.abs(truth[both] - exact[both]) / exact[both]) < 0.01


def test_the_same_sequence_imports_to_the_same_bytes(scene, tmp_path):
    # Matching on several threads handed RANSAC's per-thread generators other pairs, and the
    # triangulation's bundle adjustment summed in another order: other points, another
    # calibrated focal length and ground truth from run to run.
    source = _seven_scenes(tmp_path / "seq", scene)
    options = RGBDOptions(views=6, min_baseline=0.1, min_overlap=0.3)
    digests = []
    for run in ("first", "second"):
        out = tmp_path / run
        import_rgbd("7scenes", source, out, options, max_image_size=160, num_threads=4)
        files = sorted(p for d in ("sparse", "ground_truth") for p in (out / d).rglob("*"))
        digests.append({str(p.relative_to(out)): p.read_bytes() for p in files if p.is_file()})
    assert len(digests[0]) > 10 and digests[0] == digests[1]


def test_keyframes_follow_the_rule(scene, tmp_path):
    frames, _ = scene
    source = _seven_scenes(tmp_path / "seq", scene)
    sequence = read_sequence("7scenes", source, RGBDOptions())
    centers = [f["pose"][:3, 3] for f in frames]
    gaps = [float(np.linalg.norm(centers[i + 1] - centers[i])) for i in range(len(frames) - 1)]
    # A baseline of 0: every next frame (that overlaps) is a keyframe.
    every = select_keyframes(sequence, RGBDOptions(views=5, min_baseline=0, min_overlap=0.1))
    assert [k["frame"] for k in every] == [0, 1, 2, 3, 4]
    assert [k["baseline"] for k in every[1:]] == pytest.approx(gaps[:4])
    # A baseline no pair reaches: the last frame that still overlaps enough.
    far = select_keyframes(
        sequence, RGBDOptions(views=2, start=3, min_baseline=100, min_overlap=0.5)
    )
    assert far[1]["overlap"] >= 0.5 and far[1]["frame"] > 3
    if far[1]["frame"] + 1 < len(frames):
        from dvpmvs.evaluation.rgbd import _overlap

        after = far[1]["frame"] + 1
        depth = sequence.read_depth
        f = sequence.frames
        assert _overlap(sequence, f[3], depth(f[3]), f[after], depth(f[after])) < 0.5
    with pytest.raises(DvpmvsError, match="rgbd.views=9 keyframes found from rgbd.start=0"):
        select_keyframes(sequence, RGBDOptions(views=9, min_baseline=0, min_overlap=0.1))


@pytest.mark.parametrize(
    "layout,breaks,needle",
    [
        (
            "7scenes",
            lambda f: (f / "frame-000003.pose.txt").unlink(),
            "has no pose frame-000003.pose.txt",
        ),
        ("7scenes", lambda f: (f / "frame-000001.pose.txt").write_text("1 0 0"), "found 3"),
        ("tum", lambda f: (f / "groundtruth.txt").unlink(), "groundtruth.txt is missing"),
        ("rgbd", lambda f: (f / "depth" / "v2.png").unlink(), "v2.png is missing"),
        (
            "scannet",
            lambda f: (f / "intrinsic" / "intrinsic_depth.txt").unlink(),
            "not a ScanNet export",
        ),
    ],
)
def test_a_broken_sequence_is_named(scene, tmp_path, layout, breaks, needle):
    source = WRITERS[layout](tmp_path / "rgbd_dataset_freiburg3_x", scene)
    breaks(source)
    with pytest.raises(DvpmvsError, match=needle):
        read_sequence(layout, source, RGBDOptions())


def test_options_are_checked():
    for bad, needle in (
        ({"views": 1}, "rgbd.views=1"),
        ({"min_overlap": 0}, "rgbd.min_overlap=0"),
        ({"pixel_centre": "corner"}, "choose integer"),
        ({"intrinsics": [1, 2, 3]}, "fx, fy, cx, cy"),
        ({"views": "ten"}, "rgbd.views"),
    ):
        with pytest.raises((DvpmvsError, ValueError), match=needle):
            RGBDOptions(**bad)


@pytest.mark.slow
@pytest.mark.skipif(not SHARED_KITCHEN.is_dir(), reason=f"{SHARED_KITCHEN} is not on this machine")
def test_the_shared_kitchen_clip_imports_with_its_sensor_ground_truth(tmp_path):
    options = RGBDOptions(views=10, start=0)
    stats = import_rgbd(
        "7scenes", SHARED_KITCHEN, tmp_path / "ws", options, max_image_size=640, num_sources=3
    )
    record = json.loads((tmp_path / "ws" / "rgbd.json").read_text())
    keys = record["keyframes"]
    assert [k["image"] for k in keys][0] == "frame-000000.color.jpg"
    assert all(k["baseline"] >= 0.05 or k["overlap"] < 0.7 for k in keys[1:])
    assert all(0.7 < k["sensor_depth_share"] < 1 for k in keys)  # about 89 % valid (README)
    assert stats["points3D"] > 200 and stats["mean_reprojection_error_px"] < 2
    assert stats["scan_points"] > 100_000
    # Its colour camera is not the depth camera of 585 px: about 518 px fits the poses.
    calibration = record["camera"]["color_calibration"]
    assert 510 < calibration["focal"] < 526 and calibration["reprojection_error_px"] < 1.2


def test_an_openmvs_depth_map_file_is_read_as_its_layout_says(tmp_path):
    """``read_dmap`` against OpenMVS's ``ExportDepthDataRaw`` layout (libs/MVS/DepthMap.cpp):
    header, image name, view IDs, K, R, C, then depth, normals, confidence."""
    import struct

    from dvpmvs.evaluation.experiments.rgbd_clips import read_dmap

    depth = np.arange(12, dtype=np.float32).reshape(3, 4) / 10
    name = b"images/frame-000005.color.jpg"
    data = struct.pack("<HBBIIIIff", *struct.unpack("<H", b"DR"), 1 | 2 | 4, 0, 8, 6, 4, 3, 0.5, 9)
    data += struct.pack("<H", len(name)) + name + struct.pack("<I3I", 3, 0, 4, 7)
    data += np.arange(21, dtype=np.float64).tobytes() + depth.tobytes()
    data += np.ones((3, 4, 3), np.float32).tobytes() + np.ones((3, 4), np.float32).tobytes()
    (tmp_path / "depth0000.dmap").write_bytes(data)
    image, read = read_dmap(tmp_path / "depth0000.dmap")
    assert image == name.decode() and np.array_equal(read, depth)


@pytest.mark.slow
def test_the_clip_benchmark_runs_and_scores_a_clip(scene, tmp_path, capsys):
    from dvpmvs.evaluation.experiments.rgbd_clips import main

    source = _seven_scenes(tmp_path / "sequence", scene)
    args = ["--source", str(source), "--starts", "0", "--views", "4", "--seeds", "0"]
    args += ["--max-image-size", "160", "--out", str(tmp_path / "clips")]
    args += ["--import-overrides", "rgbd.min_baseline=0.1", "rgbd.min_overlap=0.3"]
    assert main([*args, "--configs", "quality=fast patch_match.num_iterations=2"]) == 0
    table = capsys.readouterr().out.splitlines()
    row = next(line for line in table if line.startswith("| `quality=fast"))
    cells = [float(cell.split()[0]) for cell in row.split("|")[2:-1]]
    # Measured: F1 at 10 cm 59.7 (maps of 80x60 on 4 views), AbsRel 3.6 %, δ < 1.25 97.7 %.
    assert 50 < cells[2] < 70 and 1 < cells[5] < 6 and cells[10] > 90, row
    # A rerun with the same code and commands reuses the clip and the run (and says the same).
    run = tmp_path / "clips" / "runs" / "clip_000"
    stamp = (run / "quality-fast_patch_match.num_iterations-2_seed0.json").stat().st_mtime_ns
    assert main([*args, "--configs", "quality=fast patch_match.num_iterations=2"]) == 0
    assert row in capsys.readouterr().out.splitlines()
    assert (
        run / "quality-fast_patch_match.num_iterations-2_seed0.json"
    ).stat().st_mtime_ns == stamp
