"""Options of the depth-normal-edge aligned prior's segmentation (:mod:`dvpmvs.segmentation`), with the
paper's Table V symbols."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, fields
from typing import Any

from dvpmvs.validation import check_field_types

__all__ = ["PAPER_SYMBOLS", "SegmentationOptions"]


@dataclass(frozen=True)
class SegmentationOptions:
    """The depth-normal-edge aligned prior's segmentation (paper section 3.2, Table V's symbols in
    brackets; ``SegmentationOptions.from_config`` also takes the symbols as keys).

    Parameters
    ----------
    min_region : int
        [eta] regions of at least this many pixels get a RANSAC plane.
    plane_similarity : float
        [varphi] the Psi threshold of erosion (at most) and dilation (at least).
    normal_similarity : float
        [phi] the mean Phi along a boundary (erosion at most; dilation and filtering at least).
    erosion_gain : float
        [gamma] the (r_i + r_j) / 2 r_k of a valid erosion.
    min_inlier_ratio : float
        [kappa] planes this reliable may merge or take boundary pixels.
    filter_distance : float
        [delta] boundary pixels this close to a plane join it, in ``distance_unit``.
    distance_unit : float
        Relative depth: RANSAC's inlier distance, the unit of delta and of Psi's plane gap.
    depth_gradient : float
        [epsilon] on depth normalised over the view's range (without normals).
    normal_search : int
        Pixels searched along each direction for Phi.
    adjacency_radius : int
        Regions closer than this (across an edge) are neighbours.
    seam_band : int
        Psi's plane gap is also measured between each side's plane moved to the depth prior of its pixels within
        this many pixels of the other side (0: the planes only).
    max_step_tilt : float
        With an independent normal prior whose normals do not turn inside a region, erosion's division at the
        depth prior's planes is a depth step, and stands only when the two planes' normals lie within this many
        degrees (180: no limit).
    ransac_iterations, ransac_points : int
        RANSAC's iterations and the points it samples per region.
    max_erosion_rounds : int
        Erosion's rounds at most.
    filter_iterations : int
        How many pixels deep filtering reaches into a band of boundary pixels.
    erosion, dilation, filtering, use_normals : bool
        The ablation switches (the paper's w/o Ero, w/o Fil, w/o Mon).
    split_by_normals : bool
        Erosion divides a region along the turn of its normal prior (with an independent one, not
        ``from_depth``; false: at the intersection of the depth prior's two planes).
    filter_by_normal : bool
        Pixel filtering also needs the pixel's prior normal within phi of the plane's normal (with an
        independent normal prior; false: eq. 8's distance and Phi only).
    seed : int
        RANSAC's seed.
    """

    min_region: int = 500  # eta: regions of at least this many pixels get a RANSAC plane
    plane_similarity: float = 0.5  # varphi: Psi threshold of erosion (<=) and dilation (>=)
    # phi: mean Phi along a boundary (erosion <=, dilation >=, filtering >=)
    normal_similarity: float = 0.4
    erosion_gain: float = 1.2  # gamma: (r_i + r_j) / 2 r_k of a valid erosion
    min_inlier_ratio: float = 0.7  # kappa: planes this reliable may merge or take boundary pixels
    # delta, in distance units: boundary pixels this close to a plane join it
    filter_distance: float = 0.8
    # relative depth: RANSAC inlier distance, the unit of delta and of Psi's plane gap
    distance_unit: float = 0.02
    # epsilon, on depth normalised over the view's range (without normals)
    depth_gradient: float = 0.005
    normal_search: int = 3  # pixels searched along each direction for Phi
    adjacency_radius: int = 5  # regions closer than this (across an edge) are neighbours
    # Psi's gap also between the planes moved onto the prior this close to the boundary (0: planes only)
    seam_band: int = 15
    # degrees: where those normals do not turn, a division at the depth planes is a step, its planes this parallel
    max_step_tilt: float = 20.0
    ransac_iterations: int = 64
    ransac_points: int = 2000
    max_erosion_rounds: int = 3
    # how many pixels deep filtering reaches into a band of boundary pixels
    filter_iterations: int = 3
    erosion: bool = True  # false with dilation: false is the paper's "w/o Ero"
    dilation: bool = True
    filtering: bool = True  # false: "w/o Fil"
    use_normals: bool = True  # false: "w/o Mon" (DVP-MVS's depth-edge prior)
    # erosion divides a region where an independent normal prior turns (false: where its two planes meet)
    split_by_normals: bool = True
    # filtering also needs an independent prior normal within phi of the plane's (false: eq. 8 as written)
    filter_by_normal: bool = True
    seed: int = 0

    def __post_init__(self):
        check_field_types(self, "segmentation.")
        if self.min_region < 3:
            raise ValueError(f"min_region must be >= 3, got {self.min_region}")
        for name in ("plane_similarity", "normal_similarity"):
            if not -1 <= getattr(self, name) <= 1:
                raise ValueError(f"{name} must be in [-1, 1], got {getattr(self, name)}")
        for name in ("erosion_gain", "filter_distance", "distance_unit", "depth_gradient"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        if not 0 < self.min_inlier_ratio <= 1:
            raise ValueError(f"min_inlier_ratio must be in (0, 1], got {self.min_inlier_ratio}")
        if self.normal_search < 1 or self.adjacency_radius < 1:
            raise ValueError("normal_search and adjacency_radius must be >= 1")
        if self.seam_band < 0:
            raise ValueError(f"seam_band must be >= 0, got {self.seam_band}")
        if not 0 < self.max_step_tilt <= 180:
            raise ValueError(f"max_step_tilt must be in (0, 180] degrees, got {self.max_step_tilt}")
        if self.filter_iterations < 1:
            raise ValueError(f"filter_iterations must be >= 1, got {self.filter_iterations}")
        if self.ransac_iterations < 1 or self.ransac_points < 3:
            raise ValueError("ransac_iterations must be >= 1 and ransac_points >= 3")

    @classmethod
    def from_mapping(cls, values: Mapping[str, Any]) -> SegmentationOptions:
        """Build from a config mapping in which the paper's Table V symbols (``PAPER_SYMBOLS``:
        ``eta``, ``varphi``, ``phi``, ``gamma``, ``kappa``, ``delta``) may stand for the options
        they name; a symbol set (not None) replaces its option's value. Unknown keys are named."""
        values = dict(values)
        for symbol, name in PAPER_SYMBOLS.items():
            value = values.pop(symbol, None)
            if value is not None:
                values[name] = value
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(values) - known)
        if unknown:
            raise ValueError(
                f"unknown segmentation option(s) {', '.join(unknown)}; known: "
                f"{', '.join(sorted(known | set(PAPER_SYMBOLS)))}"
            )
        return cls(**values)


PAPER_SYMBOLS = {
    "eta": "min_region",
    "varphi": "plane_similarity",
    "phi": "normal_similarity",
    "gamma": "erosion_gain",
    "kappa": "min_inlier_ratio",
    "delta": "filter_distance",
}
