"""Camera poses against given ones after a similarity (evaluation/poses.py)."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from dvpmvs.evaluation.poses import pose_errors


def _arc(n=6, seed=0):
    """Cameras on a flat arc looking at the origin: name -> (world-to-camera R, centre)."""
    rng = np.random.default_rng(seed)
    poses = {}
    for i, angle in enumerate(np.linspace(-0.6, 0.6, n)):
        centre = np.array([4 * np.sin(angle), 0.0, -4 * np.cos(angle)])
        forward = -centre / np.linalg.norm(centre)
        right = np.cross([0.0, 1.0, 0.0], forward)
        right /= np.linalg.norm(right)
        R = np.stack([right, np.cross(forward, right), forward])  # rows: camera axes in the world
        poses[f"{i:04d}.jpg"] = (
            Rotation.from_rotvec(rng.normal(0, 1e-3, 3)).as_matrix() @ R,
            centre,
        )
    return poses


def _similar(poses, scale, Q, t):
    """The same cameras in a world X' = scale Q X + t."""
    return {n: (R @ Q.T, scale * Q @ c + t) for n, (R, c) in poses.items()}


def test_a_similar_model_has_no_error():
    truth = _arc()
    Q = Rotation.from_euler("xyz", [30, -50, 120], degrees=True).as_matrix()
    errors = pose_errors(_similar(truth, 0.37, Q, np.array([5.0, -2.0, 1.0])), truth)
    assert errors.centre.max() < 1e-9 and errors.rotation.max() < 1e-5
    assert errors.scale == pytest.approx(1 / 0.37) and errors.extent == pytest.approx(
        8 * np.sin(0.6), rel=1e-6
    )


def test_one_camera_turned_by_two_degrees_is_found():
    truth = _arc()
    moved = dict(
        _similar(truth, 2.0, Rotation.from_euler("y", 40, degrees=True).as_matrix(), np.zeros(3))
    )
    R, c = moved["0002.jpg"]
    moved["0002.jpg"] = (Rotation.from_euler("x", 2, degrees=True).as_matrix() @ R, c)
    errors = pose_errors(moved, truth)
    turned = errors.names.index("0002.jpg")
    assert errors.rotation[turned] == pytest.approx(
        2 * 5 / 6, abs=0.05
    )  # the mean absorbs 1/6 of it
    assert np.delete(errors.rotation, turned).max() == pytest.approx(2 / 6, abs=0.05)
    # The alignment's rotation is off by that 1/3 degree, which moves the centres a little.
    assert errors.centre.max() < 0.005 and errors.centre.max() / errors.extent < 0.001


def test_too_few_common_images_is_an_error():
    truth = _arc(3)
    with pytest.raises(ValueError, match="2 images in common"):
        pose_errors({n: p for n, p in list(truth.items())[:2]}, truth)
