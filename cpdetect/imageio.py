"""Reading photographs safely: every failure is a one-line :class:`InputError` naming the file.

Images come back as uint8 (8-bit gray or BGR). 16-bit images are scaled to 8 bits by their data's
bit depth (10-, 12- and 14-bit data in 16-bit files keep their contrast), alpha is dropped.
Pixels come back as stored in the file: an EXIF orientation tag is *not* applied (OpenCV applies it
to JPEGs by default, and not to other formats). COLMAP and OpenSfM / OpenDroneMap measure image
points in the stored frame too; Metashape keeps the tag beside its sensor's stored size. The sizes
that :func:`probe_image` reads from the header are that frame's as well, so a portrait photograph's
detections, its size and its camera model agree.
``reduce`` (1, 2, 4 or 8) decodes JPEGs at reduced size through libjpeg's DCT scaling
(``cv2.IMREAD_REDUCED_*``), which is several times faster than decoding in full and resizing.
"""
from __future__ import annotations

import os
import sys
import tempfile
import threading
from contextlib import contextmanager
from dataclasses import dataclass
from itertools import islice
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from .errors import InputError, opencv_words

if TYPE_CHECKING:
    from concurrent.futures import Future

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".tif", ".tiff", ".bmp")
MAX_PIXELS = 400_000_000  # 20000 x 20000; larger is refused before decoding
_TAIL = 1024  # bytes read at the end of a file: JPEG end-of-image marker, PNG IEND chunk (after a little junk)

_REDUCED_GRAY = {1: "IMREAD_GRAYSCALE", 2: "IMREAD_REDUCED_GRAYSCALE_2", 4: "IMREAD_REDUCED_GRAYSCALE_4",
                 8: "IMREAD_REDUCED_GRAYSCALE_8"}
_REDUCED_COLOR = {1: "IMREAD_COLOR", 2: "IMREAD_REDUCED_COLOR_2", 4: "IMREAD_REDUCED_COLOR_4",
                  8: "IMREAD_REDUCED_COLOR_8"}


@dataclass(frozen=True)
class ImageInfo:
    path: str
    width: int
    height: int
    format: str  # "jpeg", "png", "tiff", "bmp"


# formats people do photograph in, which OpenCV's build here may or may not decode reliably:
# named in the error, so that a WebP or HEIC file is not called "not an image"
_UNSUPPORTED = (
    (lambda h: h[:4] == b"RIFF" and h[8:12] == b"WEBP", "WebP"),
    (lambda h: h[4:8] == b"ftyp" and h[8:12] in (b"heic", b"heix", b"mif1", b"msf1", b"hevc", b"heim", b"heis"), "HEIC/HEIF"),
    (lambda h: h[4:8] == b"ftyp" and h[8:12] in (b"avif", b"avis"), "AVIF"),
    (lambda h: h.startswith(b"\x00\x00\x00\x0cjP  \r\n\x87\n") or h.startswith(b"\xff\x4f\xff\x51"), "JPEG 2000"),
    (lambda h: h[:6] in (b"GIF87a", b"GIF89a"), "GIF"),
)


def _not_an_image(head: bytes) -> str:
    """The error for a file whose first bytes are no JPEG, PNG, TIFF or BMP."""
    for test, name in _UNSUPPORTED:
        if test(head):
            return f"unsupported image format ({name}): convert it to JPEG, PNG or TIFF"
    return "not an image (unrecognised format)"


_NOT_A_FILE = "neither an image file nor a folder (a device, pipe or socket)"


def _sniff(head: bytes) -> str | None:
    if head.startswith(b"\xff\xd8\xff"):
        return "jpeg"
    if head.startswith(b"\x89PNG\r\n\x1a\n"):
        return "png"
    if head[:4] in (b"II*\x00", b"MM\x00*"):
        return "tiff"
    if head.startswith(b"BM"):
        return "bmp"
    return None


