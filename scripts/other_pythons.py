"""The smoke tests and the demo on the oldest and the newest Python that pyproject.toml claims.

`make test` runs this after the main suite (on the Python of `.venv`). Each claimed version found on
this machine (``python3.X`` on the PATH, or under pyenv's versions) gets its own virtual environment
``.venv-3.X`` and its own copy of the checkout, ``.venv-3.X/src`` (the files git sees, as they are in
the working tree, uncommitted changes included): the package is installed there as `make setup`
installs it, then the smoke tests (``-m "smoke and not slow"``: the compiled kernels, the formats,
the plugins, every module's import) and ``dvpmvs demo`` end to end (its fast preset) run in that
copy; the main suite runs on the Python of ``.venv``. Each version builds its kernels in its own
copy, so the versions run side by side, the cores shared between them: most of an install is pip
unpacking wheels on one core. A version that is not installed is skipped with the reason; a version whose install
fails says which package has no wheel (or no build) for it.

Usage: python scripts/other_pythons.py [--versions 3.10 3.13] [--workers 2]
Exit status: 0 when every version found passed, 1 otherwise.
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
EXTRAS = ".[onnx,eval,test,dask]"  # as the Makefile's setup


def claimed_versions(pyproject: Path) -> list[str]:
    """The ``Programming Language :: Python :: 3.X`` classifiers, oldest first; the oldest must be
    the one ``requires-python`` names (a claim the classifiers do not back is an error)."""
    text = pyproject.read_text()
    versions = sorted(set(re.findall(r'"Programming Language :: Python :: (3\.\d+)"', text)),
                      key=lambda v: int(v.split(".")[1]))
    floor = re.search(r'requires-python\s*=\s*">=\s*(3\.\d+)"', text)
    if not versions or floor is None or versions[0] != floor.group(1):
        raise SystemExit(f"{pyproject}: requires-python and the Python classifiers must name the same oldest "
                         f"version (got {floor.group(1) if floor else None} and {versions[:1]})")
    return versions


def find_interpreter(version: str) -> Path | None:
    """``python3.X`` on the PATH, else the newest ``3.X.*`` under pyenv's versions folder; each
    candidate must run (a pyenv shim of a version that is installed but not selected does not)."""
    candidates = [Path(found)] if (found := shutil.which(f"python{version}")) else []
    pyenv = Path(os.environ.get("PYENV_ROOT", Path.home() / ".pyenv")) / "versions"
    candidates += sorted(pyenv.glob(f"{version}.*/bin/python{version}"),
                         key=lambda p: [int(x) for x in re.findall(r"\d+", p.parts[-3])], reverse=True)
    for candidate in candidates:
        try:
            ran = subprocess.run([str(candidate), "-c", "import sys; print(sys.version_info[:2])"],
                                 capture_output=True, text=True, timeout=60)
        except OSError:
            continue
        if ran.returncode == 0 and ran.stdout.strip() == str(tuple(int(v) for v in version.split("."))):
            return candidate
    return None


_NO_PACKAGE = (re.compile(r"No matching distribution found for ([A-Za-z0-9_.\-]+)"),
               re.compile(r"Could not find a version that satisfies the requirement ([A-Za-z0-9_.\-]+)"),
               re.compile(r"Failed (?:to )?build(?:ing wheel for)? ([A-Za-z0-9_.\-]+)"))


def failing_package(log: str) -> str | None:
    """The package a failed ``pip install`` could not get, from its messages."""
    for pattern in _NO_PACKAGE:
        found = pattern.search(log)
        if found:
            return found.group(1)
    return None


def _failures(log: str) -> str:
    """pytest's summary lines of the failed tests and its count, for the output CI keeps (the log
    file stays on the machine that ran it)."""
    lines = [line for line in log.splitlines() if line.startswith(("FAILED ", "ERROR "))]
    counts = [line for line in log.splitlines() if re.match(r"^=*\s*\d+ (failed|passed|error)", line)]
    return "\n".join(f"  {line}" for line in lines[:30] + counts[-1:])


def _last_messages(log: str, lines: int = 12) -> str:
    """The last command's error lines (or its last lines when it printed none), for the output CI
    keeps: the log file stays on the machine that ran it."""
    last = log[log.rfind("\n$ "):].splitlines()
    errors = [line for line in last if line.startswith(("ERROR", "error:")) or "Error" in line.split(":")[0]]
    return "\n".join(f"  {line}" for line in (errors or last)[-lines:])


def _free_space() -> str:
    """Free space where the environments and pip's temporary files go (a full disk fails an install
    with messages that name neither)."""
    places = {ROOT, Path(tempfile.gettempdir())}
    return "free space: " + ", ".join(f"{place} {shutil.disk_usage(place).free / 2**30:.1f} GiB"
                                      for place in sorted(places))


def install(python: Path, log: Path, source: Path = ROOT, jobs: int | None = None) -> bool:
    """The package of the checkout ``source`` into the environment of ``python``, as `make setup`
    installs it, its kernels built by ``jobs`` compilers (default: one per core)."""
    env = {**os.environ, **({"DVPMVS_BUILD_JOBS": str(jobs)} if jobs else {})}
    return (run([str(python), "-m", "pip", "install", "--quiet", "--upgrade", "pip"], log, cwd=source)
            and run([str(python), "-m", "pip", "install", "--quiet", "-c", "constraints.txt", "-e", EXTRAS], log,
                    cwd=source, env=env))


def run(command: list[str], log: Path, cwd: Path = ROOT, **kwargs) -> bool:
    with open(log, "a") as out:
        out.write(f"\n$ {' '.join(command)}\n")
        out.flush()
        return subprocess.run(command, stdout=out, stderr=subprocess.STDOUT, cwd=cwd, **kwargs).returncode == 0


_NOT_SOURCE = shutil.ignore_patterns(".git", ".venv*", "build", "dist", "*.egg-info", "__pycache__", "*.so",
                                     "_*.c", ".pytest_cache", "outputs", "multirun", "dvpmvs_demo", "bench_scenes")


def source_files(root: Path = ROOT) -> list[Path]:
    """The checkout's files, relative to ``root``: those git tracks or would track (untracked but
    not ignored), as the working tree has them; every file but the ignored ones where ``root`` is
    not a git checkout (an unpacked source archive)."""
    listed = subprocess.run(["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"],
                            cwd=root, capture_output=True)
    if listed.returncode == 0:
        names = [Path(name.decode()) for name in listed.stdout.split(b"\0") if name]
        return [name for name in names if (root / name).is_file()]  # not the deleted ones
    files = []
    for folder, subfolders, names in os.walk(root):
        ignored = _NOT_SOURCE(folder, subfolders + names)
        subfolders[:] = [d for d in subfolders if d not in ignored]
        files += [Path(folder, n).relative_to(root) for n in names if n not in ignored]
    return files


def _size_and_time(path: Path) -> tuple[int, int]:
    stat = path.stat()
    return stat.st_size, stat.st_mtime_ns


def sync_copy(copy: Path, root: Path = ROOT) -> None:
    """Make ``copy`` hold the source files of ``root``: changed ones copied, those ``root`` no longer
    has removed; the files a build made in the copy (its kernels, for that copy's Python) stay, so
    that a second run rebuilds only what changed. The copies are what lets the versions build side
    by side: an editable install writes its metadata and kernels into the tree it installs."""
    manifest = copy / ".dvpmvs-source-files"
    before = set(manifest.read_text().splitlines()) if manifest.is_file() else set()
    files = source_files(root)
    for name in files:
        source, target = root / name, copy / name
        if not target.is_file() or _size_and_time(target) != _size_and_time(source):
            target.parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(source, target)  # keeps the time, so an unchanged file is not copied again
    for gone in before - {str(name) for name in files}:
        (copy / gone).unlink(missing_ok=True)
    manifest.write_text("".join(f"{name}\n" for name in files))


def check(version: str, interpreter: Path, workers: int = 2) -> tuple[bool, str]:
    """Install, smoke tests and demo on one interpreter, in its own copy of the checkout, on
    ``workers`` cores; (passed, what happened)."""
    venv = ROOT / f".venv-{version}"
    log = ROOT / f".venv-{version}.log"
    log.write_text("")
    python = venv / "bin" / "python"
    if not python.is_file() and not run([str(interpreter), "-m", "venv", str(venv)], log):
        return False, (f"could not make a virtual environment with {interpreter} (see {log}); it said:\n"
                       f"{_last_messages(log.read_text())}\n  {_free_space()}")
    source = venv / "src"
    sync_copy(source)
    laps, start = [], time.perf_counter()

    def lap(stage: str) -> str:
        nonlocal start
        now = time.perf_counter()
        laps.append(f"{stage} {now - start:.0f} s")
        start = now
        return ", ".join(laps)

    if not install(python, log, source, workers):
        # A second attempt, because a download or a temporary file can fail once without the
        # package being at fault; both attempts' messages stay in the log and in what is printed.
        first = _last_messages(log.read_text())
        print(f"Python {version}: the install failed, trying once more; it said:\n{first}", flush=True)
        if not install(python, log, source, workers):
            text = log.read_text()
            package = failing_package(text)
            what = f"no wheel (or no build) of {package} for Python {version}" if package else "the install failed"
            return False, f"{what} (see {log}); it said:\n{_last_messages(text)}\n  {_free_space()}"
    lap("install")
    threads = {**os.environ, "OMP_NUM_THREADS": str(workers)}  # the kernels' share of the cores
    parallel = ["-n", str(workers), "--dist", "worksteal"] if workers > 1 else ["-p", "no:xdist"]
    if not run([str(python), "-m", "pytest", "-m", "smoke and not slow", "-q", "-p", "no:cacheprovider", *parallel],
               log, cwd=source, env=threads):
        return False, f"the smoke tests failed (see {log}):\n" + _failures(log.read_text())
    lap("smoke tests")
    with tempfile.TemporaryDirectory(prefix=f"dvpmvs-demo-{version}-") as folder:
        # The fast preset: every stage of the demo (maps, fusion, scores, report) on this Python's
        # libraries in less time than the default's; the main suite checks the default's figures.
        if not run([str(venv / "bin" / "dvpmvs"), "demo", f"out={Path(folder) / 'demo'}", "quality=fast",
                    "progress=false", f"num_threads={workers}"], log, cwd=source):
            return False, f"`dvpmvs demo` failed (see {log}); it said:\n{_last_messages(log.read_text())}"
    return True, f"smoke tests and demo passed ({interpreter}; {lap('demo')})"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--versions", nargs="*", help="the versions to check (default: the oldest and the newest "
                                                       "pyproject.toml claims)")
    parser.add_argument("--workers", type=int, default=2, help="the cores the versions share (the smoke tests' "
                                                                 "pytest-xdist workers and the demo's threads)")
    args = parser.parse_args(argv)
    claimed = claimed_versions(ROOT / "pyproject.toml")
    versions = args.versions or sorted({claimed[0], claimed[-1]}, key=claimed.index)
    current = f"{sys.version_info.major}.{sys.version_info.minor}"
    found = {}
    for version in versions:
        if version == current:
            print(f"Python {version}: the main suite ran on it", flush=True)
        elif (interpreter := find_interpreter(version)) is None:
            print(f"Python {version}: skipped, no python{version} on the PATH or under pyenv", flush=True)
        else:
            found[version] = interpreter
    if not found:
        return 0
    share = max(1, args.workers // len(found))
    print(f"Python {', '.join(found)}: installing and testing side by side in "
          f"{', '.join(f'.venv-{v}' for v in found)} ({share} core{'s' * (share > 1)} each) ...", flush=True)

    def checked(version: str) -> bool:
        start = time.perf_counter()
        ok, what = check(version, found[version], share)
        print(f"Python {version}: {'ok' if ok else 'FAILED'} in {time.perf_counter() - start:.0f} s: {what}",
              flush=True)
        return ok

    with ThreadPoolExecutor(max_workers=len(found)) as pool:
        return 0 if all(list(pool.map(checked, found))) else 1


if __name__ == "__main__":
    sys.exit(main())
