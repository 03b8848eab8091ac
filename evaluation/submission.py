"""Leaderboard submission files.

- ETH3D: ``<track>/<scene>.ply`` (float32 x, y, z) and ``<track>/<scene>.txt`` containing
  ``runtime <seconds>``, the track (``high_res_multi_view`` or ``low_res_many_view``) given by the
  scene. The benchmark takes one archive per track holding that folder with every scene of the
  track (training and test), as the ETH3D authors' Robust Vision Challenge devkit packs it
  (``7z a high_res_multi_view.7z high_res_multi_view``).
- Tanks and Temples: ``<scene>.ply`` and ``<scene>.log``, the camera-to-world trajectory of the
  input images (used by the server to align the reconstruction), one entry per image.

Scene names are checked against each benchmark's list, as the benchmarks spell them.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pycolmap

from dvpmvs.errors import DvpmvsError
from dvpmvs.evaluation.pointclouds import read_point_cloud, write_point_cloud
from dvpmvs.evaluation.tanks import write_log
from dvpmvs.maps import atomic_path, read_json_object, write_json
from dvpmvs.reconstruction import IMAGE_SUFFIXES

__all__ = [
    "SCENES",
    "ETH3D_TRACKS",
    "check_scene",
    "eth3d_track",
    "missing_eth3d_scenes",
    "write_eth3d_submission",
    "write_tanks_submission",
]

# The benchmarks' scene names (the case matters).
SCENES = {
    "tanks": (
        "Barn",
        "Caterpillar",
        "Church",
        "Courthouse",
        "Ignatius",
        "Meetingroom",
        "Truck",  # training
        "Family",
        "Francis",
        "Horse",
        "Lighthouse",
        "M60",
        "Panther",
        "Playground",
        "Train",  # intermediate
        "Auditorium",
        "Ballroom",
        "Courtroom",
        "Museum",
        "Palace",
        "Temple",
    ),  # advanced
}
# ETH3D's multi-view tracks and their scenes (training, then test). A submission folder is named
# after its track.
ETH3D_TRACKS = {
    "high_res_multi_view": (
        "courtyard",
        "delivery_area",
        "electro",
        "facade",
        "kicker",
        "meadow",
        "office",
        "pipes",
        "playground",
        "relief",
        "relief_2",
        "terrace",
        "terrains",  # training
        "botanical_garden",
        "boulders",
        "bridge",
        "door",
        "exhibition_hall",
        "lecture_room",
        "living_room",
        "lounge",
        "observatory",
        "old_computer",
        "statue",
        "terrace_2",
    ),
    "low_res_many_view": (
        "delivery_area",
        "electro",
        "forest",
        "playground",
        "terrains",  # training
        "lakeside",
        "sand_box",
        "storage_room",
        "storage_room_2",
        "tunnel",
    ),
}
SCENES["eth3d"] = tuple(
    dict.fromkeys(ETH3D_TRACKS["high_res_multi_view"] + ETH3D_TRACKS["low_res_many_view"])
)


# Lists, in a submission folder, the files `dvpmvs submit` wrote there: only those are replaced
# unasked (a scene submitted again); any other file of the same name is the user's.
_SUBMISSION_RECORD = ".dvpmvs-submission"


def _written_files(out_dir: Path) -> set[str]:
    return set((read_json_object(out_dir / _SUBMISSION_RECORD) or {}).get("files", []))


def _refuse_foreign(out_dir: Path, targets: list[Path], overwrite: bool) -> None:
    """Stop before writing where one of ``targets`` exists and dvpmvs did not write it."""
    if overwrite:
        return
    written = _written_files(out_dir)
    for target in targets:
        if target.exists() and target.relative_to(out_dir).as_posix() not in written:
            raise DvpmvsError(
                f"{target} exists and dvpmvs did not write it; it is not replaced unasked: give "
                f"out= another folder, or overwrite=true to replace it"
            )


def _record_written(out_dir: Path, files: list[Path]) -> None:
    written = _written_files(out_dir) | {f.relative_to(out_dir).as_posix() for f in files}
    write_json(out_dir / _SUBMISSION_RECORD, {"files": sorted(written)})


def _copy_cloud(cloud_path: str | Path, target: Path) -> None:
    cloud = read_point_cloud(cloud_path)
    colors = np.asarray(cloud.colors) if cloud.has_colors() else None
    normals = np.asarray(cloud.normals) if cloud.has_normals() else None
    write_point_cloud(target, np.asarray(cloud.points), colors, normals)


def eth3d_track(scene: str, track: str | None = None) -> str:
    """The ETH3D track ``scene`` belongs to; ``track`` chooses for a scene in both (the low-res
    many-view track's training scenes ``delivery_area``, ``electro``, ``playground`` and
    ``terrains`` share their names with high-res ones)."""
    check_scene("eth3d", scene)
    if track is not None:
        if track not in ETH3D_TRACKS:
            raise DvpmvsError(f"unknown ETH3D track {track!r}; choose {' or '.join(ETH3D_TRACKS)}")
        if scene not in ETH3D_TRACKS[track]:
            raise DvpmvsError(
                f"{scene!r} is not a scene of ETH3D's {track} track; its scenes: "
                f"{', '.join(ETH3D_TRACKS[track])}"
            )
        return track
    tracks = [name for name, scenes in ETH3D_TRACKS.items() if scene in scenes]
    if len(tracks) > 1:
        raise DvpmvsError(
            f"{scene!r} is a scene of both ETH3D tracks; say which with track="
            f"{' or track='.join(tracks)}"
        )
    return tracks[0]


def missing_eth3d_scenes(out_dir: str | Path, track: str) -> list[str]:
    """The scenes of ``track`` whose ``.ply`` or ``.txt`` is not yet in ``out_dir/<track>``:
    the benchmark takes a track's archive only with all of them."""
    folder = Path(out_dir) / track
    return [
        scene
        for scene in ETH3D_TRACKS[track]
        if not ((folder / f"{scene}.ply").is_file() and (folder / f"{scene}.txt").is_file())
    ]


