"""Image reading: every bad file is a one-line InputError naming it; odd but valid images are converted."""
import cv2
import numpy as np
import pytest

from cpdetect.errors import InputError
from cpdetect.imageio import list_images, probe_image, read_image, read_reduced_colour_then_gray


@pytest.fixture()
def jpeg(tmp_path):
    img = np.zeros((60, 80, 3), np.uint8)
    img[10:30, 20:50] = (10, 200, 30)
    p = tmp_path / "a.jpg"
    cv2.imwrite(str(p), img)
    return p


def test_reads_colour_and_gray(jpeg):
    bgr = read_image(jpeg)
    gray = read_image(jpeg, gray=True)
    assert bgr.shape == (60, 80, 3) and bgr.dtype == np.uint8
    assert gray.shape == (60, 80)
    info = probe_image(jpeg)
    assert (info.width, info.height, info.format) == (80, 60, "jpeg")


def test_reduced_decode_halves_the_size(jpeg):
    assert read_image(jpeg, gray=True, reduce=2).shape == (30, 40)
    assert read_image(jpeg, gray=True, reduce=8).shape == (8, 10)


def with_exif_orientation(jpeg_bytes: bytes, orientation: int) -> bytes:
    """The JPEG with an EXIF APP1 segment holding only the orientation tag (0x0112) inserted after SOI."""
    ifd = ((1).to_bytes(2, "little") + (0x0112).to_bytes(2, "little") + (3).to_bytes(2, "little")
           + (1).to_bytes(4, "little") + orientation.to_bytes(2, "little") + bytes(2) + bytes(4))
    body = b"Exif\x00\x00" + b"II*\x00" + (8).to_bytes(4, "little") + ifd
    return jpeg_bytes[:2] + b"\xff\xe1" + (len(body) + 2).to_bytes(2, "big") + body + jpeg_bytes[2:]


@pytest.mark.parametrize("orientation", [3, 6, 8])
def test_exif_orientation_is_not_applied(tmp_path, jpeg, orientation):
    # pixels as stored, the frame of the header's size and of COLMAP, OpenSfM and Metashape
    tagged = tmp_path / "tagged.jpg"
    tagged.write_bytes(with_exif_orientation(jpeg.read_bytes(), orientation))
    # OpenCV on its own would rotate this one (the test would show nothing if it did not)
    rotated = cv2.imread(str(tagged), cv2.IMREAD_GRAYSCALE)
    assert rotated.shape == ((80, 60) if orientation in (6, 8) else (60, 80))
    assert not np.array_equal(rotated, cv2.imread(str(jpeg), cv2.IMREAD_GRAYSCALE))
    info = probe_image(tagged)
    for gray in (True, False):
        np.testing.assert_array_equal(read_image(tagged, gray=gray), read_image(jpeg, gray=gray))
    assert read_image(tagged, gray=True).shape == (info.height, info.width)
    np.testing.assert_array_equal(read_image(tagged, reduce=2), read_image(jpeg, reduce=2))
    small, full = read_reduced_colour_then_gray(tagged, 2)
    np.testing.assert_array_equal(small, read_image(jpeg, reduce=2))
    np.testing.assert_array_equal(full.result(), read_image(jpeg, gray=True))


@pytest.mark.parametrize("case, message", [
    ("zero", "empty"), ("truncated", "truncated"), ("text", "not an image"), ("missing", "not found"),
])
def test_bad_files_name_the_file(tmp_path, jpeg, case, message):
    p = tmp_path / f"{case}.jpg"
    if case == "zero":
        p.write_bytes(b"")
    elif case == "truncated":
        p.write_bytes(jpeg.read_bytes()[:200])
    elif case == "text":
        p.write_text("hello")
    for fn in (read_image, probe_image):
        with pytest.raises(InputError) as e:
            fn(p)
        assert message in str(e.value) and str(p) in str(e.value)
        assert "\n" not in str(e.value)


def _noisy_jpeg_bytes() -> bytes:
    img = (np.random.default_rng(0).random((240, 320, 3)) * 255).astype(np.uint8)
    return cv2.imencode(".jpg", img)[1].tobytes()


