"""Real background photographs shipped with cpdetect, their categories and a fixed held-out split.

The photographs live in the package data folder ``cpdetect.data/backgrounds`` (the top-level ``data/``
folder of the checkout) and are described by ``MANIFEST.tsv`` (tab-separated; columns ``file``,
``category``, ``license``, ``attribution`` and provenance). Attribution travels with every synthetic
image: the generator records the background's file name and category in ``markers.json``.

Held-out split: within each category the files are ordered by the SHA-256 of their file name and the
first ``round(0.2 * n)`` (at least one when the category has two or more files) form the ``test`` split;
the rest form ``train``. The split depends only on file names and categories, never on a seed, so a
benchmark on ``--split test`` always sees backgrounds that training on ``--split train`` never saw.
"""
from __future__ import annotations

import csv
import hashlib
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .errors import InputError, UsageError
from .package_data import data_path

SPLITS = ("train", "test", "all")
TEST_FRACTION = 0.2


@dataclass(frozen=True)
class Background:
    """One background photograph: absolute ``path``, ``file`` name, ``category`` and ``split``
    ("train" or "test"), and the MANIFEST's ``license`` and ``attribution`` text."""

    path: Path
    file: str
    category: str
    split: str
    license: str = ""
    attribution: str = ""


def default_folder() -> Path:
    """The shipped backgrounds folder (works in a checkout and after ``pip install``)."""
    return data_path("backgrounds")


def _name_hash(name: str) -> str:
    return hashlib.sha256(name.encode("utf-8")).hexdigest()


def _assign_splits(rows: list[dict]) -> dict[str, str]:
    by_cat: dict[str, list[str]] = {}
    for r in rows:
        by_cat.setdefault(r["category"], []).append(r["file"])
    split: dict[str, str] = {}
    for files in by_cat.values():
        ordered = sorted(files, key=lambda f: (_name_hash(f), f))
        n_test = int(round(TEST_FRACTION * len(ordered)))
        if len(ordered) >= 2:
            n_test = max(n_test, 1)
        for k, f in enumerate(ordered):
            split[f] = "test" if k < n_test else "train"
    return split


def list_backgrounds(split: str = "all", folder: str | os.PathLike | None = None,
                     categories: tuple[str, ...] | None = None) -> list[Background]:
    """Backgrounds listed in ``folder/MANIFEST.tsv`` (default: the shipped set), sorted by file name.

    ``split`` is "train", "test" or "all"; ``categories`` optionally keeps only those categories.
    Raises :class:`InputError` naming the manifest when it is missing or malformed, or a listed file
    is missing; :class:`UsageError` for an unknown split or when the selection is empty.
    """
    if split not in SPLITS:
        raise UsageError(f"unknown background split {split!r}; valid: {', '.join(SPLITS)}")
    root = Path(folder) if folder is not None else default_folder()
    manifest = root / "MANIFEST.tsv"
    if not manifest.is_file():
        raise InputError("background manifest not found", manifest)
    try:
        with open(manifest, newline="", encoding="utf-8") as fh:
            reader = csv.DictReader(fh, delimiter="\t")
            rows = []
            for lineno, row in enumerate(reader, start=2):
                if not row.get("file") or not row.get("category"):
                    raise InputError("row lacks 'file' or 'category'", manifest, lineno)
                rows.append({k: (v or "").strip() for k, v in row.items() if k is not None})
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise InputError(f"cannot read manifest: {exc}", manifest) from None
    splits = _assign_splits(rows)
    out = []
    for r in sorted(rows, key=lambda r: r["file"]):
        if split != "all" and splits[r["file"]] != split:
            continue
        if categories is not None and r["category"] not in categories:
            continue
        path = root / r["file"]
        if not path.is_file():
            raise InputError(f"background listed in {manifest.name} is missing", path)
        out.append(Background(path=path, file=r["file"], category=r["category"], split=splits[r["file"]],
                              license=r.get("license", ""), attribution=r.get("attribution", "")))
    if not out:
        raise UsageError(f"no backgrounds selected (split={split!r}, categories={categories}) in {root}")
    return out


class BackgroundLibrary:
    """Decoded backgrounds (uint8 BGR), loaded on first use and kept for the library's lifetime."""

    def __init__(self, backgrounds: list[Background]):
        if not backgrounds:
            raise ValueError("empty background list")
        self.backgrounds = list(backgrounds)
        self._cache: dict[str, np.ndarray] = {}

    def __len__(self) -> int:
        return len(self.backgrounds)

    def image(self, index: int) -> np.ndarray:
        """The ``index``-th background as a read-only uint8 BGR array (H, W, 3)."""
        from .imageio import read_image

        bg = self.backgrounds[index]
        img = self._cache.get(bg.file)
        if img is None:
            img = read_image(bg.path)
            img.setflags(write=False)
            self._cache[bg.file] = img
        return img
