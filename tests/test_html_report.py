"""The HTML report opens in a real headless browser, its plots decode, and the table is visible."""
import re

import cv2
import numpy as np
import pytest

from cpdetect.browser import dump_dom, find_chromium, screenshot
from cpdetect.html_report import GalleryItem, HtmlReport, crop_with_marker, figure_png, read_rejects
from cpdetect.errors import InputError

pytestmark = pytest.mark.skipif(find_chromium() is None, reason="chromium is installed by make setup")


def _report(tmp_path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rep = HtmlReport("cpdetect test report")
    rep.heading("Summary")
    rep.table(["detector", "recall", "precision"], [["classical", 0.99, 1.0], ["hma", 0.95, 0.97]],
              table_id="summary")
    fig, ax = plt.subplots(figsize=(3, 2))
    ax.plot([0, 1], [1, 0])
    rep.figure(figure_png(fig), "PR curve")
    img = np.full((100, 100), 90, np.uint8)
    img[:50, :50] = 20
    img[50:, 50:] = 20
    rep.gallery([GalleryItem("m1@a.jpg", "a.jpg", 49.5, 49.5, crop_with_marker(img, 49.5, 49.5, 20.0))])
    path = tmp_path / "report.html"
    rep.write(path)
    return path


def test_report_loads_without_broken_images(tmp_path):
    path = _report(tmp_path)
    text = path.read_text()
    assert "http://" not in text and "https://" not in text  # self-contained
    dom = dump_dom(path)
    body = re.search(r"<body[^>]*>", dom).group(0)
    assert 'data-ready="1"' in body
    assert 'data-images="2"' in body
    assert 'data-broken-images="0"' in body


def test_screenshot_shows_the_summary_table(tmp_path):
    path = _report(tmp_path)
    png = screenshot(path, tmp_path / "shot.png", 1000, 700)
    shot = cv2.imread(str(png), cv2.IMREAD_GRAYSCALE)
    assert shot is not None and shot.shape == (700, 1000)
    # the table's header row has a grey background and dark text: rows with many dark pixels near the top
    top = shot[:300]
    dark_rows = (top < 100).sum(axis=1)
    assert (dark_rows > 20).sum() >= 10
    assert shot.std() > 10


def test_rejects_file_round_trip_and_errors(tmp_path):
    good = tmp_path / "rejects.json"
    good.write_text('{"format": "cpdetect.rejects/1", "rejects": [{"id": "m1", "image": "a.jpg", "x": 1, "y": 2}]}')
    assert read_rejects(good) == [{"id": "m1", "image": "a.jpg", "x": 1.0, "y": 2.0}]
    bad = tmp_path / "bad.json"
    bad.write_text('{"rejects": [{"id": "m1"}]}')
    with pytest.raises(InputError, match=r"rejects\[0\]"):
        read_rejects(bad)
