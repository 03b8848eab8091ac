"""Reports of an evaluation: a table on the terminal, JSON, coloured clouds and an F1 plot."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from rich.console import Console
from rich.table import Table

from dvpmvs.evaluation.eth3d_metric import (
    ACCURATE,
    INACCURATE,
    ETH3DParameters,
    ETH3DResult,
    evaluate_eth3d,
)
from dvpmvs.evaluation.pointclouds import write_point_cloud
from dvpmvs.maps import atomic_path, write_json
from dvpmvs.preview import write_png  # re-exported: reports write images too

__all__ = [
    "print_eth3d_table",
    "write_json",
    "write_png",
    "write_eth3d_clouds",
    "plot_f1_curve",
    "draw_f1_curve",
    "plotting_available",
    "CURVE_TOLERANCES",
]


def print_eth3d_table(
    result: ETH3DResult, title: str = "ETH3D evaluation", console: Console | None = None
) -> None:
    table = Table(title=title)
    table.add_column("tolerance", justify="right")
    for col in ("accuracy", "completeness", "F1"):
        table.add_column(col, justify="right")
    for t, a, c, f in zip(result.tolerances, result.accuracy, result.completeness, result.f1):
        table.add_row(f"{t * 100:g} cm", f"{100 * a:.2f}", f"{100 * c:.2f}", f"{100 * f:.2f}")
    (console or Console()).print(table)


def write_eth3d_clouds(
    folder: str | Path, reconstruction: np.ndarray, result: ETH3DResult
) -> list[Path]:
    """Per tolerance: ``accuracy.tolerance_<t>.ply`` (green accurate, red inaccurate, blue
    unobserved) and ``completeness.tolerance_<t>.ply`` (green complete, red missing), as the
    official program colours them."""
    if result.point_accuracy is None:
        raise ValueError("evaluate with keep_point_results=True to write clouds")
    folder = Path(folder)
    written = []
    for k, tol in enumerate(result.tolerances):
        labels = result.point_accuracy[k]
        colors = np.zeros((len(labels), 3), np.uint8)
        colors[:, 2] = 255
        colors[labels == ACCURATE] = (0, 255, 0)
        colors[labels == INACCURATE] = (255, 0, 0)
        written.append(
            write_point_cloud(folder / f"accuracy.tolerance_{tol:g}.ply", reconstruction, colors)
        )
        complete = result.point_completeness[k]
        colors = np.where(complete[:, None], np.uint8([0, 255, 0]), np.uint8([255, 0, 0])).astype(
            np.uint8
        )
        written.append(
            write_point_cloud(
                folder / f"completeness.tolerance_{tol:g}.ply", result.ground_truth_points, colors
            )
        )
    return written


def plotting_available() -> bool:
    """Whether matplotlib, which only the F1 curves need, is installed (the ``eval`` extra)."""
    import importlib.util

    return importlib.util.find_spec("matplotlib") is not None


# The tolerances of a run's accuracy / completeness / F1 curve (the demo's, bench's and dense's
# scoring, which their HTML reports draw): 2.5 mm to 20 cm.
CURVE_TOLERANCES = tuple(float(t) for t in np.geomspace(0.0025, 0.2, 12))


def plot_f1_curve(
    path: str | Path,
    reconstruction: np.ndarray,
    ground_truth,
    parameters: ETH3DParameters,
    max_tolerance: float = 0.2,
    steps: int = 40,
    title: str = "",
) -> Path:
    """Accuracy, completeness and F1 of ``reconstruction`` at ``steps`` tolerances from 2.5 mm to
    ``max_tolerance``, drawn by :func:`draw_f1_curve`."""
    tolerances = np.geomspace(0.0025, max_tolerance, steps)
    return draw_f1_curve(
        path, evaluate_eth3d(reconstruction, ground_truth, tolerances, parameters), title
    )


def draw_f1_curve(path: str | Path, res: ETH3DResult, title: str = "") -> Path:
    """Accuracy, completeness and F1 against the tolerance (log axis), as a PNG, and the curve's
    figures beside it (``<name>.json``, which a run's HTML report draws). Needs matplotlib
    (``pip install 'dvpmvs[eval]'``): :func:`plotting_available` says whether it is there."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4), dpi=120)
    ax.plot(res.tolerances, 100 * np.array(res.accuracy), label="accuracy")
    ax.plot(res.tolerances, 100 * np.array(res.completeness), label="completeness")
    ax.plot(res.tolerances, 100 * np.array(res.f1), label="F1", linewidth=2.5)
    for t in (0.02, 0.1):
        ax.axvline(t, color="grey", linestyle=":", linewidth=1)
    ax.set_xscale("log")
    ax.set_xlabel("tolerance [m]")
    ax.set_ylabel("score [%]")
    ax.set_ylim(0, 100)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(loc="lower right")
    ax.set_title(title or "ETH3D scores against tolerance")
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)
    write_json(Path(path).with_suffix(".json"), res.as_dict())
    return path
