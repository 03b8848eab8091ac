"""``dvpmvs compare``: two builds of dvpmvs timed interleaved on the same views, and their maps compared.

A speed figure on a shared machine is only a ratio measured in one run: this machine's speed
changes by 2x from one day to the next. ``dvpmvs compare A B`` runs ``dvpmvs dense`` with build A
and with build B on each synthetic scene in turn, alternating which goes first, each on its own
copy of the scene, and prints per scene and overall the seconds per view of each build, their
ratio A / B, whether the two builds made the same maps (depth and normal, both passes, byte for
byte) and where each build's time goes (the share of every kernel call in the estimator's
time, from timers the worker puts around them: :mod:`compare_worker`).

A build is
  * ``current``: this interpreter's dvpmvs;
  * a path to another interpreter (``/opt/dvpmvs-0.1/bin/python``): an installed build;
  * a commit of this repository (``11e3861``, ``HEAD~3``): checked out into ``--builds-dir`` and
    set up there with its own ``make setup`` (once; it needs PyPI);
followed by ``@VAR=VALUE,...`` to run it with environment variables (``current@DVPMVS_SIMD=scalar``).
Dense options after ``--`` go to both builds; ``--a-options`` and ``--b-options`` to one of them
(``--b-options "quality=fast"``: a preset against another build's default).

Example (the figures of docs/benchmarks.md)::

    dvpmvs compare 11e3861 current --scenes room,facade,tabletop --width 800 --threads 2
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

__all__ = ["Build", "copy_scene", "main"]

_WORKER = Path(__file__).with_name("compare_worker.py")
_MAP_KINDS = ("depth_maps", "normal_maps")


@dataclass
class Build:
    spec: str
    python: str
    env: dict[str, str] = field(default_factory=dict)

    @property
    def label(self) -> str:
        return self.spec


def _git(*args: str, cwd: Path) -> str:
    return subprocess.run(
        ["git", *args], cwd=cwd, check=True, capture_output=True, text=True
    ).stdout.strip()


def _repository() -> Path:
    """The git checkout of dvpmvs that commits are named in: the one this file lies in, else the
    current folder's."""
    for folder in (Path(__file__).resolve().parent, Path.cwd()):
        try:
            return Path(_git("rev-parse", "--show-toplevel", cwd=folder))
        except (subprocess.CalledProcessError, FileNotFoundError):
            continue
    raise SystemExit(
        "dvpmvs compare: a commit can be named only from a git checkout of dvpmvs (run it there); "
        "or give the path of an installed build's python"
    )


def _commit_build(ref: str, builds_dir: Path) -> str:
    """The python of ``ref``'s checkout in ``builds_dir``, set up by that commit's own Makefile."""
    repo = _repository()
    try:
        sha = _git("rev-parse", "--verify", f"{ref}^{{commit}}", cwd=repo)
    except subprocess.CalledProcessError:
        raise SystemExit(
            f"dvpmvs compare: {ref!r} is neither an interpreter nor a commit of {repo}"
        ) from None
    source = builds_dir / sha[:12]
    python = source / ".venv" / "bin" / "python"
    if (source / ".venv" / ".dvpmvs-installed").is_file():
        return str(python)
    if not source.exists():
        source.parent.mkdir(parents=True, exist_ok=True)
        staging = source.with_name(source.name + ".partial")
        shutil.rmtree(staging, ignore_errors=True)
        staging.mkdir()
        archive = subprocess.run(
            ["git", "archive", sha], cwd=repo, check=True, capture_output=True
        ).stdout
        subprocess.run(["tar", "x", "-C", str(staging)], input=archive, check=True)
        staging.rename(source)
    print(f"setting up {ref} ({sha[:12]}) in {source} ...", flush=True)
    subprocess.run(["make", "setup"], cwd=source, check=True)
    return str(python)


def resolve(spec: str, builds_dir: Path) -> Build:
    """A build from its command-line spec (see the module docstring)."""
    name, _, assignments = spec.partition("@")
    env = {}
    for item in filter(None, assignments.split(",")):
        key, sep, value = item.partition("=")
        if not sep:
            raise SystemExit(f"dvpmvs compare: {item!r} in {spec!r} is not VAR=VALUE")
        env[key] = value
    if name == "current":
        python = sys.executable
    elif os.sep in name and os.access(name, os.X_OK) and Path(name).is_file():
        python = name
    else:
        python = _commit_build(name, builds_dir)
    return Build(spec, python, env)


