"""The dense stage's last product: the fused cloud of a workspace's maps (ours, or COLMAP's
``stereo_fusion``), stored with its record (``<cloud>.provenance.json``: the maps fused, by their
fingerprints, the fusion options and the code), so a rerun with the same maps and options keeps
it and one with a new fusion option fuses again and nothing else."""

from __future__ import annotations

import logging
import os
import shutil
import time
from contextlib import nullcontext
from dataclasses import asdict, dataclass, field
from pathlib import Path

from dvpmvs.dense.masks import MaskStore
from dvpmvs.dense.report import DenseError
from dvpmvs.digests import file_digest, matches_stamp
from dvpmvs.fusion import (
    FusionOptions,
    empty_cloud_message,
    fuse_to_ply,
    fuse_with_colmap,
    missing_maps_hint,
    visibility_path,
)
from dvpmvs.maps import map_path, remove_temporaries
from dvpmvs.options.dense import FUSION_BACKENDS
from dvpmvs.passes import Pass
from dvpmvs.provenance import CachedOutput, Status, code_identity, read_record, record_path
from dvpmvs.validation import check_ply_output
from dvpmvs.view import View
from dvpmvs.workspace import Workspace
from dvpmvs.writer_lock import writer_lock

__all__ = [
    "FusionReport",
    "PlannedCloud",
    "plan_cloud",
    "make_cloud",
    "fuse_workspace",
    "fuse_to_file",
    "cloud_record_path",
    "check_cloud_path",
    "no_sources_error",
    "cloud_bytes",
    "check_space",
]

log = logging.getLogger(__name__)

# Fusion options that never change a cloud's points: the cloud's record lists the views fused
# without maps, and a missing view stops the run unless allowed, whatever the record says.
_SPEED_ONLY_FUSION_OPTIONS = frozenset({"num_threads", "cache_views", "allow_missing"})
MISSING_MAPS = "missing"  # a view with sources but no maps, in a cloud's inputs (a partial cloud)
NO_SOURCES = "no sources"  # a view the dense stage gives no maps (no source view)


def no_sources_error(workspace: Workspace) -> DenseError:
    views = workspace.reference_views()
    return DenseError(
        f"none of the {len(views)} view(s) of {workspace.root} has a source view, so no depth can be computed: "
        f"multi-view stereo needs each view to overlap others. Check the source lists of "
        f"{workspace.stereo_dir / 'patch-match.cfg'} and the sparse model (a model with one registered image, or "
        f"views that share no sparse point, give none)"
    )


def _fused_maps(views: list[View], stereo: Path, pass_: Pass) -> dict[str, object]:
    """Per reference view, what fusion reads of it as found on disk, as the cloud's record must
    describe it: the fingerprint of its maps where their record is complete and the depth and
    normal maps are the files it stamped (as a run's plan names them); else (maps without a
    record, COLMAP's; or changed since written) the digests of the two files; :data:`MISSING_MAPS`
    where a view with sources has none; :data:`NO_SOURCES` where a view without sources has
    none."""
    maps: dict[str, object] = {}
    for view in views:
        depth, normal = (map_path(stereo, view.name, kind, pass_) for kind in ("depth", "normal"))
        if not (depth.is_file() and normal.is_file()):
            maps[view.name] = MISSING_MAPS if view.sources else NO_SOURCES
            continue
        record = read_record(record_path(stereo, view.name, pass_.value))
        stamps = record.files if record is not None and record.complete else {}
        if all(
            kind in stamps
            and (stereo / stamps[kind]["path"]) == path
            and matches_stamp(path, stamps[kind])
            for kind, path in (("depth", depth), ("normal", normal))
        ):
            maps[view.name] = record.fingerprint
        else:
            maps[view.name] = {
                "depth": file_digest(depth),
                "normal": file_digest(normal),
                "image": file_digest(view.path),
            }
    return maps


def _fusion_inputs(fusion: FusionOptions, backend: str, maps: dict[str, object]) -> dict:
    """What shapes a fused cloud: the fusion options and backend, the code, and the maps fused
    (:func:`_fused_maps`)."""
    options = {k: v for k, v in asdict(fusion).items() if k not in _SPEED_ONLY_FUSION_OPTIONS}
    return {"fusion": options, "backend": backend, "code": code_identity(), "maps": maps}


def cloud_record_path(cloud: str | Path) -> Path:
    """The provenance record beside a fused cloud: ``<cloud>.provenance.json``."""
    cloud = Path(cloud)
    return cloud.with_name(cloud.name + ".provenance.json")


@dataclass
class FusionReport:
    output: Path
    points: int
    seconds: float
    reused: bool
    fingerprint: str
    views_without_maps: list[str] = field(
        default_factory=list
    )  # fused without them (allow_missing)


