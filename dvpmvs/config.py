"""The ``dvpmvs`` configuration: Hydra composition and the options objects built from it.

:func:`compose` gives the configuration of a subcommand (``conf/<command>.yaml``, the installed
plugins' config groups, overrides in Hydra's syntax) without the command line, and the
``*_options`` functions turn a composed configuration into the options objects that validate
themselves (:class:`~dvpmvs.workspace.WorkspaceOptions`, :class:`~dvpmvs.dense.DenseOptions`,
...). The command line and the Python API (:mod:`dvpmvs.api`) both build their options here.
"""

from __future__ import annotations

import dataclasses
import os
import sys
import threading
from collections.abc import Mapping, Sequence

from omegaconf import DictConfig, ListConfig, OmegaConf
from omegaconf.errors import MissingMandatoryValue

from dvpmvs import registry
from dvpmvs.errors import DvpmvsError
from dvpmvs.masks import mask_config
from dvpmvs.options import (
    PAPER_SYMBOLS,
    DenseOptions,
    ExecutorOptions,
    FusionOptions,
    MeshingOptions,
    PatchMatchOptions,
    SegmentationOptions,
    SfmOptions,
    WorkspaceOptions,
)

__all__ = [
    "ConfigError",
    "compose",
    "register_option_configs",
    "configure_output",
    "dense_options",
    "executor_options",
    "fusion_options",
    "meshing_options",
    "number_list",
    "number_pair",
    "open_workspace",
    "patch_match_options",
    "prior_configs",
    "progress_enabled",
    "require",
    "segmentation_options",
    "sfm_options",
    "typed",
    "workspace_options",
]


class ConfigError(DvpmvsError, ValueError):
    """An option is missing, of the wrong type or out of range; the message names it."""


def _option_defaults(options, exclude: Sequence[str] = ()) -> dict:
    """The defaults of an option dataclass as a plain config node (tuples as lists)."""
    values = {}
    for field in dataclasses.fields(options):
        if field.name in exclude:
            continue
        default = (
            field.default if field.default is not dataclasses.MISSING else field.default_factory()
        )
        values[field.name] = list(default) if isinstance(default, tuple) else default
    return values


def register_option_configs() -> None:
    """Config nodes made from the option dataclasses, so that each default is written once, in
    its dataclass.

    ``meshing_options`` and ``sfm_options`` are typed (a config file lists them in its defaults:
    ``- meshing_options@meshing``). ``patch_match``, ``segmentation``, ``fusion_options`` and
    ``workspace`` are plain nodes of the dataclasses' defaults, as a YAML file would give them:
    their options objects check types and ranges themselves, with messages naming the key, and
    ``segmentation`` also takes ``null`` (no aligned prior) and the paper's Table V symbols as
    aliases (``segmentation.eta=100``: null means the option itself holds)."""
    from hydra.core.config_store import ConfigStore

    store = ConfigStore.instance()
    for name, options in (("meshing_options", MeshingOptions), ("sfm_options", SfmOptions)):
        # The options are frozen, their schema must take overrides: a typed, writable copy.
        schema = OmegaConf.structured(options)
        OmegaConf.set_readonly(schema, False)
        store.store(name=name, node=schema)
    # seed and num_threads are the command's own (one value for every stage); input_type is
    # fuse's, view_selector a config group.
    store.store(
        name="patch_match",
        package="patch_match",
        node=_option_defaults(PatchMatchOptions, ("seed", "num_threads")),
    )
    store.store(
        name="segmentation",
        package="segmentation",
        node={
            **_option_defaults(SegmentationOptions),
            **{symbol: None for symbol in PAPER_SYMBOLS},
        },
    )
    store.store(
        name="fusion_options",
        package="fusion_options",
        node=_option_defaults(FusionOptions, ("input_type", "num_threads", "mask")),
    )
    store.store(
        name="workspace",
        package="_global_",
        node={"workspace": "???", **_option_defaults(WorkspaceOptions, ("view_selector",))},
    )


_COMPOSE_LOCK = threading.RLock()


def checked_overrides(overrides: Sequence[str]) -> list[str]:
    """``overrides`` as a list, after checking it is a sequence of strings (a lone string would
    be read character by character; a dict is no override list)."""
    if isinstance(overrides, (str, bytes, Mapping)) or not all(
        isinstance(o, str) for o in overrides
    ):
        shown = (
            repr(overrides)
            if isinstance(overrides, (str, bytes, Mapping))
            else f"a {type(overrides).__name__} holding {sorted({type(o).__name__ for o in overrides})}"
        )
        raise TypeError(
            f"overrides must be a list of 'key=value' strings, e.g. ['quality=fast', "
            f"'patch_match.num_iterations=2'], got {shown}"
        )
    return list(overrides)


