"""Per-image work on a Dask cluster (a LocalCluster here) gives exactly the serial result."""
import json
import subprocess
import sys
import time

import pytest

distributed = pytest.importorskip("distributed")

from batch_helpers import without_timing, write_marker_images  # noqa: E402
from cpdetect.batch import collect_jobs, detect_batch  # noqa: E402
from cpdetect.cli import main  # noqa: E402
from cpdetect.errors import CpdetectError, UsageError  # noqa: E402
from cpdetect.executors import DaskExecutor, SerialExecutor, make_executor  # noqa: E402


@pytest.fixture(scope="module")
def cluster():
    # threads in this process, but a real TCP scheduler address as `--scheduler tcp://host:port` gets
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=False, protocol="tcp://",
                                  dashboard_address=None) as cl, distributed.Client(cl) as client:
        yield cl, client


@pytest.fixture(scope="module")
def images(tmp_path_factory):
    return write_marker_images(tmp_path_factory.mktemp("dask") / "images", 10)


@pytest.fixture(scope="module")
def serial_doc(images, tmp_path_factory):
    out = tmp_path_factory.mktemp("serial") / "det.json"
    return detect_batch(collect_jobs([images]), "classical", {}, out)


def test_dask_client_equals_serial(images, serial_doc, cluster, tmp_path):
    _, client = cluster
    out = tmp_path / "det.json"
    doc = detect_batch(collect_jobs([images]), "classical", {}, out, scheduler=client)
    assert without_timing(doc) == without_timing(serial_doc)
    assert without_timing(json.loads(out.read_text())) == without_timing(serial_doc)
    assert [im["file"] for im in doc["images"]] == [f"{i:04d}.jpg" for i in range(10)]
    # the markers were found: the comparison is not between two empty results
    assert sum(len(im["detections"]) for im in doc["images"]) >= 8
    assert not (tmp_path / "det.json.parts").exists()
    assert client.status == "running"  # a Client we were given is not closed


def test_cli_scheduler_address(images, serial_doc, cluster, tmp_path, capsys):
    cl, _ = cluster
    assert cl.scheduler_address.startswith("tcp://127.0.0.1:")
    out = tmp_path / "det.json"
    assert main(["-q", "detect", str(images), "--out", str(out), "--scheduler", cl.scheduler_address]) == 0
    assert without_timing(json.loads(out.read_text())) == without_timing(serial_doc)


def test_imap_keeps_input_order_with_a_small_window(cluster):
    _, client = cluster
    ex = DaskExecutor(client, window=3)
    items = [0.05, 0.0, 0.03, 0.0, 0.04, 0.0, 0.01]  # later tasks finish first
    assert list(ex.imap(_sleep_then_echo, items)) == items
    assert list(SerialExecutor().imap(_sleep_then_echo, items)) == items
    ex.close()
    assert client.status == "running"


def _sleep_then_echo(x):
    time.sleep(x)
    return x


def test_bad_image_on_dask_stops_with_its_name(images, cluster, tmp_path):
    _, client = cluster
    bad = tmp_path / "zzz_bad.jpg"
    bad.write_bytes(b"")
    out = tmp_path / "det.json"
    jobs = collect_jobs([images, bad])
    with pytest.raises(CpdetectError, match="zzz_bad.jpg.*empty"):
        detect_batch(jobs, "classical", {}, out, scheduler=client)
    assert not out.exists()
    # the finished images are kept for a rerun
    assert 1 <= len(list((tmp_path / "det.json.parts").glob("*.json"))) <= 10


def test_unreachable_scheduler_is_a_usage_error():
    t0 = time.perf_counter()
    with pytest.raises(UsageError, match="cannot connect to the Dask scheduler at tcp://127.0.0.1:9"):
        make_executor(scheduler="tcp://127.0.0.1:9", connect_timeout=1.0)
    assert time.perf_counter() - t0 < 20


def test_importing_cpdetect_does_not_import_dask():
    code = ("import sys, cpdetect, cpdetect.cli, cpdetect.batch, cpdetect.executors; "
            "cpdetect.cli.build_parser(); print(sorted(m for m in sys.modules if m.split('.')[0] in "
            "('dask', 'distributed')))")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "[]"


def test_without_dask_a_scheduler_is_a_usage_error(monkeypatch):
    monkeypatch.setitem(sys.modules, "distributed", None)  # as if not installed
    with pytest.raises(UsageError, match=r"pip install 'cpdetect\[dask\]'"):
        make_executor(scheduler="tcp://127.0.0.1:9")


def test_georef_detect_stage_on_dask_equals_serial(images, cluster, tmp_path):
    """`cpdetect georef --scheduler`: the detect stage's records are those of a serial run."""
    from test_bad_input import GOOD_SURVEYED, _colmap_text

    cl, _ = cluster
    model = _colmap_text(tmp_path / "model", [f"{i:04d}.jpg" for i in range(10)])
    (tmp_path / "gcps.csv").write_text(GOOD_SURVEYED)
    base = ["-q", "georef", "--reconstruction", str(model), "--images", str(images), "--gcps",
            str(tmp_path / "gcps.csv")]
    records = []
    for name, extra in (("serial", []), ("dask", ["--scheduler", cl.scheduler_address])):
        main(base + ["--out", str(tmp_path / name), *extra])  # too few views to georeference: exit 1
        data = json.loads((tmp_path / name / "stages" / "detect.json").read_text())["data"]
        records.append({n: {k: v for k, v in d.items() if k != "seconds"} for n, d in data.items()})
    assert records[0] == records[1] and len(records[0]) == 10
    assert sum(len(d["detections"]) for d in records[0].values()) >= 8
