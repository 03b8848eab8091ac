"""A dense run as the ``dense`` and ``bench`` commands run it.

Around :func:`dvpmvs.pipeline.run_dense` this adds what belongs to a run rather than to the
method: where its outputs go (the workspace, ``out=DIR``, or under a Hydra multirun each job's
own folder, the workspace then only read), the map cache the jobs of a sweep share, the thread
count of jobs run side by side (Hydra's joblib launcher), the scores of the fused cloud against
ground truth (``evaluate.*``; a synthetic workspace's own ``ground_truth/`` by default), and the
run's *manifest*: ``OUT/dvpmvs_run.json`` (and ``report=PATH``), with the resolved config, the
code and library versions, per-pass timings, the scores and the closing summary, so that every
figure can be traced to what produced it. :mod:`dvpmvs.evaluation.sweep` builds the sweep's
table from the jobs' manifests.
"""

from __future__ import annotations

import json
import logging
import os
import sys
import time
from dataclasses import asdict, dataclass, replace
from datetime import datetime, timezone
from pathlib import Path

from omegaconf import DictConfig, OmegaConf
from rich.console import Console

from dvpmvs.errors import DvpmvsError, Interrupted
from dvpmvs.digests import file_digest, fingerprint, sources_digest
from dvpmvs.provenance import code_identity, environment

__all__ = ["MANIFEST_NAME", "JobContext", "job_context", "run_dense_job", "score_cloud", "job_ground_truth", "peak_rss_mb"]

log = logging.getLogger(__name__)
_console = Console(stderr=True)

