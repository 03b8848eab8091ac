"""Weight-free depth priors: ``coarse_mvs`` (the estimator at low resolution), ``sparse`` (the
sparse points interpolated over the image) and ``file`` (per-view arrays from a folder).

A provider is called as ``provider(ctx)`` with a :class:`dvpmvs.priors.PriorContext` and returns a
:class:`dvpmvs.priors.DepthPrior` at the view's size.
"""

from __future__ import annotations

import logging
from pathlib import Path

import cv2
import numpy as np

from dvpmvs.priors import DepthPrior, PriorError, fit_prior_to_view, read_prior_array

__all__ = [
    "CoarseMvsDepth",
    "SparseDepth",
    "FileDepth",
    "find_prior_file",
    "fill_holes",
    "make_coarse_mvs",
    "make_sparse",
    "make_file",
]

log = logging.getLogger(__name__)

PRIOR_SUFFIXES = (".npy", ".pfm", ".bin")


def fill_holes(depth: np.ndarray) -> np.ndarray:
    """Depth with its zero pixels filled from the nearest valid ones (OpenCV's Telea inpainting on
    log depth, so that the fill follows relative, not absolute, differences)."""
    valid = depth > 0
    if valid.all():
        return depth.astype(np.float32)
    if not valid.any():
        raise PriorError("the depth map has no valid pixel to fill from")
    log_depth = np.where(valid, np.log(np.where(valid, depth, 1.0)), 0).astype(np.float32)
    filled = cv2.inpaint(log_depth, (~valid).astype(np.uint8), 3, cv2.INPAINT_TELEA)
    return np.exp(filled).astype(np.float32)


class CoarseMvsDepth:
    """The estimator's photometric pass on images downscaled to ``max_size`` (longer side, at
    resolution level 0: with a ``resolution_level`` the prior shrinks with the images), with
    ``num_scales`` pyramid levels, filtered (cost under ``max_cost``), hole-filled and median-filtered
    (``median_size`` pixels at the low resolution, 0 = none), then resized to the view's size.
    Metric: the sparse model's scale.

    Why the median: at low resolution a textureless wall's shading ramp is matched by wrong planes
    at low cost, leaving isolated far-off pixels that split the wall into many regions in the
    segmentation. On 9 views of the 400x300 suite the 5-pixel median raised the share of prior
    pixels within 5 % of the true depth by about a tenth of the pixels, and a second pyramid level
    a little more, for a fraction of a second per view."""

    def __init__(
        self,
        max_size: int = 200,
        num_scales: int = 2,
        num_iterations: int = 3,
        max_cost: float = 0.6,
        max_sources: int = 6,
        median_size: int = 5,
    ):
        if max_size < 32:
            raise ValueError(f"max_size must be >= 32, got {max_size}")
        if not 0 < max_cost <= 2:
            raise ValueError(f"max_cost must be in (0, 2], got {max_cost}")
        if median_size < 0:
            raise ValueError(f"median_size must be >= 0, got {median_size}")
        self.max_size, self.num_scales, self.num_iterations = (
            int(max_size),
            int(num_scales),
            int(num_iterations),
        )
        self.max_cost, self.max_sources, self.median_size = (
            float(max_cost),
            int(max_sources),
            int(median_size),
        )

    def __call__(self, ctx) -> DepthPrior:
        if ctx.low_resolution_depth is None:
            raise PriorError(
                "the coarse_mvs depth prior needs the view's source images, which this context "
                "does not offer (no low_resolution_depth)"
            )
        h, w = ctx.shape
        depth = ctx.low_resolution_depth(
            max_size=self.max_size,
            num_scales=self.num_scales,
            num_iterations=self.num_iterations,
            max_cost=self.max_cost,
            max_sources=self.max_sources,
        )
        if (depth > 0).sum() < 3:
            # Nothing reliable at low resolution (a tiny or textureless view): the sparse points
            # are the other weight-free source of depth.
            log.warning(
                "coarse_mvs found no reliable depth in view %s; using its sparse points instead",
                ctx.name,
            )
            return SparseDepth(min_points=3)(ctx)
        filled = fill_holes(depth)
        if self.median_size > 1:
            # scipy's modules are imported where they are used: a command that stops at its checks
            # (or `--help`) loads the providers but never runs them.
            from scipy.ndimage import median_filter

            filled = median_filter(filled, self.median_size, mode="nearest")
        depth = cv2.resize(filled, (w, h), interpolation=cv2.INTER_LINEAR)
        return DepthPrior(depth=depth, valid=depth > 0, metric=True)


