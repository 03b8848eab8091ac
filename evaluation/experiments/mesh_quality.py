"""Meshes of a fused cloud scored against ground truth: which mesher, depth and trim serve.

For each workspace (a fused cloud ``fused.ply`` beside ``ground_truth/scan_alignment.mlp``, as
``dvpmvs demo`` or ``dvpmvs bench`` leave them): the cloud itself, then each meshing
configuration through :func:`dvpmvs.meshing.mesh_cloud`; a mesh is scored by the ETH3D metric
on points sampled uniformly on its surface (seeded), one per ``--spacing`` squared of area (5 mm:
well below the 2 cm tolerance, so that the samples' own spacing does not cost completeness), so
that a mesh and a cloud are judged alike. Time is the mesher's, one thread unless ``--threads``.

    python -m dvpmvs.evaluation.experiments.mesh_quality WORKSPACE [...] [--depths 10 11]
        [--trim-quantiles 0 0.05 0.1] [--colmap-trims 5 7]

Prints a markdown table per workspace.
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np

from dvpmvs.evaluation.commands import eth3d_parameters_for
from dvpmvs.evaluation.eth3d_metric import evaluate_eth3d
from dvpmvs.evaluation.pointclouds import read_meshlab_project, read_points
from dvpmvs.meshing import MeshingOptions, mesh_cloud

TOLERANCES = (0.02, 0.1)


def surface_samples(
    mesh_path: Path, spacing: float, seed: int = 0, limit: int = 20_000_000
) -> np.ndarray:
    """Points drawn uniformly (by area) on the triangles of a mesh file, one per ``spacing``
    squared of surface (at most ``limit``)."""
    import open3d as o3d

    mesh = o3d.io.read_triangle_mesh(str(mesh_path))
    vertices, triangles = np.asarray(mesh.vertices), np.asarray(mesh.triangles)
    if not len(triangles):
        return np.zeros((0, 3))
    a, b, c = (vertices[triangles[:, i]] for i in range(3))
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    count = int(min(area.sum() / spacing**2, limit))
    rng = np.random.default_rng(seed)
    chosen = rng.choice(len(triangles), count, p=area / area.sum())
    u, v = rng.random((2, count))
    flip = u + v > 1
    u[flip], v[flip] = 1 - u[flip], 1 - v[flip]
    return a[chosen] + u[:, None] * (b - a)[chosen] + v[:, None] * (c - a)[chosen]


def configurations(depths, trim_quantiles, colmap_trims, threads) -> list[MeshingOptions]:
    configs = [
        MeshingOptions(method="poisson", depth=d, trim_quantile=q, num_threads=threads)
        for d in depths
        for q in trim_quantiles
    ]
    configs += [
        MeshingOptions(method="colmap_poisson", depth=d, colmap_trim=t, num_threads=threads)
        for d in depths
        for t in colmap_trims
    ]
    return configs


def score_workspace(workspace: Path, configs: list[MeshingOptions], spacing: float) -> list[dict]:
    mlp = workspace / "ground_truth" / "scan_alignment.mlp"
    truth, parameters = read_meshlab_project(mlp), eth3d_parameters_for(mlp)
    cloud = workspace / "fused.ply"
    result = evaluate_eth3d(read_points(cloud), truth, TOLERANCES, parameters)
    rows = [{"what": "fused cloud", "triangles": None, "seconds": None, "result": result}]
    with tempfile.TemporaryDirectory() as folder:
        for i, options in enumerate(configs):
            output = Path(folder) / f"mesh{i}.ply"
            report = mesh_cloud(cloud, output, options, reuse=False)
            points = surface_samples(output, spacing)
            scored = evaluate_eth3d(points, truth, TOLERANCES, parameters) if len(points) else None
            trim = (
                f"trim_quantile {options.trim_quantile}"
                if options.method == "poisson"
                else f"colmap_trim {options.colmap_trim:g}"
            )
            rows.append(
                {
                    "what": f"{options.method}, depth {options.depth}, {trim}",
                    "triangles": report.triangles,
                    "seconds": report.seconds,
                    "result": scored,
                }
            )
    return rows


def markdown(workspace: Path, rows: list[dict]) -> str:
    lines = [
        f"### {workspace}",
        "",
        "| what | triangles | s | F1 2 cm | F1 10 cm | acc. 2 cm | compl. 2 cm |",
        "|---|---:|---:|---:|---:|---:|---:|",
    ]
    for row in rows:
        r = row["result"]
        figures = (
            ("empty",) * 4
            if r is None
            else (
                f"{100 * r.f1[0]:.2f}",
                f"{100 * r.f1[1]:.2f}",
                f"{100 * r.accuracy[0]:.2f}",
                f"{100 * r.completeness[0]:.2f}",
            )
        )
        triangles = "" if row["triangles"] is None else f"{row['triangles']:,}"
        seconds = "" if row["seconds"] is None else f"{row['seconds']:.1f}"
        lines.append(f"| {row['what']} | {triangles} | {seconds} | " + " | ".join(figures) + " |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("workspaces", nargs="+", type=Path)
    parser.add_argument("--depths", nargs="+", type=int, default=[10, 11])
    parser.add_argument("--trim-quantiles", nargs="+", type=float, default=[0.0, 0.05, 0.1])
    parser.add_argument("--colmap-trims", nargs="+", type=float, default=[5.0, 7.0])
    parser.add_argument(
        "--spacing", type=float, default=0.005, help="metres between surface samples"
    )
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args(argv)
    configs = configurations(args.depths, args.trim_quantiles, args.colmap_trims, args.threads)
    for workspace in args.workspaces:
        print(markdown(workspace, score_workspace(workspace, configs, args.spacing)), flush=True)
        print()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
