"""Every time (and memory) the documents state holds within 2x of its measurement.

A statement carries the measurement it rests on right after it, ``<!-- measured: KEY -->`` (or
``<!-- measured: KEY peak_rss_mb -->`` for memory); ``scripts/measure_stated_times.py`` measures
each KEY on a fresh clone of an idle 2-core machine into ``docs/measured_times.json``. Nothing is
timed here: the test compares the words with the record, and finds the time statements that name
no measurement. docs/benchmarks.md is not read: its figures stand beside the commands that
produce them.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from tests.helpers import DOCS, ROOT

RECORD = ROOT / "docs" / "measured_times.json"
STATED_IN = [doc for doc in DOCS if doc.name != "benchmarks.md"]
# "about 30 s", "1 min 41 s", "under a minute", "2.2 GB", each maybe followed by its marker.
_QUANTITY = (
    r"(?:(?P<minutes>\d+) min (?P<seconds>\d+) s"
    r"|(?P<value>\d+(?:\.\d+)?|a|an) (?P<unit>s|seconds?|min|minutes?|hours?|GB|MB)\b)"
)
_STATEMENT = re.compile(
    rf"(?P<under>under )?(?P<about>about )?{_QUANTITY}"
    r"(?:<!-- measured: (?P<key>\w+)(?: (?P<field>\w+))? -->)?"
)
# A duration the text gives as a rule, not as a measurement: a heartbeat's or a timeout's period.
_RULE = re.compile(r"(every|within|at least every|for) $")
_SCALE = {"s": 1, "second": 1, "min": 60, "minute": 60, "hour": 3600, "GB": 1024, "MB": 1}


def _prose(doc: Path) -> str:
    """The document without its code blocks and inline code (commands, not statements)."""
    text = re.sub(r"^```.*?^```", "", doc.read_text(), flags=re.M | re.S)
    return re.sub(r"`[^`\n]*`", "", text)


def _amount(match: re.Match) -> float:
    """Seconds (or MB) a statement gives."""
    if match["minutes"]:
        return 60 * int(match["minutes"]) + int(match["seconds"])
    value = 1.0 if match["value"] in ("a", "an") else float(match["value"])
    return value * _SCALE[match["unit"].rstrip("s") or "s"]


def _statements() -> list[tuple[Path, re.Match]]:
    found = []
    for doc in STATED_IN:
        text = _prose(doc)
        for match in _STATEMENT.finditer(text):
            is_article = match["value"] in ("a", "an")
            approximate = match["under"] or match["about"]
            if is_article and match["unit"] not in ("minute", "hour") and not approximate:
                continue  # "a second run" is an ordinal, not a time
            if match["unit"] in ("GB", "MB") and not match["key"]:
                continue  # sizes of files and data sets are not measured times
            if not match["key"] and _RULE.search(text[max(0, match.start() - 20) : match.start()]):
                continue
            found.append((doc, match))
    return found


def test_every_stated_time_names_its_measurement():
    unmarked = [
        f"{doc.name}: {match.group(0)!r}" for doc, match in _statements() if not match["key"]
    ]
    assert not unmarked, (
        "time statements without <!-- measured: KEY --> after them (measure them with "
        f"scripts/measure_stated_times.py, or say no time): {unmarked}"
    )


def test_every_stated_time_holds_within_2x_of_its_measurement():
    steps = json.loads(RECORD.read_text())["steps"]
    marked = [(doc, match) for doc, match in _statements() if match["key"]]
    assert len(marked) >= 5  # the demo, the setup, the suites, the tutorial's commands
    wrong = []
    for doc, match in marked:
        step = steps.get(match["key"])
        if step is None:
            wrong.append(f"{doc.name}: {match.group(0)!r} names no measurement in {RECORD.name}")
            continue
        assert step["machine"]["cores"] == 2 and step["load_before"] <= 0.5, (
            f"{match['key']} was not measured on an idle 2-core machine: {step}"
        )
        measured = step[match["field"] or "seconds"]
        stated = _amount(match)
        holds = measured <= stated if match["under"] else 0.5 <= stated / measured <= 2
        if not holds:
            wrong.append(f"{doc.name}: {match.group(0)!r}, measured {measured}")
    assert not wrong, wrong


def test_the_setup_steps_say_how_long_they_take_as_measured():
    # make setup's steps announce their time: each within 2x of the step's own measured time.
    stages = json.loads(RECORD.read_text())["steps"]["setup"]["stages"]
    announced = re.findall(r'echo "setup (\d/\d): ([^"]*)"', (ROOT / "Makefile").read_text())
    checked = 0
    for step, text in announced:
        match = _STATEMENT.search(text)
        if match is None:
            continue
        checked += 1
        stated, measured = _amount(match), max(stages[step], 1.0)
        assert 0.5 <= stated / measured <= 2, (
            f"setup {step}: {match.group(0)!r}, measured {measured}"
        )
    assert checked == 2  # the virtual environment, the packages (apt's time depends on the machine)


@pytest.mark.parametrize(
    ("text", "amount"),
    [("about 30 s", 30), ("1 min 41 s", 101), ("under a minute", 60), ("2.2 GB", 2252.8)],
)
def test_statements_read_as_amounts(text, amount):
    match = _STATEMENT.search(text)
    assert match is not None and _amount(match) == pytest.approx(amount)
