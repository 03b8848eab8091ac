"""A sweep's table again with its clouds scored by the current ETH3D metric, maps untouched.

For each sweep folder given (``multirun/bench-...``), every job's ``fused.ply`` is scored against
the ground truth of the workspace its manifest names (a relative workspace is looked up from the
folders above the job's, where the sweep ran), with the tolerances the job used; the scores are
kept in ``evaluation/eth3d_rescored.json`` beside the job (fingerprinted: a rerun with the same
cloud, ground truth and metric code reads them back). The sweep's table is then written as the
sweep itself writes it, as ``table_rescored.md`` and ``table_rescored.csv`` (and printed), its
other columns (seconds per view, depth maps, memory) as the jobs recorded them.

    python -m dvpmvs.evaluation.experiments.rescore multirun/bench-7b03706a7e multirun/bench-6d5b7fb41f

Use it when the metric's code changed and the clouds did not: rerunning the sweep would also
recompute every map whose code fingerprint changed.
"""

from __future__ import annotations

import argparse
from pathlib import Path


def rescore_sweep(sweep: Path) -> str:
    import json

    from dvpmvs.evaluation.runs import job_ground_truth, score_cloud, score_columns
    from dvpmvs.run import MANIFEST_NAME
    from dvpmvs.sweep import read_jobs, render_csv, render_markdown

    rows = read_jobs(sweep)
    if not rows:
        raise SystemExit(f"{sweep}: no job manifests ({MANIFEST_NAME}) in its folders")
    for row in rows:
        cloud = row.folder / "fused.ply"
        manifest = json.loads((row.folder / MANIFEST_NAME).read_text())
        eth3d = (manifest.get("evaluation") or {}).get("eth3d")
        if not eth3d or not cloud.is_file():
            continue
        scores = score_cloud(
            cloud,
            job_ground_truth(row.folder),
            [float(t) for t in eth3d["tolerances"]],
            row.folder / "evaluation" / "eth3d_rescored.json",
        )
        row.metrics.update(score_columns({"evaluation": {"eth3d": scores}}))
    table = render_markdown(rows)
    (sweep / "table_rescored.md").write_text(table)
    (sweep / "table_rescored.csv").write_text(render_csv(rows))
    return table


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("sweeps", nargs="+", type=Path)
    args = parser.parse_args(argv)
    from dvpmvs.errors import DvpmvsError

    for sweep in args.sweeps:
        try:
            print(f"## {sweep}\n\n{rescore_sweep(sweep)}")
        except DvpmvsError as exc:
            raise SystemExit(str(exc)) from None
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
