"""The tables a dense run prints: the workspace's views, and its closing summary."""

import re

import pytest
from rich.console import Console

from dvpmvs.dense import run_dense
from dvpmvs.evaluation.synthetic import SynthOptions, generate
from dvpmvs.options.dense import DenseOptions
from dvpmvs.patchmatch import PatchMatchOptions
from dvpmvs.tables import partial_cloud_note, print_summary, print_workspace_summary
from dvpmvs.workspace import Workspace


@pytest.fixture(scope="module")
def small_run(tmp_path_factory):
    """The tabletop, 3 views of 96x72, its dense stage run once."""
    root = tmp_path_factory.mktemp("tables") / "tabletop"
    generate(root, SynthOptions(scene="tabletop", views=3, width=96, priors=False))
    workspace = Workspace.open(root)
    options = DenseOptions(patch_match=PatchMatchOptions(num_scales=1), previews=False)
    return workspace, run_dense(workspace, options, progress=False)


def _printed(draw) -> str:
    console = Console(record=True, width=160)
    draw(console)
    return console.export_text()


def test_the_summary_counts_each_pass_and_the_cloud(small_run):
    _, summary = small_run
    text = _printed(lambda console: print_summary(summary, console))
    stages = text[: text.index("work per pixel")]
    rows = {
        line.split("│")[1].strip(): [cell.strip() for cell in line.split("│")[2:-1]]
        for line in stages.splitlines()
        if re.match(r"^│ *(photometric|geometric|fusion) *│ *\d", line)
    }
    assert rows["photometric"][:2] == ["3", "0"] and rows["geometric"][:2] == ["3", "0"]
    assert rows["photometric"][-1] == "96x72" and rows["fusion"][4] == f"{summary.num_points:,} pts"
    assert summary.num_points > 1000
    assert "work per pixel (estimator)" in text and f"maps: {summary.stereo_dir}" in text


def test_the_workspace_table_lists_every_view_with_its_sources(small_run, capsys):
    workspace, _ = small_run
    print_workspace_summary(workspace)
    said = capsys.readouterr().err
    for view in workspace.reference_views():
        assert view.name in said
    assert "96x72" in said and "2: " in said  # each view's two sources


def test_a_partial_cloud_names_at_most_five_views():
    note = partial_cloud_note([f"{i}.png" for i in range(7)])
    assert (
        note
        == "warning: partial cloud: 7 view(s) without maps added no points (0.png, 1.png, 2.png, 3.png, "
        "4.png +2 more)"
    )
