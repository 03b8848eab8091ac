"""Fingerprints of input trees, and digests and stamps of files and source folders."""

import math
import os

import numpy as np
import pytest

from dvpmvs.digests import (
    canonical,
    differences,
    file_digest,
    file_stamp,
    fingerprint,
    matches_stamp,
    sources_digest,
)
from dvpmvs.passes import Pass


def test_fingerprints_ignore_key_order_and_spelling_but_not_values():
    a = {
        "patch_match": {"window_radius": 5, "limit": math.inf},
        "K": np.eye(3),
        "sources": ("a", "b"),
    }
    b = {
        "sources": ["a", "b"],
        "K": np.eye(3).tolist(),
        "patch_match": {"limit": float("inf"), "window_radius": 5},
    }
    assert fingerprint(a) == fingerprint(b)
    assert fingerprint(a) != fingerprint({**a, "sources": ("b", "a")})
    assert fingerprint(a) != fingerprint({**a, "patch_match": {"window_radius": 5, "limit": 1e30}})
    # Standard JSON: no Infinity literal in a record; enums and paths by their value.
    assert canonical({"x": -math.inf, "y": np.float32(0.5), "p": Pass.GEOMETRIC}) == {
        "x": "-inf",
        "y": 0.5,
        "p": "geometric",
    }
    with pytest.raises(TypeError):
        fingerprint({"x": object()})


def test_differences_name_the_changed_leaves():
    old = {"patch_match": {"a": 1, "b": 2}, "code": {"sources": "x"}}
    new = {"patch_match": {"a": 1, "b": 3, "c": True}, "code": {"sources": "x"}}
    assert differences(old, new) == [("patch_match.b", 2, 3), ("patch_match.c", None, True)]


def test_a_stamp_matches_a_copy_with_another_time_but_not_other_bytes(tmp_path):
    path = tmp_path / "map.bin"
    path.write_bytes(b"depth")
    stamp = file_stamp(path)
    assert (
        stamp["size"] == 5 and stamp["sha256"] == file_digest(path) and matches_stamp(path, stamp)
    )
    os.utime(path, ns=(1, 1))
    assert matches_stamp(path, stamp)  # same bytes, another time: the digest decides
    path.write_bytes(b"dopth")
    assert not matches_stamp(path, stamp)
    assert not matches_stamp(tmp_path / "missing.bin", stamp)


def test_file_digest_follows_the_content(tmp_path):
    path = tmp_path / "image.png"
    path.write_bytes(b"one")
    first = file_digest(path)
    path.write_bytes(b"two")
    assert file_digest(path) != first


def test_the_sources_digest_sees_sources_only_and_leaves_out_what_it_is_told(tmp_path):
    (tmp_path / "pkg").mkdir()
    (tmp_path / "pkg" / "a.py").write_text("x = 1\n")
    (tmp_path / "tests").mkdir()
    (tmp_path / "tests" / "t.py").write_text("y = 1\n")
    digest = sources_digest(tmp_path, exclude=("tests",))
    (tmp_path / "pkg" / "notes.txt").write_text("not a source")
    (tmp_path / "tests" / "t.py").write_text("y = 2\n")
    assert sources_digest(tmp_path, exclude=("tests",)) == digest
    (tmp_path / "pkg" / "_k.pyx").write_text("cdef int z\n")
    assert sources_digest(tmp_path, exclude=("tests",)) != digest
