"""Atomic writes: complete files with normal permissions, nothing left behind on failure."""
import json
import os
import stat

import pytest

from cpdetect.errors import InputError
from cpdetect.fileio import atomic_path, read_json, write_json_atomic


def test_written_file_has_umask_permissions(tmp_path):
    p = tmp_path / "out.json"
    write_json_atomic(p, {"a": 1})
    umask = os.umask(0)
    os.umask(umask)
    assert stat.S_IMODE(p.stat().st_mode) == 0o666 & ~umask
    assert json.loads(p.read_text()) == {"a": 1}


def test_failed_write_keeps_old_file_and_leaves_no_temp(tmp_path):
    p = tmp_path / "out.txt"
    p.write_text("old")
    with pytest.raises(RuntimeError):
        with atomic_path(p) as tmp:
            tmp.write_text("half")
            raise RuntimeError("boom")
    assert p.read_text() == "old"
    assert sorted(f.name for f in tmp_path.iterdir()) == ["out.txt"]


def test_nan_is_refused_before_anything_is_written(tmp_path):
    p = tmp_path / "bad.json"
    with pytest.raises(ValueError):
        write_json_atomic(p, {"x": float("nan")})
    assert list(tmp_path.iterdir()) == []


def test_read_json_errors_name_file_and_line(tmp_path):
    p = tmp_path / "broken.json"
    p.write_text('{\n "a": 1,\n oops\n}')
    with pytest.raises(InputError, match=r"broken.json:3: not valid JSON"):
        read_json(p)
    with pytest.raises(InputError, match="not found"):
        read_json(tmp_path / "absent.json")


def test_an_output_through_a_link_replaces_the_linked_file_and_keeps_the_link(tmp_path):
    real = tmp_path / "results" / "out.json"
    real.parent.mkdir()
    real.write_text("old\n")
    link = tmp_path / "out.json"
    link.symlink_to(real)
    write_json_atomic(link, {"a": 1})
    assert link.is_symlink() and json.loads(real.read_text()) == {"a": 1}


def test_a_pipe_is_no_output_file_and_is_left_as_it_is(tmp_path):
    # renaming the finished file onto a device or a pipe replaces the device itself (as root,
    # --out /dev/null replaced /dev/null with a regular file); a pipe stands in for one here
    fifo = tmp_path / "out.json"
    os.mkfifo(fifo)
    link = tmp_path / "via_link.json"
    link.symlink_to(fifo)
    for p in (fifo, link):
        with pytest.raises(InputError, match="not a regular file"):
            write_json_atomic(p, {"a": 1})
    assert stat.S_ISFIFO(os.stat(fifo).st_mode) and sorted(x.name for x in tmp_path.iterdir()) == ["out.json", "via_link.json"]


def test_a_target_name_of_250_bytes_is_written_and_a_longer_one_is_one_error(tmp_path):
    # the temporary name repeated the whole target name: 250 bytes + '.xxxxxxxx.part' went over 255
    long_ok = tmp_path / ("n" * 245 + ".json")
    write_json_atomic(long_ok, {"a": 1})
    assert json.loads(long_ok.read_text()) == {"a": 1} and os.listdir(tmp_path) == [long_ok.name]
    with pytest.raises(InputError, match="cannot write here: File name too long"):
        write_json_atomic(tmp_path / ("n" * 300 + ".json"), {"a": 1})
