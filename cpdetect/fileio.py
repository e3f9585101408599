"""Atomic file output: a reader never sees a half-written file, a failed write leaves nothing behind."""
from __future__ import annotations

import json
import os
import tempfile
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Iterator

from .errors import InputError


def cannot_write(exc: OSError, path: str | os.PathLike) -> InputError:
    """The InputError for an output ``path`` that could not be created: where a folder on the way is
    an existing file, it says so and names that file (the system's own words are "File exists" or
    "Not a directory", which do not say which part is wrong)."""
    for folder in Path(path).parents:
        if folder.exists() and not folder.is_dir():
            return InputError(f"cannot write here: {folder} is a file, not a folder", path)
    return InputError(f"cannot write here: {exc.strerror or exc}", path)


def output_target(path: str | os.PathLike) -> Path:
    """The file an output named ``path`` is written to: a symbolic link's target (so that the rename
    of :func:`atomic_path` replaces the file it points to, not the link). InputError naming ``path``
    for an existing device, pipe or socket: renaming a file onto ``/dev/null`` as root replaces the
    device itself, and writing into a pipe is not atomic."""
    given = Path(path)
    try:
        link = given.is_symlink()
        target = Path(os.path.realpath(given)) if link else given
        exists = target.exists()
    except OSError as exc:  # e.g. a name over 255 bytes
        raise cannot_write(exc, given) from None
    if exists and not target.is_file() and not target.is_dir():
        raise InputError("not a regular file (a device, pipe or socket); outputs are written to files", given)
    if link and not exists and not target.parent.is_dir():
        raise InputError(f"a link to {target}, which cannot be created", given)
    return target


@contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path in the target's folder; rename it onto ``path`` only on success.

    The folder is created if needed. A write that raises removes the temporary file and leaves any
    previous ``path`` untouched. ``path`` goes through :func:`output_target` (links followed,
    devices and pipes refused).
    """
    path = output_target(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        # the temporary name stays within the 255 bytes a name may have wherever the target's does
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name[:64]}.", suffix=".part", dir=path.parent)
    except OSError as exc:
        raise cannot_write(exc, path) from None
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        if tmp_path.is_file():
            # mkstemp creates 0600 files; outputs get the usual permissions under the user's umask.
            umask = os.umask(0)
            os.umask(umask)
            os.chmod(tmp_path, 0o666 & ~umask)
        os.replace(tmp_path, path)
    except BaseException:
        tmp_path.unlink(missing_ok=True)
        raise


def write_bytes_atomic(path: str | os.PathLike, data: bytes) -> None:
    with atomic_path(path) as tmp:
        try:
            with open(tmp, "wb") as fh:
                fh.write(data)
                fh.flush()
                os.fsync(fh.fileno())
        except OSError as exc:
            raise InputError(f"cannot write: {exc.strerror or exc}", path) from None


def write_text_atomic(path: str | os.PathLike, text: str) -> None:
    write_bytes_atomic(path, text.encode("utf-8"))


def write_json_atomic(path: str | os.PathLike, obj: Any, indent: int | None = 1) -> None:
    write_text_atomic(path, json.dumps(obj, indent=indent, allow_nan=False) + "\n")


def read_text_utf8(path: str | os.PathLike, what: str = "file") -> str:
    """Read a UTF-8 text file, turning every failure (missing, a folder, unreadable, not UTF-8) into a
    one-line :class:`InputError` naming ``path``."""
    path = Path(path)
    if not path.exists():
        raise InputError(f"{what} not found", path)
    if path.is_dir():
        raise InputError(f"expected a {what}, found a folder", path)
    if not path.is_file():  # reading a pipe or a device could block or never end
        raise InputError(f"expected a {what}, found a device, pipe or socket", path)
    try:
        return path.read_bytes().decode("utf-8")
    except UnicodeDecodeError as exc:
        raise InputError(f"not UTF-8 text (byte {exc.start})", path) from None
    except OSError as exc:
        raise InputError(f"cannot read: {exc.strerror or exc}", path) from None


def read_json(path: str | os.PathLike, what: str = "JSON file") -> Any:
    """Read a JSON file, turning every failure into a one-line :class:`InputError`."""
    text = read_text_utf8(path, what)
    try:
        return json.loads(text)
    except json.JSONDecodeError as exc:
        raise InputError(f"not valid JSON: {exc.msg}", path, exc.lineno) from None


@contextmanager
def staged_outputs(folder: str | os.PathLike, stale: tuple[str, ...] = ()) -> Iterator[Path]:
    """Write a set of outputs together: yield a temporary folder inside ``folder``; when the block ends
    normally, move every file written there onto ``folder`` (each move atomic, replacing a previous
    file) and delete the names in ``stale`` that were not rewritten; when it raises, delete the
    temporary folder: ``folder`` keeps exactly what it had, no output is half-written and none is from
    this run while another is from the previous one.
    """
    import shutil

    folder = Path(folder)
    try:
        folder.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=".staged-", dir=folder))
    except OSError as exc:
        raise cannot_write(exc, folder) from None
    try:
        yield tmp
        written = sorted(p.relative_to(tmp) for p in tmp.rglob("*") if p.is_file())
        for rel in written:
            (folder / rel).parent.mkdir(parents=True, exist_ok=True)
            os.replace(tmp / rel, folder / rel)
        for name in stale:
            if Path(name) not in written:
                (folder / name).unlink(missing_ok=True)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