@dataclass
class PlannedCloud:
    """The fused cloud as a product of a run's plan: the views fused (the maps' ``fusion.cfg``),
    those among them without maps (:data:`MISSING_MAPS`, a partial cloud), and ``stored``: its
    inputs (the fusion options, the code, the fingerprints of the maps fused and of the masks)
    against the record beside ``output``."""

    output: Path
    fusion: FusionOptions
    backend: str
    views: list[View]
    missing: list[str]
    stored: CachedOutput

    @property
    def fingerprint(self) -> str:
        return self.stored.fingerprint

    def wanted(self, overwrite: bool) -> bool:
        """Whether a run makes it: it is not current, or the user asked for all."""
        return overwrite or self.stored.current is None

    def explain(self, overwrite: bool) -> str:
        """One line: whether the run fuses, and why."""
        if not self.wanted(overwrite):
            return (
                f"fusion: the cloud {self.output} is current (same maps and fusion options): reused"
            )
        why = {
            Status.MISSING: "not fused yet",
            Status.STALE: "other maps or fusion options",
            Status.INTERRUPTED: "interrupted",
            Status.MODIFIED: "changed on disk since it was written",
            Status.FOREIGN: "without a record",
            Status.CURRENT: "overwrite=true",
        }[self.stored.state]
        return f"fusion: fusing {len(self.views)} views into {self.output} ({why})"


def plan_cloud(
    workspace: Workspace,
    stereo: Path,
    fusion: FusionOptions,
    backend: str,
    output: Path,
    masks: MaskStore,
    views: list[View],
    maps: dict[str, object],
) -> PlannedCloud:
    """The cloud of the ``fusion.input_type`` maps of ``views`` (those of the maps' fusion.cfg:
    the record describes them, the fusion fuses them) in ``stereo``, fused into ``output``;
    ``maps``: view name -> the fingerprint of its maps, where a run's plan makes them or
    :func:`_fused_maps` finds them. A cloud that cannot be made (no maps, or some missing without
    ``fusion.allow_missing``) stops here, before anything is computed."""
    pass_ = Pass(fusion.input_type)
    fused = {v.name: maps.get(v.name, MISSING_MAPS if v.sources else NO_SOURCES) for v in views}
    if all(value == NO_SOURCES for value in fused.values()):
        raise no_sources_error(workspace)
    missing = [name for name, value in fused.items() if value == MISSING_MAPS]
    if missing and all(value in (MISSING_MAPS, NO_SOURCES) for value in fused.values()):
        raise DenseError(
            f"no {fusion.input_type} maps in {stereo}: "
            f"{missing_maps_hint(workspace, stereo, pass_, missing)}"
        )
    if missing and not fusion.allow_missing:
        raise DenseError(
            f"{len(missing)} of {len(fused)} views have no {fusion.input_type} maps in {stereo} (e.g. "
            f"{map_path(stereo, missing[0], 'depth', pass_)}): a cloud without them would lack "
            f"their part of the scene. Compute them (`dvpmvs dense`, which recomputes only what is missing), or "
            f"give fusion_options.allow_missing=true for a partial cloud"
        )
    if missing and backend == "colmap":
        raise DenseError(
            f"fusion_options.allow_missing=true is for fusion=dvpmvs: COLMAP's fusion needs the maps "
            f"of every view of stereo/fusion.cfg ({len(missing)} missing, e.g. {missing[0]})"
        )
    inputs = _fusion_inputs(fusion, backend, fused)
    if masks.active:
        # The masks' files: a changed mask changes the cloud even where the maps are not ours.
        inputs["masks"] = {name: masks.masks.provenance(name, workspace.root) for name in fused}
    stored = CachedOutput.check(cloud_record_path(output), inputs, output.parent, [output])
    return PlannedCloud(output, fusion, backend, views, missing, stored)


def make_cloud(
    workspace: Workspace,
    cloud: PlannedCloud,
    stereo: Path,
    colmap_root: str | Path | None,
    progress: bool,
    reuse: bool,
    overwrite: bool,
    masks: MaskStore,
) -> FusionReport:
    """Fuse ``cloud`` (planned by :func:`plan_cloud`, its maps made since) and write its record;
    with ``reuse`` a current one is kept. ``overwrite``: replace a cloud dvpmvs did not write."""
    output, missing = cloud.output, cloud.missing
    if cloud.missing:
        log.warning(
            "fusion: %d view(s) have no %s maps and add no points: %s (allow_missing=true: a partial "
            "cloud)",
            len(missing),
            cloud.fusion.input_type,
            ", ".join(missing),
        )
    current = cloud.stored.current
    if reuse and current is not None:
        stats = current.stats
        return FusionReport(
            output,
            int(stats.get("points", 0)),
            float(stats.get("seconds", 0.0)),
            True,
            cloud.fingerprint,
            missing,
        )
    check_space(
        output.parent,
        cloud_bytes(workspace),
        f"the fused cloud, at most about {cloud_bytes(workspace) / 2**20:,.1f} MB",
        "give output=PATH on another disk",
    )
    start = time.perf_counter()
    with cloud.stored.making(overwrite):
        points = fuse_to_file(
            workspace,
            cloud.fusion,
            cloud.backend,
            output,
            progress,
            stereo,
            colmap_root,
            masks,
            cloud.views,
        )
    seconds = time.perf_counter() - start
    # The visibility file is part of the cloud (COLMAP's meshers read both): without it the cloud
    # is not current.
    files = {"cloud": output}
    if visibility_path(output).is_file():
        files["visibility"] = visibility_path(output)
    cloud.stored.complete(
        files, {"points": points, "seconds": seconds, "views_without_maps": missing}
    )
    return FusionReport(output, points, seconds, False, cloud.fingerprint, missing)


