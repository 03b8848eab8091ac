"""Hydra config groups of the ONNX priors (added to the CLI's search path by entry point)."""
