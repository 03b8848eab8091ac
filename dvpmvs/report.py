"""A run's HTML report, and a sweep's: what a run made, to look at in a browser.

``RUN/report.html`` shows, from the run's folder alone: the configuration, provenance and timing
(the manifest's), per view its sources, depth range, seconds, work per pixel and the previews the
run wrote (depth, normal, cost, priors, and the error maps where it was scored), the scores with
their curve against the tolerance, and the fused cloud in an interactive 3D view (three.js, with
the cameras as frusta), subsampled to ``max_points``. A sweep's ``report.html`` has the table of
its jobs (sortable), each row linking to the job's report, and the jobs' clouds side by side.

The page works offline and from disk (``file://``): every script and style is copied into
``RUN/report_files/`` (three.js is vendored at a pinned version, :file:`report_assets/`), and the
cloud is a script (``report_files/cloud.js``) rather than a file the page fetches, because a
browser refuses ``fetch`` and ES-module imports from file URLs. No URL in the page leaves the
folder.
"""

from __future__ import annotations

import base64
import functools
import html
import json
import re
import shlex
import shutil
from dataclasses import dataclass, field
from pathlib import Path
from urllib.parse import quote

import numpy as np

from dvpmvs.errors import DvpmvsError
from dvpmvs.maps import atomic_path, path_from_manifest, read_json_object

__all__ = [
    "ASSETS_DIR",
    "DEFAULT_MAX_POINTS",
    "REPORT_NAME",
    "REPORT_SECTIONS_GROUP",
    "ReportError",
    "escape",
    "format_value",
    "write_cloud_page",
    "write_run_report",
    "write_sweep_report",
]

REPORT_NAME = "report.html"
ASSETS_DIR = "report_files"
DEFAULT_MAX_POINTS = 2_000_000  # what a browser's WebGL holds without trouble
_ASSETS = Path(__file__).parent / "report_assets"
# (shipped file, its name in report_files/); three.js is vendored at a pinned version
_STATIC = (
    ("vendor/three.bundle.js", "three.bundle.js"),
    ("vendor/LICENSE.three.txt", "LICENSE.three.txt"),
    ("viewer.js", "viewer.js"),
    ("report.css", "report.css"),
)
_MANIFEST = "dvpmvs_run.json"
# Plugins that add sections to a run's report: each a callable ``(folder, manifest) -> HTML``
# ("" for none), by entry-point name; the harness registers its scores.
REPORT_SECTIONS_GROUP = "dvpmvs.report_sections"


class ReportError(DvpmvsError):
    """A folder a report cannot be written for."""


# -- what a run folder holds ---------------------------------------------------------------------


@dataclass
class PassFigures:
    """One pass of one view, as its provenance record has it."""

    seconds: float | None
    windows_per_pixel: float | None
    valid_fraction: float | None


@dataclass
class ViewRow:
    """One view: its sources, depth range and camera (its records'), per pass the figures, and
    the pictures the run drew of it."""

    name: str
    sources: list[str] = field(default_factory=list)
    depth_range: tuple[float, float] | None = None
    camera: dict | None = None
    passes: dict[str, PassFigures] = field(default_factory=dict)
    images: list[tuple[str, str]] = field(
        default_factory=list
    )  # (label, path relative to the report)


def _url(path: str) -> str:
    """A relative path as a link's ``href``/``src``: each part percent-encoded (a ``#``, ``%`` or
    ``?`` in a file name is a character, not a fragment, an escape or a query), HTML-escaped."""
    return escape(quote(path, safe="/"))


def _inside(path: Path, folder: Path) -> bool:
    try:
        path.resolve().relative_to(folder.resolve())
        return True
    except ValueError:
        return False


def _stereo_dir(folder: Path, manifest: dict) -> Path:
    recorded = (manifest.get("dense") or {}).get("stereo_dir")
    if recorded and _inside(path_from_manifest(recorded, folder), folder):
        return path_from_manifest(recorded, folder)
    return folder / "stereo"


_PASS_ORDER = ("photometric", "geometric")


def _preview_order(kind: str) -> tuple[int, int, str]:
    """Priors first, then each pass's depth, normal and cost."""
    parts = kind.split(".")
    pass_ = _PASS_ORDER.index(parts[0]) if parts[0] in _PASS_ORDER else -1
    what = (
        ("depth", "normal", "cost").index(parts[1])
        if pass_ >= 0 and parts[1] in ("depth", "normal", "cost")
        else 3
    )
    return pass_, what, kind


def _image_thumbnail(folder: Path, name: str) -> str | None:
    """A copy of the view's photo at most 640 px wide in ``report_files/images/`` (a run's
    ``images/`` is often a link to the workspace's, which a copied folder loses), its path
    relative to the report; None where the photo is not found. Made anew each time (a few ms):
    a kept copy could be of another photo of the same name."""
    import cv2

    source = folder / "images" / name
    target = folder / ASSETS_DIR / "images" / f"{name}.jpg"
    # As COLMAP and the dense stage read it: the stored pixels, whatever the EXIF orientation.
    flags = cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION
    image = cv2.imread(str(source), flags) if source.is_file() else None
    if image is None:
        return None
    scale = min(1.0, 640 / image.shape[1])
    if scale < 1.0:
        image = cv2.resize(
            image,
            (round(image.shape[1] * scale), round(image.shape[0] * scale)),
            interpolation=cv2.INTER_AREA,
        )
    ok, data = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, 88])
    if not ok:
        return None
    with atomic_path(target) as tmp:
        tmp.write_bytes(data.tobytes())
    return target.relative_to(folder).as_posix()