def _jpeg_size(data: bytes) -> tuple[int, int] | None:
    """(width, height) from the JPEG SOF marker, without decoding."""
    i = 2
    n = len(data)
    while i + 9 < n:
        if data[i] != 0xFF:
            i += 1
            continue
        marker = data[i + 1]
        if marker in (0xD8, 0x01) or 0xD0 <= marker <= 0xD7 or marker == 0xFF:
            i += 1 if marker == 0xFF else 2
            continue
        seg_len = int.from_bytes(data[i + 2:i + 4], "big")
        if marker in (0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF):
            h = int.from_bytes(data[i + 5:i + 7], "big")
            w = int.from_bytes(data[i + 7:i + 9], "big")
            return w, h
        i += 2 + seg_len
    return None


def probe_image(path: str | os.PathLike) -> ImageInfo:
    """Check that ``path`` is a readable, complete, not oversized image and return its size.

    Reads the header (and, for JPEG, the trailing end-of-image marker) without a full decode.
    """
    p = Path(path)
    if not p.exists():
        raise InputError("image not found", p)
    if p.is_dir():
        raise InputError("expected an image file, found a folder", p)
    if not p.is_file():
        raise InputError(_NOT_A_FILE, p)
    try:
        size = p.stat().st_size
        with open(p, "rb") as fh:
            head = fh.read(65536)
            tail = b""
            if size >= 2:
                fh.seek(max(0, size - _TAIL))
                tail = fh.read(_TAIL)
    except OSError as exc:
        raise InputError(f"cannot read image: {exc.strerror or exc}", p) from None
    if size == 0:
        raise InputError("image file is empty (0 bytes)", p)
    fmt = _sniff(head)
    if fmt is None:
        raise InputError(_not_an_image(head), p)
    width = height = None
    if fmt == "jpeg":
        if tail[-2:] != b"\xff\xd9":
            raise InputError("truncated JPEG (no end-of-image marker)", p)
        wh = _jpeg_size(head)
        if wh is None:
            with open(p, "rb") as fh:
                wh = _jpeg_size(fh.read())
        if wh is None:
            raise InputError("corrupt JPEG (no frame header)", p)
        width, height = wh
    elif fmt == "png":
        if len(head) < 24:
            raise InputError("truncated PNG", p)
        width = int.from_bytes(head[16:20], "big")
        height = int.from_bytes(head[20:24], "big")
        if b"IEND" not in tail and 0 < width * height <= MAX_PIXELS:
            raise InputError("truncated PNG (no IEND chunk at the end)", p)
    if width is not None and height is not None:
        if width <= 0 or height <= 0:
            raise InputError(f"image has an invalid size {width}x{height}", p)
        if width * height > MAX_PIXELS:
            raise InputError(f"image too large ({width}x{height} > {MAX_PIXELS // 1_000_000} MP)", p)
        return ImageInfo(str(p), int(width), int(height), fmt)
    # TIFF/BMP: decode header through OpenCV (rare inputs, small cost)
    img = read_image(p, gray=True)
    return ImageInfo(str(p), int(img.shape[1]), int(img.shape[0]), fmt)


def _to_uint8(img: np.ndarray) -> np.ndarray:
    """8 bits from a decoded image. 16-bit: shifted right by the data's own bit depth less 8, so 10-,
    12- or 14-bit data in a 16-bit file (machine-vision and thermal cameras) keep their contrast (the
    high byte alone left 12-bit data 16 grey levels); full-range data lose their low byte as before.
    Float: [0, 1] to 0..255, data up to 255 as they are, larger ones scaled by their maximum. All linear (no
    clipping, no stretch): the detectors' contrast thresholds keep their meaning in grey levels."""
    if img.dtype == np.uint8:
        return img
    if img.dtype == np.uint16:
        shift = max(int(img.max(initial=0)).bit_length() - 8, 0)
        return (img >> shift).astype(np.uint8)
    if np.issubdtype(img.dtype, np.floating):
        img = np.nan_to_num(img, nan=0.0, posinf=0.0, neginf=0.0)
        top = float(img.max(initial=0.0))
        scale = 255.0 if top <= 1.0 else 1.0 if top <= 255.0 else 255.0 / top
        return np.clip(img * scale + 0.5, 0, 255).astype(np.uint8)
    return np.clip(img, 0, 255).astype(np.uint8)


