"""Highlight correctors. ``none`` matches the images as they are (no highlight mask)."""

from __future__ import annotations

import numpy as np

__all__ = ["NoHighlight", "make_none"]


class NoHighlight:
    def __call__(self, ctx) -> tuple[np.ndarray, np.ndarray]:
        return ctx.image, np.zeros(ctx.shape, bool)


def make_none(params: dict) -> NoHighlight:
    if params:
        raise ValueError(f"the 'none' highlight corrector takes no parameters, got {sorted(params)}")
    return NoHighlight()
