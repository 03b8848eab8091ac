"""Each view's mask made once and kept: ``OUT/stereo/mask_maps/<image>.png`` with its record.

The mask provider (:class:`dvpmvs.masks.ViewMasks`) may be a network: the estimator's passes
and fusion read the stored mask instead of asking the provider again, so a view's mask is made
once per run, and a rerun with the same provider (config, plugin code, the files it reads) and
view size reuses it
(``stereo/provenance/<image>.mask.json``, the same record scheme as the maps'). The files are in
COLMAP's mask layout (8-bit PNG named after the image, 0 where the pixel is masked), so that
``colmap stereo_fusion --StereoFusion.mask_path OUT/stereo/mask_maps`` reads them as they are.

Where the maps' folder cannot be written (``dvpmvs fuse`` on another's workspace), the masks are
made once per process and kept in memory instead.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np

from dvpmvs.maps import atomic_path
from dvpmvs.masks import MaskError, MaskView, ViewMasks
from dvpmvs.provenance import CachedOutput

__all__ = ["MASK_DIR", "MaskStore", "mask_path"]

log = logging.getLogger(__name__)

MASK_DIR = "mask_maps"
_RECORD = "mask"  # stereo/provenance/<image>.mask.json


def mask_path(stereo: str | Path, image_name: str) -> Path:
    """``stereo/mask_maps/<image>.png`` (COLMAP's ``mask_path`` layout)."""
    return Path(stereo) / MASK_DIR / f"{image_name}.png"


class MaskStore:
    """The masks of ``masks``'s provider for the views of the workspace at ``root``, kept in the
    maps' folder ``stereo`` (in memory where it cannot be written)."""

    def __init__(
        self, masks: ViewMasks, stereo: str | Path, root: Path | None, overwrite: bool = False
    ):
        self.masks, self.stereo, self.root = masks, Path(stereo), root
        self.overwrite = overwrite
        self._kept: dict[str, np.ndarray] = {}
        self._writable: bool | None = None

    @classmethod
    def from_config(
        cls, config, stereo: str | Path, root: Path | None, overwrite: bool = False
    ) -> MaskStore:
        """The store of the provider the ``mask`` config names (none: every pixel kept)."""
        return cls(ViewMasks.from_config(config), stereo, root, overwrite)

    @property
    def active(self) -> bool:
        return self.masks.active

    def prepare(self, views: Sequence[MaskView]) -> None:
        """Make (or reuse) the masks before any view is computed, so that a missing or broken
        mask stops the run there (:class:`MaskError`): every view's, or where the provider's
        masks are costly (``costly = True``: a network) the first view's, its check; the others'
        are made when their views are computed."""
        for view in self.masks.checked_first(views):
            self.load(view)

    def check(self, view: MaskView) -> CachedOutput:
        """The view's stored mask against its record: current, or to be made."""
        return CachedOutput.of_view(
            self.stereo,
            view.name,
            _RECORD,
            self._inputs(view),
            {"mask": mask_path(self.stereo, view.name)},
        )

    def load(self, view: MaskView, stored: CachedOutput | None = None) -> np.ndarray | None:
        """The view's keep mask, (height, width) bool: read where stored for the same inputs,
        else made by the provider and stored; None without a provider. ``stored``: its
        :meth:`check`, where the caller made it."""
        if not self.active:
            return None
        if view.name in self._kept:
            return self._kept[view.name]
        if not self._can_write():
            keep = self._kept[view.name] = self.masks.mask(view, self.root)
            return keep
        path = mask_path(self.stereo, view.name)
        cached = stored if stored is not None else self.check(view)
        if cached.current is not None:
            kept = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
            if kept is not None and kept.shape == (view.height, view.width):
                return kept > 0
            log.warning("the stored mask %s is unreadable: made again", path)
        keep = self.masks.mask(view, self.root)
        # A file at this path that dvpmvs did not write is replaced only with ``overwrite``.
        with cached.making(self.overwrite):
            path.parent.mkdir(parents=True, exist_ok=True)
            with atomic_path(path, suffix=".tmp.png") as tmp:
                if not cv2.imwrite(str(tmp), keep.astype(np.uint8) * 255):
                    raise MaskError(f"could not write the mask {path}")
        cached.complete({"mask": path}, {"kept": float(keep.mean())})
        return keep

    def _inputs(self, view: MaskView) -> dict:
        """What a view's mask depends on: the provider's inputs for it, and the view's size."""
        return {
            "stage": _RECORD,
            "mask": self.masks.provenance(view.name, self.root),
            "size": [view.height, view.width],
        }

    def stored_folder(self, views: Sequence[MaskView]) -> Path | None:
        """The folder holding every view's mask in COLMAP's layout, made where missing; None
        where they cannot be stored (then the caller writes its own copy)."""
        for view in views:
            self.load(view)
        return self.stereo / MASK_DIR if self.active and self._can_write() else None

    def _can_write(self) -> bool:
        if self._writable is None:
            folder = self.stereo if self.stereo.is_dir() else self.stereo.parent
            self._writable = os.access(folder, os.W_OK)
        return self._writable