def _previews_of(previews: Path, name: str) -> list[Path]:
    """The previews of image ``name`` (``<name>.<what>.png``; in a subfolder for an image in
    one), found by their names, not by a pattern: ``[``, ``*`` or ``?`` in a name are characters."""
    folder, prefix = (previews / name).parent, Path(name).name + "."
    if not folder.is_dir():
        return []
    return [p for p in folder.iterdir() if p.name.startswith(prefix) and p.suffix == ".png"]


def _view_rows(folder: Path, stereo: Path) -> list[ViewRow]:
    rows: dict[str, ViewRow] = {}
    records = [
        # rglob: an image in a subfolder of images/ (as COLMAP allows) has its record in one
        (path, read_json_object(path))
        for path in sorted((stereo / "provenance").rglob("*.json"))
    ]
    for path, record in records:
        if record is None or record.get("state", "complete") != "complete":
            continue
        inputs, stats = record.get("inputs") or {}, record.get("stats") or {}
        reference = inputs.get("reference") or {}
        name = str(reference.get("name") or path.name.rsplit(".", 2)[0])
        row = rows.setdefault(name, ViewRow(name))
        row.sources = [
            str(source.get("name")) for source in inputs.get("sources") or []
        ] or row.sources
        if reference.get("depth_range"):
            row.depth_range = tuple(reference["depth_range"])
        if all(key in reference for key in ("K", "R", "t", "size")):
            row.camera = {key: reference[key] for key in ("K", "R", "t", "size")}
        size = reference.get("size") or [0, 0]
        pixels, work = float(size[0]) * float(size[1]), stats.get("work") or []
        windows = (
            sum(float(level.get("windows", 0)) for level in work) / pixels
            if pixels and work
            else None
        )
        row.passes[str(inputs.get("pass", ""))] = PassFigures(
            stats.get("seconds"), windows, stats.get("valid_fraction")
        )
    previews, errors = stereo / "previews", folder / "evaluation" / "error_maps"
    for name, row in rows.items():
        ordered = sorted(
            _previews_of(previews, name),
            key=lambda p: _preview_order(p.name[len(Path(name).name) + 1 :]),
        )
        thumbnail = _image_thumbnail(folder, name)
        if thumbnail is not None:
            row.images.append(("image", thumbnail))
        for preview in ordered:
            label = preview.name[len(Path(name).name) + 1 : -len(".png")]
            label = label.replace(".", " ").replace("_", " ")
            row.images.append((label, preview.relative_to(folder).as_posix()))
        error = errors / f"{Path(name).stem}.error.png"
        if error.is_file():
            row.images.append(("depth error", error.relative_to(folder).as_posix()))
    return [rows[name] for name in sorted(rows)]


def _cloud_path(folder: Path, manifest: dict) -> Path | None:
    """The run's fused cloud: where its manifest says (``output=`` may put it outside the folder:
    the page then carries a copy of its points and names it without a link), else
    ``folder/fused.ply``."""
    recorded = ((manifest.get("dense") or {}).get("fusion") or {}).get("output")
    candidates = ([path_from_manifest(recorded, folder)] if recorded else []) + [
        folder / "fused.ply"
    ]
    for path in candidates:
        if path.is_file():
            return path
    return None


# -- the cloud as a script -------------------------------------------------------------------------


def _b64(array: np.ndarray) -> str:
    return base64.b64encode(np.ascontiguousarray(array).tobytes()).decode("ascii")


def _subsample(count: int, max_points: int) -> np.ndarray | None:
    """Which points to keep, the same ones on every run (a fixed seed)."""
    if count <= max_points:
        return None
    return np.sort(np.random.default_rng(0).choice(count, max_points, replace=False))


def _colour_map(values: np.ndarray, top: float) -> np.ndarray:
    import cv2

    scaled = np.clip(np.asarray(values, np.float64) / max(top, 1e-9), 0, 1)
    lookup = cv2.applyColorMap(np.arange(256, dtype=np.uint8).reshape(16, 16), cv2.COLORMAP_TURBO)
    return lookup.reshape(256, 3)[:, ::-1][np.round(scaled * 255).astype(np.intp)]


def _rgb8(colors: np.ndarray | None, count: int) -> np.ndarray:
    if colors is None:
        return np.full((count, 3), 200, np.uint8)
    return np.round(np.clip(colors, 0, 1) * 255).astype(np.uint8)


def _frusta(cameras: list[dict], scale: float) -> np.ndarray:
    """Each camera as 8 line segments (centre to the 4 image corners at depth ``scale``, and the
    image rectangle), in world coordinates: (segments * 2, 3) float32."""
    lines = []
    for camera in cameras:
        K, R, t = (np.asarray(camera[k], np.float64) for k in ("K", "R", "t"))
        width, height = camera["size"]
        centre = -R.T @ t
        pixels = np.array(
            [[0, 0, 1], [width, 0, 1], [width, height, 1], [0, height, 1]], np.float64
        )
        corners = (R.T @ (np.linalg.solve(K, pixels.T) * scale - t.reshape(3, 1))).T
        for i in range(4):
            lines += [centre, corners[i], corners[i], corners[(i + 1) % 4]]
    return np.asarray(lines, np.float32).reshape(-1, 3)


