"""One ONNX Runtime model behind a prior: options (with presets), pre-processing, inference,
post-processing back to the view's pixels.

A network sees the view's RGB image resized to its input size, either stretched or with its
aspect kept and the rest padded (``resize: pad``), scaled by ``scale`` then normalised per
channel with ``mean`` and ``std``. Its output is cropped back to the image (padding removed)
and resized to the view's size, so that a prior is always pixel-aligned with the reference view.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from dvpmvs.priors import PriorError
from dvpmvs.validation import check_field_types

__all__ = ["OnnxOptions", "OnnxModel", "PRESETS", "as_image", "select_output"]

log = logging.getLogger(__name__)

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)

# What is known about each network's published ONNX export; any key can be overridden in the
# config. Sizes are (height, width).
PRESETS: dict[str, dict[str, Any]] = {
    # Depth Anything V2 (onnx-community / fabio-sim exports): 518x518 (a multiple of the ViT's
    # 14-pixel patch), ImageNet normalisation of 0..1 RGB, output relative inverse depth
    # (affine-invariant disparity).
    "depth_anything_v2": dict(
        input_size=(518, 518),
        resize="stretch",
        scale=1.0,
        mean=IMAGENET_MEAN,
        std=IMAGENET_STD,
        output="inverse_depth",
        metric=False,
    ),
    # Depth Pro: 1536x1536, 0..1 RGB mapped to [-1, 1]; its first output is canonical inverse
    # depth (metric only given the focal length). SfM units are arbitrary anyway, so it is
    # aligned to the sparse points like a relative prior.
    "depthpro": dict(
        input_size=(1536, 1536),
        resize="stretch",
        scale=1.0,
        mean=(0.5, 0.5, 0.5),
        std=(0.5, 0.5, 0.5),
        output="inverse_depth",
        metric=False,
    ),
    # Metric3Dv2 (ViT; the repository's ONNX export normalises inside the model): 616x1064, RGB
    # 0..255, aspect kept and padded with the ImageNet mean colour; the normal output has 3
    # (or 4, with a confidence) channels in the OpenCV camera frame.
    "metric3dv2": dict(
        input_size=(616, 1064),
        resize="pad",
        scale=255.0,
        mean=(0.0, 0.0, 0.0),
        std=(1.0, 1.0, 1.0),
        pad_value=IMAGENET_MEAN,
    ),
    # JSHDR, the joint highlight detection and removal network of SHIQ (Fu et al., CVPR 2021),
    # exported to ONNX from the authors' PyTorch model: RGB in [0, 1] without normalisation,
    # trained on SHIQ's 200x200 crops and run here over 200x200 tiles of the view at its own
    # resolution; its outputs in the order the authors' predict returns them: the highlight
    # mask (a probability), the specular residue and the highlight-free image.
    "jshdr": dict(
        input_size=(200, 200),
        resize="stretch",
        scale=1.0,
        mean=(0.0, 0.0, 0.0),
        std=(1.0, 1.0, 1.0),
        mask_output=0,
        corrected_output=2,
        tile=True,
    ),
}


# Which config group each preset is made for.
PRESET_GROUP = {
    "depth_anything_v2": "depth_prior",
    "depthpro": "depth_prior",
    "metric3dv2": "normal_prior",
    "jshdr": "highlight",
}


def _triple(value, key: str) -> tuple[float, float, float]:
    values = tuple(float(v) for v in (value if isinstance(value, Sequence) else [value] * 3))
    if len(values) != 3:
        raise ValueError(f"{key} needs 3 values (R, G, B), got {len(values)}")
    return values  # type: ignore[return-value]


@dataclass(frozen=True)
class OnnxOptions:
    """How to run one ONNX network. ``key``: the config group it was built from (messages name
    ``<key>.model`` etc.); ``input_size``: (height, width), None takes the model's static input
    size; ``layout``: nchw or nhwc; ``input_name``/``output_name``: None takes the first input
    and the first output of the right shape; ``execution_providers``: ONNX Runtime's names, CPU
    by default; ``num_threads``: intra-op threads, 0 lets ONNX Runtime choose."""

    model: str | None = None
    key: str = "depth_prior"
    preset: str | None = None
    input_size: tuple[int, int] | None = None
    resize: str = "stretch"
    scale: float = 1.0
    mean: tuple[float, float, float] = (0.0, 0.0, 0.0)
    std: tuple[float, float, float] = (1.0, 1.0, 1.0)
    pad_value: tuple[float, float, float] = (0.0, 0.0, 0.0)
    layout: str = "nchw"
    input_name: str | None = None
    output_name: str | None = None
    execution_providers: tuple[str, ...] = ("CPUExecutionProvider",)
    num_threads: int = 0

    def __post_init__(self):
        key = self.key
        check_field_types(self, f"{key}.")
        if self.resize not in ("stretch", "pad"):
            raise ValueError(f"{key}.resize must be stretch or pad, got {self.resize!r}")
        if self.layout not in ("nchw", "nhwc"):
            raise ValueError(f"{key}.layout must be nchw or nhwc, got {self.layout!r}")
        if self.input_size is not None:
            size = tuple(int(v) for v in self.input_size)
            if len(size) != 2 or min(size) < 1:
                raise ValueError(
                    f"{key}.input_size must be [height, width], got {list(self.input_size)}"
                )
            object.__setattr__(self, "input_size", size)
        for name in ("mean", "std", "pad_value"):
            object.__setattr__(self, name, _triple(getattr(self, name), f"{key}.{name}"))
        if min(abs(v) for v in self.std) == 0:
            raise ValueError(f"{key}.std must not contain 0")
        if not self.scale > 0:
            raise ValueError(f"{key}.scale must be > 0, got {self.scale}")
        if self.num_threads < 0:
            raise ValueError(f"{key}.num_threads must be >= 0, got {self.num_threads}")
        providers = self.execution_providers
        object.__setattr__(
            self,
            "execution_providers",
            (providers,) if isinstance(providers, str) else tuple(providers),
        )

    @classmethod
    def from_config(
        cls, key: str, params: Mapping[str, Any], own: Sequence[str] = ()
    ) -> tuple[OnnxOptions, dict]:
        """Options from a config mapping: its preset's values, overridden by every key that is set
        (not None). Returns the options and the keys that belong to the provider (``own``)."""
        params = {k: v for k, v in dict(params).items() if v is not None}
        preset = params.get("preset")
        merged: dict[str, Any] = {}
        if preset is not None:
            if preset not in PRESETS:
                raise ValueError(
                    f"{key}.preset: unknown preset {preset!r}; presets: {', '.join(sorted(PRESETS))}"
                )
            if PRESET_GROUP[preset] != key:
                raise ValueError(f"{key}.preset: {preset!r} is a {PRESET_GROUP[preset]} preset")
            merged.update(PRESETS[preset])
        merged.update(params)
        provider = {k: merged.pop(k) for k in own if k in merged}
        names = {f.name for f in fields(cls)} - {"key"}
        unknown = sorted(set(merged) - names)
        if unknown:
            raise ValueError(f"unknown {key} option(s) for the onnx provider: {', '.join(unknown)}")
        return cls(key=key, **merged), provider


def as_image(array, channels: int, max_channels: int | None = None) -> np.ndarray | None:
    """A network output as an image: (H, W) for ``channels`` 1, (H, W, 3) for 3 (channels first
    or last; up to ``max_channels`` of them, the extra ones dropped); None when it is not shaped
    so. Axes of length 1 (batch, a single channel) are squeezed first."""
    array = np.asarray(array, np.float32)
    squeezed = array.reshape([d for d in array.shape if d != 1] or [1])
    if channels == 1:
        return squeezed if squeezed.ndim == 2 else None
    if squeezed.ndim != 3:
        return None
    allowed = tuple(range(channels, (max_channels or channels) + 1))
    if squeezed.shape[0] in allowed and squeezed.shape[2] not in allowed:
        squeezed = squeezed.transpose(1, 2, 0)
    return squeezed[..., :channels] if squeezed.shape[2] in allowed else None


def select_output(
    outputs: Sequence,
    names: Sequence[str],
    which,
    convert,
    option: str,
    wanted: str,
    error: type[Exception] = PriorError,
):
    """One of a network's ``outputs`` converted by ``convert`` (None: not convertible): the first
    one it converts when ``which`` is None, else the one named (str) or numbered (int) ``which``.
    ``option``: the key that names it, ``wanted``: what it must hold, both for the messages."""
    described = "; ".join(f"{n} {list(np.shape(o))}" for n, o in zip(names, outputs))
    if which is None:
        for array in outputs:
            value = convert(array)
            if value is not None:
                return value
        raise error(f"no output is {wanted}; outputs: {described} (name it with {option})")
    if isinstance(which, str):
        if which not in names:
            raise error(f"{option}: the model has no output {which!r} (outputs: {described})")
        index = list(names).index(which)
    else:
        index = int(which)
        if not 0 <= index < len(outputs):
            raise error(
                f"{option}: the model has {len(outputs)} output(s), no output number {index} "
                f"(outputs: {described})"
            )
    value = convert(outputs[index])
    if value is None:
        raise error(
            f"{option}: output {names[index]} {list(np.shape(outputs[index]))} is not {wanted}"
        )
    return value


class OnnxModel:
    """An ONNX Runtime session, loaded on first use and kept for every later view."""

    def __init__(self, options: OnnxOptions):
        self.options = options
        self._session = None

    def path(self, root: Path | None = None) -> Path:
        """The model file: as given, else relative to the workspace; a clear error if missing."""
        key = self.options.key
        if self.options.model in (None, ""):
            raise PriorError(
                f"the onnx {key} needs a model file: set {key}.model=/path/to/model.onnx "
                f"(dvpmvs never downloads weights)"
            )
        path = Path(os.path.expanduser(str(self.options.model)))
        candidates = [path] if path.is_absolute() or root is None else [path, Path(root) / path]
        for candidate in candidates:
            if candidate.is_file():
                return candidate
        raise PriorError(
            f"{key}.model: ONNX model file not found: {path}"
            + (f" (nor under the workspace {root})" if len(candidates) > 1 else "")
        )

    def session(self, root: Path | None = None):
        if self._session is None:
            try:
                import onnxruntime as ort
            except ImportError:
                raise PriorError(
                    f"{self.options.key}: the learned priors run on ONNX Runtime, which is not "
                    f"installed: pip install 'dvpmvs[onnx]'"
                ) from None

            path = self.path(root)
            so = ort.SessionOptions()
            so.log_severity_level = 3
            if self.options.num_threads:
                so.intra_op_num_threads = self.options.num_threads
            available = set(ort.get_available_providers())
            missing = [p for p in self.options.execution_providers if p not in available]
            if missing:
                raise PriorError(
                    f"{self.options.key}.execution_providers: {', '.join(missing)} not available in "
                    f"this ONNX Runtime (available: {', '.join(sorted(available))})"
                )
            try:
                self._session = ort.InferenceSession(
                    str(path), so, providers=list(self.options.execution_providers)
                )
            except Exception as exc:  # ONNX Runtime raises its own exception types for a bad file
                raise PriorError(
                    f"{self.options.key}.model: ONNX Runtime cannot load {path}: {exc}"
                ) from exc
            log.info(
                "%s: loaded %s (%s)",
                self.options.key,
                path,
                ", ".join(self._session.get_providers()),
            )
        return self._session

    def _input(self, session):
        inputs = session.get_inputs()
        if self.options.input_name is None:
            return inputs[0]
        for item in inputs:
            if item.name == self.options.input_name:
                return item
        raise PriorError(
            f"{self.options.key}.input_name: the model has no input {self.options.input_name!r} "
            f"(inputs: {', '.join(i.name for i in inputs)})"
        )

    def _input_size(self, spec) -> tuple[int, int]:
        key, opts = self.options.key, self.options
        shape = list(spec.shape)
        if len(shape) != 4:
            raise PriorError(
                f"{key}.model: expected a 4-d image input, {spec.name} has shape {shape}"
            )
        dims = shape[2:4] if opts.layout == "nchw" else shape[1:3]
        static = tuple(dims) if all(isinstance(d, int) and d > 0 for d in dims) else None
        if opts.input_size is not None:
            if static is not None and static != opts.input_size:
                raise PriorError(
                    f"{key}.input_size is {list(opts.input_size)} but the model's input {spec.name} is "
                    f"fixed at {list(static)}; set {key}.input_size={list(static)}"
                )
            return opts.input_size
        if static is None:
            raise PriorError(
                f"{key}.input_size: the model's input size is dynamic ({shape}); set it, "
                f"e.g. {key}.input_size=[518,518]"
            )
        return static  # type: ignore[return-value]

    def _preprocess(
        self, rgb: np.ndarray, size: tuple[int, int]
    ) -> tuple[np.ndarray, tuple[float, ...]]:
        """The network input and the image's box inside it, as fractions (top, left, bottom, right)."""
        opts = self.options
        h, w = rgb.shape[:2]
        th, tw = size
        if opts.resize == "stretch":
            nh, nw, top, left = th, tw, 0, 0
        else:
            factor = min(th / h, tw / w)
            nh, nw = max(1, round(h * factor)), max(1, round(w * factor))
            top, left = (th - nh) // 2, (tw - nw) // 2
        shrink = nh < h or nw < w
        resized = cv2.resize(
            rgb, (nw, nh), interpolation=cv2.INTER_AREA if shrink else cv2.INTER_LINEAR
        )
        canvas = np.empty((th, tw, 3), np.float32)
        canvas[:] = np.asarray(opts.pad_value, np.float32)
        canvas[top : top + nh, left : left + nw] = resized
        x = (canvas * np.float32(opts.scale) - np.asarray(opts.mean, np.float32)) / np.asarray(
            opts.std, np.float32
        )
        x = x.transpose(2, 0, 1)[None] if opts.layout == "nchw" else x[None]
        box = (top / th, left / tw, (top + nh) / th, (left + nw) / tw)
        return np.ascontiguousarray(x, np.float32), box

    def predict(self, rgb: np.ndarray, channels: int, root: Path | None = None) -> np.ndarray:
        """Run the network on one (H, W, 3) RGB image in [0, 1]; returns its output of ``channels``
        channels (1: (H, W); 3: (H, W, 3), a 4th confidence channel dropped) at the image's size."""
        outputs, names, box = self.run(rgb, root)
        return self.to_image(self._pick_output(outputs, names, channels), box, rgb.shape[:2])

    def input_size(self, root: Path | None = None) -> tuple[int, int]:
        """The network's input (height, width)."""
        session = self.session(root)
        return self._input_size(self._input(session))

    def run(
        self, rgb: np.ndarray, root: Path | None = None
    ) -> tuple[list, list[str], tuple[float, ...]]:
        """Run the network on one (H, W, 3) RGB image in [0, 1]: its outputs, their names, and
        the image's box in the input (fractions, for :meth:`to_image`)."""
        key = self.options.key
        session = self.session(root)
        spec = self._input(session)
        x, box = self._preprocess(np.asarray(rgb, np.float32), self._input_size(spec))
        try:
            outputs = session.run(None, {spec.name: x})
        except Exception as exc:
            raise PriorError(f"{key}.model: inference failed: {exc}") from exc
        return outputs, [o.name for o in session.get_outputs()], box

    def to_image(
        self, array: np.ndarray, box: tuple[float, ...], shape: tuple[int, int]
    ) -> np.ndarray:
        """An output (H', W'[, C]) cropped to the image's box and resized to ``shape`` (H, W)."""
        key = self.options.key
        if not np.isfinite(array).all():
            raise PriorError(
                f"{key}.model returned {int((~np.isfinite(array)).sum())} NaN or infinite value(s)"
            )
        oh, ow = array.shape[:2]
        top, left, bottom, right = (
            round(box[0] * oh),
            round(box[1] * ow),
            round(box[2] * oh),
            round(box[3] * ow),
        )
        array = np.ascontiguousarray(array[top:bottom, left:right], np.float32)
        h, w = shape
        return cv2.resize(array, (w, h), interpolation=cv2.INTER_LINEAR)

    def _pick_output(self, outputs: list, names: list[str], channels: int) -> np.ndarray:
        key = self.options.key
        if self.options.output_name is not None:
            if self.options.output_name not in names:
                raise PriorError(
                    f"{key}.output_name: the model has no output {self.options.output_name!r} "
                    f"(outputs: {', '.join(names)})"
                )
            candidates = [names.index(self.options.output_name)]
        else:
            candidates = list(range(len(outputs)))
        shapes = []
        for index in candidates:
            shapes.append(f"{names[index]} {list(np.shape(outputs[index]))}")
            image = as_image(
                outputs[index], channels, max_channels=4
            )  # normals may carry a confidence
            if image is not None:
                return image
        what = "a depth map (1 channel)" if channels == 1 else "normals (3 channels)"
        raise PriorError(
            f"{key}.model: no output holds {what}; outputs: {'; '.join(shapes)}"
            + ("" if self.options.output_name else f" (name one with {key}.output_name)")
        )
