"""Camera geometry helpers for building scenes with known ground truth."""

from __future__ import annotations

import numpy as np

from dvpmvs.evaluation.portable import matvec, norm


def look_at(
    center: np.ndarray, target: np.ndarray, up=(0.0, -1.0, 0.0)
) -> tuple[np.ndarray, np.ndarray]:
    """World -> camera (R, t) of a camera at ``center`` looking at ``target``.

    COLMAP's camera frame: x right, y down, z forward; ``up`` is the world direction that appears
    upwards in the image (default -y, so world y points down as in the camera).
    """
    z = np.asarray(target, float) - np.asarray(center, float)
    z = z / norm(z)
    # The image's y axis points down, i.e. along -up: x = y cross z = z cross up.
    x = np.cross(z, np.asarray(up, float))
    x = x / norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    return R, matvec(-R, np.asarray(center, float))