def compose(command: str, overrides: Sequence[str] = (), hydra_config: bool = False) -> DictConfig:
    """The configuration ``dvpmvs <command> <overrides>`` runs with: ``conf/<command>.yaml``
    (``dense``, ``fuse``, ``mesh``, ``reconstruct`` ...) with the installed plugins' config
    groups on the search path and ``overrides`` in Hydra's syntax (``key=value``,
    ``group=option``). Hydra's own settings are not resolved (no job is run); ``hydra_config``
    keeps them in the result (its ``hydra`` node)."""
    from hydra import compose as hydra_compose
    from hydra import initialize_config_module
    from hydra.core.global_hydra import GlobalHydra
    from hydra.errors import HydraException
    from omegaconf.errors import OmegaConfBaseException

    given = checked_overrides(overrides)
    overrides = (
        given
        if any(o.startswith("hydra.searchpath=") for o in given)
        else [*registry.plugin_search_path(), *given]
    )
    # Hydra's state is one per process: threads (the Python API called from several) compose one
    # at a time. A Hydra application (the command line) may be running: compose beside it, then
    # restore it.
    with _COMPOSE_LOCK:
        saved = GlobalHydra.instance().hydra if GlobalHydra.instance().is_initialized() else None
        GlobalHydra.instance().clear()
        try:
            with initialize_config_module(config_module="dvpmvs.conf", version_base=None):
                return hydra_compose(
                    config_name=command, overrides=overrides, return_hydra_config=hydra_config
                )
        except (HydraException, OmegaConfBaseException) as exc:
            cause = f" ({exc.__cause__})" if exc.__cause__ is not None else ""
            raise ConfigError(
                f"dvpmvs {command} {' '.join(given)}: {exc}{cause}".replace("\n", " ")
            ) from None
        finally:
            GlobalHydra.instance().clear()
            if saved is not None:
                GlobalHydra.instance().initialize(saved)


def require(cfg: DictConfig, key: str) -> object:
    try:
        return cfg[key]
    except MissingMandatoryValue:
        raise ConfigError(
            f"missing required option {key}=...; see `dvpmvs {_job_name()} --help`"
        ) from None


def _job_name() -> str:
    """The subcommand running (the command line names the program ``dvpmvs <subcommand>``
    while Hydra runs it), or a placeholder under the Python API."""
    program = os.path.basename(sys.argv[0]) if sys.argv else ""
    return program.removeprefix("dvpmvs ").strip() if program.startswith("dvpmvs ") else "<command>"


def workspace_options(cfg: DictConfig):
    """WorkspaceOptions from the top-level workspace keys (validated by the options object)."""

    depth_range = cfg.depth_range
    try:
        return WorkspaceOptions(
            max_image_size=cfg.max_image_size,
            resolution_level=cfg.resolution_level,
            min_resolution=cfg.min_resolution,
            depth_quantiles=number_pair(
                cfg.depth_quantiles, "depth_quantiles", "[low,high], e.g. [0.01,0.99]"
            ),
            depth_margin=cfg.depth_margin,
            min_points_for_range=cfg.min_points_for_range,
            depth_range=None
            if depth_range is None
            else number_pair(
                depth_range, "depth_range", "[min,max] in the model's units, e.g. [0.5,20]"
            ),
            default_num_sources=cfg.default_num_sources,
            view_selector=OmegaConf.to_container(cfg.view_selector, resolve=True),
        )
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"invalid workspace option: {exc}") from None


def number_pair(value, key: str, form: str) -> tuple[float, float]:
    """``value`` as two numbers, else an error naming ``key`` and its ``form``."""
    if isinstance(value, (ListConfig, list, tuple)) and len(value) == 2:
        try:
            return tuple(_checked(key, v, float) for v in value)
        except ConfigError:
            pass
    shown = OmegaConf.to_container(value) if isinstance(value, ListConfig) else value
    raise ConfigError(f"{key} must be two numbers, {key}={form}; got {shown!r}")


def number_list(value, key: str, form: str, positive: bool = True) -> list[float]:
    """``value`` (one number or a list of them) as a list of numbers (> 0 with ``positive``),
    else an error naming ``key`` and its ``form``."""
    values = list(value) if isinstance(value, (ListConfig, list, tuple)) else [value]
    shown = OmegaConf.to_container(value) if isinstance(value, ListConfig) else value
    try:
        numbers = [_checked(key, v, float) for v in values]
    except ConfigError:
        numbers = None
    if not numbers or (positive and min(numbers) <= 0):
        raise ConfigError(
            f"{key} must be {'positive ' if positive else ''}numbers, {key}={form}; got {shown!r}"
        )
    return numbers


def typed(cfg: DictConfig, key: str, kind: type):
    """``cfg[key]`` checked against ``kind`` (bool, int, float or str): a wrong type is an error
    naming the key, not a silent conversion (``bool("maybe")`` is true, ``int(2.5)`` is 2)."""
    return _checked(key, require(cfg, key), kind)


