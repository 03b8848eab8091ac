"""Meshing a fused cloud: Open3D's and COLMAP's Poisson on a sampled sphere, trimming, reuse,
reproducible bytes, and the errors of the Delaunay mesher's requirements."""

import hashlib
import logging
import shutil
import subprocess
import time

import numpy as np
import open3d as o3d
import pytest

from dvpmvs.cli import main
from dvpmvs.meshing import (
    MeshingError,
    MeshingOptions,
    default_mesh_path,
    mesh_cloud,
    mesh_record_path,
)
from dvpmvs.pointcloud import write_point_cloud
from dvpmvs.stage_progress import StepProgress


@pytest.fixture
def sphere_cloud(tmp_path):
    """20,000 points on the unit sphere around (1, 2, 3), with outward normals and grey colour."""
    rng = np.random.default_rng(0)
    normals = rng.normal(size=(20_000, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    path = tmp_path / "fused.ply"
    write_point_cloud(
        path, normals + [1.0, 2.0, 3.0], np.full((len(normals), 3), 128, np.uint8), normals
    )
    return path


def _radii(mesh_path):
    mesh = o3d.io.read_triangle_mesh(str(mesh_path))
    return np.linalg.norm(np.asarray(mesh.vertices) - [1.0, 2.0, 3.0], axis=1), len(mesh.triangles)


@pytest.mark.parametrize("method", ["poisson", "colmap_poisson"])
def test_poisson_meshes_lie_on_the_sampled_surface(sphere_cloud, tmp_path, method):
    output = tmp_path / f"{method}.ply"
    report = mesh_cloud(sphere_cloud, output, MeshingOptions(method=method, depth=8, colmap_trim=0))
    radii, triangles = _radii(output)
    assert report.triangles == triangles > 100_000 and report.vertices == len(
        radii
    )  # 114,928 and 127,222
    assert (
        np.abs(radii - 1).mean() < 0.001 and np.abs(radii - 1).max() < 0.01
    )  # 0.0002 and 0.002-0.005


@pytest.mark.slow
def test_trimming_removes_the_stated_share_and_a_rerun_reuses_the_mesh(sphere_cloud, tmp_path):
    full = mesh_cloud(sphere_cloud, tmp_path / "full.ply", MeshingOptions(depth=8, trim_quantile=0))
    trimmed = mesh_cloud(
        sphere_cloud, tmp_path / "trimmed.ply", MeshingOptions(depth=8, trim_quantile=0.2)
    )
    assert 0.78 < trimmed.vertices / full.vertices < 0.82  # 0.7996
    again = mesh_cloud(
        sphere_cloud, tmp_path / "trimmed.ply", MeshingOptions(depth=8, trim_quantile=0.2)
    )
    assert again.reused and again.triangles == trimmed.triangles
    # Another option or another cloud: meshed again.
    assert not mesh_cloud(
        sphere_cloud, tmp_path / "trimmed.ply", MeshingOptions(depth=7, trim_quantile=0.2)
    ).reused
    write_point_cloud(sphere_cloud, o3d.io.read_point_cloud(str(sphere_cloud)).points)
    assert not mesh_cloud(
        sphere_cloud, tmp_path / "trimmed.ply", MeshingOptions(depth=7, trim_quantile=0.2)
    ).reused


def test_one_thread_gives_the_same_bytes(sphere_cloud, tmp_path):
    digests = []
    for name in ("a.ply", "b.ply"):
        mesh_cloud(sphere_cloud, tmp_path / name, MeshingOptions(depth=8))
        digests.append(hashlib.sha256((tmp_path / name).read_bytes()).hexdigest())
    assert digests[0] == digests[1]


def test_the_meshing_step_keeps_saying_it_runs_while_open3d_meshes(
    sphere_cloud, tmp_path, monkeypatch, caplog
):
    # Open3D holds the GIL while it meshes; in this process no heartbeat could be said then.
    monkeypatch.setattr("dvpmvs.stage_progress.HEARTBEAT_SECONDS", 0.2)
    monkeypatch.setattr("dvpmvs.stage_progress.POLL_SECONDS", 0.02)
    with caplog.at_level(logging.INFO, logger="dvpmvs.stage_progress"):
        start = time.time()  # the log records' clock
        with StepProgress("meshing", ""):
            mesh_cloud(sphere_cloud, tmp_path / "mesh.ply", MeshingOptions(depth=9))
        end = time.time()
    said = [r.created for r in caplog.records if r.getMessage().startswith("meshing: running")]
    gaps = np.diff([start, *said, end]).tolist()
    assert max(gaps) < 1.0, gaps  # 0.2 s apart; 2-5 s of silence with the mesher in-process


def test_the_command_writes_colmaps_name_beside_the_cloud(sphere_cloud, capsys):
    assert main(["mesh", f"workspace={sphere_cloud.parent}", "meshing.depth=7"]) == 0
    output = default_mesh_path(sphere_cloud.parent, "poisson")
    assert (
        output.name == "meshed-poisson.ply"
        and output.is_file()
        and mesh_record_path(output).is_file()
    )
    assert "triangles" in capsys.readouterr().err


def test_bad_inputs_say_what_to_do(sphere_cloud, tmp_path):
    with pytest.raises(MeshingError, match="does not exist; run `dvpmvs dense`"):
        mesh_cloud(tmp_path / "none.ply", tmp_path / "mesh.ply")
    with pytest.raises(MeshingError, match="fused.ply.vis, which is missing"):
        mesh_cloud(
            sphere_cloud,
            tmp_path / "mesh.ply",
            MeshingOptions(method="delaunay"),
            model_dir=tmp_path,
        )
    with pytest.raises(ValueError, match="meshing.method must be one of"):
        MeshingOptions(method="ball_pivoting")
    with pytest.raises(ValueError, match="trim_quantile"):
        MeshingOptions(trim_quantile=1.0)
    (sphere_cloud.parent / "fused.ply.vis").write_bytes(b"\0" * 8)
    with pytest.raises(MeshingError, match="no program 'no-such-colmap'"):
        mesh_cloud(
            sphere_cloud,
            tmp_path / "mesh.ply",
            MeshingOptions(method="delaunay", colmap_binary="no-such-colmap"),
            model_dir=tmp_path,
        )
    assert not mesh_record_path(tmp_path / "mesh.ply").exists()


def test_delaunay_names_a_colmap_without_cgal(sphere_cloud, tmp_path):
    colmap = shutil.which("colmap")
    if colmap is None:
        pytest.skip("COLMAP's command-line program is not installed")
    probe = subprocess.run(
        [
            colmap,
            "delaunay_mesher",
            "--input_path",
            str(tmp_path),
            "--output_path",
            str(tmp_path / "probe.ply"),
        ],
        capture_output=True,
        text=True,
    )
    if "requires CGAL" not in probe.stdout + probe.stderr:
        pytest.skip("this COLMAP has CGAL: its Delaunay mesher runs in tests/dense/test_cloud.py")
    (sphere_cloud.parent / "fused.ply.vis").write_bytes(b"\0" * 8)
    with pytest.raises(MeshingError, match="built without CGAL"):
        mesh_cloud(
            sphere_cloud,
            tmp_path / "mesh.ply",
            MeshingOptions(method="delaunay"),
            model_dir=tmp_path,
        )


def test_surface_samples_cover_the_mesh_at_the_stated_spacing(sphere_cloud, tmp_path):
    from dvpmvs.evaluation.experiments.mesh_quality import surface_samples

    output = tmp_path / "mesh.ply"
    mesh_cloud(sphere_cloud, output, MeshingOptions(depth=8, trim_quantile=0))
    points = surface_samples(output, spacing=0.01)
    assert len(points) == pytest.approx(
        4 * np.pi / 0.01**2, rel=0.01
    )  # the sphere's area / spacing^2
    assert np.abs(np.linalg.norm(points - [1.0, 2.0, 3.0], axis=1) - 1).max() < 0.01
    assert np.array_equal(points, surface_samples(output, spacing=0.01))  # seeded