def write_eth3d_submission(
    out_dir: str | Path,
    scene: str,
    cloud_path: str | Path,
    runtime_seconds: float,
    track: str | None = None,
    overwrite: bool = False,
) -> list[Path]:
    """``out_dir/<track>/<scene>.ply`` and ``.txt``; the track is the scene's (``track`` where it is
    in both). A file there that dvpmvs did not write is replaced only with ``overwrite``."""
    track = eth3d_track(scene, track)
    if not (math.isfinite(runtime_seconds) and runtime_seconds >= 0):
        raise DvpmvsError(
            f"runtime must be a finite, non-negative number of seconds (the time the method took on "
            f"the scene), got {runtime_seconds}"
        )
    out_dir = Path(out_dir)
    ply, txt = out_dir / track / f"{scene}.ply", out_dir / track / f"{scene}.txt"
    _refuse_foreign(out_dir, [ply, txt], overwrite)
    _copy_cloud(cloud_path, ply)
    with atomic_path(txt) as tmp:
        tmp.write_text(f"runtime {runtime_seconds:.2f}\n")
    _record_written(out_dir, [ply, txt])
    return [ply, txt]


def check_scene(benchmark: str, scene: str) -> None:
    """``scene`` must be one of the benchmark's scene names, spelt as the benchmark spells them."""
    names = SCENES[benchmark]
    if scene not in names:
        near = [name for name in names if name.lower() == scene.lower()]
        hint = f" (did you mean {near[0]}? the case matters)" if near else ""
        raise DvpmvsError(
            f"{scene!r} is not a scene of {benchmark}{hint}; its scenes: {', '.join(names)}"
        )


def write_tanks_submission(
    out_dir: str | Path,
    scene: str,
    cloud_path: str | Path,
    sparse_model: str | Path,
    images: str | Path,
    overwrite: bool = False,
) -> list[Path]:
    """``<scene>.ply`` and ``<scene>.log`` (a file there that dvpmvs did not write is replaced
    only with ``overwrite``). ``sparse_model``: the COLMAP model whose cameras the
    reconstruction was made from; ``images``: the folder of the scene's input images. As the
    toolbox's ``convert_to_logfile.py``, the log has one entry per input image, in the order of
    their sorted names: the registered image's camera-to-world pose (metadata ``k k 0``), or the
    identity for an image the model lacks (``k -1 0``). The server pairs cameras by index, so an
    image left out would shift every later one and give a wrong alignment."""
    check_scene("tanks", scene)
    out_dir = Path(out_dir)
    try:
        recon = pycolmap.Reconstruction(str(sparse_model))
    except Exception as exc:  # pycolmap raises plain RuntimeErrors for unreadable models
        raise DvpmvsError(f"cannot read the COLMAP model {sparse_model}: {exc}") from None
    registered = {Path(im.name).name: im for im in recon.images.values() if im.has_pose}
    if not registered:
        raise DvpmvsError(f"the COLMAP model {sparse_model} has no registered images")
    folder = Path(images)
    if not folder.is_dir():
        raise DvpmvsError(
            f"images={folder} is not a folder: a Tanks and Temples log lists every input image"
        )
    names = sorted(
        p.name for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES
    )
    unknown = sorted(set(registered) - set(names))
    if unknown:
        raise DvpmvsError(
            f"{len(unknown)} image(s) of the model are not in images={folder} (e.g. {unknown[0]}): give the "
            f"folder of the images the model was made from"
        )
    poses, metadata = [], []
    for k, name in enumerate(names):
        world_from_cam = np.eye(4)
        if name in registered:
            world_from_cam[:3, :] = registered[name].cam_from_world().inverse().matrix()
        poses.append(world_from_cam)
        metadata.append((k, k if name in registered else -1, 0))
    ply, log = out_dir / f"{scene}.ply", out_dir / f"{scene}.log"
    _refuse_foreign(out_dir, [ply, log], overwrite)
    _copy_cloud(cloud_path, ply)
    write_log(log, poses, metadata)
    _record_written(out_dir, [ply, log])
    return [ply, log]
