"""Per-view depth and normal map errors against ground-truth maps, with error images.

For each view with a ground-truth depth map: over the pixels where the ground truth has a depth,
the share estimated within 1 %, 2 % and 5 % of the true depth and within 2 cm (pixels without an
estimate count as failures: completeness), the share with an estimate at all, the mean absolute
depth error over estimated pixels, and the mean and median angle between estimated and true
normals. Over the estimated pixels, the RGB-D literature's depth errors (Eigen et al.): AbsRel
(mean |d - d*| / d*), SqRel (mean (d - d*)^2 / d*), RMSE, and the shares with
max(d / d*, d* / d) below 1.05, 1.10 and 1.25 (δ). :func:`pooled_depth_metrics` gives them over
all views, pooled by pixel. With a
ground-truth highlight mask (a synthetic scene's ``ground_truth/highlights/<view>``), the share
within 1 % is also given inside the mask and outside it; with a ground-truth textureless mask
(``ground_truth/textureless/<view>``: surfaces of uniform albedo), on the plain surfaces and on
the textured ones.

:func:`sky_point_share`: the share of a cloud's points that lie where a view sees open sky (no
surface along its ray, so no point can be there): false surfaces in a plain region with nothing
in it.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from dvpmvs.errors import DvpmvsError
from dvpmvs.maps import read_depth_map, read_normal_map
from dvpmvs.preview import write_png

__all__ = [
    "DepthMetrics",
    "depth_map_metrics",
    "evaluate_depth_maps",
    "error_image",
    "comparable_sizes",
    "pooled_depth_metrics",
    "pooled_highlight_shares",
    "pooled_textureless_shares",
    "sky_point_share",
]


@dataclass
class DepthMetrics:
    view: str
    valid_pixels: int  # pixels with a true depth
    estimated: float  # share of them with an estimate
    within_1_percent: float
    within_2_cm: float
    mean_abs_error: float  # over estimated pixels, in scene units
    within_2_percent: float = 0.0
    within_5_percent: float = 0.0
    abs_rel: float = float("nan")  # over estimated pixels, as the δ shares and SqRel, RMSE
    sq_rel: float = float("nan")
    rmse: float = float("nan")
    delta_1_05: float = float("nan")
    delta_1_10: float = float("nan")
    delta_1_25: float = float("nan")
    estimated_pixels: int = 0
    normal_mean_deg: float | None = None
    normal_median_deg: float | None = None
    highlight_pixels: int = 0  # pixels with a true depth in the ground-truth highlight mask
    highlight_within_1_percent: float | None = None  # share of them within 1 % (None: no mask)
    highlight_estimated: float | None = None  # share of them with an estimate
    outside_within_1_percent: float | None = None  # the same outside the mask
    textureless_pixels: int = 0  # pixels with a true depth on a surface of uniform albedo
    textureless_within_1_percent: float | None = None  # share of them within 1 % (None: no mask)
    textured_within_1_percent: float | None = None  # the same on the other surfaces

    def as_dict(self) -> dict:
        return asdict(self)


# The RGB-D errors over estimated pixels, and the completeness shares over pixels with truth.
_OVER_ESTIMATED = ("abs_rel", "sq_rel", "delta_1_05", "delta_1_10", "delta_1_25")
_OVER_TRUTH = (
    "estimated",
    "within_1_percent",
    "within_2_percent",
    "within_5_percent",
    "within_2_cm",
)


def pooled_depth_metrics(views: list[DepthMetrics]) -> dict[str, float | None]:
    """Over all views, pooled by pixel: each error over all estimated pixels (RMSE the root of
    the pooled mean square), each completeness share over all pixels with a true depth."""
    estimated = sum(v.estimated_pixels for v in views)
    truth = sum(v.valid_pixels for v in views)
    pooled: dict[str, float | None] = {
        key: sum(getattr(v, key) * v.valid_pixels for v in views) / truth if truth else None
        for key in _OVER_TRUTH
    }
    with_estimate = [v for v in views if v.estimated_pixels]
    for key in _OVER_ESTIMATED:
        pooled[key] = (
            sum(getattr(v, key) * v.estimated_pixels for v in with_estimate) / estimated
            if estimated
            else None
        )
    pooled["rmse"] = (
        float(np.sqrt(sum(v.rmse**2 * v.estimated_pixels for v in with_estimate) / estimated))
        if estimated
        else None
    )
    return pooled


def pooled_highlight_shares(views: list[DepthMetrics]) -> dict[str, float | None]:
    """Over views, the share within 1 % inside the highlight masks and outside, pooled by pixel
    (a view with a small highlight weighs little); None where no view has a mask."""
    with_mask = [v for v in views if v.highlight_within_1_percent is not None]
    inside = sum(v.highlight_pixels for v in with_mask)
    outside = sum(v.valid_pixels - v.highlight_pixels for v in with_mask)
    return {
        "highlight_within_1_percent": sum(
            v.highlight_within_1_percent * v.highlight_pixels for v in with_mask
        )
        / inside
        if inside
        else None,
        "highlight_estimated": sum(v.highlight_estimated * v.highlight_pixels for v in with_mask)
        / inside
        if inside
        else None,
        "outside_within_1_percent": sum(
            v.outside_within_1_percent * (v.valid_pixels - v.highlight_pixels) for v in with_mask
        )
        / outside
        if outside
        else None,
        "highlight_pixels": inside,
    }


def pooled_textureless_shares(views: list[DepthMetrics]) -> dict[str, float | None]:
    """Over views, the share within 1 % on the plain (uniform albedo) surfaces and on the
    textured ones, pooled by pixel; None where no view has a mask."""
    with_mask = [v for v in views if v.textureless_within_1_percent is not None]
    plain = sum(v.textureless_pixels for v in with_mask)
    textured = sum(v.valid_pixels - v.textureless_pixels for v in with_mask)
    return {
        "textureless_within_1_percent": sum(
            v.textureless_within_1_percent * v.textureless_pixels for v in with_mask
        )
        / plain
        if plain
        else None,
        "textured_within_1_percent": sum(
            v.textured_within_1_percent * (v.valid_pixels - v.textureless_pixels) for v in with_mask
        )
        / textured
        if textured
        else None,
        "textureless_pixels": plain,
    }


def comparable_sizes(map_size: tuple[int, int], truth_size: tuple[int, int]) -> bool:
    """A map of ``map_size`` (height, width) is scored against ground truth of ``truth_size``:
    the same size, or the same image at a lower resolution (``max_image_size``, a preset's half
    size) whose sides round to the truth's aspect ratio."""
    (h, w), (th, tw) = map_size, truth_size
    return (h, w) == (th, tw) or (w <= tw and abs(h * tw / w - th) <= tw / w)


