"""A tilted plane in a small camera, and the context a prior provider gets for it."""

import numpy as np

from dvpmvs.priors import PriorContext

K = np.array([[100.0, 0, 40], [0, 100.0, 30], [0, 0, 1]])
H, W = 60, 80


def plane_depth(a=0.2, b=-0.1, c=4.0):
    rows, cols = np.mgrid[0:H, 0:W].astype(np.float64)
    return (c / (1 - a * (cols - 40) / 100 - b * (rows - 30) / 100)).astype(np.float32)


def prior_context(tmp_path, image=None, sparse=None, name="im.png"):
    if image is None:
        image = np.zeros((H, W), np.float32)
        image[:, 40:] = 1.0  # one vertical step edge
    if sparse is None:
        depth = plane_depth()
        rng = np.random.default_rng(0)
        cols, rows = rng.integers(0, W, 200), rng.integers(0, H, 200)
        sparse = np.stack([cols, rows, depth[rows, cols]], axis=1).astype(np.float64)
    return PriorContext(name, image, K, (2.0, 8.0), sparse, root=tmp_path)
