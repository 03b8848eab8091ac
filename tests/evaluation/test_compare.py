"""dvpmvs compare: two builds timed interleaved on the same views, their maps compared."""

import json
import subprocess
import sys

import pytest


@pytest.mark.slow
def test_compare_times_two_builds_and_finds_the_vector_and_scalar_maps_equal(tmp_path):
    # The same build twice, once forced to its scalar loops: the maps must agree byte for byte,
    # and the report carries both builds' seconds per view, their ratio and the kernel shares.
    result = subprocess.run(
        [
            sys.executable,
            "-m",
            "dvpmvs.cli",
            "compare",
            "current@DVPMVS_SIMD=scalar",
            "current",
            "--scenes",
            "room",
            "--width",
            "160",
            "--views",
            "4",
            "--threads",
            "2",
            "--scenes-dir",
            str(tmp_path / "scenes"),
            "--out",
            str(tmp_path / "out"),
            "--",
            "patch_match.num_scales=1",
        ],
        capture_output=True,
        text=True,
        cwd=tmp_path,
    )
    assert result.returncode == 0, result.stdout + result.stderr
    report = (tmp_path / "out" / "report.md").read_text()
    row = next(line for line in report.splitlines() if line.startswith("| room |"))
    cells = [cell.strip() for cell in row.strip("|").split("|")]
    a, b, ratio = float(cells[1]), float(cells[2]), float(cells[3])
    # the ratio of the unrounded seconds: within the rounding of the two printed to 0.01 s
    assert a > 0 and b > 0 and abs(ratio / (a / b) - 1) < 0.01
    assert cells[-1] == "yes"
    assert "photometric/sweep" in report and "geometric/sweep" in report
    # The work per pixel, per build: both paths score the same hypotheses (the vector path's
    # early stop may give a hypothesis up after other windows than the scalar one).
    tables = report.split("estimator matched per pixel")[1:3]
    work = [
        [line.split("|")[1:-1] for line in table.splitlines() if line.startswith("| photometric |")]
        for table in tables
    ]
    assert len(work[0]) == len(work[1]) == 1
    assert work[0][0][3] == work[1][0][3] and 20 < float(work[0][0][3]) < 80, work
    assert (
        20 * float(work[0][0][4])
        < float(work[0][0][5].replace(",", ""))
        < 40 * float(work[0][0][4])
    ), work
    # The CPU time per sample: the sweeps are part of both passes, and the scalar loops cost more
    # per sample than the vector path.
    costs = [
        line for line in report.splitlines() if line.startswith("CPU time per sample matched:")
    ]
    per_sample = [
        [float(word) for word in line.replace(",", "").split() if word.replace(".", "").isdigit()][
            :2
        ]
        for line in costs
    ]
    assert len(per_sample) == 2 and all(0 < sweeps < passes for passes, sweeps in per_sample), costs
    assert per_sample[0][1] > per_sample[1][1], costs
    data = json.loads((tmp_path / "out" / "report.json").read_text())
    assert data["same_maps"] == {"room": True}
    runs = data["results"]["room/0"] + data["results"]["room/1"]
    assert {run["simd"] for run in runs} >= {"scalar"}
    assert all(run["peak_rss_mb"] > 50 for run in runs)


def test_compare_refuses_what_is_neither_an_interpreter_nor_a_commit(tmp_path):
    result = subprocess.run(
        [
            sys.executable,
            "-m",
            "dvpmvs.cli",
            "compare",
            "no-such-commit-xyz",
            "current",
            "--out",
            str(tmp_path / "out"),
        ],
        capture_output=True,
        text=True,
        cwd=tmp_path,
    )
    assert result.returncode != 0
    assert (
        "no-such-commit-xyz" in result.stderr
        and "neither an interpreter nor a commit" in result.stderr
    )
