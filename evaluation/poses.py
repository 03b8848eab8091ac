"""Recovered camera poses against given ones, after the similarity that best aligns them.

Structure from motion recovers poses up to a similarity (scale, rotation, translation). The
rotation is the chordal mean of the per-image rotations that map one model's frame onto the
other's (every camera's orientation votes), then scale and translation are the least-squares fit
of the camera centres under that rotation. Aligning on the centres alone (Umeyama, or pycolmap's
``align_reconstructions_via_proj_centers``) leaves the rotation about a line of nearly collinear
centres free: on the embedded scene's five cameras along an arc it misplaces every orientation by
about 20 degrees where this alignment finds 2 to 5.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["PoseErrors", "pose_errors"]


@dataclass
class PoseErrors:
    """Per image (names in ``names``): ``centre`` error in the reference's units, ``rotation``
    error in degrees; ``extent``: the largest distance between two reference centres, the
    scale to read centre errors against; ``scale``: the similarity's scale."""

    names: list[str]
    centre: np.ndarray
    rotation: np.ndarray
    extent: float
    scale: float

    def table(self) -> str:
        lines = [
            "| image | centre error | of the extent | rotation error (deg) |",
            "|---|---:|---:|---:|",
        ]
        for name, c, r in zip(self.names, self.centre, self.rotation):
            lines.append(f"| {name} | {c:.4f} | {100 * c / self.extent:.2f} % | {r:.3f} |")
        lines.append(
            f"| max | {self.centre.max():.4f} | {100 * self.centre.max() / self.extent:.2f} % | "
            f"{self.rotation.max():.3f} |"
        )
        return "\n".join(lines)


def _rotation_and_centre(image) -> tuple[np.ndarray, np.ndarray]:
    pose = image.cam_from_world() if callable(image.cam_from_world) else image.cam_from_world
    return np.asarray(pose.rotation.matrix()), np.asarray(image.projection_center())


def _poses(model) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """name -> (world-to-camera rotation, centre) of a pycolmap Reconstruction's posed images,
    or ``model`` itself when it is such a mapping already."""
    if isinstance(model, dict):
        return {
            name: (np.asarray(R, float), np.asarray(c, float)) for name, (R, c) in model.items()
        }
    return {
        image.name: _rotation_and_centre(image) for image in model.images.values() if image.has_pose
    }


def pose_errors(estimated, reference) -> PoseErrors:
    """Errors of the images of ``estimated`` against the same-named images of ``reference``
    (each a pycolmap Reconstruction, or a mapping name -> (world-to-camera rotation, centre)),
    after the best similarity (module doc)."""
    ours, theirs = _poses(estimated), _poses(reference)
    names = sorted(set(ours) & set(theirs))
    if len(names) < 3:
        raise ValueError(
            f"{len(names)} images in common between the two models; the alignment needs 3"
        )
    # x_cam = R_ours X_ours = R_ref X_ref with X_ref = s Q X_ours + t, so R_ours = R_ref Q.
    votes = sum(theirs[n][0].T @ ours[n][0] for n in names)
    u, _, vt = np.linalg.svd(votes)
    q = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
    a = np.array([q @ ours[n][1] for n in names])
    b = np.array([theirs[n][1] for n in names])
    a0, b0 = a - a.mean(axis=0), b - b.mean(axis=0)
    scale = float((a0 * b0).sum() / (a0 * a0).sum())
    centre = np.linalg.norm(scale * a0 - b0, axis=1)
    cosines = [(np.trace(ours[n][0] @ q.T @ theirs[n][0].T) - 1) / 2 for n in names]
    rotation = np.degrees(np.arccos(np.clip(cosines, -1.0, 1.0)))
    extent = float(
        max(np.linalg.norm(b[i] - b[j]) for i in range(len(b)) for j in range(i + 1, len(b)))
    )
    return PoseErrors(names, centre, rotation, extent, scale)
