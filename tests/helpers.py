"""What several test modules share: the command as a user types it, and the documents' commands."""

from __future__ import annotations

import fcntl
import os
import re
import shlex
import shutil
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
DOCS = [README, *sorted((ROOT / "docs").glob("*.md"))]


def dvpmvs(*args, cwd, **kwargs) -> subprocess.CompletedProcess:
    """``dvpmvs ARGS`` in a subprocess, as from a shell, with its output captured as text.

    ``cwd`` is required: a test runs it in its own folder (outside the repository, so that the
    installed package is what runs and nothing lands in the checkout)."""
    return subprocess.run([sys.executable, "-m", "dvpmvs.cli", *args], capture_output=True, text=True, cwd=cwd,
                          **kwargs)


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
    return " ".join(word if word in ("&&", "&") or re.fullmatch(r"[\w@%+=:,./$*-]+", word) else shlex.quote(word)
                    for word in words)
