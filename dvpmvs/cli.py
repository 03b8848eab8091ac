"""The ``dvpmvs`` command: one console script, a Hydra-configured task per subcommand.

``dvpmvs <subcommand> [key=value ...]`` composes ``conf/<subcommand>.yaml`` with the overrides
(Hydra syntax, ``-m`` for multirun sweeps) and runs the task. ``dvpmvs --help`` lists the
subcommands; ``dvpmvs <subcommand> --help`` shows that subcommand's options.
"""

from __future__ import annotations

import os

# The kernels' OpenMP threads take the cores (``num_threads``). numpy's and SciPy's OpenBLAS
# would start as many threads again for the few-row products and solves around them (a view's
# Delaunay lookup, its camera algebra), which only spin against the kernels' threads: set before
# numpy loads, and only where the user has not chosen.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import errno
import hashlib
import sys
from collections.abc import Callable
from dataclasses import dataclass

from omegaconf import DictConfig, OmegaConf

from dvpmvs import registry
from dvpmvs._version import __version__
from dvpmvs.config import (
    ConfigError,
    configure_output,
    dense_options,
    fusion_options,
    meshing_options,
    open_workspace,
    progress_enabled,
    sfm_options,
    workspace_options,
)
from dvpmvs.config import compose as compose_config
from dvpmvs.config import require as _require
from dvpmvs.config import typed as _typed
from dvpmvs.errors import DvpmvsError, Interrupted
from dvpmvs.interrupts import report_interruption, stop_on_signals

# bad input or failed run; a run stopped by Ctrl-C or SIGTERM: 128 + the signal's number
EXIT_ERROR = 1
# OS errors of an output folder (full, read-only) that no writer turned into a message of its own.
_FOLDER_ERRORS = (errno.ENOSPC, errno.EDQUOT, errno.EACCES, errno.EPERM, errno.EROFS)


@dataclass(frozen=True)
class Subcommand:
    summary: str
    task: Callable[[DictConfig], int]
    hydra: bool = True  # composed from conf/<name>.yaml; otherwise plain argv
    # The keys naming where the subcommand writes, for a message that asks to write elsewhere.
    outputs: str = ""


class CliError(ConfigError):
    """A user-facing error: printed without a traceback, exit status EXIT_ERROR."""


# -- tasks ---------------------------------------------------------------------------------------


def dense_task(cfg: DictConfig, scene: dict | None = None) -> int:
    # Outputs, scores and the manifest belong to the run, not to the method: the harness's.
    # ``scene``: the rendered scene's identity (bench), recorded in the manifest.
    from dvpmvs.run import run_dense_job

    if "undistort" in cfg and _typed(cfg, "undistort", bool):
        from omegaconf import OmegaConf, open_dict

        from dvpmvs.masks import mask_config
        from dvpmvs.reconstruction import undistorted_workspace
        from dvpmvs.workspace import Workspace

        mask = cfg.get("mask")
        mask = OmegaConf.to_container(mask, resolve=True) if OmegaConf.is_config(mask) else mask
        root, mask = undistorted_workspace(
            str(_require(cfg, "workspace")), cfg.get("out"), mask_config(mask)
        )
        if str(root) != str(cfg.workspace):
            cfg.workspace, cfg.out = str(root), str(root)
            with open_dict(cfg):
                cfg.mask = mask  # the photos' masks, undistorted with them
        return run_dense_job(
            cfg, Workspace.open(root, workspace_options(cfg)), dense_options(cfg), scene=scene
        )
    return run_dense_job(cfg, open_workspace(cfg), dense_options(cfg), scene=scene)


def bench_task(cfg: DictConfig) -> int:
    from dvpmvs.evaluation.bench import render_scene, rendered_digest
    from dvpmvs.evaluation.scene_digest import compare_with_documented, documented, scene_key

    scene, views, width, seed = (
        _typed(cfg, "scene", str),
        _typed(cfg, "views", int),
        _typed(cfg, "width", int),
        _typed(cfg, "scene_seed", int),
    )
    render_scene(str(cfg.workspace), scene=scene, views=views, width=width, seed=seed)
    key, digest = scene_key(scene, views, width, seed), rendered_digest(str(cfg.workspace))
    print(compare_with_documented(key, digest), file=sys.stderr)
    entry = documented(key)
    return dense_task(
        cfg,
        scene={
            "key": key,
            **digest.to_json(),
            "short": digest.short,
            "documented": entry is not None and entry["digest"] == digest.digest,
        },
    )


