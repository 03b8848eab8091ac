"""Runs and sweeps as a user types them (``dvpmvs.run``): job folders, manifests, the sweep's table,
resuming, jobs side by side."""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from dvpmvs.run import MANIFEST_NAME
from tests.helpers import dvpmvs


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
    result = dvpmvs(
        "dense",
        "-m",
        f"workspace={embedded}",
        "max_image_size=120",
        "method=default,baseline,w_o_agn",
        cwd=tmp_path,
    )
    assert result.returncode == 0, result.stderr
    sweep = _sweep_folder(tmp_path)
    # The workspace was only read: its own stereo/ (and everything else) is as it was.
    assert _snapshot(embedded) == before
    manifests = _manifests(sweep)
    assert [m["sweep"]["job"] for m in manifests] == [0, 1, 2]
    clouds = {(sweep / str(m["sweep"]["job"]) / "fused.ply").read_bytes() for m in manifests}
    assert len(clouds) == 3
    for m in manifests:
        assert m["status"] == "ok" and m["config"]["max_image_size"] == 120
        assert m["environment"]["libraries"]["pycolmap"] and len(m["code"]["sources"]) == 64
        assert set(m["dense"]["passes"]) == {"photometric", "geometric"}
        assert m["dense"]["passes"]["photometric"]["computed"] == 5
    assert [m["config"]["patch_match"]["deformable"] for m in manifests] == [True, False, True]
    # One table, a row per job, named by the override that differs, each with its own scores.
    table = (sweep / "table.md").read_text()
    for method in ("default", "baseline", "w_o_agn"):
        assert f"| method={method} | ok |" in table
    f1 = [m["evaluation"]["eth3d"]["f1"][0] for m in manifests]
    assert len(set(f1)) == 3 and all(0.2 < f for f in f1)  # 0.23-0.27 at 120 px
    assert f"{100 * f1[1]:.2f}" in table
    assert (
        "| method | default | baseline | w_o_agn |" in table
    )  # one parameter swept: Table V's layout
    rows = (sweep / "table.csv").read_text().splitlines()
    assert len(rows) == 4 and rows[0].startswith(
        "job,folder,status,workspace,max_image_size,method,F1 2cm"
    )
    assert "sweep:" in result.stderr and "table.md" in result.stderr
    # The same command again finds the same folders and recomputes nothing.
    again = dvpmvs(
        "dense",
        "-m",
        f"workspace={embedded}",
        "max_image_size=120",
        "method=default,baseline,w_o_agn",
        cwd=tmp_path,
    )
    assert again.returncode == 0, again.stderr
    for m in _manifests(sweep):
        assert (
            all(p["computed"] == 0 for p in m["dense"]["passes"].values())
            and m["dense"]["fusion"]["reused"]
        )
    assert [m["evaluation"]["eth3d"]["f1"][0] for m in _manifests(sweep)] == f1
    assert [m["dense"]["seconds_per_view"] for m in _manifests(sweep)] == [
        m["dense"]["seconds_per_view"] for m in manifests
    ]


