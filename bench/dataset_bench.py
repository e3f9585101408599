"""What the benches that run ``hma`` over a dataset share: their arguments, loading the dataset with a
one-line error, and how a figure is printed."""
from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path


def fmt(v) -> str:
    """A figure to 4 decimals; "n/a" for None or NaN (undefined)."""
    return "n/a" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:.4f}"


def parse_args(doc: str, results: Path, argv=None) -> argparse.Namespace:
    """``DATASET [--limit N] [--threads N] [--out F]``, described by the first line of ``doc``."""
    ap = argparse.ArgumentParser(description=doc.splitlines()[0])
    ap.add_argument("dataset")
    ap.add_argument("--limit", type=int, help="the first N images only")
    ap.add_argument("--threads", type=int, default=1, help="network threads (1: two runs share 2 cores)")
    ap.add_argument("--out", default=str(results))
    return ap.parse_args(argv)


def load_dataset_or_none(path: str):
    """The dataset at ``path`` (:func:`cpdetect.dataset.load_dataset`), or None after printing why
    not in one line on standard error."""
    from cpdetect.dataset import load_dataset
    from cpdetect.errors import InputError

    try:
        return load_dataset(path)
    except (InputError, OSError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return None
