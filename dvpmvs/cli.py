"""The ``dvpmvs`` command: one console script, a Hydra-configured task per subcommand.

``dvpmvs <subcommand> [key=value ...]`` composes ``conf/<subcommand>.yaml`` with the overrides
(Hydra syntax, ``-m`` for multirun sweeps) and runs the task. ``dvpmvs --help`` lists the
subcommands; ``dvpmvs <subcommand> --help`` shows that subcommand's options.
"""

from __future__ import annotations

import hashlib
import os
import sys
from dataclasses import dataclass
from typing import Callable

from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import MissingMandatoryValue

from dvpmvs import __version__, registry
from dvpmvs.errors import DvpmvsError

EXIT_ERROR = 1  # bad input or failed run


@dataclass(frozen=True)
class Subcommand:
    summary: str
    task: Callable[[DictConfig], int]
    hydra: bool = True  # composed from conf/<name>.yaml; otherwise plain argv


class CliError(DvpmvsError):
    """A user-facing error: printed without a traceback, exit status EXIT_ERROR."""


def _require(cfg: DictConfig, key: str) -> object:
    try:
        return cfg[key]
    except MissingMandatoryValue:
        raise CliError(f"missing required option {key}=...; see `dvpmvs {_job_name()} --help`") from None


def _job_name() -> str:
    return os.path.basename(sys.argv[0]).removeprefix("dvpmvs ").strip() or "dvpmvs"


def workspace_options(cfg: DictConfig):
    """WorkspaceOptions from the keys of conf/workspace.yaml (validated by the options object)."""
    from dvpmvs.workspace import WorkspaceOptions

    depth_range = cfg.depth_range
    try:
        return WorkspaceOptions(
            max_image_size=cfg.max_image_size,
            resolution_level=cfg.resolution_level,
            min_resolution=cfg.min_resolution,
            depth_quantiles=tuple(_number(q, "depth_quantiles") for q in cfg.depth_quantiles),
            depth_margin=cfg.depth_margin,
            min_points_for_range=cfg.min_points_for_range,
            depth_range=None if depth_range is None else tuple(_number(d, "depth_range") for d in depth_range),
            default_num_sources=cfg.default_num_sources,
            view_selector=OmegaConf.to_container(cfg.view_selector, resolve=True),
        )
    except (TypeError, ValueError) as exc:
        raise CliError(f"invalid workspace option: {exc}") from None


def _number(value, key: str) -> float:
    return _checked(key, value, float)


def _typed(cfg: DictConfig, key: str, kind: type):
    """``cfg[key]`` checked against ``kind`` (bool, int, float or str): a wrong type is an error
    naming the key, not a silent conversion (``bool("maybe")`` is true, ``int(2.5)`` is 2)."""
    return _checked(key, _require(cfg, key), kind)


def _checked(key: str, value, kind: type):
    from dvpmvs.validation import check_value

    try:
        return check_value(key, value, (kind,))
    except ValueError as exc:
        raise CliError(str(exc)) from None


def open_workspace(cfg: DictConfig):
    from dvpmvs.workspace import Workspace

    return Workspace.open(str(_require(cfg, "workspace")), workspace_options(cfg))


def print_workspace_summary(workspace) -> None:
    from rich.console import Console
    from rich.table import Table

    table = Table(title=f"COLMAP workspace {workspace.root}", title_justify="left")
    for column in ("image", "size", "depth range", "sparse pts", "sources"):
        table.add_column(column, overflow="fold")
    for view in workspace.reference_views():
        fallback = " (fallback)" if view.depth_range_is_fallback else ""
        sources = ", ".join(view.sources[:4]) + (f" +{len(view.sources) - 4}" if len(view.sources) > 4 else "")
        table.add_row(
            view.name,
            f"{view.width}x{view.height}",
            f"{view.depth_range[0]:.3g} - {view.depth_range[1]:.3g}{fallback}",
            str(view.num_sparse_points),
            f"{len(view.sources)}: {sources}",
        )
    Console(stderr=True).print(table)


# -- tasks ---------------------------------------------------------------------------------------


def patch_match_options(cfg: DictConfig):
    from dvpmvs.patchmatch import PatchMatchOptions

    values = OmegaConf.to_container(cfg.patch_match, resolve=True)
    try:
        return PatchMatchOptions.from_mapping({**values, "seed": cfg.seed, "num_threads": cfg.num_threads})
    except (TypeError, ValueError) as exc:
        raise CliError(f"invalid patch_match option: {exc}") from None


def fusion_options(cfg: DictConfig, input_type: str):
    from dvpmvs.fusion import FusionOptions

    values = OmegaConf.to_container(cfg.fusion_options, resolve=True)
    try:
        return FusionOptions(**values, input_type=input_type, num_threads=cfg.num_threads)
    except (TypeError, ValueError) as exc:
        raise CliError(f"invalid fusion option: {exc}") from None