def read_image(path: str | os.PathLike, gray: bool = False, reduce: int = 1) -> np.ndarray:
    """Decode an image as uint8 gray (HxW) or BGR (HxWx3).

    ``reduce`` in {1, 2, 4, 8} decodes at 1/reduce size (rounded up, as libjpeg does); for non-JPEG
    files the full image is decoded and resized with area averaging. A JPEG whose data libjpeg finds
    damaged (it would fill the rest with grey) is an :class:`InputError`, like an unreadable one.
    """
    _check_reduce(reduce)
    p = Path(path)
    data, fmt = _checked_bytes(p)
    if fmt != "jpeg":
        return _decode_other(data, fmt, p, gray, reduce)
    with _captured_stderr() as printed:
        img = _decode_jpeg(data, p, gray, reduce)
    _raise_if_damaged(printed, p)
    return img


def read_reduced_colour_then_gray(path: str | os.PathLike, reduce: int) -> tuple[np.ndarray, "Future[np.ndarray]"]:
    """The BGR image at 1/``reduce`` size of one JPEG, and a future of its full-size gray image,
    decoded meanwhile in a second thread, so that a caller's work on the small image overlaps the
    big decode. The future raises :class:`InputError` for a damaged file (its warnings are
    captured as :func:`read_image` captures them, for both decodes); wait for it (``result()`` or
    ``exception()``) before anything else writes to standard error. Other formats: the future
    holds the gray image already."""
    from concurrent.futures import Future, ThreadPoolExecutor

    _check_reduce(reduce)
    p = Path(path)
    data, fmt = _checked_bytes(p)
    if fmt != "jpeg":
        done: Future = Future()
        done.set_result(_decode_other(data, fmt, p, True, 1))
        return _decode_other(data, fmt, p, False, reduce), done
    capturing, small_done = threading.Event(), threading.Event()

    def full() -> np.ndarray:
        try:
            with _captured_stderr() as printed:
                capturing.set()
                try:
                    gray = _decode_jpeg(data, p, True, 1)
                finally:
                    small_done.wait()  # the small decode's warnings land in the same capture
        finally:
            capturing.set()
        _raise_if_damaged(printed, p)
        return gray

    pool = ThreadPoolExecutor(1)
    future = pool.submit(full)
    pool.shutdown(wait=False)
    capturing.wait()
    try:
        small = _decode_jpeg(data, p, False, reduce)
    except BaseException:
        small_done.set()
        future.exception()  # the capture ends before the error is reported
        raise
    small_done.set()
    return small, future


def _check_reduce(reduce: int) -> None:
    if reduce not in (1, 2, 4, 8):
        raise ValueError(f"reduce must be 1, 2, 4 or 8, got {reduce}")


def _checked_bytes(p: Path) -> tuple[np.ndarray, str]:
    """The file's bytes and format, after the checks that need no decoding."""
    if p.exists() and not p.is_file() and not p.is_dir():
        raise InputError(_NOT_A_FILE, p)  # reading a pipe or a device could block or never end
    try:
        data = np.fromfile(str(p), dtype=np.uint8)
    except FileNotFoundError:
        raise InputError("image not found", p) from None
    except IsADirectoryError:
        raise InputError("expected an image file, found a folder", p) from None
    except OSError as exc:
        raise InputError(f"cannot read image: {exc.strerror or exc}", p) from None
    if data.size == 0:
        raise InputError("image file is empty (0 bytes)", p)
    info_fmt = _sniff(data[:16].tobytes())
    if info_fmt is None:
        raise InputError(_not_an_image(data[:16].tobytes()), p)
    if info_fmt == "jpeg" and data[-2:].tobytes() != b"\xff\xd9":
        raise InputError("truncated JPEG (no end-of-image marker)", p)
    wh = None
    if info_fmt == "jpeg":
        wh = _jpeg_size(data[:65536].tobytes()) or _jpeg_size(data.tobytes())
    elif info_fmt == "png" and data.size >= 24:
        wh = (int.from_bytes(data[16:20].tobytes(), "big"), int.from_bytes(data[20:24].tobytes(), "big"))
    if wh is not None and wh[0] * wh[1] > MAX_PIXELS:
        raise InputError(f"image too large ({wh[0]}x{wh[1]} > {MAX_PIXELS // 1_000_000} MP)", p)
    if info_fmt == "png" and b"IEND" not in data[-_TAIL:].tobytes():
        raise InputError("truncated PNG (no IEND chunk at the end)", p)
    return data, info_fmt


