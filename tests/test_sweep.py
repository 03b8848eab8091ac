"""A sweep's tables (``dvpmvs.sweep``): Table IV's and Table V's layouts, estimator seeds folded
into a mean and a spread, failed jobs listed."""

from pathlib import Path

from dvpmvs.sweep import JobRow, render_markdown, render_seeds_csv, write_tables


def _row(num, overrides, f1, seconds=10.0, status="ok"):
    # As the harness's table columns give them: F1 the headline, "scene" a scene key.
    metrics = {"F1 2cm": f1, "Comp. 2cm": f1 - 5, "Acc. 2cm": f1 + 5, "s/view": seconds}
    return JobRow(
        num,
        Path(str(num)),
        overrides,
        status,
        metrics,
        headline=frozenset({"F1 2cm"}),
        scene_keys=frozenset({"workspace", "scene"}),
    )


def test_tables_in_the_layouts_of_the_papers_tables_iv_and_v():
    rows = [
        _row(0, {"scene": "room", "method": "paper"}, 70.0),
        _row(1, {"scene": "facade", "method": "paper"}, 80.0),
        _row(2, {"scene": "room", "method": "w_o_agn"}, 60.0),
        _row(3, {"scene": "facade", "method": "w_o_agn"}, 0.0, status="error"),
    ]
    table = render_markdown(rows)
    # Table IV: a row per configuration, the mean over the scenes that ran, columns F1 / Comp. / Acc.
    assert "| method | scenes | F1 2cm | Comp. 2cm | Acc. 2cm | s/view |" in table
    assert "| method=paper | 2/2 | 75.00 | 70.00 | 80.00 | 10.0 |" in table
    assert "| method=w_o_agn | 1/2 | 60.00 |" in table
    assert "| 3 | scene=facade method=w_o_agn | **error** |" in table and "Failed jobs" in table
    # Table V: one parameter's values as columns.
    eta = [
        _row(i, {"segmentation.min_region": str(v)}, 60.0 + i)
        for i, v in enumerate((100, 200, 500))
    ]
    assert (
        "| segmentation.min_region | 100 | 200 | 500 |\n|---|---|---|---|\n| F1 2cm | 60.00 | 61.00 | 62.00 |"
        in render_markdown(eta)
    )


def test_a_sweep_over_the_estimators_seed_folds_it_into_a_mean_and_a_spread(tmp_path):
    # Two configurations on two scenes, seeds 0-2; one job failed.
    rows, num = [], 0
    for method in ("default", "fast"):
        for scene in ("room", "facade"):
            for seed in "012":
                rows.append(
                    _row(
                        num,
                        {"scene": scene, "method": method, "seed": seed},
                        60.0 + num,
                        status="error" if num == 7 else "ok",
                    )
                )
                num += 1
    table = render_markdown(rows)
    # One row per configuration and scene: the mean over the seeds that ran and their min-max.
    assert "| scene method | seeds | F1 2cm | Comp. 2cm | Acc. 2cm | s/view |" in table
    assert (
        "| scene=room method=default | 3/3 | 61.00 (60.00-62.00) | 56.00 | 66.00 | 10.0 |" in table
    )
    assert "| scene=room method=fast | 2/3 | 67.00 (66.00-68.00) |" in table
    # Over the scenes: the spread of the seeds' scene means (seed 1 of fast lost a scene: left out).
    assert "| method=default | 6/6 | 62.50 (61.50-63.50) |" in table
    assert "| method=fast | 5/6 | 68.80 (67.50-69.50) |" in table
    assert "| method | default | fast |" in table and "(mean over scene, seed)" in table
    assert "| 7 | scene=room method=fast seed=1 | **error** |" in table  # the jobs stay listed
    lines = render_seeds_csv(rows).splitlines()
    assert lines[0].startswith(
        "scene,method,seeds,F1 2cm,F1 2cm min,F1 2cm max,Comp. 2cm"
    ) and lines[0].endswith(",scene digest")
    assert lines[3] == "room,fast,2/3,67,66,68,62,61,63,72,71,73,10,10,10,"
    write_tables(tmp_path, rows)
    assert (tmp_path / "table.csv").read_text().splitlines() == lines
    assert len((tmp_path / "jobs.csv").read_text().splitlines()) == 13
    # Without a seed sweep, nothing is folded and table.csv lists the jobs.
    (tmp_path / "plain").mkdir()
    write_tables(tmp_path / "plain", [rows[0], rows[3]])  # seed 0 on both scenes
    assert not (tmp_path / "plain" / "jobs.csv").exists()
    assert (
        (tmp_path / "plain" / "table.csv")
        .read_text()
        .startswith("job,folder,status,scene,method,seed,F1 2cm")
    )


def test_a_sweeps_report_shows_a_deleted_job_as_missing_and_only_its_own_jobs(tmp_path):
    import json
    import re
    import shutil

    from tests.helpers import dvpmvs_here

    sweep = tmp_path / "sweep"
    result = dvpmvs_here(
        "bench",
        "-m",
        "scene=room",
        "views=4",
        "width=160",
        "seed=0,1,2",
        "quality=fast",
        "max_image_size=64",
        "patch_match.num_scales=1",
        "previews=false",
        "num_threads=2",
        "progress=false",
        f"scenes_dir={tmp_path / 'scenes'}",
        f"hydra.sweep.dir={sweep}",
        cwd=tmp_path,
    )
    assert result.returncode == 0, result.stderr[-2000:]
    table = (sweep / "table.md").read_text()
    assert "| (no overrides) | 3/3 |" in table
    # A job of an earlier sweep in the same folder (another sweep id), and a job deleted since.
    shutil.copytree(sweep / "2", sweep / "7")
    manifest = json.loads((sweep / "7" / "dvpmvs_run.json").read_text())
    manifest["sweep"] = {**manifest["sweep"], "id": "an-earlier-sweep", "job": 7}
    (sweep / "7" / "dvpmvs_run.json").write_text(json.dumps(manifest))
    shutil.rmtree(sweep / "1")
    result = dvpmvs_here("report", str(sweep), cwd=tmp_path)
    assert result.returncode == 0, result.stderr[-2000:]
    text = re.sub(r"<[^>]+>", " ", (sweep / "report.html").read_text())
    text = " ".join(text.split())
    assert "seed=1 missing" in text and "job 7" not in text
    f1 = [float(v) for v in re.findall(r"seed=[02] ok \S+ ([\d.]+)", text)]
    assert len(f1) == 2
    mean = re.search(r"\(no overrides\) 2/3 ([\d.]+)", text)
    assert mean and abs(float(mean[1]) - sum(f1) / 2) <= 0.01  # the mean of the two jobs there
    assert f"job 1 ({sweep / '1'}): its manifest" in text
    assert (sweep / "table.md").read_text() == table  # the sweep's own record of its three jobs
