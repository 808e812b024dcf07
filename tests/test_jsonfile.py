"""The runtime's JSON cache files: lenient reads, atomic writes that never leave a partial file."""
from clrf.runtime.jsonfile import read_dict, write_dict


def test_round_trip_and_lenient_reads(tmp_path):
    p = tmp_path / "sub" / "cache.json"
    assert read_dict(p) == {}                          # missing
    assert write_dict(p, {"a": 1, "b": [2, 3]}) is True
    assert read_dict(p) == {"a": 1, "b": [2, 3]}
    p.write_text("{not json")
    assert read_dict(p) == {}                          # corrupt
    p.write_text("[1, 2]")
    assert read_dict(p) == {}                          # not an object


def test_unwritable_cache_is_skipped_and_leaves_nothing(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    assert write_dict(blocker / "cache.json", {"a": 1}) is False   # parent is a file
    d = tmp_path / "d"
    d.mkdir()
    (d / "cache.json").mkdir()                         # the rename onto a directory fails
    assert write_dict(d / "cache.json", {"a": 1}) is False
    assert sorted(x.name for x in d.iterdir()) == ["cache.json"]     # no temporary file left