def _point_set(
    label: str, points: np.ndarray, colours: dict[str, np.ndarray], total: int, centre: np.ndarray
) -> dict:
    return {
        "label": label,
        "count": int(len(points)),
        "total": int(total),
        "positions": _b64((points - centre).astype("<f4")),
        "colours": {mode: _b64(values.astype(np.uint8)) for mode, values in colours.items()},
    }


def _evaluation_clouds(folder: Path) -> list[Path]:
    """The evaluation's coloured clouds in ``folder`` at its smallest tolerance (accuracy: the
    reconstruction's points, completeness: the ground truth's), the pair that shows where the
    cloud is wrong."""
    clouds = sorted(folder.glob("*.tolerance_*.ply"))

    def tolerance(path: Path) -> float:
        try:
            return float(path.stem.rsplit("_", 1)[1])
        except (IndexError, ValueError):
            return float("inf")

    smallest = min((tolerance(path) for path in clouds), default=None)
    return [path for path in clouds if tolerance(path) == smallest]


def _cloud_script(
    cloud: Path,
    scored: list[Path],
    cameras: list[dict],
    max_points: int,
    label: str = "fused cloud",
    mesh: Path | None = None,
) -> tuple[str, dict]:
    """``report_files/cloud.js``'s text and what the page says of it: the cloud (RGB, and the
    number of views behind each point where ``<cloud>.vis`` is there), the evaluation's coloured
    clouds ``scored``, the cameras' frusta, and the run's ``mesh`` (decimated to
    MAX_MESH_TRIANGLES) where given."""
    from dvpmvs.fusion import read_visibility
    from dvpmvs.pointcloud import read_ply

    fused = read_ply(cloud)
    keep = _subsample(len(fused), max_points)
    points = fused.points if keep is None else fused.points[keep]
    centre = np.median(points, axis=0) if len(points) else np.zeros(3)
    colours = {
        "rgb": _rgb8(
            fused.colors if keep is None or fused.colors is None else fused.colors[keep],
            len(points),
        )
    }
    vis = cloud.with_name(cloud.name + ".vis")
    if vis.is_file():
        try:
            counts = np.array([len(v) for v in read_visibility(vis)], np.float64)
        except DvpmvsError:
            counts = None
        if counts is not None and len(counts) == len(fused):
            counts = counts if keep is None else counts[keep]
            colours["views"] = _colour_map(counts, max(float(counts.max(initial=1)), 2.0))
    sets = [_point_set(label, points, colours, len(fused), centre)]
    for path in scored:
        evaluated = read_ply(path)
        chosen = _subsample(len(evaluated), max_points)
        shown = evaluated.points if chosen is None else evaluated.points[chosen]
        colours = (
            evaluated.colors
            if chosen is None or evaluated.colors is None
            else evaluated.colors[chosen]
        )
        sets.append(
            _point_set(
                f"evaluation: {path.stem.replace('.tolerance_', ' at ')} m",
                shown,
                {"error": _rgb8(colours, len(shown))},
                len(evaluated),
                centre,
            )
        )
    extent = (
        float(np.linalg.norm(np.percentile(points, 95, axis=0) - np.percentile(points, 5, axis=0)))
        if len(points)
        else 1.0
    )
    frusta = (
        _frusta(cameras, 0.06 * extent) - centre.astype(np.float32)
        if cameras
        else np.zeros((0, 3), np.float32)
    )
    data = {
        "sets": sets,
        "frusta": _b64(frusta.astype("<f4")),
        "extent": extent,
        "centre": centre.tolist(),
    }
    mesh_summary = None
    if mesh is not None and mesh.is_file():
        data["mesh"] = mesh_summary = _mesh_data(mesh, centre)
    script = (
        "(window.dvpmvsClouds = window.dvpmvsClouds || {})"
        f"[(document.currentScript && document.currentScript.dataset.key) || 'run'] = {json.dumps(data)};\n"
    )
    summary = {
        "points": len(fused),
        "shown": int(len(points)),
        "sets": [s["label"] for s in sets],
        "mesh": None
        if mesh_summary is None
        else {k: mesh_summary[k] for k in ("triangles", "shown")},
    }
    return script, summary


# The triangles of a mesh the page draws at most (a few MB of script; a browser draws them at once).
MAX_MESH_TRIANGLES = 300_000


def _mesh_data(path: Path, centre: np.ndarray) -> dict:
    """A mesh for the viewer: its vertices (centred as the cloud), colours and triangles,
    decimated (quadric error, Open3D) to MAX_MESH_TRIANGLES where it has more."""
    from dvpmvs.pointcloud import ply_element_counts
    from dvpmvs.stage_progress import in_child_process

    if ply_element_counts(path)[1] > MAX_MESH_TRIANGLES:
        # Open3D's decimation holds the GIL for seconds; the report's heartbeat keeps talking.
        return in_child_process(_viewer_mesh, path, centre)
    return _viewer_mesh(path, centre)


