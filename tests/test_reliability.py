"""Bad inputs, interrupted runs and concurrent writers, as a user meets them on the command line.

Each test builds its bad input, runs ``dvpmvs`` as a user would, and checks the exit status, that
the message names the file or key at fault, and that no output was changed or half-written.
The guarantees these tests back are listed in docs/guarantees.md.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pycolmap
import pytest

from dvpmvs.maps import map_path, read_depth_map, write_depth_map, write_extra_map
from dvpmvs.provenance import Record, read_record, record_path
from dvpmvs.writer_lock import LOCK_NAME, lock_holder
from tests.helpers import built_once, dvpmvs, dvpmvs_here, read_only
from tests.scenes import make_workspace

FAST = [
    "max_image_size=64",
    "view_selector=sparse_score",
    "patch_match.num_scales=1",
    "previews=false",
]


def _snapshot(folder: Path) -> dict:
    """Every file's content, but the writer lock's (whose holder record each writer rewrites)."""
    return {
        p: hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(folder.rglob("*"))
        if p.is_file() and p.name != LOCK_NAME
    }


def _failed(result, *needles):
    """The command stopped with status 1, a message holding every needle, and no traceback."""
    assert result.returncode == 1, result.stderr[-2000:]
    assert "Traceback" not in result.stderr, result.stderr[-3000:]
    for needle in needles:
        assert str(needle) in result.stderr, (needle, result.stderr[-2000:])


@pytest.fixture(scope="module")
def computed(tmp_path_factory):
    """A 5-view workspace of 64x48 with its maps and (empty-free) cloud computed once."""

    def build(folder: Path) -> None:
        make_workspace(folder / "ws")
        result = dvpmvs(
            "dense", "workspace=ws", *FAST, "fusion_options.min_consistent_views=1", cwd=folder
        )
        assert result.returncode == 0, result.stderr

    return built_once(tmp_path_factory, "reliability", build) / "ws"


def _private_copy(workspace: Path, folder: Path) -> Path:
    target = folder / "ws"
    shutil.copytree(workspace, target, symlinks=True)
    return target


@pytest.fixture
def ws(computed, tmp_path):
    """A private copy of the computed workspace."""
    return _private_copy(computed, tmp_path)


# -- options: validated at the start, by name ------------------------------------------------------


@pytest.mark.parametrize(
    "override,needle",
    [
        (
            "patch_match.num_iterations=2.5",
            "patch_match.num_iterations must be an integer, got 2.5",
        ),
        (
            "patch_match.num_iterations=abc",
            "patch_match.num_iterations must be an integer, got 'abc'",
        ),
        (
            "patch_match.planar_prior=maybe",
            "patch_match.planar_prior must be true or false, got 'maybe'",
        ),
        ("patch_match.deformable=2", "patch_match.deformable must be true or false, got 2"),
        ("geometric=maybe", "geometric must be true or false"),
        ("max_image_size=8", "max_image_size must be -1 (the images' own size) or at least 32"),
        ("+patch_match.num_iteratons=3", "unknown patch-match option(s) num_iteratons"),
        (
            "+evaluate.tolerence=0.1",
            "unknown option evaluate.tolerence (given as +evaluate.tolerence=0.1)",
        ),
        ("+fooo=1", "unknown option fooo"),
        ("depth_range=[1]", "depth_range must be two numbers, depth_range=[min,max]"),
        ("depth_range=5", "depth_range must be two numbers, depth_range=[min,max]"),
        ("depth_range=[1,2,3]", "got [1, 2, 3]"),
        ("depth_quantiles=0.5", "depth_quantiles must be two numbers, depth_quantiles=[low,high]"),
        ("evaluate.tolerances=abc", "evaluate.tolerances must be positive numbers"),
        ("evaluate.tolerances=[0.02,-1]", "evaluate.tolerances must be positive numbers"),
        ("evaluate.depth_maps=maybe", "evaluate.depth_maps must be true or false"),
        ("undistort=maybe", "undistort must be true or false"),
        ("output=cloud.xyz", "fused clouds are written as binary PLY"),
        ("num_threads=100000", "num_threads=100000 is more threads than this machine can run"),
        ("num_threads=-2", "num_threads must be >= 0"),
    ],
)
def test_a_wrong_option_stops_the_run_before_it_starts(ws, override, needle):
    before = _snapshot(ws)
    _failed(
        dvpmvs_here("dense", f"workspace={ws}", *FAST, "overwrite=true", override, cwd=ws.parent),
        needle,
    )
    assert _snapshot(ws) == before


# -- inputs: checked before any compute --------------------------------------------------------------


def test_a_truncated_jpeg_is_an_error_naming_it(ws):
    import cv2

    image = ws / "images" / "view_02.png"  # JPEG bytes under the model's name: decoded by content
    ok, data = cv2.imencode(".jpg", cv2.imread(str(image)))
    image.write_bytes(data.tobytes()[: len(data) * 6 // 10])
    before = _snapshot(ws / "stereo")
    _failed(
        dvpmvs_here("dense", f"workspace={ws}", *FAST, "overwrite=true", cwd=ws.parent),
        f"image {image} is truncated",
        "copy it again",
    )
    assert _snapshot(ws / "stereo") == before


def test_a_complete_jpeg_with_data_after_its_end_is_read(tmp_path):
    import cv2

    from dvpmvs.image import check_image_file, read_image

    path = tmp_path / "a.jpg"
    rng = np.random.default_rng(0)
    ok, data = cv2.imencode(".jpg", (rng.random((48, 64, 3)) * 255).astype(np.uint8))
    path.write_bytes(data.tobytes() + b"appended trailer, as motion photos have")
    assert check_image_file(path) == (64, 48)
    assert read_image(path).shape == (48, 64, 3)


@pytest.mark.parametrize("name", ["cameras.bin", "images.bin", "points3D.bin"])
def test_a_truncated_model_file_is_named(ws, name):
    path = ws / "sparse" / name
    path.write_bytes(path.read_bytes()[: path.stat().st_size * 2 // 3])
    _failed(dvpmvs_here("dense", f"workspace={ws}", *FAST, cwd=ws.parent), f"{path} is truncated")


def test_duplicate_image_names_are_an_error(ws):
    model = pycolmap.Reconstruction(str(ws / "sparse"))
    first, second = sorted(model.images)[:2]
    model.images[second].name = model.images[first].name
    model.write(str(ws / "sparse"))
    _failed(
        dvpmvs_here("dense", f"workspace={ws}", *FAST, cwd=ws.parent),
        "names 1 image(s) more than once",
        "'view_00.png'",
    )


def test_a_non_utf8_patch_match_cfg_is_named_with_its_line(ws):
    cfg = ws / "stereo" / "patch-match.cfg"
    cfg.write_bytes("view_00.png\n__auto__, 2\ncaf\xe9.png\n__all__\n".encode("latin-1"))
    _failed(
        dvpmvs_here("dense", f"workspace={ws}", *FAST, cwd=ws.parent),
        f"{cfg}:3: not UTF-8 text (byte 0xe9)",
    )


def test_an_empty_patch_match_cfg_is_an_error(ws):
    cfg = ws / "stereo" / "patch-match.cfg"
    cfg.write_text("# nothing yet\n")
    _failed(
        dvpmvs_here("dense", f"workspace={ws}", *FAST, cwd=ws.parent),
        f"{cfg} lists no reference image",
    )


def test_a_view_without_overlap_gets_no_maps_and_the_others_run(ws, caplog):
    from dvpmvs.dense import DenseOptions, run_dense
    from dvpmvs.workspace import Workspace, WorkspaceOptions

    # view_04 keeps its pose but no sparse point: it shares none with anything, yet __all__ lists
    # every other view as its source.
    model = pycolmap.Reconstruction(str(ws / "sparse"))
    lonely = next(image for image in model.images.values() if image.name == "view_04.png")
    for point_id in [p.point3D_id for p in lonely.points2D if p.has_point3D()]:
        track = model.points3D[point_id].track
        if track.length() <= 2:
            model.delete_point3D(point_id)
        else:
            model.delete_observation(
                lonely.image_id,
                next(e.point2D_idx for e in track.elements if e.image_id == lonely.image_id),
            )
    model.write(str(ws / "sparse"))
    (ws / "stereo" / "patch-match.cfg").write_text("view_00.png\n__all__\nview_04.png\n__all__\n")
    workspace = Workspace.open(ws, WorkspaceOptions(view_selector={"name": "sparse_score"}))
    assert workspace["view_04.png"].sources == () and len(workspace["view_00.png"].sources) == 4
    assert "view_04.png shares no sparse point with any of its 4 source view(s)" in caplog.text
    summary = run_dense(
        workspace, DenseOptions(overwrite=True, previews=False), progress=False, out=ws.parent / "o"
    )
    assert {r.name for r in summary.reports} == {"view_00.png"}


@pytest.mark.slow
def test_a_prior_of_another_aspect_ratio_is_an_error_unless_resized(ws):
    folder = ws / "priors"
    folder.mkdir()
    for name in ("view_00.png", "view_01.png", "view_02.png", "view_03.png", "view_04.png"):
        np.save(folder / f"{name}.npy", np.full((50, 50), 4.0, np.float32))
    args = [
        "dense",
        f"workspace={ws}",
        *FAST,
        "overwrite=true",
        "depth_prior=file",
        "depth_prior.path=priors",
        "depth_prior.metric=true",
        "fuse=false",
        "geometric=false",
    ]
    _failed(
        dvpmvs_here(*args, cwd=ws.parent),
        f"{folder / 'view_00.png.npy'}: the prior is 50x50 but the view is 64x48",
    )
    assert dvpmvs(*args, "depth_prior.resize=true", cwd=ws.parent).returncode == 0
    # Another resolution of the same image (here half) is resized without being asked.
    for path in folder.iterdir():
        np.save(path, np.full((24, 32), 4.0, np.float32))
    assert dvpmvs(*args, cwd=ws.parent).returncode == 0


# -- outputs: writable, named as files, never half-written ---------------------------------------------


def test_output_naming_a_folder_is_an_error(ws):
    (ws / "clouds").mkdir()
    before = _snapshot(ws / "stereo")
    _failed(
        dvpmvs_here(
            "dense",
            f"workspace={ws}",
            *FAST,
            "overwrite=true",
            f"output={ws / 'clouds'}",
            cwd=ws.parent,
        ),
        f"output={ws / 'clouds'} is a folder",
    )
    assert _snapshot(ws / "stereo") == before


def test_an_output_folder_that_cannot_be_made_is_an_error_before_any_compute(ws):
    (ws / "a_file").write_text("not a folder")
    out = ws / "a_file" / "out"
    _failed(
        dvpmvs_here("dense", f"workspace={ws}", *FAST, f"out={out}", cwd=ws.parent),
        f"cannot write to the output folder {out}",
    )


@pytest.mark.slow
def test_a_read_only_workspace_is_an_error_before_any_compute(ws):
    before = _snapshot(ws)
    with read_only(ws, ws / "stereo"):
        _failed(
            dvpmvs_here("dense", f"workspace={ws}", *FAST, "overwrite=true", cwd=ws.parent),
            f"cannot write to the output folder {ws}",
            "out=DIR",
        )
    # Only the workspace's own folder read-only (stereo/ writable): the cloud could not be written.
    with read_only(ws):
        _failed(
            dvpmvs_here("dense", f"workspace={ws}", *FAST, "overwrite=true", cwd=ws.parent),
            f"cannot write to the output folder {ws}",
        )
    assert _snapshot(ws) == before
    # Maps and cloud elsewhere: the workspace is only read.
    with read_only(ws, ws / "stereo"):
        result = dvpmvs(
            "dense",
            f"workspace={ws}",
            *FAST,
            f"out={ws.parent / 'out'}",
            "fuse=false",
            cwd=ws.parent,
        )
    assert result.returncode == 0, result.stderr
    assert _snapshot(ws) == before


def test_temporaries_of_an_interrupted_run_are_removed_by_the_next(ws):
    leftovers = [
        ws / "stereo" / "depth_maps" / ".view_00.png.geometric.bin.k2x_9aQz.tmp",
        ws / ".fused.ply.abcdEFGH.tmp.ply",
        ws / ".fused.ply.abcdEFGH.tmp.ply.vis",
    ]
    for path in leftovers:
        path.write_bytes(b"half a map")
    keep = ws / "stereo" / "depth_maps" / ".my_notes"
    keep.write_text("not ours")
    result = dvpmvs(
        "dense", f"workspace={ws}", *FAST, "fusion_options.min_consistent_views=1", cwd=ws.parent
    )
    assert result.returncode == 0, result.stderr
    assert not any(path.exists() for path in leftovers) and keep.exists()
    assert "removed 3 temporary file(s) of an interrupted run" in result.stdout


# -- maps: corrupt values are errors, whoever fuses ----------------------------------------------------


@pytest.mark.parametrize("backend", ["dvpmvs", "colmap"])
def test_negative_depths_are_an_error_naming_the_map(ws, backend):
    path = map_path(ws / "stereo", "view_01.png", "depth", "geometric")
    depth = read_depth_map(path)
    depth[::3] = -1.0
    write_depth_map(path, depth)
    before = _snapshot(ws)
    _failed(
        dvpmvs_here(
            "fuse",
            f"workspace={ws}",
            "max_image_size=64",
            "view_selector=sparse_score",
            f"fusion={backend}",
            cwd=ws.parent,
        ),
        f"{path}: ",
        "negative depth(s)",
        "rerun `dvpmvs dense`",
    )
    assert _snapshot(ws) == before


@pytest.mark.parametrize("backend", ["dvpmvs", "colmap"])
def test_non_unit_normals_are_an_error_naming_the_map(ws, backend):
    path = map_path(ws / "stereo", "view_03.png", "normal", "geometric")
    write_extra_map(
        path, np.full((48, 64, 3), 0.5, np.float32)
    )  # COLMAP's container, normals of length 0.87
    _failed(
        dvpmvs_here(
            "fuse",
            f"workspace={ws}",
            "max_image_size=64",
            "view_selector=sparse_score",
            f"fusion={backend}",
            cwd=ws.parent,
        ),
        f"{path}: 3072 normal(s) are neither unit vectors nor (0, 0, 0)",
    )


def test_colmap_fusion_leaves_its_vis_beside_the_cloud(ws):
    for _ in range(2):
        result = dvpmvs(
            "fuse",
            f"workspace={ws}",
            "max_image_size=64",
            "view_selector=sparse_score",
            "fusion=colmap",
            "fusion_options.min_consistent_views=1",
            f"output={ws / 'colmap.ply'}",
            cwd=ws.parent,
        )
        assert result.returncode == 0, result.stderr
    assert (ws / "colmap.ply.vis").is_file()
    assert not [p.name for p in ws.glob(".*") if "tmp" in p.name]


# -- eval: partial or invalid clouds are never scored ----------------------------------------------------


def _eval(reconstruction, ground_truth, cwd, *args):
    return dvpmvs(
        "eval", f"reconstruction={reconstruction}", f"ground_truth={ground_truth}", *args, cwd=cwd
    )


@pytest.mark.slow
def test_eval_refuses_a_truncated_reconstruction_or_ground_truth(tmp_path):
    from dvpmvs.pointcloud import write_point_cloud

    cloud = write_point_cloud(tmp_path / "cloud.ply", np.random.default_rng(0).random((5000, 3)))
    assert _eval(cloud, cloud, tmp_path).returncode == 0
    cut = tmp_path / "cut.ply"
    cut.write_bytes(cloud.read_bytes()[: cloud.stat().st_size * 3 // 4])
    _failed(_eval(cut, cloud, tmp_path), f"{cut} is truncated: its header declares")
    _failed(_eval(cloud, cut, tmp_path), f"{cut} is truncated")
    # A scan of an ETH3D ground truth (a MeshLab project's PLY).
    from dvpmvs.evaluation.pointclouds import write_meshlab_project

    mlp = write_meshlab_project(tmp_path / "scan_alignment.mlp", [("cut.ply", np.eye(4))])
    _failed(_eval(cloud, mlp, tmp_path), f"{cut} is truncated")


def test_eval_refuses_nan_points_in_an_ascii_ply(tmp_path):
    import open3d as o3d

    rng = np.random.default_rng(1)
    cloud = tmp_path / "ascii.ply"
    o3d.io.write_point_cloud(
        str(cloud),
        o3d.geometry.PointCloud(o3d.utility.Vector3dVector(rng.random((20, 3)))),
        write_ascii=True,
    )
    lines = cloud.read_text().splitlines()
    lines[lines.index("end_header") + 5] = "nan nan nan"
    cloud.write_text("\n".join(lines) + "\n")
    _failed(
        _eval(cloud, cloud, tmp_path),
        f"{cloud}: 1 of its 20 points have NaN or infinite coordinates (e.g. point 4)",
    )


# -- one writer per output folder -------------------------------------------------------------------------


@pytest.mark.slow
def test_a_second_writer_stops_with_the_holder_named_and_maps_carry_one_configuration(tmp_path):
    from dvpmvs.evaluation.embedded import materialise

    root = materialise(tmp_path / "room")
    first = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "dvpmvs.cli",
            "dense",
            f"workspace={root}",
            "max_image_size=160",
            "previews=false",
            "patch_match.perturbation=0.02",
        ],
        cwd=tmp_path,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        deadline = time.monotonic() + 120
        while not (
            (lock_holder(root) or {}).get("pid") == first.pid
            and (lock_holder(root) or {}).get("active")
        ):
            assert first.poll() is None and time.monotonic() < deadline, (
                "the first run never took the lock"
            )
            time.sleep(0.05)
        second = dvpmvs(
            "dense",
            f"workspace={root}",
            "max_image_size=160",
            "previews=false",
            "patch_match.perturbation=0.04",
            cwd=tmp_path,
        )
        assert first.poll() is None, (
            "the first run ended before the second was refused: the test proves nothing"
        )
        _failed(
            second, f"{root.resolve()} is being written by another dvpmvs run (PID {first.pid} on"
        )
        fuse = dvpmvs("fuse", f"workspace={root}", "max_image_size=160", cwd=tmp_path)
        _failed(fuse, f"(PID {first.pid} on")
    finally:
        assert first.wait(timeout=300) == 0, first.stderr.read()[-2000:]
    names = sorted(p.name for p in (root / "images").iterdir())
    for name in names:
        for pass_ in ("photometric", "geometric"):
            record = read_record(record_path(root / "stereo", name, pass_))
            assert record.complete and record.inputs["patch_match"]["perturbation"] == 0.02
    assert json.loads((root / LOCK_NAME).read_text())["active"] is False


def test_a_non_ascii_workspace_path_needs_no_quoting(ws):
    target = ws.parent / "café ws"
    ws.rename(target)
    result = dvpmvs("dense", f"workspace={target}", *FAST, "fuse=false", cwd=target.parent)
    assert result.returncode == 0, result.stderr
    assert "the maps of all 5 views are current" in result.stdout


# -- a cloud's record describes exactly the maps it was fused from ------------------------------------------


ROOM = ["quality=fast", "previews=false", "evaluate.ground_truth=none", "num_threads=1"]


@pytest.fixture(scope="module")
def room_computed(tmp_path_factory):
    """The synthetic room, 4 views of 120x90, with its maps and a cloud of about 4,900 points."""

    def build(folder: Path) -> None:
        made = dvpmvs("synth", "out=ws", "scene=room", "views=4", "width=120", "seed=3", cwd=folder)
        assert made.returncode == 0, made.stderr
        result = dvpmvs("dense", "workspace=ws", *ROOM, cwd=folder)
        assert result.returncode == 0, result.stderr

    return built_once(tmp_path_factory, "reliability_room", build) / "ws"


@pytest.fixture
def room(room_computed, tmp_path):
    """A private copy of the computed room."""
    return _private_copy(room_computed, tmp_path)


def _cloud_points(cloud: Path) -> int:
    from dvpmvs.evaluation.pointclouds import read_points

    return len(read_points(cloud))


@pytest.mark.slow
def test_a_view_without_maps_stops_fusion_unless_a_partial_cloud_is_asked_for(room):
    ws = room
    full = _cloud_points(ws / "fused.ply")
    assert full > 4000
    depth = map_path(ws / "stereo", "0002.png", "depth", "geometric")
    depth.unlink()
    before = _snapshot(ws)
    _failed(
        dvpmvs_here("fuse", f"workspace={ws}", cwd=ws.parent),
        "1 of 4 views have no geometric maps",
        str(depth),
        "fusion_options.allow_missing=true",
    )
    assert _snapshot(ws) == before
    partial = dvpmvs("fuse", f"workspace={ws}", "fusion_options.allow_missing=true", cwd=ws.parent)
    assert partial.returncode == 0, partial.stderr
    # The closing lines (stderr) say so, not only the log.
    assert (
        "warning: partial cloud: 1 view(s) without maps added no points (0002.png)"
        in partial.stderr
    )
    record = json.loads((ws / "fused.ply.provenance.json").read_text())
    assert record["inputs"]["maps"]["0002.png"] == "missing"
    assert record["stats"]["views_without_maps"] == ["0002.png"]
    assert _cloud_points(ws / "fused.ply") < 0.8 * full
    # The dense stage makes the missing map again (the same bytes): the partial cloud is not current.
    rerun = dvpmvs("dense", f"workspace={ws}", *ROOM, cwd=ws.parent)
    assert rerun.returncode == 0, rerun.stderr
    assert "computing 1 of 4 views" in rerun.stdout and "is current" not in rerun.stdout
    assert _cloud_points(ws / "fused.ply") == full
    assert (
        json.loads((ws / "fused.ply.provenance.json").read_text())["inputs"]["maps"]["0002.png"]
        != "missing"
    )


@pytest.mark.slow
def test_a_cloud_fused_from_a_changed_map_is_not_current_once_the_map_is_made_again(room):
    ws = room
    full = (ws / "fused.ply").read_bytes()
    # A map changed by hand (or another tool) after it was written: its record no longer describes it.
    path = map_path(ws / "stereo", "0001.png", "depth", "geometric")
    depth = read_depth_map(path)
    depth[:, : depth.shape[1] // 2] = 0
    write_depth_map(path, depth)
    result = dvpmvs("fuse", f"workspace={ws}", cwd=ws.parent)
    assert result.returncode == 0, result.stderr
    assert (ws / "fused.ply").read_bytes() != full
    record = json.loads((ws / "fused.ply.provenance.json").read_text())
    assert set(record["inputs"]["maps"]["0001.png"]) == {
        "depth",
        "normal",
        "image",
    }  # digests, not a fingerprint
    # The dense stage restores the map's bytes; the cloud from the changed map is fused again.
    rerun = dvpmvs("dense", f"workspace={ws}", *ROOM, cwd=ws.parent)
    assert rerun.returncode == 0, rerun.stderr
    assert "changed on disk" in rerun.stdout and "is current" not in rerun.stdout
    assert (ws / "fused.ply").read_bytes() == full


def test_a_workspace_where_no_view_has_a_source_says_so(ws):
    model = pycolmap.Reconstruction(str(ws / "sparse"))
    first = next(image for image in model.images.values() if image.name == "view_00.png")
    for frame_id in [f for f in model.frames if f != first.frame_id]:
        model.deregister_frame(frame_id)
    model.write(str(ws / "sparse"))
    (ws / "stereo" / "patch-match.cfg").write_text("view_00.png\n__auto__, 2\n")
    (ws / "stereo" / "fusion.cfg").write_text(
        "view_00.png\n"
    )  # else fusion.cfg names deregistered images
    shutil.rmtree(ws / "stereo" / "depth_maps")
    for command in ("dense", "fuse"):
        _failed(
            dvpmvs_here(
                command,
                f"workspace={ws}",
                *FAST[:2],
                "depth_range=[3,5]",
                f"out={ws.parent / 'o'}" if command == "dense" else "fusion=dvpmvs",
                cwd=ws.parent,
            ),
            "none of the 1 view(s)",
            "has a source view",
            "patch-match.cfg",
        )


# -- every option and output checked before compute ----------------------------------------------------------


@pytest.mark.slow
@pytest.mark.parametrize("tolerances", ["0.02", "abc", "[a,b]", "[0.02,0]"])
def test_eval_names_a_wrong_tolerance(room, tolerances):
    ws = room
    result = dvpmvs(
        "eval",
        f"reconstruction={ws / 'fused.ply'}",
        f"ground_truth={ws / 'fused.ply'}",
        f"tolerances={tolerances}",
        cwd=ws.parent,
    )
    if tolerances == "0.02":  # one number is one tolerance
        assert result.returncode == 0, result.stderr
        assert "2 cm" in result.stderr
    else:
        _failed(result, "tolerances must be positive numbers, tolerances=[0.02,0.1]")


def test_a_read_only_maps_folder_is_found_before_the_first_view(ws):
    before = _snapshot(ws)
    with read_only(ws / "stereo" / "depth_maps"):
        _failed(
            dvpmvs_here("dense", f"workspace={ws}", *FAST, "overwrite=true", cwd=ws.parent),
            f"cannot write to the maps' folder {ws / 'stereo' / 'depth_maps'}",
        )
    assert _snapshot(ws) == before


@pytest.mark.parametrize("command", ["fuse", "dense"])
def test_a_cloud_path_other_than_ply_is_refused(ws, command):
    args = (
        ["max_image_size=64", "view_selector=sparse_score"]
        if command == "fuse"
        else [*FAST, "overwrite=true"]
    )
    before = _snapshot(ws)
    _failed(
        dvpmvs_here(command, f"workspace={ws}", *args, f"output={ws / 'cloud.xyz'}", cwd=ws.parent),
        f"output={ws / 'cloud.xyz'}: fused clouds are written as binary PLY",
    )
    assert _snapshot(ws) == before and not (ws / "cloud.xyz").exists()


# -- a full disk -------------------------------------------------------------------------------------------------


@contextmanager
def _small_disk(folder: Path, size: str):
    """A tmpfs of ``size`` mounted on ``folder`` (root only; skipped where mounting is refused)."""
    folder.mkdir(parents=True, exist_ok=True)
    if (
        os.geteuid() != 0
        or subprocess.run(
            ["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(folder)],
            capture_output=True,
        ).returncode
    ):
        pytest.skip("mounting a small tmpfs needs root and a kernel that allows it")
    try:
        yield folder
    finally:
        subprocess.run(["umount", "-l", str(folder)], check=True)


def test_a_disk_too_small_for_the_run_is_named_with_the_space_needed_before_compute(ws, tmp_path):
    with _small_disk(tmp_path / "disk", "256k") as disk:
        result = dvpmvs("dense", f"workspace={ws}", *FAST, f"out={disk / 'o'}", cwd=ws.parent)
        _failed(
            result,
            f"{disk / 'o' / 'stereo'} is on a disk with",
            "MB free; this run writes the maps of 10 view pass(es)",
            "give out=DIR on another disk",
        )
        assert not list((disk / "o" / "stereo" / "depth_maps").iterdir())


def test_a_disk_that_fills_during_a_write_leaves_no_partial_file(tmp_path):
    from dvpmvs.fusion import FusedCloud, write_fused_cloud
    from dvpmvs.maps import DiskFullError, write_normal_map
    from dvpmvs.provenance import Record, write_record

    with _small_disk(tmp_path / "disk", "64k") as disk:
        # pycolmap's writer stops silently on a full disk; the map is checked, not renamed into place.
        for write in (
            lambda: write_depth_map(disk / "d.bin", np.ones((200, 200), np.float32)),
            lambda: write_normal_map(disk / "n.bin", np.full((200, 200, 3), 3**-0.5, np.float32)),
            lambda: write_extra_map(disk / "e.bin", np.ones((200, 200), np.float32)),
            lambda: write_record(disk / "r.json", Record("f", {"blob": "x" * 100_000})),
            lambda: write_fused_cloud(
                disk / "c.ply",
                FusedCloud(
                    np.zeros((5000, 3), np.float32),
                    np.zeros((5000, 3), np.float32),
                    np.zeros((5000, 3), np.uint8),
                    {},
                    np.ones(5000, np.uint32),
                    np.zeros(5000, np.uint32),
                ),
            ),
        ):
            with pytest.raises(
                DiskFullError, match=f"no space left on the disk of {disk} .*MB free.*rerun"
            ):
                write()
            assert list(disk.iterdir()) == []


def test_eval_on_a_full_disk_prints_its_scores_and_warns_naming_report(tmp_path):
    from dvpmvs.pointcloud import write_point_cloud

    cloud = write_point_cloud(tmp_path / "cloud.ply", np.random.default_rng(0).random((2000, 3)))
    with _small_disk(tmp_path / "disk", "64k") as disk:
        with pytest.raises(OSError), open(disk / "filler", "wb") as filler:
            for _ in range(100):
                filler.write(b"\0" * 4096)
                filler.flush()
        report = disk / "scores.json"
        result = _eval(cloud, cloud, tmp_path, f"report={report}")
        assert result.returncode == 0, result.stderr[-2000:]
        assert "Traceback" not in result.stderr and "| F1" not in result.stderr
        assert "10 cm" in result.stderr  # the scores are printed before the report is written
        text = " ".join(result.stderr.split())
        assert f"the scores above are not written to report={report} (no space left" in text
        assert "give report= another path" in text and "out=" not in text
        assert sorted(p.name for p in disk.iterdir()) == ["filler"]


def test_dvpmvs_report_on_a_read_only_folder_is_one_line(computed, tmp_path):
    run = tmp_path / "run"
    shutil.copytree(computed, run, symlinks=True)
    before = _snapshot(run)
    with read_only(run):
        result = dvpmvs_here("report", str(run), cwd=tmp_path)
    _failed(
        result,
        f"dvpmvs report: cannot write to the folder {run} (",
        "copy the folder (cp -a) somewhere you can write",
    )
    assert _snapshot(run) == before


# -- photos for reconstruct ---------------------------------------------------------------------------------------


@pytest.fixture
def photos(tmp_path):
    """Four photos of a textured scene as JPEG files."""
    import cv2

    folder = tmp_path / "photos"
    folder.mkdir()
    rng = np.random.default_rng(0)
    for i in range(4):
        ok, data = cv2.imencode(".jpg", (rng.random((48, 64, 3)) * 255).astype(np.uint8))
        (folder / f"p{i}.jpg").write_bytes(data.tobytes())
    return folder


@pytest.mark.parametrize("where", ["photos/project", "photos/a/b/project", "photos"])
def test_reconstruct_refuses_a_project_folder_inside_the_photos(photos, where):
    out = photos.parent / where
    before = _snapshot(photos)
    _failed(
        dvpmvs_here("reconstruct", f"images={photos}", f"out={out}", cwd=photos.parent),
        f"out={out} ",
        f"images={photos}",
        "would be read as more photos",
    )
    assert _snapshot(photos) == before and not (photos / "project").exists()


def test_reconstruct_refuses_photos_inside_the_folder_undistortion_replaces(photos):
    out = photos.parent / "project"
    inside = out / "dense" / "images"
    shutil.copytree(photos, inside)
    _failed(
        dvpmvs_here("reconstruct", f"images={inside}", f"out={out}", cwd=photos.parent),
        f"lies inside {out / 'dense'}, which the undistortion stage replaces",
    )
    assert len(list(inside.iterdir())) == 4


def test_reconstruct_reads_subfolders_only_when_asked(photos):
    from dvpmvs.reconstruction import image_files

    (photos / "more").mkdir()
    shutil.copy(photos / "p0.jpg", photos / "more" / "q0.jpg")
    assert image_files(photos) == ["p0.jpg", "p1.jpg", "p2.jpg", "p3.jpg"]
    assert image_files(photos, recursive=True) == [
        "more/q0.jpg",
        "p0.jpg",
        "p1.jpg",
        "p2.jpg",
        "p3.jpg",
    ]


def test_a_failed_mapping_is_dvpmvss_line_alone_unless_verbose(photos):
    # Noise photos match nothing: the mapper registers no pair. COLMAP's own glog lines
    # ("W20261206 15:38:50.751418 ... No images with matches") show with verbose=true only.
    glog = re.compile(r"^[IWEF]\d{8} \d\d:\d\d:\d\d\.\d+ ", re.M)
    out = photos.parent / "project"
    # In a process of its own: COLMAP writes to the process's standard error, not to Python's.
    result = dvpmvs("reconstruct", f"images={photos}", f"out={out}", cwd=photos.parent)
    _failed(result, "the mapper registered no pair of the 4 photos")
    assert not glog.search(result.stdout + result.stderr), result.stderr[-2000:]
    shutil.rmtree(out)
    result = dvpmvs(
        "reconstruct", f"images={photos}", f"out={out}", "verbose=true", cwd=photos.parent
    )
    _failed(result, "the mapper registered no pair of the 4 photos")
    assert glog.search(result.stdout + result.stderr)


def test_reconstruct_names_a_truncated_photo_before_any_stage(photos):
    cut = photos / "p2.jpg"
    cut.write_bytes(cut.read_bytes()[:700])
    out = photos.parent / "project"
    _failed(
        dvpmvs_here("reconstruct", f"images={photos}", f"out={out}", cwd=photos.parent),
        "1 of the 4 photos cannot be used",
        f"image {cut} is truncated",
        "copy it again",
    )
    assert not (out / "database.db").exists()


# -- eval and mesh ---------------------------------------------------------------------------------------------------


@pytest.mark.slow
def test_eval_of_ground_truth_in_other_units_names_both_extents(room, tmp_path):
    ws = room
    from dvpmvs.evaluation.pointclouds import read_points
    from dvpmvs.pointcloud import write_point_cloud

    points = read_points(ws / "fused.ply")
    millimetres = write_point_cloud(tmp_path / "gt_mm.ply", points * 1000)
    _failed(
        _eval(ws / "fused.ply", millimetres, tmp_path),
        "differ 1000-fold in size (units?)",
        "the reconstruction spans",
        "the ground truth",
    )
    shifted = write_point_cloud(tmp_path / "gt_elsewhere.ply", points + 100)
    _failed(
        _eval(ws / "fused.ply", shifted, tmp_path),
        "the reconstruction and the ground truth do not overlap",
    )


def test_eval_names_the_properties_a_ply_lacks(tmp_path):
    colours = tmp_path / "colours.ply"
    colours.write_text(
        "ply\nformat ascii 1.0\nelement vertex 2\nproperty uchar red\nproperty uchar green\n"
        "property uchar blue\nend_header\n1 2 3\n4 5 6\n"
    )
    _failed(
        _eval(colours, colours, tmp_path),
        f"{colours}: its vertices have no x, y, z properties (they have: red, green, blue)",
    )


@pytest.mark.slow
def test_mesh_refuses_a_cloud_too_small_and_warns_of_surface_far_from_the_points(room, tmp_path):
    ws = room
    from dvpmvs.meshing import MIN_MESH_POINTS
    from dvpmvs.pointcloud import write_point_cloud

    tiny = write_point_cloud(tmp_path / "three.ply", np.random.default_rng(0).random((3, 3)))
    _failed(
        dvpmvs_here("mesh", f"input={tiny}", cwd=tmp_path),
        f"{tiny} has 3 point(s); meshing needs at least {MIN_MESH_POINTS}",
    )
    assert not (tmp_path / "meshed-poisson.ply").exists()
    _failed(
        dvpmvs_here(
            "mesh", f"input={ws / 'fused.ply'}", f"output={tmp_path / 'mesh.obj'}", cwd=tmp_path
        ),
        "meshes are written as binary PLY",
    )
    # Untrimmed, Poisson closes the open scene far beyond its points.
    result = dvpmvs(
        "mesh",
        f"input={ws / 'fused.ply'}",
        "meshing.trim_quantile=0",
        "meshing.depth=7",
        f"output={tmp_path / 'mesh.ply'}",
        cwd=tmp_path,
    )
    assert result.returncode == 0, result.stderr
    assert (
        "beyond the bounding box of its cloud" in result.stdout
        and "meshing.trim_quantile" in result.stdout
    )


# -- stopped runs ---------------------------------------------------------------------------------------------------


@pytest.mark.slow
@pytest.mark.parametrize("signal_number", [signal.SIGINT, signal.SIGTERM])
def test_a_stopped_run_says_how_far_it_got_in_one_line_and_a_rerun_resumes(room, signal_number):
    out = room.parent / "o"
    # The default quality: a view takes seconds, time to stop the run between two.
    args = [
        f"workspace={room}",
        f"out={out}",
        "previews=false",
        "evaluate.ground_truth=none",
        "num_threads=1",
    ]
    # As in a terminal: a test run started in the background of a script inherits SIGINT ignored,
    # which dvpmvs leaves ignored (as any program does).
    run = subprocess.Popen(
        [sys.executable, "-m", "dvpmvs.cli", "dense", *args],
        cwd=room.parent,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )
    first = record_path(out / "stereo", "0000.png", "photometric")
    deadline = time.monotonic() + 120
    while not ((read_record(first) or Record("", {})).complete):
        assert run.poll() is None and time.monotonic() < deadline, (
            "the run ended before its first view was done"
        )
        time.sleep(0.05)
    run.send_signal(signal_number)
    stdout, stderr = run.communicate(timeout=120)
    assert run.returncode == 128 + signal_number, stderr[-2000:]
    name = signal.Signals(signal_number).name
    last = stderr.strip().splitlines()[-1]
    assert last.startswith(f"dvpmvs dense: interrupted ({name}): "), stderr[-2000:]
    assert "of 4 views done in the photometric pass" in last and last.endswith(
        "rerun the same command to resume (what was finished is kept)"
    )
    for noise in ("Traceback", "Aborted at", "KeyboardInterrupt", "stack trace"):
        assert noise not in stderr + stdout
    assert not [p for p in out.rglob(".*") if p.name != LOCK_NAME]  # no temporaries
    assert json.loads((out / LOCK_NAME).read_text())["active"] is False
    assert json.loads((out / "dvpmvs_run.json").read_text())["status"] == "interrupted"
    rerun = dvpmvs("dense", *args, "quality=fast", cwd=room.parent)
    assert rerun.returncode == 0, rerun.stderr
    rerun = dvpmvs("dense", *args, cwd=room.parent)
    assert rerun.returncode == 0, rerun.stderr


@pytest.mark.slow
def test_the_demo_without_previews_names_no_previews_folder(demo_run, tmp_path):
    # A rerun of the suite's demo (its maps are reused) with its previews gone and not asked for.
    assert demo_run.returncode == 0, demo_run.stderr[-2000:]
    shutil.copytree(demo_run.cwd / "dvpmvs_demo", tmp_path / "demo", symlinks=True)
    shutil.rmtree(tmp_path / "demo" / "stereo" / "previews")
    result = dvpmvs("demo", f"out={tmp_path / 'demo'}", "previews=false", cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    assert "reused" in result.stderr, result.stderr[-2000:]
    assert not (tmp_path / "demo" / "stereo" / "previews").exists()
    assert "no previews (previews=false)" in result.stderr
    assert str(Path("stereo") / "previews") not in result.stderr


# -- files we did not write are never replaced unasked ----------------------------------------------


@pytest.mark.parametrize("backend", ["dvpmvs", "colmap"])
def test_fuse_refuses_to_replace_a_cloud_it_did_not_write(ws, backend):
    foreign = ws / "fused.ply"
    (ws / "fused.ply.provenance.json").unlink()  # as COLMAP leaves it: a cloud and no record
    foreign.write_bytes(
        b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\n"
        b"property float z\nend_header\n0 0 1\n"
    )
    before = foreign.read_bytes()
    result = dvpmvs(
        "fuse",
        f"workspace={ws}",
        f"fusion={backend}",
        "fusion_options.min_consistent_views=1",
        cwd=ws.parent,
    )
    _failed(result, str(foreign), "no dvpmvs provenance record", "overwrite=true")
    assert foreign.read_bytes() == before
    assert not (ws / "fused.ply.provenance.json").exists()
    result = dvpmvs(
        "fuse",
        f"workspace={ws}",
        f"fusion={backend}",
        "fusion_options.min_consistent_views=1",
        "overwrite=true",
        cwd=ws.parent,
    )
    assert result.returncode == 0, result.stderr[-2000:]
    assert foreign.read_bytes() != before
    # Now ours: a second fuse replaces it without asking.
    result = dvpmvs(
        "fuse",
        f"workspace={ws}",
        f"fusion={backend}",
        "fusion_options.min_consistent_views=1",
        cwd=ws.parent,
    )
    assert result.returncode == 0, result.stderr[-2000:]


@pytest.mark.parametrize(
    "fault", ["nan translation", "inf quaternion", "zero focal", "nan principal point"]
)
def test_a_camera_that_is_not_finite_is_named_before_compute(ws, fault):
    model = pycolmap.Reconstruction(str(ws / "sparse"))
    image = next(i for i in model.images.values() if i.name == "view_01.png")
    pose = image.cam_from_world() if callable(image.cam_from_world) else image.cam_from_world
    frame = model.frames[image.frame_id]
    if fault == "nan translation":
        frame.rig_from_world = pycolmap.Rigid3d(pose.rotation, np.array([0.1, np.nan, 0.0]))
    elif fault == "inf quaternion":
        frame.rig_from_world = pycolmap.Rigid3d(
            pycolmap.Rotation3d(np.array([np.inf, 0, 0, 1.0])), pose.translation
        )
    else:
        camera = model.cameras[image.camera_id]
        params = np.asarray(camera.params).copy()
        params[0 if fault == "zero focal" else 2] = 0.0 if fault == "zero focal" else np.nan
        camera.params = params
    model.write(str(ws / "sparse"))
    before = _snapshot(ws / "stereo")
    result = dvpmvs("dense", f"workspace={ws}", *FAST, "overwrite=true", cwd=ws.parent)
    needle = (
        "pose that is not finite"
        if "translation" in fault or "quaternion" in fault
        else "positive focal"
    )
    _failed(result, "image 'view_0", needle)
    assert _snapshot(ws / "stereo") == before


@pytest.mark.parametrize("suffix", [".bmp", ".tiff"])
def test_an_image_of_the_wrong_size_in_any_format_is_named_before_compute(ws, suffix):
    import cv2

    from dvpmvs.image import check_image_file

    image = ws / "images" / "view_03.png"
    other = ws / f"other{suffix}"
    cv2.imwrite(str(other), cv2.resize(cv2.imread(str(image)), (80, 60)))
    assert check_image_file(other) == (80, 60)
    image.write_bytes(other.read_bytes())  # decoded by content under the model's name
    before = _snapshot(ws / "stereo")
    _failed(
        dvpmvs_here("dense", f"workspace={ws}", *FAST, "overwrite=true", cwd=ws.parent),
        f"image {image} is 80x60 but its camera",
        "64x48",
    )
    assert _snapshot(ws / "stereo") == before


@pytest.mark.slow
@pytest.mark.parametrize("backend", ["dvpmvs", "colmap"])
def test_fusion_obeys_fusion_cfg_and_names_an_unknown_image(room, backend):
    from dvpmvs.fusion import read_visibility
    from dvpmvs.workspace import Workspace

    ws = room
    args = ["fuse", f"workspace={ws}", f"fusion={backend}", "overwrite=true"]
    assert dvpmvs(*args, cwd=ws.parent).returncode == 0
    every = read_visibility(ws / "fused.ply.vis")
    listed = ["0000.png", "0001.png", "0002.png"]
    (ws / "stereo" / "fusion.cfg").write_text("\n".join(listed) + "\n\n")
    result = dvpmvs(*args, cwd=ws.parent)
    assert result.returncode == 0, result.stderr[-2000:]
    index = Workspace.open(ws).colmap_image_indices
    some = read_visibility(ws / "fused.ply.vis")
    assert 500 < len(some) < 0.9 * len(every), (len(some), len(every))
    assert set(np.concatenate(some).tolist()) == {index[name] for name in listed}
    (ws / "stereo" / "fusion.cfg").write_text("0000.png\nno_such_view.png\n")
    before = (ws / "fused.ply").read_bytes()
    _failed(
        dvpmvs_here(*args, cwd=ws.parent),
        f"{ws / 'stereo' / 'fusion.cfg'}:2: image 'no_such_view.png' is not",
    )
    assert (ws / "fused.ply").read_bytes() == before


@pytest.mark.slow
def test_a_failed_sweep_job_has_its_row_and_its_error_in_the_table(ws, tmp_path):
    result = dvpmvs(
        "dense",
        "-m",
        f"workspace={ws}",
        *[o for o in FAST if not o.startswith("max_image_size")],
        "max_image_size=64,abc,48",
        f"hydra.sweep.dir={tmp_path / 'sweep'}",
        cwd=tmp_path,
    )
    assert result.returncode == 1, result.stderr[-2000:]
    assert "(3 jobs, 1 failed)" in result.stderr
    table = (tmp_path / "sweep" / "table.md").read_text()
    assert "| 1 | max_image_size=abc | **error** |" in table
    assert "max_image_size must be an integer, got 'abc'" in table
    rows = (tmp_path / "sweep" / "table.csv").read_text().splitlines()
    assert len(rows) == 4 and rows[0].endswith(",error")
    assert rows[2].startswith("1,") and "max_image_size must be an integer" in rows[2]
    assert rows[1].startswith("0,") and rows[1].split(",")[2] == "ok"


def test_a_rerun_with_previews_draws_the_previews_of_reused_maps(ws):
    previews = ws / "stereo" / "previews"
    shutil.rmtree(previews, ignore_errors=True)
    maps = _snapshot(ws / "stereo")
    result = dvpmvs(
        "dense",
        f"workspace={ws}",
        *[o for o in FAST if o != "previews=false"],
        "previews=true",
        "fusion_options.min_consistent_views=1",
        cwd=ws.parent,
    )
    assert result.returncode == 0, result.stderr[-2000:]
    for name in (
        "view_00.png.photometric.depth.png",
        "view_00.png.geometric.normal.png",
        "view_04.png.geometric.cost.png",
    ):
        assert (previews / name).is_file(), sorted(p.name for p in previews.glob("*"))
    # Nothing was computed again: every map is as it was.
    after = _snapshot(ws / "stereo")
    changed = [p.relative_to(ws).as_posix() for p, digest in maps.items() if after.get(p) != digest]
    assert changed == [], changed


@pytest.mark.slow
@pytest.mark.parametrize("name", ["x,y [3].png", "a, b.png"])
def test_an_image_name_colmaps_cfg_cannot_carry_is_refused_before_an_output_folder_is_made(
    ws, name
):
    model = pycolmap.Reconstruction(str(ws / "sparse"))
    image = next(i for i in model.images.values() if i.name == "view_01.png")
    image.name = name
    model.write(str(ws / "sparse"))
    (ws / "images" / "view_01.png").rename(ws / "images" / name)
    for cfg in (ws / "stereo" / "patch-match.cfg", ws / "stereo" / "fusion.cfg"):
        cfg.write_text(cfg.read_text().replace("view_01.png", name))
    _failed(
        dvpmvs_here(
            "dense",
            f"workspace={ws}",
            *FAST,
            "overwrite=true",
            f"out={ws.parent / 'o'}",
            cwd=ws.parent,
        ),
        f"image {name!r} cannot be listed in COLMAP's stereo/patch-match.cfg",
    )
    assert not (ws.parent / "o" / "stereo").exists()
    # In the workspace itself, whose own cfg selects sources automatically, it runs.
    result = dvpmvs("dense", f"workspace={ws}", *FAST, "overwrite=true", cwd=ws.parent)
    assert result.returncode == 0, result.stderr[-2000:]


def test_a_wrong_fusion_cfg_stops_dense_before_any_view_is_computed(ws):
    (ws / "stereo" / "fusion.cfg").write_text("view_00.png\nview_9.png\n")
    before = _snapshot(ws / "stereo")
    _failed(
        dvpmvs_here("dense", f"workspace={ws}", *FAST, "overwrite=true", cwd=ws.parent),
        f"{ws / 'stereo' / 'fusion.cfg'}:2: image 'view_9.png' is not a registered image",
    )
    assert _snapshot(ws / "stereo") == before


@pytest.mark.slow
@pytest.mark.parametrize("backend", ["dvpmvs", "colmap"])
def test_fuse_after_a_photometric_only_run_suggests_the_photometric_maps(tmp_path, backend):
    ws = tmp_path / "ws"
    make_workspace(ws)
    assert (
        dvpmvs(
            "dense", f"workspace={ws}", *FAST, "geometric=false", "fuse=false", cwd=tmp_path
        ).returncode
        == 0
    )
    _failed(
        dvpmvs_here("fuse", f"workspace={ws}", f"fusion={backend}", cwd=tmp_path),
        "no geometric maps",
        "(the dense run had geometric=false): fuse those with input_type=photometric",
    )
    result = dvpmvs(
        "fuse", f"workspace={ws}", f"fusion={backend}", "input_type=photometric", cwd=tmp_path
    )
    assert result.returncode == 0, result.stderr[-2000:]
