"""Package layering, registry behaviour, transforms and the marker renderer."""
import subprocess
import sys

import numpy as np
import pytest

from cpdetect import available_detectors, get_detector, register_detector
from cpdetect.errors import UsageError
from cpdetect.markers import MarkerSpec, frontal_homography, projected_radius, render_frontal, render_marker
from cpdetect.types import DetectionResult


def _modules_after(stmt: str) -> set[str]:
    code = f"import sys; {stmt}; print('\\n'.join(sys.modules))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    return set(out.split())


def test_geometry_imports_neither_cpdetect_nor_torch():
    mods = _modules_after("import geometry, geometry.transforms, geometry.camera, geometry.scene")
    assert "torch" not in mods and "cpdetect" not in mods and "learned" not in mods


def test_cpdetect_does_not_import_torch():
    mods = _modules_after("import cpdetect, cpdetect.cli; cpdetect.cli.build_parser()")
    assert "torch" not in mods


def test_unknown_detector_lists_valid_names():
    with pytest.raises(UsageError) as e:
        get_detector("nope")
    for name in ("classical", "hma"):
        assert name in str(e.value)


class _Dummy:
    name = "dummy"

    def __init__(self, threshold: float = 0.5):
        self.threshold = threshold

    def detect(self, image):
        return DetectionResult([], (image.shape[1], image.shape[0]))


def test_registry_rejects_unknown_settings():
    register_detector("dummy", _Dummy)
    assert "dummy" in available_detectors()
    assert get_detector("dummy", threshold=0.7).threshold == 0.7
    with pytest.raises(UsageError, match="threshold"):
        get_detector("dummy", treshold=0.7)


@pytest.mark.parametrize("marker_type", ["square", "circle", "diagonal"])
def test_render_is_symmetric_about_the_centre(marker_type):
    # Point symmetry: rotating the image 180 degrees about the aiming point maps dark to dark.
    c = (31.5 + 0.25, 31.5 - 0.125)
    img = render_frontal(marker_type, 64, 20.0, 0.3, center=c, background=0.5)
    spec = MarkerSpec(marker_type, size_m=2.0)
    r = render_marker(spec, frontal_homography(c, 20.0, 0.3, spec), (64, 64))
    area = r.pattern.sum()
    expect = {"square": 4 * 20.0 ** 2, "diagonal": 4 * 20.0 ** 2, "circle": np.pi * 20.0 ** 2}[marker_type]
    assert abs(area - expect) / expect < 2e-3
    # dark fraction of the pattern is one half
    assert abs(r.dark.sum() / area - 0.5) < 2e-3
    # centroid of the pattern coverage is the aiming point to 1e-3 px
    ys, xs = np.mgrid[r.y0:r.y0 + r.dark.shape[0], r.x0:r.x0 + r.dark.shape[1]]
    cx = (xs * r.pattern).sum() / area
    cy = (ys * r.pattern).sum() / area
    assert abs(cx - c[0]) < 1e-3 and abs(cy - c[1]) < 1e-3
    assert img.min() >= 0.0 and img.max() <= 1.0


def test_projected_radius_of_frontal_square():
    spec = MarkerSpec("square", size_m=0.2)
    H = frontal_homography((100, 100), 30.0, 0.0, spec)
    assert projected_radius(spec, H) == pytest.approx(30.0 * 2 / np.sqrt(np.pi), rel=1e-6)