MANIFEST_NAME = "dvpmvs_run.json"
SWEEP_FILE = "sweep.json"  # written by the sweep table callback at the start of a multirun


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
    return JobContext(True, Path(hc.runtime.output_dir), Path(hc.sweep.dir), int(hc.job.num), overrides, parallel)


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
    if requested > 0:
        return requested
    return max(1, (os.cpu_count() or 1) // context.parallel_jobs)


def _path_option(cfg: DictConfig, key: str) -> Path | None:
    value = cfg.get(key)
    if value is None or value is False or str(value).lower() in ("", "none", "false"):
        return None
    return Path(str(value)).expanduser()


def _cache(cfg: DictConfig, context: JobContext):
    """The map cache: ``cache=DIR``; in a sweep by default ``<sweep folder's parent>/map_cache``,
    shared by the sweeps beside it; ``cache=false``: none."""
    from dvpmvs.provenance import MapCache

    value = cfg.get("cache")
    if value is False or (isinstance(value, str) and value.lower() in ("false", "none")):
        return None
    if value is None:
        return MapCache(context.sweep_dir.parent / "map_cache") if context.multirun else None
    return MapCache(Path(str(value)).expanduser())


def _ground_truth(cfg: DictConfig, workspace_root: Path) -> Path | None:
    value = OmegaConf.select(cfg, "evaluate.ground_truth", default="auto")
    if value is None or str(value).lower() in ("none", "false", ""):
        return None
    if str(value) == "auto":
        found = workspace_root / "ground_truth" / "scan_alignment.mlp"
        return found if found.is_file() else None
    path = Path(str(value)).expanduser()
    if not path.is_file():
        raise DvpmvsError(f"evaluate.ground_truth: {path} does not exist (an ETH3D scan_alignment.mlp or a PLY)")
    return path


def _ground_truth_digest(path: Path) -> dict:
    from dvpmvs.evaluation.pointclouds import read_meshlab_project

    files = [path] + ([scan.path for scan in read_meshlab_project(path, load_points=False)]
                      if path.suffix.lower() == ".mlp" else [])
    sidecar = path.parent / "eth3d_parameters.json"
    if sidecar.is_file():
        files.append(sidecar)
    return {str(f): file_digest(f) for f in files}


def job_ground_truth(job: Path) -> Path:
    """The ETH3D ground truth (``ground_truth/scan_alignment.mlp``) of the workspace a job's
    manifest names; a relative workspace is looked up from the folders above the job's (where
    the sweep ran)."""
    manifest = json.loads((job / MANIFEST_NAME).read_text())
    mlp = Path(manifest["workspace"]) / "ground_truth" / "scan_alignment.mlp"
    for base in ([Path()] if mlp.is_absolute() else [Path(), *job.resolve().parents]):
        if (base / mlp).is_file():
            return base / mlp
    raise DvpmvsError(f"{job}: the ground truth of its workspace, {mlp}, is not found")


def score_cloud(cloud: Path, ground_truth: Path, tolerances: list[float], report: Path) -> dict:
    """The ETH3D metric of ``cloud`` against ``ground_truth`` (beam parameters from
    ``eth3d_parameters.json`` beside it, else the official ones), kept in ``report`` with the
    fingerprint of its inputs (the cloud's and ground truth's bytes, the tolerances, the code):
    a rerun with the same inputs reads it back instead of scoring again."""
    from dvpmvs.evaluation.commands import eth3d_parameters_for
    from dvpmvs.evaluation.eth3d_metric import evaluate_eth3d
    from dvpmvs.evaluation.pointclouds import load_ground_truth, read_points
    from dvpmvs.evaluation.report import write_json

    inputs = {"cloud": file_digest(cloud), "ground_truth": _ground_truth_digest(ground_truth),
              "tolerances": [float(t) for t in tolerances], "code": code_identity(),
              "evaluation_code": sources_digest(Path(__file__).resolve().parent)}
    fp = fingerprint(inputs)
    if report.is_file():
        try:
            stored = json.loads(report.read_text())
            if stored.get("fingerprint") == fp:
                return stored["result"]
        except (OSError, ValueError, KeyError):
            pass
    params = eth3d_parameters_for(ground_truth)
    start = time.perf_counter()
    points = read_points(cloud)
    result = evaluate_eth3d(points, load_ground_truth(ground_truth), tolerances, params)
    data = {**result.as_dict(), "reconstruction": str(cloud), "ground_truth": str(ground_truth),
            "reconstruction_points": int(len(points)), "seconds": round(time.perf_counter() - start, 3),
            "parameters": {"voxel_size": params.voxel_size, "beam_start_radius_meters": params.beam_start_radius_meters,
                           "beam_divergence_halfangle_deg": params.beam_divergence_halfangle_deg}}
    write_json(report, {"fingerprint": fp, "inputs": inputs, "result": data})
    return data


def _score_depth_maps(stereo: Path, truth: Path, pass_value: str) -> dict:
    import numpy as np

    from dvpmvs.evaluation.depth_metrics import evaluate_depth_maps, pooled_highlight_shares, \
        pooled_textureless_shares

    views = evaluate_depth_maps(stereo / "depth_maps", truth, suffix=f".{pass_value}.bin")
    return {"within_1_percent": float(np.mean([v.within_1_percent for v in views])),
            "within_2_cm": float(np.mean([v.within_2_cm for v in views])),
            "estimated": float(np.mean([v.estimated for v in views])), "views": len(views),
            **pooled_highlight_shares(views), **pooled_textureless_shares(views)}


def _sky_points(cloud: Path, workspace, truth: Path) -> float | None:
    """The share of the cloud's points in open sky (:func:`sky_point_share`), where the ground
    truth has sky; None where it has none."""
    from dvpmvs.evaluation.depth_metrics import sky_point_share
    from dvpmvs.evaluation.pointclouds import read_points
    from dvpmvs.maps import read_depth_map

    views = workspace.reference_views()
    truths = [read_depth_map(truth / f"{view.name}.bin") for view in views]
    if not any((t <= 0).any() for t in truths):
        return None
    return sky_point_share(read_points(cloud), [(view.K, view.R, view.t) for view in views], truths)


@dataclass(frozen=True)
class _Scoring:
    """The ``evaluate.*`` options, checked before the run computes anything."""

    ground_truth: Path | None
    tolerances: list[float]
    depth_maps: bool
    colmap_fusion: bool


def _scoring(cfg: DictConfig, workspace_root: Path) -> _Scoring:
    from dvpmvs.config import ConfigError, number_list
    from dvpmvs.validation import check_value

    section = OmegaConf.select(cfg, "evaluate", default=None) or OmegaConf.create({})
    tolerances = number_list(section.get("tolerances", [0.02, 0.1]), "evaluate.tolerances",
                             "[0.02,0.1] (metres)")
    flags = {}
    for key, default in (("depth_maps", True), ("colmap_fusion", False)):
        try:
            flags[key] = check_value(f"evaluate.{key}", section.get(key, default), (bool,))
        except ValueError as exc:
            raise ConfigError(str(exc)) from None
    return _Scoring(_ground_truth(cfg, workspace_root), tolerances, flags["depth_maps"], flags["colmap_fusion"])


def _evaluate(scoring: _Scoring, workspace, summary, options, out: Path, threads: int) -> dict | None:
    """Scores of the run's cloud (and, if asked, COLMAP's fusion of the same maps) and of its
    depth maps, where ground truth is known; None where it is not."""
    from dvpmvs.fusion import fuse_with_colmap
    from dvpmvs.evaluation.report import print_eth3d_table
    from dvpmvs.evaluation.eth3d_metric import ETH3DResult

    gt, tolerances = scoring.ground_truth, scoring.tolerances
    if gt is None or summary.output is None:
        return None
    folder = out / "evaluation"
    scores = {"ground_truth": str(gt), "eth3d": score_cloud(summary.output, gt, tolerances, folder / "eth3d.json")}
    result = scores["eth3d"]
    print_eth3d_table(ETH3DResult(result["tolerances"], result["accuracy"], result["completeness"]),
                      title=f"ETH3D evaluation of {summary.output} ({result['reconstruction_points']:,} points)",
                      console=_console)
    if scoring.colmap_fusion:
        cloud = out / "fused_colmap.ply"
        fusion = replace(options.fusion, input_type=options.final_pass.value, num_threads=threads)
        fuse_with_colmap(workspace, cloud, fusion, root=out)
        scores["colmap_fusion"] = score_cloud(cloud, gt, tolerances, folder / "eth3d_colmap_fusion.json")
    truth = gt.parent / "depth_maps"
    if scoring.depth_maps and truth.is_dir():
        if _same_size(summary.stereo_dir, truth, workspace.reference_views()[0].name, options.final_pass.value):
            scores["depth_maps"] = _score_depth_maps(summary.stereo_dir, truth, options.final_pass.value)
            scores["sky_points"] = _sky_points(summary.output, workspace, truth)
        else:
            log.info("depth maps not scored: their ground truth has another size (max_image_size)")
    masks = summary.stereo_dir / "highlights"
    if (gt.parent / "highlights").is_dir() and any(masks.glob("*.mask.bin")):
        # The masks have the maps' size (max_image_size), the ground truth the images'.
        if truth.is_dir() and _same_size(summary.stereo_dir, truth, workspace.reference_views()[0].name,
                                         options.final_pass.value):
            scores["highlight_masks"] = _score_highlight_masks(masks, gt.parent / "highlights")
        else:
            log.info("highlight masks not scored: their ground truth has another size (max_image_size)")
    return scores


def _score_highlight_masks(masks: Path, truth: Path) -> dict:
    from dvpmvs.evaluation.highlight_metrics import evaluate_highlight_masks, pooled_mask_metrics

    final = pooled_mask_metrics(evaluate_highlight_masks(masks, truth, "final"))
    single = pooled_mask_metrics(evaluate_highlight_masks(masks, truth, "single"))
    return {**final.as_dict(), "single_view": single.as_dict()}


def _same_size(stereo: Path, truth: Path, name: str, pass_value: str) -> bool:
    from dvpmvs.maps import map_path, read_map_header

    truth_file = truth / f"{name}.bin"
    return truth_file.is_file() and (read_map_header(map_path(stereo, name, "depth", pass_value))[:2]
                                     == read_map_header(truth_file)[:2])


def check_json_path(path: Path, key: str) -> None:
    """A JSON report's path: a file (not a folder) in a folder this process can write."""
    from dvpmvs.validation import check_writable

    if path.is_dir():
        raise DvpmvsError(f"{key}={path} is a folder; {key}= names the JSON file to write, e.g. "
                          f"{key}={path / 'report.json'}")
    check_writable(path.parent, f"the folder of {key}=", f"give {key}=PATH in a folder you can write")


def _resolved_config(cfg: DictConfig) -> dict:
    return OmegaConf.to_container(cfg, resolve=True)


def _write_manifest(manifest: dict, out: Path, report: Path | None) -> None:
    from dvpmvs.evaluation.report import write_json

    from dvpmvs.digests import canonical

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


def run_dense_job(cfg: DictConfig, workspace, options) -> int:
    """The dense stage on ``workspace`` with ``options`` into the run's output folder, then the
    evaluation and the manifest; returns the exit status."""
    import cv2

    from dvpmvs.cli import print_workspace_summary
    from dvpmvs.config import executor_options, progress_enabled
    from dvpmvs.pipeline import print_summary, run_dense

    context = job_context()
    out = _path_option(cfg, "out") or (context.job_dir if context.multirun else workspace.root)
    report = _path_option(cfg, "report")
    scoring = _scoring(cfg, workspace.root)  # a wrong evaluate.* option stops the run before it computes
    if report is not None:
        check_json_path(report, "report")
    threads = _threads(int(cfg.num_threads), context)
    cv2.setNumThreads(threads)
    options = replace(options, patch_match=replace(options.patch_match, num_threads=threads),
                      fusion=replace(options.fusion, num_threads=threads))
    manifest = {"dvpmvs": code_identity()["dvpmvs"], "status": "running",
                "started": datetime.now(timezone.utc).isoformat(timespec="seconds"),
                "command": ["dvpmvs", *sys.argv[1:]] if sys.argv else [], "overrides": list(context.overrides),
                "sweep": None if not context.multirun else {"dir": str(context.sweep_dir), "job": context.num,
                                                            "id": _sweep_id(context)},
                "workspace": str(workspace.root), "out": str(out), "threads": threads,
                "config": _resolved_config(cfg), "options": asdict(options), "code": code_identity(),
                "environment": environment()}
    reset_peak_rss()
    start = time.perf_counter()
    # A run stopped by a check before its start (a locked or read-only folder, foreign maps)
    # changed nothing, so it leaves the folder's manifest (maybe another run's) as it was; a
    # sweep's job always writes one into its own folder, for the sweep's table.
    started = {"yes": context.multirun}
    try:
        print_workspace_summary(workspace)
        summary = run_dense(workspace, options, output=_path_option(cfg, "output"), out=out,
                            progress=progress_enabled(cfg),
                            cache=_cache(cfg, context), on_start=lambda: started.update(yes=True),
                            executor=executor_options(cfg))
        print_summary(summary)
        manifest["dense"] = summary.as_dict()
        manifest["evaluation"] = _evaluate(scoring, workspace, summary, options, out, threads)
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
                _console.print(f"manifest: {out / MANIFEST_NAME}" + (f" (and {report})" if report else ""))
            except OSError as exc:  # the run's own error, if any, is the one to report
                log.warning("could not write the run's manifest: %s", exc)