def prior_configs(cfg: DictConfig) -> dict:
    """The provider configs of the groups depth_prior, normal_prior, edge, highlight."""
    return {group: OmegaConf.to_container(cfg[group], resolve=True) if cfg.get(group) is not None else None
            for group in ("depth_prior", "normal_prior", "edge", "highlight")}


def segmentation_options(cfg: DictConfig):
    from dvpmvs.segmentation import SegmentationOptions

    if cfg.get("segmentation") is None:
        return None
    values = OmegaConf.to_container(cfg.segmentation, resolve=True)
    try:
        return SegmentationOptions.from_mapping(values)
    except (TypeError, ValueError) as exc:
        raise CliError(f"invalid segmentation option: {exc}") from None


def dense_options(cfg: DictConfig):
    from dvpmvs.pipeline import DenseOptions

    try:
        geometric = _typed(cfg, "geometric", bool)
        return DenseOptions(patch_match=patch_match_options(cfg), geometric=geometric,
                            overwrite=cfg.overwrite, fuse=cfg.fuse,
                            fusion=fusion_options(cfg, "geometric" if geometric else "photometric"),
                            fusion_backend=cfg.fusion, previews=cfg.previews,
                            priors=prior_configs(cfg), segmentation=segmentation_options(cfg))
    except ValueError as exc:
        raise CliError(str(exc)) from None


def dense_task(cfg: DictConfig) -> int:
    # Outputs, scores and the manifest belong to the run, not to the method: the harness's.
    from dvpmvs.evaluation.runs import run_dense_job

    return run_dense_job(cfg, open_workspace(cfg), dense_options(cfg))


def bench_task(cfg: DictConfig) -> int:
    from dvpmvs.evaluation.bench import render_scene

    render_scene(str(cfg.workspace), scene=_typed(cfg, "scene", str), views=_typed(cfg, "views", int),
                 width=_typed(cfg, "width", int), seed=_typed(cfg, "scene_seed", int))
    return dense_task(cfg)


def fuse_task(cfg: DictConfig) -> int:
    from dvpmvs.pipeline import FUSION_BACKENDS, fuse_workspace

    backend = str(cfg.fusion)
    if backend not in FUSION_BACKENDS:
        raise CliError(f"unknown fusion backend {backend!r}; choose {' or '.join(FUSION_BACKENDS)}")
    options = fusion_options(cfg, _typed(cfg, "input_type", str))
    workspace = open_workspace(cfg)
    output = cfg.get("output") or workspace.root / "fused.ply"
    # An explicit request: always fused; the record lets a later `dvpmvs dense` reuse the cloud.
    report = fuse_workspace(workspace, options, backend, output, reuse=False)
    print(f"dvpmvs fuse: {report.points:,} points -> {output}", file=sys.stderr)
    return 0


def _optional_float(cfg: DictConfig, key: str) -> float | None:
    return None if cfg.get(key) is None else _typed(cfg, key, float)


def eval_task(cfg: DictConfig) -> int:
    # The core does not depend on the benchmark harness; the command line joins them.
    from dvpmvs.evaluation import commands

    return commands.evaluate(
        metric=str(cfg.metric),
        reconstruction=str(_require(cfg, "reconstruction")),
        ground_truth=str(_require(cfg, "ground_truth")),
        tolerances=list(cfg.tolerances),
        voxel_size=_optional_float(cfg, "voxel_size"),
        beam_start_radius_meters=_optional_float(cfg, "beam_start_radius_meters"),
        beam_divergence_halfangle_deg=_optional_float(cfg, "beam_divergence_halfangle_deg"),
        threshold=_optional_float(cfg, "threshold"),
        trajectory=cfg.get("trajectory"),
        refine=_typed(cfg, "refine", bool),
        report=cfg.get("report"),
        clouds=cfg.get("clouds"),
        plot=cfg.get("plot"),
        error_maps=cfg.get("error_maps"),
    )


def synth_task(cfg: DictConfig) -> int:
    from dvpmvs.evaluation import commands

    return commands.synth(out=str(_require(cfg, "out")), scene=_typed(cfg, "scene", str),
                          views=_typed(cfg, "views", int), width=_typed(cfg, "width", int),
                          height=None if cfg.height is None else _typed(cfg, "height", int),
                          seed=_typed(cfg, "seed", int), noise=_typed(cfg, "noise", float),
                          priors=_typed(cfg, "priors", bool))


