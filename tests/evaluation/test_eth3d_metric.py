"""The ETH3D metric on analytic cases, and its beam kernel against a brute-force reference."""

import numpy as np
import pytest

from dvpmvs.errors import DvpmvsError
from dvpmvs.evaluation.eth3d_metric import (
    ACCURATE,
    INACCURATE,
    UNOBSERVED,
    ETH3DParameters,
    accuracy,
    evaluate_eth3d,
)
from dvpmvs.evaluation.pointclouds import (
    GroundTruthError,
    Scan,
    read_meshlab_project,
    read_points,
    write_meshlab_project,
    write_point_cloud,
)

# Also run on the other Pythons `make test` checks (scripts/other_pythons.py).
pytestmark = pytest.mark.smoke

# A scanner at the origin of its frame looks along +x at a 2 m x 2 m wall 5 m away, sampled every
# 5 mm (an angular pitch of 1 mrad); beams of 0.75 mrad half-angle overlap, as a real scan's do.
WALL_PARAMS = ETH3DParameters(
    beam_start_radius_meters=0.0, beam_divergence_halfangle_deg=np.rad2deg(7.5e-4)
)


def wall(distance=5.0, half=1.0, step=0.005):
    g = np.arange(-half, half + step / 2, step)
    y, z = np.meshgrid(g, g)
    return np.stack([np.full(y.size, distance), y.ravel(), z.ravel()], 1).astype(np.float32)


def scan_of(points, global_T_scan=None):
    pose = np.eye(4) if global_T_scan is None else np.asarray(global_T_scan, float)
    return [Scan("wall", None, pose, points)]


def test_a_copy_shifted_by_1_5_cm_is_perfect_at_2_cm_and_fails_at_1_cm():
    gt = wall()
    for sign in (+1, -1):  # behind and in front of the wall
        rec = gt + np.float32([sign * 0.015, 0, 0])
        for ground_truth in (scan_of(gt), gt):  # MeshLab scans and a plain point cloud
            res = evaluate_eth3d(rec, ground_truth, [0.01, 0.02], WALL_PARAMS)
            assert res.tolerances == [0.01, 0.02]
            assert res.accuracy == pytest.approx([0.0, 1.0])
            assert res.completeness == pytest.approx([0.0, 1.0])
            assert res.f1 == pytest.approx([0.0, 1.0])


def test_in_plane_shift_within_the_beams_is_accurate():
    # Shifting along the wall by half the sample spacing keeps every point on a beam.
    gt = wall()
    rec = gt + np.float32([0, 0.0025, 0.0])
    res = evaluate_eth3d(rec, scan_of(gt), [0.005, 0.02], WALL_PARAMS)
    assert res.accuracy == pytest.approx([1.0, 1.0])
    assert res.completeness == pytest.approx([1.0, 1.0])


def test_points_behind_the_scanned_surface_are_unobserved_and_do_not_cost_accuracy():
    gt = wall()
    rng = np.random.default_rng(0)
    central = gt[
        (np.abs(gt[:, 1]) < 0.8) & (np.abs(gt[:, 2]) < 0.8)
    ]  # in front, still inside the beams
    behind = central[rng.choice(len(central), 20000)] + np.float32(
        [0.5, 0, 0]
    )  # 50 cm behind the wall
    base = evaluate_eth3d(gt, scan_of(gt), [0.02, 0.1], WALL_PARAMS)
    more = evaluate_eth3d(
        np.concatenate([gt, behind]), scan_of(gt), [0.02, 0.1], WALL_PARAMS, keep_point_results=True
    )
    assert base.accuracy == pytest.approx([1.0, 1.0])
    assert more.accuracy == pytest.approx([1.0, 1.0])
    assert np.all(more.point_accuracy[:, len(gt) :] == UNOBSERVED)
    # The same points in front of the wall lie in space the laser passed through: inaccurate.
    front = evaluate_eth3d(
        np.concatenate([gt, behind - np.float32([1.0, 0, 0])]),
        scan_of(gt),
        [0.02, 0.1],
        WALL_PARAMS,
        keep_point_results=True,
    )
    assert np.all(front.point_accuracy[:, len(gt) :] == INACCURATE)
    assert front.accuracy[0] < 0.9
    # A plain point cloud has no beams: everything is observed and the behind points count.
    plain = evaluate_eth3d(np.concatenate([gt, behind]), gt, [0.02, 0.1])
    assert plain.accuracy[0] < 0.9


