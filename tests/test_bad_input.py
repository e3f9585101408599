"""Messy inputs through the public command line: each gives a clear one-line error naming the file (and a
non-zero exit, no traceback, no output or partial file left behind), or a documented outcome.

Documented outcomes (docs/scale.md, "Messy inputs"): a PNG named .jpg is read by its content; 16-bit,
gray and 4-channel images are converted to 8 bits; images larger than 400 MP are refused before
decoding; ``--skip-bad`` records unreadable images as errors and goes on; a run that stops keeps the
finished images' parts for a rerun (and nothing else); registered images missing from the image folder
are ignored with a warning; a collinear or symmetric surveyed layout is a registration that fails
(exit 3, the JSON says why and lists the alternatives). The interrupted run is in test_interrupt.py.
"""
import json
import logging
import shutil
import struct
import subprocess
import sys
import zlib
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pytest

from batch_helpers import write_marker_images
from cpdetect.cli import main

# the marker of write_marker_images' image 0: X-corner at pixel (25.5, 23.5)
CORNER0 = np.array([25.5, 23.5])


@dataclass
class Run:
    rc: int
    err: list[str]
    out: str


@pytest.fixture
def cli(capsys):
    """Run ``cpdetect ARGS`` in this process as a shell would: logging configured by the CLI itself, to
    the captured stderr (pytest's own log handlers are set aside during the call)."""

    def run(*argv) -> Run:
        root = logging.getLogger()
        handlers, level = root.handlers[:], root.level
        root.handlers = []
        try:
            rc = main([str(a) for a in argv])
        finally:
            root.handlers = handlers
            root.setLevel(level)
        cap = capsys.readouterr()
        return Run(rc, cap.err.splitlines(), cap.out)

    return run


def assert_one_line_error(res: Run, *named, code=2):
    assert res.rc == code, res.err
    assert len(res.err) == 1, res.err
    line = res.err[0]
    assert "Traceback" not in line and "internal error" not in line
    assert " error: " in line
    for n in named:
        assert str(n) in line, (n, line)


def files_under(folder: Path) -> list[str]:
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*")) if folder.exists() else []


# ---------------------------------------------------------------------------------------------------
# Images


def _png_header(w, h) -> bytes:
    ihdr = struct.pack(">IIBBBBB", w, h, 8, 0, 0, 0, 0)
    chunk = b"IHDR" + ihdr
    return b"\x89PNG\r\n\x1a\n" + struct.pack(">I", len(ihdr)) + chunk + struct.pack(">I", zlib.crc32(chunk))


@pytest.fixture(scope="module")
def marker_jpeg(tmp_path_factory):
    return write_marker_images(tmp_path_factory.mktemp("marker"), 1) / "0000.jpg"


def _png_bytes(img) -> bytes:
    return cv2.imencode(".png", img)[1].tobytes()


