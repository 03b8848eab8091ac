"""The ETH3D multi-view metric: accuracy, completeness and F1 per tolerance.

This follows the official ETH3D multi-view evaluation program (github.com/ETH3D/
multi-view-evaluation, ``accuracy.cc`` and ``completeness.cc``), so that scores agree with the
leaderboard's:

- **Completeness**: a ground-truth scan point is complete for a tolerance if a reconstruction
  point lies within it.
- **Accuracy**: a reconstruction point is classified against the laser beams of each scan (see
  ``_accuracy.pyx``): accurate, inaccurate, or unobserved (in space no scan observed, ignored).
  It is accurate if any scan says so, else inaccurate if any scan says so, else unobserved.
- **Voxel normalisation**: both scores are averaged per voxel (default 1 cm) rather than per
  point, over two voxel grids shifted by half a voxel against each other, so that densely
  sampled areas do not dominate.
- **F1** is the harmonic mean of accuracy and completeness (0 if both are 0).

The official program's parameters are kept: voxel size 0.01 m, beam start radius 1.125 mm,
beam divergence half-angle 0.011 degrees. Ground truth given as a plain point cloud (no scans,
so no beams) is scored without the unobserved-space rule: every reconstruction point is
observed, accurate if a ground-truth point lies within the tolerance.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from dvpmvs._kernel_sources import require_current
from dvpmvs.errors import DvpmvsError
from dvpmvs.evaluation import _accuracy
from dvpmvs.evaluation._accuracy import classify
from dvpmvs.evaluation.pointclouds import Scan

require_current(_accuracy)

log = logging.getLogger(__name__)

__all__ = [
    "ETH3DParameters",
    "ETH3DResult",
    "UNOBSERVED",
    "ACCURATE",
    "INACCURATE",
    "evaluate_eth3d",
    "f_score",
    "completeness",
    "accuracy",
    "check_same_frame",
]

# Extents (robust diagonals) further apart than this are an error, beyond the first a warning:
# a cloud in millimetres against ground truth in metres is 1000x; a partial reconstruction of a
# scanned scene is a few times smaller, not fifty.
_EXTENT_WARNING, _EXTENT_ERROR = 10.0, 50.0

# Per-point accuracy labels.
UNOBSERVED, ACCURATE, INACCURATE = 0, 1, 2

# The official program's spherical bucket grid (only affects speed, not results).
_CELLS_INCLINATION = 1024
_CELLS_AZIMUTH = 2 * _CELLS_INCLINATION
_GRID_SHIFTS = (0.0, 0.5)


@dataclass(frozen=True)
class ETH3DParameters:
    """The official program's options, with its defaults."""

    voxel_size: float = 0.01
    beam_start_radius_meters: float = 0.5 * 0.00225
    beam_divergence_halfangle_deg: float = 0.011

    def __post_init__(self):
        if not self.voxel_size > 0:
            raise DvpmvsError(f"voxel_size must be positive, got {self.voxel_size}")
        if self.beam_start_radius_meters < 0 or self.beam_divergence_halfangle_deg < 0:
            raise DvpmvsError("the beam start radius and divergence angle must be non-negative")


@dataclass
class ETH3DResult:
    """Scores per tolerance (sorted increasing), and optional per-point labels."""

    tolerances: list[float]
    accuracy: list[float]
    completeness: list[float]
    f1: list[float] = field(init=False)
    # [tolerance][reconstruction point]: UNOBSERVED / ACCURATE / INACCURATE
    point_accuracy: np.ndarray | None = None
    # [tolerance][ground-truth point]: complete or not
    point_completeness: np.ndarray | None = None
    ground_truth_points: np.ndarray | None = None

    def __post_init__(self):
        self.f1 = [f_score(a, c) for a, c in zip(self.accuracy, self.completeness)]

    def at(self, tolerances) -> ETH3DResult:
        """The scores (and per-point labels) at some of this result's tolerances: an evaluation
        at several tolerances gives each the figures it gets alone, so one evaluation at their
        union serves several uses."""
        index = [self.tolerances.index(float(t)) for t in tolerances]
        labels = lambda a: None if a is None else a[index]  # noqa: E731
        return ETH3DResult(
            [self.tolerances[i] for i in index],
            [self.accuracy[i] for i in index],
            [self.completeness[i] for i in index],
            labels(self.point_accuracy),
            labels(self.point_completeness),
            self.ground_truth_points,
        )

    def as_dict(self) -> dict:
        return {
            "tolerances": [float(t) for t in self.tolerances],
            "accuracy": [float(v) for v in self.accuracy],
            "completeness": [float(v) for v in self.completeness],
            "f1": [float(v) for v in self.f1],
        }


