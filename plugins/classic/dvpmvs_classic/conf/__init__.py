"""Hydra config groups of the classic providers (added to the search path by entry point)."""
