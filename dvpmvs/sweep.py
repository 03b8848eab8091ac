"""The table at the end of a sweep: a Hydra callback that reads the jobs' manifests.

``dvpmvs dense -m ...`` and ``dvpmvs bench -m ...`` register :class:`SweepTable` (``hydra.callbacks``).
At the start of a multirun it marks the sweep folder with a fresh sweep id (``sweep.json``); every
job writes its manifest (:mod:`dvpmvs.run`) into its own folder with that id; at the
end the callback gathers the manifests that carry it (a sweep folder reused by another sweep
keeps its old jobs out of the table) and writes ``table.md`` and ``table.csv`` beside them:

- one row per job, named by the overrides that differ between the jobs, with the columns the
  installed table plugins give (:class:`TableColumns`; the harness's: F1 / completeness /
  accuracy at each tolerance, the layout of the paper's Table IV, and where measured the depth
  maps' share within 1 % and COLMAP's fusion's F1), then seconds per view, points and peak memory;
- where the jobs also differ in their scene (``workspace``, or a plugin's scene keys), the same
  table with one row per configuration, averaged over the scenes;
- where one parameter alone is swept, its values as columns with the plugins' headline columns
  (the harness's F1 at each tolerance) below them (the layout of the paper's Table V);
- where the estimator's ``seed`` is swept, the rows that differ only by it folded into one per
  configuration and scene: each metric's mean over the seeds with its spread (min-max), so that a
  difference between configurations can be read against the random draws' noise; the scenes'
  mean then gives the spread of the seeds' scene means. ``table.csv`` then holds the folded rows
  (``seeds``, each metric's mean, ``min`` and ``max``) and ``jobs.csv`` one row per job.
"""

from __future__ import annotations

import csv
import io
import json
import logging
import sys
import uuid
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

from hydra.experimental.callback import Callback
from omegaconf import DictConfig, OmegaConf

__all__ = [
    "SweepTable",
    "JobRow",
    "TableColumns",
    "TABLE_COLUMNS_GROUP",
    "SeedGroup",
    "fold_seeds",
    "read_jobs",
    "write_tables",
    "render_markdown",
    "render_csv",
    "render_seeds_csv",
    "write_report",
    "FAILED_JOBS",
]

log = logging.getLogger(__name__)

# The override that names the data a job ran on, not its configuration (plugins add theirs; a
# sweep over the image size or the view count is a study of the configuration: those stay columns
# of their own).
SCENE_KEYS = ("workspace",)
# The columns every job has (the run's own figures), after the plugins'.
RUN_COLUMNS = ("s/view", "points", "peak MB")
# The estimator's seed: swept to measure the random draws' noise, folded into a mean and a spread.
SEED_KEY = "seed"

# Failed jobs of the last sweep in this process (the command's exit status reads it: jobs that
# run in other processes, under the joblib launcher, report through their manifests).
FAILED_JOBS: list[str] = []


TABLE_COLUMNS_GROUP = "dvpmvs.table_columns"


def _never(name: str) -> bool:
    return False


@dataclass(frozen=True)
class TableColumns:
    """What a plugin adds to a sweep's tables (an object registered in the entry-point group
    :data:`TABLE_COLUMNS_GROUP`; the harness registers the scores against ground truth).

    ``columns(manifest)``: a job's columns from its manifest (:mod:`dvpmvs.run`), name -> value
    as printed (percentages in percent), in table order; ``{}`` where the job has none.
    ``headline(name)``: the columns shown with their spread over the estimator's seeds and in
    the one-parameter table. ``scene_keys``: the override keys that name the data a job ran on
    rather than its configuration (the tables average over them)."""

    columns: Callable[[dict], dict[str, float]]
    headline: Callable[[str], bool] = _never
    scene_keys: tuple[str, ...] = ()