def test_voxel_normalisation_makes_a_locally_duplicated_cloud_score_the_same():
    gt = wall()
    rng = np.random.default_rng(1)
    rec = gt + rng.normal(0, 0.008, gt.shape).astype(np.float32)
    # A 4 cm gap around y = -0.5 and z = -0.5 so that no voxel holds points from both sides.
    gap = (np.abs(rec[:, 1] + 0.5) < 0.02) | (np.abs(rec[:, 2] + 0.5) < 0.02)
    rec = rec[~gap]
    # Ten copies of the points in one corner of the wall: many more points, same voxels.
    corner = rec[(rec[:, 1] < -0.5) & (rec[:, 2] < -0.5)]
    duplicated = np.concatenate([rec] + [corner] * 10)
    a = evaluate_eth3d(rec, scan_of(gt), [0.01, 0.02], WALL_PARAMS)
    b = evaluate_eth3d(duplicated, scan_of(gt), [0.01, 0.02], WALL_PARAMS)
    assert 0.3 < a.accuracy[0] < 0.95  # a non-trivial score, so the comparison means something
    assert b.accuracy == pytest.approx(a.accuracy, abs=1e-6)
    assert b.completeness == pytest.approx(a.completeness, abs=1e-6)


def test_scan_poses_are_applied():
    # The same wall scanned from a scanner that sits elsewhere and is rotated.
    gt = wall()
    angle = np.deg2rad(30)
    T = np.eye(4)
    T[:3, :3] = [[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]]
    T[:3, 3] = [1.0, -2.0, 0.5]
    global_points = (gt @ T[:3, :3].T + T[:3, 3]).astype(np.float32)
    res = evaluate_eth3d(global_points, scan_of(gt, T), [0.01], WALL_PARAMS)
    assert res.accuracy == pytest.approx([1.0]) and res.completeness == pytest.approx([1.0])
    normal = (T[:3, :3] @ [1.0, 0.0, 0.0]).astype(np.float32)
    off = evaluate_eth3d(global_points + 0.05 * normal, scan_of(gt, T), [0.01], WALL_PARAMS)
    assert off.completeness[0] < 0.1


def brute_force_labels(rec, scans, tolerances, params):
    """The beam model written directly from its definition, over every scan point."""
    tan_div = np.tan(np.deg2rad(params.beam_divergence_halfangle_deg))
    labels = np.full((len(tolerances), len(rec)), UNOBSERVED)
    for i, p in enumerate(rec.astype(np.float64)):
        first, flagged = len(tolerances), False
        for scan in scans:
            inv = np.linalg.inv(scan.global_T_scan)
            q = inv[:3, :3] @ p + inv[:3, 3]
            pts = scan.points.astype(np.float64)
            r = np.linalg.norm(pts, axis=1)
            d = pts / r[:, None]
            along = d @ q
            off_ray = np.linalg.norm(q - along[:, None] * d, axis=1)
            beam = params.beam_start_radius_meters + np.linalg.norm(q) * tan_div
            inside = (along >= 0) & (off_ray <= beam)
            if not inside.any():
                continue
            dist = np.linalg.norm(pts[inside] - q, axis=1).min()
            for ti, tol in enumerate(tolerances):
                if dist <= tol:
                    first = min(first, ti)
                    break
            flagged |= bool(np.any(along[inside] < r[inside]))
        for ti in range(len(tolerances)):
            labels[ti, i] = ACCURATE if ti >= first else (INACCURATE if flagged else UNOBSERVED)
    return labels


