"""Masks: the user's files (COLMAP's and OpenMVS's layouts) keep pixels out of the maps."""

from __future__ import annotations

import subprocess
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pytest

from dvpmvs.maps import read_depth_map
from tests.helpers import built_once, dvpmvs, dvpmvs_here

FAST = [
    "quality=fast",
    "previews=false",
    "fuse=false",
    "evaluate.ground_truth=none",
    "num_threads=2",
]
W, H = 120, 90


def _depths(ws: Path, out: Path) -> dict[str, np.ndarray]:
    return {
        p.name: read_depth_map(p)
        for p in sorted((out / "stereo" / "depth_maps").glob("*.geometric.bin"))
    }


def _assert_in_the_kept_left_half(ws: Path, points: np.ndarray, visibility: Path) -> None:
    """Every point projects into the kept (left) half of each view its .vis file says supports it."""
    from dvpmvs.fusion import read_visibility
    from dvpmvs.workspace import Workspace

    workspace = Workspace.open(ws)
    by_index = {i: name for name, i in workspace.colmap_image_indices.items()}
    for point, views in zip(points, read_visibility(visibility)):
        for index in views:
            view = workspace[by_index[int(index)]]
            x = view.K @ (view.R @ point + view.t)
            assert x[0] / x[2] < W // 2 + 1.0, (point, view.name)


