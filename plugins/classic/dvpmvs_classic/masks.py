"""Masks from files, in COLMAP's layout or OpenMVS's.

- ``layout=colmap`` (COLMAP's ``StereoFusion.mask_path`` and ``ImageReader.mask_path``):
  ``<path>/<image name>.png`` (or ``<path>/<image name>`` when the name already ends in ``.png``),
  read as grey (8- or 16-bit, its full value), box-resized to the view (``cv2.INTER_AREA``), and
  a pixel whose value is 0 is masked.
- ``layout=openmvs`` (``DensifyPointCloud --mask-path DIR --ignore-mask-label L``):
  ``<path>/<image stem>.mask.png`` (``<path>/a/<stem>.mask.png`` for an image ``a/x.png``), 8- or
  16-bit labels resized by nearest neighbour, and a pixel whose label is ``ignore_label`` is
  masked.

A mask of another aspect ratio than its view is refused with both sizes; a missing mask is an
error naming the paths looked for, unless ``allow_missing`` (the view is then unmasked, with a
warning naming it); a ``path`` that is not a folder, or a mask that is a folder or a symbolic
link to no file, is always an error.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

import cv2
import numpy as np

from dvpmvs.masks import MaskError

__all__ = ["FileMasks", "LAYOUTS", "make_files"]

log = logging.getLogger(__name__)

LAYOUTS = ("colmap", "openmvs")
_ASPECT_TOLERANCE = 0.01  # relative: image_undistorter's rounding moves a side by a pixel
_MAX_LABEL = 65535  # masks are 8- or 16-bit images


class FileMasks:
    """Per-view masks from the folder ``path`` (relative: to the workspace)."""

    def __init__(
        self,
        path: str | None = None,
        layout: str = "colmap",
        ignore_label: int = 0,
        allow_missing: bool = False,
    ):
        if not path:
            raise ValueError("mask=files needs mask.path=DIR, the folder of the masks")
        if layout not in LAYOUTS:
            raise ValueError(f"mask.layout must be one of {', '.join(LAYOUTS)}, got {layout!r}")
        if not isinstance(ignore_label, int) or not 0 <= ignore_label <= _MAX_LABEL:
            raise ValueError(
                f"mask.ignore_label must be a label of an 8- or 16-bit mask (an integer from 0 "
                f"to {_MAX_LABEL}), got {ignore_label!r}"
            )
        if layout == "colmap" and ignore_label != 0:
            raise ValueError(
                "mask.ignore_label is for mask.layout=openmvs (COLMAP's masks exclude the value 0)"
            )
        self.path, self.layout, self.ignore_label, self.allow_missing = (
            path,
            layout,
            ignore_label,
            allow_missing,
        )

    def folder(self, root: Path | None) -> Path:
        folder = Path(self.path).expanduser()
        return folder if folder.is_absolute() or root is None else Path(root) / folder

    def candidates(self, view_name: str, root: Path | None) -> list[Path]:
        """The files looked for, in order."""
        folder = self.folder(root)
        if self.layout == "openmvs":
            # In the image's subfolder (as COLMAP's layout keeps it): a/x.png and b/x.png are two
            # images with two masks.
            name = Path(view_name)
            return [folder / name.parent / f"{name.stem}.mask.png"]
        names = [f"{view_name}.png"] + ([view_name] if view_name.lower().endswith(".png") else [])
        return [folder / name for name in names]

    def input_files(self, view_name: str, root: Path | None) -> list[Path]:
        return [p for p in self.candidates(view_name, root) if p.is_file()][:1]

    def __call__(self, view, root: Path | None) -> np.ndarray:
        view_name, shape = view.name, (view.height, view.width)
        folder = self.folder(root)
        if not folder.is_dir():
            raise MaskError(
                f"mask.path={self.path}: {folder} "
                f"{'is not a folder' if folder.exists() else 'does not exist'}; mask.path names "
                f"the folder of the masks"
            )
        for candidate in self.candidates(view_name, root):
            if os.path.lexists(candidate) and not candidate.is_file():
                what = "a folder" if candidate.is_dir() else "a symbolic link to no file"
                raise MaskError(f"the mask {candidate} is {what}, not an image")
        found = self.input_files(view_name, root)
        if not found:
            if self.allow_missing:
                log.warning(
                    "no mask for image %s in %s: every pixel kept (mask.allow_missing=true)",
                    view_name,
                    folder,
                )
                return np.ones(shape, bool)
            looked = " or ".join(str(p) for p in self.candidates(view_name, root))
            raise MaskError(
                f"no mask for image {view_name}: {looked} does not exist; add it, or give "
                f"mask.allow_missing=true to keep every pixel of images without one"
            )
        path = found[0]
        # Unchanged: a 16-bit mask keeps its values (a grey conversion keeps the high byte).
        data = np.fromfile(path, np.uint8)
        mask = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data.size else None
        if mask is None or mask.size == 0:
            raise MaskError(
                f"the mask {path} cannot be read as an image (corrupt, or not an image file)"
            )
        if mask.ndim == 3:
            if self.layout == "openmvs":
                raise MaskError(
                    f"the mask {path} has {mask.shape[2]} channels; OpenMVS's masks are one channel "
                    f"of labels"
                )
            # COLMAP reads a colour mask as its grey level.
            code = cv2.COLOR_BGRA2GRAY if mask.shape[2] == 4 else cv2.COLOR_BGR2GRAY
            mask = cv2.cvtColor(mask, code)
        if self.layout == "openmvs" and self.ignore_label > np.iinfo(mask.dtype).max:
            raise MaskError(
                f"the mask {path} is {8 * mask.dtype.itemsize}-bit: mask.ignore_label="
                f"{self.ignore_label} cannot occur in it, so it would mask nothing"
            )
        height, width = shape
        mh, mw = mask.shape
        if abs((mw / mh) / (width / height) - 1) > _ASPECT_TOLERANCE:
            raise MaskError(
                f"the mask {path} is {mw}x{mh} but image {view_name} is {width}x{height} here: another "
                f"aspect ratio (a mask of another image, or of the image before undistortion?)"
            )
        if self.layout == "openmvs":
            labels = (
                cv2.resize(mask, (width, height), interpolation=cv2.INTER_NEAREST)
                if (mh, mw) != shape
                else mask
            )
            return labels != self.ignore_label
        values = (
            cv2.resize(mask, (width, height), interpolation=cv2.INTER_AREA)
            if (mh, mw) != shape
            else mask
        )
        return values != 0


def make_files(params: dict) -> FileMasks:
    return FileMasks(**params)