def f_score(precision: float, recall: float) -> float:
    """The harmonic mean of precision (accuracy) and recall (completeness); 0 when both are 0."""
    if precision <= 0 and recall <= 0:
        return 0.0
    return float(2 * precision * recall / (precision + recall))


def _voxel_keys(points: np.ndarray, voxel_size: float, shift: float) -> np.ndarray:
    """Integer voxel of each point, packed into one int64 key (float32 as the official program)."""
    v = points.astype(np.float32) * np.float32(1.0 / np.float32(voxel_size)) + np.float32(shift)
    cells = np.floor(v).astype(np.int64)
    # 21 bits per axis: +-1e6 voxels, i.e. +-10 km at 1 cm voxels.
    if cells.size and (np.abs(cells).max() >= 1 << 20):
        raise DvpmvsError(
            "the point cloud spans more than 10,000 voxels from the origin; "
            "use a larger voxel_size or centre the coordinates"
        )
    cells += 1 << 20
    return (cells[:, 0] << 42) | (cells[:, 1] << 21) | cells[:, 2]


def _sorted_tolerances(tolerances) -> np.ndarray:
    tol = np.sort(np.asarray(list(tolerances), dtype=np.float32))
    if tol.size == 0 or np.any(~np.isfinite(tol)) or np.any(tol < 0):
        raise DvpmvsError(
            f"tolerances must be a non-empty list of non-negative numbers, got {list(tolerances)}"
        )
    return tol


def completeness(
    reconstruction: np.ndarray,
    ground_truth: np.ndarray,
    tolerances,
    voxel_size: float = 0.01,
    workers: int = -1,
) -> tuple[list[float], np.ndarray]:
    """Voxel-averaged share of ground-truth points within each tolerance of the reconstruction.

    Returns the scores and a ``[tolerance][ground-truth point]`` boolean array.
    """
    tol = _sorted_tolerances(tolerances)
    gt = np.asarray(ground_truth, np.float32).reshape(-1, 3)
    rec = np.asarray(reconstruction, np.float32).reshape(-1, 3)
    if len(rec) == 0:
        return [0.0] * len(tol), np.zeros((len(tol), len(gt)), bool)
    tree = cKDTree(rec.astype(np.float64))
    # A little beyond the largest tolerance; the comparison below is the official float32 one.
    bound = float(np.nextafter(tol[-1], np.float32(np.inf))) * (1 + 1e-6)
    dist, _ = tree.query(gt.astype(np.float64), k=1, distance_upper_bound=bound, workers=workers)
    dist2 = np.where(np.isfinite(dist), dist, np.inf).astype(np.float32) ** 2
    complete = dist2[None, :] <= (tol**2)[:, None]
    score_sum = np.zeros(len(tol))
    cell_count = 0
    for shift in _GRID_SHIFTS:
        _, inverse, counts = np.unique(
            _voxel_keys(gt, voxel_size, shift), return_inverse=True, return_counts=True
        )
        cell_count += len(counts)
        for t in range(len(tol)):
            hits = np.bincount(inverse, weights=complete[t], minlength=len(counts))
            score_sum[t] += np.sum(hits / counts)
    scores = [float(s / cell_count) if cell_count else 0.0 for s in score_sum]
    return scores, complete


def _scan_from_global(global_T_scan: np.ndarray) -> np.ndarray:
    """[R | T] (3, 4) float32 taking global points into the scan's frame, as the official program
    builds it from the MLP's float matrix: R the rotation's transpose, T = R (-t) summed in
    float32 left to right. A last-bit difference here decides a point at a tolerance's edge."""
    M = np.asarray(global_T_scan, np.float64).astype(np.float32)
    R = np.ascontiguousarray(M[:3, :3].T)
    minus_t = -M[:3, 3]
    T = (R[:, 0] * minus_t[0] + R[:, 1] * minus_t[1]) + R[:, 2] * minus_t[2]
    return np.ascontiguousarray(np.concatenate([R, T[:, None]], axis=1), np.float32)


