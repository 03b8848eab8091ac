"""Options of structure from motion from a folder of photos (:mod:`dvpmvs.reconstruction`)."""

from __future__ import annotations

from dataclasses import dataclass

from dvpmvs.validation import check_field_types, check_threads

__all__ = ["MATCHING_METHODS", "SfmOptions"]


MATCHING_METHODS = ("auto", "exhaustive", "sequential", "spatial")


@dataclass(frozen=True)
class SfmOptions:
    """Structure from motion from a folder of photos (pycolmap's extraction, matching and mapping).

    Parameters
    ----------
    camera_model : str
        COLMAP's camera model for the photos (``SIMPLE_RADIAL``, ``PINHOLE``, ``OPENCV`` ...).
    single_camera : bool
        One camera for all photos (else one per size and EXIF).
    camera_params : str
        Known intrinsics, comma-separated in the model's order (empty: estimated).
    matching : str
        ``auto``, ``exhaustive``, ``sequential`` or ``spatial``.
    exhaustive_max_images : int
        Where ``auto`` switches to sequential.
    sequential_overlap : int
        Photos each is matched with.
    max_num_features : int
        SIFT features per photo.
    feature_max_image_size : int
        Photos are read at most this long (-1: COLMAP's default, 3200).
    min_num_matches : int
        Pairs with fewer verified matches are ignored by the mapper.
    seed : int
        The random seed of verification and mapping.
    num_threads : int
        0 uses every core.
    reproducible : bool
        Structure from motion on one thread (extraction, matching, mapping, bundle adjustment), so that the same
        photos and seed give the same model, bit for bit; several threads number the features, hand RANSAC's
        seeded generators other pairs and sum the adjustment's residuals in another order from run to run.
    """

    camera_model: str = "SIMPLE_RADIAL"
    single_camera: bool = False
    camera_params: str = ""
    matching: str = "auto"
    exhaustive_max_images: int = 150
    sequential_overlap: int = 10
    max_num_features: int = 8192
    feature_max_image_size: int = -1
    min_num_matches: int = 15
    seed: int = 0
    num_threads: int = 0
    reproducible: bool = True

    def __post_init__(self):
        import pycolmap

        check_field_types(self, "sfm.")
        try:
            model = pycolmap.CameraModelId.__members__[self.camera_model]
        except KeyError:
            known = ", ".join(m for m in pycolmap.CameraModelId.__members__ if m != "INVALID")
            raise ValueError(
                f"sfm.camera_model {self.camera_model!r} is not a COLMAP camera model; one of {known}"
            ) from None
        if self.camera_params:
            try:
                values = [float(v) for v in self.camera_params.split(",")]
            except ValueError:
                raise ValueError(
                    f"sfm.camera_params must be comma-separated numbers, got {self.camera_params!r}"
                ) from None
            expected = len(pycolmap.Camera.create_from_model_id(1, model, 1.0, 1, 1).params)
            if len(values) != expected:
                raise ValueError(
                    f"sfm.camera_params has {len(values)} values; {self.camera_model} takes {expected} "
                    f"({pycolmap.Camera.create_from_model_id(1, model, 1.0, 1, 1).params_info})"
                )
        if self.matching not in MATCHING_METHODS:
            raise ValueError(
                f"sfm.matching must be one of {', '.join(MATCHING_METHODS)}, got {self.matching!r}"
            )
        for key in (
            "exhaustive_max_images",
            "sequential_overlap",
            "max_num_features",
            "min_num_matches",
        ):
            if getattr(self, key) < 1:
                raise ValueError(f"sfm.{key} must be >= 1, got {getattr(self, key)}")
        check_threads("sfm.num_threads", self.num_threads)

    def matcher(self, num_images: int) -> str:
        if self.matching != "auto":
            return self.matching
        return "exhaustive" if num_images <= self.exhaustive_max_images else "sequential"