def _table_plugins() -> list[TableColumns]:
    from dvpmvs.registry import PluginError, load_entry_points

    plugins = []
    for name, plugin in load_entry_points(TABLE_COLUMNS_GROUP, "table columns"):
        if not isinstance(plugin, TableColumns):
            raise PluginError(
                f"the table columns {name!r} ({TABLE_COLUMNS_GROUP}) are a {type(plugin).__name__}, "
                f"not a dvpmvs.sweep.TableColumns"
            )
        plugins.append(plugin)
    return plugins


@dataclass
class JobRow:
    """One job of a sweep: its overrides, status and columns (``metrics``, in table order);
    ``headline`` and ``scene_keys`` as its table plugins (:class:`TableColumns`) name them."""

    num: int
    folder: Path
    overrides: dict[str, str]
    status: str
    metrics: dict[str, float] = field(default_factory=dict)
    headline: frozenset[str] = frozenset()
    scene_keys: frozenset[str] = frozenset(SCENE_KEYS)
    error: str = ""
    scene_digest: str = ""  # the rendered scene's digest (bench), short form


def _parse_overrides(overrides: list[str]) -> dict[str, str]:
    parsed = {}
    for item in overrides:
        key, _, value = str(item).partition("=")
        key = key.lstrip("+~")
        if key.startswith("hydra.") or key.startswith("hydra/"):
            continue
        parsed[key] = value
    return parsed


def _run_metrics(manifest: dict) -> dict[str, float]:
    """The run's own columns (:data:`RUN_COLUMNS`)."""
    metrics: dict[str, float] = {}
    dense = manifest.get("dense") or {}
    if "seconds_per_view" in dense:
        metrics["s/view"] = float(dense["seconds_per_view"])
        metrics["points"] = float((dense.get("fusion") or {}).get("points", 0))
    if manifest.get("peak_rss_mb") is not None:
        metrics["peak MB"] = float(manifest["peak_rss_mb"])
    return metrics


def job_row(manifest: dict, folder: Path, plugins: list[TableColumns]) -> JobRow:
    """A job's row from its manifest, with the columns of the table ``plugins``."""
    metrics: dict[str, float] = {}
    for plugin in plugins:
        metrics.update(plugin.columns(manifest))
    metrics.update(_run_metrics(manifest))
    sweep = manifest.get("sweep") or {}
    scene = manifest.get("scene") or {}
    return JobRow(
        int(sweep.get("job", -1)),
        folder,
        _parse_overrides(manifest.get("overrides", [])),
        str(manifest.get("status")),
        metrics,
        headline=frozenset(c for c in metrics for p in plugins if p.headline(c)),
        scene_keys=frozenset(SCENE_KEYS).union(*(p.scene_keys for p in plugins)),
        error=str(manifest.get("error", "")),
        scene_digest=str(scene.get("short", "")),
    )


def read_jobs(sweep_dir: Path, sweep_id: str | None = None) -> list[JobRow]:
    """The jobs of the sweep in ``sweep_dir`` (those of sweep ``sweep_id`` when given), by
    number, with the columns of the installed table plugins."""
    from dvpmvs.run import MANIFEST_NAME

    plugins = _table_plugins()
    rows = []
    for path in sorted(sweep_dir.glob(f"*/{MANIFEST_NAME}")):
        try:
            manifest = json.loads(path.read_text())
        except (OSError, ValueError):
            log.warning("%s is unreadable; its job is left out of the table", path)
            continue
        sweep = manifest.get("sweep") or {}
        if sweep_id is not None and sweep.get("id") != sweep_id:
            continue
        rows.append(job_row(manifest, path.parent, plugins))
    return sorted(rows, key=lambda row: row.num)


