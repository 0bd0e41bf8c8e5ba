"""The atomic writers of :mod:`calendaring.core.fileio`: a file appears complete under its
real name or not at all, and a failed write leaves what was there before."""

from __future__ import annotations

import os

import pytest

from calendaring.core.fileio import atomic_path, write_h5, write_text


def test_atomic_path_renames_on_success_and_leaves_no_temporary(tmp_path):
    path = tmp_path / "out.txt"
    with atomic_path(path) as tmp:
        assert tmp.parent == tmp_path and tmp.name == f".out.txt.tmp-{os.getpid()}"
        tmp.write_text("new")
        assert not path.exists()  # nothing under the real name until the block ends
    assert path.read_text() == "new"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.txt"]


def test_atomic_path_failure_keeps_the_old_file_and_removes_the_temporary(tmp_path):
    path = tmp_path / "out.txt"
    path.write_text("old")
    with pytest.raises(RuntimeError, match="interrupted"), atomic_path(path, fsync=True) as tmp:
        tmp.write_text("half")
        raise RuntimeError("interrupted")
    assert path.read_text() == "old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.txt"]


def test_atomic_path_keeps_the_previous_file_and_the_suffix_on_request(tmp_path):
    path, previous = tmp_path / "ck.h5", tmp_path / "ck.h5.prev"
    path.write_text("first")
    with atomic_path(path, previous=previous, keep_suffix=True) as tmp:
        assert tmp.name == f".ck.tmp-{os.getpid()}.h5"
        tmp.write_text("second")
    assert path.read_text() == "second" and previous.read_text() == "first"


def test_write_text_and_write_h5_go_through_it(tmp_path):
    write_text(tmp_path / "a" / "t.txt", "x")
    assert (tmp_path / "a" / "t.txt").read_text() == "x"

    def fill(f):
        f.attrs["k"] = 1
        raise OSError("disk full")

    (tmp_path / "r.h5").write_text("old")
    with pytest.raises(OSError, match="disk full"):
        write_h5(tmp_path / "r.h5", fill)
    assert (tmp_path / "r.h5").read_text() == "old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a", "r.h5"]
