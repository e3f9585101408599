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