def test_beam_kernel_matches_a_brute_force_reference():
    rng = np.random.default_rng(2)
    # Two scanners seeing a bumpy surface; reconstruction points scattered around it.
    g = np.linspace(-1, 1, 60)
    y, z = np.meshgrid(g, g)
    surface = np.stack([3 + 0.1 * np.sin(3 * y.ravel()), y.ravel(), z.ravel()], 1).astype(
        np.float32
    )
    T2 = np.eye(4)
    T2[:3, 3] = [0.0, 0.5, 0.0]
    scans = [
        Scan("a", None, np.eye(4), surface),
        Scan("b", None, T2, (surface - np.float32([0, 0.5, 0]))),
    ]
    rec = (surface[rng.choice(len(surface), 400)] + rng.normal(0, 0.05, (400, 3))).astype(
        np.float32
    )
    params = ETH3DParameters(beam_start_radius_meters=0.002, beam_divergence_halfangle_deg=0.4)
    tolerances = [0.01, 0.03, 0.1]
    _, labels = accuracy(rec, scans, tolerances, params)
    expected = brute_force_labels(rec, scans, tolerances, params)
    assert {ACCURATE, INACCURATE, UNOBSERVED} <= set(np.unique(expected))
    # Float32 (kernel) against float64 (reference): at most a point on a boundary may differ.
    assert np.mean(labels != expected) < 0.005


def test_meshlab_project_round_trip_and_errors(tmp_path):
    gt = wall(half=0.2)
    T = np.eye(4)
    T[:3, 3] = [1, 2, 3]
    write_point_cloud(tmp_path / "scans" / "a.ply", gt)
    write_meshlab_project(tmp_path / "gt.mlp", [("scans/a.ply", T)])
    scans = read_meshlab_project(tmp_path / "gt.mlp")
    assert len(scans) == 1 and np.allclose(scans[0].global_T_scan, T)
    assert np.array_equal(scans[0].points, gt)
    assert np.allclose(scans[0].global_points(), gt + np.float32([1, 2, 3]))
    assert (
        b"property float x" in (tmp_path / "scans" / "a.ply").read_bytes()[:300]
    )  # the official reader's type

    (tmp_path / "bad.mlp").write_text(
        "<MeshLabProject><MeshGroup><MLMesh filename='x.ply'>"
        "<MLMatrix44>1 0 0</MLMatrix44></MLMesh></MeshGroup></MeshLabProject>"
    )
    with pytest.raises(GroundTruthError, match="16 numbers"):
        read_meshlab_project(tmp_path / "bad.mlp")
    with pytest.raises(GroundTruthError, match="does not exist"):
        read_points(tmp_path / "missing.ply")
    (tmp_path / "corrupt.ply").write_bytes(
        b"ply\nformat binary_little_endian 1.0\nelement vertex 10\n"
    )
    with pytest.raises(
        GroundTruthError, match="a PLY header without end_header; the file is truncated"
    ):
        read_points(tmp_path / "corrupt.ply")
    with pytest.raises(DvpmvsError, match="tolerances"):
        evaluate_eth3d(gt, gt, [])


def test_an_empty_reconstruction_scores_zero():
    gt = wall(half=0.2)
    res = evaluate_eth3d(np.zeros((0, 3), np.float32), scan_of(gt), [0.02], WALL_PARAMS)
    assert res.accuracy == [0.0] and res.completeness == [0.0] and res.f1 == [0.0]


def test_one_evaluation_at_several_tolerances_gives_each_its_own_figures():
    # ETH3DResult.at: the demo and bench score once at the union of the table's and the curve's
    # tolerances; each tolerance must get what it gets alone, labels included.
    gt = wall()
    rng = np.random.default_rng(1)
    rec = gt + rng.normal(0, 0.01, gt.shape).astype(np.float32)
    union = evaluate_eth3d(
        rec, scan_of(gt), [0.005, 0.01, 0.02, 0.05, 0.1], WALL_PARAMS, keep_point_results=True
    )
    for asked in ([0.02, 0.1], [0.005]):
        alone = evaluate_eth3d(rec, scan_of(gt), asked, WALL_PARAMS, keep_point_results=True)
        picked = union.at(asked)
        assert picked.tolerances == asked
        assert picked.accuracy == alone.accuracy and picked.completeness == alone.completeness
        assert picked.f1 == alone.f1
        assert np.array_equal(picked.point_accuracy, alone.point_accuracy)
        assert np.array_equal(picked.point_completeness, alone.point_completeness)
    assert (
        0.81 < union.f1[1] < 0.91 < union.f1[2] < 0.99
    )  # 0.86 and 0.98: the noise makes them differ
    with pytest.raises(ValueError):
        union.at([0.03])
