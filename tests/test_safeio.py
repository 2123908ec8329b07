"""softcrawl.safeio: only regular files of bounded size and nesting are read; atomic writes."""

from __future__ import annotations

import os

import pytest

from softcrawl.safeio import (UnsafeFileError, atomic_write_text, check_regular_file, load_json, load_toml,
                             read_text)


def test_device_fifo_and_folder_are_refused(tmp_path):
    link = tmp_path / "zero.json"
    link.symlink_to("/dev/zero")
    fifo = tmp_path / "fifo.json"
    os.mkfifo(fifo)
    for p in (link, fifo, tmp_path):
        with pytest.raises(UnsafeFileError, match="not a regular file"):
            read_text(p)

    for p in (link, fifo, tmp_path):  # the check for files a library opens by name
        with pytest.raises(UnsafeFileError, match="not a regular file"):
            check_regular_file(p)
    (tmp_path / "video.avi").write_bytes(b"x" * 10)
    assert check_regular_file(tmp_path / "video.avi", max_bytes=10) == tmp_path / "video.avi"
    with pytest.raises(UnsafeFileError, match="10 bytes, more than the 9 allowed"):
        check_regular_file(tmp_path / "video.avi", max_bytes=9)
    with pytest.raises(FileNotFoundError):
        check_regular_file(tmp_path / "missing.avi")


def test_size_limit_refuses_not_truncates(tmp_path):
    p = tmp_path / "big.json"
    p.write_text("[" + "0," * 100 + "0]")
    with pytest.raises(UnsafeFileError, match="bytes"):
        load_json(p, max_bytes=50)
    assert load_json(p)[-1] == 0


def test_deep_nesting_is_one_error_not_a_recursion(tmp_path):
    p = tmp_path / "deep.json"
    p.write_text("[" * 5000 + "]" * 5000)
    with pytest.raises(UnsafeFileError, match="nest"):
        load_json(p)
    p.write_text("[" * 70 + "]" * 70)  # parses, but deeper than the limit
    with pytest.raises(UnsafeFileError, match="more than 64"):
        load_json(p)
    t = tmp_path / "deep.toml"
    t.write_text("a = " + "[" * 5000 + "]" * 5000)
    with pytest.raises(UnsafeFileError, match="nest"):
        load_toml(t)


def test_nan_bom_and_bad_text(tmp_path):
    p = tmp_path / "x.json"
    p.write_text('{"r": NaN}')
    with pytest.raises(UnsafeFileError, match="NaN"):
        load_json(p)
    p.write_bytes("\ufeff{\"r\": 1}".encode())
    assert load_json(p) == {"r": 1}
    p.write_bytes(b"\xff\xfe{}")
    with pytest.raises(UnsafeFileError, match="UTF-8"):
        load_json(p)


def test_atomic_write_replaces_a_symlink_instead_of_writing_through(tmp_path):
    target = tmp_path / "target.jsonl"
    target.write_text("precious\n")
    link = tmp_path / "results.jsonl"
    link.symlink_to(target)
    atomic_write_text(link, "new\n")
    assert target.read_text() == "precious\n"
    assert not link.is_symlink() and link.read_text() == "new\n"
    assert [p.name for p in tmp_path.iterdir() if p.name.endswith(".tmp")] == []
