"""The harness's part of the HTML reports (:mod:`dvpmvs.report`): the scores against ground
truth, with their curve against the tolerance.

A run's report takes :func:`run_scores_section` through the entry-point group
``dvpmvs.report_sections`` (the page of a run without scores has none); ``dvpmvs eval``'s page
is :func:`write_evaluation_page`.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from dvpmvs.maps import read_json_object
from dvpmvs.report import escape, format_value, write_cloud_page

__all__ = ["curve_svg", "run_scores_section", "scores_section", "write_evaluation_page"]


def _run_scores(folder: Path, manifest: dict) -> dict:
    evaluation = dict(manifest.get("evaluation") or {})
    if "eth3d" not in evaluation:
        fused = read_json_object(folder / "evaluation" / "fused_eth3d.json")
        if fused is not None:
            evaluation["eth3d"] = fused
    if "depth_maps" not in evaluation:
        depth = read_json_object(folder / "evaluation" / "depth_maps.json")
        if depth is not None:
            evaluation["depth_maps"] = depth
    return evaluation


def curve_svg(curve: dict, names: tuple[str, str] = ("accuracy", "completeness")) -> str:
    """Accuracy, completeness and F1 (%) against the tolerance (log axis), as inline SVG;
    ``names``: what the first two curves are called (Tanks and Temples: precision, recall)."""
    tolerances = np.asarray(curve["tolerances"], np.float64)
    if len(tolerances) < 2 or np.any(tolerances <= 0):
        return ""
    width, height, left, bottom, top, right = 560, 300, 48, 36, 12, 12
    lo, hi = np.log10(tolerances.min()), np.log10(tolerances.max())
    x = lambda t: left + (np.log10(t) - lo) / max(hi - lo, 1e-9) * (width - left - right)  # noqa: E731
    y = lambda v: top + (1 - v) * (height - top - bottom)  # noqa: E731
    parts = [
        f'<svg class="curve" viewBox="0 0 {width} {height}" role="img" aria-label="scores against tolerance">'
    ]
    for v in (0, 0.25, 0.5, 0.75, 1):
        parts.append(
            f'<line class="grid" x1="{left}" x2="{width - right}" y1="{y(v):.1f}" y2="{y(v):.1f}"/>'
            f'<text x="{left - 6}" y="{y(v) + 4:.1f}" text-anchor="end">{int(v * 100)}</text>'
        )
    for t in tolerances[:: max(1, len(tolerances) // 6)]:
        parts.append(
            f'<text x="{x(t):.1f}" y="{height - 14}" text-anchor="middle">{t * 100:.2g}</text>'
        )
    parts.append(
        f'<text x="{(width + left) / 2}" y="{height - 1}" text-anchor="middle">tolerance [cm]</text>'
    )
    for key, css in (("accuracy", "acc"), ("completeness", "comp"), ("f1", "f1")):
        values = curve.get(key) or []
        path = " ".join(f"{x(t):.1f},{y(float(v)):.1f}" for t, v in zip(tolerances, values))
        parts.append(f'<polyline class="{css}" points="{path}"><title>{key}</title></polyline>')
    parts.append(
        f'<g class="legend"><text class="acc" x="60" y="28">{escape(names[0])}</text>'
        f'<text class="comp" x="140" y="28">{escape(names[1])}</text><text class="f1" x="250" y="28">F1</text></g>'
    )
    return "".join(parts) + "</svg>"


def scores_section(
    evaluation: dict,
    curve: dict | None = None,
    curve_image: str | None = None,
    what: str = "Fused cloud",
) -> str:
    """The scores: ETH3D's per tolerance, Tanks and Temples', the depth maps' means; the curve
    against the tolerance (``curve``: its figures, drawn; else ``curve_image``: a picture of it)."""
    if not evaluation:
        return ""
    parts = ['<section id="scores"><h2>Scores</h2>']
    eth3d = evaluation.get("eth3d")
    if eth3d:
        rows = "".join(
            f"<tr><td>{100 * t:g} cm</td><td>{100 * a:.2f}</td><td>{100 * c:.2f}</td><td><b>{100 * f:.2f}</b>"
            f"</td></tr>"
            for t, a, c, f in zip(
                eth3d["tolerances"], eth3d["accuracy"], eth3d["completeness"], eth3d["f1"]
            )
        )
        parts.append(
            f"<h3>{escape(what)} against the ground truth (ETH3D metric)</h3><table><thead><tr><th>tolerance"
            "</th><th>accuracy %</th><th>completeness %</th><th>F1 %</th></tr></thead>"
            f"<tbody>{rows}</tbody></table>"
        )
    tanks = evaluation.get("tanks")
    if tanks:
        parts.append(
            f"<h3>{escape(what)} against the ground truth (Tanks and Temples metric)</h3><table><thead><tr>"
            "<th>threshold</th><th>precision %</th><th>recall %</th><th>F-score %</th></tr></thead><tbody>"
            f"<tr><td>{format_value(tanks.get('threshold'), 4)} m</td><td>{100 * tanks['precision']:.2f}</td>"
            f"<td>{100 * tanks['recall']:.2f}</td><td><b>{100 * tanks['fscore']:.2f}</b></td></tr>"
            "</tbody></table>"
        )
        steps = tanks.get("curve") or {}
        if steps.get("thresholds"):
            parts.append(
                curve_svg(
                    {
                        "tolerances": steps["thresholds"],
                        "accuracy": steps["precision"],
                        "completeness": steps["recall"],
                        "f1": steps["fscore"],
                    },
                    ("precision", "recall"),
                )
            )
    if curve is not None and curve.get("tolerances"):
        parts.append(curve_svg(curve))
    elif curve_image is not None:
        parts.append(
            f'<img class="curve" src="{escape(curve_image)}" alt="scores against tolerance">'
        )
    depth = evaluation.get("depth_maps") or {}
    mean = depth.get("mean") or {
        key: value for key, value in depth.items() if isinstance(value, (int, float))
    }
    if mean:
        cells = "".join(
            f"<tr><td>{escape(key.replace('_', ' '))}</td><td>{format_value(value, 4)}</td></tr>"
            for key, value in mean.items()
            if isinstance(value, (int, float))
        )
        parts.append(
            f"<h3>Depth maps against the ground truth (mean over the views)</h3><table><tbody>{cells}"
            f"</tbody></table>"
        )
    others = {k: v for k, v in evaluation.items() if k not in ("eth3d", "tanks") and v is not None}
    if others:
        parts.append(
            f"<details><summary>every score (JSON)</summary><pre>{escape(json.dumps(others, indent=1))}</pre>"
            f"</details>"
        )
    return "".join(parts) + "</section>"


def run_scores_section(folder: Path, manifest: dict) -> str:
    """The scores section of the report of the run in ``folder`` (its manifest's scores, or the
    files the scoring wrote in ``folder/evaluation``); "" where the run was not scored."""
    return scores_section(
        _run_scores(folder, manifest),
        read_json_object(folder / "evaluation" / "fused_f1.json"),
        "evaluation/fused_f1.png" if (folder / "evaluation" / "fused_f1.png").is_file() else None,
    )


def write_evaluation_page(
    page: str | Path,
    scores: dict,
    reconstruction: str | Path | None = None,
    clouds: str | Path | None = None,
    curve: str | Path | None = None,
    overwrite: bool = False,
) -> Path:
    """``dvpmvs eval``'s page, ``page`` (beside its ``report=`` JSON): the scores (``scores``,
    that JSON's content), the curve against the tolerance (``curve``: the figures ``plot=``
    wrote beside its PNG), and the scored cloud ``reconstruction`` in 3D with the coloured clouds
    of ``clouds=``."""
    metric = str(scores.get("metric", "eth3d"))
    items = [
        (key.replace("_", " "), escape(scores[key]))
        for key in (
            "metric",
            "reconstruction",
            "ground_truth",
            "scene",
            "reconstruction_points",
            "seconds",
        )
        if key in scores
    ]
    items += [
        (key.replace("_", " "), escape(value))
        for key, value in (scores.get("parameters") or {}).items()
    ]
    section = {"eth3d": "eth3d", "tanks": "tanks", "depth": "depth_maps"}.get(metric, metric)
    details = "".join(f"<dt>{escape(k)}</dt><dd>{v}</dd>" for k, v in items)
    sections = (
        f'<section id="run"><h2>Evaluation</h2><dl>{details}</dl></section>'
        + scores_section(
            {section: scores},
            read_json_object(Path(curve)) if curve is not None else None,
            what="The cloud",
        )
    )
    cloud = Path(reconstruction) if reconstruction is not None else None
    return write_cloud_page(
        page,
        f"dvpmvs eval: {cloud.name if cloud is not None else metric}",
        sections,
        cloud,
        Path(clouds) if clouds is not None else None,
        overwrite=overwrite,
    )