def _decode_jpeg(data: np.ndarray, p: Path, gray: bool, reduce: int) -> np.ndarray:
    import cv2

    flags = getattr(cv2, (_REDUCED_GRAY if gray else _REDUCED_COLOR)[reduce]) | cv2.IMREAD_IGNORE_ORIENTATION
    img = cv2.imdecode(data, flags)
    if img is None:
        raise InputError("corrupt JPEG (cannot decode)", p)
    return img


# libjpeg reports damaged data only as a printed warning, and OpenCV returns the image with the rest
# filled in grey: these lines mean pixels did not come from the file ("N extraneous bytes before
# marker" is junk between segments, common in camera files, with every pixel intact)
_JPEG_DAMAGE = ("corrupt jpeg data", "premature end of jpeg file")
_BENIGN = ("extraneous bytes",)
_STDERR_LOCK = threading.Lock()


@contextmanager
def _captured_stderr():
    """Collects the lines written to the process's standard error (file descriptor 2, where libjpeg
    prints) meanwhile into the yielded list, filled at exit; one capture at a time. Where fd 2
    cannot be redirected, nothing is captured."""
    lines: list[str] = []
    with _STDERR_LOCK:
        saved = None
        try:
            if sys.stderr is not None:
                sys.stderr.flush()
            saved = os.dup(2)
            tmp = tempfile.TemporaryFile()
        except (OSError, ValueError):
            if saved is not None:
                os.close(saved)
            yield lines
            return
        with tmp:
            os.dup2(tmp.fileno(), 2)
            try:
                yield lines
            finally:
                os.dup2(saved, 2)
                os.close(saved)
                tmp.seek(0)
                lines.extend(tmp.read().decode("utf-8", "replace").splitlines())


def _pass_on(lines: list[str]) -> None:
    """Writes captured decoder lines that are not turned into an error back to standard error."""
    if lines:
        os.write(2, ("\n".join(lines) + "\n").encode())


def _raise_if_damaged(printed: list[str], p: Path) -> None:
    """InputError for the first damage warning among ``printed``; the other lines are passed on."""
    damage = [ln for ln in printed
              if ln.lower().startswith(_JPEG_DAMAGE) and not any(b in ln.lower() for b in _BENIGN)]
    _pass_on([ln for ln in printed if ln not in damage])
    if damage:
        what = damage[0].split(":", 1)[-1].strip() if damage[0].lower().startswith("corrupt") else damage[0]
        raise InputError(f"damaged JPEG data ({what}; the decoder would fill the rest in grey)", p)


# what libpng, libtiff (through OpenCV's log) and OpenCV's own decoders print about data they could
# not decode; libtiff may still return an image whose damaged strips are left blank or garbled (an
# LZW stream with a wrong code: "Using code not yet in table")
_DECODE_ERRORS = ("libpng error: ", "TIFF_Error ", "can't read data: ", "readData OpenCV TIFF")
def _decode_errors(printed: list[str]) -> list[str]:
    """The decoder's own words for each error line among ``printed``; the other non-blank lines are
    passed on to standard error."""
    errors, rest = [], []
    for ln in printed:
        hit = next((m for m in _DECODE_ERRORS if m in ln), None)
        if hit is None:
            if ln.strip():
                rest.append(ln)
            continue
        words = ln.split(hit, 1)[1].strip(" :")
        if hit == "readData OpenCV TIFF":  # "(line 1234): failed TIFFReadRGBAStrip(tif, y, ...)"
            words = words.split("): ", 1)[-1]
        errors.append(opencv_words(words) or ln.strip())
    _pass_on(rest)
    return errors


