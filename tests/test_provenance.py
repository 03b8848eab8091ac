"""Provenance records: fingerprints, the status of outputs on disk, and the map cache."""

import math
import os

import numpy as np
import pytest

from dvpmvs.provenance import (
    MapCache,
    Record,
    Status,
    code_identity,
    read_record,
    record_path,
    stamp_files,
    status,
    write_record,
)


def test_code_identity_names_the_kernels_and_libraries():
    code = code_identity()
    assert len(code["sources"]) == 64
    assert set(code["kernels"]) >= {"dvpmvs.patchmatch._patchmatch", "dvpmvs._fusion"}
    assert all(len(d) == 64 for d in code["kernels"].values())
    assert code["libraries"]["numpy"] == np.__version__


def _outputs(folder, content=b"map"):
    paths = {"depth": folder / "depth_maps" / "v.bin", "normal": folder / "normal_maps" / "v.bin"}
    for path in paths.values():
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(content)
    return paths


def test_status_tells_every_state_of_a_view(tmp_path):
    files = {"depth": tmp_path / "depth_maps" / "v.bin"}
    assert status(None, "f", tmp_path, files.values()) is Status.MISSING
    paths = _outputs(tmp_path)
    assert status(None, "f", tmp_path, paths.values()) is Status.FOREIGN
    assert status(Record("f", {}), "f", tmp_path, paths.values()) is Status.INTERRUPTED
    record = Record("f", {"x": 1}, True, stamp_files(tmp_path, paths))
    assert status(record, "f", tmp_path, paths.values()) is Status.CURRENT
    assert status(record, "g", tmp_path, paths.values()) is Status.STALE
    # A copy with a new modification time is the same map; other bytes are not.
    os.utime(paths["depth"], ns=(1, 1))
    assert status(record, "f", tmp_path, paths.values()) is Status.CURRENT
    paths["normal"].write_bytes(b"mop")
    assert status(record, "f", tmp_path, paths.values()) is Status.MODIFIED
    paths["normal"].unlink()
    assert status(record, "f", tmp_path, paths.values()) is Status.MODIFIED


def test_records_round_trip_and_an_unreadable_one_reads_as_unfinished(tmp_path):
    path = record_path(tmp_path, "0001.png", "photometric")
    assert path == tmp_path / "provenance" / "0001.png.photometric.json"
    assert read_record(path) is None
    write_record(path, Record("f", {"x": math.inf}, True, {}, ["a.png"], {"seconds": 1.5}))
    back = read_record(path)
    assert (back.fingerprint, back.inputs, back.complete, back.extras, back.stats) == (
        "f",
        {"x": "inf"},
        True,
        ["a.png"],
        {"seconds": 1.5},
    )
    path.write_text("{not json")
    unreadable = read_record(path)
    assert not unreadable.complete and status(unreadable, "f", tmp_path, []) is Status.INTERRUPTED


def test_the_cache_links_whole_entries_and_ignores_damaged_ones(tmp_path):
    cache = MapCache(tmp_path / "cache")
    one, two = tmp_path / "one", tmp_path / "two"
    paths = _outputs(one)
    preview = one / "previews" / "v.png"
    preview.parent.mkdir()
    preview.write_bytes(b"png")
    record = Record("ab" * 32, {"x": 1}, True, stamp_files(one, paths), stats={"seconds": 3.0})
    targets = {kind: two / path.relative_to(one) for kind, path in paths.items()}
    assert cache.fetch("photometric", record.fingerprint, two, targets, {}) is None
    cache.store("photometric", record, one, {"v.png": preview})
    cache.store("photometric", record, one, {"v.png": preview})  # a second store changes nothing
    fetched = cache.fetch(
        "photometric", record.fingerprint, two, targets, {"v.png": two / "previews" / "v.png"}
    )
    assert (
        fetched.complete
        and fetched.stats == {"seconds": 3.0}
        and fetched.extras == ["previews/v.png"]
    )
    assert targets["depth"].stat().st_ino == paths["depth"].stat().st_ino
    assert status(fetched, record.fingerprint, two, targets.values()) is Status.CURRENT
    # Another fingerprint misses; a damaged entry is not served.
    assert cache.fetch("photometric", "cd" * 32, two, targets, {}) is None
    entry = next((tmp_path / "cache" / "photometric").rglob("depth.bin"))
    os.unlink(entry)
    entry.write_bytes(b"xxx")
    assert cache.fetch("photometric", record.fingerprint, tmp_path / "three", targets, {}) is None


def test_a_cache_that_is_a_file_is_refused_before_anything_runs(tmp_path):
    from dvpmvs.errors import DvpmvsError

    (tmp_path / "file").write_text("x")
    with pytest.raises(DvpmvsError, match="is a file; cache= names a folder"):
        MapCache(tmp_path / "file")


def test_a_cached_output_is_current_only_for_its_inputs_and_a_failed_remake_keeps_the_old_record(
    tmp_path,
):
    from dvpmvs.provenance import CachedOutput

    out = tmp_path / "mesh.ply"
    record_file = tmp_path / "mesh.ply.provenance.json"
    first = CachedOutput.check(record_file, {"cloud": "a"}, tmp_path, [out])
    assert first.current is None and first.state is Status.MISSING
    with first.making():
        assert read_record(record_file).complete is False  # pending while it is made
        out.write_bytes(b"mesh")
    first.complete({"mesh": out}, {"triangles": 3})
    again = CachedOutput.check(record_file, {"cloud": "a"}, tmp_path, [out])
    assert again.current is not None and again.current.stats == {"triangles": 3}
    other = CachedOutput.check(record_file, {"cloud": "b"}, tmp_path, [out])
    assert other.current is None and other.state is Status.STALE
    with pytest.raises(RuntimeError):
        with other.making():
            raise RuntimeError("the remake failed")
    assert CachedOutput.check(record_file, {"cloud": "a"}, tmp_path, [out]).current is not None
    out.write_bytes(b"edited")
    assert CachedOutput.check(record_file, {"cloud": "a"}, tmp_path, [out]).state is Status.MODIFIED


def test_an_output_without_a_record_is_replaced_only_when_asked(tmp_path):
    from dvpmvs.provenance import CachedOutput, ForeignOutputError, Status

    output = tmp_path / "mesh.ply"
    output.write_bytes(b"someone else's")
    cached = CachedOutput.check(tmp_path / "mesh.ply.provenance.json", {"a": 1}, tmp_path, [output])
    assert cached.state is Status.FOREIGN
    with pytest.raises(
        ForeignOutputError, match="mesh.ply exists and carries no dvpmvs provenance record"
    ):
        with cached.making():
            output.write_bytes(b"ours")
    assert output.read_bytes() == b"someone else's"
    with cached.making(overwrite=True):
        output.write_bytes(b"ours")
    cached.complete({"mesh": output}, {})
    again = CachedOutput.check(tmp_path / "mesh.ply.provenance.json", {"a": 2}, tmp_path, [output])
    assert again.state is Status.STALE
    with again.making():  # ours, out of date: replaced without asking
        pass