def _viewer_mesh(path: Path, centre: np.ndarray) -> dict:
    import open3d as o3d

    mesh = o3d.io.read_triangle_mesh(str(path))
    total = len(mesh.triangles)
    if total > MAX_MESH_TRIANGLES:
        mesh = mesh.simplify_quadric_decimation(MAX_MESH_TRIANGLES)
    vertices = np.asarray(mesh.vertices, np.float64) - centre
    colours = np.asarray(mesh.vertex_colors) if mesh.has_vertex_colors() else None
    return {
        "positions": _b64(vertices.astype("<f4")),
        "colours": _b64(_rgb8(colours, len(vertices))),
        "indices": _b64(np.asarray(mesh.triangles, "<u4")),
        "triangles": total,
        "shown": len(mesh.triangles),
    }


# -- HTML -------------------------------------------------------------------------------------------


def escape(value) -> str:
    """``value`` as HTML text (for a report section's plugin too)."""
    return html.escape(str(value), quote=True)


def format_value(value, digits: int = 2) -> str:
    """``value`` as a report shows it: "-" for None, thousands separated, ``digits`` decimals."""
    if value is None:
        return "-"
    if isinstance(value, bool):
        return escape(value)
    if isinstance(value, int):
        return f"{value:,}"
    if isinstance(value, float):
        return f"{value:,.{digits}f}"
    return escape(value)


def _copy_assets(target: Path) -> None:
    target.mkdir(parents=True, exist_ok=True)
    for shipped, name in _STATIC:
        source = _ASSETS / shipped
        destination = target / name
        if not destination.is_file() or destination.read_bytes() != source.read_bytes():
            with atomic_path(destination) as tmp:
                shutil.copyfile(source, tmp)


# how a page of ours is told from a user's
_GENERATOR = '<meta name="generator" content="dvpmvs report">'
# What a page is, in its head: a run's report, a sweep's, or a page of its own (``dvpmvs eval``).
_KIND = '<meta name="dvpmvs-page" content="{}">'
_KIND_WORDS = {"run": "a run's report", "sweep": "a sweep's report", "page": "an evaluation's page"}


def _check_ours(page: Path, overwrite: bool, kind: str) -> None:
    """A page (or ``report_files/`` folder) at the report's place that dvpmvs did not write, or
    that is another kind of page (``kind``: ``run``, ``sweep``, ``page``; an evaluation's page
    never replaces a run's report), is not replaced unless ``overwrite``."""
    if overwrite:
        return
    assets = page.parent / ASSETS_DIR
    foreign = []
    if page.exists():
        try:
            head = page.read_text(errors="replace")[:2000]
        except OSError:
            head = ""
        if _GENERATOR not in head:
            foreign.append(str(page))
        else:
            found = re.search(r'<meta name="dvpmvs-page" content="(\w+)">', head)
            if found is not None and found.group(1) != kind:
                remedy = (
                    "give report= another name"
                    if kind == "page"
                    else "move it away, or `dvpmvs report --overwrite` to replace it"
                )
                raise ReportError(
                    f"{page} is {_KIND_WORDS.get(found.group(1), found.group(1))}; "
                    f"{_KIND_WORDS[kind]} is not written over it: {remedy} (or overwrite=true)"
                )
    if assets.exists() and not (assets / "viewer.js").is_file():
        foreign.append(f"{assets}/")
    if foreign:
        raise ReportError(
            f"{' and '.join(foreign)} exist{'s' if len(foreign) == 1 else ''} and dvpmvs did not write "
            f"{'it' if len(foreign) == 1 else 'them'}; the report is not written over "
            f"{'it' if len(foreign) == 1 else 'them'} (overwrite=true, or `dvpmvs report --overwrite`, "
            f"replaces {'it' if len(foreign) == 1 else 'them'})"
        )


def _page(title: str, body: str, scripts: list[str], setup: str, kind: str) -> str:
    tags = "\n".join(f'<script src="{escape(src)}"></script>' for src in scripts)
    return (
        f'<!doctype html>\n<html lang="en"><head><meta charset="utf-8">{_GENERATOR}'
        f"{_KIND.format(kind)}"
        f'<meta name="viewport" content="width=device-width, initial-scale=1">'
        f'<title>{escape(title)}</title><link rel="stylesheet" href="{ASSETS_DIR}/report.css"></head>\n'
        f"<body>\n{body}\n{tags}\n<script>{setup}</script>\n</body></html>\n"
    )


def _definition_list(items: list[tuple[str, str]]) -> str:
    return "<dl>" + "".join(f"<dt>{escape(k)}</dt><dd>{v}</dd>" for k, v in items) + "</dl>"