@pytest.fixture(scope="module")
def workspace(tmp_path_factory):
    """A 4-view synthetic room with both layouts' masks, made once for the run's workers."""

    def build(folder: Path) -> None:
        root = folder / "ws"
        made = dvpmvs(
            "synth", f"out={root}", "scene=room", "views=4", f"width={W}", "seed=3", cwd=folder
        )
        assert made.returncode == 0, made.stderr
        # Each view keeps its left half; OpenMVS's labels say the same with label 3 ignored.
        colmap, openmvs = root / "masks_colmap", root / "masks_openmvs"
        colmap.mkdir()
        openmvs.mkdir()
        for image in sorted((root / "images").glob("*.png")):
            keep = np.zeros((H, W), np.uint8)
            keep[:, : W // 2] = 255
            cv2.imwrite(
                str(colmap / f"{image.name}.png"),
                cv2.resize(keep, (2 * W, 2 * H), interpolation=cv2.INTER_NEAREST),
            )
            labels = np.where(keep > 0, 1, 3).astype(np.uint16)
            cv2.imwrite(str(openmvs / f"{image.stem}.mask.png"), labels)

    return built_once(tmp_path_factory, "masks", build) / "ws"


@pytest.mark.slow
def test_masked_pixels_get_no_depth_and_both_layouts_agree(workspace, tmp_path):
    assert (
        dvpmvs(
            "dense", f"workspace={workspace}", *FAST, f"out={tmp_path / 'plain'}", cwd=tmp_path
        ).returncode
        == 0
    )
    result = dvpmvs(
        "dense",
        f"workspace={workspace}",
        *FAST,
        f"out={tmp_path / 'colmap'}",
        "mask=files",
        "mask.path=masks_colmap",
        cwd=tmp_path,
    )
    assert result.returncode == 0, result.stderr[-2000:]
    result = dvpmvs(
        "dense",
        f"workspace={workspace}",
        *FAST,
        f"out={tmp_path / 'openmvs'}",
        "mask=files",
        f"mask.path={workspace / 'masks_openmvs'}",
        "mask.layout=openmvs",
        "mask.ignore_label=3",
        cwd=tmp_path,
    )
    assert result.returncode == 0, result.stderr[-2000:]
    plain, colmap, openmvs = (
        _depths(workspace, tmp_path / n) for n in ("plain", "colmap", "openmvs")
    )
    assert plain.keys() == colmap.keys() and len(plain) == 4
    for name in plain:
        assert (plain[name][:, W // 2 :] > 0).mean() > 0.3  # unmasked, the right half has depth
        assert not (colmap[name][:, W // 2 :] > 0).any()
        assert (colmap[name][:, : W // 2] > 0).mean() > 0.3
        np.testing.assert_array_equal(colmap[name], openmvs[name])


@pytest.mark.slow
def test_a_changed_mask_recomputes_only_its_view(workspace, tmp_path):
    ws = tmp_path / "ws"
    import shutil

    shutil.copytree(workspace, ws)
    args = ["dense", f"workspace={ws}", *FAST, "mask=files", "mask.path=masks_colmap"]
    assert dvpmvs(*args, cwd=tmp_path).returncode == 0
    mask = ws / "masks_colmap" / "0002.png.png"
    keep = cv2.imread(str(mask), cv2.IMREAD_GRAYSCALE)
    keep[:, :10] = 0
    cv2.imwrite(str(mask), keep)
    before = {
        p.name: p.stat().st_mtime_ns
        for p in (ws / "stereo" / "depth_maps").glob("*.photometric.bin")
    }
    assert dvpmvs(*args, cwd=tmp_path).returncode == 0
    after = {
        p.name: p.stat().st_mtime_ns
        for p in (ws / "stereo" / "depth_maps").glob("*.photometric.bin")
    }
    assert [n for n in before if before[n] != after[n]] == ["0002.png.photometric.bin"]


@pytest.mark.parametrize(
    "case,needle",
    [
        ("missing", "no mask for image 0000.png"),
        ("aspect", f"is {W}x{W} but image 0000.png is {W}x{H} here: another aspect ratio"),
        ("garbage", "cannot be read as an image"),
        ("label", "mask.ignore_label is for mask.layout=openmvs"),
        ("nofolder", "does not exist; mask.path names the folder of the masks"),
        ("file", "is not a folder; mask.path names the folder of the masks"),
        ("selflink", "0000.png.png is a symbolic link to no file, not an image"),
        ("folder", "0000.png.png is a folder, not an image"),
        ("label16", "an integer from 0 to 65535), got 70000"),
    ],
)
def test_bad_masks_are_named_before_any_view_is_computed(workspace, tmp_path, case, needle):
    folder = tmp_path / "m"
    folder.mkdir()
    for image in sorted((workspace / "images").glob("*.png")):
        cv2.imwrite(str(folder / f"{image.name}.png"), np.full((H, W), 255, np.uint8))
    target = folder / "0000.png.png"
    if case == "missing":
        target.unlink()
    elif case == "aspect":
        cv2.imwrite(str(target), np.full((W, W), 255, np.uint8))
    elif case == "garbage":
        target.write_bytes(b"not an image")
    elif case in ("selflink", "folder"):
        target.unlink()
        target.symlink_to(target) if case == "selflink" else target.mkdir()
    extra = {
        "label": ["mask.ignore_label=2"],
        "label16": ["mask.layout=openmvs", "mask.ignore_label=70000"],
        # A folder that is not there is no "image without a mask", even when those are allowed.
        "nofolder": ["mask.allow_missing=true"],
        "selflink": ["mask.allow_missing=true"],
    }.get(case, [])
    path = {"nofolder": tmp_path / "nowhere", "file": target}.get(case, folder)
    result = dvpmvs_here(
        "dense",
        f"workspace={workspace}",
        *FAST,
        f"out={tmp_path / 'o'}",
        "mask=files",
        f"mask.path={path}",
        *extra,
        cwd=tmp_path,
    )
    assert (
        result.returncode == 1 and needle in result.stderr and "Traceback" not in result.stderr
    ), result.stderr[-2000:]
    assert not list((tmp_path / "o").glob("stereo/depth_maps/*.bin"))
    if case == "missing":
        # allowed, the run goes through (at half size: only that it does is checked)
        result = dvpmvs(
            "dense",
            f"workspace={workspace}",
            *FAST,
            f"out={tmp_path / 'o'}",
            "mask=files",
            f"mask.path={folder}",
            "mask.allow_missing=true",
            f"max_image_size={W // 2}",
            cwd=tmp_path,
        )
        assert result.returncode == 0, result.stderr[-2000:]
        # and says which view kept every pixel
        said = " ".join((result.stdout + result.stderr).split())
        assert "no mask for image 0000.png" in said and "every pixel kept" in said


@dataclass
class _View:
    name: str
    height: int
    width: int


@pytest.mark.parametrize("layout", ["colmap", "openmvs"])
def test_sixteen_bit_masks_are_read_whole(tmp_path, layout):
    from dvpmvs.masks import MaskError, ViewMasks

    # Labels 0..511: a grey conversion keeps the high byte, reading 1..255 as 0.
    labels = np.arange(H * W, dtype=np.uint16).reshape(H, W) % 512
    name = "0000.mask.png" if layout == "openmvs" else "0000.png.png"
    cv2.imwrite(str(tmp_path / name), labels)
    config = {"name": "files", "path": str(tmp_path), "layout": layout}
    if layout == "openmvs":
        config["ignore_label"] = 300  # only a 16-bit mask holds it
    keep = ViewMasks.from_config(config).mask(_View("0000.png", H, W))
    masked = labels == 300 if layout == "openmvs" else labels == 0
    np.testing.assert_array_equal(keep, ~masked)
    if layout == "openmvs":
        cv2.imwrite(str(tmp_path / name), (labels % 256).astype(np.uint8))
        with pytest.raises(MaskError, match="is 8-bit: mask.ignore_label=300 cannot occur"):
            ViewMasks.from_config(config).mask(_View("0000.png", H, W))


@pytest.mark.slow
@pytest.mark.parametrize("backend", ["dvpmvs", "colmap"])
def test_fusion_takes_no_masked_pixel_from_unmasked_maps(workspace, tmp_path, backend):
    """Maps computed without masks, fused with them: no point projects into a masked pixel of
    the view it started from (nor of any view that joined it, as the .vis says)."""
    import shutil

    from dvpmvs.evaluation.pointclouds import read_points

    ws = tmp_path / "ws"
    shutil.copytree(workspace, ws)
    assert dvpmvs("dense", f"workspace={ws}", *FAST, cwd=tmp_path).returncode == 0
    assert (
        dvpmvs(
            "fuse", f"workspace={ws}", f"fusion={backend}", f"output={ws / 'all.ply'}", cwd=tmp_path
        ).returncode
        == 0
    )
    result = dvpmvs(
        "fuse",
        f"workspace={ws}",
        f"fusion={backend}",
        f"output={ws / 'masked.ply'}",
        "mask=files",
        "mask.path=masks_openmvs",
        "mask.layout=openmvs",
        "mask.ignore_label=3",
        cwd=tmp_path,
    )
    assert result.returncode == 0, result.stderr[-2000:]
    every, kept = read_points(ws / "all.ply"), read_points(ws / "masked.ply")
    assert 0.2 * len(every) < len(kept) < 0.8 * len(every)
    _assert_in_the_kept_left_half(ws, kept, ws / "masked.ply.vis")


@pytest.mark.slow
def test_colmaps_program_with_the_same_masks_takes_no_masked_pixel_of_our_maps(workspace, tmp_path):
    """The masks in COLMAP's layout, given to Debian's ``colmap stereo_fusion`` with our maps made
    without them: COLMAP reads the same files the same way."""
    import shutil

    from dvpmvs.evaluation.pointclouds import read_points

    if shutil.which("colmap") is None:
        pytest.skip(
            "COLMAP's command-line program is not installed (`make test` installs Debian's `colmap` "
            "where apt-get can be used)"
        )
    ws = tmp_path / "ws"
    shutil.copytree(workspace, ws)
    assert dvpmvs("dense", f"workspace={ws}", *FAST, cwd=tmp_path).returncode == 0
    run = subprocess.run(
        [
            "colmap",
            "stereo_fusion",
            "--workspace_path",
            ws,
            "--input_type",
            "geometric",
            "--output_path",
            ws / "colmap.ply",
            "--StereoFusion.min_num_pixels",
            "2",
            "--StereoFusion.mask_path",
            ws / "masks_colmap",
        ],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert run.returncode == 0, run.stderr[-2000:]
    points = read_points(ws / "colmap.ply")
    assert len(points) > 500
    _assert_in_the_kept_left_half(ws, points, ws / "colmap.ply.vis")


@pytest.mark.slow
def test_colmaps_program_with_ground_truth_sky_masks_puts_no_point_in_the_sky(tmp_path):
    """The courtyard's open sky (ground truth) as masks in COLMAP's layout, given to Debian's
    ``colmap stereo_fusion`` with our maps made without them: no point in the sky, where the same
    fusion without the masks puts some."""
    import shutil

    from dvpmvs.evaluation.experiments.sky_masks import write_sky_masks
    from dvpmvs.evaluation.runs import _sky_points
    from dvpmvs.workspace import Workspace

    if shutil.which("colmap") is None:
        pytest.skip(
            "COLMAP's command-line program is not installed (`make test` installs Debian's `colmap` "
            "where apt-get can be used)"
        )
    ws = tmp_path / "courtyard"
    made = dvpmvs(
        "synth", f"out={ws}", "scene=courtyard", "views=4", "width=240", "seed=0", cwd=tmp_path
    )
    assert made.returncode == 0, made.stderr[-2000:]
    write_sky_masks(ws, ws / "sky")
    assert dvpmvs("dense", f"workspace={ws}", *FAST, cwd=tmp_path).returncode == 0
    workspace, shares = Workspace.open(ws), {}
    for name, extra in (("all", []), ("masked", ["--StereoFusion.mask_path", ws / "sky"])):
        run = subprocess.run(
            [
                "colmap",
                "stereo_fusion",
                "--workspace_path",
                ws,
                "--input_type",
                "geometric",
                "--output_path",
                ws / f"{name}.ply",
                *extra,
            ],
            capture_output=True,
            text=True,
            timeout=600,
        )
        assert run.returncode == 0, run.stderr[-2000:]
        shares[name] = _sky_points(
            ws / f"{name}.ply", workspace, ws / "ground_truth" / "depth_maps"
        )
    assert shares["all"] > 0.008 and shares["masked"] == 0, (
        shares
    )  # measured: 1.7 % without the masks


def test_masks_that_keep_nothing_are_named_for_an_empty_cloud(workspace, tmp_path):
    folder = tmp_path / "m"
    folder.mkdir()
    for image in sorted((workspace / "images").glob("*.png")):
        cv2.imwrite(str(folder / f"{image.name}.png"), np.zeros((H, W), np.uint8))
    args = [f"workspace={workspace}", *FAST, f"out={tmp_path / 'o'}", "fuse=true"]
    result = dvpmvs("dense", *args, "mask=files", f"mask.path={folder}", cwd=tmp_path)
    said = " ".join((result.stdout + result.stderr).split())
    assert result.returncode == 0, result.stderr[-2000:]
    assert "the masks (mask=files) keep no pixel of any view" in said
    assert "fusion thresholds" not in said  # not blamed on fusion
