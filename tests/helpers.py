"""What several test modules share: the command as a user types it, and the documents' commands."""

from __future__ import annotations

import atexit
import fcntl
import functools
import importlib.util
import os
import re
import shlex
import shutil
import subprocess
import sys
from collections.abc import Callable
from contextlib import contextmanager
from pathlib import Path

import pytest

from tests.command_server import CommandServer

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
DOCS = [README, *sorted((ROOT / "docs").glob("*.md"))]


def dvpmvs(*args, cwd, **kwargs) -> subprocess.CompletedProcess:
    """``python -m dvpmvs.cli ARGS`` in a process of its own, as from a shell, with its output
    captured as text.

    The process is forked from the worker's command server (:mod:`tests.command_server`), which
    has done the imports a new interpreter would do first; with other ``subprocess.run`` keywords,
    or an environment the server cannot give, it is a new interpreter. ``cwd`` is required: a
    test runs it in its own folder (outside the repository, so that the installed package is what
    runs and nothing lands in the checkout)."""
    if not kwargs and command_server().can_run(dict(os.environ)):
        return command_server().run(_CLI_FILE, [str(a) for a in args], cwd, module="cwd")
    return subprocess.run(
        [sys.executable, "-m", "dvpmvs.cli", *args],
        capture_output=True,
        text=True,
        cwd=cwd,
        **kwargs,
    )


def shell(command: str, cwd: Path, env: dict[str, str]) -> subprocess.CompletedProcess:
    """``bash -c COMMAND`` in ``cwd`` with ``env``, its output captured as text. A simple
    ``dvpmvs`` command (no operator, redirection or assignment) has its words expanded by bash
    (quotes, variables, globs) and runs as the console script, forked from the command server
    as :func:`dvpmvs` runs its commands."""
    lexer = shlex.shlex(command, posix=True, punctuation_chars=True)
    lexer.whitespace_split = True
    tokens = list(lexer)
    program = shutil.which("dvpmvs", path=env.get("PATH"))
    if (
        tokens
        and tokens[0] == "dvpmvs"
        and program
        and not any(set(t) <= set("();<>|&") for t in tokens)
        and command_server().can_run(env)
    ):
        words = subprocess.run(
            ["bash", "-c", f"printf '%s\\0' {command}"], cwd=cwd, env=env, capture_output=True
        )
        if words.returncode == 0 and words.stdout.split(b"\0")[0] == b"dvpmvs":
            args = [w.decode() for w in words.stdout.split(b"\0")[1:-1]]
            return command_server().run(program, args, cwd, env=env)
    return subprocess.run(["bash", "-c", command], cwd=cwd, env=env, capture_output=True, text=True)


_CLI_FILE = importlib.util.find_spec(
    "dvpmvs.cli"
).origin  # sys.argv[0] under ``python -m dvpmvs.cli``


@functools.cache
def command_server() -> CommandServer:
    """This process's command server, stopped when the process ends."""
    server = CommandServer()
    atexit.register(server.close)
    return server


def dvpmvs_here(*args, cwd) -> subprocess.CompletedProcess:
    """``dvpmvs ARGS`` run in this process (:func:`dvpmvs.cli.main`, the entry point the command
    calls), its output captured as text, in ``cwd``.

    For the many cases of bad input, which stop at the checks before anything is computed: the
    same code path as :func:`dvpmvs` without an interpreter's start and the imports per case. An
    exception the command lets out is printed as Python prints it, with status 1, as from a shell.
    The logging configuration Hydra sets up for the command is undone afterwards."""
    import contextlib
    import io
    import logging
    import traceback

    from dvpmvs.cli import main

    root, ours = logging.getLogger(), logging.getLogger("dvpmvs")
    handlers, levels = root.handlers[:], (root.level, ours.level)
    out, err = io.StringIO(), io.StringIO()
    here = os.getcwd()
    os.chdir(cwd)
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            try:
                code = main([str(arg) for arg in args])
            except SystemExit as stop:
                if stop.code is None or isinstance(stop.code, int):
                    code = stop.code or 0
                else:  # sys.exit("message"): printed, status 1
                    print(stop.code, file=sys.stderr)
                    code = 1
            except Exception:
                traceback.print_exc()
                code = 1
    finally:
        os.chdir(here)
        root.handlers[:] = handlers
        root.setLevel(levels[0])
        ours.setLevel(levels[1])
    return subprocess.CompletedProcess(
        ["dvpmvs", *map(str, args)], code, out.getvalue(), err.getvalue()
    )


def built_once(tmp_path_factory, name: str, build: Callable[[Path], None]) -> Path:
    """The folder ``name`` that ``build`` fills once for the whole pytest run.

    pytest-xdist's workers share it: the first to ask builds it under a lock, the others wait and
    read it; without xdist it is the run's own. A module fixture built this way is not built again
    by each worker that runs one of its tests. The tests that use it only read it (one that changes
    it works on a copy)."""
    base = tmp_path_factory.getbasetemp()
    shared = base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base
    folder, done = shared / name, shared / f"{name}.done"
    with open(shared / f"{name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        try:
            if not done.is_file():
                shutil.rmtree(folder, ignore_errors=True)
                folder.mkdir()
                build(folder)
                done.touch()
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)
    return folder


def code_blocks(doc: Path, language: str = "bash") -> list[str]:
    """The text of a document's fenced blocks of ``language``, in order."""
    return re.findall(rf"^```{language}\n(.*?)^```", doc.read_text(), re.M | re.S)


def block_commands(block: str) -> list[str]:
    """The shell commands of a block: continuation lines joined, comments and blank lines dropped."""
    commands = []
    for line in block.replace("\\\n", " ").splitlines():
        words = shlex.split(line, comments=True)
        if words:
            commands.append(join_words(words))
    return commands


def documented_commands(doc: Path) -> list[str]:
    """The shell commands of a document's ``bash`` blocks."""
    return [command for block in code_blocks(doc) for command in block_commands(block)]


def join_words(words: list[str]) -> str:
    """A command line from its words, quoted where the shell needs it; variables (``$PEERS``),
    globs (``multirun/bench-*``) and ``&&`` / ``&`` are left for the shell, as the documents mean."""
    return " ".join(
        word
        if word in ("&&", "&") or re.fullmatch(r"[\w@%+=:,./$*-]+", word)
        else shlex.quote(word)
        for word in words
    )


@contextmanager
def read_only(*folders: Path):
    """Folders nobody may write into: permissions for a user; for root (whom permissions do not
    stop) the immutable attribute, where the file system has one."""
    root = os.geteuid() == 0
    if root and shutil.which("chattr") is None:
        pytest.skip("root writes into read-only folders, and chattr is missing")
    for folder in folders:
        if root:
            if subprocess.run(["chattr", "+i", str(folder)], capture_output=True).returncode:
                pytest.skip(f"the file system of {folder} has no immutable attribute")
        else:
            folder.chmod(0o555)
    try:
        yield
    finally:
        for folder in folders:
            if root:
                subprocess.run(["chattr", "-i", str(folder)], check=True)
            else:
                folder.chmod(0o755)
