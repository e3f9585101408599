"""A self-contained HTML report: one file, PNG plots embedded as data URIs, no network access.

The review gallery shows one crop per observation with the detected centre drawn. A reviewer ticks
"reject" on wrong ones and presses the download button: the page writes ``rejects.json``
(``{"format": "cpdetect.rejects/1", "rejects": [{"id", "image", "x", "y"}]}``), which
``cpdetect georef --rejects rejects.json`` honours on the next run.

On load, a small script records self-checks on ``<body>``: ``data-images`` (number of <img>),
``data-broken-images`` (images that failed to decode) and ``data-ready="1"``; the browser test reads them.
"""
from __future__ import annotations

import base64
import html
import io
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Sequence

from .fileio import write_text_atomic

_CSS = """
body{font-family:system-ui,-apple-system,Segoe UI,Roboto,sans-serif;margin:24px auto;max-width:1200px;
color:#1d2125;padding:0 16px}
h1{font-size:1.6em;margin-bottom:4px} h2{border-bottom:2px solid #d0d7de;padding-bottom:4px;margin-top:32px}
table{border-collapse:collapse;margin:8px 0 16px} th,td{border:1px solid #d0d7de;padding:4px 10px;text-align:right}
th{background:#f3f5f7} td:first-child,th:first-child{text-align:left}
.note{color:#57606a} .good{color:#1a7f37;font-weight:600} .bad{color:#cf222e;font-weight:600}
.rec{background:#eef6ff;border-left:4px solid #0969da;padding:8px 14px;margin:12px 0}
figure{display:inline-block;margin:8px 12px 8px 0} figcaption{font-size:.85em;color:#57606a}
.gallery{display:flex;flex-wrap:wrap;gap:8px} .tile{border:1px solid #d0d7de;padding:4px;font-size:.75em;width:140px}
.tile img{width:128px;height:128px;image-rendering:pixelated;display:block}
.tile.rejected{opacity:.45;border-color:#cf222e} button{display:block;padding:6px 14px;margin:8px 0}
"""

_SCRIPT = """
window.addEventListener('load', function () {
  var imgs = document.images, broken = 0;
  for (var i = 0; i < imgs.length; i++) { if (!imgs[i].complete || imgs[i].naturalWidth === 0) broken++; }
  document.body.dataset.images = imgs.length;
  document.body.dataset.brokenImages = broken;
  document.body.dataset.ready = '1';
});
function cpdToggle(box) { box.closest('.tile').classList.toggle('rejected', box.checked); }
function cpdDownloadRejects() {
  var out = [];
  document.querySelectorAll('input.reject:checked').forEach(function (b) {
    out.push({id: b.dataset.id, image: b.dataset.image, x: parseFloat(b.dataset.x), y: parseFloat(b.dataset.y)});
  });
  var blob = new Blob([JSON.stringify({format: 'cpdetect.rejects/1', rejects: out}, null, 1)],
                      {type: 'application/json'});
  var a = document.createElement('a'); a.href = URL.createObjectURL(blob); a.download = 'rejects.json';
  document.body.appendChild(a); a.click(); a.remove();
}
"""


def png_data_uri(png: bytes) -> str:
    return "data:image/png;base64," + base64.b64encode(png).decode("ascii")


def figure_png(fig: Any, dpi: int = 100) -> bytes:
    """PNG bytes of a matplotlib figure (closed afterwards)."""
    import matplotlib.pyplot as plt

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi, bbox_inches="tight")
    plt.close(fig)
    return buf.getvalue()


@dataclass
class GalleryItem:
    """One crop to review: ``png`` bytes, the observation's id, image name and detected (x, y)."""

    id: str
    image: str
    x: float
    y: float
    png: bytes
    caption: str = ""


