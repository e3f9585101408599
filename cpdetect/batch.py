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

Where the work runs is an :class:`~cpdetect.executors.Executor`: serial, a local process pool
(``workers``) or a Dask cluster (``scheduler``: an address or a ``distributed.Client``). Each task gets
the image's path and reads the image itself (on a cluster: from storage every worker can see), and
sends back only the small record; the results, in input order, are identical whatever the executor
(but for the ``seconds`` timings). Memory is bounded by the images in flight, never by their number.

A run that stops on an error keeps the parts of the images it finished (a rerun resumes), but leaves
no output file and no folder that it created and left empty.
"""
from __future__ import annotations

import hashlib
import json
import logging
import os
import shutil
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Sequence

from .errors import CpdetectError, InputError
from .executors import SerialExecutor, make_executor
from .fileio import cannot_write, write_json_atomic

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
    rec = {"file": job.rel, "width": int(info.width), "height": int(info.height), "seconds": round(res.seconds, 4),
           "detections": [d.to_dict() for d in res.detections]}
    unverified = (res.extras or {}).get("unverified")
    if unverified:
        rec["warning"] = (f"{unverified} candidates left unverified (a regular pattern such as a checkerboard "
                          "or tiles?); --set max_verified=N checks more")
    return rec


# detectors built in this process or thread, by (name, settings): a task builds its detector once per
# worker, not once per image. Thread-local because a Dask worker may run tasks in several threads.
_LOCAL = threading.local()


def _cached_detector(name: str, settings: dict) -> Any:
    from .detector import get_detector

    cache = getattr(_LOCAL, "detectors", None)
    if cache is None:
        cache = _LOCAL.detectors = {}
    key = (name, json.dumps(settings, sort_keys=True))
    if key not in cache:
        cache[key] = get_detector(name, **settings)
    return cache[key]


@dataclass(frozen=True)
class DetectTask:
    """The per-image task an executor runs: ``task(job) -> record`` (see :func:`run_one`).

    Picklable (it travels to worker processes and Dask workers). A :class:`CpdetectError` that is not
    skipped comes back as ``{"file": rel, "fatal": message}`` so that the caller stops with the
    one-line message whatever the executor.
    """

    detector: str
    settings: dict
    skip_bad: bool = False

    def __call__(self, job: BatchJob) -> dict:
        try:
            return run_one(_cached_detector(self.detector, self.settings), job, self.skip_bad)
        except CpdetectError as exc:
            return {"file": job.rel, "fatal": str(exc)}


def detect_batch(jobs: Sequence[BatchJob], detector_name: str, settings: dict, out: str | os.PathLike,
                 workers: int = 1, skip_bad: bool = False, progress: Callable[[int, int], None] | None = None,
                 scheduler: Any = None, executor: Any = None) -> dict:
    """Run the detector on every job, resumably (see module doc); returns the output document.

    Where it runs: ``executor`` (an :class:`~cpdetect.executors.Executor`, used and not closed) if
    given, else a Dask cluster if ``scheduler`` (address or ``distributed.Client``), else ``workers``
    local processes (1: in this process).
    """
    from .fileio import output_target

    out = output_target(out)
    parts = out.with_name(out.name + ".parts")
    if out.is_dir():
        raise InputError("the output is a folder; give a file name such as detections.json", out)
    created = [d for d in (parts, *parts.parents) if not d.exists()]  # deepest first
    try:
        parts.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        # name the output the user gave, unless the parts folder's own name is what is taken
        raise cannot_write(exc, parts if parts.exists() else out) from None
    try:
        return _run_batch(jobs, detector_name, settings, out, parts, workers, skip_bad, progress, scheduler,
                          executor)
    except BaseException:
        # keep finished parts for a rerun, but no empty folder that this run made
        for d in created:
            try:
                d.rmdir()
            except OSError:
                break
        raise


def _run_batch(jobs, detector_name, settings, out, parts, workers, skip_bad, progress, scheduler, executor) -> dict:
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
        if "warning" in rec:
            log.warning("%s: %s", rec["file"], rec["warning"])
        n_done += 1
        if progress:
            progress(n_done, len(jobs))

    if n_done:
        log.info("resuming: %d of %d images already done in %s", n_done, len(jobs), parts)
    task = DetectTask(detector_name, settings, skip_bad)
    if executor is None and scheduler is None and len(todo) <= 1:
        workers = 1  # no pool for one image
    if todo:
        own = executor is None
        ex = make_executor(workers, scheduler) if own else executor
        try:
            if not isinstance(ex, SerialExecutor):  # remote workers resolve paths from their own cwd
                todo = [BatchJob(os.path.abspath(j.path), j.rel) for j in todo]
            for rec in ex.imap(task, todo):
                finish(rec)
                log.debug("processed %s", rec["file"])
        finally:
            if own:
                ex.close()
    log.info("processed %d images (%d done before)", len(todo), len(jobs) - len(todo))
    doc = {"format": FORMAT, "detector": detector_name, "settings": settings,
           "images": [done[j.rel] for j in jobs]}
    write_json_atomic(out, doc)
    shutil.rmtree(parts, ignore_errors=True)
    return doc


__all__ = ["FORMAT", "BatchJob", "DetectTask", "collect_jobs", "detect_batch", "run_one", "part_name"]
