"""``dvpmvs synth``: synthetic COLMAP workspaces with exact ground truth.

Writes, under ``out``::

    images/<view>.png                 rendered views (8-bit, with sensor noise)
    sparse/                           COLMAP binary model: PINHOLE camera, posed images, sparse
                                      points whose tracks are exact projections (corners found by
                                      OpenCV, lifted with the true depth, kept if seen twice)
    stereo/patch-match.cfg, fusion.cfg
    ground_truth/depth_maps/<view>.bin, normal_maps/<view>.bin   COLMAP format (pycolmap)
    ground_truth/previews/<view>.{depth,normal}.png
    ground_truth/scan_alignment.mlp, scans/<view>.ply            ETH3D format (see below)
    ground_truth/eth3d_parameters.json  beam parameters matching these scans
    ground_truth/specular/<view>.bin    the specular term of each pixel (grey, COLMAP map format)
    ground_truth/highlights/<view>      the highlight mask (8-bit PNG, 255: highlight; see below)
    ground_truth/diffuse/<view>         the view without its specular term (with the same noise)
    ground_truth/textureless/<view>     the pixels on surfaces of uniform albedo (8-bit PNG, 255: plain
                                        walls, ceilings; shading is their only signal)
    simulated_priors/depth/<view>.bin, normal/<view>.bin         SIMULATED monocular priors
    scene.json                        generation parameters and statistics

ETH3D ground truth: one scan per view, the scanner at the camera centre, holding that view's
surface points (one per pixel) that at least one other view also sees within 1 % of its depth
(:mod:`dvpmvs.evaluation.depth_scans`); ``eth3d_parameters.json`` gives the beam divergence to
pass to the official program as ``--beam_divergence_halfangle_deg``.

Simulated priors stand in for monocular networks: depth = true depth under a smooth random
scale and shift field, blurred across edges, defined everywhere; normals = true normals
smoothed and perturbed. They let prior-guided methods be evaluated without network weights.
Same parameters and seed give the same bytes.

Highlight ground truth: a pixel is a highlight when its specular term (Blinn-Phong, white light)
is at least ``HIGHLIGHT_MIN_SPECULAR`` (0.04, ten grey levels) and at least
``HIGHLIGHT_MIN_SHARE`` (20 %) of the pixel's rendered intensity: where the lobe changes what
the views see enough to break photo-consistency.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from dataclasses import asdict, dataclass
from pathlib import Path

import cv2
import numpy as np
import pycolmap
from scipy.ndimage import gaussian_filter

from dvpmvs.errors import DvpmvsError
from dvpmvs.evaluation.depth_scans import (
    CAM_FROM_SCAN,
    backproject,
    beam_parameters,
    visible_in,
    write_scans,
)
from dvpmvs.evaluation.portable import matmul
from dvpmvs.evaluation.render import SceneRenderer
from dvpmvs.evaluation.report import write_json
from dvpmvs.evaluation.synthetic_scenes import SCENES, build_scene
from dvpmvs.evaluation.textures import make_texture
from dvpmvs.maps import (
    atomic_path,
    read_json_object,
    write_depth_map,
    write_extra_map,
    write_normal_map,
)
from dvpmvs.preview import colorize_depth, colorize_normals, write_png
from dvpmvs.validation import check_field_types
from dvpmvs.workspace import write_stereo_configs
from dvpmvs.writer_lock import writer_lock

__all__ = ["SynthOptions", "generate", "colorize_depth", "colorize_normals", "CAM_FROM_SCAN"]

HIGHLIGHT_MIN_SPECULAR = 0.04
HIGHLIGHT_MIN_SHARE = 0.2


def highlight_mask(specular: np.ndarray, image: np.ndarray) -> np.ndarray:
    """The ground-truth highlight mask of a rendering: specular term (H, W) against the rendered
    colour (H, W, 3) in [0, 1] (see the module docstring)."""
    intensity = image.mean(axis=2)
    return (specular >= HIGHLIGHT_MIN_SPECULAR) & (specular >= HIGHLIGHT_MIN_SHARE * intensity)


@dataclass(frozen=True)
class SynthOptions:
    scene: str = "room"
    views: int = 8
    width: int = 800
    height: int | None = None  # default: 3/4 of the width
    seed: int = 0
    noise: float = 0.01  # sensor noise, standard deviation in [0, 1] units
    corners_per_view: int = 600  # candidate sparse points per view (before the 2-view filter)
    texture_size: int = 512
    priors: bool = True  # write the simulated priors

    def __post_init__(self):
        check_field_types(self)
        if self.scene not in SCENES:
            raise DvpmvsError(
                f"unknown scene {self.scene!r}; choose one of {', '.join(sorted(SCENES))}"
            )
        if self.views < 2:
            raise DvpmvsError(f"views must be at least 2, got {self.views}")
        if self.width < 32 or (self.height is not None and self.height < 24):
            raise DvpmvsError("images must be at least 32 x 24 pixels")
        if self.noise < 0:
            raise DvpmvsError("noise must be non-negative")

    @property
    def image_height(self) -> int:
        return self.height if self.height is not None else int(round(self.width * 3 / 4))


def _write_map(path: Path, array: np.ndarray, kind: str) -> None:
    (write_depth_map if kind == "depth" else write_normal_map)(path, array)


def _smooth_field(rng: np.random.Generator, shape, cells: int, amplitude: float) -> np.ndarray:
    """A smooth random field (float64: OpenCV's float32 resampling differs between SIMD paths)."""
    grid = rng.standard_normal((cells, cells)).astype(np.float32).astype(np.float64) * amplitude
    return cv2.resize(grid, (shape[1], shape[0]), interpolation=cv2.INTER_CUBIC)


def _blurred(image: np.ndarray, sigma: float) -> np.ndarray:
    """A Gaussian blur of each channel in float64 (SciPy's, compiled without per-CPU variants;
    OpenCV's float32 blur has SIMD paths that differ in the last bits), borders mirrored."""
    sigmas = (sigma, sigma) + (0,) * (image.ndim - 2)
    return gaussian_filter(np.asarray(image, np.float64), sigmas, mode="mirror", truncate=4.0)


def _simulated_depth_prior(rng, depth: np.ndarray) -> np.ndarray:
    """True depth under a smooth scale/shift field, blurred across edges, filled everywhere."""
    valid = depth > 0
    h, w = depth.shape
    filled = depth.copy()
    if not np.all(valid):
        far = float(np.percentile(depth[valid], 99)) * 1.5 if np.any(valid) else 1.0
        filled[~valid] = far
    median = float(np.median(filled))
    # exp in float64, rounded once: numpy's float32 exp differs between its SIMD variants
    scale = np.exp(_smooth_field(rng, (h, w), 3, 0.08)) * rng.uniform(0.7, 1.3)
    shift = _smooth_field(rng, (h, w), 3, 0.05 * median)
    sigma = max(1.0, 2.5 * w / 800)
    prior = _blurred(filled, sigma) * scale + shift
    return np.maximum(prior, 1e-3 * median).astype(np.float32)


def _simulated_normal_prior(rng, normal: np.ndarray) -> np.ndarray:
    """True normals smoothed and perturbed by a smooth random field, renormalised."""
    h, w = normal.shape[:2]
    filled = normal.copy()
    filled[np.all(normal == 0, axis=-1)] = (0.0, 0.0, -1.0)
    sigma = max(1.0, 2.0 * w / 800)
    smooth = _blurred(filled, sigma)
    noise = np.stack([_smooth_field(rng, (h, w), 8, 0.08) for _ in range(3)], axis=-1)
    noisy = smooth + noise + rng.normal(0, 0.02, smooth.shape).astype(np.float32)
    noisy /= (
        np.sqrt(noisy[..., 0] ** 2 + noisy[..., 1] ** 2 + noisy[..., 2] ** 2)[..., None] + 1e-12
    )
    noisy[noisy[..., 2] > 0] *= -1  # keep facing the camera
    return noisy.astype(np.float32)


# What a rendered scene is in its folder: replaced whole by a rerun, so that the folder holds
# exactly the scene it names (a run's outputs beside them, stereo/'s maps, are left alone).
SCENE_ENTRIES = (
    "images",
    "sparse",
    "ground_truth",
    "simulated_priors",
    "stereo/patch-match.cfg",
    "stereo/fusion.cfg",
)
_MARKER = ".dvpmvs-synth"  # beside the scene (hidden: not part of its digest)


def _written_by_synth(folder: Path) -> bool:
    """Whether ``folder`` is empty (hidden files aside) or holds a scene ``generate`` wrote (its
    marker; or, written before the marker, a ``scene.json`` with synth's statistics)."""
    if (folder / _MARKER).is_file() or not any(
        not p.name.startswith(".") for p in folder.iterdir()
    ):
        return True
    scene = read_json_object(folder / "scene.json") or {}
    return {"options", "intrinsics", "eth3d_parameters"} <= set(scene)


def generate(
    out: str | Path,
    options: SynthOptions = SynthOptions(),
    progress=None,
    overwrite: bool = False,
) -> dict:
    """Render a scene and write the workspace, ground truth and simulated priors to ``out``.

    ``progress``, if given, is called as ``progress(step_description)`` per view and stage.
    Returns the statistics also written to ``scene.json``. The scene is rendered into a
    temporary folder inside ``out`` and then replaces the scene there whole
    (:data:`SCENE_ENTRIES`: a rerun with fewer views leaves none of the others), under ``out``'s
    writer lock (another synth writing there stops this one with its holder named). A folder
    holding files that dvpmvs did not write is refused unless ``overwrite``.
    """
    out = Path(out)
    with writer_lock(out):
        if not overwrite and not _written_by_synth(out):
            raise DvpmvsError(
                f"{out} holds files dvpmvs synth did not write; it does not render a scene over "
                f"them unasked: give out= an empty or new folder, or overwrite=true to replace "
                f"its {', '.join(SCENE_ENTRIES)} and scene.json"
            )
        staging = Path(tempfile.mkdtemp(prefix=".synth-", dir=out))
        try:
            stats = _render(staging, options, progress)
            (out / "scene.json").unlink(missing_ok=True)  # a half-replaced scene has none
            for entry in SCENE_ENTRIES:
                target, made = out / entry, staging / entry
                if target.is_dir() and not target.is_symlink():
                    shutil.rmtree(target)
                elif target.exists() or target.is_symlink():
                    target.unlink()
                if made.exists():
                    target.parent.mkdir(parents=True, exist_ok=True)
                    os.replace(made, target)
            with atomic_path(out / _MARKER) as tmp:
                tmp.write_text(json.dumps(asdict(options)) + "\n")
            os.replace(staging / "scene.json", out / "scene.json")
        finally:
            shutil.rmtree(staging, ignore_errors=True)
    return stats


def _render(out: Path, options: SynthOptions, progress) -> dict:
    """:func:`generate`'s rendering into the (new, empty) folder ``out``."""
    width, height = options.width, options.image_height
    streams = np.random.SeedSequence(options.seed).spawn(5)
    rng_scene, rng_tex, rng_noise, rng_prior, rng_misc = (np.random.default_rng(s) for s in streams)
    scene = build_scene(options.scene, rng_scene, options.views)
    textures = {
        name: make_texture(scene.materials[name].texture, rng_tex, options.texture_size)
        for name in sorted(scene.materials)
    }
    renderer = SceneRenderer(scene, textures)
    focal = scene.focal_factor * width
    K = np.array([[focal, 0, width / 2], [0, focal, height / 2], [0, 0, 1.0]])
    names = [f"{i:04d}.png" for i in range(options.views)]
    stems = [Path(n).stem for n in names]

    images, depths, normals, speculars, highlights = [], [], [], [], []
    for i, (R, t) in enumerate(scene.cameras):
        if progress:
            progress(f"render {names[i]}")
        r = renderer.render(K, R, t, width, height)
        noise = rng_noise.normal(0, options.noise, r.image.shape).astype(np.float32)
        image8 = np.clip(np.round((r.image + noise) * 255), 0, 255).astype(np.uint8)
        write_png(
            out / "ground_truth" / "textureless" / names[i], r.textureless.astype(np.uint8) * 255
        )
        write_png(
            out / "ground_truth" / "diffuse" / names[i],
            np.clip(np.round((r.diffuse + noise) * 255), 0, 255).astype(np.uint8)[..., ::-1],
        )
        images.append(image8)
        depths.append(r.depth)
        normals.append(r.normal)
        speculars.append(r.specular)
        highlights.append(highlight_mask(r.specular, r.image))
        write_png(out / "images" / names[i], image8[..., ::-1])

    # Ground-truth maps, previews and the per-view ETH3D scans.
    gt = out / "ground_truth"
    for i in range(len(scene.cameras)):
        if progress:
            progress(f"ground truth {names[i]}")
        _write_map(gt / "depth_maps" / f"{names[i]}.bin", depths[i], "depth")
        _write_map(gt / "normal_maps" / f"{names[i]}.bin", normals[i], "normal")
        write_png(gt / "previews" / f"{stems[i]}.depth.png", colorize_depth(depths[i]))
        write_png(gt / "previews" / f"{stems[i]}.normal.png", colorize_normals(normals[i]))
        write_extra_map(gt / "specular" / f"{names[i]}.bin", speculars[i])
        write_png(gt / "highlights" / f"{names[i]}", highlights[i].astype(np.uint8) * 255)
    scan_points_total = write_scans(gt, stems, depths, scene.cameras, K)
    beam = beam_parameters(focal)
    write_json(gt / "eth3d_parameters.json", beam)

    # Sparse model: corners of each view, lifted with the true depth, tracked by projection.
    if progress:
        progress("sparse model")
    reconstruction, num_points, mean_track = _sparse_model(
        images, depths, scene.cameras, K, names, width, height, options.corners_per_view
    )
    sparse = out / "sparse"
    sparse.mkdir(parents=True, exist_ok=True)
    reconstruction.write(str(sparse))

    num_sources = min(20, options.views - 1)
    write_stereo_configs(out / "stereo", {n: f"__auto__, {num_sources}" for n in names})

    if options.priors:
        priors = out / "simulated_priors"
        for i in range(options.views):
            if progress:
                progress(f"simulated priors {names[i]}")
            depth_prior = _simulated_depth_prior(rng_prior, depths[i])
            normal_prior = _simulated_normal_prior(rng_prior, normals[i])
            _write_map(priors / "depth" / f"{names[i]}.bin", depth_prior, "depth")
            _write_map(priors / "normal" / f"{names[i]}.bin", normal_prior, "normal")
            write_png(priors / "previews" / f"{stems[i]}.depth.png", colorize_depth(depth_prior))
            write_png(
                priors / "previews" / f"{stems[i]}.normal.png", colorize_normals(normal_prior)
            )
        with atomic_path(priors / "README.txt") as tmp:
            tmp.write_text(
                "SIMULATED monocular priors, not the output of any network.\n"
                "depth/<image>.bin: true depth times a smooth random scale field plus a smooth random\n"
                "shift field, Gaussian-blurred across edges, defined at every pixel (sky included).\n"
                "normal/<image>.bin: true camera-frame normals, Gaussian-smoothed, perturbed by a smooth\n"
                "random field and pixel noise, renormalised. Both in COLMAP's map format.\n"
            )

    valid = np.concatenate([d[d > 0] for d in depths])
    stats = {
        "options": asdict(options) | {"height": height},
        "intrinsics": {"model": "PINHOLE", "params": [focal, focal, width / 2, height / 2]},
        "depth_range": [float(valid.min()), float(valid.max())] if len(valid) else [0.0, 0.0],
        "sparse_points": num_points,
        "mean_track_length": mean_track,
        "scan_points": scan_points_total,
        "highlight_fraction": float(np.mean([h.mean() for h in highlights])),
        "eth3d_parameters": beam,
    }
    write_json(out / "scene.json", stats)
    return stats


def _sparse_model(images, depths, cameras, K, names, width, height, corners_per_view):
    recon = pycolmap.Reconstruction()
    camera = pycolmap.Camera(
        model="PINHOLE",
        width=width,
        height=height,
        params=[K[0, 0], K[1, 1], K[0, 2], K[1, 2]],
        camera_id=1,
    )
    recon.add_camera_with_trivial_rig(camera)
    min_distance = max(3, width // 100)
    points, tracks = [], []
    for i, (image, depth) in enumerate(zip(images, depths)):
        grey = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
        corners = cv2.goodFeaturesToTrack(grey, corners_per_view, 0.01, min_distance)
        if corners is None:
            continue
        xy = np.round(corners.reshape(-1, 2)).astype(np.int64)
        cols, rows = xy[:, 0], xy[:, 1]
        keep = depth[rows, cols] > 0
        rows, cols = rows[keep], cols[keep]
        world = backproject(depth, K, *cameras[i], rows, cols)
        vis = np.stack(
            [visible_in(world, R, t, K, d) for (R, t), d in zip(cameras, depths)], axis=1
        )
        vis[:, i] = True
        ok = vis.sum(axis=1) >= 2
        points.append(world[ok])
        tracks.append(vis[ok])
    points = np.concatenate(points) if points else np.zeros((0, 3))
    tracks = np.concatenate(tracks) if tracks else np.zeros((0, len(names)), bool)

    # Keypoints per image: the exact projections of the points that image sees.
    keypoints = []
    for j, (R, t) in enumerate(cameras):
        pc = matmul(points[tracks[:, j]], R.T) + t
        xy = np.stack(
            [K[0, 0] * pc[:, 0] / pc[:, 2] + K[0, 2], K[1, 1] * pc[:, 1] / pc[:, 2] + K[1, 2]],
            axis=1,
        )
        keypoints.append(xy)
        image = pycolmap.Image(
            name=names[j], keypoints=xy.astype(np.float64), camera_id=1, image_id=j + 1
        )
        recon.add_image_with_trivial_frame(image, pycolmap.Rigid3d(pycolmap.Rotation3d(R), t))
    index_in_image = np.cumsum(tracks, axis=0) - 1
    for p, (xyz, vis) in enumerate(zip(points, tracks)):
        track = pycolmap.Track()
        for j in np.flatnonzero(vis):
            track.add_element(int(j + 1), int(index_in_image[p, j]))
        pid = recon.add_point3D(xyz, track)
        first = int(np.flatnonzero(vis)[0])
        kp = keypoints[first][index_in_image[p, first]]
        col = np.clip(np.round(kp), 0, [width - 1, height - 1]).astype(int)
        recon.point3D(pid).color = images[first][col[1], col[0]]
    mean_track = float(tracks.sum(axis=1).mean()) if len(tracks) else 0.0
    return recon, int(len(points)), mean_track