def sweep_jobs(sweep_dir: Path) -> list[JobRow]:
    """The jobs of the sweep whose folder is ``sweep_dir``, as :func:`read_jobs` reads them, for
    a report written after the sweep: only those of its last sweep (``sweep.json``'s id), and a
    job the sweep ran whose folder or manifest is gone since is a row of status ``missing`` (it
    is neither averaged nor dropped unseen)."""
    from dvpmvs.maps import read_json_object
    from dvpmvs.run import SWEEP_FILE

    record = read_json_object(sweep_dir / SWEEP_FILE) or {}
    sweep_id = record.get("id") if isinstance(record.get("id"), str) else None
    rows = read_jobs(sweep_dir, sweep_id)
    found = {row.num for row in rows}
    recorded = record.get("jobs") if isinstance(record.get("jobs"), list) else []
    for job in recorded:
        if not isinstance(job, dict) or not isinstance(job.get("job"), int):
            continue
        if job["job"] in found:
            continue
        overrides = job.get("overrides") if isinstance(job.get("overrides"), dict) else {}
        folder = sweep_dir / str(job.get("folder", job["job"]))
        rows.append(
            JobRow(
                job["job"],
                folder,
                {str(k): str(v) for k, v in overrides.items()},
                "missing",
                error=f"its manifest {folder / 'dvpmvs_run.json'} is gone since the sweep ran "
                "(table.md kept its figures)",
            )
        )
    return sorted(rows, key=lambda row: row.num)


def _swept_keys(rows: list[JobRow]) -> list[str]:
    """The override keys whose values differ between the jobs, in command-line order."""
    keys: list[str] = []
    for row in rows:
        for key in row.overrides:
            if key not in keys:
                keys.append(key)
    return [k for k in keys if len({row.overrides.get(k) for row in rows}) > 1]


def _metric_columns(rows: list[JobRow]) -> list[str]:
    """The columns of the jobs, in their order (a job without some keeps the others' order),
    the run's own last."""
    columns: list[str] = []
    for row in rows:
        columns += [c for c in row.metrics if c not in columns]
    return sorted(columns, key=lambda c: c in RUN_COLUMNS)


def _headline(rows: list[JobRow]) -> frozenset[str]:
    return frozenset().union(*(row.headline for row in rows))


def _format(name: str, value: float | None) -> str:
    if value is None:
        return "-"
    if name == "points":
        return f"{value:,.0f}"
    if name in ("peak MB",):
        return f"{value:.0f}"
    if name == "s/view":
        return f"{value:.1f}"
    return f"{value:.2f}"