BAD_IMAGES = {
    # name: (file name, bytes from the good JPEG's bytes, expected words)
    "zero-byte JPEG": ("empty.jpg", lambda jpg, png: b"", "empty (0 bytes)"),
    "truncated JPEG": ("cut.jpg", lambda jpg, png: jpg[: len(jpg) // 2], "truncated JPEG"),
    "JPEG cut short, end marker added": ("cut_end.jpg", lambda jpg, png: jpg[: len(jpg) // 2] + b"\xff\xd9",
                                         "damaged JPEG data"),
    "truncated PNG": ("cut.png", lambda jpg, png: png[: len(png) // 2], "truncated PNG"),
    "text named .jpg": ("notes.jpg", lambda jpg, png: b"just some text\n", "not an image"),
    "huge 20001x20000 PNG": ("huge.png", lambda jpg, png: _png_header(20001, 20000), "too large (20001x20000"),
    # formats people photograph in that cpdetect does not read: named, not "not an image"
    "WebP": ("photo.webp", lambda jpg, png: b"RIFF\x24\x00\x00\x00WEBPVP8 " + b"\x00" * 32,
             "unsupported image format (WebP): convert it to JPEG, PNG or TIFF"),
    "HEIC named .jpg": ("IMG_0001.jpg", lambda jpg, png: b"\x00\x00\x00\x18ftypheic\x00\x00\x00\x00mif1heic" + b"\x00" * 16,
                        "unsupported image format (HEIC/HEIF)"),
    "JPEG 2000": ("ortho.jp2", lambda jpg, png: b"\x00\x00\x00\x0cjP  \r\n\x87\n" + b"\x00" * 32,
                  "unsupported image format (JPEG 2000)"),
}


@pytest.mark.parametrize("case", list(BAD_IMAGES))
def test_bad_image_alone(cli, tmp_path, marker_jpeg, case):
    fname, make, words = BAD_IMAGES[case]
    jpg = marker_jpeg.read_bytes()
    bad = tmp_path / "in" / fname
    bad.parent.mkdir()
    bad.write_bytes(make(jpg, _png_bytes(cv2.imread(str(marker_jpeg)))))
    out = tmp_path / "out"
    res = cli("-q", "detect", bad, "--out", out / "det.json")
    assert_one_line_error(res, bad, words)
    assert not out.exists()


@pytest.mark.parametrize("detector", ["classical", "hma"])
@pytest.mark.parametrize("shape", [(40, 40000), (30000, 9)])
def test_images_wider_than_remap_allows_or_thin_strips_are_read(cli, tmp_path, detector, shape):
    # "internal error" before: cv2.remap refuses images of 32767 px a side (classical), and a strip
    # downscaled to 2048 px was 0 px wide at hma's half scale
    p = tmp_path / "strip.png"
    p.write_bytes(_png_bytes(np.random.default_rng(0).integers(0, 256, shape).astype(np.uint8)))
    out = tmp_path / "det.json"
    res = cli("-q", "detect", p, "--detector", detector, "--out", out)
    assert res.rc == 0 and res.err == []
    (im,) = json.loads(out.read_text())["images"]
    assert (im["width"], im["height"]) == (shape[1], shape[0]) and im["detections"] == []


def test_a_pipe_or_a_device_is_refused_without_reading_it(cli, tmp_path):
    # a named pipe would block the read forever; /dev/zero was "internal error: NotADirectoryError"
    import os

    fifo = tmp_path / "photo.jpg"
    os.mkfifo(fifo)
    for p in (fifo, Path("/dev/zero")):
        res = cli("-q", "detect", p, "--out", tmp_path / "out" / "det.json")
        assert_one_line_error(res, p, "neither an image file nor a folder")
    assert not (tmp_path / "out").exists()


def test_a_pipe_as_the_output_is_refused_and_left_as_it_is(cli, tmp_path):
    # as root, "--out /dev/null" replaced the device with a regular file (the finished output is
    # renamed onto the target); a named pipe stands in for the device here
    import os
    import stat

    images = write_marker_images(tmp_path / "in", 1)
    out = tmp_path / "det.json"
    os.mkfifo(out)
    res = cli("-q", "detect", images, "--out", out)
    assert_one_line_error(res, out, "not a regular file (a device, pipe or socket)")
    assert stat.S_ISFIFO(os.stat(out).st_mode) and files_under(tmp_path) == ["det.json", "in", "in/0000.jpg"]


def test_bad_image_among_good_ones_keeps_finished_parts_then_skip_bad(cli, tmp_path):
    images = write_marker_images(tmp_path / "in", 3)
    bad = images / "zz_cut.jpg"
    bad.write_bytes((images / "0000.jpg").read_bytes()[:300])
    out = tmp_path / "out" / "det.json"
    res = cli("-q", "detect", images, "--out", out)
    assert_one_line_error(res, bad, "truncated JPEG")
    # no output file; the three finished images are kept for a rerun, nothing else
    left = files_under(out.parent)
    assert left[0] == "det.json.parts" and len(left) == 4
    assert all(p.startswith("det.json.parts/") and p.endswith(".json") for p in left[1:])
    res = cli("-q", "detect", images, "--out", out, "--skip-bad")
    assert res.rc == 0 and res.err == []
    doc = json.loads(out.read_text())
    assert [im["file"] for im in doc["images"]] == ["0000.jpg", "0001.jpg", "0002.jpg", "zz_cut.jpg"]
    assert "truncated JPEG" in doc["images"][3]["error"] and "detections" not in doc["images"][3]
    assert all(len(im["detections"]) == 1 for im in doc["images"][:3])
    assert files_under(out.parent) == ["det.json"]


def _odd(marker_jpeg, case) -> tuple[str, bytes]:
    gray = cv2.imread(str(marker_jpeg), cv2.IMREAD_GRAYSCALE)
    if case == "PNG named .jpg":
        return "really_png.jpg", _png_bytes(gray)
    if case == "16-bit PNG":
        return "deep.png", _png_bytes(gray.astype(np.uint16) * 257)
    if case == "grayscale JPEG":
        return "gray.jpg", cv2.imencode(".jpg", gray, [cv2.IMWRITE_JPEG_QUALITY, 95])[1].tobytes()
    if case == "BGRA PNG":
        return "alpha.png", _png_bytes(np.dstack([gray, gray, gray, np.full_like(gray, 255)]))
    raise KeyError(case)


@pytest.mark.parametrize("case", ["PNG named .jpg", "16-bit PNG", "grayscale JPEG", "BGRA PNG"])
def test_odd_but_valid_images_are_read_by_content(cli, tmp_path, marker_jpeg, case):
    name, data = _odd(marker_jpeg, case)
    p = tmp_path / name
    p.write_bytes(data)
    out = tmp_path / "det.json"
    res = cli("-q", "detect", p, "--out", out)
    assert res.rc == 0 and res.err == []
    (im,) = json.loads(out.read_text())["images"]
    assert (im["width"], im["height"]) == (96, 72)
    (d,) = im["detections"]
    assert np.hypot(d["x"] - CORNER0[0], d["y"] - CORNER0[1]) < 1.0


# ---------------------------------------------------------------------------------------------------
# Where the output goes, and requests that cannot be honoured


def _writable(folder: Path) -> bool:
    try:
        (folder / ".probe").write_bytes(b"")
    except OSError:
        return False
    (folder / ".probe").unlink()
    return True


@pytest.fixture
def read_only_dir(tmp_path):
    d = tmp_path / "ro"
    d.mkdir()
    d.chmod(0o555)
    immutable = False
    if _writable(d) and shutil.which("chattr"):  # root ignores permissions, not the immutable flag
        immutable = subprocess.run(["chattr", "+i", str(d)], capture_output=True).returncode == 0
    try:
        if _writable(d):
            pytest.skip("cannot make a read-only folder here")
        yield d
    finally:
        if immutable:
            subprocess.run(["chattr", "-i", str(d)], check=True)
        d.chmod(0o755)


def test_read_only_output_folder(cli, tmp_path, marker_jpeg, read_only_dir):
    res = cli("-q", "detect", marker_jpeg, "--out", read_only_dir / "det.json")
    assert_one_line_error(res, read_only_dir, "cannot write here")
    assert files_under(read_only_dir) == []


@pytest.mark.parametrize("case", ["output is a folder", "output under a file", "parts folder's name taken",
                                  "missing input", "folder without images", "workers 0", "unknown detector",
                                  "unknown setting", "setting of the wrong type"])
def test_detect_requests(cli, tmp_path, marker_jpeg, case):
    (tmp_path / "afile").write_text("x")
    (tmp_path / "empty").mkdir()
    (tmp_path / "empty" / "readme.txt").write_text("x")
    out = tmp_path / "out" / "det.json"
    inp, extra, named = marker_jpeg, [], []
    if case == "output is a folder":
        out = tmp_path / "empty"
        named = [out, "is a folder"]
    elif case == "output under a file":
        out = tmp_path / "afile" / "det.json"
        # the output the user gave is named, not the resumable parts folder beside it
        named = [f"{out}: cannot write here: {tmp_path / 'afile'} is a file, not a folder"]
    elif case == "parts folder's name taken":
        (tmp_path / "det.json.parts").write_text("x")
        out = tmp_path / "det.json"
        named = [f"{out}.parts: cannot write here"]
    elif case == "missing input":
        inp = tmp_path / "absent.jpg"
        named = [inp, "not found"]
    elif case == "folder without images":
        inp = tmp_path / "empty"
        named = [inp, "no images"]
    elif case == "workers 0":
        extra, named = ["--workers", "0"], ["--workers"]
    elif case == "unknown detector":
        extra, named = ["--detector", "nosuch"], ["nosuch", "classical"]
    elif case == "unknown setting":
        extra, named = ["--set", "min_scor=0.5"], ["min_scor", "min_score"]
    elif case == "setting of the wrong type":
        extra, named = ["--set", "min_score=high"], ["min_score", "expected float"]
    before = files_under(tmp_path)
    res = cli("-q", "detect", inp, "--out", out, *extra)
    assert_one_line_error(res, *named)
    assert files_under(tmp_path) == before


# ---------------------------------------------------------------------------------------------------
# Point tables, CRS and degenerate layouts (cpdetect register)

RNG_POINTS = np.random.default_rng(5).uniform(0.0, 50.0, (8, 3))


def _csv(rows, head="name,x,y,z") -> str:
    return head + "\n" + "".join(f"{n},{x!r},{y!r},{z!r}\n" for n, (x, y, z) in rows)


GOOD_SURVEYED = _csv([(f"P{i}", tuple(map(float, p))) for i, p in enumerate(RNG_POINTS)])
GOOD_DETECTED = _csv([(f"m{i}", tuple(map(float, 3.0 * p + 2.0))) for i, p in enumerate(RNG_POINTS[::-1])],
                     head="id,x,y,z")

BAD_CSV = {
    # case: (bytes, 1-based line named or None, expected words)
    "missing column": (b"name,x,y\nA,1,2\nB,3,4\nC,5,6\n", 1, "lacks column(s) z"),
    "NaN": (GOOD_SURVEYED.replace(repr(float(RNG_POINTS[2, 1])), "nan").encode(), 4, "not finite"),
    "duplicate names": (GOOD_SURVEYED.replace("P3,", "P1,").encode(), 5, "duplicate point name 'P1'"),
    "non-UTF-8 bytes": (GOOD_SURVEYED.replace("P4", "P\u00e94").encode("latin-1"), 6, "not UTF-8"),
    "two points": (b"name,x,y,z\nA,0,0,0\nB,1,0,0\n", None, "need at least 3"),
    "header only": (b"name,x,y,z\n", None, "need at least 3"),
    "no header": (b"1,0,0,0\n2,1,0,0\n3,0,1,0\n", 1, "must be a header"),
    "short row": (b"name,x,y,z\nA,0,0,0\nB,1,0\nC,0,1,0\n", 3, "row has 3 field(s)"),
    "not a number": (b"name,x,y,z\nA,0,0,0\nB,1,zero,0\nC,0,1,0\n", 3, "not a number"),
}


@pytest.fixture
def points(tmp_path):
    (tmp_path / "surveyed.csv").write_text(GOOD_SURVEYED)
    (tmp_path / "detected.csv").write_text(GOOD_DETECTED)
    return tmp_path


def test_good_tables_register(cli, points):
    out = points / "reg.json"
    res = cli("-q", "register", "--detected", points / "detected.csv", "--surveyed", points / "surveyed.csv",
              "--out", out)
    assert res.rc == 0 and res.err == []
    doc = json.loads(out.read_text())
    assert doc["status"] == "ok" and len(doc["pairs"]) == 8
    assert doc["scale"] == pytest.approx(1 / 3, rel=1e-9)


@pytest.mark.parametrize("role", ["surveyed", "detected"])
@pytest.mark.parametrize("case", list(BAD_CSV))
def test_bad_point_table(cli, points, case, role):
    data, line, words = BAD_CSV[case]
    bad = points / "bad.csv"
    bad.write_bytes(data)
    args = {"surveyed": points / "surveyed.csv", "detected": points / "detected.csv", role: bad}
    out = points / "out" / "reg.json"
    res = cli("-q", "register", "--detected", args["detected"], "--surveyed", args["surveyed"], "--out", out)
    assert_one_line_error(res, f"{bad}:{line}:" if line else f"{bad}:", words)
    assert not (points / "out").exists()


def test_unknown_epsg(cli, points):
    out = points / "reg.json"
    res = cli("-q", "register", "--detected", points / "detected.csv", "--surveyed", points / "surveyed.csv",
              "--crs", "EPSG:999999", "--out", out)
    assert_one_line_error(res, "--crs", "EPSG:999999")
    gcp = points / "gcp_list.txt"
    gcp.write_text("EPSG:999999\n" + "".join(f"{x} {y} {z} 10 20 a.jpg P{i}\n"
                                            for i, (x, y, z) in enumerate(RNG_POINTS)))
    res = cli("-q", "register", "--detected", points / "detected.csv", "--surveyed", gcp, "--out", out)
    assert_one_line_error(res, f"{gcp}:1:", "EPSG:999999")
    assert not out.exists()


@pytest.mark.parametrize("case", ["collinear surveyed", "collinear detected", "symmetric square"])
def test_degenerate_layouts_fail_with_a_reason(cli, points, case):
    line = _csv([(f"C{i}", (3.0 * i, 1.5 * i, 0.5 * i)) for i in range(6)])
    square = "name,x,y,z\nA,0,0,0\nB,10,0,0\nC,10,10,0\nD,0,10,0\n"
    det, sur = points / "detected.csv", points / "surveyed.csv"
    if case == "collinear surveyed":
        sur.write_text(line)
        status, words = "failed", "surveyed points are collinear"
    elif case == "collinear detected":
        det.write_text(line)
        status, words = "failed", "detected points are collinear"
    else:
        sur.write_text(square)
        det.write_text(square.replace("name", "id"))
        status, words = "ambiguous", "symmetric layout"
    out = points / "reg.json"
    res = cli("-q", "register", "--detected", det, "--surveyed", sur, "--out", out)
    assert res.rc == 3
    assert len(res.err) == 1 and res.err[0].startswith(f"WARNING: {status}") and words in res.err[0]
    doc = json.loads(out.read_text())  # documented: the JSON is still written, complete
    assert doc["status"] == status and words in doc["reason"]
    if status == "ambiguous":
        # the best pairing and the equally good alternatives (the square's 7 other symmetries)
        assert len(doc["pairs"]) == 4 and doc["matrix"] is not None
        assert len(doc["alternatives"]) == 7 and all(a["n_pairs"] == 4 for a in doc["alternatives"])
    else:
        assert doc["matrix"] is None and doc["pairs"] == []


# ---------------------------------------------------------------------------------------------------
# Reconstructions and their images (cpdetect georef)


def _colmap_text(folder: Path, names) -> Path:
    """A COLMAP text model: one 96x72 pinhole camera, the named images in a row 5 units from the origin."""
    folder.mkdir(parents=True)
    (folder / "cameras.txt").write_text("1 PINHOLE 96 72 80 80 47.5 35.5\n")
    (folder / "images.txt").write_text("".join(f"{i + 1} 1 0 0 0 {0.5 * i} 0 5 1 {n}\n\n"
                                               for i, n in enumerate(names)))
    (folder / "points3D.txt").write_text("")
    return folder


@pytest.fixture
def site(tmp_path):
    write_marker_images(tmp_path / "images", 4)
    (tmp_path / "gcps.csv").write_text(GOOD_SURVEYED)
    return tmp_path


def _dets(path: Path, names) -> Path:
    path.write_text(json.dumps({"format": "cpdetect.detections/1", "detector": "test", "images": [
        {"file": n, "width": 96, "height": 72,
         "detections": [{"x": 40.0, "y": 30.0, "score": 0.9, "type": "square", "radius_px": 12.0,
                         "sigma_px": 0.2}]} for n in names]}))
    return path


@pytest.mark.parametrize("case", ["reconstruction without images", "no reconstruction image in the folder",
                                  "detections of images not in the reconstruction", "detections not JSON",
                                  "detections not UTF-8", "reconstruction missing", "image folder missing",
                                  "unknown EPSG", "two surveyed points", "detector setting of the wrong type"])
def test_georef_inputs(cli, site, case):
    names = [f"{i:04d}.jpg" for i in range(4)]
    model = site / "model"
    images, gcps, extra, named = site / "images", site / "gcps.csv", [], []
    if case == "reconstruction without images":
        _colmap_text(model, [])
        named = [model, "no registered"]
    elif case == "no reconstruction image in the folder":
        _colmap_text(model, ["a.jpg", "b.jpg"])
        named = [images, "none of the 2 images", "a.jpg"]
    else:
        _colmap_text(model, names)
    if case == "detections of images not in the reconstruction":
        write_marker_images(site / "extra", 1)
        shutil.copy(site / "extra" / "0000.jpg", images / "extra.jpg")  # in the folder, not in the model
        d = _dets(site / "dets.json", ["extra.jpg"])
        extra, named = ["--detections", d], [d, "no image of the reconstruction", "extra.jpg"]
    elif case == "detections not JSON":
        d = site / "dets.json"
        d.write_text('{"format": "cpdetect.detections/1", "images": [')
        extra, named = ["--detections", d], [f"{d}:1:", "not valid JSON"]
    elif case == "detections not UTF-8":
        d = site / "dets.json"
        d.write_bytes(b'{"format": "caf\xe9"}')
        extra, named = ["--detections", d], [d, "not UTF-8"]
    elif case == "reconstruction missing":
        model = site / "nomodel"
        named = [model, "not found"]
    elif case == "image folder missing":
        images = site / "noimages"
        named = [images, "not found"]
    elif case == "unknown EPSG":
        extra, named = ["--crs", "EPSG:999999"], ["--crs", "EPSG:999999"]
    elif case == "two surveyed points":
        gcps.write_text("name,x,y,z\nA,0,0,0\nB,1,0,0\n")
        named = [gcps, "need at least 3"]
    elif case == "detector setting of the wrong type":
        extra, named = ["--set", "min_score=high"], ["min_score", "expected float"]
    out = site / "out"
    res = cli("-q", "georef", "--reconstruction", model, "--images", images, "--gcps", gcps, "--out", out, *extra)
    assert_one_line_error(res, *named)
    if case == "unknown EPSG":  # the option is at fault, not the surveyed points file
        assert str(gcps) not in res.err[0]
    assert not out.exists()


def test_compare_blames_a_bad_crs_on_the_option(cli, site):
    _colmap_text(site / "sparse", [f"{i:04d}.jpg" for i in range(4)])
    out = site / "report"
    res = cli("-q", "compare", site, "--detectors", "classical", "--crs", "EPSG:999999", "--out", out)
    assert_one_line_error(res, "--crs", "EPSG:999999")
    assert str(site / "gcps.csv") not in res.err[0] and not out.exists()


def test_georef_ignores_registered_images_missing_from_the_folder(cli, site):
    """Documented: registered images that are not in the image folder are ignored with a warning
    naming the folder. (Here the two remaining views cannot place any marker: a failed report, exit 1.)"""
    model = _colmap_text(site / "model", ["0000.jpg", "0001.jpg", "lost.jpg"])
    d = _dets(site / "dets.json", ["0000.jpg", "0001.jpg"])
    out = site / "out"
    res = cli("-q", "georef", "--reconstruction", model, "--images", site / "images", "--gcps", site / "gcps.csv",
              "--detections", d, "--out", out)
    assert res.rc == 1
    assert res.err[0] == f"WARNING: 1 registered images are not in {site / 'images'}; they are ignored"
    assert all(line.startswith("WARNING: ") for line in res.err)
    assert [im["file"] for im in json.loads((out / "detections.json").read_text())["images"]] == \
        ["0000.jpg", "0001.jpg"]
    assert json.loads((out / "report.json").read_text())["status"] == "failed"


# ---------------------------------------------------------------------------------------------------
# The real console entry point: one line, no traceback, in a separate process


@pytest.mark.parametrize("case", ["zero-byte image", "CSV without z"])
def test_in_a_real_process(tmp_path, case):
    out = tmp_path / "out" / "result.json"
    if case == "zero-byte image":
        bad = tmp_path / "empty.jpg"
        bad.write_bytes(b"")
        argv = ["detect", str(bad), "--out", str(out)]
    else:
        bad = tmp_path / "s.csv"
        bad.write_text("name,x,y\nA,1,2\n")
        (tmp_path / "d.csv").write_text(GOOD_DETECTED)
        argv = ["register", "--detected", str(tmp_path / "d.csv"), "--surveyed", str(bad), "--out", str(out)]
    r = subprocess.run([sys.executable, "-m", "cpdetect.cli", *argv], capture_output=True, text=True, timeout=120)
    assert r.returncode == 2
    assert r.stdout == ""
    assert len(r.stderr.splitlines()) == 1 and str(bad) in r.stderr and "Traceback" not in r.stderr
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("argv", [["synth", "images", "--n", "1"], ["synth", "scene"], ["demo"]])
def test_a_negative_seed_is_a_usage_error(cli, tmp_path, argv):
    # NumPy refuses negative seeds: "internal error: ValueError: expected non-negative integer" before
    out = tmp_path / "out"
    with pytest.raises(SystemExit) as exc:
        cli("-q", *argv, *(["--out", out] if argv[0] == "synth" else ["--workdir", out]), "--seed", "-3")
    assert exc.value.code == 2 and not out.exists()


@pytest.mark.parametrize("argv, words", [
    # the ONNX file was written, then the check failed against a tolerance no difference can meet
    (["export-onnx", "MODEL", "OUT/m.onnx", "--tolerance", "-1"], "--tolerance must be a positive number"),
    # NaN passed the "< 0" check and ended in "internal error" when the scene's JSON was written
    (["synth", "scene", "--out", "OUT/site", "--survey-sigma", "nan"], "noise sigmas must be finite"),
    (["train", "--data", "OUT/none", "--out", "OUT/model", "--checkpoint-minutes", "-1"],
     "--checkpoint-minutes must be >= 0"),
])
def test_numbers_out_of_range_are_refused_before_anything_is_written(cli, tmp_path, argv, words):
    pytest.importorskip("torch")
    from learned.adapter import default_model_dir

    out = tmp_path / "out"
    args = [str(default_model_dir()) if a == "MODEL" else a.replace("OUT", str(out)) for a in argv]
    res = cli("-q", *args)
    assert_one_line_error(res, words)
    assert not out.exists()


def test_an_image_whose_candidates_pass_max_verified_is_detected_with_a_warning(cli, tmp_path):
    # a checkerboard passes a candidate at every corner; the classical detector verifies at most
    # max_verified of them (a 12 MP checkerboard took 6.5 s for 3,000) and names the image
    yy, xx = np.indices((240, 320))
    board = np.where((yy // 20 + xx // 20) % 2, 220, 30).astype(np.float32)
    p = tmp_path / "board.png"
    p.write_bytes(_png_bytes(cv2.GaussianBlur(board, (0, 0), 0.7).astype(np.uint8)))
    out = tmp_path / "det.json"
    res = cli("-q", "detect", p, "--set", "max_verified=2", "--out", out)
    assert res.rc == 0 and len(res.err) == 1 and res.err[0].startswith("WARNING: board.png: ")
    assert "left unverified" in res.err[0]
    (im,) = json.loads(out.read_text())["images"]
    assert im["detections"] == [] and "left unverified" in im["warning"]


@pytest.mark.parametrize("which", ["--detected", "--surveyed"])
def test_a_pipe_given_as_a_point_file_is_refused_without_reading_it(tmp_path, which):
    # reading a named pipe blocks until something writes to it: 'register' waited forever. A
    # subprocess with a timeout, so that a regression fails instead of hanging the suite
    import os

    pts = tmp_path / "points.csv"
    pts.write_text("id,x,y,z\n" + "".join(f"P{i},{i},{i * i % 5},{i % 3}\n" for i in range(5)))
    fifo = tmp_path / "pipe.csv"
    os.mkfifo(fifo)
    args = {"--detected": pts, "--surveyed": pts, which: fifo}
    run_cli = "import sys; from cpdetect.cli import main; sys.exit(main())"
    r = subprocess.run([sys.executable, "-c", run_cli, "-q", "register", "--detected", str(args["--detected"]),
                        "--surveyed", str(args["--surveyed"]), "--out", str(tmp_path / "r.json")],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and r.stderr.strip().splitlines() == [
        f"cpdetect register: error: {fifo}: expected a CSV file, found a device, pipe or socket"]
    assert not (tmp_path / "r.json").exists()


@pytest.mark.parametrize("command", ["detect", "synth images", "synth scene", "register", "train"])
def test_output_under_a_file_is_named(cli, tmp_path, marker_jpeg, command):
    # the system says "File exists" or "Not a directory"; the user is told which part of the path is a file
    (tmp_path / "afile").write_text("x")
    out = tmp_path / "afile" / "sub" / "out"
    if command == "train":
        pytest.importorskip("torch")
        assert cli("-q", "synth", "images", "--out", tmp_path / "ds", "--n", "1").rc == 0
    argv = {"train": ["train", "--data", tmp_path / "ds", "--out", out, "--epochs", "1", "--iters-per-epoch", "1"],
            "detect": ["detect", marker_jpeg, "--out", out],
            "synth images": ["synth", "images", "--out", out, "--n", "1"],
            "synth scene": ["synth", "scene", "--out", out],
            "register": ["register", "--detected", tmp_path / "d.csv", "--surveyed", tmp_path / "s.csv",
                         "--out", out]}[command]
    (tmp_path / "d.csv").write_text(GOOD_DETECTED)
    (tmp_path / "s.csv").write_text(GOOD_SURVEYED)
    before = files_under(tmp_path)
    res = cli("-q", *argv)
    assert_one_line_error(res, f"cannot write here: {tmp_path / 'afile'} is a file, not a folder")
    assert files_under(tmp_path) == before