@pytest.mark.slow
def test_a_killed_sweep_resumes_without_recomputing_finished_views(embedded, tmp_path):
    args = ["dense", "-m", f"workspace={embedded}", "max_image_size=128", "method=default,baseline"]
    process = subprocess.Popen(
        [sys.executable, "-m", "dvpmvs.cli", *args],
        cwd=tmp_path,
        start_new_session=True,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
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
    result = dvpmvs(
        "dense",
        "-m",
        f"workspace={embedded}",
        "max_image_size=96",
        "method=default,baseline",
        "hydra/launcher=joblib",
        "hydra.launcher.n_jobs=2",
        cwd=tmp_path,
    )
    assert result.returncode == 0, result.stderr
    manifests = _manifests(_sweep_folder(tmp_path))
    assert [m["threads"] for m in manifests] == [max(1, os.cpu_count() // 2)] * 2
    assert all(m["status"] == "ok" for m in manifests)
    # The same maps as one job at a time with every core: threads change no map.
    single = dvpmvs(
        "dense",
        f"workspace={embedded}",
        "max_image_size=96",
        f"out={tmp_path / 'single'}",
        f"report={tmp_path / 'single.json'}",
        cwd=tmp_path,
    )
    assert single.returncode == 0, single.stderr
    alone = json.loads((tmp_path / "single.json").read_text())
    assert alone["evaluation"]["eth3d"] == {
        **manifests[0]["evaluation"]["eth3d"],
        "reconstruction": alone["evaluation"]["eth3d"]["reconstruction"],
        "seconds": alone["evaluation"]["eth3d"]["seconds"],
    }


def test_a_failed_job_is_in_the_table_and_the_exit_status(tmp_path):
    result = dvpmvs(
        "dense", "-m", f"workspace={tmp_path / 'nowhere'}", "method=default,baseline", cwd=tmp_path
    )
    assert result.returncode == 1
    assert "workspace folder not found" in result.stderr and "Traceback" not in result.stderr


def test_sweep_folders_follow_the_command_not_the_clock():
    from dvpmvs.cli import _sweep_dir_override

    one = _sweep_dir_override("dense", ["-m", "workspace=ws", "method=paper,w_o_agn"])
    assert one == _sweep_dir_override(
        "dense",
        ["-m", "workspace=ws", "method=paper,w_o_agn", "num_threads=1", "hydra/launcher=joblib"],
    )
    assert one != _sweep_dir_override("dense", ["-m", "workspace=ws", "method=paper,w_o_mon"])
    assert _sweep_dir_override("dense", ["-m", "hydra.sweep.dir=mine", "method=paper"]) == []


# ``dvpmvs`` with the harness (``dvpmvs.evaluation``) absent: every import of it fails, as where
# only the product is installed.
_WITHOUT_HARNESS = """
import importlib.abc
import sys


class NoHarness(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path, target=None):
        if name.split(".")[:2] == ["dvpmvs", "evaluation"]:
            raise ImportError(f"no module named {name!r} (the harness is not installed)")


sys.meta_path.insert(0, NoHarness())
from dvpmvs.cli import main

sys.exit(main(sys.argv[1:]))
"""


@pytest.mark.slow
def test_dense_runs_sweeps_and_reports_without_the_harness(embedded, tmp_path):
    quick = ["quality=fast", "max_image_size=64", "patch_match.num_scales=1", "progress=false"]

    def without_harness(*args):
        return subprocess.run(
            [sys.executable, "-c", _WITHOUT_HARNESS, *args],
            capture_output=True,
            text=True,
            cwd=tmp_path,
        )

    run = without_harness("dense", f"workspace={embedded}", "out=run", *quick)
    assert run.returncode == 0, run.stderr
    # The scoring hook is named as left out; maps, cloud, manifest and report are written.
    said = run.stdout + run.stderr  # the log (Hydra's job logging) goes to stdout
    assert "scoring hook 'ground_truth'" in said and "is left out" in said
    manifest = json.loads((tmp_path / "run" / MANIFEST_NAME).read_text())
    assert manifest["status"] == "ok" and not manifest.get("evaluation")
    assert "evaluate" not in manifest["config"]
    assert (tmp_path / "run" / "fused.ply").stat().st_size > 10_000
    assert (tmp_path / "run" / "report.html").is_file()
    # A sweep's table: the run's own columns, without the scores.
    sweep = without_harness("dense", "-m", f"workspace={embedded}", *quick, "seed=0,1")
    assert sweep.returncode == 0, sweep.stderr
    table = (_sweep_folder(tmp_path) / "table.md").read_text()
    assert "seeds (0, 1); means:" in table and "F1" not in table
    assert "| configuration | seeds | s/view | points | peak MB |" in table
    # The harness's options are the harness's: without it they are unknown keys.
    scored = without_harness("dense", f"workspace={embedded}", "evaluate.ground_truth=none")
    assert scored.returncode != 0 and "evaluate.ground_truth" in scored.stderr


def test_a_json_report_dvpmvs_did_not_write_is_not_replaced(embedded, tmp_path):
    mine = tmp_path / "mine.json"
    mine.write_text('{"my": "notes"}')
    args = ("dense", f"workspace={embedded}", f"out={tmp_path / 'out'}", f"report={mine}")
    result = dvpmvs(*args, cwd=tmp_path)
    assert result.returncode == 1 and "dvpmvs did not write it" in " ".join(result.stderr.split())
    assert json.loads(mine.read_text()) == {"my": "notes"}
    assert not (tmp_path / "out" / "stereo").exists()  # refused before anything was computed