def _bucket_scans(scans: list[Scan]):
    """Scan points sorted into spherical buckets, per scan, for the accuracy kernel."""
    n_cells = _CELLS_AZIMUTH * _CELLS_INCLINATION
    extent_az = np.float32(2 * np.pi / _CELLS_AZIMUTH)
    extent_inc = np.float32(np.pi / _CELLS_INCLINATION)
    points, dirs, radii, starts, transforms = [], [], [], [], []
    offset = 0
    for scan in scans:
        p = np.asarray(scan.points, np.float32).reshape(-1, 3)
        r = np.sqrt(np.sum(p * p, axis=1, dtype=np.float32))
        with np.errstate(invalid="ignore", divide="ignore"):
            d = np.where(r[:, None] > 0, p / r[:, None], 0).astype(np.float32)
            inc = np.arccos(np.clip(p[:, 2] / r, -1, 1)).astype(np.float32)
        inc = np.nan_to_num(inc)
        az = np.arctan2(p[:, 1], p[:, 0]).astype(np.float32)
        ia = np.mod(np.floor(az / extent_az).astype(np.int64), _CELLS_AZIMUTH)
        ii = np.clip(np.floor(inc / extent_inc).astype(np.int64), 0, _CELLS_INCLINATION - 1)
        cell = ia + _CELLS_AZIMUTH * ii
        order = np.argsort(cell, kind="stable")
        counts = np.bincount(cell, minlength=n_cells)
        start = np.zeros(n_cells + 1, np.int64)
        np.cumsum(counts, out=start[1:])
        points.append(p[order])
        dirs.append(d[order])
        radii.append(r[order])
        starts.append(start + offset)
        offset += len(p)
        transforms.append(_scan_from_global(scan.global_T_scan))
    return (
        np.ascontiguousarray(np.concatenate(points), np.float32),
        np.ascontiguousarray(np.concatenate(dirs), np.float32),
        np.ascontiguousarray(np.concatenate(radii), np.float32),
        np.ascontiguousarray(np.stack(starts), np.int64),
        np.ascontiguousarray(np.stack(transforms), np.float32),
    )


def _classify_against_points(
    reconstruction: np.ndarray, ground_truth: np.ndarray, tol: np.ndarray, workers: int = -1
) -> tuple[np.ndarray, np.ndarray]:
    """Plain point-cloud ground truth: every point observed, accurate by nearest distance."""
    n = len(reconstruction)
    if len(ground_truth) == 0:
        return np.full(n, len(tol), np.int32), np.ones(n, np.uint8)
    tree = cKDTree(np.asarray(ground_truth, np.float64))
    bound = float(tol[-1]) * (1 + 1e-6)
    dist, _ = tree.query(
        reconstruction.astype(np.float64), k=1, distance_upper_bound=bound, workers=workers
    )
    dist2 = np.where(np.isfinite(dist), dist, np.inf).astype(np.float32) ** 2
    # The first accurate tolerance is the number of tolerances the distance exceeds.
    first = np.sum(dist2[:, None] > (tol**2)[None, :], axis=1).astype(np.int32)
    return first, np.ones(n, np.uint8)


def accuracy(
    reconstruction: np.ndarray,
    ground_truth: list[Scan] | np.ndarray,
    tolerances,
    parameters: ETH3DParameters = ETH3DParameters(),
) -> tuple[list[float], np.ndarray]:
    """Voxel-averaged share of accurate among observed reconstruction points, per tolerance.

    Returns the scores and a ``[tolerance][point]`` array of UNOBSERVED / ACCURATE / INACCURATE.
    """
    tol = _sorted_tolerances(tolerances)
    rec = np.ascontiguousarray(np.asarray(reconstruction, np.float32).reshape(-1, 3))
    if isinstance(ground_truth, np.ndarray):
        first, inaccurate = _classify_against_points(rec, ground_truth, tol)
    else:
        points, dirs, radii, starts, transforms = _bucket_scans(ground_truth)
        tan_div = np.float32(
            np.tan(np.deg2rad(np.float32(parameters.beam_divergence_halfangle_deg)))
        )
        first, inaccurate = classify(
            rec,
            transforms,
            points,
            dirs,
            radii,
            starts,
            _CELLS_AZIMUTH,
            _CELLS_INCLINATION,
            np.ascontiguousarray(tol**2, np.float32),
            np.float32(parameters.beam_start_radius_meters),
            tan_div,
        )
    t_index = np.arange(len(tol))[:, None]
    labels = np.where(
        t_index >= first[None, :],
        ACCURATE,
        np.where(inaccurate[None, :] > 0, INACCURATE, UNOBSERVED),
    ).astype(np.uint8)
    score_sum = np.zeros(len(tol))
    valid_cells = np.zeros(len(tol), np.int64)
    for shift in _GRID_SHIFTS:
        _, inverse = np.unique(_voxel_keys(rec, parameters.voxel_size, shift), return_inverse=True)
        n_cells = int(inverse.max()) + 1 if len(inverse) else 0
        for t in range(len(tol)):
            accurate = np.bincount(inverse, weights=labels[t] == ACCURATE, minlength=n_cells)
            valid = np.bincount(inverse, weights=labels[t] != UNOBSERVED, minlength=n_cells)
            has = valid > 0
            score_sum[t] += np.sum(accurate[has] / valid[has])
            valid_cells[t] += int(np.count_nonzero(has))
    scores = [float(s / v) if v else 0.0 for s, v in zip(score_sum, valid_cells)]
    return scores, labels