def import_task(cfg: DictConfig) -> int:
    from dvpmvs.evaluation import commands

    return commands.import_dataset(dataset=str(cfg.dataset), source=str(_require(cfg, "source")),
                                   out=str(_require(cfg, "out")),
                                   max_image_size=_typed(cfg, "max_image_size", int),
                                   num_sources=_typed(cfg, "num_sources", int),
                                   num_threads=_typed(cfg, "num_threads", int))


def submit_task(cfg: DictConfig) -> int:
    from dvpmvs.evaluation import commands

    return commands.submit(format=str(cfg.format), cloud=str(_require(cfg, "cloud")),
                           scene=str(_require(cfg, "scene")), out=str(_require(cfg, "out")),
                           runtime=_optional_float(cfg, "runtime"), sparse=cfg.get("sparse"))


def demo_task(cfg: DictConfig) -> int:
    from dvpmvs.evaluation import commands

    return commands.demo(str(cfg.out), dense_options(cfg))


def plugins_task(argv: list[str]) -> int:
    """List the installed plugins of every kind."""
    if argv and argv[0] in ("-h", "--help"):
        print("usage: dvpmvs plugins\n\nList the installed plugins (entry points) of every kind.")
        return 0
    for kind, group in registry.GROUPS.items():
        names = registry.available(kind)
        print(f"{kind:14s} ({group}): {', '.join(names) if names else '-'}")
    return 0


def compare_task(argv: list[str]) -> int:
    """Two builds timed interleaved on the same views (``dvpmvs compare --help``)."""
    from dvpmvs.evaluation import compare

    return compare.main(argv)


SUBCOMMANDS: dict[str, Subcommand] = {
    "dense": Subcommand("depth/normal maps for a COLMAP workspace, then fusion", dense_task),
    "fuse": Subcommand("fuse a workspace's depth maps into a point cloud", fuse_task),
    "eval": Subcommand("score a cloud (ETH3D, Tanks and Temples) or depth maps against ground truth", eval_task),
    "bench": Subcommand("the dense stage on a rendered synthetic scene, scored (-m: a table)", bench_task),
    "synth": Subcommand("render a synthetic workspace with exact ground truth", synth_task),
    "import": Subcommand("turn a Strecha / ETH3D / Tanks and Temples scene into a workspace", import_task),
    "submit": Subcommand("write ETH3D or Tanks and Temples submission files", submit_task),
    "demo": Subcommand("dense stage + evaluation on the embedded synthetic scene", demo_task),
    "compare": Subcommand("two builds timed interleaved on the same views, maps compared", compare_task,
                          hydra=False),  # type: ignore[arg-type]
    "plugins": Subcommand("list the installed plugins", plugins_task, hydra=False),  # type: ignore[arg-type]
}


def usage() -> str:
    lines = [
        f"dvpmvs {__version__}: CPU multi-view stereo (DVP-MVS++) for COLMAP dense workspaces",
        "",
        "usage: dvpmvs <subcommand> [key=value ...] [-m] [--help]",
        "",
        "subcommands:",
    ]
    lines += [f"  {name:9s} {sub.summary}" for name, sub in SUBCOMMANDS.items()]
    lines += [
        "",
        "Options are Hydra overrides (key=value, group=option); `dvpmvs <subcommand> --help` lists",
        "them with their current values, -m runs a multirun sweep (key=a,b,c).",
        "Example: dvpmvs dense workspace=/data/ws max_image_size=1200 depth_prior=coarse_mvs",
    ]
    return "\n".join(lines)


def _with_plugin_search_path(argv: list[str]) -> list[str]:
    """``argv`` with the installed plugins' config groups on Hydra's search path, so that a
    plugin's `view_selector=its_name` works like a built-in one (unless the user set the path).

    Hydra's parser takes its overrides as one run of positional arguments: the added override
    joins the user's (before the first), or leads when there are none. Anywhere else, Hydra's
    flags would split the run (`workspace=X --cfg job` then the override: "unrecognized
    arguments"; `-m a=1,2` after it: the same).
    """
    if any(arg.startswith("hydra.searchpath=") for arg in argv):
        return argv
    first = next((i for i, arg in enumerate(argv) if "=" in arg and not arg.startswith("-")), 0)
    return [*argv[:first], *registry.plugin_search_path(), *argv[first:]]


# Overrides that do not change what a sweep's jobs compute: its folder does not depend on them.
_RUN_ONLY_KEYS = ("hydra.", "hydra/", "num_threads=", "cache=")