def fuse_task(cfg: DictConfig) -> int:
    from dvpmvs.dense import FUSION_BACKENDS, fuse_workspace
    from dvpmvs.tables import partial_cloud_note

    backend = str(cfg.fusion)
    if backend not in FUSION_BACKENDS:
        raise CliError(f"unknown fusion backend {backend!r}; choose {' or '.join(FUSION_BACKENDS)}")
    options = fusion_options(cfg, _typed(cfg, "input_type", str))
    workspace = open_workspace(cfg)
    output = cfg.get("output") or workspace.root / "fused.ply"
    # An explicit request: always fused; the record lets a later `dvpmvs dense` reuse the cloud.
    report = fuse_workspace(
        workspace,
        options,
        backend,
        output,
        reuse=False,
        progress=progress_enabled(cfg),
        overwrite=_typed(cfg, "overwrite", bool),
    )
    print(f"dvpmvs fuse: {report.points:,} points -> {output}", file=sys.stderr)
    if report.views_without_maps:
        print(partial_cloud_note(report.views_without_maps), file=sys.stderr)
    return 0


def mesh_task(cfg: DictConfig) -> int:
    from pathlib import Path

    from dvpmvs.meshing import default_mesh_path, mesh_cloud
    from dvpmvs.stage_progress import StepProgress

    options = meshing_options(cfg)
    workspace, cloud = cfg.get("workspace"), cfg.get("input")
    if workspace is None and cloud is None:
        raise CliError(
            "give workspace=WS (its fused.ply is meshed) or input=CLOUD; see `dvpmvs mesh --help`"
        )
    cloud = (
        Path(str(cloud)).expanduser()
        if cloud is not None
        else Path(str(workspace)).expanduser() / "fused.ply"
    )
    model_dir = None
    if workspace is not None and options.method == "delaunay":
        from dvpmvs.workspace import Workspace

        model_dir = Workspace.open(str(workspace)).model_dir
    output = cfg.get("output") or default_mesh_path(cloud.parent, options.method)
    with StepProgress("meshing", "", progress=progress_enabled(cfg)):
        report = mesh_cloud(
            cloud, output, options, model_dir=model_dir, reuse=not _typed(cfg, "overwrite", bool)
        )
    state = "current, reused" if report.reused else f"{report.seconds:.1f} s"
    print(
        f"dvpmvs mesh: {report.vertices:,} vertices, {report.triangles:,} triangles -> {report.output} ({state})",
        file=sys.stderr,
    )
    return 0


def reconstruct_task(cfg: DictConfig) -> int:
    from dvpmvs.reconstruction import print_reconstruct_summary, reconstruct

    summary = reconstruct(
        images=str(_require(cfg, "images")),
        out=str(_require(cfg, "out")),
        sfm=sfm_options(cfg),
        workspace_options=workspace_options(cfg),
        dense_options=dense_options(cfg),
        meshing_options=meshing_options(cfg) if _typed(cfg, "mesh", bool) else None,
        sparse=None if cfg.get("sparse") is None else str(cfg.sparse),
        max_image_size=_typed(cfg, "max_image_size", int),
        progress=progress_enabled(cfg),
        overwrite=_typed(cfg, "overwrite", bool),
        recursive=_typed(cfg, "recursive", bool),
    )
    print_reconstruct_summary(summary)
    if _typed(cfg, "report", bool) and summary.workspace is not None:
        from dvpmvs.maps import path_for_manifest
        from dvpmvs.run import dense_manifest, write_report

        write_report(
            summary.workspace,
            overwrite=_typed(cfg, "overwrite", bool),
            manifest=dense_manifest(
                summary.dense,
                dense_options(cfg),
                summary.workspace,
                mesh=None
                if summary.mesh is None
                else path_for_manifest(summary.mesh, summary.workspace),
                stages=[
                    {"stage": r.name, "reused": r.reused, "seconds": r.seconds, "result": r.summary}
                    for r in summary.stages
                ],
            ),
        )
    return 0


