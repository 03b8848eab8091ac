"""scripts/kernel_layouts.c, the timing program behind docs/benchmarks.md's kernel layouts: it
builds against the kernels' header and its layouts compute the same sums."""

import re
import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


def test_the_layouts_program_builds_and_its_layouts_agree(tmp_path):
    if shutil.which("gcc") is None:
        pytest.skip("no gcc on this machine")
    program = tmp_path / "kernel_layouts"
    source = ROOT / "scripts" / "kernel_layouts.c"
    built = subprocess.run(
        [
            "gcc",
            "-O2",
            "-ffp-contract=off",
            "-Wall",
            "-Werror",
            "-o",
            str(program),
            str(source),
            "-lm",
        ],
        capture_output=True,
        text=True,
    )
    assert built.returncode == 0, built.stderr
    for samples in (36, 9):
        done = subprocess.run([str(program), str(samples)], capture_output=True, text=True)
        if done.returncode == 2 and "AVX2" in done.stderr:
            pytest.skip("this CPU has no AVX2 and FMA")
        assert done.returncode == 0, done.stderr
        timing, sums = done.stdout.splitlines()
        times = [float(t) for t in re.findall(r" (\d+\.\d)\b", timing)]
        assert len(times) == 3 and min(times) > 0, done.stdout
        sums = [float(x) for x in sums.split()[1:]]
        assert len(sums) == 3 and sums[0] > 0, done.stdout
        assert sums[1] == pytest.approx(sums[0], rel=1e-6) and sums[2] == pytest.approx(
            sums[0], rel=1e-6
        )
    assert subprocess.run([str(program), "0"], capture_output=True).returncode == 2
