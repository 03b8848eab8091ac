"""The smoke tests and the demo on the oldest and the newest Python that pyproject.toml claims, and
the package as a wheel, alone and with its extras.

`make test` runs this after the main suite (on the Python of `.venv`). Each claimed version found on
this machine (``python3.X`` on the PATH, or under pyenv's versions) gets its own virtual environment
``.venv-3.X`` and its own copy of the checkout, ``.venv-3.X/src`` (the files git sees, as they are in
the working tree, uncommitted changes included). The newest version found gets the package as a
user gets it from an index: a wheel built from its copy, installed alone into a new environment,
where ``dvpmvs demo`` (its fast preset) runs outside the source tree with none of the extras (no
ONNX Runtime, no matplotlib: the learned presets are refused by name, the F1 curves are skipped
with the extra to install), then the extras on top (the learned presets compose) and the smoke
tests (``-m "smoke and not slow"``: the compiled kernels, the formats, the plugins, every
module's import) against the installed wheel. The other versions are installed in their copy as
`make setup` installs (editable, with the extras), and the smoke tests and the demo run there.
Where no other version is found, the wheel's check runs on this Python, in ``.venv-wheel``. The
main suite runs on the Python of ``.venv``.

Each version builds its kernels in its own copy, so the versions run side by side, the cores shared
between them: most of an install is pip unpacking wheels on one core. A version that is not
installed is skipped with the reason; a version whose install fails says which package has no
wheel (or no build) for it.

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
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
EXTRAS = ".[onnx,eval,test,dask]"  # as the Makefile's setup


def _minor(version: str) -> int:
    return int(version.split(".")[1])


def claimed_versions(pyproject: Path) -> list[str]:
    """The ``Programming Language :: Python :: 3.X`` classifiers, oldest first; the oldest must be
    the one ``requires-python`` names (a claim the classifiers do not back is an error)."""
    text = pyproject.read_text()
    versions = sorted(
        set(re.findall(r'"Programming Language :: Python :: (3\.\d+)"', text)), key=_minor
    )
    floor = re.search(r'requires-python\s*=\s*">=\s*(3\.\d+)"', text)
    if not versions or floor is None or versions[0] != floor.group(1):
        raise SystemExit(
            f"{pyproject}: requires-python and the Python classifiers must name the same oldest "
            f"version (got {floor.group(1) if floor else None} and {versions[:1]})"
        )
    return versions


def find_interpreter(version: str) -> Path | None:
    """``python3.X`` on the PATH, else the newest ``3.X.*`` under pyenv's versions folder; each
    candidate must run (a pyenv shim of a version that is installed but not selected does not)."""
    candidates = [Path(found)] if (found := shutil.which(f"python{version}")) else []
    pyenv = Path(os.environ.get("PYENV_ROOT", Path.home() / ".pyenv")) / "versions"
    candidates += sorted(
        pyenv.glob(f"{version}.*/bin/python{version}"),
        key=lambda p: [int(x) for x in re.findall(r"\d+", p.parts[-3])],
        reverse=True,
    )
    for candidate in candidates:
        try:
            ran = subprocess.run(
                [str(candidate), "-c", "import sys; print(sys.version_info[:2])"],
                capture_output=True,
                text=True,
                timeout=60,
            )
        except OSError:
            continue
        if ran.returncode == 0 and ran.stdout.strip() == str(
            tuple(int(v) for v in version.split("."))
        ):
            return candidate
    return None


_NO_PACKAGE = (
    re.compile(r"No matching distribution found for ([A-Za-z0-9_.\-]+)"),
    re.compile(r"Could not find a version that satisfies the requirement ([A-Za-z0-9_.\-]+)"),
    re.compile(r"Failed (?:to )?build(?:ing wheel for)? ([A-Za-z0-9_.\-]+)"),
)


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
    counts = [
        line for line in log.splitlines() if re.match(r"^=*\s*\d+ (failed|passed|error)", line)
    ]
    return "\n".join(f"  {line}" for line in lines[:30] + counts[-1:])


def _last_messages(log: str, lines: int = 12) -> str:
    """The last command's error lines (or its last lines when it printed none), for the output CI
    keeps: the log file stays on the machine that ran it."""
    last = log[log.rfind("\n$ ") :].splitlines()
    errors = [
        line
        for line in last
        if line.startswith(("ERROR", "error:")) or "Error" in line.split(":")[0]
    ]
    return "\n".join(f"  {line}" for line in (errors or last)[-lines:])


def _free_space() -> str:
    """Free space where the environments and pip's temporary files go (a full disk fails an install
    with messages that name neither)."""
    places = {ROOT, Path(tempfile.gettempdir())}
    return "free space: " + ", ".join(
        f"{place} {shutil.disk_usage(place).free / 2**30:.1f} GiB" for place in sorted(places)
    )


def install(python: Path, log: Path, source: Path = ROOT, jobs: int | None = None) -> bool:
    """The package of the checkout ``source`` into the environment of ``python``, as `make setup`
    installs it, its kernels built by ``jobs`` compilers (default: one per core)."""
    env = {**os.environ, **({"DVPMVS_BUILD_JOBS": str(jobs)} if jobs else {})}
    return run(
        [str(python), "-m", "pip", "install", "--quiet", "--upgrade", "pip"], log, cwd=source
    ) and run(
        [str(python), "-m", "pip", "install", "--quiet", "-c", "constraints.txt", "-e", EXTRAS],
        log,
        cwd=source,
        env=env,
    )


def run(command: list[str], log: Path, cwd: Path = ROOT, **kwargs) -> bool:
    with open(log, "a") as out:
        out.write(f"\n$ {' '.join(command)}\n")
        out.flush()
        return (
            subprocess.run(
                command, stdout=out, stderr=subprocess.STDOUT, cwd=cwd, **kwargs
            ).returncode
            == 0
        )


_NOT_SOURCE = shutil.ignore_patterns(
    ".git",
    ".venv*",
    "build",
    "dist",
    "*.egg-info",
    "__pycache__",
    "*.so",
    "_*.c",
    ".pytest_cache",
    "outputs",
    "multirun",
    "dvpmvs_demo",
    "bench_scenes",
)


def source_files(root: Path = ROOT) -> list[Path]:
    """The checkout's files, relative to ``root``: those git tracks or would track (untracked but
    not ignored), as the working tree has them; every file but the ignored ones where ``root`` is
    not a git checkout (an unpacked source archive)."""
    listed = subprocess.run(
        ["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"],
        cwd=root,
        capture_output=True,
    )
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


class _Lane:
    """One version's run: its environment, log, the time of each stage, and the failure's text."""

    def __init__(self, name: str, workers: int):
        self.venv, self.log = ROOT / f".venv-{name}", ROOT / f".venv-{name}.log"
        self.python, self.bin = self.venv / "bin" / "python", self.venv / "bin"
        self.workers, self.laps, self.start = workers, [], time.perf_counter()
        self.log.write_text("")

    def lap(self, stage: str) -> str:
        now = time.perf_counter()
        self.laps.append(f"{stage} {now - self.start:.0f} s")
        self.start = now
        return ", ".join(self.laps)

    def said(self) -> str:
        return _last_messages(self.log.read_text())

    def make_venv(self, interpreter: Path) -> str | None:
        if self.python.is_file() or run([str(interpreter), "-m", "venv", str(self.venv)], self.log):
            return None
        return (
            f"could not make a virtual environment with {interpreter} (see {self.log}); it said:\n"
            f"{self.said()}\n  {_free_space()}"
        )

    def install(self, version: str, command: list[str], source: Path) -> str | None:
        """``pip install`` of ``command``'s arguments (with a second attempt: a download or a
        temporary file can fail once without the package being at fault); the failure's text."""
        env = {**os.environ, "DVPMVS_BUILD_JOBS": str(self.workers)}
        pip = [str(self.python), "-m", "pip", "install", "--quiet"]
        for attempt in range(2):
            if run([*pip, "--upgrade", "pip"], self.log, cwd=source) and run(
                [*pip, *command], self.log, cwd=source, env=env
            ):
                return None
            if attempt == 0:
                print(
                    f"Python {version}: the install failed, trying once more; it said:\n{self.said()}",
                    flush=True,
                )
        text = self.log.read_text()
        package = failing_package(text)
        what = (
            f"no wheel (or no build) of {package} for Python {version}"
            if package
            else "the install failed"
        )
        return f"{what} (see {self.log}); it said:\n{_last_messages(text)}\n  {_free_space()}"

    def smoke_tests(self, folder: Path) -> str | None:
        threads = {
            **os.environ,
            "OMP_NUM_THREADS": str(self.workers),
        }  # the kernels' share of the cores
        parallel = (
            ["-n", str(self.workers), "--dist", "worksteal"]
            if self.workers > 1
            else ["-p", "no:xdist"]
        )
        if run(
            [
                str(self.python),
                "-m",
                "pytest",
                "-m",
                "smoke and not slow",
                "-q",
                "-p",
                "no:cacheprovider",
                *parallel,
            ],
            self.log,
            cwd=folder,
            env=threads,
        ):
            return None
        return f"the smoke tests failed (see {self.log}):\n" + _failures(self.log.read_text())

    def demo(self, folder: Path, cwd: Path) -> subprocess.CompletedProcess:
        """``dvpmvs demo`` on the fast preset: every stage of the demo (maps, fusion, scores,
        report) on this Python's libraries in less time than the default's; the main suite checks
        the default's figures."""
        return capture(
            [
                str(self.bin / "dvpmvs"),
                "demo",
                f"out={folder}",
                "quality=fast",
                "progress=false",
                f"num_threads={self.workers}",
            ],
            self.log,
            cwd=cwd,
        )


