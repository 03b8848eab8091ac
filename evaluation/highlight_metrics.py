"""Highlight masks against ground truth: precision, recall and F1 per view and pooled.

Predicted masks are a run's ``stereo/highlights/<view>.mask.bin`` (:mod:`dvpmvs.highlight`);
ground truth is a synthetic scene's ``ground_truth/highlights/<view>`` (255: highlight; see
:mod:`dvpmvs.evaluation.synthetic`). Pixels are pooled over the views for the totals, so that a
view with a small highlight weighs little. Masks of a run at a reduced size (``max_image_size``)
are scored against the ground truth reduced to their size.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path

import cv2
import numpy as np

from dvpmvs.errors import DvpmvsError
from dvpmvs.maps import read_extra_map

__all__ = [
    "MaskMetrics",
    "mask_metrics",
    "truth_at_size",
    "evaluate_highlight_masks",
    "pooled_mask_metrics",
]


@dataclass
class MaskMetrics:
    view: str
    true_positive: int
    false_positive: int
    false_negative: int

    @property
    def precision(self) -> float | None:
        found = self.true_positive + self.false_positive
        return self.true_positive / found if found else None

    @property
    def recall(self) -> float | None:
        actual = self.true_positive + self.false_negative
        return self.true_positive / actual if actual else None

    @property
    def f1(self) -> float | None:
        p, r = self.precision, self.recall
        return (
            2 * p * r / (p + r) if p and r else (0.0 if p is not None and r is not None else None)
        )

    def as_dict(self) -> dict:
        return {**asdict(self), "precision": self.precision, "recall": self.recall, "f1": self.f1}


def mask_metrics(view: str, predicted: np.ndarray, truth: np.ndarray) -> MaskMetrics:
    """Pixel counts of a predicted (H, W) bool mask against the true one."""
    if predicted.shape != truth.shape:
        raise DvpmvsError(
            f"{view}: the highlight mask is {predicted.shape[::-1]} but its ground truth is "
            f"{truth.shape[::-1]}; evaluate at the ground truth's resolution"
        )
    predicted, truth = predicted.astype(bool), truth.astype(bool)
    return MaskMetrics(
        view,
        int(np.sum(predicted & truth)),
        int(np.sum(predicted & ~truth)),
        int(np.sum(~predicted & truth)),
    )


def truth_at_size(truth: np.ndarray, shape: tuple[int, int], view: str = "") -> np.ndarray:
    """The (H, W) bool ground-truth mask ``truth`` at the (h, w) ``shape`` of a run's masks: a
    pixel is a highlight where most of the true pixels it covers are (area resampling), as a
    reduced image averages them. The sizes must have one aspect ratio, up to the pixel that
    rounding a reduced size gives."""
    truth = truth.astype(bool)
    if truth.shape == tuple(shape):
        return truth
    (h, w), (th, tw) = shape, truth.shape
    if abs(w * th - h * tw) > max(th, tw):
        raise DvpmvsError(
            f"{view}: the highlight mask is {w}x{h} but its ground truth is {tw}x{th}, another "
            f"aspect ratio: were the masks computed on these images?"
        )
    return cv2.resize(truth.astype(np.float32), (w, h), interpolation=cv2.INTER_AREA) > 0.5


def pooled_mask_metrics(views: list[MaskMetrics]) -> MaskMetrics:
    return MaskMetrics(
        "all",
        sum(v.true_positive for v in views),
        sum(v.false_positive for v in views),
        sum(v.false_negative for v in views),
    )


def evaluate_highlight_masks(
    highlight_dir: str | Path, truth_dir: str | Path, which: str = "final"
) -> list[MaskMetrics]:
    """Score the masks in ``highlight_dir`` (a run's ``stereo/highlights``) against
    ``truth_dir/<view>`` (a synthetic scene's ``ground_truth/highlights``). ``which``:
    ``single`` the provider's masks (``<view>.mask.bin``), ``final`` the masks the final maps
    used (the multi-view refined ``<view>.geometric.mask.bin`` where there is one). Masks smaller
    than their ground truth (a run at ``max_image_size``) are scored against it at their size
    (:func:`truth_at_size`)."""
    if which not in ("single", "final"):
        raise DvpmvsError(f"which must be single or final, got {which!r}")
    highlight_dir, truth_dir = Path(highlight_dir), Path(truth_dir)
    if not truth_dir.is_dir():
        raise DvpmvsError(
            f"the ground-truth highlight folder {truth_dir} does not exist (scenes rendered by "
            f"`dvpmvs synth` have ground_truth/highlights/)"
        )
    predictions = sorted(
        p for p in highlight_dir.glob("*.mask.bin") if not p.name.endswith(".geometric.mask.bin")
    )
    if not predictions:
        raise DvpmvsError(
            f"no highlight masks (*.mask.bin) in {highlight_dir}: run `dvpmvs dense` with a "
            f"highlight= corrector other than none"
        )
    results = []
    for path in predictions:
        view = path.name.removesuffix(".mask.bin")
        refined = path.with_name(f"{view}.geometric.mask.bin")
        if which == "final" and refined.is_file():
            path = refined
        truth_path = truth_dir / view
        truth = cv2.imread(str(truth_path), cv2.IMREAD_GRAYSCALE)
        if truth is None:
            raise DvpmvsError(f"no readable ground-truth highlight mask for {view}: {truth_path}")
        predicted = read_extra_map(path) > 0.5
        results.append(
            mask_metrics(view, predicted, truth_at_size(truth > 127, predicted.shape, view))
        )
    return results