REPORT_USAGE = """usage: dvpmvs report FOLDER [--max-points N] [--overwrite]

Write FOLDER/report.html: the HTML report of the run whose outputs are in FOLDER (a `dvpmvs dense`,
`bench` or `reconstruct` output folder, or the demo's), or of the sweep FOLDER is (a -m run's
folder: its table, each job linking to its report, the jobs' clouds side by side). Open it in a
browser; it works offline, from the folder alone. `dense`, `bench`, `reconstruct` and `demo` write
it themselves unless report=false.

  --max-points N   the most points of a cloud the page shows (a fixed subsample; default 2000000)
  --overwrite      replace a report.html (or report_files/) there that dvpmvs did not write"""


def report_task(argv: list[str]) -> int:
    """The HTML report of a run or of a sweep, written anew (``dvpmvs report --help``)."""
    if not argv or argv[0] in ("-h", "--help"):
        print(REPORT_USAGE, file=sys.stdout if argv else sys.stderr)
        return 0 if argv else EXIT_ERROR
    try:
        return _write_report(argv)
    except DvpmvsError as exc:
        print(f"dvpmvs report: {exc}", file=sys.stderr)
        return EXIT_ERROR
    except OSError as exc:  # the folder turned read-only or its disk filled while writing
        where = f" ({exc.filename})" if exc.filename else ""
        print(
            f"dvpmvs report: could not write the report: {exc.strerror or exc}{where}; the run's "
            f"outputs are unchanged: free space there, or copy the folder (cp -a) somewhere you "
            f"can write and give the copy",
            file=sys.stderr,
        )
        return EXIT_ERROR


def _write_report(argv: list[str]) -> int:
    import argparse
    import contextlib
    import io
    from pathlib import Path

    from dvpmvs.report import DEFAULT_MAX_POINTS, write_run_report
    from dvpmvs.run import SWEEP_FILE
    from dvpmvs.validation import check_writable

    parser = argparse.ArgumentParser(prog="dvpmvs report", add_help=False)
    parser.add_argument("folder")
    parser.add_argument("--max-points", type=int, default=DEFAULT_MAX_POINTS)
    parser.add_argument("--overwrite", action="store_true")
    try:
        with contextlib.redirect_stderr(
            io.StringIO()
        ):  # argparse's own usage text: ours is the help
            args = parser.parse_args(argv)
    except SystemExit:
        raise CliError(f"cannot read {' '.join(argv)!r}; see `dvpmvs report --help`") from None
    folder = Path(args.folder).expanduser()
    if folder.is_dir():
        check_writable(
            folder,
            "the folder",
            "the report is written beside the run's outputs: copy the folder (cp -a) somewhere "
            "you can write and give the copy",
        )
    if (folder / SWEEP_FILE).is_file():
        from dvpmvs.sweep import sweep_jobs, write_report

        rows = sweep_jobs(folder)
        for row in rows:
            if row.status == "ok":
                write_run_report(row.folder, max_points=args.max_points, overwrite=args.overwrite)
        path = write_report(folder, rows, overwrite=args.overwrite)
        if path is None:
            raise CliError(
                f"the report of the sweep {folder} could not be written (see the warning above)"
            )
    else:
        path = write_run_report(folder, max_points=args.max_points, overwrite=args.overwrite)
    print(f"dvpmvs report: {path}", file=sys.stderr)
    return 0


def plugins_task(argv: list[str]) -> int:
    """List the installed plugins of every kind."""
    if argv and argv[0] in ("-h", "--help"):
        print("usage: dvpmvs plugins\n\nList the installed plugins (entry points) of every kind.")
        return 0
    dense = compose_config("dense", ["workspace=unused"])
    print("plugins (entry point group): installed providers; * the default of `dvpmvs dense`")
    for kind, group in registry.GROUPS.items():
        chosen = OmegaConf.select(dense, f"{kind}.name")
        available = registry.available(kind)
        if chosen == "none" and "none" not in available:
            available.append("none")  # the group's option that loads no plugin
        names = [f"{name}*" if name == chosen else name for name in available]
        print(f"  {kind:14s} ({group}): {', '.join(names) if names else '-'}")
    groups = config_groups()
    print("presets of the dense stage (dense, reconstruct, bench ...): * the default")
    for group, default in DEFAULT_PRESETS.items():
        names = [f"{name}*" if name == default else name for name in groups.get(group, [])]
        print(f"  {group}={' | '.join(names)}")
    return 0


