"""The README's examples run as written, in the folder the demo leaves."""

import os
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from test_docs import block_commands, code_blocks

README = Path(__file__).resolve().parents[1] / "README.md"


def test_the_readme_names_its_two_commands_first():
    first = block_commands(code_blocks(README)[0])
    assert [shlex.split(c, comments=True) for c in first] == [["make", "demo"], ["make", "test"]]


@pytest.mark.slow
def test_every_readme_example_runs_as_written(tmp_path):
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}", "CI": "true"}
    # What `make demo` does once set up.
    subprocess.run([sys.executable, "-m", "dvpmvs.cli", "demo", "out=dvpmvs_demo"], cwd=tmp_path, env=env,
                   check=True, capture_output=True)
    ran = []
    for block in code_blocks(README)[1:]:
        for command in block_commands(block):
            words = shlex.split(command, comments=True)
            if words[0] == "colmap" and shutil.which("colmap") is None:
                continue  # COLMAP's own program is an optional client (`make test` installs it where apt can)
            assert words[0] in ("dvpmvs", "colmap"), command
            done = subprocess.run(words, cwd=tmp_path, env=env, capture_output=True, text=True)
            assert done.returncode == 0, f"{command}\n{done.stderr[-3000:]}"
            ran.append(words[:2])
    for block in code_blocks(README, "python"):
        done = subprocess.run([sys.executable, "-c", block], cwd=tmp_path, env=env, capture_output=True, text=True)
        assert done.returncode == 0, f"{block}\n{done.stderr[-3000:]}"
        assert "maps;" in done.stdout and "triangles" in done.stdout
    assert ["dvpmvs", "reconstruct"] in ran and ["dvpmvs", "bench"] in ran
    assert (tmp_path / "run_fast" / "fused.ply").is_file()
    assert (tmp_path / "demo_project" / "dense" / "meshed-poisson.ply").is_file()
    assert (tmp_path / "submission" / "high_res_multi_view" / "courtyard.txt").read_text().startswith("runtime")
