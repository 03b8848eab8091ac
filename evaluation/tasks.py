"""The benchmark harness's subcommands (``dvpmvs eval / synth / import / submit / demo /
compare``): each turns its composed config into a call of :mod:`dvpmvs.evaluation.commands` (the
command line reaches them through :mod:`dvpmvs.cli`, which imports this module only for them)."""

from __future__ import annotations

import math

from omegaconf import DictConfig

from dvpmvs.config import (
    dense_options,
    executor_options,
    number_list,
    progress_enabled,
    require,
    typed,
    workspace_options,
)
from dvpmvs.errors import DvpmvsError
from dvpmvs.validation import check_threads

__all__ = ["compare_task", "demo_task", "eval_task", "import_task", "submit_task", "synth_task"]


def _optional_float(cfg: DictConfig, key: str) -> float | None:
    """``cfg[key]`` as a finite float, or None where it is not given."""
    if cfg.get(key) is None:
        return None
    value = typed(cfg, key, float)
    if not math.isfinite(value):
        raise DvpmvsError(f"{key} must be a finite number, got {value}")
    return value


def _thread_count(cfg: DictConfig) -> int:
    """``num_threads`` of ``dvpmvs import``: -1 or 0 (every core, as COLMAP reads them) or a bounded count."""
    value = typed(cfg, "num_threads", int)
    if value > 0:
        try:
            check_threads("num_threads", value)
        except ValueError as exc:
            raise DvpmvsError(str(exc)) from None
    return value


def eval_task(cfg: DictConfig) -> int:
    from dvpmvs.evaluation import commands

    return commands.evaluate(
        metric=str(cfg.metric),
        reconstruction=str(require(cfg, "reconstruction")),
        ground_truth=str(require(cfg, "ground_truth")),
        tolerances=number_list(cfg.tolerances, "tolerances", "[0.02,0.1] (metres)"),
        voxel_size=_optional_float(cfg, "voxel_size"),
        beam_start_radius_meters=_optional_float(cfg, "beam_start_radius_meters"),
        beam_divergence_halfangle_deg=_optional_float(cfg, "beam_divergence_halfangle_deg"),
        threshold=_optional_float(cfg, "threshold"),
        trajectory=cfg.get("trajectory"),
        refine=typed(cfg, "refine", bool),
        report=cfg.get("report"),
        clouds=cfg.get("clouds"),
        plot=cfg.get("plot"),
        error_maps=cfg.get("error_maps"),
        overwrite=typed(cfg, "overwrite", bool),
    )


def synth_task(cfg: DictConfig) -> int:
    from dvpmvs.evaluation import commands

    return commands.synth(
        out=str(require(cfg, "out")),
        scene=typed(cfg, "scene", str),
        views=typed(cfg, "views", int),
        width=typed(cfg, "width", int),
        height=None if cfg.height is None else typed(cfg, "height", int),
        seed=typed(cfg, "seed", int),
        noise=typed(cfg, "noise", float),
        priors=typed(cfg, "priors", bool),
        overwrite=typed(cfg, "overwrite", bool),
    )


def import_task(cfg: DictConfig) -> int:
    from dvpmvs.evaluation import commands

    return commands.import_dataset(
        dataset=str(cfg.dataset),
        source=str(require(cfg, "source")),
        out=str(require(cfg, "out")),
        max_image_size=typed(cfg, "max_image_size", int),
        num_sources=typed(cfg, "num_sources", int),
        num_threads=_thread_count(cfg),
        overwrite=typed(cfg, "overwrite", bool),
        rgbd=_rgbd_options(cfg),
    )


def _rgbd_options(cfg: DictConfig):
    """The ``rgbd`` section (RGB-D layouts' clip) as :class:`~dvpmvs.evaluation.rgbd.RGBDOptions`."""
    from dvpmvs.config import section_options
    from dvpmvs.evaluation.rgbd import RGBDOptions

    return section_options(cfg, "rgbd", RGBDOptions)


def submit_task(cfg: DictConfig) -> int:
    from dvpmvs.evaluation import commands

    return commands.submit(
        format=str(cfg.format),
        cloud=str(require(cfg, "cloud")),
        scene=str(require(cfg, "scene")),
        out=str(require(cfg, "out")),
        runtime=_optional_float(cfg, "runtime"),
        sparse=cfg.get("sparse"),
        images=cfg.get("images"),
        track=cfg.get("track"),
        overwrite=typed(cfg, "overwrite", bool),
    )


def demo_task(cfg: DictConfig) -> int:
    from dvpmvs.evaluation import commands

    if str(cfg.workspace) != str(cfg.out):
        raise DvpmvsError(
            f"dvpmvs demo writes its workspace to out= ({cfg.out}); workspace={cfg.workspace} "
            "is not read: give out= instead"
        )
    return commands.demo(
        str(cfg.out),
        dense_options(cfg),
        workspace_options(cfg),
        progress=progress_enabled(cfg),
        executor=executor_options(cfg),
        report=typed(cfg, "report", bool),
    )


def compare_task(argv: list[str]) -> int:
    """Two builds timed interleaved on the same views (``dvpmvs compare --help``)."""
    from dvpmvs.evaluation import compare

    return compare.main(argv)
