"""A dense run as the ``dense`` and ``bench`` commands run it.

Around :func:`dvpmvs.dense.run_dense` this adds what belongs to a run rather than to the
method: where its outputs go (the workspace, ``out=DIR``, or under a Hydra multirun each job's
own folder, the workspace then only read), the map cache the jobs of a sweep share, the thread
count of jobs run side by side (Hydra's joblib launcher), and the run's *manifest*:
``OUT/dvpmvs_run.json`` (and ``report=PATH.json``), with the resolved config, the code and library
versions, per-pass timings, the scores and the closing summary, so that every figure can be
traced to what produced it; and its HTML report ``OUT/report.html`` (:mod:`dvpmvs.report`).

Scores come from *scoring hooks*, entry points of the group ``dvpmvs.run_scoring``: the
benchmark harness registers the one that scores a run against ground truth (``evaluate.*``,
:mod:`dvpmvs.evaluation.runs`); the run itself knows no metric.
"""

from __future__ import annotations

import json
import logging
import os
import sys
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, replace
from datetime import datetime, timezone
from pathlib import Path

from omegaconf import DictConfig, OmegaConf
from rich.console import Console

from dvpmvs.config import executor_options, progress_enabled
from dvpmvs.dense import run_dense
from dvpmvs.digests import canonical
from dvpmvs.errors import DvpmvsError, Interrupted
from dvpmvs.maps import read_json_object, write_json
from dvpmvs.provenance import MapCache, code_identity, environment
from dvpmvs.tables import print_summary, print_workspace_summary
from dvpmvs.validation import check_writable, resolve_threads

__all__ = [
    "MANIFEST_NAME",
    "SCORING_GROUP",
    "SWEEP_FILE",
    "JobContext",
    "check_json_path",
    "job_context",
    "dense_manifest",
    "peak_rss_mb",
    "report_option",
    "reset_peak_rss",
    "run_dense_job",
    "scoring_hooks",
    "write_failed_manifest",
    "write_report",
]

log = logging.getLogger(__name__)
_console = Console(stderr=True)

MANIFEST_NAME = "dvpmvs_run.json"
SWEEP_FILE = "sweep.json"  # written by the sweep table callback at the start of a multirun
SCORING_GROUP = "dvpmvs.run_scoring"


@dataclass(frozen=True)
class JobContext:
    """Where a run stands in Hydra: a single run, or job ``num`` of the sweep in ``sweep_dir``
    writing to ``job_dir``; ``overrides``: the job's own command-line overrides;
    ``parallel_jobs``: how many jobs the launcher runs side by side."""

    multirun: bool = False
    job_dir: Path | None = None
    sweep_dir: Path | None = None
    num: int | None = None
    overrides: tuple[str, ...] = ()
    parallel_jobs: int = 1


def job_context() -> JobContext:
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode

    if not HydraConfig.initialized():
        return JobContext()
    hc = HydraConfig.get()
    overrides = tuple(str(o) for o in hc.overrides.task)
    if hc.mode != RunMode.MULTIRUN:
        return JobContext(overrides=overrides)
    n_jobs = OmegaConf.select(hc, "launcher.n_jobs", default=None)
    cores = os.cpu_count() or 1
    parallel = 1 if n_jobs is None else (cores if int(n_jobs) < 0 else max(1, int(n_jobs)))
    return JobContext(
        True, Path(hc.runtime.output_dir), Path(hc.sweep.dir), int(hc.job.num), overrides, parallel
    )


