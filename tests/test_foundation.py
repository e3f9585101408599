"""Package layering, registry behaviour, transforms and the marker renderer."""
import subprocess
import sys
from dataclasses import dataclass

import numpy as np
import pytest

from cpdetect import available_detectors, get_detector, register_detector
from cpdetect.detector import check_settings, settings_from_dataclass
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


def _parsers(parser):
    """Every parser under ``parser`` (sub-commands and theirs), itself first."""
    import argparse

    yield parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub in action.choices.values():
                yield from _parsers(sub)


def test_no_help_text_shows_docstring_markup():
    from cpdetect.cli import build_parser

    helps = [p.format_help() for p in _parsers(build_parser())]
    assert len(helps) > 10  # every sub-command, and synth's kinds
    for text in helps:
        for markup in ("``", ":class:", ":func:", ":mod:", ":data:"):
            assert markup not in text, text.splitlines()[0]


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


@dataclass(frozen=True)
class _ToySettings:
    threshold: float = 0.5
    levels: int = 3
    mode: str = "fast"
    refine: bool = True
    max_side: int | None = None
    scales: tuple[float, ...] = (1.0,)


class _Toy:
    """A third-party style detector: a settings dataclass built by the shared helper."""

    name = "toy"
    Settings = _ToySettings

    def __init__(self, **settings):
        self.settings = settings_from_dataclass(_ToySettings, settings)

    def detect(self, image):
        return DetectionResult([], (image.shape[1], image.shape[0]))


@pytest.mark.parametrize("values, expected", [
    ({"threshold": "high"}, 'setting threshold="high": expected float (default 0.5)'),
    ({"threshold": True}, "setting threshold=true: expected float"),
    ({"levels": 2.5}, "setting levels=2.5: expected int (default 3)"),
    ({"mode": 3}, "setting mode=3: expected str"),
    ({"refine": "yes"}, 'setting refine="yes": expected bool'),
    ({"max_side": "big"}, 'setting max_side="big": expected int or null'),
    ({"scales": 1.0}, "setting scales=1.0: expected list"),
])
def test_every_detector_built_by_the_settings_helper_checks_setting_types(values, expected):
    register_detector("toy", _Toy)
    with pytest.raises(UsageError) as e:
        get_detector("toy", **values)
    assert str(e.value) == expected or str(e.value).startswith(expected)
    assert "\n" not in str(e.value)
    with pytest.raises(UsageError, match=expected.split(":")[0]):
        check_settings("toy", values)  # the same check without building the detector


def test_settings_of_the_right_type_pass():
    register_detector("toy", _Toy)
    t = get_detector("toy", threshold=1, levels=2, mode="slow", refine=False, max_side=None, scales=[1.0, 0.5])
    assert t.settings.threshold == 1 and t.settings.max_side is None
    # numpy scalars are numbers too (settings computed by scripts)
    assert get_detector("toy", threshold=np.float32(0.25), levels=np.int64(4)).settings.levels == 4


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
