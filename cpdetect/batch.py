"""Running a detector over many images, resumably, with identical results serial or in parallel.

Output: one JSON file (``cpdetect.detections/1``, see docs/formats.md)::

    {"format": "cpdetect.detections/1", "detector": NAME, "settings": {...},
     "images": [{"file": REL, "width": W, "height": H, "seconds": S,
                 "detections": [{"x", "y", "score", "type", "radius_px", "sigma_px"}, ...]}
                or {"file": REL, "error": MESSAGE}]}

``file`` is the image path relative to the input root (the folder given, or the folder of a single
image), with "/" separators. While running, each finished image is written atomically to
``<out>.parts/<sha1 of file>.json``; a rerun with the same output skips images already done (the part
records the detector and its settings; a part made with other settings is redone). The final file is
assembled in input order and the parts folder is removed after it is written.
"""
from __future__ import annotations

import hashlib
import json
import logging
import os
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Sequence

from .errors import CpdetectError, InputError
from .fileio import write_json_atomic

log = logging.getLogger(__name__)

FORMAT = "cpdetect.detections/1"


@dataclass(frozen=True)
class BatchJob:
    """One image to process: absolute ``path`` and its ``rel`` name (key in the output)."""

    path: str
    rel: str


def collect_jobs(inputs: Sequence[str | os.PathLike]) -> list[BatchJob]:
    """Images from files and/or folders (a folder: the images directly inside it, sorted)."""
    from .imageio import list_images

    jobs: list[BatchJob] = []
    seen: set[str] = set()
    for item in inputs:
        p = Path(item)
        root = p if p.is_dir() else p.parent
        for f in list_images(p):
            rel = f.relative_to(root).as_posix() if p.is_dir() else f.name
            key = str(f.resolve())
            if key in seen:
                continue
            seen.add(key)
            jobs.append(BatchJob(str(f), rel))
    rels = [j.rel for j in jobs]
    dup = sorted({r for r in rels if rels.count(r) > 1})
    if dup:
        raise InputError(f"two inputs share the image name {dup[0]!r}; pass one folder or distinct names", dup[0])
    return jobs


def part_name(rel: str) -> str:
    return hashlib.sha1(rel.encode("utf-8")).hexdigest()[:20] + ".json"


def run_one(detector: Any, job: BatchJob, skip_bad: bool) -> dict:
    """Detect in one image; a bad image raises, or with ``skip_bad`` gives an error record."""
    from .imageio import probe_image, read_image

    try:
        info = probe_image(job.path)
        # detectors that decode paths themselves (reduced-scale JPEG decoding) get the path
        res = detector.detect(job.path if getattr(detector, "accepts_path", False) else read_image(job.path))
    except CpdetectError as exc:
        if not skip_bad:
            raise
        return {"file": job.rel, "error": exc.message}
    return {"file": job.rel, "width": int(info.width), "height": int(info.height), "seconds": round(res.seconds, 4),
            "detections": [d.to_dict() for d in res.detections]}


# worker-process state (a process pool builds the detector once per worker)
_W: dict = {}


def _init_worker(name: str, settings: dict, skip_bad: bool) -> None:
    from .detector import get_detector

    _W["det"] = get_detector(name, **settings)
    _W["skip_bad"] = skip_bad


def _work(job: BatchJob) -> dict:
    try:
        return run_one(_W["det"], job, _W["skip_bad"])
    except CpdetectError as exc:
        return {"file": job.rel, "fatal": str(exc)}


def detect_batch(jobs: Sequence[BatchJob], detector_name: str, settings: dict, out: str | os.PathLike,
                 workers: int = 1, skip_bad: bool = False, progress: Callable[[int, int], None] | None = None) -> dict:
    """Run the detector on every job, resumably (see module doc); returns the output document."""
    from .detector import get_detector

    out = Path(out)
    parts = out.with_name(out.name + ".parts")
    parts.mkdir(parents=True, exist_ok=True)
    stamp = {"detector": detector_name, "settings": settings}
    done: dict[str, dict] = {}
    for job in jobs:
        pf = parts / part_name(job.rel)
        if pf.exists():
            try:
                rec = json.loads(pf.read_text("utf-8"))
                if rec.get("stamp") == stamp and rec["record"]["file"] == job.rel:
                    done[job.rel] = rec["record"]
            except (OSError, ValueError, KeyError, TypeError):
                pass  # a damaged part is redone
    todo = [j for j in jobs if j.rel not in done]
    n_done = len(done)
    if progress:
        progress(n_done, len(jobs))

    def finish(rec: dict) -> None:
        nonlocal n_done
        if "fatal" in rec:
            raise CpdetectError(rec["fatal"])
        write_json_atomic(parts / part_name(rec["file"]), {"stamp": stamp, "record": rec}, indent=None)
        done[rec["file"]] = rec
        n_done += 1
        if progress:
            progress(n_done, len(jobs))

    if workers <= 1 or len(todo) <= 1:
        det = get_detector(detector_name, **settings)
        for job in todo:
            finish(run_one(det, job, skip_bad))
    else:
        import multiprocessing as mp

        ctx = mp.get_context("spawn")
        with ctx.Pool(workers, initializer=_init_worker, initargs=(detector_name, settings, skip_bad)) as pool:
            for rec in pool.imap(_work, todo, chunksize=1):
                finish(rec)
    doc = {"format": FORMAT, "detector": detector_name, "settings": settings,
           "images": [done[j.rel] for j in jobs]}
    write_json_atomic(out, doc)
    shutil.rmtree(parts, ignore_errors=True)
    return doc


__all__ = ["FORMAT", "BatchJob", "collect_jobs", "detect_batch", "run_one", "part_name"]