def capture(
    command: list[str], log: Path, cwd: Path = ROOT, **kwargs
) -> subprocess.CompletedProcess:
    """``command``'s run with its output as text, also written to ``log``."""
    done = subprocess.run(command, capture_output=True, text=True, cwd=cwd, **kwargs)
    with open(log, "a") as out:
        out.write(f"\n$ {' '.join(command)}\n{done.stdout}{done.stderr}")
    return done


def check(version: str, interpreter: Path, workers: int = 2) -> tuple[bool, str]:
    """Install as `make setup` does, smoke tests and demo on one interpreter, in its own copy of
    the checkout, on ``workers`` cores; (passed, what happened)."""
    lane = _Lane(version, workers)
    failed = lane.make_venv(interpreter)
    if failed:
        return False, failed
    source = lane.venv / "src"
    sync_copy(source)
    failed = lane.install(version, ["-c", "constraints.txt", "-e", EXTRAS], source)
    if failed:
        return False, failed
    lane.lap("install")
    failed = lane.smoke_tests(source)
    if failed:
        return False, failed
    lane.lap("smoke tests")
    with tempfile.TemporaryDirectory(prefix=f"dvpmvs-demo-{version}-") as folder:
        if lane.demo(Path(folder) / "demo", source).returncode:
            return False, f"`dvpmvs demo` failed (see {lane.log}); it said:\n{lane.said()}"
    return True, f"smoke tests and demo passed ({interpreter}; {lane.lap('demo')})"