def fuse_workspace(
    workspace: Workspace,
    fusion: FusionOptions,
    backend: str,
    output: str | Path,
    stereo_dir: str | Path | None = None,
    colmap_root: str | Path | None = None,
    reuse: bool = True,
    progress: bool = True,
    overwrite: bool = False,
) -> FusionReport:
    """Fuse the maps in ``stereo_dir`` (default the workspace's) into ``output`` and record what
    made the cloud beside it (``<cloud>.provenance.json``), outside a dense run. With ``reuse``,
    a cloud whose record carries the same fingerprint (the same maps, fusion options and code) is
    kept as it is. A file at ``output`` that dvpmvs did not write (no record: COLMAP's
    ``fused.ply``) is replaced only with ``overwrite`` (else
    :class:`dvpmvs.provenance.ForeignOutputError`). The masks of ``fusion.mask`` are made here
    (stored beside the maps, or reused from there)."""
    output = Path(output).expanduser()
    stereo = workspace.stereo_dir if stereo_dir is None else Path(stereo_dir)
    check_cloud_path(output)
    # The maps' folder is locked: a dense run writing maps there would change them under fusion
    # (a folder this process cannot write, nobody's dense run here can write either).
    maps_folder = stereo.parent
    with writer_lock(maps_folder) if os.access(maps_folder, os.W_OK) else nullcontext():
        if output.parent.resolve() == stereo.parent.resolve():
            remove_temporaries(output.parent, recursive=False)
        masks = MaskStore.from_config(fusion.mask, stereo, workspace.root)
        views = workspace.fusion_views(stereo)
        maps = _fused_maps(views, stereo, Pass(fusion.input_type))
        cloud = plan_cloud(workspace, stereo, fusion, backend, output, masks, views, maps)
        if reuse and cloud.stored.current is not None:
            log.info(cloud.explain(overwrite=False))
        return make_cloud(workspace, cloud, stereo, colmap_root, progress, reuse, overwrite, masks)


def check_cloud_path(output: Path) -> None:
    """The fused cloud's path must name a PLY file in a folder this process can write."""
    check_ply_output(output, "fused clouds", "fused.ply")


# Bytes per pixel of a fused cloud, at most: a point is 27 bytes and its visibility record about
# 16; a fused cloud has 0.1-0.4 points per pixel of its views (the suite's scenes), so 0.5 is an
# upper bound.
CLOUD_BYTES_PER_PIXEL = 0.5 * (27 + 16)


def cloud_bytes(workspace: Workspace) -> int:
    """An upper bound of the fused cloud's size on disk (with its ``.vis``)."""
    return int(CLOUD_BYTES_PER_PIXEL * sum(v.width * v.height for v in workspace.reference_views()))


def check_space(folder: Path, needed: int, what: str, hint: str) -> None:
    free = shutil.disk_usage(folder).free
    if needed > free:
        raise DenseError(
            f"{folder} is on a disk with {free / 2**20:,.1f} MB free; this run writes {what}: free some "
            f"space there, or {hint}"
        )


def fuse_to_file(
    workspace: Workspace,
    fusion: FusionOptions,
    backend: str,
    output: str | Path,
    progress: bool,
    stereo: Path,
    colmap_root: str | Path | None,
    masks: MaskStore,
    views: list[View],
) -> int:
    """Fuse the maps of ``views`` in ``stereo`` with ``backend`` (``dvpmvs`` or ``colmap``;
    COLMAP reads the workspace ``colmap_root``, default the workspace itself) into the PLY
    ``output``, applying ``masks`` (those of ``fusion.mask``); returns the number of points.
    Without a record: :func:`make_cloud` and :func:`fuse_workspace` keep one."""
    from tqdm import tqdm

    if backend not in FUSION_BACKENDS:
        raise ValueError(
            f"unknown fusion backend {backend!r}; choose {' or '.join(FUSION_BACKENDS)}"
        )
    if backend == "colmap":
        return fuse_with_colmap(
            workspace, output, fusion, root=colmap_root, masks=masks, views=views
        )
    with tqdm(
        total=len(views), desc="fusion", unit="view", disable=not progress, dynamic_ncols=True
    ) as bar:
        per_view = fuse_to_ply(
            workspace,
            output,
            fusion,
            stereo_dir=stereo,
            masks=masks,
            views=views,
            progress=lambda name: (bar.set_postfix_str(name), bar.update()),
        )
    points = sum(per_view.values())
    if not points:
        log.warning(empty_cloud_message(fusion, stereo, masks, views))
    return points
