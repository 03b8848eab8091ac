"""Hydra config groups of the ONNX priors (added to the CLI's search path by entry point)."""

# The presets appear only where ONNX Runtime is installed (pip install 'dvpmvs[onnx]').
REQUIRES = ("onnxruntime",)