def _robust_box(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The box between the 2nd and 98th percentiles of each coordinate (a few outliers, which
    every fused cloud has, do not stretch it)."""
    sample = points[:: max(1, len(points) // 200_000)]
    return np.percentile(sample, 2, axis=0), np.percentile(sample, 98, axis=0)


def check_same_frame(reconstruction: np.ndarray, ground_truth: np.ndarray) -> None:
    """A reconstruction and ground truth in different units or frames score 0 without a word:
    an error when their boxes do not overlap or their extents differ more than 50-fold, a
    warning beyond 10-fold, each naming both extents (robust: 2nd to 98th percentile)."""
    reconstruction = np.asarray(reconstruction, np.float64).reshape(-1, 3)
    if len(reconstruction) < 10:
        return
    lo_r, hi_r = _robust_box(reconstruction)
    lo_g, hi_g = _robust_box(np.asarray(ground_truth, np.float64).reshape(-1, 3))
    extent_r, extent_g = float(np.linalg.norm(hi_r - lo_r)), float(np.linalg.norm(hi_g - lo_g))
    describe = (
        f"the reconstruction spans {extent_r:.4g} (from {np.round(lo_r, 3).tolist()} to "
        f"{np.round(hi_r, 3).tolist()}), the ground truth {extent_g:.4g} (from {np.round(lo_g, 3).tolist()} to "
        f"{np.round(hi_g, 3).tolist()})"
    )
    ratio = max(extent_r, extent_g) / max(min(extent_r, extent_g), 1e-12)
    hint = (
        "are both in metres and in the same frame? Scale or align the reconstruction (a COLMAP model's "
        "`colmap model_aligner`), or give the matching ground truth"
    )
    # The margin: boxes of a reconstruction with few points may just miss the scanned surface.
    margin = 0.05 * max(extent_r, extent_g)
    if ratio >= _EXTENT_ERROR:
        raise DvpmvsError(
            f"the reconstruction and the ground truth differ {ratio:.0f}-fold in size (units?): "
            f"{describe}; {hint}"
        )
    if np.any(lo_r > hi_g + margin) or np.any(lo_g > hi_r + margin):
        raise DvpmvsError(
            f"the reconstruction and the ground truth do not overlap: {describe}; {hint}"
        )
    if ratio >= _EXTENT_WARNING:
        log.warning(
            "the reconstruction and the ground truth differ %.0f-fold in size: %s; the scores are "
            "likely meaningless unless the reconstruction covers only a part of the scene",
            ratio,
            describe,
        )


def evaluate_eth3d(
    reconstruction: np.ndarray,
    ground_truth: list[Scan] | np.ndarray,
    tolerances=(0.02, 0.1),
    parameters: ETH3DParameters = ETH3DParameters(),
    keep_point_results: bool = False,
) -> ETH3DResult:
    """Accuracy, completeness and F1 of ``reconstruction`` (N x 3) for each tolerance.

    ``ground_truth`` is a list of scans (from a MeshLab project, with the beam model) or an
    (M, 3) array of points (no unobserved-space rule).
    """
    tol = _sorted_tolerances(tolerances)
    if isinstance(ground_truth, np.ndarray):
        gt_points = np.asarray(ground_truth, np.float32).reshape(-1, 3)
    else:
        gt_points = (
            np.concatenate([s.global_points() for s in ground_truth])
            if ground_truth
            else np.zeros((0, 3), np.float32)
        )
    if len(gt_points) == 0:
        raise DvpmvsError("the ground truth has no points")
    check_same_frame(reconstruction, gt_points)
    comp, point_comp = completeness(reconstruction, gt_points, tol, parameters.voxel_size)
    acc, point_acc = accuracy(reconstruction, ground_truth, tol, parameters)
    result = ETH3DResult(sorted(float(t) for t in tolerances), acc, comp)
    if keep_point_results:
        result.point_accuracy = point_acc
        result.point_completeness = point_comp
        result.ground_truth_points = gt_points
    return result