def _config_section(manifest: dict, folder: Path | None = None) -> str:
    code, scene = manifest.get("code") or {}, manifest.get("scene") or {}
    environment = manifest.get("environment") or {}
    items = [
        (
            "status",
            escape(manifest.get("status", "-"))
            + (f": {escape(manifest['error'])}" if manifest.get("error") else ""),
        ),
        # Quoted as a shell reads it back: the command can be pasted to run again.
        ("command", f"<code>{escape(shlex.join(manifest.get('command') or []))}</code>"),
        ("started", escape(manifest.get("started") or "-")),
        ("wall seconds", format_value(manifest.get("seconds"), 1)),
        (
            "peak memory",
            f"{format_value(manifest.get('peak_rss_mb'), 0)} MB"
            if manifest.get("peak_rss_mb")
            else "-",
        ),
        ("threads", format_value(manifest.get("threads"))),
        ("dvpmvs", escape(code.get("dvpmvs") or manifest.get("dvpmvs", "-"))),
    ]
    mesh = manifest.get("mesh")
    if mesh and folder is not None and _inside(path_from_manifest(mesh, folder), folder):
        link = path_from_manifest(mesh, folder).resolve().relative_to(folder.resolve()).as_posix()
        items.append(("mesh", f'<a href="{_url(link)}">{escape(link)}</a>'))
    stages = manifest.get("stages") or []
    if stages:
        items.append(
            (
                "stages",
                "<br>".join(
                    f"{escape(s['stage'])}: {'reused' if s.get('reused') else 'ran'}, "
                    f"{format_value(s.get('seconds'), 1)} s, {escape(s.get('result', ''))}"
                    for s in stages
                ),
            )
        )
    if scene:
        items.append(
            (
                "scene",
                f"{escape(scene.get('key', ''))} <code>{escape(scene.get('short', ''))}</code>"
                + (" (the documented render)" if scene.get("documented") else ""),
            )
        )
    if code.get("sources"):
        items.append(("sources digest", f"<code>{escape(str(code['sources'])[:12])}</code>"))
    libraries = code.get("libraries") or {}
    if libraries:
        items.append(
            ("libraries", escape(", ".join(f"{k} {v}" for k, v in sorted(libraries.items()))))
        )
    if environment:
        items.append(
            (
                "environment",
                escape(
                    ", ".join(
                        f"{k}: {v}"
                        for k, v in sorted(environment.items())
                        if not isinstance(v, (dict, list))
                    )
                ),
            )
        )
    config = manifest.get("config")
    details = (
        (
            f"<details><summary>resolved configuration</summary><pre>{escape(json.dumps(config, indent=1))}</pre>"
            f"</details>"
        )
        if config
        else ""
    )
    return f'<section id="run"><h2>Run</h2>{_definition_list(items)}{details}</section>'


def _windows_per_finest_pixel(work: list[dict]) -> float | None:
    """The windows a pass matched at every pyramid level, per pixel of its finest level (the work
    measure of docs/benchmarks.md); ``work``: the manifest's per-level figures, per pixel of each level."""
    if not work:
        return None
    finest = max(float(level["size"][0]) * float(level["size"][1]) for level in work)
    return sum(
        float(level["windows"]) * float(level["size"][0]) * float(level["size"][1]) / finest
        for level in work
    )


def _timing_section(manifest: dict) -> str:
    dense = manifest.get("dense") or {}
    passes = dense.get("passes") or {}
    if not passes:
        return ""
    rows = []
    for name, entry in passes.items():
        work = entry.get("work_per_pixel") or []
        windows = _windows_per_finest_pixel(work)
        rows.append(
            f"<tr><td>{escape(name)}</td><td>{entry.get('views', 0)}</td><td>{entry.get('computed', 0)}</td>"
            f"<td>{entry.get('reused', 0) + entry.get('cached', 0)}</td>"
            f"<td>{format_value(entry.get('seconds'), 1)}</td>"
            f"<td>{format_value(entry.get('prior_seconds'), 1)}</td>"
            f"<td>{format_value(100 * entry.get('valid_fraction', 0.0), 1)}</td>"
            f"<td>{format_value(windows, 0)}</td></tr>"
        )
    fusion = dense.get("fusion") or {}
    return (
        '<section id="timing"><h2>Timing</h2><table><thead><tr><th>pass</th><th>views</th><th>computed</th>'
        "<th>reused</th><th>seconds</th><th>of which priors</th><th>valid %</th><th>windows / pixel</th></tr>"
        f"</thead><tbody>{''.join(rows)}</tbody></table>"
        f"<p>{format_value(dense.get('seconds_per_view'), 2)} s per view (maps of both passes, priors and fusion, over "
        f"the views); fusion {format_value(fusion.get('seconds'), 1)} s, {int(fusion.get('points', 0)):,} points"
        f"{' (reused)' if fusion.get('reused') else ''}.</p></section>"
    )


@functools.cache  # the same for every depth preview of a page
def _turbo_css() -> str:
    """The turbo colour map (the depth previews') as a CSS gradient."""
    stops = _colour_map(np.linspace(0, 1, 9), 1.0)
    return "linear-gradient(90deg, " + ", ".join(f"rgb({r},{g},{b})" for r, g, b in stops) + ")"


def _legend(label: str, depth_range: tuple[float, float] | None) -> str:
    """What a preview's colours mean, under it: the depth previews' turbo map over the view's
    depth range (the range they were drawn with), the cost previews' grey from 0 to 1, the normal
    previews' axes, the depth error's tolerance colours (``error_image``)."""
    words = label.split()

    def bar(low: str, background: str, high: str) -> str:
        return (
            f'<div class="legend"><span>{low}</span><span class="bar" style="background: '
            f'{background}"></span><span>{high}</span></div>'
        )

    if label == "depth error":
        return bar("1 %", "linear-gradient(90deg, #00ff00, #ffff00, #ff0000)", "5 %+; blue: none")
    if "depth" in words and depth_range is not None:
        return bar(f"{depth_range[0]:.3g}", _turbo_css(), f"{depth_range[1]:.3g}")
    if "cost" in words:
        return bar("0", "linear-gradient(90deg, #000, #fff)", "1 (1 - NCC)")
    if "normal" in words:
        return '<div class="legend">x, y, z: red, green, blue</div>'
    return ""


