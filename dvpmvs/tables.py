"""The rich tables the commands print: a workspace's views, and the closing summary of a dense
run (per pass, the views computed and reused, time, the estimator's work per pixel)."""

from __future__ import annotations

import numpy as np
from rich.console import Console
from rich.table import Table

from dvpmvs.passes import Pass

__all__ = ["partial_cloud_note", "print_summary", "print_workspace_summary"]


def print_workspace_summary(workspace) -> None:
    """Per reference view: its size, depth range, sparse points and sources."""
    table = Table(title=f"COLMAP workspace {workspace.root}", title_justify="left")
    for column in ("image", "size", "depth range", "sparse pts", "sources"):
        table.add_column(column, overflow="fold")
    for view in workspace.reference_views():
        fallback = " (fallback)" if view.depth_range_is_fallback else ""
        sources = ", ".join(view.sources[:4]) + (
            f" +{len(view.sources) - 4}" if len(view.sources) > 4 else ""
        )
        table.add_row(
            view.name,
            f"{view.width}x{view.height}",
            f"{view.depth_range[0]:.3g} - {view.depth_range[1]:.3g}{fallback}",
            str(view.num_sparse_points),
            f"{len(view.sources)}: {sources}",
        )
    Console(stderr=True).print(table)


def print_summary(summary, console=None) -> None:
    """The closing table: per pass views computed / reused, seconds per view, evaluation rate."""
    console = console or Console(stderr=True)
    table = Table(title="dvpmvs dense", title_justify="left")
    for column in ("stage", "computed", "reused", "s / view", "M windows / s", "valid px", "size"):
        table.add_column(column, justify="right")
    for pass_name, seconds in summary.pass_seconds.items():
        pass_ = Pass(pass_name)
        done = summary.computed(pass_)
        reused = sum(1 for r in summary.of_pass(pass_) if r.skipped)
        busy = sum(r.seconds for r in done)
        evals = sum(r.evaluations for r in done)
        sizes = sorted({f"{r.width}x{r.height}" for r in summary.of_pass(pass_)})
        table.add_row(
            pass_name,
            str(len(done)),
            str(reused),
            f"{seconds / len(done):.2f}" if done else "-",
            f"{evals / busy / 1e6:.2f}" if busy > 0 else "-",
            f"{np.mean([r.valid_fraction for r in done]) * 100:.1f} %" if done else "-",
            ", ".join(sizes[:2]) + (" ..." if len(sizes) > 2 else ""),
        )
    if summary.output is not None:
        table.add_row(
            "fusion",
            "0" if summary.fusion_reused else "1",
            "1" if summary.fusion_reused else "0",
            "",
            "",
            f"{summary.num_points:,} pts",
            f"{summary.fusion_seconds:.1f} s",
        )
    console.print(table)
    work = Table(title="work per pixel (estimator)", title_justify="left")
    for column in ("pass", "level", "size", "hypotheses", "windows", "samples"):
        work.add_column(column, justify="right")
    for pass_name in summary.pass_seconds:
        for level in summary.work_per_pixel(Pass(pass_name)):
            work.add_row(
                pass_name,
                str(level["level"]),
                "x".join(map(str, level["size"])),
                f"{level['hypotheses']:.1f}",
                f"{level['windows']:.0f}",
                f"{level['samples']:,.0f}",
            )
    if work.row_count:
        console.print(work)
    console.print(
        f"maps: {summary.stereo_dir}"
        + (f"\nfused cloud: {summary.output}" if summary.output else "")
    )
    if summary.fusion_views_without_maps:
        console.print(partial_cloud_note(summary.fusion_views_without_maps))


def partial_cloud_note(views: list[str]) -> str:
    """The closing line of a run whose cloud was fused without some views' maps."""
    shown = ", ".join(views[:5]) + (f" +{len(views) - 5} more" if len(views) > 5 else "")
    return f"warning: partial cloud: {len(views)} view(s) without maps added no points ({shown})"
