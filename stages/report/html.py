"""Minimal HTML building blocks shared by the scene and batch reports (no template engine needed)."""

from __future__ import annotations

import html
import json
from pathlib import Path

CSS = """
body { font-family: system-ui, sans-serif; margin: 1.5em auto; max-width: 1300px; color: #222; }
h1 { margin-bottom: 0.2em; } h2 { border-bottom: 1px solid #ccc; padding-bottom: 0.2em; margin-top: 1.6em; }
table { border-collapse: collapse; margin: 0.6em 0; font-size: 0.9em; }
th, td { border: 1px solid #ccc; padding: 0.25em 0.6em; text-align: right; }
th { background: #f2f2f2; } td.l, th.l { text-align: left; } td.good { font-weight: bold; }
figure { display: inline-block; margin: 0.2em; text-align: center; font-size: 0.8em; }
figure img { image-rendering: pixelated; width: 256px; display: block; }
img.plot { max-width: 100%; }
.grid { display: grid; gap: 0.2em; align-items: center; }
.note { color: #555; font-size: 0.9em; }
code { background: #f4f4f4; padding: 0 0.2em; }
"""

# Sets <body data-images-loaded="ok/total"> once the page has loaded: a headless browser check that every
# embedded picture decoded (the report test reads it back through Chromium's --dump-dom).
LOAD_CHECK = """
<script>
window.addEventListener('load', function () {
  var imgs = Array.prototype.slice.call(document.images);
  var ok = imgs.filter(function (i) { return i.complete && i.naturalWidth > 0; }).length;
  document.body.setAttribute('data-images-loaded', ok + '/' + imgs.length);
});
</script>
"""


def esc(x) -> str:
    return html.escape(str(x))


def page(title: str, body: str) -> str:
    return (f"<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\"><title>{esc(title)}</title>"
            f"<style>{CSS}</style></head>\n<body>\n{body}\n{LOAD_CHECK}</body></html>\n")


def read_json(path: Path, missing=None):
    """``path``'s JSON, ``missing`` when there is no such file; a file that is not JSON raises a ValueError naming
    it (a run stopped while writing it)."""
    if not path.is_file():
        return missing
    try:
        return json.loads(path.read_text())
    except ValueError as e:
        raise ValueError(f"{path}: not JSON ({e}); run the step that writes it again") from None


def fmt(value, digits: int = 2) -> str:
    if value is None:
        return "–"
    if isinstance(value, float):
        return f"{value:.{digits}f}"
    return esc(value)


def table(header: list[str], rows: list[list], left: int = 1) -> str:
    """``left`` leading columns are left-aligned labels; cells are formatted with ``fmt`` unless already str."""
    th = "".join(f"<th class=\"{'l' if i < left else ''}\">{esc(h)}</th>" for i, h in enumerate(header))
    body = []
    for row in rows:
        tds = "".join(f"<td class=\"{'l' if i < left else ''}\">{c if isinstance(c, str) else fmt(c)}</td>"
                      for i, c in enumerate(row))
        body.append(f"<tr>{tds}</tr>")
    return f"<table><tr>{th}</tr>{''.join(body)}</table>"


def figure(uri: str, caption: str) -> str:
    return f"<figure><img src=\"{uri}\" alt=\"{esc(caption)}\"><figcaption>{esc(caption)}</figcaption></figure>"


def hms(seconds) -> str:
    """Seconds -> h:mm:ss (the paper's Table 2 format)."""
    if seconds is None:
        return "–"
    s = int(round(float(seconds)))
    return f"{s // 3600}:{s % 3600 // 60:02d}:{s % 60:02d}"