def _views_section(rows: list[ViewRow]) -> str:
    if not rows:
        return ""
    passes = [p for p in _PASS_ORDER if any(p in row.passes for row in rows)]
    body = []
    for row in rows:
        low_high = (
            f"{row.depth_range[0]:.3g} - {row.depth_range[1]:.3g}" if row.depth_range else "-"
        )
        figures = "".join(
            f"<td>{format_value(f.seconds, 1)}</td><td>{format_value(f.windows_per_pixel, 0)}</td>"
            f"<td>{format_value(None if f.valid_fraction is None else 100 * f.valid_fraction, 1)}</td>"
            if (f := row.passes.get(p)) is not None
            else "<td>-</td><td>-</td><td>-</td>"
            for p in passes
        )
        thumbs = "".join(
            f'<figure><a href="{_url(path)}" class="thumb"><img loading="lazy" src="{_url(path)}" '
            f'alt="{escape(row.name)} {escape(label)}"></a><figcaption>{escape(label)}</figcaption>'
            f"{_legend(label, row.depth_range)}</figure>"
            for label, path in row.images
        )
        body.append(
            f"<tr><td>{escape(row.name)}</td><td>{escape(', '.join(row.sources))}</td><td>{low_high}</td>"
            f'{figures}<td class="thumbs">{thumbs}</td></tr>'
        )
    head = "".join(f'<th colspan="3">{escape(p)}</th>' for p in passes)
    sub = "<th>seconds</th><th>windows / pixel</th><th>valid %</th>" * len(passes)
    return (
        '<section id="views"><h2>Views</h2><table class="views"><thead><tr><th rowspan="2">view</th>'
        f'<th rowspan="2">sources</th><th rowspan="2">depth range</th>{head}<th rowspan="2">maps and priors '
        f"(click to enlarge)</th></tr><tr>{sub}</tr></thead><tbody>{''.join(body)}</tbody></table></section>"
    )


def _viewer_section(summary: dict | None, cloud: Path | None, folder: Path) -> str:
    if summary is None:
        return '<section id="cloud"><h2>Cloud</h2><p>This run wrote no fused cloud.</p></section>'
    shown = (
        f"{summary['shown']:,} of {summary['points']:,} points shown (a fixed subsample)"
        if summary["shown"] < summary["points"]
        else f"{summary['points']:,} points"
    )
    if _inside(cloud, folder):
        link = cloud.resolve().relative_to(folder.resolve()).as_posix()
        name = f'<a href="{_url(link)}">{escape(link)}</a>'
    else:  # shown from the page's own copy of its points; the file itself lies elsewhere
        name = f"<code>{escape(cloud)}</code>"
    mesh = summary.get("mesh")
    if mesh:
        shown += (
            f"; the mesh, {mesh['triangles']:,} triangles"
            + (
                f" ({mesh['shown']:,} drawn, decimated)"
                if mesh["shown"] < mesh["triangles"]
                else ""
            )
            + ", drawn with the points or alone (the viewer's show menu)"
        )
    return (
        f'<section id="cloud"><h2>Cloud</h2><p>{name}: {shown}. '
        'Drag to orbit, scroll to zoom, right-drag to pan.</p><div class="viewer" data-key="run"></div></section>'
    )


def _cloud_script_name(page: Path) -> str:
    """The file under ``report_files/`` holding ``page``'s cloud: ``cloud.js`` for the folder's
    report (a sweep's page loads its jobs' by that name), ``<page stem>.cloud.js`` for a page
    of its own, so that pages sharing a folder never draw each other's clouds."""
    return "cloud.js" if page.name == REPORT_NAME else f"{page.stem}.cloud.js"


def _write_page(path: Path, title: str, sections: str, setup: str, with_cloud: bool) -> Path:
    scripts = [f"{ASSETS_DIR}/three.bundle.js", f"{ASSETS_DIR}/viewer.js"] + (
        [f"{ASSETS_DIR}/{_cloud_script_name(path)}"] if with_cloud else []
    )
    body = f"<header><h1>{escape(title)}</h1></header>" + sections
    page = _page(title, body, scripts, setup, "page")
    with atomic_path(path) as tmp:
        tmp.write_text(page, encoding="utf-8")
    return path


def write_cloud_page(
    page: str | Path,
    title: str,
    sections: str,
    cloud: Path | None = None,
    coloured: Path | None = None,
    max_points: int = DEFAULT_MAX_POINTS,
    overwrite: bool = False,
) -> Path:
    """A page of its own, ``page``: ``title``, the HTML ``sections`` given, and ``cloud`` in 3D
    with the coloured clouds of an evaluation in the folder ``coloured`` (``page``'s
    ``report_files/`` holds the copies of their points). A page dvpmvs did not write is an error
    unless ``overwrite``."""
    page = Path(page)
    folder = page.parent
    _check_ours(page, overwrite, "page")
    assets = folder / ASSETS_DIR
    _copy_assets(assets)
    summary = None
    if cloud is not None and cloud.is_file():
        scored = _evaluation_clouds(coloured) if coloured is not None else []
        script, summary = _cloud_script(cloud, scored, [], max_points, label="scored cloud")
        with atomic_path(assets / _cloud_script_name(page)) as tmp:
            tmp.write_text(script)
    if summary is not None:
        sections += _viewer_section(summary, cloud, folder)
    return _write_page(page, title, sections, "dvpmvsReport.setup();", summary is not None)