@dataclass
class HtmlReport:
    title: str
    parts: list[str] = field(default_factory=list)

    def heading(self, text: str, level: int = 2) -> None:
        self.parts.append(f"<h{level}>{html.escape(text)}</h{level}>")

    def paragraph(self, text: str, css: str = "") -> None:
        cls = f' class="{css}"' if css else ""
        self.parts.append(f"<p{cls}>{html.escape(text)}</p>")

    def recommendation(self, lines: Iterable[str]) -> None:
        items = "".join(f"<li>{html.escape(s)}</li>" for s in lines)
        self.parts.append(f'<div class="rec" id="recommendation"><ul>{items}</ul></div>')

    def table(self, header: Sequence[str], rows: Iterable[Sequence[Any]], table_id: str = "") -> None:
        def cell(v: Any) -> str:
            if isinstance(v, float):
                return f"{v:.4g}"
            return html.escape(str(v))

        tid = f' id="{table_id}"' if table_id else ""
        head = "".join(f"<th>{html.escape(str(h))}</th>" for h in header)
        body = "".join("<tr>" + "".join(f"<td>{cell(v)}</td>" for v in row) + "</tr>" for row in rows)
        self.parts.append(f"<table{tid}><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>")

    def figure(self, png: bytes, caption: str = "", css_class: str = "plot") -> None:
        cap = f"<figcaption>{html.escape(caption)}</figcaption>" if caption else ""
        self.parts.append(f'<figure><img class="{css_class}" alt="{html.escape(caption)}" '
                          f'src="{png_data_uri(png)}">{cap}</figure>')

    def gallery(self, items: Sequence[GalleryItem], rejectable: bool = True) -> None:
        """Crops in a grid; with ``rejectable`` each has a "reject" box and the grid a download button."""
        tiles = []
        for it in items:
            attrs = (f'data-id="{html.escape(it.id)}" data-image="{html.escape(it.image)}" '
                     f'data-x="{it.x:.3f}" data-y="{it.y:.3f}"')
            box = (f'<label><input type="checkbox" class="reject" {attrs} onchange="cpdToggle(this)"> reject</label>'
                   if rejectable else "")
            tiles.append(f'<div class="tile"><img class="crop" alt="{html.escape(it.id)}" src="{png_data_uri(it.png)}">'
                         f'<div>{html.escape(it.caption or it.image)}</div>{box}</div>')
        button = '<button onclick="cpdDownloadRejects()">Download rejects.json</button>' if rejectable else ""
        self.parts.append(f'{button}<div class="gallery">{"".join(tiles)}</div>')

    def render(self) -> str:
        return ("<!DOCTYPE html><html lang=\"en\"><head><meta charset=\"utf-8\">"
                f"<title>{html.escape(self.title)}</title><style>{_CSS}</style><script>{_SCRIPT}</script></head>"
                f"<body><h1>{html.escape(self.title)}</h1>{''.join(self.parts)}</body></html>")

    def write(self, path: str | Path) -> None:
        write_text_atomic(path, self.render())


def read_rejects(path: str | Path) -> list[dict]:
    """Read a ``rejects.json`` written by the report's review gallery (one-line errors if malformed)."""
    from .errors import InputError
    from .fileio import read_json

    data = read_json(path, "rejects file")
    if not isinstance(data, dict) or not isinstance(data.get("rejects"), list):
        raise InputError("not a cpdetect rejects file (needs a 'rejects' list)", path)
    out = []
    for i, r in enumerate(data["rejects"]):
        try:
            out.append({"id": str(r["id"]), "image": str(r["image"]), "x": float(r["x"]), "y": float(r["y"])})
        except (KeyError, TypeError, ValueError):
            raise InputError(f"rejects[{i}] needs id, image, x, y", path) from None
    return out


def crop_with_marker(image_bgr_or_gray, x: float, y: float, radius_px: float, size: int = 128) -> bytes:
    """PNG of a square crop around (x, y) (OpenCV pixel convention), scaled to ``size`` pixels, with a
    cross-hair at the detected centre drawn with sub-pixel precision."""
    import cv2
    import numpy as np

    img = image_bgr_or_gray
    if img.ndim == 2:
        img = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
    half = max(8.0, 1.6 * radius_px)
    scale = size / (2 * half)
    # affine map from the source to the crop: centre (x, y) lands at the crop's centre
    c = (size - 1) / 2.0
    M = np.array([[scale, 0, c - scale * x], [0, scale, c - scale * y]], np.float64)
    crop = cv2.warpAffine(img, M, (size, size), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                          borderValue=(40, 40, 40))
    shift = 4
    cc = int(round(c * (1 << shift)))
    arm = int(round(size * 0.18 * (1 << shift)))
    for (dx, dy) in ((1, 0), (0, 1)):
        p1 = (cc - dx * arm, cc - dy * arm)
        p2 = (cc + dx * arm, cc + dy * arm)
        cv2.line(crop, p1, p2, (0, 0, 255), 1, cv2.LINE_AA, shift)
    cv2.circle(crop, (cc, cc), int(round(radius_px * scale * (1 << shift))), (0, 200, 255), 1, cv2.LINE_AA, shift)
    ok, buf = cv2.imencode(".png", crop, [cv2.IMWRITE_PNG_COMPRESSION, 9])  # a third smaller than the default
    return buf.tobytes()
