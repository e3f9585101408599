"""SHA-256 digests of a model folder's weight files, kept in ``SHA256SUMS`` beside them.

A weight file with a few bytes changed (a bad copy, a damaged disk) still loads, in torch and in
OpenCV alike, and the network then quietly finds nothing. So :func:`learned.hma.save_model` and
``cpdetect export-onnx`` into a model folder record each file's digest, and the loaders compare it
before use. The file has the format of GNU ``sha256sum`` (``<64 hex>  <name>`` per line), so
``sha256sum -c SHA256SUMS`` checks a folder by hand. A file without a line is not checked (a folder
trained before digests were kept, or assembled by hand). No torch here: the OpenCV path uses it too.
"""
from __future__ import annotations

import hashlib
import os
import re
from pathlib import Path

DIGEST_FILE = "SHA256SUMS"
_LINE = re.compile(r"^([0-9a-f]{64}) [ *](.+)$")


def file_sha256(path: str | os.PathLike) -> str:
    """Hex SHA-256 of a file's bytes."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def read_digests(folder: str | os.PathLike) -> dict[str, str]:
    """{file name: hex digest} from ``folder/SHA256SUMS``; {} when there is none. InputError naming
    the file for a line that is not ``<64 hex>  <name>``."""
    from cpdetect.errors import InputError

    p = Path(folder) / DIGEST_FILE
    try:
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError:
        return {}
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"cannot read the weights' digests: {exc}", p) from None
    out: dict[str, str] = {}
    for i, line in enumerate(text.splitlines(), 1):
        if not line.strip():
            continue
        m = _LINE.match(line.strip())
        if not m:
            raise InputError(f"line {i} is not '<sha256>  <file name>'", p)
        out[m.group(2)] = m.group(1)
    return out


def record_digest(path: str | os.PathLike) -> None:
    """Set ``path``'s line in the ``SHA256SUMS`` of its folder (written atomically, other lines kept)."""
    from cpdetect.fileio import write_text_atomic

    p = Path(path)
    sums = read_digests(p.parent)
    sums[p.name] = file_sha256(p)
    write_text_atomic(p.parent / DIGEST_FILE, "".join(f"{d}  {n}\n" for n, d in sorted(sums.items())))


def check_digest(path: str | os.PathLike) -> None:
    """InputError naming ``path`` when its folder's ``SHA256SUMS`` lists it with another digest."""
    from cpdetect.errors import InputError

    p = Path(path)
    want = read_digests(p.parent).get(p.name)
    if want is not None and file_sha256(p) != want:
        raise InputError(f"damaged: its SHA-256 is not the one in {DIGEST_FILE} (copy the model folder again; "
                         f"for a file replaced on purpose, delete its line there)", p)


__all__ = ["DIGEST_FILE", "file_sha256", "read_digests", "record_digest", "check_digest"]
