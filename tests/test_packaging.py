"""`pip install .` into a clean environment, run from another folder, works like the checkout.

The wheel is built from the checkout and installed with --no-deps into a fresh venv that borrows the
already-installed third-party dependencies (through a .pth path line, which does not run the checkout's
editable-install hooks), so only cpdetect's own files come from the wheel.
"""
import subprocess
import sys
import sysconfig
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def installed(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("pkg")
    wheels = tmp / "wheels"
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q",
                    "-w", str(wheels), str(ROOT)], check=True, capture_output=True)
    venv = tmp / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True)
    py = venv / "bin" / "python"
    site = subprocess.run([str(py), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                          check=True, capture_output=True, text=True).stdout.strip()
    Path(site, "borrowed_deps.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    wheel = next(wheels.glob("cpdetect-*.whl"))
    subprocess.run([sys.executable, "-m", "pip", "--python", str(py), "install", "--no-deps", "-q", str(wheel)],
                   check=True, capture_output=True)
    elsewhere = tmp / "elsewhere"
    elsewhere.mkdir()
    return venv, elsewhere


def test_installed_package_has_its_data_and_runs_from_elsewhere(installed):
    venv, elsewhere = installed
    code = ("import importlib.resources as r, cpdetect, pathlib; "
            "p = r.files('cpdetect.data') / 'backgrounds'; "
            "n = sum(1 for f in p.iterdir() if f.name.endswith('.jpg')); "
            "assert (p / 'MANIFEST.tsv').is_file(); "
            "assert 'site-packages' in cpdetect.__file__, cpdetect.__file__; "
            "from cpdetect.classical import score_model; "
            "assert 'site-packages' in str(r.files('cpdetect.data')); assert score_model().feature.shape[0] >= 10; "
            "from cpdetect.marker_type import type_model; from learned.adapter import MODEL_SCORE_FILE; "
            "assert type_model().classes == ('circle', 'diagonal', 'square'); "
            "from cpdetect.classical import BASE_SCORE_FILE, SCORE_FEATURES, PATCH_FEATURES; "
            "assert score_model(MODEL_SCORE_FILE).features == score_model(BASE_SCORE_FILE).features == SCORE_FEATURES; "
            "assert score_model().features == SCORE_FEATURES + PATCH_FEATURES; "
            "from cpdetect.classical import EARLY_FEATURES, early_model; "
            "assert early_model().features == EARLY_FEATURES; "
            "print(n)")
    out = subprocess.run([str(venv / "bin" / "python"), "-c", code], cwd=elsewhere, check=True,
                         capture_output=True, text=True).stdout
    assert int(out) >= 40
    res = subprocess.run([str(venv / "bin" / "cpdetect"), "--help"], cwd=elsewhere, capture_output=True, text=True)
    assert res.returncode == 0 and "COMMAND" in res.stdout


def test_installed_package_detects_with_its_shipped_hma_weights(installed):
    venv, elsewhere = installed
    code = ("import numpy as np, learned.adapter as a, cpdetect\n"
            "from cpdetect.markers import MarkerSpec, frontal_homography, render_marker\n"
            "assert 'site-packages' in str(a.default_model_dir()), a.default_model_dir()\n"
            "assert a.shipped_weights_present()\n"
            "assert a.shipped_weights_present('lite')  # the second shipped network\n"
            "assert (a.default_model_dir() / 'SHA256SUMS').is_file()  # the digests checked on loading\n"
            "img = np.full((256, 256), 120.0)\n"
            "spec = MarkerSpec('square', size_m=1.0)\n"
            "render_marker(spec, frontal_homography((128.0, 128.0), 30.0, 0.3, spec), img.shape).composite(img, 35.0, 220.0)\n"
            "res = cpdetect.get_detector('hma', backend='opencv').detect(img.astype(np.uint8))\n"
            "print(' '.join(f'{m.x:.2f},{m.y:.2f}' for m in res.detections))\n")
    out = subprocess.run([str(venv / "bin" / "python"), "-c", code], cwd=elsewhere, capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    found = [tuple(map(float, t.split(","))) for t in out.stdout.split()]
    assert len(found) == 1
    assert abs(found[0][0] - 128.0) < 0.5 and abs(found[0][1] - 128.0) < 0.5