def _markdown(header: list[str], body: list[list[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(cells) + " |" for cells in body]
    return "\n".join(lines)


def _label(row: JobRow, keys: list[str]) -> str:
    return " ".join(f"{k}={row.overrides.get(k, '')}" for k in keys) or "(no overrides)"


def _mean(values: list[float]) -> float | None:
    return sum(values) / len(values) if values else None


def _spread(values: list[float]) -> tuple[float, float] | None:
    return (min(values), max(values)) if values else None


def _with_spread(
    name: str, mean: float | None, spread: tuple[float, float] | None, headline: frozenset[str]
) -> str:
    """A cell: the mean and, for a headline column, its spread over the seeds (min-max)."""
    if mean is None or spread is None or name not in headline:
        return _format(name, mean)
    return f"{_format(name, mean)} ({_format(name, spread[0])}-{_format(name, spread[1])})"


@dataclass
class SeedGroup:
    """The jobs that differ only by the estimator's seed: one configuration on one scene."""

    label: str
    overrides: dict[str, str]
    rows: list[JobRow]

    @property
    def ok(self) -> list[JobRow]:
        return [r for r in self.rows if r.status == "ok"]

    def values(self, column: str) -> list[float]:
        return [r.metrics[column] for r in self.ok if column in r.metrics]


def fold_seeds(rows: list[JobRow]) -> list[SeedGroup]:
    """The jobs grouped by everything swept but the estimator's seed, in job order."""
    keys = [k for k in _swept_keys(rows) if k != SEED_KEY]
    groups: dict[str, SeedGroup] = {}
    for row in rows:
        label = _label(row, keys)
        if label not in groups:
            groups[label] = SeedGroup(label, {k: row.overrides.get(k, "") for k in keys}, [])
        groups[label].rows.append(row)
    return list(groups.values())


def _values(rows: list[JobRow], key: str) -> list[str]:
    """The values ``key`` takes in the jobs, in job order, each once."""
    values: list[str] = []
    for row in rows:
        if row.overrides.get(key) not in values:
            values.append(row.overrides.get(key))
    return values


def _job_table(rows: list[JobRow]) -> tuple[list[str], list[list[str]]]:
    """The jobs one by one: the header and, per job, its cells (overrides, status, scene digest,
    metrics)."""
    swept = _swept_keys(rows)
    columns = _metric_columns(rows)
    digests = any(row.scene_digest for row in rows)
    header = [
        " ".join(swept) or "overrides",
        "status",
        *(["scene digest"] if digests else []),
        *columns,
    ]
    body = [
        [
            _label(row, swept),
            row.status,
            *([row.scene_digest or "-"] if digests else []),
            *(_format(c, row.metrics.get(c)) for c in columns),
        ]
        for row in rows
    ]
    return header, body


def render_markdown(rows: list[JobRow], per_job: bool = True) -> str:
    """The sweep's tables in Markdown (see the module doc); ``per_job=False``: without the table
    of the jobs one by one (the HTML report has its own)."""
    swept = _swept_keys(rows)
    by_seed = SEED_KEY in swept
    data_keys = frozenset().union(*(row.scene_keys for row in rows))
    config_keys = [k for k in swept if k not in data_keys and k != SEED_KEY]
    scene_keys = [k for k in swept if k in data_keys]
    columns = _metric_columns(rows)
    headline = _headline(rows)
    # The columns given with their spread over the seeds, as the tables' notes name them.
    spread_of = ", ".join(c for c in columns if c in headline)
    seeds = _values(rows, SEED_KEY) if by_seed else []
    parts = []
    if scene_keys:
        groups: dict[str, list[JobRow]] = {}
        for row in rows:
            groups.setdefault(_label(row, config_keys), []).append(row)
        scenes = sorted({_label(row, scene_keys) for row in rows})
        body = []
        for label, members in groups.items():
            ok = [r for r in members if r.status == "ok"]
            cells = [label, f"{len(ok)}/{len(scenes) * max(1, len(seeds))}"]
            for c in columns:
                spread = None
                if (
                    by_seed
                ):  # the spread of the seeds' scene means, over seeds whose every scene ran
                    means = []
                    for seed in seeds:
                        of_seed = [
                            r for r in ok if r.overrides.get(SEED_KEY) == seed and c in r.metrics
                        ]
                        if len(of_seed) == len(scenes):
                            means.append(_mean([r.metrics[c] for r in of_seed]))
                    spread = _spread(means)
                cells.append(
                    _with_spread(
                        c, _mean([r.metrics[c] for r in ok if c in r.metrics]), spread, headline
                    )
                )
            body.append(cells)
        over = (
            f" and the estimator's seeds ({', '.join(seeds)}"
            + (f"; {spread_of}: mean (min-max of the seeds' scene means))" if spread_of else ")")
            if by_seed
            else ""
        )
        parts.append(
            f"Mean over the scenes ({', '.join(scenes)}){over}:\n\n"
            + _markdown(
                [
                    " ".join(config_keys) or "configuration",
                    "jobs" if by_seed else "scenes",
                    *columns,
                ],
                body,
            )
        )
    if by_seed:
        body = []
        for group in fold_seeds(rows):
            cells = [group.label, f"{len(group.ok)}/{len(group.rows)}"]
            cells += [
                _with_spread(c, _mean(group.values(c)), _spread(group.values(c)), headline)
                for c in columns
            ]
            body.append(cells)
        keys = [k for k in swept if k != SEED_KEY]
        parts.append(
            f"Over the estimator's seeds ({', '.join(seeds)})"
            + (f"; {spread_of}: mean (min-max)" if spread_of else "; means")
            + ":\n\n"
            + _markdown([" ".join(keys) or "configuration", "seeds", *columns], body)
        )
    if per_job:
        header, body = _job_table(rows)
        body = [
            [
                str(row.num),
                cells[0],
                row.status if row.status == "ok" else f"**{row.status}**",
                *cells[2:],
            ]
            for row, cells in zip(rows, body)
        ]  # a failure stands out in the Markdown
        parts.append("Per job:\n\n" + _markdown(["job", *header], body))
    if len(config_keys) == 1:
        key = config_keys[0]
        values = _values(rows, key)
        body = []
        for c in [c for c in columns if c in headline]:
            cells = [c]
            for value in values:
                ok = [
                    r
                    for r in rows
                    if r.overrides.get(key) == value and r.status == "ok" and c in r.metrics
                ]
                cells.append(_format(c, _mean([r.metrics[c] for r in ok])))
            body.append(cells)
        if body:
            over = scene_keys + ([SEED_KEY] if by_seed else [])
            note = f" (mean over {', '.join(over)})" if over else ""
            parts.append(f"{key}{note}:\n\n" + _markdown([key, *values], body))
    failed = [row for row in rows if row.status != "ok"]
    if failed:
        parts.append(
            (
                "Failed or missing jobs"
                if any(r.status == "missing" for r in failed)
                else "Failed jobs"
            )
            + ":\n\n"
            + "\n".join(f"- job {r.num} ({r.folder}): {r.error or r.status}" for r in failed)
        )
    return "\n\n".join(parts) + "\n"


def render_seeds_csv(rows: list[JobRow]) -> str:
    """One row per configuration and scene, the estimator's seeds folded: ``seeds`` (that ran
    of those swept), each metric's mean and its ``min`` and ``max``."""
    groups = fold_seeds(rows)
    keys = [k for k in groups[0].overrides] if groups else []
    columns = _metric_columns(rows)
    buffer = io.StringIO()
    writer = csv.writer(buffer)
    writer.writerow(
        [
            *keys,
            "seeds",
            *[f"{c}{suffix}" for c in columns for suffix in ("", " min", " max")],
            "scene digest",
        ]
    )
    for group in groups:
        cells = [*[group.overrides[k] for k in keys], f"{len(group.ok)}/{len(group.rows)}"]
        for c in columns:
            values = group.values(c)
            cells += (
                ["", "", ""]
                if not values
                else [f"{v:.6g}" for v in (_mean(values), min(values), max(values))]
            )
        writer.writerow(
            [*cells, " ".join(sorted({r.scene_digest for r in group.rows if r.scene_digest}))]
        )
    return buffer.getvalue()


def render_csv(rows: list[JobRow]) -> str:
    keys: list[str] = []
    for row in rows:
        keys += [k for k in row.overrides if k not in keys]
    columns = _metric_columns(rows)
    buffer = io.StringIO()
    writer = csv.writer(buffer)
    writer.writerow(["job", "folder", "status", *keys, *columns, "scene digest", "error"])
    for row in rows:
        writer.writerow(
            [
                row.num,
                str(row.folder),
                row.status,
                *[row.overrides.get(k, "") for k in keys],
                *["" if row.metrics.get(c) is None else f"{row.metrics[c]:.6g}" for c in columns],
                row.scene_digest,
                row.error if row.status != "ok" else "",
            ]
        )
    return buffer.getvalue()


def write_tables(sweep_dir: Path, rows: list[JobRow]) -> str:
    """Write ``table.md`` and ``table.csv`` into ``sweep_dir`` (and ``jobs.csv``, the jobs one by
    one, when the estimator's seed is swept and ``table.csv`` folds it); returns the Markdown."""
    from dvpmvs.maps import atomic_path

    markdown = render_markdown(rows)
    with atomic_path(sweep_dir / "table.md") as tmp:
        tmp.write_text(markdown)
    by_seed = SEED_KEY in _swept_keys(rows)
    with atomic_path(sweep_dir / "table.csv") as tmp:
        tmp.write_text(render_seeds_csv(rows) if by_seed else render_csv(rows))
    if by_seed:
        with atomic_path(sweep_dir / "jobs.csv") as tmp:
            tmp.write_text(render_csv(rows))
    return markdown


def write_report(sweep_dir: Path, rows: list[JobRow], overwrite: bool = False) -> Path | None:
    """The sweep's HTML report, ``report.html`` in ``sweep_dir``: its jobs (sortable, each linking
    to its job's report), table.md's summaries and the jobs' clouds side by side
    (:func:`dvpmvs.report.write_sweep_report`). A report that cannot be written is a warning: the
    tables are written."""
    from dvpmvs.report import write_sweep_report

    header, body = _job_table(rows)
    jobs = [
        {"label": f"job {row.num}", "folder": row.folder, "cells": cells}
        for row, cells in zip(rows, body)
    ]
    summaries = render_markdown(rows, per_job=False) if rows else ""
    try:
        return write_sweep_report(
            sweep_dir, header, jobs, summary_markdown=summaries, overwrite=overwrite
        )
    except Exception as exc:  # noqa: BLE001 - the sweep's tables are written; the report is their picture
        log.warning(
            "could not write the sweep's HTML report in %s: %s: %s",
            sweep_dir,
            type(exc).__name__,
            exc,
        )
        return None


class SweepTable(Callback):
    """Marks a multirun's folder with a sweep id, then tabulates its jobs' manifests."""

    def __init__(self) -> None:
        self.sweep_id: str | None = None

    def on_multirun_start(self, config: DictConfig, **kwargs: Any) -> None:
        from dvpmvs.maps import atomic_path
        from dvpmvs.run import SWEEP_FILE

        sweep_dir = Path(str(config.hydra.sweep.dir))
        sweep_dir.mkdir(parents=True, exist_ok=True)
        self.sweep_id = uuid.uuid4().hex
        with atomic_path(sweep_dir / SWEEP_FILE) as tmp:
            tmp.write_text(
                json.dumps(
                    {
                        "id": self.sweep_id,
                        "started": datetime.now(timezone.utc).isoformat(timespec="seconds"),
                    }
                )
            )
        FAILED_JOBS.clear()

    def _record_jobs(self, sweep_dir: Path, rows: list[JobRow]) -> None:
        """``sweep.json`` also names the sweep's jobs, so that a report written later tells a job
        whose folder was deleted from one the sweep never ran."""
        from dvpmvs.maps import read_json_object, write_json
        from dvpmvs.run import SWEEP_FILE

        record = read_json_object(sweep_dir / SWEEP_FILE) or {"id": self.sweep_id}
        record["jobs"] = [
            {
                "job": row.num,
                "folder": row.folder.relative_to(sweep_dir).as_posix()
                if row.folder.is_relative_to(sweep_dir)
                else str(row.folder),
                "overrides": row.overrides,
            }
            for row in rows
        ]
        write_json(sweep_dir / SWEEP_FILE, record)

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        sweep_dir = Path(str(config.hydra.sweep.dir))
        rows = read_jobs(sweep_dir, self.sweep_id)
        FAILED_JOBS[:] = [str(row.folder) for row in rows if row.status != "ok"]
        if not rows:
            return
        self._record_jobs(sweep_dir, rows)
        markdown = write_tables(sweep_dir, rows)
        if OmegaConf.select(config, "report", default=True) is not False:
            write_report(sweep_dir, rows)
        # Plain Markdown: it reads in any terminal width and pastes into a document as it is.
        failed = f", {len(FAILED_JOBS)} failed" if FAILED_JOBS else ""
        print(
            f"\n{markdown}\nsweep: {sweep_dir} ({len(rows)} jobs{failed}); tables: {sweep_dir / 'table.md'}, "
            f"{sweep_dir / 'table.csv'}",
            file=sys.stderr,
            flush=True,
        )
