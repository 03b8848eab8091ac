"""The estimator's contract (COLMAP's MVSEstimator shape): a Problem and a Pass go in, a Result
comes out. Camera conventions are the workspace's: a world point X is seen at K (R X + t), the
array index [row, col] is the image point (col, row), depth is camera z."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["ViewData", "Problem", "Result", "LevelWork", "pooled_work"]


@dataclass
class ViewData:
    """One view as the estimator sees it: grey image in [0, 1], calibration and pose, and (in the
    geometric pass) its depth map from the previous pass at the image's size, 0 where unknown,
    and where the visibility restoration needs it, that pass's cost map (infinite where unknown).
    With highlight perception (paper section 3.5): ``corrected``, the grey image to match instead
    of ``image`` (the highlight corrector's), and ``highlight``, the (H, W) bool highlight mask."""

    name: str
    image: np.ndarray  # (H, W) float32
    K: np.ndarray  # (3, 3)
    R: np.ndarray  # (3, 3) world -> camera
    t: np.ndarray  # (3,)
    depth: np.ndarray | None = None
    cost: np.ndarray | None = None
    corrected: np.ndarray | None = None
    highlight: np.ndarray | None = None

    def __post_init__(self):
        self.image = np.ascontiguousarray(self.image, dtype=np.float32)
        if self.image.ndim != 2 or min(self.image.shape) < 2:
            raise ValueError(
                f"view {self.name}: expected a grey (H, W) image, got shape {self.image.shape}"
            )
        if not np.isfinite(self.image).all():
            raise ValueError(f"view {self.name}: the image holds NaN or infinite values")
        self.K = np.asarray(self.K, np.float64).reshape(3, 3)
        self.R = np.asarray(self.R, np.float64).reshape(3, 3)
        self.t = np.asarray(self.t, np.float64).reshape(3)
        if self.depth is not None:
            self.depth = np.ascontiguousarray(self.depth, dtype=np.float32)
            if self.depth.shape != self.image.shape:
                raise ValueError(
                    f"view {self.name}: depth map {self.depth.shape} does not match the image "
                    f"{self.image.shape}"
                )
            self.depth = np.where(np.isfinite(self.depth) & (self.depth > 0), self.depth, 0).astype(
                np.float32
            )
        if self.cost is not None:
            self.cost = np.asarray(self.cost, dtype=np.float32)
            if self.cost.shape != self.image.shape:
                raise ValueError(
                    f"view {self.name}: cost map {self.cost.shape} does not match the image "
                    f"{self.image.shape}"
                )
            self.cost = np.where(np.isfinite(self.cost), self.cost, np.inf).astype(np.float32)
        if self.corrected is not None:
            self.corrected = np.ascontiguousarray(self.corrected, dtype=np.float32)
            if self.corrected.shape != self.image.shape or not np.isfinite(self.corrected).all():
                raise ValueError(
                    f"view {self.name}: the corrected image {self.corrected.shape} must match the image "
                    f"{self.image.shape} and be finite"
                )
        if self.highlight is not None:
            self.highlight = np.ascontiguousarray(self.highlight, dtype=bool)
            if self.highlight.shape != self.image.shape:
                raise ValueError(
                    f"view {self.name}: the highlight mask {self.highlight.shape} does not match the "
                    f"image {self.image.shape}"
                )

    @property
    def shape(self) -> tuple[int, int]:
        return self.image.shape  # type: ignore[return-value]


@dataclass
class Problem:
    """A reference view, its source views (best first), the reference's depth range, an optional
    starting estimate (depth (H, W), camera-frame normals (H, W, 3)) for the pass, optional
    region labels (H, W) int32 of the depth-normal-edge aligned prior (0: boundary) that keep
    deformable PatchMatch's anchors inside the pixel's region (None: anchors go anywhere), and
    optionally the sparse points the reference observes ((N, 3) world), whose planes seed the
    photometric pass (``PatchMatchOptions.sparse_seed``). ``mask`` (H, W) bool: the pixels kept
    (:mod:`dvpmvs.masks`); a masked pixel is never estimated (None: every pixel is)."""

    reference: ViewData
    sources: list[ViewData]
    depth_range: tuple[float, float]
    initial: tuple[np.ndarray, np.ndarray] | None = None
    labels: np.ndarray | None = None
    sparse_points: np.ndarray | None = None
    mask: np.ndarray | None = None

    def __post_init__(self):
        if not self.sources:
            raise ValueError(f"view {self.reference.name} has no source views")
        lo, hi = (float(v) for v in self.depth_range)
        if not (np.isfinite(lo) and np.isfinite(hi) and 0 < lo < hi):
            raise ValueError(f"view {self.reference.name}: invalid depth range {self.depth_range}")
        self.depth_range = (lo, hi)
        if self.initial is not None:
            depth, normal = self.initial
            h, w = self.reference.shape
            if depth.shape != (h, w) or normal.shape != (h, w, 3):
                raise ValueError(
                    f"view {self.reference.name}: the initial maps {depth.shape}/{normal.shape} do "
                    f"not match the image {(h, w)}"
                )
        if self.labels is not None:
            self.labels = np.ascontiguousarray(self.labels, dtype=np.int32)
            if self.labels.shape != self.reference.shape:
                raise ValueError(
                    f"view {self.reference.name}: the region labels {self.labels.shape} do not match "
                    f"the image {self.reference.shape}"
                )
        if self.mask is not None:
            self.mask = np.asarray(self.mask, dtype=bool)
            if self.mask.shape != self.reference.shape:
                raise ValueError(
                    f"view {self.reference.name}: the mask {self.mask.shape} does not match the image "
                    f"{self.reference.shape}"
                )
        if self.sparse_points is not None:
            self.sparse_points = np.asarray(self.sparse_points, dtype=np.float64)
            if self.sparse_points.ndim != 2 or self.sparse_points.shape[1] != 3:
                raise ValueError(
                    f"view {self.reference.name}: sparse points must be (N, 3) world points, got "
                    f"{self.sparse_points.shape}"
                )
            self.sparse_points = self.sparse_points[np.isfinite(self.sparse_points).all(axis=1)]


_WORK_COUNTS = ("hypotheses", "windows", "samples")


@dataclass(frozen=True)
class LevelWork:
    """What the estimator matched at one pyramid level of one pass: plane hypotheses scored (a
    scoring against any number of sources counts once), windows matched (hypothesis x source x
    window; a deformed pixel's anchors' windows each count) and the image samples those windows
    read, over ``width`` x ``height`` pixels."""

    level: int
    width: int
    height: int
    hypotheses: int
    windows: int
    samples: int

    def per_pixel(self) -> dict[str, float]:
        pixels = max(self.width * self.height, 1)
        return {
            "hypotheses": self.hypotheses / pixels,
            "windows": self.windows / pixels,
            "samples": self.samples / pixels,
        }


def pooled_work(levels) -> list[dict]:
    """Per pyramid level, in order, what the estimator matched per pixel of that level over
    several views' work (``LevelWork`` as dicts): ``{"level", "size", "hypotheses", "windows",
    "samples"}``, the size being the first view's."""
    totals: dict[int, dict] = {}
    for level in levels:
        total = totals.setdefault(
            level["level"],
            {
                "size": [level["width"], level["height"]],
                "pixels": 0,
                "hypotheses": 0,
                "windows": 0,
                "samples": 0,
            },
        )
        total["pixels"] += level["width"] * level["height"]
        for key in _WORK_COUNTS:
            total[key] += level[key]
    return [
        {
            "level": index,
            "size": total["size"],
            **{key: total[key] / max(total["pixels"], 1) for key in _WORK_COUNTS},
        }
        for index, total in sorted(totals.items())
    ]


@dataclass
class Result:
    """depth (H, W), 0 where filtered out; normal (H, W, 3) camera frame; cost (H, W) the final
    weighted matching cost; visibility (H, W, S) the view-selection weights per source, in the
    order of ``sources``."""

    depth: np.ndarray
    normal: np.ndarray
    cost: np.ndarray
    visibility: np.ndarray
    sources: list[str] = field(default_factory=list)
    seconds: float = 0.0
    # windows matched (hypotheses x sources x windows), for the benchmark
    hypothesis_evaluations: int = 0
    work: list[LevelWork] = field(default_factory=list)  # per pyramid level, coarse to fine
    deformed: np.ndarray | None = None  # (H, W) bool: pixels matched with deformed patches
