"""`cpdetect detect` over 200 images killed mid-way (SIGKILL) and rerun: the same detections.json as an
uninterrupted run, and only the images without a finished part are processed again."""
import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from batch_helpers import without_timing, write_marker_images
from cpdetect.batch import part_name
from cpdetect.cli import main

N_IMAGES = 200
CPDETECT = [sys.executable, "-m", "cpdetect.cli"]


def finished_parts(parts: Path) -> dict[str, dict]:
    """{image name: record} of the complete part files (temporary files of a killed write excluded)."""
    out = {}
    for f in parts.glob("*.json"):
        rec = json.loads(f.read_text("utf-8"))["record"]
        assert f.name == part_name(rec["file"])
        out[rec["file"]] = rec
    return out


@pytest.mark.skipif(not hasattr(signal, "SIGKILL"), reason="needs SIGKILL")
@pytest.mark.parametrize("workers", [1, 2])
def test_killed_run_resumes_to_the_same_result(tmp_path, workers):
    """With workers, the whole process group (the command and its pool) is killed, as when a node dies;
    the rerun also runs with workers, and must still equal the serial reference."""
    images = write_marker_images(tmp_path / "images", N_IMAGES)
    names = {f"{i:04d}.jpg" for i in range(N_IMAGES)}

    ref = tmp_path / "ref" / "detections.json"
    assert main(["-q", "detect", str(images), "--out", str(ref)]) == 0
    reference = json.loads(ref.read_text())
    assert sum(len(im["detections"]) for im in reference["images"]) >= 0.9 * N_IMAGES

    out = tmp_path / "run" / "detections.json"
    parts = out.parent / "detections.json.parts"
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    cmd = [*CPDETECT, "-q", "detect", str(images), "--out", str(out), "--workers", str(workers)]
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                            start_new_session=True)
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and proc.poll() is None:
            if parts.is_dir() and len(list(parts.glob("*.json"))) >= 20:
                break
            time.sleep(0.01)
        assert proc.poll() is None, "the run ended before it could be interrupted"
        os.killpg(proc.pid, signal.SIGKILL)  # the command and its worker processes, if any
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(timeout=30)
    assert proc.returncode == -signal.SIGKILL
    assert not out.exists()
    before = finished_parts(parts)
    assert 1 <= len(before) < N_IMAGES, len(before)
    assert set(before) <= names

    rerun = subprocess.run([*CPDETECT, "--debug", "detect", str(images), "--out", str(out), "--workers",
                            str(workers)], env=env, capture_output=True, text=True, timeout=120)
    assert rerun.returncode == 0, rerun.stderr[-2000:]
    assert "Traceback" not in rerun.stderr
    processed = set(re.findall(r"processed (\d{4}\.jpg)$", rerun.stderr, flags=re.M))
    assert processed == names - set(before), (sorted(processed ^ (names - set(before)))[:10], len(before))
    assert f"resuming: {len(before)} of {N_IMAGES} images already done" in rerun.stderr

    result = json.loads(out.read_text())
    differ = [a["file"] for a, b in zip(without_timing(result)["images"], without_timing(reference)["images"])
              if a != b]
    assert differ == [] and without_timing(result) == without_timing(reference), differ[:10]
    # the records made before the kill were reused as they were, timings included
    by_name = {im["file"]: im for im in result["images"]}
    assert all(by_name[n] == rec for n, rec in before.items())
    assert not parts.exists()
    assert sorted(p.name for p in out.parent.iterdir()) == ["detections.json"]
