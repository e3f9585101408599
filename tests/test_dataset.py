"""The dataset contract: loading, validation errors that name the file and field, masks, CLI errors."""
import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from cpdetect.cli import main
from cpdetect.dataset import TrueMarker, image_record, load_dataset, read_mask, write_markers_json
from cpdetect.errors import InputError


def _make(root: Path, n_images: int = 2) -> Path:
    """A hand-made two-image dataset (one with an extra per-marker field)."""
    (root / "images").mkdir(parents=True)
    (root / "masks").mkdir()
    recs = []
    for i in range(n_images):
        img = np.full((40, 60, 3), 100 + i, np.uint8)
        cv2.imwrite(str(root / "images" / f"a{i}.png"), img)
        mask = np.zeros((40, 60), np.uint8)
        mask[10:20, 10:20] = 255
        cv2.imwrite(str(root / "masks" / f"a{i}.png"), mask)
        markers = [TrueMarker(15.0, 15.0, "square", 5.6, {"tilt_deg": 12.5})] if i == 0 else []
        recs.append(image_record(f"images/a{i}.png", f"masks/a{i}.png", markers, category="brick"))
    write_markers_json(root, recs, generator={"name": "test"})
    return root


def _edit(root: Path, fn) -> None:
    doc = json.loads((root / "markers.json").read_text())
    fn(doc)
    (root / "markers.json").write_text(json.dumps(doc))


def test_roundtrip_keeps_required_and_extra_fields(tmp_path):
    ds = load_dataset(_make(tmp_path))
    assert len(ds.images) == 2 and ds.n_markers == 1
    im = ds.images[0]
    assert im.file == "images/a0.png" and im.mask == "masks/a0.png" and im.stem == "a0"
    m = im.markers[0]
    assert (m.x, m.y, m.type, m.radius_px) == (15.0, 15.0, "square", 5.6)
    assert m.extra == {"tilt_deg": 12.5}
    assert im.meta == {"category": "brick"}
    assert ds.meta["generator"] == {"name": "test"} and ds.meta["version"] == 1
    mask = read_mask(ds.mask_path(im), shape=(40, 60))
    assert mask.dtype == bool and mask.sum() == 100 and mask[15, 15] and not mask[0, 0]


def test_mask_may_be_null(tmp_path):
    root = _make(tmp_path)
    _edit(root, lambda d: d["images"][1].update(mask=None))
    assert load_dataset(root).images[1].mask is None


BAD_EDITS = [
    (lambda d: d.pop("images"), "missing 'images'"),
    (lambda d: d.update(images={}), "'images' must be a list"),
    (lambda d: d["images"][1].pop("file"), "images[1]: missing 'file'"),
    (lambda d: d["images"][0].pop("markers"), "images[0]: missing 'markers'"),
    (lambda d: d["images"][0]["markers"][0].pop("radius_px"), "images[0].markers[0]: missing 'radius_px'"),
    (lambda d: d["images"][0]["markers"][0].update(x="12"), "images[0].markers[0]: 'x' must be a number"),
    (lambda d: d["images"][0]["markers"][0].update(type="triangle"), "images[0].markers[0]: 'type' must be one of"),
    (lambda d: d["images"][0]["markers"][0].update(radius_px=-1), "'radius_px' must be positive"),
    (lambda d: d["images"][0].update(file="/etc/passwd"), "must be a path inside the dataset folder"),
    (lambda d: d["images"][1].update(file="images/a0.png"), "listed twice"),
    (lambda d: d["images"][0]["markers"].append([1, 2]), "images[0].markers[1]: must be an object"),
]


@pytest.mark.parametrize("edit,message", BAD_EDITS)
def test_malformed_markers_json_names_file_and_field(tmp_path, edit, message):
    root = _make(tmp_path)
    _edit(root, edit)
    with pytest.raises(InputError) as e:
        load_dataset(root)
    assert message in str(e.value)
    assert str(root / "markers.json") in str(e.value)


def test_listed_files_must_exist(tmp_path):
    root = _make(tmp_path)
    (root / "masks" / "a1.png").unlink()
    with pytest.raises(InputError) as e:
        load_dataset(root)
    assert "a1.png" in str(e.value) and "images[1].mask" in str(e.value)


def test_missing_folder_and_json(tmp_path):
    with pytest.raises(InputError, match="not found"):
        load_dataset(tmp_path / "nope")
    with pytest.raises(InputError, match="markers.json not found"):
        load_dataset(tmp_path)
    (tmp_path / "markers.json").write_text("{not json")
    with pytest.raises(InputError, match="not valid JSON"):
        load_dataset(tmp_path)


def test_read_mask_errors(tmp_path):
    with pytest.raises(InputError, match="mask not found"):
        read_mask(tmp_path / "m.png")
    (tmp_path / "m.png").write_bytes(b"garbage")
    with pytest.raises(InputError, match="corrupt mask"):
        read_mask(tmp_path / "m.png")
    cv2.imwrite(str(tmp_path / "c.png"), np.zeros((4, 5, 3), np.uint8))
    with pytest.raises(InputError, match="single-channel"):
        read_mask(tmp_path / "c.png")
    cv2.imwrite(str(tmp_path / "g.png"), np.zeros((4, 5), np.uint8))
    with pytest.raises(InputError, match="differs.*EXIF orientation"):  # transposed: a portrait photo
        read_mask(tmp_path / "g.png", shape=(5, 4))
    with pytest.raises(InputError, match=r"differs from the image's 7x6$") as e:
        read_mask(tmp_path / "g.png", shape=(6, 7))
    assert "EXIF" not in str(e.value)


def _cli_error(capsys, argv) -> tuple[int, str]:
    rc = main(argv)
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    assert "Traceback" not in err[0]
    return rc, err[0]


def test_eval_cli_bad_inputs_one_line_errors(tmp_path, capsys):
    root = _make(tmp_path / "d")
    rc, err = _cli_error(capsys, ["eval", str(tmp_path / "missing"), "--detector", "x"])
    assert rc == 2 and "missing" in err
    (root / "markers.json").write_text("[1, 2")
    rc, err = _cli_error(capsys, ["eval", str(root), "--detector", "x"])
    assert rc == 2 and "markers.json" in err
    root2 = _make(tmp_path / "e")
    _edit(root2, lambda d: d["images"][0]["markers"][0].pop("type"))
    rc, err = _cli_error(capsys, ["eval", str(root2), "--detector", "x"])
    assert rc == 2 and "images[0].markers[0]: missing 'type'" in err


def test_eval_cli_unreadable_image_names_it(tmp_path, capsys, monkeypatch):
    import cpdetect.detector as registry
    from cpdetect.types import DetectionResult

    class Nothing:
        name = "nothing"

        def detect(self, image):
            return DetectionResult([], (image.shape[1], image.shape[0]))

    monkeypatch.setitem(registry._REGISTERED, "nothing", Nothing)
    root = _make(tmp_path)
    (root / "images" / "a1.png").write_bytes(b"\x89PNG\r\n\x1a\n" + b"\0" * 40)
    rc, err = _cli_error(capsys, ["eval", str(root), "--detector", "nothing"])
    assert rc == 2 and "a1.png" in err


def test_eval_cli_in_a_fresh_process_has_no_traceback(tmp_path):
    (tmp_path / "markers.json").write_text('{"images": [{"file": "images/x.jpg"}]}')
    r = subprocess.run([sys.executable, "-m", "cpdetect.cli", "eval", str(tmp_path), "--detector", "classical"],
                       capture_output=True, text=True)
    assert r.returncode == 2
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in r.stderr
    assert "markers.json" in lines[0] and "images[0]" in lines[0]