def test_jpeg_cut_short_with_an_end_marker_is_refused(tmp_path, capfd):
    # a copy that stopped half-way and an end-of-image marker added after it: libjpeg only prints a
    # warning and OpenCV returns the image with its lower half grey
    data = _noisy_jpeg_bytes()
    p = tmp_path / "cut.jpg"
    p.write_bytes(data[: len(data) // 2] + b"\xff\xd9")
    for call in (lambda: read_image(p), lambda: read_image(p, gray=True, reduce=4),
                 lambda: read_reduced_colour_then_gray(p, 2)[1].result()):
        with pytest.raises(InputError) as e:
            call()
        assert "damaged JPEG data" in str(e.value) and str(p) in str(e.value) and "\n" not in str(e.value)
    assert "Corrupt JPEG" not in capfd.readouterr().err  # said once, in the error, not printed as well


def test_jpeg_with_junk_before_its_end_marker_still_reads(tmp_path, capfd):
    # bytes between segments (some cameras write them): every pixel is intact, libjpeg's warning is
    # passed on and the image is returned
    data = _noisy_jpeg_bytes()
    p = tmp_path / "junk.jpg"
    p.write_bytes(data[:-2] + bytes(range(1, 41)) + data[-2:])
    assert np.array_equal(read_image(p), cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR))
    small, gray = read_reduced_colour_then_gray(p, 2)
    assert gray.result().shape == (240, 320) and small.shape == (120, 160, 3)
    assert "extraneous bytes" in capfd.readouterr().err


def test_reduced_colour_then_gray_is_both_decodes_and_refuses_what_cannot_decode(tmp_path, capfd):
    data = _noisy_jpeg_bytes()
    p = tmp_path / "ok.jpg"
    p.write_bytes(data)
    small, gray = read_reduced_colour_then_gray(p, 4)
    assert np.array_equal(small, read_image(p, reduce=4)) and np.array_equal(gray.result(), read_image(p, gray=True))
    bad = tmp_path / "garbage.jpg"
    bad.write_bytes(data[:20] + bytes(range(256)) * 4 + b"\xff\xd9")
    with pytest.raises(InputError) as e:
        read_reduced_colour_then_gray(bad, 2)
    assert "corrupt JPEG" in str(e.value) and str(bad) in str(e.value)
    png = tmp_path / "flat.png"
    cv2.imwrite(str(png), np.full((8, 12, 3), 77, np.uint8))
    small, gray = read_reduced_colour_then_gray(png, 2)
    assert small.shape == (4, 6, 3) and gray.result().shape == (8, 12)
    assert "Corrupt" not in capfd.readouterr().err


def test_png_with_jpg_name_is_read_by_content(tmp_path):
    p = tmp_path / "really_png.jpg"
    ok, buf = cv2.imencode(".png", np.full((5, 7), 99, np.uint8))
    p.write_bytes(buf.tobytes())
    assert read_image(p, gray=True).shape == (5, 7)
    assert probe_image(p).format == "png"


def test_16bit_and_alpha_are_converted(tmp_path):
    p16 = tmp_path / "deep.png"
    cv2.imwrite(str(p16), np.full((4, 6), 40000, np.uint16))
    g = read_image(p16, gray=True)
    assert g.dtype == np.uint8 and int(g[0, 0]) == 40000 >> 8
    pa = tmp_path / "alpha.png"
    cv2.imwrite(str(pa), np.full((4, 6, 4), 77, np.uint8))
    assert read_image(pa).shape == (4, 6, 3)


def test_12_bit_data_in_a_16_bit_file_keep_their_contrast_and_a_marker_is_found(tmp_path):
    # machine-vision and thermal cameras write 10-14-bit data in 16-bit files: the high byte alone
    # left a 12-bit marker 11 grey levels of contrast, under the classical detector's 12
    from cpdetect.classical import ClassicalDetector
    from cpdetect.markers import MarkerSpec, frontal_homography, render_marker

    img = np.full((200, 240), 120.0, np.float32)
    spec = MarkerSpec("circle", size_m=1.0)
    render_marker(spec, frontal_homography((120.3, 99.6), 30.0, 0.4, spec), img.shape).composite(img, 35.0, 220.0)
    twelve = (np.clip(img + 0.5, 0, 255).astype(np.uint16) * 16)  # 12-bit data: 560..3520
    p = tmp_path / "mono12.png"
    cv2.imwrite(str(p), twelve)
    g = read_image(p, gray=True)
    assert int(g.max()) == 220 and int(g.min()) == 35  # shifted by 12 - 8 bits, not 8
    (m,) = ClassicalDetector().detect(str(p)).detections
    assert abs(m.x - 120.3) < 0.1 and abs(m.y - 99.6) < 0.1
    # full-range 16-bit data keep the high byte, as before
    full = tmp_path / "full16.png"
    cv2.imwrite(str(full), (np.clip(img + 0.5, 0, 255).astype(np.uint16) * 257))
    assert np.array_equal(read_image(full, gray=True), np.clip(img + 0.5, 0, 255).astype(np.uint8))
    # float data: [0, 1] to 0..255, up to 255 as they are, larger ones scaled by their maximum
    want = np.clip(img + 0.5, 0, 255).astype(np.int64)
    stretched = np.clip(img * (255.0 / 220.0) + 0.5, 0, 255).astype(np.int64)  # its maximum (1000) to 255
    for name, data, expect in (("unit.tif", img / 255.0, want), ("grey.tif", img, want),
                               ("wide.tif", img * (1000.0 / 220.0), stretched)):
        cv2.imwrite(str(tmp_path / name), data)
        assert np.abs(read_image(tmp_path / name, gray=True).astype(int) - expect).max() <= 1, name


def test_huge_image_is_refused_before_decoding(tmp_path):
    # A valid PNG header announcing 30000 x 30000 pixels; the body is never decoded.
    import struct
    import zlib
    ihdr = struct.pack(">IIBBBBB", 30000, 30000, 8, 0, 0, 0, 0)
    chunk = b"IHDR" + ihdr
    data = b"\x89PNG\r\n\x1a\n" + struct.pack(">I", len(ihdr)) + chunk + struct.pack(">I", zlib.crc32(chunk))
    p = tmp_path / "huge.png"
    p.write_bytes(data)
    for fn in (probe_image, read_image):
        with pytest.raises(InputError, match="too large"):
            fn(p)


def test_list_images(tmp_path, jpeg):
    (tmp_path / "notes.txt").write_text("x")
    assert list_images(tmp_path) == [jpeg]
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(InputError, match="no images"):
        list_images(empty)
    with pytest.raises(InputError, match="not found"):
        list_images(tmp_path / "absent")


def test_a_folder_without_images_says_what_it_holds(tmp_path, jpeg):
    phone = tmp_path / "phone"
    phone.mkdir()
    for k in range(3):
        (phone / f"IMG_{k}.HEIC").write_bytes(b"x")
    (phone / "IMG_9.dng").write_bytes(b"x")
    with pytest.raises(InputError, match="3 HEIC, 1 raw photographs, which cpdetect cannot read"):
        list_images(phone)
    flight = tmp_path / "flight"
    (flight / "a" / "b").mkdir(parents=True)
    (flight / "a" / "b" / "DJI_0001.JPG").write_bytes(jpeg.read_bytes())
    (flight / "empty").mkdir()
    with pytest.raises(InputError, match=r"subfolders hold images \(a\): give each subfolder"):
        list_images(flight)
    empty = tmp_path / "nothing"
    empty.mkdir()
    with pytest.raises(InputError, match=r"in folder$"):
        list_images(empty)


def _garbled(ext: str) -> bytes:
    """A textured image encoded as ``ext`` with 2,000 bytes in the middle of its data overwritten."""
    rng = np.random.default_rng(3)
    img = cv2.GaussianBlur(rng.integers(0, 256, (240, 320, 3)).astype(np.uint8), (0, 0), 2.0)
    data = bytearray(cv2.imencode("." + ext, img)[1].tobytes())
    mid = len(data) // 2
    data[mid:mid + 2000] = rng.integers(0, 256, 2000, dtype=np.uint8).tobytes()
    return bytes(data)


@pytest.mark.parametrize("ext, cut, message", [
    ("png", False, "corrupt PNG (cannot decode: "),
    # libtiff returns an image for a garbled LZW strip, with the decoder's error only printed
    ("tif", False, "damaged TIFF data ("),
    ("bmp", True, "corrupt BMP (cannot decode: Unexpected end of input stream)"),
])
def test_decoder_errors_are_one_error_naming_the_file(tmp_path, capfd, ext, cut, message):
    p = tmp_path / f"garbled.{ext}"
    data = _garbled(ext)
    p.write_bytes(data[: len(data) // 2] if cut else data)
    with pytest.raises(InputError) as e:
        read_image(p)
    assert message in str(e.value) and str(p) in str(e.value) and "\n" not in str(e.value)
    assert capfd.readouterr().err.strip() == ""  # said once, in the error