def peak_rss_mb() -> float:
    """Peak resident memory of this process since :func:`reset_peak_rss` (Linux's VmHWM)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024
    except OSError:
        pass
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def reset_peak_rss() -> None:
    """Start the peak-memory count afresh (jobs of a sweep share a process); Linux only."""
    try:
        Path("/proc/self/clear_refs").write_text("5")
    except OSError:
        pass


def _threads(requested: int, context: JobContext) -> int:
    """``num_threads``; 0 (every core) is split between the jobs a launcher runs side by side."""
    return resolve_threads(requested, context.parallel_jobs)


def _path_option(cfg: DictConfig, key: str) -> Path | None:
    value = cfg.get(key)
    if value is None or value is False or str(value).lower() in ("", "none", "false"):
        return None
    return Path(str(value)).expanduser()


def _cache(cfg: DictConfig, context: JobContext):
    """The map cache: ``cache=DIR``; in a sweep by default ``<sweep folder's parent>/map_cache``,
    shared by the sweeps beside it; ``cache=false``: none."""
    value = cfg.get("cache")
    if value is False or (isinstance(value, str) and value.lower() in ("false", "none")):
        return None
    if value is None:
        return MapCache(context.sweep_dir.parent / "map_cache") if context.multirun else None
    return MapCache(Path(str(value)).expanduser())


def report_option(cfg: DictConfig) -> tuple[bool, Path | None]:
    """``report``: whether the run writes its HTML report, and the path of the manifest's JSON copy
    (``report=PATH.json``: both; ``true``: the HTML report only; ``false``: neither)."""
    value = cfg.get("report", True)
    if value is None or isinstance(value, bool):
        return bool(value is None or value), None
    text = str(value).strip()
    if text.lower() in ("true", "false", "none", ""):
        return text.lower() in ("true", "none", ""), None
    path = Path(text).expanduser()
    if path.suffix.lower() != ".json":
        raise DvpmvsError(
            f"report={value}: give true (the HTML report, OUT/report.html), false (none) or the "
            f"path of a .json file (the report and a copy of the run's manifest there)"
        )
    return True, path


def _command() -> list[str]:
    """The command that runs this job again, as a user types it: ``dvpmvs``, the subcommand and
    the job's own overrides (a sweep's job: its values; Hydra's own settings, such as the
    plugins' search path the CLI adds, left out). Outside a Hydra job, the process's arguments."""
    from hydra.core.hydra_config import HydraConfig

    if HydraConfig.initialized():
        hydra = HydraConfig.get()
        return ["dvpmvs", hydra.job.name, *hydra.overrides.task]
    return ["dvpmvs", *sys.argv[1:]] if sys.argv else []


# When the subcommand's task started (wall clock, perf_counter): see mark_command_start.
_COMMAND_START: tuple[datetime, float] | None = None


def mark_command_start() -> None:
    """Marks the start of the subcommand (the CLI calls it as the task starts) and starts the
    peak-memory count: the manifests of commands that run the dense stage among other steps
    (demo, reconstruct) give their start, wall time and peak memory from it."""
    global _COMMAND_START
    _COMMAND_START = (datetime.now(timezone.utc), time.perf_counter())
    reset_peak_rss()


def dense_manifest(summary, options, folder: Path, **fields) -> dict:
    """The manifest of a dense stage another command ran (``demo``, ``reconstruct``) into the
    run folder ``folder``: the command, its start, wall time (so far), peak memory and threads,
    the closing summary, the options, the code and the machine, and ``fields``."""
    started, seconds = None, None
    if _COMMAND_START is not None:
        started = _COMMAND_START[0].isoformat(timespec="seconds")
        seconds = time.perf_counter() - _COMMAND_START[1]
    return {
        "dvpmvs": code_identity()["dvpmvs"],
        "status": "ok",
        "command": _command(),
        "started": started,
        "seconds": seconds,
        "peak_rss_mb": peak_rss_mb(),
        "threads": resolve_threads(options.patch_match.num_threads),
        "dense": summary.as_dict(folder),
        "options": asdict(options),
        "code": code_identity(),
        "environment": environment(),
        **fields,
    }


def write_report(out: Path, manifest: dict | None = None, overwrite: bool = False) -> Path | None:
    """The run's HTML report in ``out`` (:func:`dvpmvs.report.write_run_report`); a report that
    cannot be written is a warning, not the run's failure (its maps and cloud are made)."""
    from dvpmvs.report import write_run_report
    from dvpmvs.stage_progress import StepProgress

    try:
        with StepProgress("report", ""):  # a large cloud or mesh takes a while to embed
            path = write_run_report(out, manifest, overwrite=overwrite)
    except Exception as exc:  # noqa: BLE001 - the run's outputs are made; its report is their picture
        log.warning(
            "could not write the run's HTML report in %s: %s: %s", out, type(exc).__name__, exc
        )
        return None
    _console.print(f"report: {path}")
    return path


def check_json_path(path: Path, key: str, overwrite: bool = False) -> None:
    """A JSON report's path: a file (not a folder) in a folder this process can write, and not
    a file dvpmvs did not write (unless ``overwrite``): dvpmvs's JSON reports carry its version
    (``"dvpmvs"``)."""
    if path.is_dir():
        raise DvpmvsError(
            f"{key}={path} is a folder; {key}= names the JSON file to write, e.g. "
            f"{key}={path / 'report.json'}"
        )
    if path.exists() and not overwrite and "dvpmvs" not in (read_json_object(path) or {}):
        raise DvpmvsError(
            f"{key}={path} exists and dvpmvs did not write it; it is not replaced unasked: give "
            f"{key}= another path, or overwrite=true to replace it"
        )
    check_writable(
        path.parent, f"the folder of {key}=", f"give {key}=PATH in a folder you can write"
    )


def _resolved_config(cfg: DictConfig) -> dict:
    return OmegaConf.to_container(cfg, resolve=True)


def _write_manifest(manifest: dict, out: Path, report: Path | None) -> None:
    data = canonical(manifest)
    write_json(out / MANIFEST_NAME, data)
    if report is not None:
        write_json(report, data)


def _sweep_id(context: JobContext) -> str | None:
    if not context.multirun:
        return None
    try:
        return json.loads((context.sweep_dir / SWEEP_FILE).read_text()).get("id")
    except (OSError, ValueError):
        return None