def _plugin_sections(folder: Path, manifest: dict) -> str:
    """The sections the installed report plugins give for the run in ``folder`` (entry-point
    group :data:`REPORT_SECTIONS_GROUP`; the harness's: the scores against ground truth)."""
    from dvpmvs.registry import load_entry_points

    return "".join(
        section(folder, manifest) or ""
        for _name, section in load_entry_points(REPORT_SECTIONS_GROUP, "report section")
    )


# The manifest's fields the page reads, by the type dvpmvs writes them with (run.py).
_MANIFEST_TYPES = {
    "dense": dict,
    "code": dict,
    "scene": dict,
    "environment": dict,
    "config": dict,
    "options": dict,
    "evaluation": dict,
    "command": list,
    "stages": list,
    "overrides": list,
    "status": str,
    "started": str,
    "error": str,
    "mesh": str,
    "seconds": (int, float),
    "peak_rss_mb": (int, float),
    "threads": int,
}
_DENSE_TYPES = {"fusion": dict, "passes": dict, "stereo_dir": str}


def _read_manifest(path: Path) -> dict:
    """The run's manifest at ``path`` ({} where there is none); one that is not JSON, or whose
    fields the page reads are not of the types dvpmvs writes (an edited or foreign file), is a
    :class:`ReportError` naming the file and the field."""
    if not path.exists():
        return {}
    manifest = read_json_object(path)
    if manifest is None:
        problem = "is not a JSON object (damaged, or not dvpmvs's)"
    else:
        dense = manifest.get("dense")
        fields = [(key, manifest.get(key), kind) for key, kind in _MANIFEST_TYPES.items()]
        if isinstance(dense, dict):
            fields += [(f"dense.{key}", dense.get(key), kind) for key, kind in _DENSE_TYPES.items()]
        wrong = [
            (key, value)
            for key, value, kind in fields
            if value is not None and not isinstance(value, kind)
        ]
        problem = (
            f"holds a {type(wrong[0][1]).__name__} as {wrong[0][0]!r}, not what dvpmvs writes"
            if wrong
            else None
        )
    if problem is not None:
        raise ReportError(
            f"{path} {problem}: remove it (the page is then drawn from the maps' records alone), "
            f"or run the command again to write it anew"
        )
    return manifest


def write_run_report(
    folder: str | Path,
    manifest: dict | None = None,
    max_points: int = DEFAULT_MAX_POINTS,
    title: str | None = None,
    overwrite: bool = False,
) -> Path:
    """Write ``folder/report.html`` (and ``folder/report_files/``) for the run whose outputs are in
    ``folder``; ``manifest``: the run's manifest (default: ``folder/dvpmvs_run.json`` when there).
    Returns the page's path. Every file it links lies in ``folder``. A ``report.html`` or
    ``report_files/`` there that dvpmvs did not write is an error unless ``overwrite``."""
    folder = Path(folder)
    if not folder.is_dir():
        raise ReportError(
            f"{folder} is not a folder; `dvpmvs report` takes a run's output folder (where "
            f"{_MANIFEST} or stereo/ is)"
        )
    if max_points < 1:
        raise ReportError(f"max_points={max_points}: give a positive number of points to show")
    if manifest is None:
        manifest = _read_manifest(folder / _MANIFEST)
    _check_ours(folder / REPORT_NAME, overwrite, "run")
    stereo = _stereo_dir(folder, manifest)
    views = _view_rows(folder, stereo)
    # A folder an earlier run also wrote to holds that run's records too: the page shows the
    # views this run has (its manifest's), where the manifest says which.
    ran = {
        str(report.get("name"))
        for figures in ((manifest.get("dense") or {}).get("passes") or {}).values()
        if isinstance(figures, dict)
        for report in figures.get("view_reports") or []
        if isinstance(report, dict)
    }
    views = [row for row in views if row.name in ran] if ran else views
    if not manifest and not views:
        raise ReportError(
            f"{folder} holds no run: neither {_MANIFEST} nor map records under stereo/provenance; "
            f"give the folder a `dvpmvs dense` run wrote (its out=)"
        )
    cameras = list({row.name: row.camera for row in views if row.camera is not None}.values())
    cloud = _cloud_path(folder, manifest)
    assets = folder / ASSETS_DIR
    _copy_assets(assets)
    summary = None
    if cloud is not None:
        mesh = manifest.get("mesh")
        script, summary = _cloud_script(
            cloud,
            _evaluation_clouds(folder / "evaluation" / "clouds"),
            cameras,
            max_points,
            mesh=None if not mesh else path_from_manifest(mesh, folder),
        )
        with atomic_path(assets / "cloud.js") as tmp:
            tmp.write_text(script)
    elif (assets / "cloud.js").exists():
        (assets / "cloud.js").unlink()
    title = title or f"dvpmvs run: {folder.resolve().name}"
    body = (
        f'<header><h1>{escape(title)}</h1><nav><a href="#run">run</a> <a href="#scores">scores</a> '
        f'<a href="#cloud">cloud</a> <a href="#views">views</a></nav></header>'
        + _config_section(manifest, folder)
        + _timing_section(manifest)
        + _plugin_sections(folder, manifest)
        + _viewer_section(summary, cloud, folder)
        + _views_section(views)
        + '<div id="lightbox" hidden><img alt=""></div>'
    )
    scripts = [f"{ASSETS_DIR}/three.bundle.js", f"{ASSETS_DIR}/viewer.js"]
    if summary is not None:
        scripts.append(f"{ASSETS_DIR}/cloud.js")
    page = _page(title, body, scripts, "dvpmvsReport.setup();", "run")
    path = folder / REPORT_NAME
    with atomic_path(path) as tmp:
        tmp.write_text(page, encoding="utf-8")
    return path