# The presets that are the default: composing with them gives the same config as without
# (tests/test_cli.py checks it).
DEFAULT_PRESETS = {"quality": "high", "method": "default"}


def _harness(name: str) -> Callable:
    """The harness's task ``name`` (:mod:`dvpmvs.evaluation.tasks`), imported when it runs: the
    product's subcommands never load the harness."""

    def task(cfg):
        from dvpmvs.evaluation import tasks

        return getattr(tasks, name)(cfg)

    task.__name__ = name
    return task


SUBCOMMANDS: dict[str, Subcommand] = {
    "dense": Subcommand(
        "depth/normal maps for a COLMAP workspace, then fusion",
        dense_task,
        outputs="out=DIR, output=PATH, report=PATH",
    ),
    "fuse": Subcommand(
        "fuse a workspace's depth maps into a point cloud", fuse_task, outputs="output=PATH"
    ),
    "reconstruct": Subcommand(
        "photos -> structure from motion -> dense workspace, maps, cloud, mesh",
        reconstruct_task,
        outputs="out=DIR",
    ),
    "mesh": Subcommand(
        "a surface mesh (Poisson or COLMAP's Delaunay) from a fused cloud",
        mesh_task,
        outputs="output=PATH",
    ),
    "eval": Subcommand(
        "score a cloud (ETH3D, Tanks and Temples) or depth maps against ground truth",
        _harness("eval_task"),
        outputs="report=PATH, clouds=DIR, error_maps=DIR, plot=PATH",
    ),
    "bench": Subcommand(
        "the dense stage on a rendered synthetic scene, scored (-m: a table)",
        bench_task,
        outputs="out=DIR, scenes_dir=DIR, report=PATH",
    ),
    "synth": Subcommand(
        "render a synthetic workspace with exact ground truth",
        _harness("synth_task"),
        outputs="out=DIR",
    ),
    "import": Subcommand(
        "turn a Strecha / ETH3D / Tanks and Temples scene into a workspace",
        _harness("import_task"),
        outputs="out=DIR",
    ),
    "submit": Subcommand(
        "write ETH3D or Tanks and Temples submission files",
        _harness("submit_task"),
        outputs="out=DIR",
    ),
    "demo": Subcommand(
        "dense stage + evaluation on the embedded synthetic scene",
        _harness("demo_task"),
        outputs="out=DIR",
    ),
    "compare": Subcommand(
        "two builds timed interleaved on the same views, maps compared",
        _harness("compare_task"),
        hydra=False,
    ),  # type: ignore[arg-type]
    "report": Subcommand(
        "the HTML report of a run or a sweep (its cloud in 3D, maps, scores)",
        report_task,
        hydra=False,
    ),  # type: ignore[arg-type]
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
    width = max(len(name) for name in SUBCOMMANDS)
    lines += [f"  {name:{width}s}  {sub.summary}" for name, sub in SUBCOMMANDS.items()]
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
    overrides = [
        arg
        for arg in argv
        if "=" in arg and not arg.startswith("-") and not arg.startswith(_RUN_ONLY_KEYS)
    ]
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
            kept = [
                text for text, o in zip(given, overrides) if not (o.is_add() or o.is_force_add())
            ]
            base = compose(config_name=name, overrides=[*registry.plugin_search_path(), *kept])
        if key not in _option_keys(base):
            raise CliError(
                f"unknown option {key} (given as {override.input_line}){_did_you_mean(_option_keys(base), key)}; "
                f"`dvpmvs {name} --help` lists the options: a misspelt one would otherwise be ignored"
            )


# Hydra's own command-line flags: any other --flag is no option of a subcommand.
_HYDRA_FLAGS = {
    "help", "hydra-help", "version", "cfg", "resolve", "package", "run", "multirun",
    "shell-completion", "config-path", "config-name", "config-dir", "info", "experimental-rerun",
}  # fmt: skip


def _check_option_keys(name: str, argv: list[str]) -> None:
    """Every ``key=value`` names an option of the subcommand's config, and no ``--flag`` is other
    than Hydra's: the error names the nearest options (did you mean) instead of Hydra's advice to
    add the key with ``+`` or its usage text. ``+key`` is checked in the run
    (``_check_added_keys``); group choices (``method=paper``) are Hydra's to check."""
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.errors import HydraException

    for arg in argv:
        if arg.startswith("--") and arg[2:].partition("=")[0] not in _HYDRA_FLAGS:
            raise CliError(
                f"unknown flag {arg}: dvpmvs {name} takes its options as key=value (`dvpmvs {name} "
                f"--help` lists them)"
            )
    texts = [arg for arg in argv if "=" in arg and not arg.startswith("-")]
    try:
        overrides = OverridesParser.create().parse_overrides(texts)
    except HydraException:
        return  # Hydra's message names the argument it cannot read
    groups = config_groups()
    plain, chosen = [], []
    for override in overrides:
        key = override.key_or_group
        if key.startswith(("hydra.", "hydra/")) or key == "hydra" or override.is_delete():
            continue
        if override.is_add() or override.is_force_add():
            continue
        if key in groups or "/" in key:  # a config group (nested: a/b); Hydra names the options
            value = (
                next(iter(override.sweep_string_iterator()))
                if override.is_sweep_override()
                else override.value()
            )
            chosen.append(f"{key}={value}")
        else:
            plain.append(override)
    if not plain:
        return
    try:
        base = compose_config(name, chosen)
    except ConfigError:
        return  # a group choice Hydra will name with its options
    keys = _option_keys(base)
    for override in plain:
        key = override.key_or_group
        if key not in keys:
            raise CliError(
                f"unknown option {key}{_did_you_mean(keys, key)}; `dvpmvs {name} --help` lists the "
                f"options"
            )


def _option_keys(config: DictConfig) -> list[str]:
    """Every dotted key of ``config``, its sections' too (a mandatory ``???`` value is a key)."""
    keys: list[str] = []

    def walk(node: object, prefix: str) -> None:
        if prefix:
            keys.append(prefix[:-1])
        if isinstance(node, dict):
            for child, value in node.items():
                walk(value, f"{prefix}{child}.")

    walk(OmegaConf.to_container(config, resolve=False), "")
    return keys


def _did_you_mean(keys: list[str], key: str) -> str:
    """ " (did you mean K?)" with the ``keys`` nearest to ``key`` (the whole dotted key, else its
    last part: those as near as the nearest), or "" where none is near."""
    from difflib import SequenceMatcher

    def nearest(word: str, candidates: list[str]) -> list[str]:
        ratios = {c: SequenceMatcher(None, word, c).ratio() for c in candidates}
        best = max(ratios.values(), default=0.0)
        if best < 0.75:
            return []
        return sorted((c for c, r in ratios.items() if r >= best - 0.02), key=lambda c: -ratios[c])

    found = nearest(key, keys)
    if not found:
        leaves = {known.rsplit(".", 1)[-1] for known in keys}
        near = set(nearest(key.rsplit(".", 1)[-1], sorted(leaves)))
        found = [known for known in keys if known.rsplit(".", 1)[-1] in near]
    return f" (did you mean {' or '.join(found[:3])}?)" if found else ""


def _quote_non_ascii(argv: list[str]) -> list[str]:
    """``key=value`` with non-ASCII characters in a plain value (``workspace=/data/café``), quoted
    for Hydra, whose override grammar takes only ASCII unquoted. Values that are sweeps, lists,
    interpolations or already quoted are left as they are."""
    quoted = []
    for arg in argv:
        key, sep, value = arg.partition("=")
        if (
            sep
            and not arg.startswith("-")
            and not value.isascii()
            and not any(c in value for c in "'\",[]{}()$\\")
        ):
            arg = f"{key}='{value}'"
        quoted.append(arg)
    return quoted


def config_groups() -> dict[str, list[str]]:
    """Every config group on the command's search path (the core's and the installed plugins'
    config packages) with its options, as ``group=option`` takes them."""
    from importlib.resources import files

    groups: dict[str, set[str]] = {}
    for package in ("dvpmvs.conf", *registry.plugin_config_packages()):
        for folder in files(package).iterdir():
            if (
                folder.is_dir()
                and not folder.name.startswith(("_", "."))
                and folder.name != "hydra"
            ):
                options = {
                    entry.name[:-5] for entry in folder.iterdir() if entry.name.endswith(".yaml")
                }
                groups.setdefault(folder.name, set()).update(options)
    return {group: sorted(options) for group, options in sorted(groups.items()) if options}


def _print_help(name: str, argv: list[str]) -> int:
    """A subcommand's help: its description, the config groups of the core and of the installed
    plugins (Hydra's own help lists only the core's search path), and the options with the values
    the given overrides leave them at."""
    from dvpmvs.config import compose

    overrides = [
        arg
        for arg in argv
        if arg not in ("-h", "--help") and "=" in arg and not arg.startswith("-")
    ]
    cfg = compose(name, overrides, hydra_config=True)
    template = cfg.hydra.help.template  # conf/base.yaml: the layout Hydra's own help would use
    options = OmegaConf.to_container(cfg, resolve=False)
    options.pop("hydra", None)
    groups = "\n".join(f"{group}: {', '.join(names)}" for group, names in config_groups().items())
    print(
        template.replace("$APP_CONFIG_GROUPS", groups).replace(
            "$CONFIG", OmegaConf.to_yaml(options)
        )
    )
    return 0


def _run_hydra(name: str, sub: Subcommand, argv: list[str]) -> int:
    import hydra

    from dvpmvs.colmap_flags import ColmapFlagError, translate_colmap_flags

    try:
        argv, notes = translate_colmap_flags(name, argv)
        for note in notes:
            print(f"dvpmvs {name}: {note}", file=sys.stderr)
        if "--help" not in argv and "-h" not in argv:
            _check_option_keys(name, _quote_non_ascii(argv))
    except (ColmapFlagError, CliError) as exc:
        print(f"dvpmvs {name}: error: {exc}", file=sys.stderr)
        return EXIT_ERROR
    if "--help" in argv or "-h" in argv:
        try:
            return _print_help(name, argv)
        except DvpmvsError as exc:
            from dvpmvs.maps import DiskFullError

            where = (
                f"; `dvpmvs {name}` writes where {sub.outputs} say"
                if isinstance(exc, DiskFullError) and sub.outputs
                else ""
            )
            print(f"dvpmvs {name}: error: {exc}{where}", file=sys.stderr)
            return EXIT_ERROR
    status = {"code": 0}
    multirun = "-m" in argv or "--multirun" in argv

    def task(cfg: DictConfig) -> None:
        from dvpmvs.run import mark_command_start

        mark_command_start()
        try:
            _check_added_keys(name)
            configure_output(cfg)
            code = sub.task(cfg)
        except DvpmvsError as exc:
            from dvpmvs.maps import DiskFullError

            where = (
                f"; `dvpmvs {name}` writes where {sub.outputs} say"
                if isinstance(exc, DiskFullError) and sub.outputs
                else ""
            )
            print(f"dvpmvs {name}: error: {exc}{where}", file=sys.stderr)
            code = EXIT_ERROR
            if multirun:
                from dvpmvs.run import write_failed_manifest

                write_failed_manifest(str(exc))
        except Interrupted as stop:
            # A sweep stops too: the user asked everything to stop.
            report_interruption(name, stop)
            sys.exit(stop.exit_status)
        except OSError as exc:
            # A full disk or a folder that turned read-only during the run, where no writer named it
            # (the checks before compute name the usual cases).
            if exc.errno not in _FOLDER_ERRORS:
                raise
            where = f" ({exc.filename})" if exc.filename else ""
            print(
                f"dvpmvs {name}: error: {exc.strerror}{where}; free space there or write elsewhere, then rerun the "
                f"same command to resume",
                file=sys.stderr,
            )
            code = EXIT_ERROR
        # A sweep goes on past a failed job; the command's status is the worst job's.
        status["code"] = max(status["code"], code)
        if code and not multirun:
            sys.exit(code)

    task.__module__ = __name__
    if multirun:
        first = next(
            (i for i, arg in enumerate(argv) if "=" in arg and not arg.startswith("-")), len(argv)
        )
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
        from dvpmvs.sweep import FAILED_JOBS

        if FAILED_JOBS:
            status["code"] = max(status["code"], EXIT_ERROR)
    return status["code"]


def main(argv: list[str] | None = None) -> int:
    import signal

    previous = stop_on_signals()
    try:
        return _main(argv)
    except (Interrupted, KeyboardInterrupt) as stop:
        stop = stop if isinstance(stop, Interrupted) else Interrupted(signal.SIGINT)
        report_interruption((argv or sys.argv[1:] or ["?"])[0], stop)
        return stop.exit_status
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def _main(argv: list[str] | None = None) -> int:
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