def _decode_other(data: np.ndarray, info_fmt: str, p: Path, gray: bool, reduce: int) -> np.ndarray:
    import cv2

    fmt = info_fmt.upper()
    # UNCHANGED keeps 16-bit depth and alpha so they can be converted deliberately below.
    with _captured_stderr() as printed:
        img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
    errors = _decode_errors(printed)
    if img is None:
        raise InputError(f"corrupt {fmt} (cannot decode{': ' + errors[0] if errors else ''})", p)
    if errors:
        raise InputError(f"damaged {fmt} data ({errors[0]}; part of the image would not come from the file)", p)
    if img.ndim == 2 or img.shape[2] == 1:
        img = img.reshape(img.shape[0], img.shape[1])
        if not gray:
            img = cv2.cvtColor(_to_uint8(img), cv2.COLOR_GRAY2BGR)
    else:
        if img.shape[2] == 4:
            img = img[:, :, :3]
        if gray:
            img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    img = _to_uint8(img)
    if reduce != 1:
        h, w = img.shape[:2]
        img = cv2.resize(img, ((w + reduce - 1) // reduce, (h + reduce - 1) // reduce),
                         interpolation=cv2.INTER_AREA)
    return np.ascontiguousarray(img)


def paint_image(bgr: np.ndarray) -> np.ndarray:
    """The max of the three channels (HSV value, uint8 HxW) of a BGR image: coloured paint keeps its
    full brightness there, where luminance weights red by 0.3."""
    import cv2

    b, g, r = cv2.split(bgr)
    return cv2.max(cv2.max(b, g), r)


def chroma_image(bgr: np.ndarray) -> np.ndarray:
    """The max less the min of the three channels (HSV chroma, uint8 HxW) of a BGR image: 0 for any
    grey, light or dark, so paint shows against gray or black quadrants by its colour alone, even
    where its brightness matches theirs (a dull pink on mid gray has next to no contrast in either
    luminance or the max of the channels)."""
    import cv2

    b, g, r = cv2.split(bgr)
    return cv2.subtract(cv2.max(cv2.max(b, g), r), cv2.min(cv2.min(b, g), r))


def list_images(path: str | os.PathLike) -> list[Path]:
    """A single image, or the images directly inside a folder (sorted by name)."""
    p = Path(path)
    if not p.exists():
        raise InputError("not found", p)
    if p.is_file():
        return [p]
    if not p.is_dir():  # a device, pipe or socket: reading one could block or never end
        raise InputError(_NOT_A_FILE, p)
    files = sorted(f for f in p.iterdir() if f.is_file() and f.suffix.lower() in IMAGE_SUFFIXES)
    if not files:
        raise InputError(f"no images ({', '.join(IMAGE_SUFFIXES)}) in folder{_what_is_there(p)}", p)
    return files


# photographs that OpenCV cannot decode, by suffix: what to tell their owner
_UNREADABLE = {".heic": "HEIC", ".heif": "HEIF", ".dng": "raw", ".cr2": "raw", ".cr3": "raw", ".nef": "raw",
               ".arw": "raw", ".orf": "raw", ".rw2": "raw", ".raf": "raw", ".webp": "WebP"}


def _what_is_there(folder: Path) -> str:
    """For the error of a folder without images: the photographs it holds in formats cpdetect cannot
    read, or the images in its subfolders (only the folder itself is listed), as "; ..." or ""."""
    kinds: dict[str, int] = {}
    for f in folder.iterdir():
        kind = _UNREADABLE.get(f.suffix.lower())
        if kind and f.is_file():
            kinds[kind] = kinds.get(kind, 0) + 1
    if kinds:
        found = ", ".join(f"{n} {k}" for k, n in sorted(kinds.items(), key=lambda kv: -kv[1]))
        return f"; it holds {found} photographs, which cpdetect cannot read: convert them to JPEG or TIFF"
    # a bounded look (the first 2,000 entries under each subfolder): this is only an error message
    below = [d for d in sorted(folder.iterdir()) if d.is_dir()
             and any(f.suffix.lower() in IMAGE_SUFFIXES for f in islice(d.rglob("*"), 2000))]
    if below:
        names = ", ".join(d.name for d in below[:3]) + (", ..." if len(below) > 3 else "")
        return f"; subfolders hold images ({names}): give each subfolder, only a folder's own files are read"
    return ""
