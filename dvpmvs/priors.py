"""Per-view priors: depth, normal, edge and highlight providers, and what the core does with them.

Providers are plugins (entry-point groups of :mod:`dvpmvs.registry`); each is a callable built
from its Hydra config and called once per reference view with a :class:`PriorContext`:

- depth prior ``provider(ctx) -> DepthPrior`` (depth, validity, whether it is metric);
- normal prior ``provider(ctx, depth) -> (H, W, 3)`` unit normals in the camera frame (``depth``:
  the aligned depth prior, for providers that derive normals from it; such a provider sets the
  class attribute ``derived_from_depth = True``, and the segmentation then does not add the
  depth-edge rule to its normals);
- edge detector ``detector(ctx) -> (H, W) bool``;
- highlight corrector ``corrector(ctx) -> (corrected grey image, (H, W) bool mask)``: run once per
  view by :mod:`dvpmvs.highlight` (its outputs serve the view as reference and as source).

A provider that reads files (per-view priors, model weights) names them in an optional method
``input_files(view_name, root) -> list of paths``: their contents join the maps' provenance, so
that a changed prior file or model recomputes the views it shapes (:meth:`PriorProviders.provenance`).

The core checks every output (shape, NaN, range) and names the plugin that broke the contract;
a depth prior that is not metric is aligned to the view's sparse points (robust scale and shift,
:func:`align_to_sparse`) before use. :func:`compute_priors` runs the providers for one view.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from dvpmvs.errors import DvpmvsError

__all__ = [
    "PriorError",
    "PriorContext",
    "DepthPrior",
    "DepthPriorProvider",
    "NormalPriorProvider",
    "EdgeDetector",
    "ReadsFiles",
    "ViewPriors",
    "PriorProviders",
    "align_to_sparse",
    "face_camera",
    "read_prior_array",
    "fit_prior_to_view",
    "compute_priors",
]

log = logging.getLogger(__name__)


class PriorError(DvpmvsError, ValueError):
    """A prior provider failed or returned something unusable (wrong shape, NaN, no valid pixel)."""


@dataclass
class PriorContext:
    """What a provider may use for one reference view.

    image: grey float32 (H, W) in [0, 1]; rgb: float32 (H, W, 3) in [0, 1] (lazy, may be None).
    K: (3, 3) intrinsics of the image at this size; depth_range: the view's (min, max) depth.
    sparse: (N, 3) float64 ``[col, row, depth]`` of the sparse points this view observes.
    root: the workspace folder (relative paths of file providers resolve against it).
    low_resolution_depth: where the view's sources are at hand (a dense run), the estimator's
    filtered photometric depth of this view at low resolution, as
    ``low_resolution_depth(max_size=, num_scales=, num_iterations=, max_cost=, max_sources=)``
    (:func:`dvpmvs.patchmatch.low_resolution.low_resolution_depth`; 0: no depth); None elsewhere.
    """

    name: str
    image: np.ndarray
    K: np.ndarray
    depth_range: tuple[float, float]
    sparse: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    rgb_loader: Callable[[], np.ndarray] | None = None
    root: Path | None = None
    low_resolution_depth: Callable[..., np.ndarray] | None = None

    @property
    def shape(self) -> tuple[int, int]:
        return self.image.shape  # type: ignore[return-value]

    def rgb(self) -> np.ndarray:
        if self.rgb_loader is None:
            return np.repeat(self.image[..., None], 3, axis=2)
        return self.rgb_loader()


@dataclass
class DepthPrior:
    """depth (H, W) float32; valid (H, W) bool; metric: False for depth known up to scale and
    shift (relative monocular depth), which the core aligns to the sparse points; inverse: the
    array holds inverse depth (disparity-like network outputs), so a relative one is aligned
    in inverse depth, where its unknown shift lives, and a metric one is simply inverted."""

    depth: np.ndarray
    valid: np.ndarray | None = None
    metric: bool = True
    inverse: bool = False


class DepthPriorProvider(Protocol):
    """A ``depth_prior`` plugin (entry-point group ``dvpmvs.depth_priors``): the view's depth.

    Parameters
    ----------
    ctx : PriorContext
        The view: its grey image, intrinsics, depth range and sparse points.

    Returns
    -------
    DepthPrior
        The depth at the image's size, metric or relative (aligned by the core to the sparse
        points), with an optional mask of valid pixels.
    """

    def __call__(self, ctx: PriorContext) -> DepthPrior: ...


class NormalPriorProvider(Protocol):
    """A ``normal_prior`` plugin (entry-point group ``dvpmvs.normal_priors``). A class attribute
    ``derived_from_depth = True`` says the normals are computed from the depth prior.

    Parameters
    ----------
    ctx : PriorContext
        The view.
    depth : numpy.ndarray or None
        The view's depth prior, (H, W) float32, aligned; None without one.

    Returns
    -------
    numpy.ndarray
        (H, W, 3) float32 unit normals in the camera frame, facing the camera; (0, 0, 0) where
        there is none.
    """

    def __call__(self, ctx: PriorContext, depth: np.ndarray | None) -> np.ndarray: ...


class EdgeDetector(Protocol):
    """An ``edge`` plugin (entry-point group ``dvpmvs.edge_detectors``).

    Parameters
    ----------
    ctx : PriorContext
        The view.

    Returns
    -------
    numpy.ndarray
        (H, W) bool: the view's edge map.
    """

    def __call__(self, ctx: PriorContext) -> np.ndarray: ...


class ReadsFiles(Protocol):
    """Optional for any provider: the files it reads for a view, whose digests join the maps'
    provenance (a changed file recomputes exactly the views that read it).

    Parameters
    ----------
    view_name : str
        The view's image name.
    root : pathlib.Path or None
        The workspace folder, against which relative paths resolve.

    Returns
    -------
    list of pathlib.Path
        The files the provider reads for that view.
    """

    def input_files(self, view_name: str, root: Path | None) -> list[Path]: ...


@dataclass
class ViewPriors:
    """The priors of one view at the estimator's full resolution. Any of them may be None
    (its provider switched off)."""

    depth: np.ndarray | None = None
    depth_valid: np.ndarray | None = None
    normal: np.ndarray | None = None
    normal_from_depth: bool = False  # the normal provider derived its normals from ``depth``
    edges: np.ndarray | None = None
    seconds: dict[str, float] = field(default_factory=dict)


@dataclass
class PriorProviders:
    """The providers in use (None: switched off) and their configured names (for messages)."""

    depth: DepthPriorProvider | None = None
    normal: NormalPriorProvider | None = None
    edge: EdgeDetector | None = None
    names: dict[str, str] = field(default_factory=dict)
    configs: dict[str, dict] = field(default_factory=dict)  # slot -> the config it was built from

    @classmethod
    def from_configs(cls, configs: Mapping[str, Any]) -> PriorProviders:
        """Build from ``{"depth_prior": cfg, "normal_prior": cfg, "edge": cfg}`` (other keys, such
        as ``highlight``, are :mod:`dvpmvs.highlight`'s); a missing or null entry (or ``name:
        none``) switches that provider off."""
        from dvpmvs import registry

        built, names, used = {}, {}, {}
        for kind, slot in _SLOTS:
            cfg = configs.get(kind)
            if cfg is None:
                continue
            name = cfg if isinstance(cfg, str) else dict(cfg).get("name")
            if name in (None, "none"):
                continue
            built[slot] = registry.create(kind, cfg)
            names[slot] = str(name)
            used[slot] = {"name": cfg} if isinstance(cfg, str) else dict(cfg)
        return cls(**built, names=names, configs=used)

    def provenance(self, view_name: str, root: Path | None = None) -> dict:
        """What the providers' outputs for one view depend on: per provider its config, the
        plugin that implements it (distribution, version, digest of its sources) and the SHA-256
        of every file it reads for the view (``input_files``)."""
        from dvpmvs import registry
        from dvpmvs.digests import file_digest

        found = {}
        for kind, slot in _SLOTS:
            provider = getattr(self, slot)
            if provider is None:
                continue
            files = getattr(provider, "input_files", None)
            paths = [] if files is None else [Path(p) for p in files(view_name, root)]
            found[kind] = {
                "config": self.configs.get(slot, {}),
                "plugin": registry.plugin_identity(kind, self.names[slot]),
                "files": {str(p): file_digest(p) for p in paths},
            }
        return found


_SLOTS = (("depth_prior", "depth"), ("normal_prior", "normal"), ("edge", "edge"))


def read_prior_array(path: str | Path) -> np.ndarray:
    """A prior stored as ``.npy``, ``.pfm`` or a COLMAP map (``.bin``), as float32 (H, W[, C])."""
    path = Path(path)
    suffix = path.suffix.lower()
    try:
        if suffix == ".npy":
            return np.asarray(np.load(path, allow_pickle=False), np.float32)
        if suffix == ".pfm":
            return _read_pfm(path)
        if suffix == ".bin":
            from dvpmvs.maps import read_extra_map

            return read_extra_map(path)
    except (OSError, ValueError) as exc:
        raise PriorError(f"cannot read the prior {path}: {exc}") from exc
    raise PriorError(f"unsupported prior file {path}: use .npy, .pfm or a COLMAP .bin map")


def fit_prior_to_view(
    array: np.ndarray, shape: tuple[int, int], path: str | Path, resize: bool = False
) -> np.ndarray:
    """A prior read from ``path`` brought to the view's (height, width) ``shape``.

    A prior of the image at another resolution (the same aspect ratio, to a pixel: for example
    computed on the full-size image of a view downscaled by ``max_image_size``) is resized. Any
    other shape (cropped, transposed, a network's square output) is an error naming the file and
    both shapes, unless ``resize``: then it is stretched to the view as asked.
    """
    import cv2

    h, w = shape
    ph, pw = array.shape[:2]
    if (ph, pw) == (h, w):
        return array
    same_aspect = abs(pw * h / ph - w) <= 1.0 and abs(ph * w / pw - h) <= 1.0
    if not (same_aspect or resize):
        raise PriorError(
            f"{path}: the prior is {pw}x{ph} but the view is {w}x{h} (another aspect ratio: not a "
            f"prior of this image at another size); give a prior of the view's image, or set the "
            f"provider's resize=true to stretch it"
        )
    return cv2.resize(array, (w, h), interpolation=cv2.INTER_LINEAR)


def _read_pfm(path: Path) -> np.ndarray:
    with open(path, "rb") as f:
        kind = f.readline().strip()
        if kind not in (b"Pf", b"PF"):
            raise ValueError("not a PFM file (header must be Pf or PF)")
        dims = f.readline().split()
        if len(dims) != 2:
            raise ValueError("malformed PFM size line")
        width, height = int(dims[0]), int(dims[1])
        scale = float(f.readline().strip())
        channels = 3 if kind == b"PF" else 1
        data = np.frombuffer(f.read(), dtype="<f4" if scale < 0 else ">f4")
    if data.size != width * height * channels:
        raise ValueError(
            f"PFM holds {data.size} values, its header says {width}x{height}x{channels}"
        )
    # PFM rows run bottom to top.
    array = data.reshape(height, width, channels)[::-1]
    return np.ascontiguousarray(array[..., 0] if channels == 1 else array, np.float32)


def align_to_sparse(
    depth: np.ndarray,
    sparse: np.ndarray,
    inverse: bool = False,
    valid: np.ndarray | None = None,
    pairs: int = 20000,
    iterations: int = 10,
    seed: int = 0,
) -> tuple[np.ndarray, float, float]:
    """Scale and shift a relative depth map onto the sparse points, robustly: the Theil-Sen
    estimate (median slope of random point pairs, median intercept), then Tukey-weighted least
    squares (``iterations`` rounds). ``inverse``: the map is inverse depth
    (disparity-like), aligned in inverse depth and returned as depth. ``valid``: (H, W) mask of
    the prior's pixels with a value; sparse points elsewhere are ignored.
    Returns (aligned depth, scale, shift).

    Why not RANSAC with a fixed relative inlier threshold: when a view's sparse points span a
    depth band narrower than the threshold (a table top seen from above), the constant model
    (scale 0) explains them all and wins, flattening the prior."""
    h, w = depth.shape
    if sparse.shape[0] < 3:
        raise PriorError(
            f"a relative depth prior needs at least 3 sparse points in the view to be aligned, "
            f"got {sparse.shape[0]}"
        )
    cols = np.clip(np.round(sparse[:, 0]).astype(int), 0, w - 1)
    rows = np.clip(np.round(sparse[:, 1]).astype(int), 0, h - 1)
    x = depth[rows, cols].astype(np.float64)
    target = sparse[:, 2].astype(np.float64)
    keep = np.isfinite(x) & (target > 0)
    if valid is not None:
        keep &= valid[rows, cols]
    x, target = x[keep], target[keep]
    if inverse:
        target = 1.0 / target
    if x.size < 3 or np.ptp(x) <= 1e-12 * max(1.0, float(np.abs(x).max())):
        raise PriorError(
            "fewer than 3 sparse points fall on valid, distinct prior values; the prior cannot be aligned"
        )
    # The prior is regressed on the sparse depths, not the other way round: the sparse depths are
    # the accurate variable, and regressing on the noisy one shrinks the scale (errors in
    # variables). On the synthetic suite's simulated priors (24 views at 400x300) the two
    # directions leave about the same mean of the per-view median depth error; a fixed-threshold
    # RANSAC left a higher mean and failed on one view (a flattened table-top).
    rng = np.random.default_rng(seed)
    i, j = rng.integers(0, x.size, (2, pairs))
    dt = target[i] - target[j]
    usable = np.abs(dt) > 1e-12 * np.abs(target).max()
    if not usable.any():
        raise PriorError(
            "the sparse points of the view all have one depth; the prior cannot be aligned"
        )
    a = float(np.median((x[i] - x[j])[usable] / dt[usable]))
    c = float(np.median(x - a * target))
    spread = max(float(np.median(np.abs(x))), 1e-12)
    for _ in range(iterations):
        residual = (a * target + c - x) / spread
        mad = 1.4826 * float(np.median(np.abs(residual - np.median(residual))))
        weight = np.clip(1 - (residual / (4.685 * max(mad, 1e-6))) ** 2, 0, None) ** 2
        if np.count_nonzero(weight) < 3:
            break
        sw = np.sqrt(weight)
        (a, c), *_ = np.linalg.lstsq(np.stack([target * sw, sw], axis=1), x * sw, rcond=None)
    if not a > 0:
        raise PriorError(
            "the relative depth prior correlates negatively with the sparse points "
            "(is it inverse depth? set its output kind)"
        )
    s, b = 1.0 / a, -c / a
    aligned = s * depth.astype(np.float64) + b
    if inverse:
        with np.errstate(divide="ignore"):
            aligned = np.where(aligned > 0, 1.0 / aligned, 0.0)
    return aligned.astype(np.float32), float(s), float(b)


def face_camera(normal: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Camera-frame normals (H, W, 3) flipped where they point away from the camera (a normal
    and its opposite describe the same plane; the estimator wants the one facing the viewer)."""
    h, w = normal.shape[:2]
    rows, cols = np.mgrid[0:h, 0:w].astype(np.float32)
    Ki = np.linalg.inv(K).astype(np.float32)
    ray = np.stack(
        [
            Ki[0, 0] * cols + Ki[0, 1] * rows + Ki[0, 2],
            Ki[1, 1] * rows + Ki[1, 2],
            np.ones_like(cols),
        ],
        axis=2,
    )
    flip = (normal * ray).sum(axis=2) > 0
    normal[flip] *= -1
    return normal


def _check(
    name: str, kind: str, view: str, array: np.ndarray, shape: tuple, dtype=np.float32
) -> np.ndarray:
    array = np.asarray(array)
    if array.shape != shape:
        raise PriorError(
            f"{kind} provider {name!r} returned shape {array.shape} for view {view}, expected {shape}"
        )
    array = array.astype(dtype, copy=False)
    if dtype == np.float32 and not np.isfinite(array).all():
        bad = int((~np.isfinite(array)).sum())
        raise PriorError(
            f"{kind} provider {name!r} returned {bad} NaN or infinite value(s) for view {view}"
        )
    return array


def compute_priors(ctx: PriorContext, providers: PriorProviders) -> ViewPriors:
    """Run the providers for one view and check their outputs (no segmentation: see
    :func:`dvpmvs.segmentation.segment`)."""
    h, w = ctx.shape
    out = ViewPriors()
    names = providers.names
    if providers.depth is not None:
        start = time.perf_counter()
        name = names.get("depth", "?")
        prior = providers.depth(ctx)
        if not isinstance(prior, DepthPrior):
            raise PriorError(
                f"depth prior provider {name!r} must return a DepthPrior, got {type(prior).__name__}"
            )
        valid = (
            np.ones((h, w), bool)
            if prior.valid is None
            else _check(name, "depth prior", ctx.name, prior.valid, (h, w), bool)
        )
        raw = np.asarray(prior.depth)
        if raw.shape != (h, w):
            raise PriorError(
                f"depth prior provider {name!r} returned shape {raw.shape} for view {ctx.name}, "
                f"expected {(h, w)}"
            )
        if not np.isfinite(raw[valid]).all():
            raise PriorError(
                f"depth prior provider {name!r} returned NaN or infinite depth at "
                f"{int((~np.isfinite(raw[valid])).sum())} valid pixel(s) of view {ctx.name}"
            )
        depth = np.where(valid, raw, 0).astype(np.float32)
        if not prior.metric:
            try:
                depth, scale, shift = align_to_sparse(
                    depth, ctx.sparse, inverse=prior.inverse, valid=valid
                )
            except PriorError as exc:
                raise PriorError(f"view {ctx.name}, depth prior {name!r}: {exc}") from None
            log.debug(
                "view %s: depth prior aligned with scale %.4g, shift %.4g", ctx.name, scale, shift
            )
        elif prior.inverse:
            depth = np.where(valid & (depth > 0), 1.0 / np.where(depth > 0, depth, 1.0), 0).astype(
                np.float32
            )
        valid = valid & (depth > 0)
        if not valid.any():
            raise PriorError(
                f"depth prior provider {name!r} gave no positive depth for view {ctx.name}"
            )
        out.depth, out.depth_valid = np.where(valid, depth, 0).astype(np.float32), valid
        out.seconds["depth"] = time.perf_counter() - start
    if providers.normal is not None:
        start = time.perf_counter()
        name = names.get("normal", "?")
        normal = _check(name, "normal prior", ctx.name, providers.normal(ctx, out.depth), (h, w, 3))
        norm = np.linalg.norm(normal, axis=2, keepdims=True)
        normal = np.where(norm > 1e-6, normal / np.maximum(norm, 1e-6), 0).astype(np.float32)
        out.normal = normal
        out.normal_from_depth = bool(getattr(providers.normal, "derived_from_depth", False))
        out.seconds["normal"] = time.perf_counter() - start
    if providers.edge is not None:
        start = time.perf_counter()
        out.edges = _check(
            names.get("edge", "?"), "edge", ctx.name, providers.edge(ctx), (h, w), bool
        )
        out.seconds["edge"] = time.perf_counter() - start
    return out