def _markdown_html(text: str) -> str:
    """The sweep's Markdown summaries (paragraphs, pipe tables, ``**bold**``, lists) as HTML."""

    def inline(value: str) -> str:
        parts = escape(value).split("**")
        return "".join(f"<b>{part}</b>" if i % 2 else part for i, part in enumerate(parts))

    blocks = []
    for block in text.strip().split("\n\n"):
        lines = block.splitlines()
        if lines and all(line.startswith("|") for line in lines):
            rows = [
                [cell.strip() for cell in line.strip().strip("|").split("|")]
                for line in lines
                if not set(line.replace("|", "").strip()) <= {"-", ":"}
            ]
            head = "".join(f"<th>{inline(c)}</th>" for c in rows[0])
            body = "".join(
                "<tr>" + "".join(f"<td>{inline(c)}</td>" for c in row) + "</tr>" for row in rows[1:]
            )
            blocks.append(
                f'<table class="sortable"><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>'
            )
        elif lines and all(line.startswith("- ") for line in lines):
            blocks.append(
                "<ul>" + "".join(f"<li>{inline(line[2:])}</li>" for line in lines) + "</ul>"
            )
        else:
            blocks.append(f"<p>{inline(' '.join(lines))}</p>")
    return "".join(blocks)


# The clouds a sweep's page draws when it opens (each is megabytes for the browser); the reader
# ticks the others.
CLOUDS_SHOWN = 4


def _clouds_shown_first(rows: list[dict]) -> set[int]:
    """The rows whose clouds are ticked: all of a sweep of up to CLOUDS_SHOWN jobs; in a larger
    one, the default configuration's jobs (``method=default`` in their label) first, then the
    first of the others."""
    if len(rows) <= CLOUDS_SHOWN:
        return set(range(len(rows)))
    default = [i for i, row in enumerate(rows) if "method=default" in str(row.get("label", ""))]
    others = [i for i in range(len(rows)) if i not in default]
    return set((default + others)[:CLOUDS_SHOWN])


def write_sweep_report(
    sweep_dir: str | Path,
    header: list[str],
    rows: list[dict],
    summary_markdown: str = "",
    title: str | None = None,
    overwrite: bool = False,
) -> Path:
    """Write ``sweep_dir/report.html``: the sweep's jobs (``header`` and ``rows``, each a dict with
    ``cells`` (strings, one per header column), ``folder`` (the job's folder) and ``label``), each
    row linking to its job's report, its summary tables (``summary_markdown``, as ``table.md``
    has them), and the clouds of the jobs the reader picks side by side."""
    sweep_dir = Path(sweep_dir)
    _check_ours(sweep_dir / REPORT_NAME, overwrite, "sweep")
    _copy_assets(sweep_dir / ASSETS_DIR)
    body_rows, choices = [], []
    shown = _clouds_shown_first(rows)
    for i, row in enumerate(rows):
        folder = Path(row["folder"])
        relative = folder.relative_to(sweep_dir).as_posix() if _inside(folder, sweep_dir) else None
        has_report = relative is not None and (folder / REPORT_NAME).is_file()
        link = (
            f'<a href="{_url(relative)}/{REPORT_NAME}">{escape(row["label"])}</a>'
            if has_report
            else escape(row["label"])
        )
        cells = "".join(f"<td>{escape(cell)}</td>" for cell in row["cells"])
        body_rows.append(f"<tr><td>{link}</td>{cells}</tr>")
        if has_report and (folder / ASSETS_DIR / "cloud.js").is_file():
            choices.append(
                f'<label><input type="checkbox" data-key="job{i}" data-src="{_url(relative)}/{ASSETS_DIR}/'
                f'cloud.js" data-label="{escape(row["label"])}"{" checked" if i in shown else ""}> '
                f"{escape(row['label'])}</label>"
            )
    head = "".join(f"<th>{escape(h)}</th>" for h in ["job", *header])
    title = title or f"dvpmvs sweep: {sweep_dir.resolve().name}"
    body = (
        f'<header><h1>{escape(title)}</h1></header><section id="table"><h2>Jobs</h2><p>Click a column to sort; a '
        f'job\'s name opens its report.</p><table class="sortable"><thead><tr>{head}</tr></thead><tbody>'
        f"{''.join(body_rows)}</tbody></table></section>"
        + (
            f'<section id="summary"><h2>Tables</h2>{_markdown_html(summary_markdown)}</section>'
            if summary_markdown.strip()
            else ""
        )
        + '<section id="clouds"><h2>Clouds side by side</h2><p>The views of the clouds move together.</p>'
        f'<div class="choices">{"".join(choices) or "no job wrote a cloud"}</div><div id="compare"></div></section>'
    )
    page = _page(
        title,
        body,
        [f"{ASSETS_DIR}/three.bundle.js", f"{ASSETS_DIR}/viewer.js"],
        "dvpmvsReport.setupSweep();",
        "sweep",
    )
    path = sweep_dir / REPORT_NAME
    with atomic_path(path) as tmp:
        tmp.write_text(page, encoding="utf-8")
    return path