def _at_truth_size(view: str, depth: np.ndarray, truth_shape: tuple[int, ...]) -> np.ndarray:
    """The map at the ground truth's resolution: a smaller map's pixel stands for each sensor
    pixel it covers (nearest neighbour, no depth blended across an edge), as RGB-D benchmarks
    score a network's lower-resolution output."""
    import cv2

    if depth.shape[:2] == truth_shape[:2]:
        return depth
    if not comparable_sizes(depth.shape[:2], truth_shape[:2]):
        raise DvpmvsError(
            f"{view}: the depth map is {depth.shape[1::-1]} but the ground truth is "
            f"{truth_shape[1::-1]}, another aspect ratio; evaluate maps of the ground truth's images"
        )
    return cv2.resize(depth, truth_shape[1::-1], interpolation=cv2.INTER_NEAREST)


def depth_map_metrics(
    view: str,
    depth: np.ndarray,
    truth: np.ndarray,
    normal: np.ndarray | None = None,
    true_normal: np.ndarray | None = None,
    abs_tolerance: float = 0.02,
    rel_tolerance: float = 0.01,
    highlight: np.ndarray | None = None,
    textureless: np.ndarray | None = None,
) -> DepthMetrics:
    if depth.shape != truth.shape:
        raise DvpmvsError(
            f"{view}: the depth map is {depth.shape[::-1]} but the ground truth is {truth.shape[::-1]}; "
            "evaluate at the ground truth's resolution"
        )
    valid = truth > 0
    n = int(valid.sum())
    if n == 0:
        raise DvpmvsError(f"{view}: the ground-truth depth map has no valid pixel")
    est = valid & (depth > 0)
    err = np.abs(depth - truth)
    metrics = DepthMetrics(
        view=view,
        valid_pixels=n,
        estimated=float(est.sum() / n),
        within_1_percent=float(np.sum(est & (err <= rel_tolerance * truth)) / n),
        within_2_cm=float(np.sum(est & (err <= abs_tolerance)) / n),
        mean_abs_error=float(err[est].mean()) if est.any() else float("nan"),
    )
    metrics.within_2_percent = float(np.sum(est & (err <= 0.02 * truth)) / n)
    metrics.within_5_percent = float(np.sum(est & (err <= 0.05 * truth)) / n)
    metrics.estimated_pixels = int(est.sum())
    if est.any():
        d, t = depth[est].astype(np.float64), truth[est].astype(np.float64)
        ratio = np.maximum(d / t, t / d)
        metrics.abs_rel = float(np.mean(np.abs(d - t) / t))
        metrics.sq_rel = float(np.mean((d - t) ** 2 / t))
        metrics.rmse = float(np.sqrt(np.mean((d - t) ** 2)))
        metrics.delta_1_05 = float(np.mean(ratio < 1.05))
        metrics.delta_1_10 = float(np.mean(ratio < 1.10))
        metrics.delta_1_25 = float(np.mean(ratio < 1.25))
    good = est & (err <= rel_tolerance * truth)
    share = lambda mask: float(good[mask].mean()) if mask.any() else 0.0  # noqa: E731
    if highlight is not None:
        inside, outside = _split(view, "highlight", highlight, valid)
        metrics.highlight_pixels = int(inside.sum())
        metrics.highlight_within_1_percent = share(inside)
        metrics.highlight_estimated = float(est[inside].mean()) if inside.any() else 0.0
        metrics.outside_within_1_percent = share(outside)
    if textureless is not None:
        plain, textured = _split(view, "textureless", textureless, valid)
        metrics.textureless_pixels = int(plain.sum())
        metrics.textureless_within_1_percent = share(plain)
        metrics.textured_within_1_percent = share(textured)
    if normal is not None and true_normal is not None:
        has = est & np.any(normal != 0, axis=-1)
        if has.any():
            cos = np.clip(np.sum(normal[has] * true_normal[has], axis=-1), -1, 1)
            angles = np.degrees(np.arccos(cos))
            metrics.normal_mean_deg = float(angles.mean())
            metrics.normal_median_deg = float(np.median(angles))
    return metrics