def _sweep_dir_override(name: str, argv: list[str]) -> list[str]:
    """A multirun's folder, unless the user names one: ``multirun/<subcommand>-<digest of the
    overrides>``, so that running the same sweep again finds its jobs' folders and resumes them
    (Hydra's own default, a new folder per minute, would start every job afresh)."""
    if any(arg.startswith("hydra.sweep.dir=") for arg in argv):
        return []
    overrides = [arg for arg in argv if "=" in arg and not arg.startswith("-") and not arg.startswith(_RUN_ONLY_KEYS)]
    digest = hashlib.sha256("\n".join(overrides).encode()).hexdigest()[:10]
    return [f"hydra.sweep.dir=multirun/{name}-{digest}"]


# Config sections whose readers reject keys they do not know (the options objects, the plugins'
# factories): a key added there with +key=value is checked by them, with the known keys listed.
_SELF_CHECKED_SECTIONS = ("patch_match", "segmentation", "fusion_options", *registry.GROUPS)


def _check_added_keys(name: str) -> None:
    """``+key=value`` (and ``++key=value``) add keys to the config that nothing may read: a
    misspelt option would be silently ignored. Each added key must be one the subcommand's
    config has, or lie in a section whose reader checks its keys."""
    from hydra import compose
    from hydra.core.global_hydra import GlobalHydra
    from hydra.core.hydra_config import HydraConfig
    from hydra.core.override_parser.overrides_parser import OverridesParser

    given = list(HydraConfig.get().overrides.task)
    overrides = OverridesParser.create().parse_overrides(given)
    added = [o for o in overrides if o.is_add() or o.is_force_add()]
    if not added:
        return
    loader = GlobalHydra.instance().config_loader()
    base = None
    for override in added:
        key = override.key_or_group
        if key.split(".")[0] in _SELF_CHECKED_SECTIONS or loader.get_group_options(key):
            continue
        if base is None:
            kept = [text for text, o in zip(given, overrides) if not (o.is_add() or o.is_force_add())]
            base = compose(config_name=name, overrides=kept)
        if OmegaConf.select(base, key, default="\0missing") == "\0missing":
            raise CliError(f"unknown option {key} (given as {override.input_line}); `dvpmvs {name} --help` lists "
                           f"the options: a misspelt one would otherwise be ignored")


def _quote_non_ascii(argv: list[str]) -> list[str]:
    """``key=value`` with non-ASCII characters in a plain value (``workspace=/data/café``), quoted
    for Hydra, whose override grammar takes only ASCII unquoted. Values that are sweeps, lists,
    interpolations or already quoted are left as they are."""
    quoted = []
    for arg in argv:
        key, sep, value = arg.partition("=")
        if (sep and not arg.startswith("-") and not value.isascii()
                and not any(c in value for c in "'\",[]{}()$\\")):
            arg = f"{key}='{value}'"
        quoted.append(arg)
    return quoted


def _run_hydra(name: str, sub: Subcommand, argv: list[str]) -> int:
    import hydra

    status = {"code": 0}
    multirun = "-m" in argv or "--multirun" in argv

    def task(cfg: DictConfig) -> None:
        try:
            _check_added_keys(name)
            code = sub.task(cfg)
        except DvpmvsError as exc:
            print(f"dvpmvs {name}: error: {exc}", file=sys.stderr)
            code = EXIT_ERROR
        # A sweep goes on past a failed job; the command's status is the worst job's.
        status["code"] = max(status["code"], code)
        if code and not multirun:
            sys.exit(code)

    task.__module__ = __name__
    if multirun:
        first = next((i for i, arg in enumerate(argv) if "=" in arg and not arg.startswith("-")), len(argv))
        argv = [*argv[:first], *_sweep_dir_override(name, argv), *argv[first:]]
    argv = _with_plugin_search_path(_quote_non_ascii(argv))
    # Hydra takes its arguments and the app name from sys.argv.
    saved = sys.argv
    sys.argv = [f"dvpmvs {name}", *argv]
    try:
        hydra.main(version_base=None, config_path="pkg://dvpmvs.conf", config_name=name)(task)()
    finally:
        sys.argv = saved
    if multirun:
        # Jobs that ran in other processes (the joblib launcher) report through their manifests.
        from dvpmvs.evaluation.sweep import FAILED_JOBS

        if FAILED_JOBS:
            status["code"] = max(status["code"], EXIT_ERROR)
    return status["code"]


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help", "help"):
        print(usage())
        return 0
    if argv[0] == "--version":
        print(f"dvpmvs {__version__}")
        return 0
    name, rest = argv[0], argv[1:]
    sub = SUBCOMMANDS.get(name)
    if sub is None:
        print(f"dvpmvs: unknown subcommand {name!r}\n\n{usage()}", file=sys.stderr)
        return EXIT_ERROR
    if not sub.hydra:
        return sub.task(rest)  # type: ignore[arg-type]
    return _run_hydra(name, sub, rest)


if __name__ == "__main__":
    sys.exit(main())
