"""Masks from files, in COLMAP's layout or OpenMVS's.

- ``layout=colmap`` (COLMAP's ``StereoFusion.mask_path`` and ``ImageReader.mask_path``):
  ``<path>/<image name>.png`` (or ``<path>/<image name>`` when the name already ends in ``.png``),
  read as grey, box-resized to the view (``cv2.INTER_AREA``), and a pixel whose value is 0 is
  masked.
- ``layout=openmvs`` (``DensifyPointCloud --mask-path DIR --ignore-mask-label L``):
  ``<path>/<image stem>.mask.png``, 8- or 16-bit labels resized by nearest neighbour, and a pixel
  whose label is ``ignore_label`` is masked.

A mask of another aspect ratio than its view is refused with both sizes; a missing mask is an
error naming the paths looked for, unless ``allow_missing`` (the view is then unmasked).
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from dvpmvs.masks import MaskError

__all__ = ["FileMasks", "LAYOUTS", "make_files"]

LAYOUTS = ("colmap", "openmvs")
_ASPECT_TOLERANCE = 0.01  # relative: image_undistorter's rounding moves a side by a pixel


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
        if not isinstance(ignore_label, int) or ignore_label < 0:
            raise ValueError(
                f"mask.ignore_label must be a label (an integer >= 0), got {ignore_label!r}"
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
            return [folder / f"{Path(view_name).stem}.mask.png"]
        names = [f"{view_name}.png"] + ([view_name] if view_name.lower().endswith(".png") else [])
        return [folder / name for name in names]

    def input_files(self, view_name: str, root: Path | None) -> list[Path]:
        return [p for p in self.candidates(view_name, root) if p.is_file()][:1]

    def __call__(self, view, root: Path | None) -> np.ndarray:
        view_name, shape = view.name, (view.height, view.width)
        found = self.input_files(view_name, root)
        if not found:
            if self.allow_missing:
                return np.ones(shape, bool)
            looked = " or ".join(str(p) for p in self.candidates(view_name, root))
            raise MaskError(
                f"no mask for image {view_name}: {looked} does not exist; add it, or give "
                f"mask.allow_missing=true to keep every pixel of images without one"
            )
        path = found[0]
        flags = cv2.IMREAD_UNCHANGED if self.layout == "openmvs" else cv2.IMREAD_GRAYSCALE
        data = np.fromfile(path, np.uint8)
        mask = cv2.imdecode(data, flags) if data.size else None
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
            mask = mask[..., 0]
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