def _split(
    view: str, what: str, mask: np.ndarray, valid: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The pixels with ground truth inside a ground-truth ``mask`` and outside it."""
    if mask.shape != valid.shape:
        raise DvpmvsError(
            f"{view}: the {what} mask is {mask.shape[::-1]} but the ground truth is {valid.shape[::-1]}"
        )
    return valid & mask, valid & ~mask


def error_image(depth: np.ndarray, truth: np.ndarray, rel_tolerance: float = 0.01) -> np.ndarray:
    """BGR image of the relative depth error: green within the tolerance, through yellow to red at
    5x the tolerance and beyond; blue where an estimate is missing; black without ground truth."""
    valid = truth > 0
    rel = np.abs(depth - truth) / np.where(valid, truth, 1)
    t = np.clip((rel / rel_tolerance - 1) / 4, 0, 1)  # 0 at the tolerance, 1 at 5x
    bgr = np.zeros((*truth.shape, 3), np.uint8)
    bgr[..., 1] = np.round(255 * np.clip(2 - 2 * t, 0, 1))
    bgr[..., 2] = np.round(255 * np.clip(2 * t, 0, 1))
    bgr[rel <= rel_tolerance] = (0, 200, 0)
    bgr[valid & (depth <= 0)] = (255, 0, 0)
    bgr[~valid] = 0
    return bgr


def evaluate_depth_maps(
    depth_dir: str | Path,
    truth_dir: str | Path,
    suffix: str = ".geometric.bin",
    error_dir: str | Path | None = None,
) -> list[DepthMetrics]:
    """Score every ``<view><suffix>`` in ``depth_dir`` against ``truth_dir/<view>.bin``, at the
    ground truth's resolution (a smaller map of the same images is enlarged to it).

    ``depth_dir`` is a workspace's ``stereo/depth_maps``; normals are read from the sibling
    ``normal_maps`` folders when both exist, highlight masks from ``truth_dir/../highlights/<view>``
    when there. Error images go to ``error_dir/<view>.error.png``.
    """
    import cv2

    depth_dir, truth_dir = Path(depth_dir), Path(truth_dir)
    if not truth_dir.is_dir():
        raise DvpmvsError(f"ground-truth depth folder {truth_dir} does not exist")
    estimates = sorted(depth_dir.glob(f"*{suffix}"))
    if not estimates:
        raise DvpmvsError(f"no depth maps named *{suffix} in {depth_dir}")
    results = []
    for path in estimates:
        view = path.name.removesuffix(suffix)
        truth_path = truth_dir / f"{view}.bin"
        if not truth_path.is_file():
            raise DvpmvsError(f"no ground truth for {view}: {truth_path} does not exist")
        truth = read_depth_map(truth_path)
        depth = _at_truth_size(view, read_depth_map(path), truth.shape)
        normal = true_normal = None
        normal_path = depth_dir.parent / "normal_maps" / path.name
        true_normal_path = truth_dir.parent / "normal_maps" / truth_path.name
        if normal_path.is_file() and true_normal_path.is_file():
            normal = _at_truth_size(view, read_normal_map(normal_path), truth.shape)
            true_normal = read_normal_map(true_normal_path)
        masks = {}
        for kind in ("highlights", "textureless"):
            mask_path = truth_dir.parent / kind / view
            if mask_path.is_file():
                mask = cv2.imread(str(mask_path), cv2.IMREAD_GRAYSCALE)
                if mask is None:
                    raise DvpmvsError(f"cannot read the {kind} mask {mask_path}")
                masks[kind] = mask > 127
        results.append(
            depth_map_metrics(
                view,
                depth,
                truth,
                normal,
                true_normal,
                highlight=masks.get("highlights"),
                textureless=masks.get("textureless"),
            )
        )
        if error_dir is not None:
            write_png(Path(error_dir) / f"{Path(view).stem}.error.png", error_image(depth, truth))
    return results


def sky_point_share(
    points: np.ndarray,
    cameras: list[tuple[np.ndarray, np.ndarray, np.ndarray]],
    truths: list[np.ndarray],
    margin: int = 2,
) -> float:
    """The share of ``points`` (N, 3), world frame, that lie in open sky: in front of some view
    (``cameras``: its K, R, t; ``truths``: its ground-truth depth, 0 where the ray escapes) and
    projecting into its sky, more than ``margin`` pixels from any surface. Nothing lies along a
    sky pixel's ray, so such a point is a false surface. 0 for an empty cloud."""
    import cv2

    points = np.asarray(points, np.float64).reshape(-1, 3)
    if not len(points):
        return 0.0
    in_sky = np.zeros(len(points), bool)
    kernel = np.ones((2 * margin + 1, 2 * margin + 1), np.uint8)
    for (K, R, t), truth in zip(cameras, truths):
        sky = cv2.erode((truth <= 0).astype(np.uint8), kernel) > 0
        if not sky.any():
            continue
        camera = points @ R.T + t
        front = camera[:, 2] > 0
        pixel = camera[front] @ np.asarray(K).T
        col = np.round(pixel[:, 0] / pixel[:, 2]).astype(np.int64)
        row = np.round(pixel[:, 1] / pixel[:, 2]).astype(np.int64)
        h, w = truth.shape
        inside = (col >= 0) & (col < w) & (row >= 0) & (row < h)
        hit = np.zeros(len(col), bool)
        hit[inside] = sky[row[inside], col[inside]]
        in_sky[np.flatnonzero(front)[hit]] = True
    return float(in_sky.mean())
