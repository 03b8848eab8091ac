"""Tests of the built-in providers (`plugins/classic`, `plugins/onnx`)."""