def _checked(key: str, value, kind: type):
    from dvpmvs.validation import check_value

    try:
        return check_value(key, value, (kind,))
    except ValueError as exc:
        raise ConfigError(str(exc)) from None


def open_workspace(cfg: DictConfig):
    from dvpmvs.workspace import Workspace

    return Workspace.open(str(require(cfg, "workspace")), workspace_options(cfg))


def _plain(value):
    """A config node as plain Python (lists, dicts), for options that are fingerprinted."""
    return (
        OmegaConf.to_container(value, resolve=True)
        if isinstance(value, (DictConfig, ListConfig))
        else value
    )


def patch_match_options(cfg: DictConfig):

    values = OmegaConf.to_container(cfg.patch_match, resolve=True)
    try:
        return PatchMatchOptions.from_mapping(
            {**values, "seed": cfg.seed, "num_threads": cfg.num_threads}
        )
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"invalid patch_match option: {exc}") from None


def fusion_options(cfg: DictConfig, input_type: str):

    values = OmegaConf.to_container(cfg.fusion_options, resolve=True)
    try:
        return FusionOptions(
            **values,
            input_type=input_type,
            num_threads=cfg.num_threads,
            mask=mask_config(_plain(cfg.get("mask"))),
        )
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"invalid fusion option: {exc}") from None


def prior_configs(cfg: DictConfig) -> dict:
    """The provider configs of the groups depth_prior, normal_prior, edge, highlight."""
    return {
        group: OmegaConf.to_container(cfg[group], resolve=True)
        if cfg.get(group) is not None
        else None
        for group in ("depth_prior", "normal_prior", "edge", "highlight")
    }


def segmentation_options(cfg: DictConfig):

    if cfg.get("segmentation") is None:
        return None
    values = OmegaConf.to_container(cfg.segmentation, resolve=True)
    try:
        return SegmentationOptions.from_mapping(values)
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"invalid segmentation option: {exc}") from None


def dense_options(cfg: DictConfig):

    try:
        geometric = typed(cfg, "geometric", bool)
        return DenseOptions(
            patch_match=patch_match_options(cfg),
            geometric=geometric,
            overwrite=cfg.overwrite,
            fuse=cfg.fuse,
            fusion=fusion_options(cfg, "geometric" if geometric else "photometric"),
            fusion_backend=cfg.fusion,
            previews=cfg.previews,
            priors=prior_configs(cfg),
            segmentation=segmentation_options(cfg),
            mask=mask_config(_plain(cfg.get("mask"))),
        )
    except ValueError as exc:
        raise ConfigError(str(exc)) from None


def executor_options(cfg: DictConfig):
    """ExecutorOptions from the ``executor`` group (``local`` when the config has none)."""

    if cfg.get("executor") is None:
        return ExecutorOptions()
    return section_options(cfg, "executor", ExecutorOptions)


def section_options(cfg: DictConfig, section: str, options_class):
    """``options_class`` built from the config section ``section`` (its structured config)."""
    values = OmegaConf.to_container(cfg[section], resolve=True)
    try:
        return options_class(**values)
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"invalid {section} option: {exc}") from None


def sfm_options(cfg: DictConfig):
    """SfmOptions from the ``sfm`` section."""

    return section_options(cfg, "sfm", SfmOptions)


def progress_enabled(cfg: DictConfig) -> bool:
    """Progress bars: ``progress=auto`` shows them only when standard error is a terminal (a CI
    or batch log gets none), ``quiet=true`` never."""
    value = cfg.get("progress", "auto")
    if cfg.get("quiet", False) is True:
        return False
    if value == "auto":
        return sys.stderr.isatty()
    if not isinstance(value, bool):
        raise ConfigError(f"progress must be auto, true or false, got {value!r}")
    return value


def configure_output(cfg: DictConfig) -> None:
    """Message levels from ``verbose`` / ``quiet``: ours (the ``dvpmvs`` loggers) and COLMAP's
    (pycolmap's glog lines, shown only when verbose: a structure from motion prints thousands)."""
    import logging

    verbose, quiet = typed(cfg, "verbose", bool), typed(cfg, "quiet", bool)
    if verbose and quiet:
        raise ConfigError("verbose=true and quiet=true contradict each other; give one")
    logging.getLogger("dvpmvs").setLevel(
        logging.DEBUG if verbose else logging.WARNING if quiet else logging.INFO
    )
    try:
        import pycolmap
    except ImportError:  # pragma: no cover - a core dependency
        return
    # Without verbose, COLMAP's warnings and errors are hidden too: dvpmvs names each failure of a
    # COLMAP stage in its own words (with what to do); only a fatal line (a crash) still shows.
    pycolmap.logging.minloglevel = 0 if verbose else 3


def meshing_options(cfg: DictConfig):
    """MeshingOptions from the ``meshing`` section."""

    return section_options(cfg, "meshing", MeshingOptions)
