"""Learned dvpmvs priors through ONNX Runtime.

``depth_prior=onnx`` (presets ``depthpro``, ``depth_anything_v2``) and ``normal_prior=onnx``
(preset ``metric3dv2``) run a user-given ``.onnx`` file on the CPU execution provider by default.
No weights are shipped and nothing is downloaded: the model path comes from the config.
"""

from dvpmvs_onnx.model import PRESETS, OnnxModel, OnnxOptions
from dvpmvs_onnx.providers import OnnxDepth, OnnxNormals

__all__ = ["OnnxModel", "OnnxOptions", "PRESETS", "OnnxDepth", "OnnxNormals"]
