"""The dense stage: views -> estimator passes -> maps on disk -> fusion.

A photometric pass over every reference view, then (optionally) a geometric-consistency pass
that reads the neighbours' photometric maps, then fusion. Outputs go to an output folder
(``out``: the workspace itself by default, as COLMAP does; any other folder is made a COLMAP
workspace over the same images and model, :meth:`Workspace.link_output`).

Per view and pass the estimator writes, in COLMAP's format and naming:
``stereo/depth_maps/<image>.<pass>.bin``, ``stereo/normal_maps/...`` (camera-frame normals),
``stereo/cost_maps/...`` (final matching cost), ``stereo/visibility_maps/...`` (one channel per
source view, in the order of ``patch-match.cfg``: the view-selection weights), PNG previews
under ``stereo/previews/``, and its provenance record (:mod:`dvpmvs.provenance`). Every file is
written atomically. A rerun reuses a view's maps only when their record carries the fingerprint
this run would give them (the same options, inputs and code), recomputes the others and says
why in one line per pass; maps without a record (COLMAP's, an older dvpmvs's) are neither
reused nor overwritten unless ``overwrite``. The fused cloud carries a record too, so a rerun
with a new fusion option fuses again and nothing else.

The stage is one graph of stored products (:mod:`dvpmvs.dense.products`): per view its
highlight outputs, its mask (:mod:`dvpmvs.dense.masks`), its region labels (priors, then
segmentation: :mod:`dvpmvs.dense.regions`), its maps of each pass, and the fused cloud, each with its inputs, their
fingerprint, its files and one record scheme (:class:`dvpmvs.provenance.CachedOutput`). The
plan (:mod:`dvpmvs.dense.plan`) is made once per run, the cloud's record checked with the maps'
before anything is computed; its tasks (:mod:`dvpmvs.dense.tasks`) make what is not current, the
run makes the cloud after them (:mod:`dvpmvs.dense.cloud`); later products read the files of
earlier ones.
"""

from dvpmvs.dense.cloud import (
    FusionReport,
    check_cloud_path,
    cloud_record_path,
    fuse_to_file,
    fuse_workspace,
)
from dvpmvs.dense.inputs import GEOMETRIC_ONLY_OPTIONS, map_files, pass_inputs
from dvpmvs.dense.masks import MaskStore, mask_path
from dvpmvs.dense.report import DenseError, DenseSummary, ViewReport
from dvpmvs.dense.stage import run_dense
from dvpmvs.options.dense import FUSION_BACKENDS, DenseOptions

__all__ = [
    "DenseOptions",
    "DenseError",
    "DenseSummary",
    "ViewReport",
    "FusionReport",
    "MaskStore",
    "mask_path",
    "pass_inputs",
    "map_files",
    "run_dense",
    "fuse_workspace",
    "fuse_to_file",
    "cloud_record_path",
    "check_cloud_path",
    "FUSION_BACKENDS",
    "GEOMETRIC_ONLY_OPTIONS",
]
