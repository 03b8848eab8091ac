"""``dvpmvs`` commands in processes forked from one that has already imported what they import.

A command run by a test costs about a second before it does anything: the interpreter starts and
imports numpy, SciPy, OpenCV, pycolmap, Hydra and dvpmvs. The suite runs a few hundred of them.
This module, run as a script, is a server that imports those once and then forks one child per
command; :class:`CommandServer` is its client. The child is a process of its own, as a command
typed in a shell is: it changes folder, takes the command's environment and standard streams,
runs :func:`dvpmvs.cli.main` with ``sys.argv`` as the command line sets it, and exits as the
interpreter exits (an escaping exception printed with status 1, ``atexit`` handlers and
non-daemon threads waited for).

What a forked child cannot have is what is read while the libraries load: OpenMP's and the BLAS
libraries' thread settings, Python's own variables. A command whose environment differs from the
server's in one of those (:data:`READ_AT_LOAD`) is run by the client as a new interpreter
instead, and so is every command of the tests that check what a command imports or how it starts.
The server forks only while it has a single thread (libraries that start threads when they load
would leave a child with locks nobody releases): it refuses to start otherwise.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
from pathlib import Path

# Environment variables read while a library or the interpreter loads: a child cannot take them
# from its command's environment, the server's own values hold in it.
READ_AT_LOAD = (
    "OMP_",
    "GOMP_",
    "KMP_",
    "OPENBLAS_",
    "MKL_",
    "BLIS_",
    "NUMEXPR_",
    "PYTHON",
    "LD_",
    "DVPMVS_",
    "MALLOC_",
    "OPENCV_",
)

# What a dense, fusion or evaluation command imports before it computes (the evaluation harness
# and Open3D excepted: tests check that some commands do without them, and a child imports them
# itself where its command needs them).
PRELOADED = (
    "dvpmvs.cli",
    "numpy",
    "scipy.spatial",
    "scipy.ndimage",
    "scipy.interpolate",
    "cv2",
    "pycolmap",
    "hydra",
    "hydra.compose",
    "hydra.core.override_parser.overrides_parser",
    "omegaconf",
    "rich.console",
    "tqdm",
    "plyfile",
    "dvpmvs.run",
    "dvpmvs.config",
    "dvpmvs.dense",
    "dvpmvs.report",
    "dvpmvs.sweep",
    "dvpmvs.patchmatch._patchmatch",
    "dvpmvs._image",
    "dvpmvs._fusion",
)


def _differs_at_load(env: dict[str, str], base: dict[str, str]) -> bool:
    keys = {k for k in env.keys() | base.keys() if k.startswith(READ_AT_LOAD)}
    return any(env.get(k) != base.get(k) for k in keys)


class CommandServer:
    """A server process (started on first use) and the commands it runs; one command at a time.

    ``run(argv0, args, cwd, env)`` returns a :class:`subprocess.CompletedProcess` as
    ``subprocess.run(..., capture_output=True, text=True)`` would for the same command."""

    def __init__(self):
        self._process: subprocess.Popen | None = None
        self._env: dict[str, str] | None = None
        self._lock = threading.Lock()

    def _start(self) -> None:
        self._env = dict(os.environ)
        self._process = subprocess.Popen(
            [sys.executable, __file__],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            env=self._env,
            cwd="/",
        )
        ready = self._process.stdout.readline()
        if json.loads(ready or b"null") != "ready":
            self._process.wait()
            raise RuntimeError(f"the command server did not start: {ready!r}")

    def can_run(self, env: dict[str, str]) -> bool:
        return not _differs_at_load(env, self._env if self._env is not None else dict(os.environ))

    def run(
        self,
        argv0: str,
        args: list[str],
        cwd: Path,
        env: dict[str, str] | None = None,
        module: str | None = None,
    ) -> subprocess.CompletedProcess:
        """``args`` run by ``dvpmvs.cli.main`` with ``sys.argv = [argv0, *args]``; ``module`` the
        name of ``sys.path[0]``'s kind: ``"cwd"`` as ``python -m`` puts the folder first, else
        the folder of ``argv0`` as a script puts its own."""
        import tempfile

        env = dict(os.environ if env is None else env)
        with self._lock:
            if self._process is None or self._process.poll() is not None:
                self._start()
            with tempfile.TemporaryDirectory(prefix="dvpmvs-command-") as folder:
                out, err = Path(folder, "out"), Path(folder, "err")
                request = {
                    "argv": [argv0, *map(str, args)],
                    "cwd": str(cwd),
                    "env": env,
                    "out": str(out),
                    "err": str(err),
                    "path0": str(Path(cwd).resolve())
                    if module == "cwd"
                    else str(Path(argv0).resolve().parent),
                }
                self._process.stdin.write(json.dumps(request).encode() + b"\n")
                self._process.stdin.flush()
                reply = self._process.stdout.readline()
                if not reply:
                    raise RuntimeError("the command server stopped")
                status = json.loads(reply)["status"]
                return subprocess.CompletedProcess(
                    request["argv"],
                    status,
                    out.read_text(errors="replace"),
                    err.read_text(errors="replace"),
                )

    def close(self) -> None:
        if self._process is not None and self._process.poll() is None:
            self._process.stdin.close()
            self._process.wait(timeout=60)


def _exit_status(wait_status: int) -> int:
    """As :attr:`subprocess.Popen.returncode`: the exit code, or minus the signal's number."""
    return os.waitstatus_to_exitcode(wait_status)


def _child(request: dict, protocol: tuple) -> None:
    """In the forked child: the command's folder, environment and streams, then its run. Returns
    only by raising SystemExit (or an exception), which the interpreter turns into the exit."""
    import random

    import numpy as np

    for stream in protocol:
        stream.close()
    # A new interpreter seeds these from the system; a forked child would share the server's.
    random.seed()
    np.random.seed()
    os.chdir(request["cwd"])
    os.environ.clear()
    os.environ.update(request["env"])
    null = os.open(os.devnull, os.O_RDONLY)
    out = os.open(request["out"], os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    err = os.open(request["err"], os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    for source, target in ((null, 0), (out, 1), (err, 2)):
        os.dup2(source, target)
        os.close(source)
    sys.stdout = (
        sys.__stdout__
    )  # the server pointed it at stderr; descriptor 1 is now the command's
    sys.argv = request["argv"]
    sys.path[0] = request["path0"]
    from dvpmvs.cli import main

    sys.exit(main())


def serve() -> None:
    import importlib

    # The protocol's streams get descriptors of their own; 0 and 1 are the commands' to take.
    requests = os.fdopen(os.dup(0), "rb")
    replies = os.fdopen(os.dup(1), "wb")
    sys.stdout = sys.stderr  # nothing the libraries print may reach the protocol
    for name in PRELOADED:
        importlib.import_module(name)
    threads = (
        len(os.listdir("/proc/self/task"))
        if os.path.isdir("/proc/self/task")
        else threading.active_count()
    )
    if threads != 1:
        replies.write(
            json.dumps(f"{threads} threads after the imports: forking is not safe").encode() + b"\n"
        )
        replies.flush()
        return
    replies.write(b'"ready"\n')
    replies.flush()
    for line in requests:
        request = json.loads(line)
        sys.stderr.flush()
        pid = os.fork()
        if pid == 0:
            _child(request, (requests, replies))
        _, wait_status = os.waitpid(pid, 0)
        replies.write(json.dumps({"status": _exit_status(wait_status)}).encode() + b"\n")
        replies.flush()


if __name__ == "__main__":
    serve()