class SparseDepth:
    """The view's sparse points, linearly interpolated over their convex hull (Delaunay) and
    nearest-filled outside it. Metric."""

    def __init__(self, min_points: int = 10):
        self.min_points = int(min_points)

    def __call__(self, ctx) -> DepthPrior:
        points = np.asarray(ctx.sparse, np.float64)
        if points.shape[0] < self.min_points:
            raise PriorError(
                f"view {ctx.name} observes {points.shape[0]} sparse points; the sparse depth prior "
                f"needs {self.min_points}"
            )
        h, w = ctx.shape
        xy, z = points[:, :2], points[:, 2]
        rows, cols = np.mgrid[0:h, 0:w]
        query = np.stack([cols.ravel(), rows.ravel()], axis=1).astype(np.float64)
        from scipy.interpolate import (  # see CoarseMvsDepth
            LinearNDInterpolator,
            NearestNDInterpolator,
        )

        depth = LinearNDInterpolator(xy, z)(query)
        outside = ~np.isfinite(depth)
        if outside.any():
            depth[outside] = NearestNDInterpolator(xy, z)(query[outside])
        return DepthPrior(depth=depth.reshape(h, w).astype(np.float32), metric=True)


def find_prior_file(
    folder: Path, name: str, suffixes: tuple[str, ...] = PRIOR_SUFFIXES, what: str = "prior"
) -> Path:
    """``folder/<image name><suffix>`` or ``folder/<image stem><suffix>``, the first of
    ``suffixes`` (by default .npy, .pfm, .bin; "" for the name as it is) that exists."""
    stem = Path(name).stem
    for base in (name, stem):
        for suffix in suffixes:
            candidate = folder / f"{base}{suffix}"
            if candidate.is_file():
                return candidate
    tried = "/".join(suffix or "(as is)" for suffix in suffixes)
    raise PriorError(
        f"no {what} for image {name} in {folder} (looked for {name}{tried} and {stem}{tried})"
    )


def resolve_folder(path, root, what: str) -> Path:
    if path in (None, ""):
        raise PriorError(f"the file {what} needs a folder: set {what}.path=DIR")
    folder = Path(path).expanduser()
    if not folder.is_absolute() and root is not None:
        folder = Path(root) / folder
    if not folder.is_dir():
        raise PriorError(f"{what}.path: folder not found: {folder}")
    return folder


class FileDepth:
    """Per-view depth priors read from ``path`` (relative to the workspace). ``kind``: ``depth``
    or ``inverse_depth``; ``metric``: False aligns the prior to the sparse points (scale and
    shift). Values <= 0 are invalid; NaN is an error. A prior of the image at another size is
    resized; another aspect ratio is an error unless ``resize`` (see ``fit_prior_to_view``)."""

    def __init__(
        self,
        path: str | None = None,
        metric: bool = False,
        kind: str = "depth",
        resize: bool = False,
    ):
        if kind not in ("depth", "inverse_depth"):
            raise ValueError(f"kind must be depth or inverse_depth, got {kind!r}")
        for key, value in (("metric", metric), ("resize", resize)):
            if not isinstance(value, bool):
                raise ValueError(f"{key} must be true or false, got {value!r}")
        self.path, self.metric, self.kind, self.resize = path, metric, kind, resize

    def input_files(self, name: str, root=None) -> list[Path]:
        """The prior file of view ``name`` (its content joins the maps' provenance)."""
        return [find_prior_file(resolve_folder(self.path, root, "depth_prior"), name)]

    def __call__(self, ctx) -> DepthPrior:
        folder = resolve_folder(self.path, ctx.root, "depth_prior")
        file = find_prior_file(folder, ctx.name)
        array = read_prior_array(file)
        if array.ndim == 3 and array.shape[2] == 1:
            array = array[..., 0]
        if array.ndim != 2:
            raise PriorError(f"{file}: a depth prior is (H, W), got shape {array.shape}")
        if not np.isfinite(array).all():
            raise PriorError(f"{file}: {int((~np.isfinite(array)).sum())} NaN or infinite value(s)")
        array = fit_prior_to_view(array, ctx.shape, file, self.resize)
        # Zero or negative is "no value" in either kind; a relative inverse depth is aligned in
        # inverse depth by the core (its unknown shift is a shift of disparity, not of depth).
        valid = array > 0
        return DepthPrior(
            depth=array.astype(np.float32),
            valid=valid,
            metric=self.metric,
            inverse=self.kind == "inverse_depth",
        )


def make_coarse_mvs(params: dict) -> CoarseMvsDepth:
    return CoarseMvsDepth(**params)


def make_sparse(params: dict) -> SparseDepth:
    return SparseDepth(**params)


def make_file(params: dict) -> FileDepth:
    return FileDepth(**params)
