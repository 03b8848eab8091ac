"""One timed ``dvpmvs dense`` run inside another build's interpreter (see :mod:`compare`).

Run as ``python -c "$(cat compare_worker.py)" REPORT.json dense workspace=... ...`` with the
interpreter of the build to time: it imports that build's dvpmvs, wraps the public functions of
the compiled kernel modules the estimator calls (and the estimator, the task that makes a view's
region labels, the planar prior and the filter) with a timer, as a profiler would, runs the
``dvpmvs`` command line with the arguments given and writes what it measured to REPORT.json. It
uses only what every build since the estimator's kernels were compiled modules provides, so that
old commits can be timed beside new ones; for builds older than the region labels' own task it
times their private ``_labels``, the only place those builds made them.
"""

import importlib
import json
import os
import resource
import sys
import time
import types


def _peak_memory_mb():
    """This program's peak resident memory: VmHWM, which starts anew when a process executes a
    program (getrusage's maxrss also counts the pages of the parent it was forked from)."""
    try:
        with open("/proc/self/status") as status:
            for line in status:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def main(report_path, argv):
    seconds = {}  # "pass/kernel" -> seconds
    views = []  # one entry per (view, pass) the estimator ran
    state = {"pass": "other"}

    def add(key, dt):
        seconds[key] = seconds.get(key, 0.0) + dt

    def timed(module, name, label):
        function = getattr(module, name)

        def wrapper(*args, **kwargs):
            start = time.perf_counter()
            try:
                return function(*args, **kwargs)
            finally:
                add(f"{state['pass']}/{label}", time.perf_counter() - start)

        setattr(module, name, wrapper)

    estimator = importlib.import_module("dvpmvs.patchmatch.estimator")
    # Where a view's task calls the estimator and the priors: dvpmvs.dense.view_maps; in older
    # builds dvpmvs.dense_view, or before it dvpmvs.pipeline.
    for where in ("dvpmvs.dense.view_maps", "dvpmvs.dense_view", "dvpmvs.pipeline"):
        try:
            pipeline = importlib.import_module(where)
            break
        except ImportError:
            continue
    for _attr, module in list(vars(estimator).items()):
        if isinstance(module, types.ModuleType) and str(getattr(module, "__file__", "")).endswith(
            (".so", ".pyd")
        ):
            for name, function in list(vars(module).items()):
                if (
                    callable(function)
                    and not isinstance(function, type)
                    and not name.startswith("_")
                ):
                    timed(module, name, name)
    # Public stages only: a private function is the build's own business (older builds also
    # timed _matching_images; their figures include it under "other").
    for name in ("planar_prior", "region_planes", "filter_estimate"):
        if hasattr(estimator, name):
            timed(estimator, name, name)
    # Where a view's priors and segmentation run: a task of their own
    # (dvpmvs.dense.tasks.compute_regions), or in older builds inside the view's maps (_labels).
    try:
        tasks = importlib.import_module("dvpmvs.dense.tasks")
    except ImportError:
        tasks = None
    if hasattr(tasks, "compute_regions"):
        regions_at, regions_name = tasks, "compute_regions"
    else:
        regions_at, regions_name = pipeline, "_labels"
    if hasattr(regions_at, regions_name):
        timed(regions_at, regions_name, "all")

    estimate = pipeline.estimate

    def timed_estimate(problem, options=None, pass_="photometric", *args, **kwargs):
        previous = state["pass"]
        state["pass"] = str(getattr(pass_, "value", pass_))
        start = time.perf_counter()
        result = None
        try:
            result = estimate(problem, options, pass_, *args, **kwargs)
            return result
        finally:
            dt = time.perf_counter() - start
            entry = {"view": problem.reference.name, "pass": state["pass"], "seconds": dt}
            # What the estimator matched per pyramid level (builds that count it).
            work = getattr(result, "work", None)
            if work:
                entry["work"] = [dict(vars(level)) for level in work]
            views.append(entry)
            state["pass"] = previous

    pipeline.estimate = timed_estimate
    labels = getattr(regions_at, regions_name, None)
    if labels is not None:

        def labels_in_pass(*args, **kwargs):
            # The kernels a prior provider calls (coarse_mvs runs the estimator) count as priors.
            previous = state["pass"]
            state["pass"] = "priors"
            try:
                return labels(*args, **kwargs)
            finally:
                state["pass"] = previous

        setattr(regions_at, regions_name, labels_in_pass)

    cli = importlib.import_module("dvpmvs.cli")
    kernel = importlib.import_module("dvpmvs.patchmatch._patchmatch")
    start = time.perf_counter()
    status = cli.main(list(argv))
    wall = time.perf_counter() - start
    dvpmvs = importlib.import_module("dvpmvs")

    report = {
        "status": status,
        "wall_seconds": wall,
        "views": views,
        "kernel_seconds": seconds,
        "simd": getattr(kernel, "SIMD", "scalar"),
        "package": os.path.dirname(dvpmvs.__file__),
        "peak_rss_mb": _peak_memory_mb(),
    }
    with open(report_path, "w") as handle:
        json.dump(report, handle, indent=1)
    return status


if __name__ == "__main__":
    sys.exit(main(sys.argv[1], sys.argv[2:]))
