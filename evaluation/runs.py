"""A run's scores against ground truth: the harness's scoring hook of ``dvpmvs dense`` and
``dvpmvs bench`` (entry point ``dvpmvs.run_scoring``: ``ground_truth``; see :mod:`dvpmvs.run`),
and their columns in a sweep's tables (``dvpmvs.table_columns``: :data:`TABLE_COLUMNS`).

Where ground truth is known (``evaluate.ground_truth``; a synthetic workspace's own
``ground_truth/`` by default), the fused cloud's ETH3D scores (and, with
``evaluate.colmap_fusion=true``, those of COLMAP's fusion of the same maps), the depth maps'
and the highlight masks' scores and the cloud's share of points in open sky join the run's
manifest, from which :mod:`dvpmvs.sweep` builds a sweep's table.
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from omegaconf import DictConfig, OmegaConf
from rich.console import Console

from dvpmvs.digests import file_digest, fingerprint, sources_digest
from dvpmvs.errors import DvpmvsError
from dvpmvs.provenance import code_identity
from dvpmvs.run import MANIFEST_NAME
from dvpmvs.sweep import TableColumns

__all__ = ["TABLE_COLUMNS", "ground_truth_scoring", "score_cloud", "job_ground_truth"]

log = logging.getLogger(__name__)
_console = Console(stderr=True)


def ground_truth_scoring(cfg: DictConfig, workspace_root: Path):
    """The scoring hook: checks the ``evaluate.*`` options (before the run computes anything)
    and returns what scores the finished run against its ground truth (None where none is
    known)."""
    scoring = _scoring(cfg, workspace_root)
    if scoring.ground_truth is None:
        return None  # nothing to score against: the run does not load the metric's code

    def score(workspace, summary, options, out: Path, threads: int) -> dict | None:
        return _evaluate(scoring, workspace, summary, options, out, threads)

    return score


def score_columns(manifest: dict) -> dict[str, float]:
    """A job's scores as a sweep's columns: the fused cloud's F1, completeness and accuracy at
    each tolerance (the paper's Table IV), the depth maps' share within 1 % (mean of the views)
    and, pooled by pixel, within 5 %, their AbsRel and δ < 1.05, COLMAP's fusion's F1 at the
    first tolerance; percent."""
    evaluation = manifest.get("evaluation") or {}
    columns: dict[str, float] = {}
    eth3d = evaluation.get("eth3d")
    tolerances = [float(t) for t in eth3d["tolerances"]] if eth3d else []
    if eth3d:
        for t, f1, comp, acc in zip(
            tolerances, eth3d["f1"], eth3d["completeness"], eth3d["accuracy"]
        ):
            label = f"{t * 100:g}cm"
            columns[f"F1 {label}"] = 100 * f1
            columns[f"Comp. {label}"] = 100 * comp
            columns[f"Acc. {label}"] = 100 * acc
    depth = evaluation.get("depth_maps")
    if depth:
        columns["depth <1%"] = 100 * float(depth["within_1_percent"])
        # Runs scored before the pooled RGB-D errors have only the mean share above.
        pooled = depth.get("all") or {}
        for key, column in (
            ("within_5_percent", "depth <5%"),
            ("abs_rel", "AbsRel %"),
            ("delta_1_05", "δ<1.05"),
        ):
            if pooled.get(key) is not None:
                columns[column] = 100 * float(pooled[key])
    colmap = evaluation.get("colmap_fusion")
    if colmap and tolerances:
        columns[f"COLMAP fusion F1 {tolerances[0] * 100:g}cm"] = 100 * float(colmap["f1"][0])
    return columns


# The F1s are the tables' headline (with their spread over the estimator's seeds); a bench job's
# scene and the ground truth given name the data a job ran on.
TABLE_COLUMNS = TableColumns(
    columns=score_columns,
    headline=lambda name: name.startswith("F1 "),
    scene_keys=("scene", "scene_seed", "evaluate.ground_truth"),
)


def _ground_truth(cfg: DictConfig, workspace_root: Path) -> Path | None:
    value = OmegaConf.select(cfg, "evaluate.ground_truth", default="auto")
    if value is None or str(value).lower() in ("none", "false", ""):
        return None
    if str(value) == "auto":
        found = workspace_root / "ground_truth" / "scan_alignment.mlp"
        return found if found.is_file() else None
    path = Path(str(value)).expanduser()
    if not path.is_file():
        raise DvpmvsError(
            f"evaluate.ground_truth: {path} does not exist (an ETH3D scan_alignment.mlp or a PLY)"
        )
    return path


def _ground_truth_digest(path: Path) -> dict:
    from dvpmvs.evaluation.pointclouds import read_meshlab_project

    files = [path] + (
        [scan.path for scan in read_meshlab_project(path, load_points=False)]
        if path.suffix.lower() == ".mlp"
        else []
    )
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
    for base in [Path()] if mlp.is_absolute() else [Path(), *job.resolve().parents]:
        if (base / mlp).is_file():
            return base / mlp
    raise DvpmvsError(f"{job}: the ground truth of its workspace, {mlp}, is not found")


def score_cloud(
    cloud: Path,
    ground_truth: Path,
    tolerances: list[float],
    report: Path,
    pictures: Path | None = None,
) -> dict:
    """The ETH3D metric of ``cloud`` against ``ground_truth`` (beam parameters from
    ``eth3d_parameters.json`` beside it, else the official ones), kept in ``report`` with the
    fingerprint of its inputs (the cloud's and ground truth's bytes, the tolerances, the code):
    a rerun with the same inputs reads it back instead of scoring again. ``pictures``: a folder
    for what the run's HTML report shows of the scores, ``fused_f1.json`` (the scores at
    :data:`~dvpmvs.evaluation.report.CURVE_TOLERANCES` too; one evaluation gives every tolerance
    its own figures, the same as alone) and ``clouds/`` (the coloured clouds at the smallest
    tolerance)."""
    from dvpmvs.evaluation.commands import eth3d_parameters_for
    from dvpmvs.evaluation.eth3d_metric import evaluate_eth3d
    from dvpmvs.evaluation.pointclouds import load_ground_truth, read_points
    from dvpmvs.evaluation.report import CURVE_TOLERANCES, write_eth3d_clouds, write_json

    inputs = {
        "cloud": file_digest(cloud),
        "ground_truth": _ground_truth_digest(ground_truth),
        "tolerances": [float(t) for t in tolerances],
        "code": code_identity(),
        "evaluation_code": sources_digest(Path(__file__).resolve().parent),
    }
    fp = fingerprint(inputs)
    drawn = pictures is None or (
        (pictures / "fused_f1.json").is_file() and any((pictures / "clouds").glob("*.ply"))
    )
    if report.is_file() and drawn:
        try:
            stored = json.loads(report.read_text())
            if stored.get("fingerprint") == fp:
                return stored["result"]
        except (OSError, ValueError, KeyError):
            pass
    params = eth3d_parameters_for(ground_truth)
    start = time.perf_counter()
    points = read_points(cloud)
    asked = sorted(float(t) for t in tolerances)
    every = sorted(set(asked) | (set(CURVE_TOLERANCES) if pictures is not None else set()))
    full = evaluate_eth3d(
        points,
        load_ground_truth(ground_truth),
        every,
        params,
        keep_point_results=pictures is not None,
    )
    result = full.at(asked)
    if pictures is not None:
        write_json(pictures / "fused_f1.json", full.as_dict())
        write_eth3d_clouds(pictures / "clouds", points, full.at(asked[:1]))
    data = {
        **result.as_dict(),
        "reconstruction": str(cloud),
        "ground_truth": str(ground_truth),
        "reconstruction_points": int(len(points)),
        "seconds": round(time.perf_counter() - start, 3),
        "parameters": {
            "voxel_size": params.voxel_size,
            "beam_start_radius_meters": params.beam_start_radius_meters,
            "beam_divergence_halfangle_deg": params.beam_divergence_halfangle_deg,
        },
    }
    write_json(report, {"fingerprint": fp, "inputs": inputs, "result": data})
    return data


def _score_depth_maps(stereo: Path, truth: Path, pass_value: str) -> dict:

    from dvpmvs.evaluation.depth_metrics import (
        evaluate_depth_maps,
        pooled_depth_metrics,
        pooled_highlight_shares,
        pooled_textureless_shares,
    )

    views = evaluate_depth_maps(stereo / "depth_maps", truth, suffix=f".{pass_value}.bin")
    return {
        "all": pooled_depth_metrics(views),
        "within_1_percent": float(np.mean([v.within_1_percent for v in views])),
        "within_2_cm": float(np.mean([v.within_2_cm for v in views])),
        "estimated": float(np.mean([v.estimated for v in views])),
        "views": len(views),
        **pooled_highlight_shares(views),
        **pooled_textureless_shares(views),
    }


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
    tolerances = number_list(
        section.get("tolerances", [0.02, 0.1]), "evaluate.tolerances", "[0.02,0.1] (metres)"
    )
    flags = {}
    for key, default in (("depth_maps", True), ("colmap_fusion", False)):
        try:
            flags[key] = check_value(f"evaluate.{key}", section.get(key, default), (bool,))
        except ValueError as exc:
            raise ConfigError(str(exc)) from None
    return _Scoring(
        _ground_truth(cfg, workspace_root), tolerances, flags["depth_maps"], flags["colmap_fusion"]
    )


def _evaluate(
    scoring: _Scoring, workspace, summary, options, out: Path, threads: int
) -> dict | None:
    """Scores of the run's cloud (and, if asked, COLMAP's fusion of the same maps) and of its
    depth maps, where ground truth is known; None where it is not."""
    gt, tolerances = scoring.ground_truth, scoring.tolerances
    if gt is None or summary.output is None:
        return None
    from dvpmvs.evaluation.eth3d_metric import ETH3DResult
    from dvpmvs.evaluation.report import print_eth3d_table
    from dvpmvs.fusion import fuse_with_colmap

    folder = out / "evaluation"
    scores = {
        "ground_truth": str(gt),
        "eth3d": score_cloud(
            summary.output, gt, tolerances, folder / "eth3d.json", pictures=folder
        ),
    }
    result = scores["eth3d"]
    print_eth3d_table(
        ETH3DResult(result["tolerances"], result["accuracy"], result["completeness"]),
        title=f"ETH3D evaluation of {summary.output} ({result['reconstruction_points']:,} points)",
        console=_console,
    )
    if scoring.colmap_fusion:
        cloud = out / "fused_colmap.ply"
        fusion = replace(options.fusion, input_type=options.final_pass.value, num_threads=threads)
        fuse_with_colmap(workspace, cloud, fusion, root=out)
        scores["colmap_fusion"] = score_cloud(
            cloud, gt, tolerances, folder / "eth3d_colmap_fusion.json"
        )
    truth = gt.parent / "depth_maps"
    if scoring.depth_maps and truth.is_dir():
        if _comparable_size(
            summary.stereo_dir, truth, workspace.reference_views()[0].name, options.final_pass.value
        ):
            scores["depth_maps"] = _score_depth_maps(
                summary.stereo_dir, truth, options.final_pass.value
            )
            scores["sky_points"] = _sky_points(summary.output, workspace, truth)
        else:
            log.info("depth maps not scored: their ground truth has another aspect ratio")
    masks = summary.stereo_dir / "highlights"
    if (gt.parent / "highlights").is_dir() and any(masks.glob("*.mask.bin")):
        # at the masks' size (max_image_size): the ground truth is reduced to it
        scores["highlight_masks"] = _score_highlight_masks(masks, gt.parent / "highlights")
    return scores


def _score_highlight_masks(masks: Path, truth: Path) -> dict:
    from dvpmvs.evaluation.highlight_metrics import evaluate_highlight_masks, pooled_mask_metrics

    final = pooled_mask_metrics(evaluate_highlight_masks(masks, truth, "final"))
    single = pooled_mask_metrics(evaluate_highlight_masks(masks, truth, "single"))
    return {**final.as_dict(), "single_view": single.as_dict()}


def _comparable_size(stereo: Path, truth: Path, name: str, pass_value: str) -> bool:
    from dvpmvs.evaluation.depth_metrics import comparable_sizes
    from dvpmvs.maps import map_path, read_map_header

    truth_file = truth / f"{name}.bin"
    if not truth_file.is_file():
        return False
    (w, h), (tw, th) = (
        read_map_header(map_path(stereo, name, "depth", pass_value))[:2],
        read_map_header(truth_file)[:2],
    )
    return comparable_sizes((h, w), (th, tw))
