"""The ONNX depth and normal priors (entry points ``onnx`` of ``dvpmvs.depth_priors`` and
``dvpmvs.normal_priors``).

A depth network's output is ``depth`` or ``inverse_depth``; unless ``metric``, the core aligns
it to the view's sparse points (robust scale and shift, in inverse depth for an inverse output).
A normal network's output is taken as camera-frame normals (OpenCV axes: x right, y down, z
forward; ``flip_y_z`` for networks with OpenGL axes) and turned to face the camera.
"""

from __future__ import annotations

from typing import Any, Mapping

import numpy as np

from dvpmvs.priors import DepthPrior, face_camera

from dvpmvs_onnx.model import OnnxModel, OnnxOptions

__all__ = ["OnnxDepth", "OnnxNormals", "make_depth", "make_normals"]


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
        return DepthPrior(depth=values, valid=values > 0, metric=self.metric,
                          inverse=self.output == "inverse_depth")


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
        normal = np.where(norm > 1e-6, normal / np.maximum(norm, 1e-6), np.array([0, 0, -1], np.float32))
        return face_camera(normal.astype(np.float32), ctx.K)


def make_depth(params: Mapping[str, Any]) -> OnnxDepth:
    options, own = OnnxOptions.from_config("depth_prior", params, own=("output", "metric"))
    return OnnxDepth(options, **own)


def make_normals(params: Mapping[str, Any]) -> OnnxNormals:
    options, own = OnnxOptions.from_config("normal_prior", params, own=("flip_y_z",))
    return OnnxNormals(options, **own)
