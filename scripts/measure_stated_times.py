"""Measure every time (and memory) the documents state, on a fresh clone, and record it.

A document that says "about 30 s" or "under a minute" marks the statement with the measurement it
rests on, ``<!-- measured: KEY -->`` right after it; ``tests/test_docs.py`` holds each marked
statement within 2x of ``docs/measured_times.json`` (an "under" statement: at most its bound) and
refuses a time statement without a marker. This script makes that file: it clones the checkout's
HEAD into a new folder (no ``.venv``, nothing built) and runs there, one after the other, the
commands the statements are about, each timed as a whole:

- ``setup``: ``make setup`` (pip's cache off with ``--fresh-pip``, as on a machine that never
  installed these packages; the system libraries are what this machine has);
- ``demo``: ``make demo`` once set up, the README's first command as a user reruns it;
- ``reconstruct_demo_images``: the tutorial's ``reconstruct`` on the demo's five photos;
- ``fountain_reconstruct``: the tutorial's ``reconstruct`` on fountain-P11 at 1024 px
  (``--fountain``: its images' folder; skipped without it);
- ``fast_suite``: ``make test-fast``, the suite without the tests marked slow;
- ``make_test``: ``make test``, the README's second command, set up already (its last line
  gives each stage's time).

Times hold for an idle machine: a step starts only when the 1-minute load average is under
``--max-load`` (waiting up to 10 minutes for it, else refusing), and the record keeps each step's
CPU time, its peak memory (the largest process's resident set) and the load before it, so a
record made on a busy machine shows as one.

Usage: python scripts/measure_stated_times.py [--fountain ../shared/data/strecha/fountain-P11/images]
       [--steps demo fast_suite ...] [--fresh-pip] [--out docs/measured_times.json]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import resource
import shlex
import subprocess
import sys
import tempfile
import time
from datetime import datetime, timezone
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
RECONSTRUCT = ".venv/bin/dvpmvs reconstruct images={images} out={out} max_image_size=1024"


def steps(fountain: Path | None) -> dict[str, str]:
    """Each measured key and its shell command, in the order they run (each needs the ones
    before it: setup, then the demo's folder)."""
    found = {
        "setup": "make setup",
        "demo": "make demo",
        "reconstruct_demo_images": RECONSTRUCT.format(
            images="dvpmvs_demo/images", out="runs/demo_project"
        ),
        "fountain_reconstruct": None
        if fountain is None
        else RECONSTRUCT.format(
            images=shlex.quote(str(fountain.resolve())), out="runs/fountain_project"
        ),
        "fast_suite": "make test-fast",
        "make_test": "make test",
    }
    return {key: command for key, command in found.items() if command is not None}


# The steps each needs run before it (untimed where not measured themselves).
NEEDS = {"reconstruct_demo_images": ("demo",)}


def needed(plan: dict[str, str], chosen: list[str] | None) -> list[str]:
    """The keys to run, in order: the chosen ones (all without a choice), what they need, and
    ``setup`` before anything."""
    if chosen is None:
        return list(plan)
    wanted = {"setup", *chosen}
    for key in chosen:
        wanted.update(NEEDS.get(key, ()))
    return [key for key in plan if key in wanted]


def load_average() -> float:
    return os.getloadavg()[0]


def wait_until_idle(max_load: float, patience: float = 600.0) -> float:
    """The 1-minute load average once it is under ``max_load``; SystemExit after ``patience``
    seconds of a busy machine (its time would not be an idle machine's)."""
    deadline = time.monotonic() + patience
    while (load := load_average()) >= max_load:
        if time.monotonic() > deadline:
            raise SystemExit(
                f"the machine stayed busy (load average {load:.2f} >= {max_load}) for "
                f"{patience:.0f} s: stop what runs beside this script, or give a larger --max-load"
            )
        time.sleep(10)
    return load


# Runs one shell command and writes the peak resident set of its largest process (kB): the
# children's ru_maxrss of a process that ran only this command.
_PEAK_WRAPPER = (
    "import resource, subprocess, sys\n"
    "code = subprocess.run(sys.argv[1], shell=True).returncode\n"
    "open(sys.argv[2], 'w').write(str(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss))\n"
    "sys.exit(code)\n"
)


def run_step(command: str, cwd: Path, env: dict[str, str], log: Path) -> dict[str, float]:
    """Wall seconds, CPU seconds and peak memory (MB, of its largest process) of one shell
    command, its output in ``log``; SystemExit when it fails."""
    peak = log.with_suffix(".peak")
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.perf_counter()
    with open(log, "w") as out:
        done = subprocess.run(
            [sys.executable, "-c", _PEAK_WRAPPER, command, str(peak)],
            cwd=cwd,
            env=env,
            stdout=out,
            stderr=subprocess.STDOUT,
        )
    seconds = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if done.returncode != 0:
        raise SystemExit(f"`{command}` failed (exit {done.returncode}); its output: {log}")
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return {
        "seconds": round(seconds, 1),
        "cpu_seconds": round(cpu, 1),
        "peak_rss_mb": round(int(peak.read_text()) / 1024),
        "stages": stage_times(log.read_text(errors="replace")),
    }


def stage_times(output: str) -> dict[str, float]:
    """The seconds of each stage a command reports as ``NAME K/N: done in S s`` (make setup's
    steps), by ``K/N``."""
    return {
        step: float(seconds)
        for step, seconds in re.findall(r"^\S+ (\d+/\d+): done in (\d+) s$", output, re.M)
    }


def machine() -> dict[str, object]:
    model = "unknown"
    cpuinfo = Path("/proc/cpuinfo")
    if cpuinfo.is_file():
        for line in cpuinfo.read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    return {"cpu": model, "cores": os.cpu_count(), "system": platform.platform()}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--fountain", type=Path, help="fountain-P11's images (else not measured)")
    parser.add_argument(
        "--steps", nargs="*", help="only these keys (their predecessors run untimed)"
    )
    parser.add_argument("--fresh-pip", action="store_true", help="setup without pip's cache")
    parser.add_argument("--max-load", type=float, default=0.5)
    parser.add_argument("--out", type=Path, default=ROOT / "docs" / "measured_times.json")
    parser.add_argument("--keep", action="store_true", help="keep the clone (its path is printed)")
    args = parser.parse_args(argv)
    if args.fountain is not None and not args.fountain.is_dir():
        raise SystemExit(f"--fountain {args.fountain} is not a folder of images")
    commit = subprocess.run(
        ["git", "rev-parse", "--short", "HEAD"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        check=True,
    ).stdout.strip()
    dirty = subprocess.run(
        ["git", "status", "--porcelain", "--untracked-files=no"],
        cwd=ROOT,
        capture_output=True,
        text=True,
    ).stdout.strip()
    if dirty:
        print(f"note: the working tree has uncommitted changes; the clone measures HEAD ({commit})")
    plan = steps(args.fountain)
    unknown = set(args.steps or []) - set(plan)
    if unknown:
        raise SystemExit(f"unknown step(s) {sorted(unknown)}; the steps: {list(plan)}")
    record = json.loads(args.out.read_text()) if args.out.is_file() else {"steps": {}}
    env = dict(os.environ)
    setup_env = {**env, "PIP_NO_CACHE_DIR": "1"} if args.fresh_pip else env
    clone = Path(tempfile.mkdtemp(prefix="dvpmvs-times-"))
    subprocess.run(["git", "clone", "--quiet", "--no-hardlinks", str(ROOT), str(clone)], check=True)
    print(f"fresh clone of {commit}: {clone}")
    for key in needed(plan, args.steps):
        command = plan[key]
        measured = args.steps is None or key in args.steps
        log = clone / f"measure_{key}.log"
        load = wait_until_idle(args.max_load) if measured else load_average()
        print(
            f"{key}: `{command}` ({'measured' if measured else 'untimed, needed by a later step'}, load {load:.2f})",
            flush=True,
        )
        result = run_step(command, clone, setup_env if key == "setup" else env, log)
        print(
            f"{key}: {result['seconds']:.1f} s ({result['cpu_seconds']:.1f} s of CPU)", flush=True
        )
        if measured:
            record["steps"][key] = {
                "command": command,
                **result,
                "load_before": round(load, 2),
                "commit": commit,
                "date": datetime.now(timezone.utc).strftime("%Y-%m-%d"),
                "machine": machine(),
                "pip_cache": not args.fresh_pip if key == "setup" else None,
            }
            args.out.write_text(json.dumps(record, indent=1, sort_keys=True) + "\n")
    print(f"written: {args.out}")
    if not args.keep:
        subprocess.run(["rm", "-rf", str(clone)], check=False)
    return 0


if __name__ == "__main__":
    sys.exit(main())
