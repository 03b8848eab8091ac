"""The small rendered scene the dense stage's tests share (the tabletop, 4 views), run once per
test session, and what those tests ask of its output folders."""

import pickle
import shutil
from pathlib import Path

from dvpmvs.dense import (
    DenseOptions,
    map_files,
    run_dense,
)
from dvpmvs.evaluation.commands import eth3d_parameters_for
from dvpmvs.evaluation.eth3d_metric import evaluate_eth3d
from dvpmvs.evaluation.pointclouds import read_meshlab_project, read_points
from dvpmvs.evaluation.synthetic import SynthOptions, generate
from dvpmvs.provenance import Status, read_record, record_path, status
from dvpmvs.workspace import Workspace
from dvpmvs.writer_lock import LOCK_NAME
from tests.helpers import built_once


def tabletop_run(tmp_path_factory, width: int):
    """The tabletop scene, 4 views ``width`` pixels wide, with the whole dense stage run once."""

    def build(folder: Path) -> None:
        generate(
            folder / "tabletop", SynthOptions(scene="tabletop", views=4, width=width, priors=False)
        )
        summary = run_dense(Workspace.open(folder / "tabletop"), DenseOptions(), progress=False)
        (folder / "summary.pickle").write_bytes(pickle.dumps(summary))

    folder = built_once(tmp_path_factory, f"pipeline_tabletop_{width}", build)
    return folder / "tabletop", pickle.loads((folder / "summary.pickle").read_bytes())


# The records, reuse and formats hold at any size: they are checked on 96x72 views, where the
# default runs in a fraction of the time of the accuracy check's 200x150.
SMALL = (96, 72)


def copy_workspace(root, tmp_path):
    target = tmp_path / "ws"
    shutil.copytree(root, target)
    return target


def maps_are_current(stereo, view, pass_):
    """True when the view's maps of the pass carry a complete record and match it."""
    record = read_record(record_path(stereo, view.name, pass_.value))
    files = map_files(stereo, view.name, pass_)
    return (
        record is not None
        and status(record, record.fingerprint, stereo, files.values()) is Status.CURRENT
    )


def file_times(folder):
    """Every file's time, but the writer lock's (each writer records itself there: not an output)."""
    return {
        p: p.stat().st_mtime_ns
        for p in sorted(folder.rglob("*"))
        if p.is_file() and p.name != LOCK_NAME
    }


def eth3d_scores(root, cloud_path):
    mlp = root / "ground_truth" / "scan_alignment.mlp"
    return evaluate_eth3d(
        read_points(cloud_path), read_meshlab_project(mlp), (0.02, 0.1), eth3d_parameters_for(mlp)
    )
