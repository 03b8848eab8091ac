"""The checks that run before any compute: option types, thread counts, writable outputs."""

import math
import os
from dataclasses import dataclass

import pytest

from dvpmvs.validation import (
    OutputNotWritableError,
    check_field_types,
    check_ply_output,
    check_threads,
    check_value,
    check_writable,
    max_threads,
)


@pytest.mark.parametrize(
    "value,allowed,message",
    [
        (1, (bool,), "must be true or false, got 1"),
        ("yes", (bool,), "must be true or false, got 'yes'"),
        (2.5, (int,), "must be an integer, got 2.5"),
        (True, (int,), "must be an integer, got True"),
        (math.nan, (float,), "must be a number, got nan"),
        (None, (int, float), "must be an integer or a number, got None"),
    ],
)
def test_a_value_of_another_type_is_refused_with_its_name(value, allowed, message):
    with pytest.raises(ValueError, match=f"^patch_match.x {message}$"):
        check_value("patch_match.x", value, allowed)


def test_integers_are_numbers_and_none_is_allowed_only_where_declared():
    assert check_value("x", 1, (float,)) == 1.0 and isinstance(check_value("x", 1, (float,)), float)
    assert check_value("x", None, (int, type(None))) is None
    assert check_value("x", "a", (str,)) == "a"


@dataclass(frozen=True)
class _Options:
    perturbation: float = 0.02
    iterations: int = 3
    name: str | None = None
    matrix: tuple = ()  # left to the options themselves


def test_the_fields_of_an_options_object_are_checked_and_normalised_by_their_annotations():
    options = _Options(perturbation=1)
    check_field_types(options)
    assert options.perturbation == 1.0 and isinstance(options.perturbation, float)
    check_field_types(_Options(matrix=("anything",)))
    with pytest.raises(ValueError, match="^pm.iterations must be an integer, got 2.5$"):
        check_field_types(_Options(iterations=2.5), prefix="pm.")


def test_thread_counts_are_zero_for_every_core_or_a_few_per_core():
    check_threads("num_threads", 0)
    check_threads("num_threads", max_threads())
    with pytest.raises(ValueError, match="num_threads must be >= 0"):
        check_threads("num_threads", -1)
    with pytest.raises(ValueError, match=f"it has {os.cpu_count()} cores"):
        check_threads("num_threads", max_threads() + 1)


def test_an_output_that_cannot_be_written_is_named_before_any_compute(tmp_path):
    check_writable(tmp_path / "new" / "folder", "the output folder")
    assert (tmp_path / "new" / "folder").is_dir() and not list(
        (tmp_path / "new" / "folder").iterdir()
    )
    (tmp_path / "file").write_text("x")
    with pytest.raises(
        OutputNotWritableError, match="the output folder .*file is a file, not a folder; use out="
    ):
        check_writable(tmp_path / "file", "the output folder", "use out=")
    if os.geteuid() != 0:  # root writes anywhere
        locked = tmp_path / "locked"
        locked.mkdir(mode=0o555)
        with pytest.raises(OutputNotWritableError, match="cannot write to"):
            check_writable(locked, "the output folder")


def test_a_ply_output_is_a_ply_file_in_a_writable_folder(tmp_path):
    check_ply_output(tmp_path / "cloud.PLY", "fused clouds", "fused.ply")
    with pytest.raises(OutputNotWritableError, match=r"is a folder; .* e\.g\. output=.*fused\.ply"):
        check_ply_output(tmp_path, "fused clouds", "fused.ply")
    with pytest.raises(OutputNotWritableError, match="fused clouds are written as binary PLY"):
        check_ply_output(tmp_path / "cloud.xyz", "fused clouds", "fused.ply")


def test_zero_threads_resolve_to_every_core_shared_between_jobs():
    from dvpmvs.validation import resolve_threads

    cores = os.cpu_count() or 1
    assert resolve_threads(3) == 3 and resolve_threads(3, shared_by=2) == 3
    assert resolve_threads(0) == cores
    assert resolve_threads(0, shared_by=2) == max(1, cores // 2)
    assert resolve_threads(0, shared_by=cores * 4) == 1
