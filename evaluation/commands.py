"""The harness's command-line tasks (``dvpmvs eval / synth / import / submit``).

Each validates its options, runs, prints a short summary table and returns an exit status.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np
from rich.console import Console
from rich.table import Table

from dvpmvs.errors import DvpmvsError

_console = Console(stderr=True)


def _progress_printer(prefix: str):
    start = time.perf_counter()

    def show(step: str) -> None:
        _console.print(f"[dim]{prefix} {time.perf_counter() - start:6.1f} s[/dim]  {step}")

    return show


def eth3d_parameters_for(
    ground_truth: Path, voxel_size=None, beam_start=None, beam_divergence=None
):
    """Official defaults, overridden by ``eth3d_parameters.json`` beside the ground truth, then
    by explicit options."""
    from dvpmvs.evaluation.eth3d_metric import ETH3DParameters

    values = {}
    sidecar = ground_truth.parent / "eth3d_parameters.json"
    if sidecar.is_file():
        try:
            values = json.loads(sidecar.read_text())
        except json.JSONDecodeError as exc:
            raise DvpmvsError(f"{sidecar} is not valid JSON: {exc}") from None
    for key, value in (
        ("voxel_size", voxel_size),
        ("beam_start_radius_meters", beam_start),
        ("beam_divergence_halfangle_deg", beam_divergence),
    ):
        if value is not None:
            values[key] = value
    known = {"voxel_size", "beam_start_radius_meters", "beam_divergence_halfangle_deg"}
    return ETH3DParameters(**{k: float(v) for k, v in values.items() if k in known})


def evaluate(
    metric: str,
    reconstruction: str,
    ground_truth: str,
    tolerances: list,
    voxel_size=None,
    beam_start_radius_meters=None,
    beam_divergence_halfangle_deg=None,
    threshold=None,
    trajectory=None,
    refine=True,
    report=None,
    clouds=None,
    plot=None,
    error_maps=None,
    overwrite=False,
) -> int:
    from dvpmvs._version import __version__
    from dvpmvs.evaluation.report import write_json
    from dvpmvs.maps import DiskFullError
    from dvpmvs.run import check_json_path
    from dvpmvs.validation import check_writable

    # Where the results go, checked before anything is scored.
    if report is not None:
        check_json_path(Path(report), "report", overwrite)
    for key, folder in (("clouds", clouds), ("error_maps", error_maps)):
        if folder is not None:
            check_writable(
                Path(folder), f"the folder {key}=", f"give {key}=DIR (a folder you can write)"
            )
    if plot is not None:
        if Path(plot).suffix.lower() != ".png":
            raise DvpmvsError(
                f"plot={plot}: the F1 curve is written as PNG; give a file name ending in .png"
            )
        check_writable(
            Path(plot).parent, "the folder of plot=", "give plot=PATH in a folder you can write"
        )
    if metric == "eth3d":
        data = _evaluate_eth3d(
            Path(reconstruction),
            Path(ground_truth),
            tolerances,
            voxel_size,
            beam_start_radius_meters,
            beam_divergence_halfangle_deg,
            clouds,
            plot,
        )
    elif metric == "tanks":
        data = _evaluate_tanks(
            Path(reconstruction), Path(ground_truth), threshold, trajectory, refine
        )
    elif metric == "depth":
        data = _evaluate_depth(Path(reconstruction), Path(ground_truth), error_maps)
    elif metric == "highlight":
        data = _evaluate_highlight(Path(reconstruction), Path(ground_truth))
    else:
        raise DvpmvsError(f"unknown metric {metric!r}; choose eth3d, tanks, depth or highlight")
    if report is not None:
        from dvpmvs.evaluation.run_report import write_evaluation_page
        from dvpmvs.report import ReportError

        try:
            write_json(report, {"dvpmvs": __version__, **data})  # the version marks it as ours
        except OSError as exc:
            # As a run's report: the scores are printed above, the command's work is done.
            reason = (
                "no space left on its disk"
                if isinstance(exc, DiskFullError)
                else exc.strerror or str(exc)
            )
            _console.print(
                f"warning: the scores above are not written to report={report} ({reason}); free "
                f"space there or give report= another path, and run the evaluation again",
                soft_wrap=True,  # a path is not broken across lines
            )
            return 0
        try:
            page = write_evaluation_page(
                Path(report).with_suffix(".html"),
                data,
                reconstruction=reconstruction if metric in ("eth3d", "tanks") else None,
                clouds=clouds,
                curve=Path(plot).with_suffix(".json")
                if plot is not None and metric == "eth3d"
                else None,
                overwrite=overwrite,
            )
            _console.print(f"report written to {report} and {page} (open it in a browser)")
        except (ReportError, OSError) as exc:  # the scores are written; the page is their picture
            reason = exc if isinstance(exc, ReportError) else exc.strerror or exc
            _console.print(f"report written to {report}; its HTML page is not: {reason}")
    return 0


def _evaluate_eth3d(
    reconstruction, ground_truth, tolerances, voxel_size, beam_start, beam_divergence, clouds, plot
) -> dict:
    from dvpmvs.evaluation.eth3d_metric import evaluate_eth3d
    from dvpmvs.evaluation.pointclouds import load_ground_truth, read_points
    from dvpmvs.evaluation.report import (
        plot_f1_curve,
        plotting_available,
        print_eth3d_table,
        write_eth3d_clouds,
    )

    params = eth3d_parameters_for(ground_truth, voxel_size, beam_start, beam_divergence)
    start = time.perf_counter()
    points = read_points(reconstruction)
    gt = load_ground_truth(ground_truth)
    result = evaluate_eth3d(points, gt, tolerances, params, keep_point_results=clouds is not None)
    seconds = time.perf_counter() - start
    print_eth3d_table(
        result,
        title=f"ETH3D evaluation of {reconstruction.name} ({len(points):,} points)",
        console=_console,
    )
    if clouds is not None:
        written = write_eth3d_clouds(clouds, points, result)
        _console.print(f"{len(written)} coloured clouds written to {clouds}")
    if plot is not None:
        if not plotting_available():
            raise DvpmvsError(
                f"plot={plot} draws with matplotlib, which is not installed: pip install 'dvpmvs[eval]'"
            )
        plot_f1_curve(plot, points, gt, params, title=reconstruction.name)
        _console.print(f"F1 plot written to {plot}")
    data = result.as_dict()
    data.update(
        {
            "metric": "eth3d",
            "reconstruction": str(reconstruction),
            "ground_truth": str(ground_truth),
            "reconstruction_points": int(len(points)),
            "parameters": {
                "voxel_size": params.voxel_size,
                "beam_start_radius_meters": params.beam_start_radius_meters,
                "beam_divergence_halfangle_deg": params.beam_divergence_halfangle_deg,
                "unobserved_space_rule": not isinstance(gt, np.ndarray),
            },
            "seconds": round(seconds, 3),
        }
    )
    return data


def _evaluate_tanks(reconstruction, scene_dir, threshold, trajectory, refine) -> dict:
    from dvpmvs.evaluation.tanks import TanksScene, evaluate_tanks_scene

    scene = TanksScene.open(scene_dir, threshold)
    result = evaluate_tanks_scene(scene, reconstruction, trajectory, refine)
    table = Table(title=f"Tanks and Temples: {scene.name} (tau = {result.threshold:g} m)")
    for col in ("precision", "recall", "F-score"):
        table.add_column(col, justify="right")
    table.add_row(
        f"{100 * result.precision:.2f}", f"{100 * result.recall:.2f}", f"{100 * result.fscore:.2f}"
    )
    _console.print(table)
    return {"metric": "tanks", "scene": scene.name, **result.as_dict()}


def _evaluate_depth(workspace, truth_dir, error_maps) -> dict:
    from dvpmvs.evaluation.depth_metrics import (
        evaluate_depth_maps,
        pooled_depth_metrics,
        pooled_highlight_shares,
    )

    depth_dir = (
        workspace / "stereo" / "depth_maps" if (workspace / "stereo").is_dir() else workspace
    )
    results = evaluate_depth_maps(
        depth_dir,
        truth_dir / "depth_maps" if (truth_dir / "depth_maps").is_dir() else truth_dir,
        error_dir=error_maps,
    )
    overall = pooled_depth_metrics(results)
    table = Table(
        title=f"depth maps of {workspace} (< 1 / 2 / 5 %, < 2 cm: of the true pixels; AbsRel, "
        f"SqRel, RMSE, δ: over the estimated ones)"
    )
    columns = ("view", "estimated", "< 1 %", "< 2 %", "< 5 %", "< 2 cm", "AbsRel", "SqRel")
    for col in (*columns, "RMSE", "δ < 1.05 / 1.10 / 1.25", "normal mean / median"):
        table.add_column(col, justify="right")

    def row(name, r: dict, normal: str):
        def share(key):
            return "-" if r[key] is None else f"{100 * r[key]:.1f} %"

        def number(key):
            return "-" if r[key] is None or np.isnan(r[key]) else f"{r[key]:.4f}"

        deltas = " / ".join(share(k) for k in ("delta_1_05", "delta_1_10", "delta_1_25"))
        table.add_row(
            name,
            share("estimated"),
            share("within_1_percent"),
            share("within_2_percent"),
            share("within_5_percent"),
            share("within_2_cm"),
            number("abs_rel"),
            number("sq_rel"),
            number("rmse"),
            deltas if r["abs_rel"] is not None else "-",
            normal,
        )

    for r in results:
        normal = (
            "-"
            if r.normal_mean_deg is None
            else f"{r.normal_mean_deg:.1f} / {r.normal_median_deg:.1f} deg"
        )
        row(r.view, r.as_dict(), normal)
    row("all (pooled)", overall, "")
    _console.print(table)
    views = [r.as_dict() for r in results]
    mean = {
        k: float(np.mean([v[k] for v in views]))
        for k in ("estimated", "within_1_percent", "within_2_cm")
    }
    pooled = pooled_highlight_shares(results)
    if pooled["highlight_within_1_percent"] is not None:
        _console.print(
            f"within 1 %: {100 * pooled['highlight_within_1_percent']:.1f} % of the "
            f"{pooled['highlight_pixels']:,} ground-truth highlight pixels, "
            f"{100 * pooled['outside_within_1_percent']:.1f} % of the others"
        )
    return {"metric": "depth", "views": views, "mean": {**mean, **pooled}, "all": overall}


def _evaluate_highlight(workspace: Path, truth_dir: Path) -> dict:
    from dvpmvs.evaluation.highlight_metrics import evaluate_highlight_masks, pooled_mask_metrics

    masks = workspace / "stereo" / "highlights" if (workspace / "stereo").is_dir() else workspace
    truth = truth_dir / "highlights" if (truth_dir / "highlights").is_dir() else truth_dir
    results = evaluate_highlight_masks(masks, truth, "final")
    single = pooled_mask_metrics(evaluate_highlight_masks(masks, truth, "single"))
    table = Table(
        title=f"highlight masks of {workspace} (with multi-view evidence where the run refined them)"
    )
    for col in ("view", "true px", "found px", "precision", "recall"):
        table.add_column(col, justify="right")

    def share(value):
        return "-" if value is None else f"{100 * value:.1f} %"

    single.view = "all, provider's"
    for r in [*results, pooled_mask_metrics(results), single]:
        table.add_row(
            r.view,
            f"{r.true_positive + r.false_negative:,}",
            f"{r.true_positive + r.false_positive:,}",
            share(r.precision),
            share(r.recall),
        )
    _console.print(table)
    return {
        "metric": "highlight",
        "views": [r.as_dict() for r in results],
        "all": pooled_mask_metrics(results).as_dict(),
        "single_view": single.as_dict(),
    }


def synth(
    out: str,
    scene: str,
    views: int,
    width: int,
    height,
    seed: int,
    noise: float,
    priors: bool,
    overwrite: bool = False,
) -> int:
    from dvpmvs.evaluation.scene_digest import compare_with_documented, scene_digest, scene_key
    from dvpmvs.evaluation.synthetic import SynthOptions, generate

    options = SynthOptions(
        scene=scene, views=views, width=width, height=height, seed=seed, noise=noise, priors=priors
    )
    stats = generate(out, options, progress=_progress_printer("synth"), overwrite=overwrite)
    table = Table(title=f"synthetic scene {scene!r} in {out}")
    table.add_column("item")
    table.add_column("value", justify="right")
    table.add_row("views", f"{views} x {width}x{options.image_height}")
    table.add_row("depth range", "{:.2f} - {:.2f} m".format(*stats["depth_range"]))
    table.add_row(
        "sparse points", f"{stats['sparse_points']:,} (mean track {stats['mean_track_length']:.1f})"
    )
    table.add_row("ground-truth scan points", f"{stats['scan_points']:,}")
    digest = scene_digest(out)
    table.add_row("scene digest", digest.short)
    _console.print(table)
    print(compare_with_documented(scene_key(scene, views, width, seed), digest), file=sys.stderr)
    return 0


# Marks a workspace `dvpmvs import` wrote, so that a rerun may write there again.
_IMPORT_MARKER = ".dvpmvs-import"


def import_dataset(
    dataset: str,
    source: str,
    out: str,
    max_image_size: int,
    num_sources: int,
    num_threads: int,
    overwrite: bool = False,
    rgbd=None,
) -> int:
    from dvpmvs.evaluation import datasets, strecha
    from dvpmvs.evaluation import rgbd as rgbd_sequences
    from dvpmvs.maps import atomic_path

    src = Path(source)
    if not src.is_dir():
        raise DvpmvsError(f"the scene folder {src} does not exist")
    target = Path(out)
    if (
        not overwrite
        and target.is_dir()
        and not (target / _IMPORT_MARKER).is_file()
        and any(not p.name.startswith(".") for p in target.iterdir())
    ):
        raise DvpmvsError(
            f"out={target} holds files dvpmvs import did not write (its images/ or sparse/ would "
            f"be replaced); give out= an empty or new folder, or overwrite=true to write there"
        )
    start = time.perf_counter()
    table = Table(title=f"{dataset} scene {src.name} -> {out}")
    table.add_column("item")
    table.add_column("value", justify="right")
    stats: dict = {}
    if dataset == "strecha":
        stats = strecha.import_strecha(
            src,
            out,
            max_image_size=max_image_size,
            num_threads=num_threads,
            num_sources=num_sources,
            progress=_progress_printer("import"),
        )
    elif dataset == "eth3d":
        mlp = datasets.prepare_eth3d(src, out, num_sources=num_sources)
        table.add_row("ground truth", str(mlp))
    elif dataset == "tanks":
        ws = datasets.prepare_tanks(
            src,
            out,
            num_sources=num_sources,
            max_image_size=max_image_size,
            num_threads=num_threads,
        )
        table.add_row("workspace", str(ws))
    elif dataset in rgbd_sequences.LAYOUTS:
        stats = rgbd_sequences.import_rgbd(
            dataset,
            src,
            out,
            rgbd or rgbd_sequences.RGBDOptions(),
            max_image_size=max_image_size,
            num_threads=num_threads,
            num_sources=num_sources,
            progress=_progress_printer("import"),
        )
    else:
        raise DvpmvsError(
            f"unknown dataset {dataset!r}; choose strecha, eth3d, tanks or an RGB-D layout "
            f"({', '.join(rgbd_sequences.LAYOUTS)})"
        )
    for key, value in stats.items():
        table.add_row(
            key.replace("_", " "), f"{value:.3g}" if isinstance(value, float) else str(value)
        )
    with atomic_path(target / _IMPORT_MARKER) as tmp:
        tmp.write_text(json.dumps({"dataset": dataset, "source": str(src.resolve())}) + "\n")
    table.add_row("seconds", f"{time.perf_counter() - start:.1f}")
    _console.print(table)
    return 0


def submit(
    format: str,
    cloud: str,
    scene: str,
    out: str,
    runtime=None,
    sparse=None,
    images=None,
    track=None,
    overwrite=False,
) -> int:
    from dvpmvs.evaluation.submission import (
        eth3d_track,
        missing_eth3d_scenes,
        write_eth3d_submission,
        write_tanks_submission,
    )

    if format == "eth3d":
        if runtime is None:
            raise DvpmvsError("an ETH3D submission needs runtime=<seconds>")
        track = eth3d_track(scene, track)
        files = write_eth3d_submission(out, scene, cloud, runtime, track, overwrite)
    elif format == "tanks":
        if track is not None:
            raise DvpmvsError(
                f"track={track} is for format=eth3d (Tanks and Temples has no tracks); drop it"
            )
        if sparse is None or images is None:
            raise DvpmvsError(
                "a Tanks and Temples submission needs sparse=<COLMAP model> and images=<the folder of "
                "the scene's input images> for the trajectory (one entry per input image)"
            )
        files = write_tanks_submission(out, scene, cloud, sparse, images, overwrite)
    else:
        raise DvpmvsError(f"unknown submission format {format!r}; choose eth3d or tanks")
    for f in files:
        _console.print(f"wrote {f}")
    if format == "eth3d":
        missing = missing_eth3d_scenes(out, track)
        if missing:
            _console.print(
                f"{track}: {len(missing)} scene(s) still to add before packing: {', '.join(missing)}",
                soft_wrap=True,
            )
        else:
            _console.print(
                f"{track}: every scene is in; pack it for upload with: cd {out} && 7z a {track}.7z {track}",
                soft_wrap=True,
                markup=False,
            )
    return 0


def demo(
    out: str,
    options,
    workspace_options=None,
    progress: bool = True,
    executor=None,
    report: bool = True,
) -> int:
    """The README's first command: write the embedded scene, run the dense stage on it (maps,
    previews, fused cloud), then score the fused cloud (ETH3D metric, coloured clouds, F1 plot)
    and the depth maps (error images) against the ground truth; the sparse model is the baseline.
    ``workspace_options``: how the workspace is read (a preset's image size and view selector;
    None: the defaults). ``report``: also the HTML report ``out/report.html``."""
    import pycolmap

    from dvpmvs.dense import run_dense
    from dvpmvs.evaluation.embedded import materialise
    from dvpmvs.evaluation.eth3d_metric import evaluate_eth3d
    from dvpmvs.evaluation.pointclouds import read_meshlab_project, read_points
    from dvpmvs.evaluation.report import (
        CURVE_TOLERANCES,
        draw_f1_curve,
        plotting_available,
        print_eth3d_table,
        write_eth3d_clouds,
        write_json,
    )
    from dvpmvs.tables import print_summary, print_workspace_summary
    from dvpmvs.workspace import Workspace

    root = materialise(out, progress=_progress_printer("demo"))
    workspace = Workspace.open(root, workspace_options)
    print_workspace_summary(workspace)
    summary = run_dense(workspace, options, progress=progress, executor=executor)
    print_summary(summary, console=_console)

    evaluation = root / "evaluation"
    gt_mlp = root / "ground_truth" / "scan_alignment.mlp"
    params = eth3d_parameters_for(gt_mlp)
    scans = read_meshlab_project(gt_mlp)
    recon = pycolmap.Reconstruction(str(root / "sparse"))
    sparse = np.array([p.xyz for p in recon.points3D.values()], np.float32)
    baseline = evaluate_eth3d(sparse, scans, [0.02, 0.1], params)
    write_json(evaluation / "sparse_eth3d.json", baseline.as_dict())
    result = None
    if summary.output is not None:
        fused = read_points(summary.output)
        # One evaluation for the table, the coloured clouds and the curve.
        curve = evaluate_eth3d(
            fused, scans, sorted({0.02, 0.1, *CURVE_TOLERANCES}), params, keep_point_results=True
        )
        result = curve.at([0.02, 0.1])
        write_json(evaluation / "fused_eth3d.json", result.as_dict())
        write_eth3d_clouds(evaluation / "clouds", fused, result)
        if plotting_available():
            draw_f1_curve(
                evaluation / "fused_f1.png",
                curve,
                title="embedded room: fused cloud vs ground truth",
            )
        else:
            write_json(evaluation / "fused_f1.json", curve.as_dict())
    depth_report = _evaluate_depth(root, root / "ground_truth", evaluation / "error_maps")
    write_json(evaluation / "depth_maps.json", depth_report)
    page = None
    if report:
        from dvpmvs.digests import canonical
        from dvpmvs.run import MANIFEST_NAME, dense_manifest, write_report

        # The demo's manifest, as a dense run's: `dvpmvs report` on the folder finds it again.
        manifest = dense_manifest(
            summary,
            options,
            root,
            scene={"key": "room_5v_320_seed0 (embedded)"},
            evaluation={
                "eth3d": None if result is None else result.as_dict(),
                "sparse_model_eth3d": baseline.as_dict(),
                "depth_maps": depth_report,
            },
        )
        write_json(root / MANIFEST_NAME, canonical(manifest))
        page = write_report(root, manifest)
    print_eth3d_table(
        baseline, title=f"sparse model ({len(sparse):,} points), the baseline", console=_console
    )
    if result is not None:
        print_eth3d_table(
            result, title=f"fused cloud ({len(fused):,} points) vs ground truth", console=_console
        )
    _console.print(
        f"dvpmvs demo: workspace and ground truth in {root}\n"
        + (
            f"  depth / normal / cost previews: {root / 'stereo' / 'previews'}\n"
            if options.previews
            else "  no previews (previews=false)\n"
        )
        + f"  depth error images: {evaluation / 'error_maps'}\n"
        + (
            f"  fused cloud: {summary.output}; coloured evaluation clouds: {evaluation / 'clouds'}; "
            + (
                f"F1 curve: {evaluation / 'fused_f1.png'}"
                if plotting_available()
                # (in rich markup, \\[ prints a bracket)
                else "no F1 curve (it needs matplotlib: pip install 'dvpmvs\\[eval]')"
            )
            if result is not None
            else "  (fusion was switched off)"
        )
        + (f"\n  report (open in a browser): {page}" if page is not None else "")
    )
    return 0
