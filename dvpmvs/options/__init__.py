"""The options of every stage, as COLMAP's option structs: frozen dataclasses that validate
themselves on construction (a bad value raises ``ValueError`` naming the key). They import
nothing above :mod:`dvpmvs.validation`, so that the configuration (:mod:`dvpmvs.config`) and
any client reach them without loading the stages or their compiled kernels."""

from dvpmvs.options.dense import FUSION_BACKENDS, DenseOptions
from dvpmvs.options.executor import EXECUTORS, ExecutorOptions
from dvpmvs.options.fusion import FusionOptions
from dvpmvs.options.meshing import MESHING_METHODS, MeshingOptions
from dvpmvs.options.patch_match import MAX_SOURCES, PatchMatchOptions
from dvpmvs.options.segmentation import PAPER_SYMBOLS, SegmentationOptions
from dvpmvs.options.sfm import MATCHING_METHODS, SfmOptions
from dvpmvs.options.workspace import MIN_IMAGE_SIZE, WorkspaceOptions

__all__ = [
    "DenseOptions",
    "ExecutorOptions",
    "FusionOptions",
    "MeshingOptions",
    "PatchMatchOptions",
    "SegmentationOptions",
    "SfmOptions",
    "WorkspaceOptions",
    "EXECUTORS",
    "FUSION_BACKENDS",
    "MATCHING_METHODS",
    "MAX_SOURCES",
    "MESHING_METHODS",
    "MIN_IMAGE_SIZE",
    "PAPER_SYMBOLS",
]
