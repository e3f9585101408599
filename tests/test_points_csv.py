"""cpdetect.formats.points_csv: name,x,y,z tables with located errors."""
import numpy as np
import pytest

from cpdetect.errors import InputError
from cpdetect.formats.points_csv import read_points_csv, write_points_csv


def write(tmp_path, text, name="p.csv", raw=False):
    path = tmp_path / name
    if raw:
        path.write_bytes(text)
    else:
        path.write_text(text, encoding="utf-8")
    return path


def test_roundtrip_is_exact_in_float64(tmp_path):
    rng = np.random.default_rng(0)
    xyz = rng.normal(0, 1, (5, 3)) * [1e5, 1e6, 10] + [512000.123456789, 5781000.987654321, 80]
    names = ["A", "B 2", "c,3", "ü", "5"]
    path = write_points_csv(tmp_path / "out.csv", names, xyz)
    t = read_points_csv(path)
    assert t.names == names and t.xyz.dtype == np.float64
    np.testing.assert_array_equal(t.xyz, xyz)
    assert t.lines == [2, 3, 4, 5, 6] and t.path == str(path)


def test_extra_columns_order_case_aliases_and_id(tmp_path):
    text = "\ufeff# surveyed 2026\nCode, Z ,Y,X,Name\n\nq,3,2,1,P1\n# comment\nq,6,5,4,P2\n"
    t = read_points_csv(write(tmp_path, text))
    assert t.names == ["P1", "P2"]
    np.testing.assert_array_equal(t.xyz, [[1, 2, 3], [4, 5, 6]])
    assert t.lines == [4, 6]
    t = read_points_csv(write(tmp_path, "id;easting;northing;height\n7;1.5;2.5;3.5\n"))
    assert t.names == ["7"] and t.xyz.tolist() == [[1.5, 2.5, 3.5]]
    t = read_points_csv(write(tmp_path, 'name,x,y,z\n"a, b",1,2,3\n'))
    assert t.names == ["a, b"]


@pytest.mark.parametrize("text, where, word", [
    ("1,2,3,4\n5,6,7,8\n", ":1:", "header"),
    ("name,x,y\nA,1,2\n", ":1:", "lacks column(s) z"),
    ("x,y,z\n1,2,3\n", ":1:", "lacks column(s) name"),
    ("name,x,y,z\nA,1,2,3\nB,1,two,3\n", ":3:", "y of 'B' is not a number: 'two'"),
    ("name,x,y,z\nA,1,2,NaN\n", ":2:", "z of 'A' is not finite"),
    ("name,x,y,z\nA,inf,2,3\n", ":2:", "x of 'A' is not finite"),
    ("name,x,y,z\nA,1,2,3\n\nA,4,5,6\n", ":4:", "duplicate point name 'A' (first on line 2)"),
    ("name,x,y,z\n,1,2,3\n", ":2:", "empty point name"),
    ("name,x,y,z\nA,1,2\n", ":2:", "row has 3 field(s)"),
    ("", ":1:", "empty"),
    ("# only a comment\n", ":1:", "empty"),
])
def test_bad_files_name_file_and_line(tmp_path, text, where, word):
    path = write(tmp_path, text)
    with pytest.raises(InputError) as exc:
        read_points_csv(path)
    msg = str(exc.value)
    assert msg.startswith(str(path) + where), msg
    assert word in msg and "\n" not in msg


def test_non_utf8_bytes_give_one_line_with_line_number(tmp_path):
    path = write(tmp_path, b"name,x,y,z\nA,1,2,3\nB\xe9,1,2,3\n", raw=True)
    with pytest.raises(InputError) as exc:
        read_points_csv(path)
    assert str(exc.value).startswith(f"{path}:3: not UTF-8") and "\n" not in str(exc.value)


def test_too_few_points_missing_file_and_folder(tmp_path):
    path = write(tmp_path, "name,x,y,z\nA,1,2,3\nB,4,5,6\n")
    assert len(read_points_csv(path, min_points=2)) == 2
    with pytest.raises(InputError, match="need at least 3 surveyed points, found 2"):
        read_points_csv(path, min_points=3, what="surveyed points")
    with pytest.raises(InputError, match="not found"):
        read_points_csv(tmp_path / "nope.csv")
    with pytest.raises(InputError, match="folder"):
        read_points_csv(tmp_path)


def test_header_only_is_zero_points(tmp_path):
    t = read_points_csv(write(tmp_path, "name,x,y,z\n"))
    assert len(t) == 0 and t.xyz.shape == (0, 3)
