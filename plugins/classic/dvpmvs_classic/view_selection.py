"""View selectors: rank the source views of a reference view from the sparse model.

A selector is called as ``selector(workspace, reference_name, max_sources)`` and returns
``[(source_name, score), ...]`` best first. Both read ``workspace.covisibility``: for each pair of
images, the triangulation angles (degrees) of the sparse points they share.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = [
    "ColmapSelector",
    "SparseScoreSelector",
    "make_colmap_selector",
    "make_sparse_score_selector",
]


def _ranked(scores: dict[str, float], max_sources: int) -> list[tuple[str, float]]:
    # Ties are broken by name so that the order never depends on dictionary order.
    order = sorted(scores.items(), key=lambda item: (-item[1], item[0]))
    return [(name, score) for name, score in order if score > 0][:max_sources]


class ColmapSelector:
    """COLMAP's ``__auto__`` rule: most shared sparse points among the images whose 75th-percentile
    triangulation angle with the reference reaches ``min_triangulation_angle`` degrees."""

    def __init__(self, min_triangulation_angle: float = 1.0, angle_percentile: float = 75.0):
        if not 0.0 <= min_triangulation_angle < 90.0:
            raise ValueError(
                f"min_triangulation_angle must be in [0, 90) degrees, got {min_triangulation_angle}"
            )
        if not 0.0 <= angle_percentile <= 100.0:
            raise ValueError(f"angle_percentile must be in [0, 100], got {angle_percentile}")
        self.min_triangulation_angle = float(min_triangulation_angle)
        self.angle_percentile = float(angle_percentile)

    def __call__(self, workspace, reference: str, max_sources: int) -> list[tuple[str, float]]:
        scores = {
            other: float(angles.size)
            for other, angles in workspace.covisibility.get(reference, {}).items()
            if np.percentile(angles, self.angle_percentile) >= self.min_triangulation_angle
        }
        return _ranked(scores, max_sources)


class SparseScoreSelector:
    """The MVSNet / ACMM-style score: every shared point adds a piecewise Gaussian of its
    triangulation angle, peaking at ``theta0`` degrees (spread ``sigma1`` below, ``sigma2`` above),
    so views with a useful baseline outrank near-duplicates and extreme angles."""

    def __init__(self, theta0: float = 5.0, sigma1: float = 1.0, sigma2: float = 10.0):
        if not (theta0 > 0 and sigma1 > 0 and sigma2 > 0):
            raise ValueError(
                f"theta0, sigma1 and sigma2 must be positive, got {theta0}, {sigma1}, {sigma2}"
            )
        self.theta0, self.sigma1, self.sigma2 = float(theta0), float(sigma1), float(sigma2)

    def __call__(self, workspace, reference: str, max_sources: int) -> list[tuple[str, float]]:
        scores = {}
        for other, angles in workspace.covisibility.get(reference, {}).items():
            sigma = np.where(angles <= self.theta0, self.sigma1, self.sigma2)
            scores[other] = float(np.exp(-((angles - self.theta0) ** 2) / (2.0 * sigma**2)).sum())
        return _ranked({k: v for k, v in scores.items() if math.isfinite(v)}, max_sources)


def make_colmap_selector(params: dict) -> ColmapSelector:
    return ColmapSelector(**params)


def make_sparse_score_selector(params: dict) -> SparseScoreSelector:
    return SparseScoreSelector(**params)