def copy_scene(scene: Path, target: Path) -> Path:
    """A fresh copy of a rendered scene's workspace (images, sparse model, stereo/*.cfg)."""
    if target.exists():
        shutil.rmtree(target)
    target.mkdir(parents=True)
    for name in ("images", "sparse"):
        shutil.copytree(scene / name, target / name)
    (target / "stereo").mkdir()
    for cfg in (scene / "stereo").glob("*.cfg"):
        shutil.copy2(cfg, target / "stereo" / cfg.name)
    return target


def _run(build: Build, workspace: Path, report: Path, threads: int, overrides: list[str]) -> dict:
    env = {**os.environ, **build.env}
    env.pop("PYTHONPATH", None)
    argv = [
        "dense",
        f"workspace={workspace}",
        f"num_threads={threads}",
        "previews=false",
        *overrides,
    ]
    command = [build.python, "-c", _WORKER.read_text(), str(report), *argv]
    log = report.with_suffix(".log")
    with open(log, "w") as out:
        status = subprocess.run(
            command, env=env, stdout=out, stderr=subprocess.STDOUT, cwd=workspace
        ).returncode
    if status != 0 or not report.is_file():
        raise SystemExit(f"dvpmvs compare: build {build.label} failed on {workspace} (see {log})")
    return json.loads(report.read_text())


def _maps(workspace: Path) -> dict[str, bytes]:
    stereo = workspace / "stereo"
    return {
        f"{kind}/{path.name}": path.read_bytes()
        for kind in _MAP_KINDS
        for path in sorted((stereo / kind).glob("*.bin"))
    }


def _per_view(result: dict) -> dict[str, float]:
    """Seconds per view: both passes of the estimator, and the priors and segmentation."""
    views = {entry["view"] for entry in result["views"]}
    count = max(1, len(views))
    out = {"total": 0.0}
    for entry in result["views"]:
        out[entry["pass"]] = out.get(entry["pass"], 0.0) + entry["seconds"] / count
        out["total"] += entry["seconds"] / count
    priors = result["kernel_seconds"].get("priors/all", 0.0)
    out["priors"] = priors / count
    out["total"] += priors / count
    out["wall"] = result["wall_seconds"] / count
    return out


def _work(results: list[dict]) -> list[tuple[str, int, str, float, float, float]]:
    """(pass, level, size, hypotheses, windows, samples per pixel) over the runs' views, for a
    build whose estimator counts its work (empty for one that does not)."""
    from dvpmvs.patchmatch.problem import pooled_work

    rows = []
    for pass_ in ("priors", "photometric", "geometric"):  # the order they run in
        levels = [
            level
            for r in results
            for entry in r["views"]
            if entry["pass"] == pass_
            for level in entry.get("work", [])
        ]
        rows += [
            (
                pass_,
                w["level"],
                "x".join(map(str, w["size"])),
                w["hypotheses"],
                w["windows"],
                w["samples"],
            )
            for w in pooled_work(levels)
        ]
    return rows


def _nominal_ghz() -> float | None:
    """The CPU's clock as the kernel reports it (/proc/cpuinfo; a VM's is its host's nominal one),
    or None where it does not."""
    try:
        text = Path("/proc/cpuinfo").read_text()
    except OSError:
        return None
    mhz = [float(line.split(":")[1]) for line in text.splitlines() if line.startswith("cpu MHz")]
    return max(mhz) / 1000 if mhz else None


def _per_sample(results: list[dict], threads: int) -> tuple[float, float]:
    """CPU nanoseconds per sample matched by the estimator's passes (the runs' views, priors
    excluded): all of both passes, and their sweeps and initialisations alone (the matching with
    the work around each window), each as seconds x threads / samples."""
    samples = sum(
        level["samples"] for r in results for entry in r["views"] for level in entry.get("work", [])
    )
    passes = sum(entry["seconds"] for r in results for entry in r["views"])
    kernels = sum(
        s
        for r in results
        for key, s in r["kernel_seconds"].items()
        if key.split("/")[0] in ("photometric", "geometric")
        and key.split("/")[1] in ("sweep", "initialise")
    )
    scale = 1e9 * threads / max(samples, 1)
    return passes * scale, kernels * scale