# The extras' distributions, and the plugins' and ONNX presets' names, that the core alone lacks.
EXTRA_DISTRIBUTIONS = {"onnxruntime", "matplotlib"}
LEARNED_PRESETS = ["depth_prior=depth_anything_v2", "normal_prior=metric3dv2"]
REPORT_FILES = ("three.bundle.js", "LICENSE.three.txt", "viewer.js", "report.css", "cloud.js")


def check_wheel(name: str, interpreter: Path, workers: int = 2) -> tuple[bool, str]:
    """The package as an index serves it, on one interpreter, on ``workers`` cores: a wheel built
    from a copy of the checkout, installed alone into a new environment (no leftovers of a former
    run), the demo run outside the source tree, the plugins listed and the learned presets refused
    by name; then the wheel's extras on top, the presets composed, and the smoke tests run against
    the installed wheel (from a folder holding only the tests); (passed, what happened)."""
    lane = _Lane(name, workers)
    shutil.rmtree(lane.venv, ignore_errors=True)
    failed = lane.make_venv(interpreter)
    if failed:
        return False, failed
    source, wheels = lane.venv / "src", lane.venv / "wheels"
    sync_copy(source)
    env = {**os.environ, "DVPMVS_BUILD_JOBS": str(workers)}
    if not run(
        [
            str(lane.python),
            "-m",
            "pip",
            "wheel",
            "--quiet",
            "--no-deps",
            "--wheel-dir",
            str(wheels),
            ".",
        ],
        lane.log,
        cwd=source,
        env=env,
    ):
        return (
            False,
            f"the wheel could not be built (see {lane.log}); it said:\n{lane.said()}\n  {_free_space()}",
        )
    (wheel,) = wheels.glob("dvpmvs-*.whl")
    failed = lane.install(name, ["-c", "constraints.txt", str(wheel)], source)
    if failed:
        return False, failed
    lane.lap("wheel and install")
    listed = capture([str(lane.python), "-m", "pip", "list", "--format=freeze"], lane.log)
    installed = {line.split("==")[0].lower() for line in listed.stdout.split()}
    if installed & EXTRA_DISTRIBUTIONS or any(n.startswith("dvpmvs-") for n in installed):
        return (
            False,
            f"the core alone installed {sorted(installed & EXTRA_DISTRIBUTIONS)} (see {lane.log})",
        )
    with tempfile.TemporaryDirectory(prefix=f"dvpmvs-demo-{name}-") as folder:
        # Run outside the source tree, so that nothing is imported from it.
        demo, out = lane.demo(Path(folder) / "demo", Path(folder)), Path(folder) / "demo"
        said = demo.stdout + demo.stderr
        missing = [
            str(p.relative_to(out))
            for p in (
                out / "fused.ply",
                out / "fused.ply.vis",
                out / "report.html",
                *(out / "report_files" / n for n in REPORT_FILES),
            )
            if not p.is_file()
        ]
        if (
            demo.returncode
            or missing
            or "fused cloud" not in said
            or "pip install 'dvpmvs[eval]'" not in said
        ):
            return False, (
                f"`dvpmvs demo` of the core alone failed or lacks {missing or 'its messages'} "
                f"(see {lane.log}); it said:\n{_last_messages(said)}"
            )
        plugins = capture([str(lane.bin / "dvpmvs"), "plugins"], lane.log, cwd=Path(folder)).stdout
        presets = [
            str(lane.bin / "dvpmvs"),
            "dense",
            "workspace=x",
            *LEARNED_PRESETS,
            "--cfg",
            "job",
        ]
        refused = capture(presets, lane.log, cwd=Path(folder))
        if "coarse_mvs" not in plugins or "colmap_cfg" not in plugins:
            return (
                False,
                f"`dvpmvs plugins` of the core alone lacks the classic providers (see {lane.log})",
            )
        if refused.returncode == 0 or "Could not find" not in refused.stderr:
            return (
                False,
                f"the core alone composed the learned presets without ONNX Runtime (see {lane.log})",
            )
        lane.lap("core alone")
        failed = lane.install(
            name, ["-c", "constraints.txt", f"{wheel}[{EXTRAS.removeprefix('.[')}"], source
        )
        if failed:
            return False, failed
        composed = capture(presets, lane.log, cwd=Path(folder))
        if (
            "preset: depth_anything_v2" not in composed.stdout
            or "preset: metric3dv2" not in composed.stdout
        ):
            return (
                False,
                f"the learned presets do not compose with the [onnx] extra (see {lane.log})",
            )
    lane.lap("extras")
    # The tests alone, so that `import dvpmvs` finds the installed wheel, not the copy's sources.
    tests = lane.venv / "tests-only"
    shutil.copytree(source / "tests", tests / "tests")
    shutil.copy2(source / "pyproject.toml", tests)
    failed = lane.smoke_tests(tests)
    if failed:
        return False, failed
    return (
        True,
        f"the wheel alone, its extras and the smoke tests passed ({interpreter}; {lane.lap('smoke tests')})",
    )


