"""Tanks and Temples: precision, recall and F-score at the scene threshold, and the scene files.

As the official toolbox (github.com/isl-org/TanksAndTemples, ``python_toolbox/evaluation``)
does it: the reconstruction is brought into the ground truth's frame by the alignment
(``<scene>_trans.txt`` applied to the reference COLMAP trajectory, matched to the submitted
trajectory by RANSAC on the camera centres, when a trajectory is given; a trajectory of every
video frame is first reduced with ``<scene>_mapping_reference.txt``), refined by three ICP
rounds inside the crop volume (voxel tau, then tau/2, then uniform subsampling at 2 tau), then
both clouds are cropped (``<scene>.json``) and voxel-downsampled at tau/2, and
precision / recall are the shares of points closer than tau to the other cloud.

The ICP rounds stop as the toolbox's do, quirk included: it builds its convergence criteria as
``ICPConvergenceCriteria(1e-6, max_itr)``, which sets the relative fitness to 1e-6 and the
*relative RMSE* to ``max_itr`` (20), leaving the iteration cap at Open3D's 30; so each round stops
as soon as the fitness settles. Iterating until the RMSE settles too, point-to-point ICP with
scaling lets outliers shrink the scale (0.55 instead of 0.98 at 5 cm on a cloud with 3 %
outliers) and scores 15 to 41 F-points off the leaderboard's program (docs/formats.md).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import open3d as o3d

from dvpmvs.errors import DvpmvsError
from dvpmvs.evaluation.eth3d_metric import f_score
from dvpmvs.maps import atomic_path

__all__ = [
    "TanksScene",
    "TanksResult",
    "read_log",
    "write_log",
    "evaluate_tanks",
    "align_trajectories",
]

_MAX_POINTS = 4_000_000  # the toolbox subsamples larger clouds for the final ICP round
_ICP_MAX_ITERATIONS = 30  # Open3D's default, which the toolbox's criteria leave in place
reg = o3d.pipelines.registration


def read_log(path: str | Path) -> list[np.ndarray]:
    """Camera-to-world 4x4 poses of a ``.log`` trajectory (a metadata line, then 4 rows, per camera)."""
    path = Path(path)
    try:
        lines = [ln for ln in path.read_text().splitlines() if ln.strip()]
    except OSError as exc:
        raise DvpmvsError(f"cannot read trajectory {path}: {exc}") from None
    if len(lines) % 5:
        raise DvpmvsError(
            f"{path}: a .log trajectory has 5 lines per camera; found {len(lines)} lines"
        )
    poses = []
    for k in range(0, len(lines), 5):
        try:
            poses.append(np.array([[float(v) for v in lines[k + i].split()] for i in range(1, 5)]))
        except ValueError:
            raise DvpmvsError(f"{path}: camera {k // 5} has a malformed matrix") from None
        if poses[-1].shape != (4, 4):
            raise DvpmvsError(f"{path}: camera {k // 5} is not a 4x4 matrix")
    return poses


def write_log(
    path: str | Path, poses: list[np.ndarray], metadata: list[tuple[int, int, int]] | None = None
) -> Path:
    """Write camera-to-world poses as a ``.log`` trajectory; ``metadata``: each entry's first line
    (default ``i i 0``; the toolbox writes ``i -1 0`` for an image its reconstruction lacks)."""
    text = []
    for i, pose in enumerate(poses):
        text.append(
            " ".join(str(int(v)) for v in (metadata[i] if metadata is not None else (i, i, 0)))
        )
        text.extend(" ".join(f"{v:.12f}" for v in row) for row in np.asarray(pose).reshape(4, 4))
    with atomic_path(path) as tmp:
        tmp.write_text("\n".join(text) + "\n")
    return Path(path)


@dataclass
class TanksScene:
    """The ground-truth files of one Tanks and Temples training scene."""

    name: str
    ground_truth: Path  # <scene>.ply
    crop: Path  # <scene>.json, an Open3D selection polygon volume
    alignment: Path | None  # <scene>_trans.txt
    reference_log: Path | None  # <scene>_COLMAP_SfM.log
    threshold: float | None = None

    @classmethod
    def open(cls, folder: str | Path, threshold: float | None = None) -> TanksScene:
        folder = Path(folder)
        name = folder.name
        gt = folder / f"{name}.ply"
        crop = folder / f"{name}.json"
        for path in (gt, crop):
            if not path.is_file():
                raise DvpmvsError(
                    f"{folder} is not a Tanks and Temples ground-truth folder: {path.name} is missing"
                )
        trans = folder / f"{name}_trans.txt"
        log = folder / f"{name}_COLMAP_SfM.log"
        return cls(
            name,
            gt,
            crop,
            trans if trans.is_file() else None,
            log if log.is_file() else None,
            threshold,
        )


@dataclass
class TanksResult:
    threshold: float
    precision: float
    recall: float
    fscore: float
    transformation: list = field(default_factory=list)  # reconstruction -> ground truth, row-major
    # precision, recall and F-score at thresholds from a tenth of ``threshold`` to five times it,
    # as the toolbox plots them (its plot_stretch of 5): {"thresholds", "precision", "recall", "fscore"}
    curve: dict = field(default_factory=dict)

    def as_dict(self) -> dict:
        return asdict(self)


def align_trajectories(
    submitted: list[np.ndarray],
    reference: list[np.ndarray],
    reference_to_gt: np.ndarray,
    seed: int = 0,
) -> np.ndarray:
    """Similarity taking the submitted trajectory's camera centres onto the reference's in the
    ground-truth frame (RANSAC on corresponding centres, as the toolbox's first step)."""
    if len(submitted) != len(reference):
        raise DvpmvsError(
            f"the trajectory has {len(submitted)} cameras, the reference {len(reference)}"
        )
    src = o3d.geometry.PointCloud(
        o3d.utility.Vector3dVector(np.array([p[:3, 3] for p in submitted]))
    )
    dst = o3d.geometry.PointCloud(
        o3d.utility.Vector3dVector(np.array([p[:3, 3] for p in reference]))
    )
    dst.transform(reference_to_gt)
    corres = o3d.utility.Vector2iVector(
        np.stack([np.arange(len(submitted))] * 2, axis=1).astype(np.int32)
    )
    o3d.utility.random.seed(seed)
    result = reg.registration_ransac_based_on_correspondence(
        src,
        dst,
        corres,
        0.2,
        reg.TransformationEstimationPointToPoint(True),
        6,
        [],
        reg.RANSACConvergenceCriteria(100000, 0.999),
    )
    return np.asarray(result.transformation)


def _crop_down(cloud, volume, transform, voxel=None, uniform=False):
    c = o3d.geometry.PointCloud(cloud)
    c.transform(transform)
    if volume is not None:
        c = volume.crop_point_cloud(c)
    if voxel is not None:
        c = c.voxel_down_sample(voxel)
    elif uniform and len(c.points) > _MAX_POINTS:
        c = c.uniform_down_sample(int(round(len(c.points) / _MAX_POINTS)))
    return c


def _icp(source, target, init, volume, threshold, iterations, voxel=None, uniform=False):
    s = _crop_down(source, volume, init, voxel=voxel, uniform=uniform)
    t = _crop_down(target, volume, np.eye(4), voxel=voxel, uniform=uniform)
    if len(s.points) == 0 or len(t.points) == 0:
        return init
    # The toolbox's ICPConvergenceCriteria(1e-6, iterations): ``iterations`` lands on the relative
    # RMSE (see the module doc).
    criteria = reg.ICPConvergenceCriteria(
        relative_fitness=1e-6, relative_rmse=float(iterations), max_iteration=_ICP_MAX_ITERATIONS
    )
    result = reg.registration_icp(
        s, t, threshold, np.eye(4), reg.TransformationEstimationPointToPoint(True), criteria
    )
    return np.asarray(result.transformation) @ init


def evaluate_tanks(
    reconstruction: o3d.geometry.PointCloud,
    ground_truth: o3d.geometry.PointCloud,
    threshold: float,
    initial: np.ndarray | None = None,
    crop=None,
    refine: bool = True,
) -> TanksResult:
    """Precision, recall and F-score at ``threshold`` after alignment and crop.

    ``initial`` takes the reconstruction into the ground truth's frame; ``crop`` is an Open3D
    ``SelectionPolygonVolume`` (or None); ``refine`` runs the toolbox's three ICP rounds.
    """
    if not threshold > 0:
        raise DvpmvsError(f"the threshold must be positive, got {threshold}")
    T = np.eye(4) if initial is None else np.asarray(initial, float)
    if refine:
        T = _icp(reconstruction, ground_truth, T, crop, threshold * 80, 20, voxel=threshold)
        T = _icp(reconstruction, ground_truth, T, crop, threshold * 20, 20, voxel=threshold / 2)
        T = _icp(reconstruction, ground_truth, T, crop, 2 * threshold, 20, uniform=True)
    s = _crop_down(reconstruction, crop, T, voxel=threshold / 2)
    t = _crop_down(ground_truth, crop, np.eye(4), voxel=threshold / 2)
    if len(s.points) == 0 or len(t.points) == 0:
        return TanksResult(threshold, 0.0, 0.0, 0.0, T.tolist())
    to_truth = np.asarray(s.compute_point_cloud_distance(t))
    to_reconstruction = np.asarray(t.compute_point_cloud_distance(s))
    precision = float(np.mean(to_truth < threshold))
    recall = float(np.mean(to_reconstruction < threshold))
    return TanksResult(
        threshold,
        precision,
        recall,
        f_score(precision, recall),
        T.tolist(),
        _curve(to_truth, to_reconstruction, threshold),
    )


def _curve(
    to_truth: np.ndarray, to_reconstruction: np.ndarray, threshold: float, steps: int = 20
) -> dict:
    thresholds = threshold * np.geomspace(0.1, 5.0, steps)
    precision = [float(np.mean(to_truth < t)) for t in thresholds]
    recall = [float(np.mean(to_reconstruction < t)) for t in thresholds]
    return {
        "thresholds": thresholds.tolist(),
        "precision": precision,
        "recall": recall,
        "fscore": [f_score(p, r) for p, r in zip(precision, recall)],
    }


def read_mapping(path: str | Path) -> list[int]:
    """Frame numbers (1-based) of the reference cameras in a full video trajectory, from
    ``<scene>_mapping_reference.txt`` (sampled count, total count, then ``index frame`` rows)."""
    path = Path(path)
    try:
        rows = [ln.split() for ln in path.read_text().splitlines() if ln.strip()]
        count = int(rows[0][0])
        frames = [int(r[1]) for r in rows[2 : 2 + count]]
    except (OSError, ValueError, IndexError):
        raise DvpmvsError(f"{path} is not a Tanks and Temples mapping file") from None
    if len(frames) != count:
        raise DvpmvsError(f"{path} announces {count} frames but lists {len(frames)}")
    return frames


def evaluate_tanks_scene(
    scene: TanksScene,
    reconstruction_path: str | Path,
    trajectory: str | Path | None = None,
    refine: bool = True,
) -> TanksResult:
    """The toolbox's whole procedure on a scene folder and a submission (cloud + optional .log)."""
    from dvpmvs.evaluation.pointclouds import read_point_cloud

    if scene.threshold is None:
        raise DvpmvsError(
            f"no threshold for scene {scene.name}; give threshold=... (the scene's tau)"
        )
    recon = read_point_cloud(reconstruction_path)
    gt = read_point_cloud(scene.ground_truth)
    crop = o3d.visualization.read_selection_polygon_volume(str(scene.crop))
    initial = np.eye(4)
    if trajectory is not None:
        if scene.reference_log is None or scene.alignment is None:
            raise DvpmvsError(
                f"aligning a trajectory needs {scene.name}_COLMAP_SfM.log and {scene.name}_trans.txt"
            )
        submitted = read_log(trajectory)
        reference = read_log(scene.reference_log)
        mapping = scene.ground_truth.with_name(f"{scene.name}_mapping_reference.txt")
        if len(submitted) != len(reference) and mapping.is_file():
            # A trajectory of every video frame: keep the frames the reference cameras came from.
            frames = read_mapping(mapping)
            outside = [f for f in frames if not 1 <= f <= len(submitted)]
            if outside:
                raise DvpmvsError(
                    f"{mapping} names {len(outside)} frame(s) outside the trajectory {trajectory}, which has "
                    f"{len(submitted)} cameras (e.g. frame {outside[0]}; frames are numbered from 1): the trajectory "
                    f"is not the scene's video (or is cut short), or the mapping file is another scene's"
                )
            submitted = [submitted[f - 1] for f in frames]
        initial = align_trajectories(submitted, reference, np.loadtxt(scene.alignment))
    elif scene.alignment is not None:
        initial = np.loadtxt(scene.alignment)
    return evaluate_tanks(recon, gt, scene.threshold, initial, crop, refine)