def _shares(results: list[dict]) -> list[tuple[str, float, float]]:
    """(stage/kernel, seconds, share of the view's time: both passes and the priors) summed over
    runs, largest first; "priors/all" is the priors and segmentation, the kernels they call
    (the coarse_mvs depth prior runs the estimator) are also listed under "priors/"."""
    total = sum(entry["seconds"] for r in results for entry in r["views"])
    total += sum(r["kernel_seconds"].get("priors/all", 0.0) for r in results)
    kernels: dict[str, float] = {}
    for r in results:
        for key, s in r["kernel_seconds"].items():
            kernels[key] = kernels.get(key, 0.0) + s
    rows = sorted(kernels.items(), key=lambda item: -item[1])
    return [(k, s, s / total if total else 0.0) for k, s in rows]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="dvpmvs compare",
        description=__doc__.split("\n\n")[0],
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="\n\n".join(__doc__.split("\n\n")[1:]),
    )
    parser.add_argument(
        "builds", nargs=2, metavar="BUILD", help="current, a python interpreter, or a commit"
    )
    parser.add_argument(
        "--scenes", default="room,facade,tabletop", help="synthetic scenes, comma-separated"
    )
    parser.add_argument("--width", type=int, default=800)
    parser.add_argument("--views", type=int, default=8)
    parser.add_argument("--scene-seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=1, help="runs of each build per scene")
    parser.add_argument("--scenes-dir", type=Path, default=Path("bench_scenes"))
    parser.add_argument("--out", type=Path, default=Path("compare_runs"))
    parser.add_argument(
        "--builds-dir", type=Path, default=Path.home() / ".cache" / "dvpmvs" / "builds"
    )
    parser.add_argument(
        "--keep-maps", action="store_true", help="keep every run's workspace (default: the last)"
    )
    parser.add_argument("--a-options", default="", help="dense options for the first build only")
    parser.add_argument("--b-options", default="", help="dense options for the second build only")
    parser.add_argument(
        "overrides", nargs="*", default=[], help="dense options for both builds, after --"
    )
    argv = list(sys.argv[1:] if argv is None else argv)
    # Everything after "--" is dense options: split there, since argparse cannot give the trailing
    # positional its words once the options sit between it and the builds.
    overrides = argv[argv.index("--") + 1 :] if "--" in argv else []
    args = parser.parse_args(argv[: argv.index("--")] if "--" in argv else argv)
    args.overrides = args.overrides + overrides
    own_options = [args.a_options.split(), args.b_options.split()]

    from dvpmvs.evaluation.bench import render_scene
    from dvpmvs.evaluation.scene_digest import scene_key

    builds = [resolve(spec, args.builds_dir) for spec in args.builds]
    for build, options in zip(builds, own_options):
        if options:
            build.spec = f"{build.spec} {' '.join(options)}"
    out = args.out.resolve()
    out.mkdir(parents=True, exist_ok=True)
    scenes = [s for s in args.scenes.split(",") if s]
    results: dict[tuple[str, int], list[dict]] = {}
    same: dict[str, bool] = {}
    for index, scene in enumerate(scenes):
        rendered = render_scene(
            args.scenes_dir / scene_key(scene, args.views, args.width, args.scene_seed),
            scene,
            args.views,
            args.width,
            args.scene_seed,
        )
        maps = {}
        for repeat in range(args.repeats):
            order = [0, 1] if (index + repeat) % 2 == 0 else [1, 0]
            for b in order:
                build = builds[b]
                run_dir = out / scene / f"build{b}-run{repeat}"
                workspace = copy_scene(rendered, run_dir / "workspace")
                started = time.strftime("%H:%M:%S")
                result = _run(
                    build,
                    workspace,
                    run_dir / "report.json",
                    args.threads,
                    args.overrides + own_options[b],
                )
                per_view = _per_view(result)
                print(
                    f"{started} {scene:9s} {build.label:28s} {per_view['total']:7.2f} s / view "
                    f"(photometric {per_view.get('photometric', 0):.2f}, geometric "
                    f"{per_view.get('geometric', 0):.2f}, priors {per_view['priors']:.2f}; wall "
                    f"{per_view['wall']:.2f}), {result['simd']}, peak {result['peak_rss_mb']:.0f} MB",
                    flush=True,
                )
                results.setdefault((scene, b), []).append(result)
                maps.setdefault(b, _maps(workspace))
                if not args.keep_maps and repeat < args.repeats - 1:
                    shutil.rmtree(workspace)
        # None: the builds ran with other options, so their maps are not expected to agree.
        same[scene] = (
            (maps[0] == maps[1] and len(maps[0]) > 0) if own_options[0] == own_options[1] else None
        )
    _report(builds, scenes, results, same, out, args.threads)
    return 0


def _same(value: bool | None) -> str:
    return "-" if value is None else ("yes" if value else "NO")


def _mean(values: list[float]) -> float:
    return sum(values) / len(values) if values else 0.0


def _report(
    builds: list[Build], scenes: list[str], results: dict, same: dict, out: Path, threads: int
) -> None:
    lines = [
        f"# dvpmvs compare: {builds[0].label} (A) against {builds[1].label} (B)",
        "",
        "| scene | A s / view | B s / view | A / B | photometric A / B | geometric A / B | same maps |",
        "|---|---|---|---|---|---|---|",
    ]
    totals = {0: [], 1: []}
    for scene in scenes:
        rows = {b: [_per_view(r) for r in results[(scene, b)]] for b in (0, 1)}
        t = {b: _mean([r["total"] for r in rows[b]]) for b in (0, 1)}
        photometric = {b: _mean([r.get("photometric", 0) for r in rows[b]]) for b in (0, 1)}
        geometric = {b: _mean([r.get("geometric", 0) for r in rows[b]]) for b in (0, 1)}
        for b in (0, 1):
            totals[b].append(t[b])
        lines.append(
            f"| {scene} | {t[0]:.2f} | {t[1]:.2f} | {t[0] / t[1]:.3f} | "
            f"{photometric[0] / photometric[1]:.3f} | "
            f"{(geometric[0] / geometric[1]) if geometric[1] else float('nan'):.3f} | "
            f"{_same(same[scene])} |"
        )
    a, b = _mean(totals[0]), _mean(totals[1])
    lines.append(
        f"| **mean** | {a:.2f} | {b:.2f} | **{a / b:.3f}** | | | "
        f"{_same(None if None in same.values() else all(same.values()))} |"
    )
    lines += [
        "",
        "Seconds per view: both passes of the estimator plus the priors and segmentation "
        "(fusion and I/O not included). Peak memory per run:",
    ]
    for index, build in enumerate(builds):
        peaks = [r["peak_rss_mb"] for scene in scenes for r in results[(scene, index)]]
        simd = {r["simd"] for scene in scenes for r in results[(scene, index)]}
        lines.append(
            f"- {'AB'[index]} ({build.label}, vector path {', '.join(sorted(simd))}): "
            f"{max(peaks):.0f} MB"
        )
    for index, build in enumerate(builds):
        work = _work([r for scene in scenes for r in results[(scene, index)]])
        lines += ["", f"What {'AB'[index]}'s estimator matched per pixel ({build.label}):", ""]
        if not work:
            lines.append("(this build does not count its work)")
            continue
        lines += [
            "| pass | level | size | hypotheses | windows | samples |",
            "|---|---|---|---|---|---|",
        ]
        lines += [
            f"| {p} | {i} | {size} | {h:.1f} | {w:.0f} | {s:,.0f} |" for p, i, size, h, w, s in work
        ]
        passes, kernels = _per_sample(
            [r for scene in scenes for r in results[(scene, index)]], threads
        )
        ghz = _nominal_ghz()
        cycles = (
            f" ({passes * ghz:.1f} and {kernels * ghz:.1f} cycles at the nominal {ghz:.2f} GHz)"
            if ghz
            else ""
        )
        lines += [
            "",
            f"CPU time per sample matched: {passes:.2f} ns for both passes, {kernels:.2f} ns in their "
            f"sweeps and initialisations (the matching and the work around each window){cycles}.",
        ]
    for index, build in enumerate(builds):
        lines += [
            "",
            f"Where {'AB'[index]}'s time goes ({build.label}; shares of the seconds per view above):",
            "",
            "| pass / kernel call | seconds | share |",
            "|---|---|---|",
        ]
        for name, seconds, share in _shares(
            [r for scene in scenes for r in results[(scene, index)]]
        )[:14]:
            lines.append(f"| {name} | {seconds:.1f} | {100 * share:.1f} % |")
    text = "\n".join(lines) + "\n"
    (out / "report.md").write_text(text)
    (out / "report.json").write_text(
        json.dumps(
            {
                "builds": [b.__dict__ for b in builds],
                "same_maps": same,
                "results": {
                    f"{scene}/{b}": results[(scene, b)] for scene in scenes for b in (0, 1)
                },
            },
            indent=1,
        )
    )
    print("\n" + text + f"(also {out / 'report.md'})")


if __name__ == "__main__":
    sys.exit(main())
