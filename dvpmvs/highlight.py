"""Highlight perception (paper section 3.5): every view's corrected image and highlight mask.

The ``highlight`` provider (entry-point group ``dvpmvs.highlight_correctors``; ``none`` switches
highlight perception off) runs once per view, before the passes, and its outputs are stored as
``OUT/stereo/highlights/<image>.corrected.bin`` (grey, [0, 1]) and ``<image>.mask.bin`` (1 in
the highlight) in COLMAP's map format, with a record ``stereo/provenance/<image>.highlight.json``:
a rerun reuses them only when the image, the provider (config, plugin code, the files it reads)
and dvpmvs's code are the same. The estimator reads them for the view as reference and as a
source (:class:`~dvpmvs.patchmatch.problem.ViewData`'s ``corrected`` and ``highlight``); what it
does with them is ``PatchMatchOptions``' ``highlight_*`` rules.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from dvpmvs.maps import MapFormatError, read_extra_map, write_extra_map
from dvpmvs.priors import PriorContext, PriorError
from dvpmvs.provenance import (Record, code_identity, file_digest, fingerprint, pending_record, read_record,
                               record_path, stamp_files, status, write_record)

__all__ = ["HighlightMaps", "HighlightStage", "highlight_config", "check_highlight_output"]

log = logging.getLogger(__name__)

HIGHLIGHT_DIR = "highlights"
_PASS_NAME = "highlight"  # the records' suffix: stereo/provenance/<image>.highlight.json


@dataclass
class HighlightMaps:
    """One view's highlight outputs: the grey image to match (float32 (H, W) in [0, 1]) and the
    highlight mask ((H, W) bool)."""

    corrected: np.ndarray
    mask: np.ndarray


def highlight_config(config: Mapping[str, Any] | str | None) -> dict | None:
    """The provider's config as a dict, or None when highlight perception is off (no config,
    or ``name: none``)."""
    if config is None:
        return None
    config = {"name": config} if isinstance(config, str) else dict(config)
    return None if config.get("name") in (None, "none") else config


def check_highlight_output(name: str, view: str, corrected: Any, mask: Any,
                           shape: tuple[int, int]) -> HighlightMaps:
    """A provider's (corrected image, mask) checked: shapes, finite values in [0, 1]; the error
    names the provider and the view."""
    corrected = np.asarray(corrected)
    mask = np.asarray(mask)
    for what, array in (("corrected image", corrected), ("mask", mask)):
        if array.shape != shape:
            raise PriorError(f"highlight provider {name!r} returned a {what} of shape {array.shape} for view "
                             f"{view}, expected {shape} (the view's grey image)")
    corrected = corrected.astype(np.float32, copy=False)
    bad = int((~np.isfinite(corrected)).sum())
    if bad:
        raise PriorError(f"highlight provider {name!r} returned {bad} NaN or infinite value(s) in the corrected "
                         f"image of view {view}")
    if corrected.size and (corrected.min() < -1e-3 or corrected.max() > 1 + 1e-3):
        raise PriorError(f"highlight provider {name!r} returned a corrected image of view {view} outside [0, 1] "
                         f"({corrected.min():.3g} to {corrected.max():.3g}); grey levels are in [0, 1]")
    if mask.dtype != bool:
        if not np.isfinite(mask.astype(np.float64)).all():
            raise PriorError(f"highlight provider {name!r} returned NaN in the mask of view {view}")
        mask = mask > 0.5
    return HighlightMaps(np.clip(corrected, 0, 1), mask)


class HighlightStage:
    """The highlight provider of a run and the stored outputs it made in ``stereo``."""

    def __init__(self, workspace, stereo: Path, config: Mapping[str, Any]):
        from dvpmvs import registry

        self.workspace, self.stereo = workspace, Path(stereo)
        self.config = dict(config)
        self.name = str(self.config["name"])
        self.provider = registry.create("highlight", self.config)
        self._plugin = registry.plugin_identity("highlight", self.name)
        self._fingerprints: dict[str, str] = {}

    def files(self, view_name: str) -> dict[str, Path]:
        folder = self.stereo / HIGHLIGHT_DIR
        return {"corrected": folder / f"{view_name}.corrected.bin", "mask": folder / f"{view_name}.mask.bin"}

    def inputs(self, view_name: str) -> dict:
        """What a view's highlight outputs depend on: its image (digest, size), the provider
        (config, plugin, the files it reads for the view) and the code."""
        view = self.workspace[view_name]
        files = getattr(self.provider, "input_files", None)
        read = [] if files is None else [Path(p) for p in files(view_name, self.workspace.root)]
        return {"stage": _PASS_NAME, "code": code_identity(), "image": file_digest(view.path),
                "size": [view.width, view.height], "config": self.config, "plugin": self._plugin,
                "files": {str(p): file_digest(p) for p in read}}

    def fingerprint(self, view_name: str) -> str:
        if view_name not in self._fingerprints:
            self._fingerprints[view_name] = fingerprint(self.inputs(view_name))
        return self._fingerprints[view_name]

    def prepare(self, view_names, overwrite: bool = False, progress: bool = False,
                previews: bool = False) -> dict[str, float]:
        """Make the outputs of every view of ``view_names`` not current; returns the seconds each
        computed view took (reused views are not in it)."""
        from tqdm import tqdm

        seconds = {}
        names = list(dict.fromkeys(view_names))
        for name in tqdm(names, desc="highlights", unit="view", disable=not progress, dynamic_ncols=True):
            path = record_path(self.stereo, name, _PASS_NAME)
            record = read_record(path)
            fp = self.fingerprint(name)
            files = self.files(name)
            if not overwrite and status(record, fp, self.stereo, files.values()).reusable:
                continue
            start = time.perf_counter()
            with pending_record(path, fp, self.inputs(name), record):
                maps = self.compute(name)
                write_extra_map(files["corrected"], maps.corrected)
                write_extra_map(files["mask"], maps.mask.astype(np.uint8))
            seconds[name] = time.perf_counter() - start
            extras = []
            if previews:
                from dvpmvs.preview import write_png
                preview = self.stereo / "previews" / f"{name}.highlight.png"
                write_png(preview, _overlay(maps))
                extras.append(preview.relative_to(self.stereo).as_posix())
            write_record(path, Record(fp, self.inputs(name), complete=True, files=stamp_files(self.stereo, files),
                                      extras=extras, stats={"seconds": seconds[name],
                                                            "mask_fraction": float(maps.mask.mean())}))
            log.debug("view %s: highlight mask %.2f %% of the image (%.2f s)", name, 100 * maps.mask.mean(),
                      seconds[name])
        return seconds

    def compute(self, view_name: str) -> HighlightMaps:
        """Run the provider on one view (nothing stored)."""
        view = self.workspace[view_name]
        ctx = PriorContext(view.name, view.load_grey(), view.K, view.depth_range,
                           self.workspace.sparse_points(view.name), rgb_loader=view.load_rgb,
                           root=self.workspace.root)
        try:
            corrected, mask = self.provider(ctx)
        except PriorError:
            raise
        except (ValueError, RuntimeError) as exc:
            raise PriorError(f"highlight provider {self.name!r} failed on view {view_name}: {exc}") from exc
        return check_highlight_output(self.name, view_name, corrected, mask, ctx.shape)

    def load(self, view_name: str) -> HighlightMaps:
        """The stored outputs of a view (made by :meth:`prepare`)."""
        files = self.files(view_name)
        try:
            corrected = read_extra_map(files["corrected"])
            mask = read_extra_map(files["mask"]) > 0.5
        except (OSError, MapFormatError) as exc:
            raise PriorError(f"the highlight outputs of view {view_name} cannot be read ({exc}); rerun, or "
                             f"delete {files['corrected'].parent} to make them again") from exc
        return HighlightMaps(corrected, mask)

    def seconds(self, view_name: str) -> float:
        """The seconds the provider took for a view, from its record (0 when unknown)."""
        record = read_record(record_path(self.stereo, view_name, _PASS_NAME))
        return float(record.stats.get("seconds", 0.0)) if record is not None else 0.0


def _overlay(maps: HighlightMaps) -> np.ndarray:
    """A preview: the corrected image in grey, the mask's pixels tinted red (BGR uint8)."""
    grey = np.clip(maps.corrected * 255, 0, 255).astype(np.uint8)
    out = np.repeat(grey[..., None], 3, axis=2)
    out[maps.mask, 2] = np.maximum(out[maps.mask, 2], 200)
    out[maps.mask, :2] //= 2
    return out
