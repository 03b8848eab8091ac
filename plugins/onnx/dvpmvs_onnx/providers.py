"""The ONNX depth and normal priors and highlight corrector (entry points ``onnx`` of
``dvpmvs.depth_priors``, ``dvpmvs.normal_priors`` and ``dvpmvs.highlight_correctors``).

A depth network's output is ``depth`` or ``inverse_depth``; unless ``metric``, the core aligns
it to the view's sparse points (robust scale and shift, in inverse depth for an inverse output).
A normal network's output is taken as camera-frame normals (OpenCV axes: x right, y down, z
forward; ``flip_y_z`` for networks with OpenGL axes) and turned to face the camera. A highlight
network (preset ``jshdr``) gives a mask and a highlight-free image: two of its outputs, named or
numbered.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import cv2
import numpy as np

from dvpmvs.priors import DepthPrior, face_camera
from dvpmvs_onnx.model import OnnxModel, OnnxOptions, as_image, select_output

__all__ = [
    "OnnxDepth",
    "OnnxNormals",
    "OnnxHighlight",
    "make_depth",
    "make_normals",
    "make_highlight",
]


class OnnxDepth:
    """Monocular depth from an ONNX network (presets ``depthpro``, ``depth_anything_v2``)."""

    def __init__(self, options: OnnxOptions, output: str = "inverse_depth", metric: bool = False):
        if output not in ("depth", "inverse_depth"):
            raise ValueError(f"depth_prior.output must be depth or inverse_depth, got {output!r}")
        self.model, self.output, self.metric = OnnxModel(options), output, bool(metric)

    def input_files(self, name: str, root=None) -> list:
        """The model file (its content joins the maps' provenance)."""
        return [self.model.path(root)]

    def __call__(self, ctx) -> DepthPrior:
        values = self.model.predict(ctx.rgb(), channels=1, root=ctx.root)
        # Zero or negative means "no value" (sky in a disparity map, padding); the core aligns the rest.
        return DepthPrior(
            depth=values,
            valid=values > 0,
            metric=self.metric,
            inverse=self.output == "inverse_depth",
        )


class OnnxNormals:
    """Monocular normals from an ONNX network (preset ``metric3dv2``)."""

    def __init__(self, options: OnnxOptions, flip_y_z: bool = False):
        self.model, self.flip_y_z = OnnxModel(options), bool(flip_y_z)

    def input_files(self, name: str, root=None) -> list:
        """The model file (its content joins the maps' provenance)."""
        return [self.model.path(root)]

    def __call__(self, ctx, depth) -> np.ndarray:
        normal = self.model.predict(ctx.rgb(), channels=3, root=ctx.root)
        if self.flip_y_z:
            normal = normal * np.array([1, -1, -1], np.float32)
        norm = np.linalg.norm(normal, axis=2, keepdims=True)
        normal = np.where(
            norm > 1e-6, normal / np.maximum(norm, 1e-6), np.array([0, 0, -1], np.float32)
        )
        return face_camera(normal.astype(np.float32), ctx.K)


def make_depth(params: Mapping[str, Any]) -> OnnxDepth:
    options, own = OnnxOptions.from_config("depth_prior", params, own=("output", "metric"))
    return OnnxDepth(options, **own)


def make_normals(params: Mapping[str, Any]) -> OnnxNormals:
    options, own = OnnxOptions.from_config("normal_prior", params, own=("flip_y_z",))
    return OnnxNormals(options, **own)


class OnnxHighlight:
    """Highlight detection and removal from an ONNX network (preset ``jshdr``, the SHIQ family).

    ``mask_output`` / ``corrected_output``: the output holding the mask (one channel, a
    probability; ``mask_logits``: logits, put through a sigmoid) and the one holding the
    highlight-free RGB image (values in [0, ``corrected_scale``]), each by name or by position
    (None: the first output with one channel, the first with three). ``mask_threshold``: the
    probability from which a pixel is a highlight. ``tile``: run the network over tiles of its
    input size covering the view at its own resolution (overlapping by ``tile_overlap`` pixels,
    blended), instead of on the view resized to that size: for networks trained on small crops.
    """

    def __init__(
        self,
        options: OnnxOptions,
        mask_output=None,
        corrected_output=None,
        mask_threshold: float = 0.5,
        mask_logits: bool = False,
        corrected_scale: float = 1.0,
        tile: bool = False,
        tile_overlap: int = 16,
    ):
        if not 0 < float(mask_threshold) < 1:
            raise ValueError(f"highlight.mask_threshold must be in (0, 1), got {mask_threshold}")
        if not float(corrected_scale) > 0:
            raise ValueError(f"highlight.corrected_scale must be > 0, got {corrected_scale}")
        if int(tile_overlap) < 0:
            raise ValueError(f"highlight.tile_overlap must be >= 0, got {tile_overlap}")
        self.model = OnnxModel(options)
        self.mask_output, self.corrected_output = mask_output, corrected_output
        self.mask_threshold, self.mask_logits = float(mask_threshold), bool(mask_logits)
        self.corrected_scale, self.tile, self.tile_overlap = (
            float(corrected_scale),
            bool(tile),
            int(tile_overlap),
        )

    def input_files(self, name: str, root=None) -> list:
        """The model file (its content joins the outputs' provenance)."""
        return [self.model.path(root)]

    def _output(
        self, outputs: list, names: list[str], which, channels: int, what: str
    ) -> np.ndarray:
        kind = "a one-channel map" if channels == 1 else "an RGB image"
        option = f"highlight.{'mask' if channels == 1 else 'corrected'}_output"
        return select_output(
            outputs,
            names,
            which,
            lambda array: as_image(array, channels),
            option,
            f"{kind} (the {what})",
        )

    def _predict(self, rgb: np.ndarray, root) -> tuple[np.ndarray, np.ndarray]:
        outputs, names, box = self.model.run(rgb, root)
        shape = rgb.shape[:2]
        mask = self.model.to_image(
            self._output(outputs, names, self.mask_output, 1, "mask"), box, shape
        )
        corrected = self.model.to_image(
            self._output(outputs, names, self.corrected_output, 3, "corrected image"), box, shape
        )
        return mask, corrected

    def _tiled(self, rgb: np.ndarray, root) -> tuple[np.ndarray, np.ndarray]:
        th, tw = self.model.input_size(root)
        h, w = rgb.shape[:2]
        # A view smaller than a tile is padded (reflected) to one.
        ph, pw = max(h, th), max(w, tw)
        padded = (
            cv2.copyMakeBorder(rgb, 0, ph - h, 0, pw - w, cv2.BORDER_REFLECT_101)
            if (ph, pw) != (h, w)
            else rgb
        )

        def starts(size, tile):
            step = max(1, tile - self.tile_overlap)
            out = list(range(0, size - tile + 1, step))
            return out if out[-1] == size - tile else out + [size - tile]

        mask = np.zeros((ph, pw), np.float32)
        corrected = np.zeros((ph, pw, 3), np.float32)
        weight = np.zeros((ph, pw, 1), np.float32)
        for top in starts(ph, th):
            for left in starts(pw, tw):
                m, c = self._predict(
                    np.ascontiguousarray(padded[top : top + th, left : left + tw]), root
                )
                mask[top : top + th, left : left + tw] += m
                corrected[top : top + th, left : left + tw] += c
                weight[top : top + th, left : left + tw] += 1
        return (mask / weight[..., 0])[:h, :w], (corrected / weight)[:h, :w]

    def __call__(self, ctx) -> tuple[np.ndarray, np.ndarray]:
        from dvpmvs.image import to_grey

        rgb = np.asarray(ctx.rgb(), np.float32)
        mask, corrected = self._tiled(rgb, ctx.root) if self.tile else self._predict(rgb, ctx.root)
        if self.mask_logits:
            mask = 1.0 / (1.0 + np.exp(-mask))
        grey = to_grey(np.clip(corrected / self.corrected_scale, 0, 1).astype(np.float32))
        return grey.astype(np.float32), mask >= self.mask_threshold


def make_highlight(params: Mapping[str, Any]) -> OnnxHighlight:
    options, own = OnnxOptions.from_config(
        "highlight",
        params,
        own=(
            "mask_output",
            "corrected_output",
            "mask_threshold",
            "mask_logits",
            "corrected_scale",
            "tile",
            "tile_overlap",
        ),
    )
    return OnnxHighlight(options, **own)