def choose_lanes(found: dict[str, Path]) -> dict[str, tuple[Path, Callable]]:
    """Each version found and its check: the newest checks the wheel, the others install as `make
    setup` does; with none found, this Python checks the wheel, in ``.venv-wheel``."""
    if not found:
        return {"wheel": (Path(sys.executable), check_wheel)}
    newest = max(found, key=_minor)
    return {
        version: (interpreter, check_wheel if version == newest else check)
        for version, interpreter in found.items()
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--versions",
        nargs="*",
        help="the versions to check (default: the oldest and the newest pyproject.toml claims)",
    )
    parser.add_argument(
        "--workers",
        type=int,
        default=2,
        help="the cores the versions share (the smoke tests' "
        "pytest-xdist workers and the demo's threads)",
    )
    args = parser.parse_args(argv)
    claimed = claimed_versions(ROOT / "pyproject.toml")
    versions = args.versions or sorted({claimed[0], claimed[-1]}, key=claimed.index)
    current = f"{sys.version_info.major}.{sys.version_info.minor}"
    found = {}
    for version in versions:
        if version == current:
            print(f"Python {version}: the main suite ran on it", flush=True)
        elif (interpreter := find_interpreter(version)) is None:
            print(
                f"Python {version}: skipped, no python{version} on the PATH or under pyenv",
                flush=True,
            )
        else:
            found[version] = interpreter
    lanes = choose_lanes(found)
    share = max(1, args.workers // len(lanes))
    print(
        f"Python {', '.join(v if v != 'wheel' else current for v in lanes)}: installing and testing side by side "
        f"in {', '.join(f'.venv-{v}' for v in lanes)} ({share} core{'s' * (share > 1)} each) ...",
        flush=True,
    )

    def checked(name: str) -> bool:
        start = time.perf_counter()
        interpreter, lane = lanes[name]
        ok, what = lane(name, interpreter, share)
        version = current if name == "wheel" else name
        print(
            f"Python {version}: {'ok' if ok else 'FAILED'} in {time.perf_counter() - start:.0f} s: {what}",
            flush=True,
        )
        return ok

    with ThreadPoolExecutor(max_workers=len(lanes)) as pool:
        return 0 if all(list(pool.map(checked, lanes))) else 1


if __name__ == "__main__":
    sys.exit(main())
