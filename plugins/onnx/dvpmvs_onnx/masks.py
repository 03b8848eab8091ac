"""Masks from a segmentation network (entry point ``onnx`` of ``dvpmvs.masks``).

The network sees the view's image as the ONNX priors do (``input_size``, ``resize``, ``scale``,
``mean``, ``std``, ``layout``: :class:`~dvpmvs_onnx.model.OnnxOptions`). Its output is a
per-pixel class map, either labels in one channel ((h, w), (1, h, w) or (1, 1, h, w); floats are
rounded to the nearest class, so a one-class probability is class 1 from 0.5) or one score per
class (C >= 2 channels, first or last: the class is the argmax).
The class map is cropped to the image and resized by nearest neighbour to the view; a pixel
whose class is in ``exclude`` is masked.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from dvpmvs.masks import MaskError
from dvpmvs.priors import PriorError
from dvpmvs_onnx.model import OnnxModel, OnnxOptions, select_output

__all__ = ["OnnxMasks", "class_map", "make_masks"]


def class_map(array: np.ndarray, layout: str) -> np.ndarray | None:
    """A network output as an (h, w) int64 class map, or None when it is not one: labels in one
    channel (or an integer tensor), else the argmax of per-class scores (channels first for
    ``layout`` nchw, last for nhwc; a batch of one). Labels or scores that are NaN or infinite
    are no classes: :class:`~dvpmvs.masks.MaskError` says how many (an argmax would call them
    class 0)."""
    array = np.asarray(array)
    shape = array.shape
    if array.ndim == 4:
        if shape[0] != 1:
            return None
        array = array[0]
    if array.ndim == 2:
        labels = array
    elif array.ndim == 3:
        channels_first = layout == "nchw"
        channels = array.shape[0] if channels_first else array.shape[2]
        if channels == 1:
            labels = array[0] if channels_first else array[..., 0]
        elif np.issubdtype(array.dtype, np.integer):
            return None  # several integer channels are no class map
        else:
            _check_finite(array)
            labels = array.argmax(axis=0 if channels_first else 2)
    else:
        return None
    if min(labels.shape) < 2:
        return None
    if not np.issubdtype(labels.dtype, np.integer):
        _check_finite(labels)
        labels = np.rint(labels)
    return labels.astype(np.int64)


def _check_finite(array: np.ndarray) -> None:
    bad = int((~np.isfinite(array)).sum())
    if bad:
        raise MaskError(
            f"mask.model returned {bad} NaN or infinite value(s) where a class map was expected: "
            f"check the model and its input options (mask.scale, mask.mean, mask.std)"
        )


class OnnxMasks:
    """Per-view masks from an ONNX segmentation network: pixels of the classes ``exclude`` (by
    index) are masked. ``output``: the output holding the class map, by name or position (None:
    the first output that is one)."""

    # A network run per view: the core checks the first view's mask before any compute, and
    # makes the others' when their views are computed.
    costly = True

    def __init__(self, options: OnnxOptions, exclude: Sequence[int] = (), output=None):
        if isinstance(exclude, (int, str)):
            exclude = [exclude]
        try:
            classes = sorted({int(c) for c in exclude})
        except (TypeError, ValueError):
            raise ValueError(
                f"mask.exclude must list class indices (integers), got {list(exclude)}"
            ) from None
        if not classes or min(classes) < 0:
            raise ValueError(
                f"mask.exclude must list the class indices to mask (integers >= 0), e.g. "
                f"mask.exclude=[2], got {list(exclude)}"
            )
        self.model, self.exclude, self.output = (
            OnnxModel(options),
            np.asarray(classes, np.int64),
            output,
        )

    def input_files(self, view_name: str, root: Path | None = None) -> list[Path]:
        """The model file (its content joins the maps' provenance)."""
        try:
            return [self.model.path(root)]
        except PriorError as exc:
            raise MaskError(str(exc)) from None

    def _labels(self, outputs: list, names: list[str]) -> np.ndarray:
        layout = self.model.options.layout
        return select_output(
            outputs,
            names,
            self.output,
            lambda array: class_map(array, layout),
            "mask.output",
            "a per-pixel class map (labels in one channel, or per-class scores)",
            MaskError,
        )

    def __call__(self, view, root: Path | None) -> np.ndarray:
        rgb = view.load_rgb()
        try:
            outputs, names, box = self.model.run(rgb, root)
        except PriorError as exc:
            raise MaskError(str(exc)) from None
        labels = self._labels(outputs, names)
        h, w = labels.shape
        top, left, bottom, right = (
            round(box[0] * h),
            round(box[1] * w),
            round(box[2] * h),
            round(box[3] * w),
        )
        labels = np.ascontiguousarray(labels[top:bottom, left:right])
        # Nearest neighbour: a class index is no quantity to interpolate. OpenCV resizes int32.
        if labels.shape != (view.height, view.width):
            labels = cv2.resize(
                labels.astype(np.int32), (view.width, view.height), interpolation=cv2.INTER_NEAREST
            )
        return ~np.isin(labels, self.exclude)


def make_masks(params: Mapping[str, Any]) -> OnnxMasks:
    options, own = OnnxOptions.from_config("mask", params, own=("exclude", "output"))
    return OnnxMasks(options, **own)
