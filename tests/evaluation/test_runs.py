"""Runs and sweeps as a user types them: job folders, manifests, the sweep's table, resuming."""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from dvpmvs.run import MANIFEST_NAME
from dvpmvs.sweep import JobRow, render_markdown, render_seeds_csv, write_tables


def dvpmvs(*args, cwd, **kwargs):
    return subprocess.run([sys.executable, "-m", "dvpmvs.cli", *args], capture_output=True, text=True, cwd=cwd,
                          **kwargs)


@pytest.fixture(scope="module")
def embedded(tmp_path_factory):
    """The embedded demo scene (5 views of 320x240, ground truth regenerated)."""
    from dvpmvs.evaluation.embedded import materialise

    return materialise(tmp_path_factory.mktemp("embedded") / "room")


def _snapshot(folder: Path) -> dict:
    return {p: p.stat().st_mtime_ns for p in sorted(folder.rglob("*")) if p.is_file()}


def _manifests(sweep: Path) -> list[dict]:
    return [json.loads(p.read_text()) for p in sorted(sweep.glob(f"*/{MANIFEST_NAME}"))]


def _sweep_folder(cwd: Path) -> Path:
    (folder,) = (cwd / "multirun").glob("dense-*")
    return folder


@pytest.mark.slow
def test_a_sweep_writes_one_folder_per_job_and_one_table(embedded, tmp_path):
    before = _snapshot(embedded)
    result = dvpmvs("dense", "-m", f"workspace={embedded}", "max_image_size=160", "method=default,baseline,w_o_agn",
                    cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    sweep = _sweep_folder(tmp_path)
    # The workspace was only read: its own stereo/ (and everything else) is as it was.
    assert _snapshot(embedded) == before
    manifests = _manifests(sweep)
    assert [m["sweep"]["job"] for m in manifests] == [0, 1, 2]
    clouds = {(sweep / str(m["sweep"]["job"]) / "fused.ply").read_bytes() for m in manifests}
    assert len(clouds) == 3
    for m in manifests:
        assert m["status"] == "ok" and m["config"]["max_image_size"] == 160
        assert m["environment"]["libraries"]["pycolmap"] and len(m["code"]["sources"]) == 64
        assert set(m["dense"]["passes"]) == {"photometric", "geometric"}
        assert m["dense"]["passes"]["photometric"]["computed"] == 5
    assert [m["config"]["patch_match"]["deformable"] for m in manifests] == [True, False, True]
    # One table, a row per job, named by the override that differs, each with its own scores.
    table = (sweep / "table.md").read_text()
    for method in ("default", "baseline", "w_o_agn"):
        assert f"| method={method} | ok |" in table
    f1 = [m["evaluation"]["eth3d"]["f1"][0] for m in manifests]
    assert len(set(f1)) == 3 and all(0.3 < f for f in f1)
    assert f"{100 * f1[1]:.2f}" in table
    assert "| method | default | baseline | w_o_agn |" in table  # one parameter swept: Table V's layout
    rows = (sweep / "table.csv").read_text().splitlines()
    assert len(rows) == 4 and rows[0].startswith("job,folder,status,workspace,max_image_size,method,F1 2cm")
    assert "sweep:" in result.stderr and "table.md" in result.stderr
    # The same command again finds the same folders and recomputes nothing.
    again = dvpmvs("dense", "-m", f"workspace={embedded}", "max_image_size=160", "method=default,baseline,w_o_agn",
                   cwd=tmp_path)
    assert again.returncode == 0, again.stderr
    for m in _manifests(sweep):
        assert all(p["computed"] == 0 for p in m["dense"]["passes"].values()) and m["dense"]["fusion"]["reused"]
    assert [m["evaluation"]["eth3d"]["f1"][0] for m in _manifests(sweep)] == f1
    assert [m["dense"]["seconds_per_view"] for m in _manifests(sweep)] == [m["dense"]["seconds_per_view"]
                                                                           for m in manifests]


@pytest.mark.slow
def test_a_killed_sweep_resumes_without_recomputing_finished_views(embedded, tmp_path):
    args = ["dense", "-m", f"workspace={embedded}", "max_image_size=200", "method=default,baseline"]
    process = subprocess.Popen([sys.executable, "-m", "dvpmvs.cli", *args], cwd=tmp_path, start_new_session=True,
                               stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    # Kill the sweep (the whole process group, as kill -9 would) once the second job has
    # finished at least one view and before it has finished them all.
    finished = []
    deadline = time.monotonic() + 300
    while time.monotonic() < deadline and process.poll() is None:
        records = list(tmp_path.glob("multirun/dense-*/1/stereo/provenance/*.photometric.json"))
        finished = [p.name for p in records if '"state": "complete"' in p.read_text()]
        if finished:
            os.killpg(process.pid, signal.SIGKILL)
            break
        time.sleep(0.02)
    process.wait()
    assert 1 <= len(finished) < 5, finished
    sweep = _sweep_folder(tmp_path)
    assert not (sweep / "1" / MANIFEST_NAME).exists()
    result = dvpmvs(*args, cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    first, second = _manifests(sweep)
    # The finished job recomputes nothing; the killed one only what it had not finished.
    assert all(p["computed"] == 0 for p in first["dense"]["passes"].values())
    photometric = second["dense"]["passes"]["photometric"]
    reused = {r["name"] for r in photometric["view_reports"] if r["action"] == "reused"}
    assert {name.removesuffix(".photometric.json") for name in finished} <= reused
    assert photometric["computed"] == 5 - len(reused) and second["status"] == "ok"
    assert "| method=baseline | ok |" in (sweep / "table.md").read_text()


@pytest.mark.slow
def test_joblib_runs_jobs_side_by_side_with_their_threads_split(embedded, tmp_path):
    pytest.importorskip("hydra_plugins.hydra_joblib_launcher")
    result = dvpmvs("dense", "-m", f"workspace={embedded}", "max_image_size=120", "method=default,baseline",
                    "hydra/launcher=joblib", "hydra.launcher.n_jobs=2", cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    manifests = _manifests(_sweep_folder(tmp_path))
    assert [m["threads"] for m in manifests] == [max(1, os.cpu_count() // 2)] * 2
    assert all(m["status"] == "ok" for m in manifests)
    # The same maps as one job at a time with every core: threads change no map.
    single = dvpmvs("dense", f"workspace={embedded}", "max_image_size=120", f"out={tmp_path / 'single'}",
                    f"report={tmp_path / 'single.json'}", cwd=tmp_path)
    assert single.returncode == 0, single.stderr
    alone = json.loads((tmp_path / "single.json").read_text())
    assert alone["evaluation"]["eth3d"] == {**manifests[0]["evaluation"]["eth3d"],
                                            "reconstruction": alone["evaluation"]["eth3d"]["reconstruction"],
                                            "seconds": alone["evaluation"]["eth3d"]["seconds"]}


def test_a_failed_job_is_in_the_table_and_the_exit_status(tmp_path):
    result = dvpmvs("dense", "-m", f"workspace={tmp_path / 'nowhere'}", "method=default,baseline", cwd=tmp_path)
    assert result.returncode == 1
    assert "workspace folder not found" in result.stderr and "Traceback" not in result.stderr


def test_sweep_folders_follow_the_command_not_the_clock():
    from dvpmvs.cli import _sweep_dir_override

    one = _sweep_dir_override("dense", ["-m", "workspace=ws", "method=paper,w_o_agn"])
    assert one == _sweep_dir_override("dense", ["-m", "workspace=ws", "method=paper,w_o_agn", "num_threads=1",
                                                "hydra/launcher=joblib"])
    assert one != _sweep_dir_override("dense", ["-m", "workspace=ws", "method=paper,w_o_mon"])
    assert _sweep_dir_override("dense", ["-m", "hydra.sweep.dir=mine", "method=paper"]) == []


def _row(num, overrides, f1, seconds=10.0, status="ok"):
    metrics = {"F1 2cm": f1, "Comp. 2cm": f1 - 5, "Acc. 2cm": f1 + 5, "s/view": seconds}
    return JobRow(num, Path(str(num)), overrides, status, metrics, [0.02])


def test_tables_in_the_layouts_of_the_papers_tables_iv_and_v():
    rows = [_row(0, {"scene": "room", "method": "paper"}, 70.0), _row(1, {"scene": "facade", "method": "paper"}, 80.0),
            _row(2, {"scene": "room", "method": "w_o_agn"}, 60.0),
            _row(3, {"scene": "facade", "method": "w_o_agn"}, 0.0, status="error")]
    table = render_markdown(rows)
    # Table IV: a row per configuration, the mean over the scenes that ran, columns F1 / Comp. / Acc.
    assert "| method | scenes | F1 2cm | Comp. 2cm | Acc. 2cm | s/view |" in table
    assert "| method=paper | 2/2 | 75.00 | 70.00 | 80.00 | 10.0 |" in table
    assert "| method=w_o_agn | 1/2 | 60.00 |" in table
    assert "| 3 | scene=facade method=w_o_agn | **error** |" in table and "Failed jobs" in table
    # Table V: one parameter's values as columns.
    eta = [_row(i, {"segmentation.min_region": str(v)}, 60.0 + i) for i, v in enumerate((100, 200, 500))]
    assert "| segmentation.min_region | 100 | 200 | 500 |\n|---|---|---|---|\n| F1 2cm | 60.00 | 61.00 | 62.00 |" \
        in render_markdown(eta)


def test_a_sweep_over_the_estimators_seed_folds_it_into_a_mean_and_a_spread(tmp_path):
    # Two configurations on two scenes, seeds 0-2; one job failed.
    rows, num = [], 0
    for method in ("default", "fast"):
        for scene in ("room", "facade"):
            for seed in "012":
                rows.append(_row(num, {"scene": scene, "method": method, "seed": seed}, 60.0 + num,
                                 status="error" if num == 7 else "ok"))
                num += 1
    table = render_markdown(rows)
    # One row per configuration and scene: the mean over the seeds that ran and their min-max.
    assert "| scene method | seeds | F1 2cm | Comp. 2cm | Acc. 2cm | s/view |" in table
    assert "| scene=room method=default | 3/3 | 61.00 (60.00-62.00) | 56.00 | 66.00 | 10.0 |" in table
    assert "| scene=room method=fast | 2/3 | 67.00 (66.00-68.00) |" in table
    # Over the scenes: the spread of the seeds' scene means (seed 1 of fast lost a scene: left out).
    assert "| method=default | 6/6 | 62.50 (61.50-63.50) |" in table
    assert "| method=fast | 5/6 | 68.80 (67.50-69.50) |" in table
    assert "| method | default | fast |" in table and "(mean over scene, seed)" in table
    assert "| 7 | scene=room method=fast seed=1 | **error** |" in table  # the jobs stay listed
    lines = render_seeds_csv(rows).splitlines()
    assert lines[0].startswith("scene,method,seeds,F1 2cm,F1 2cm min,F1 2cm max,Comp. 2cm") and lines[0].endswith(",scene digest")
    assert lines[3] == "room,fast,2/3,67,66,68,62,61,63,72,71,73,10,10,10,"
    write_tables(tmp_path, rows)
    assert (tmp_path / "table.csv").read_text().splitlines() == lines
    assert len((tmp_path / "jobs.csv").read_text().splitlines()) == 13
    # Without a seed sweep, nothing is folded and table.csv lists the jobs.
    (tmp_path / "plain").mkdir()
    write_tables(tmp_path / "plain", [rows[0], rows[3]])  # seed 0 on both scenes
    assert not (tmp_path / "plain" / "jobs.csv").exists()
    assert (tmp_path / "plain" / "table.csv").read_text().startswith("job,folder,status,scene,method,seed,F1 2cm")
