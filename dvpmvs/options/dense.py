"""Options of the dense stage (:mod:`dvpmvs.dense`): the estimator's, the priors', fusion's."""

from __future__ import annotations

from dataclasses import dataclass, field

from dvpmvs.options.fusion import FusionOptions
from dvpmvs.options.patch_match import PatchMatchOptions
from dvpmvs.options.segmentation import SegmentationOptions
from dvpmvs.passes import Pass
from dvpmvs.validation import check_field_types

__all__ = ["FUSION_BACKENDS", "DenseOptions"]


FUSION_BACKENDS = ("dvpmvs", "colmap")


@dataclass(frozen=True)
class DenseOptions:
    """The dense stage: maps, then fusion.

    Parameters
    ----------
    patch_match : PatchMatchOptions
        The estimator's options.
    priors : dict
        The provider configs ``{"depth_prior": ..., "normal_prior": ..., "edge": ..., "highlight": ...}``
        (highlight: :mod:`dvpmvs.highlight`, absent or ``none`` for none).
    segmentation : SegmentationOptions | None
        The depth-normal-edge aligned prior's options; None lets deformable PatchMatch's anchors go anywhere
        (the paper's ``w/o Agn``).
    geometric : bool
        Run the geometric-consistency pass.
    overwrite : bool
        Recompute every view, whatever the maps found (also maps without a record).
    fuse : bool
        Fuse the maps (false: stop after them).
    fusion : FusionOptions
        Fusion's options.
    fusion_backend : str
        Who fuses the maps: ``dvpmvs`` or ``colmap``.
    previews : bool
        Write PNG previews of the maps.
    mask : dict | None
        The mask provider's config (:mod:`dvpmvs.masks`; None: every pixel kept): masked pixels are
        never estimated and never fused.
    """

    patch_match: PatchMatchOptions = field(default_factory=PatchMatchOptions)
    priors: dict = field(
        default_factory=lambda: {
            "depth_prior": {"name": "coarse_mvs"},
            "normal_prior": {"name": "from_depth"},
            "edge": {"name": "roberts"},
        }
    )
    segmentation: SegmentationOptions | None = field(default_factory=SegmentationOptions)
    geometric: bool = True
    overwrite: bool = False
    fuse: bool = True
    fusion: FusionOptions = field(default_factory=FusionOptions)
    fusion_backend: str = "dvpmvs"
    previews: bool = True
    mask: dict | None = None

    def __post_init__(self):
        check_field_types(self)
        if self.fusion_backend not in FUSION_BACKENDS:
            raise ValueError(
                f"unknown fusion backend {self.fusion_backend!r}; choose {' or '.join(FUSION_BACKENDS)}"
            )

    @property
    def final_pass(self) -> Pass:
        return Pass.GEOMETRIC if self.geometric else Pass.PHOTOMETRIC

    @property
    def passes(self) -> list[Pass]:
        return [Pass.PHOTOMETRIC] + ([Pass.GEOMETRIC] if self.geometric else [])