def write_failed_manifest(error: str) -> Path | None:
    """In a sweep's job that stopped before its run wrote a manifest (a wrong option, a
    workspace that does not open), one for it: status ``error`` with the message, so that the
    sweep's table has its row and its failure. Returns its path; None outside a sweep or where
    the job's own manifest of this sweep exists."""
    context = job_context()
    if not context.multirun or context.job_dir is None:
        return None
    path = context.job_dir / MANIFEST_NAME
    sweep_id = _sweep_id(context)
    try:
        if (json.loads(path.read_text()).get("sweep") or {}).get("id") == sweep_id:
            return None
    except (OSError, ValueError, AttributeError):
        pass
    manifest = {
        "dvpmvs": code_identity()["dvpmvs"],
        "status": "error",
        "error": error,
        "started": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "command": _command(),
        "overrides": list(context.overrides),
        "sweep": {"dir": str(context.sweep_dir), "job": context.num, "id": sweep_id},
    }
    try:
        context.job_dir.mkdir(parents=True, exist_ok=True)
        _write_manifest(manifest, context.job_dir, None)
    except OSError as exc:
        log.warning("could not write the failed job's manifest: %s", exc)
        return None
    return path


def scoring_hooks(cfg: DictConfig, workspace_root: Path) -> list[Callable]:
    """The installed scoring hooks (entry points of :data:`SCORING_GROUP`, by name), each called
    with the run's config and workspace folder before anything is computed (a hook checks its
    own options then) and returning what scores the finished run,
    ``score(workspace, summary, options, out, threads) -> dict | None``, or None.

    A hook whose code cannot be imported (its package removed, a dependency missing) is left
    out with a warning: the run computes its maps and cloud, unscored."""
    from dvpmvs.registry import load_entry_points

    hooks = []
    for _name, make in load_entry_points(SCORING_GROUP, "scoring hook"):
        score = make(cfg, workspace_root)
        if score is not None:
            hooks.append(score)
    return hooks


def run_dense_job(cfg: DictConfig, workspace, options, scene: dict | None = None) -> int:
    """The dense stage on ``workspace`` with ``options`` into the run's output folder, then the
    scoring hooks' scores and the manifest (with ``scene``, the identity of a rendered scene,
    when given); returns the exit status."""
    import cv2

    context = job_context()
    out = _path_option(cfg, "out") or (context.job_dir if context.multirun else workspace.root)
    html, report = report_option(cfg)
    scorers = scoring_hooks(
        cfg, workspace.root
    )  # a wrong evaluate.* option stops the run before it computes
    if report is not None:
        check_json_path(report, "report", options.overwrite)
    threads = _threads(int(cfg.num_threads), context)
    cv2.setNumThreads(threads)
    options = replace(
        options,
        patch_match=replace(options.patch_match, num_threads=threads),
        fusion=replace(options.fusion, num_threads=threads),
    )
    manifest = {
        "dvpmvs": code_identity()["dvpmvs"],
        "status": "running",
        "started": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "command": _command(),
        "overrides": list(context.overrides),
        "sweep": None
        if not context.multirun
        else {
            "dir": str(Path(context.sweep_dir).absolute()),
            "job": context.num,
            "id": _sweep_id(context),
        },
        # Absolute: never relative to the folder the command ran in. Paths of the run's own
        # files are relative to the run folder (DenseSummary.as_dict).
        "workspace": str(workspace.root.absolute()),
        "scene": scene,
        "out": str(Path(out).absolute()),
        "threads": threads,
        "config": _resolved_config(cfg),
        "options": asdict(options),
        "code": code_identity(),
        "environment": environment(),
    }
    reset_peak_rss()
    start = time.perf_counter()
    # A run stopped by a check before its start (a locked or read-only folder, foreign maps)
    # changed nothing, so it leaves the folder's manifest (maybe another run's) as it was; a
    # sweep's job always writes one into its own folder, for the sweep's table.
    started = {"yes": context.multirun}
    try:
        print_workspace_summary(workspace)
        summary = run_dense(
            workspace,
            options,
            output=_path_option(cfg, "output"),
            out=out,
            progress=progress_enabled(cfg),
            cache=_cache(cfg, context),
            on_start=lambda: started.update(yes=True),
            executor=executor_options(cfg),
        )
        print_summary(summary)
        manifest["dense"] = summary.as_dict(out)
        manifest["evaluation"] = None
        for score in scorers:
            scores = score(workspace, summary, options, out, threads)
            if scores is not None:
                manifest["evaluation"] = {**(manifest["evaluation"] or {}), **scores}
        manifest["status"] = "ok"
        return 0
    except DvpmvsError as exc:
        manifest["status"], manifest["error"] = "error", str(exc)
        raise
    except Interrupted as stop:
        manifest["status"], manifest["error"] = "interrupted", stop.progress or "interrupted"
        raise
    finally:
        manifest["seconds"] = time.perf_counter() - start
        manifest["peak_rss_mb"] = peak_rss_mb()
        if manifest["status"] == "running":  # an exception other than a user error
            manifest["status"] = "error"
        if started["yes"]:
            try:
                out.mkdir(parents=True, exist_ok=True)
                _write_manifest(manifest, out, report)
                _console.print(
                    f"manifest: {out / MANIFEST_NAME}" + (f" (and {report})" if report else "")
                )
            except OSError as exc:  # the run's own error, if any, is the one to report
                log.warning("could not write the run's manifest: %s", exc)
            if html and manifest["status"] == "ok":
                write_report(out, manifest, overwrite=options.overwrite)
