"""The estimator's passes: which maps a file holds (part of COLMAP's file names) and which a
stage reads."""

from enum import Enum

__all__ = ["Pass"]


class Pass(str, Enum):
    """Estimator pass whose output a map holds (part of COLMAP's file name)."""

    PHOTOMETRIC = "photometric"
    GEOMETRIC = "geometric"
