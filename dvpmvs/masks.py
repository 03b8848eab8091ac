"""Per-view masks: which pixels of a view are kept (sky, background, moving things left out).

A mask provider is a plugin (entry-point group ``dvpmvs.masks``, Hydra group ``mask``) built from
its config and called once per view, as ``provider(view, root)`` (``view``: its ``name``,
``height``, ``width`` and ``load_rgb()``), returning a boolean "keep" array of the view's size
(False: masked). Like a prior provider, one that reads files names them in
``input_files(view_name, root)``: their contents join the maps' provenance, so a changed mask
recomputes the views it touches and nothing else. Before any view is computed, the core makes
every view's mask, to stop at a missing or broken one there; a provider whose masks are costly
to make (a network) sets ``costly = True``, and only the first view's is made then, the others
when their views are computed. The dense stage keeps each mask it made
(:mod:`dvpmvs.dense.masks`), so a provider is asked once per view and run.

The core checks every mask (shape, type, a view left with no pixel is a warning) and applies it in
every stage: the estimator never estimates a masked pixel (nor takes it as an anchor, a planar
prior's support or a propagation source, all of which need a depth), and fusion neither starts at
nor takes one. ``mask=none`` (the default) keeps every pixel.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from dvpmvs.errors import DvpmvsError

__all__ = ["MaskError", "MaskProvider", "MaskView", "ViewMasks", "mask_config"]

log = logging.getLogger(__name__)


class MaskError(DvpmvsError, ValueError):
    """A mask is missing, unreadable, of another aspect ratio, or a provider broke the contract."""


class MaskView(Protocol):
    """What a provider sees of a view: its image name, its size as the dense stage sees it, and
    its pixels (float32 RGB in [0, 1], (height, width, 3))."""

    name: str
    height: int
    width: int

    def load_rgb(self) -> np.ndarray: ...


class MaskProvider(Protocol):
    """``provider(view, root) -> (view.height, view.width) bool``: True where the view's pixel is
    kept. ``root``: the workspace folder (a relative mask folder or model resolves against it)."""

    def __call__(self, view: MaskView, root: Path | None) -> np.ndarray: ...


def mask_config(cfg: Any) -> dict | None:
    """The ``mask`` config as a plain dict, or None for none (absent, null, ``name: none``)."""
    if cfg is None:
        return None
    values = {"name": cfg} if isinstance(cfg, str) else dict(cfg)
    return None if values.get("name") in (None, "none") else values


@dataclass
class ViewMasks:
    """The mask provider in use (built from ``config``; none: every pixel kept)."""

    config: dict | None = None
    provider: MaskProvider | None = field(default=None, repr=False)

    @classmethod
    def from_config(cls, config: Mapping[str, Any] | None) -> ViewMasks:
        from dvpmvs import registry

        config = mask_config(config)
        if config is None:
            return cls()
        return cls(config, registry.create("mask", config))

    @property
    def active(self) -> bool:
        return self.provider is not None

    def mask(self, view: MaskView, root: Path | None = None) -> np.ndarray | None:
        """The view's keep mask (height, width) bool, checked; None without a provider."""
        if self.provider is None:
            return None
        name, view_name, shape = self.config["name"], view.name, (view.height, view.width)
        try:
            keep = self.provider(view, root)
        except MaskError:
            raise
        except (OSError, ValueError) as exc:
            raise MaskError(f"mask provider {name!r} failed on view {view_name}: {exc}") from exc
        keep = np.asarray(keep)
        if keep.shape != tuple(shape):
            raise MaskError(
                f"mask provider {name!r} returned a {keep.shape} mask for view {view_name}, whose size is "
                f"{tuple(shape)} (height, width)"
            )
        if keep.dtype != bool:
            raise MaskError(
                f"mask provider {name!r} returned a {keep.dtype} mask for view {view_name}; a mask is "
                f"boolean (True: keep the pixel)"
            )
        if not keep.any():
            log.warning("the mask of view %s keeps no pixel: it gets no depth", view_name)
        return keep

    def checked_first(self, views: Sequence[MaskView]) -> Sequence[MaskView]:
        """The views whose masks are made before any compute, as a check: all of them, or the
        first one where the provider's masks are costly (``costly = True``)."""
        if self.provider is None:
            return []
        return views[:1] if getattr(self.provider, "costly", False) else views

    def check(self, views: Sequence[MaskView], root: Path | None = None) -> None:
        """Raise :class:`MaskError` now where a mask cannot be made (missing, unreadable, another
        aspect ratio, a model that gives no class map): the masks of :meth:`checked_first`."""
        for view in self.checked_first(views):
            self.mask(view, root)

    def provenance(self, view_name: str, root: Path | None = None) -> dict | None:
        """What the view's mask depends on: the config, the plugin implementing it and the
        SHA-256 of every file it reads for the view; None without a provider."""
        if self.provider is None:
            return None
        from dvpmvs import registry
        from dvpmvs.digests import file_digest

        files = getattr(self.provider, "input_files", None)
        paths = [] if files is None else [Path(p) for p in files(view_name, root)]
        return {
            "config": self.config,
            "plugin": registry.plugin_identity("mask", self.config["name"]),
            "files": {str(p): file_digest(p) for p in paths},
        }
