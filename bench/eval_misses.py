"""Shared by the miss-stage benches: read the metrics JSON of ``cpdetect eval ... --out F`` and walk its misses."""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any, Iterator


def arguments(doc: str, detector: str, results: Path) -> argparse.ArgumentParser:
    """The command line both miss-stage benches share: the metrics JSON and ``--out``."""
    ap = argparse.ArgumentParser(description=doc.splitlines()[0])
    ap.add_argument("eval_json", help=f"metrics JSON of `cpdetect eval DIR --detector {detector} --out F`")
    ap.add_argument("--out", default=str(results), help=f"JSON to write (default {results})")
    return ap


def read_eval(path: str, detector: str) -> tuple[dict, Any] | None:
    """The metrics of ``cpdetect eval DIR --detector DETECTOR --out F`` in ``path`` and the dataset
    they name; None after printing one line ("error: PATH: problem") when either cannot be read."""
    from cpdetect.dataset import load_dataset
    from cpdetect.errors import InputError

    try:
        ev = json.loads(Path(path).read_text())
        if not isinstance(ev, dict) or ev.get("detector") != detector or "per_image" not in ev or "dataset" not in ev:
            raise ValueError(f"not the metrics of `cpdetect eval --detector {detector} --out F`")
        return ev, load_dataset(ev["dataset"])
    except FileNotFoundError:
        print(f"error: {path}: file not found", file=sys.stderr)
    except (InputError, OSError, ValueError) as exc:
        print(f"error: {path}: {exc}", file=sys.stderr)
    return None


def images_with_misses(ev: dict, ds: Any) -> Iterator[tuple[dict, Any]]:
    """(per-image record, dataset item) of each image with a missed marker; raises
    :class:`cpdetect.errors.InputError` for an image the dataset does not hold."""
    from cpdetect.errors import InputError

    items = {it.file: it for it in ds.images}
    for rec in ev["per_image"]:
        if not rec["missed"]:
            continue
        item = items.get(rec["file"])
        if item is None:
            raise InputError("not in the dataset the metrics name", Path(ev["dataset"]) / rec["file"])
        yield rec, item
