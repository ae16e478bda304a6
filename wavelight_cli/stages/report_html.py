"""out/report.html: the report (`report.Doc`) as one self-contained page.

Every image is embedded as a data URI; the style and the few lines of script (the photo / relit
slider) are inline; no font, script or style comes from elsewhere, and the page's Content-Security-
Policy forbids the browser to fetch anything (a stray external reference shows as a console error
instead of a silent request).
"""

from __future__ import annotations

import base64
import html
import re
import struct
from pathlib import Path

CSP = "default-src 'none'; img-src data:; style-src 'unsafe-inline'; script-src 'unsafe-inline'"
SMALL = 400  # images narrower than this (the photo's own pixels) are shown enlarged, pixelated

STYLE = """
body { font-family: system-ui, -apple-system, "Segoe UI", Roboto, "DejaVu Sans", sans-serif; margin: 0;
       color: #1d1d1f; background: #fff; line-height: 1.45; }
main { max-width: 1240px; margin: 0 auto; padding: 0 24px 48px; }
header { background: #1d2a3a; color: #fff; padding: 18px 24px; }
header h1 { margin: 0; font-size: 1.5em; font-weight: 600; }
nav { margin-top: 6px; font-size: .9em; }
nav a { color: #bcd6ff; margin-right: 14px; text-decoration: none; }
h2 { border-bottom: 1px solid #d8dde3; padding-bottom: 4px; margin-top: 2em; }
h3 { margin-top: 1.6em; }
code { background: #f1f3f5; padding: 0 3px; border-radius: 3px; font-size: .92em; }
table { border-collapse: collapse; margin: .8em 0; font-size: .92em; }
th, td { border: 1px solid #d8dde3; padding: 3px 9px; vertical-align: top; }
th { background: #f3f5f8; text-align: left; }
td.r, th.r { text-align: right; font-variant-numeric: tabular-nums; }
table.numbers td:first-child { color: #555; }
.figs { display: flex; flex-wrap: wrap; gap: 18px; align-items: flex-start; margin: .8em 0; }
figure { margin: 0; max-width: 100%; display: table; }
figure img { max-width: 100%; height: auto; display: block; }
figure img.px { image-rendering: pixelated; }
figcaption { font-size: .86em; color: #444; display: table-caption; caption-side: bottom;
             text-align: left; margin-top: 4px; }
.wl-slider { position: relative; display: inline-block; line-height: 0; user-select: none; }
.wl-slider img { image-rendering: pixelated; display: block; }
.wl-slider img.over { position: absolute; top: 0; left: 0; }
.wl-slider .line { position: absolute; top: 0; bottom: 0; width: 2px; margin-left: -1px; background: #ffd400; }
.wl-slider .lab { position: absolute; top: 6px; font: 12px/1.4 sans-serif; color: #fff; background: rgba(0,0,0,.55);
                  padding: 1px 6px; border-radius: 3px; }
.wl-slider .lab.l { left: 6px; } .wl-slider .lab.r { right: 6px; }
.controls { display: flex; gap: 12px; align-items: center; margin-top: 6px; font-size: .9em; }
.controls input[type=range] { flex: 1; }
footer { color: #666; font-size: .85em; margin-top: 3em; }
"""

SCRIPT = """
document.querySelectorAll('figure.slider').forEach(function (fig) {
  var range = fig.querySelector('input[type=range]');
  var over = fig.querySelector('img.over');
  var line = fig.querySelector('.line');
  function show() {
    over.style.clipPath = 'inset(0 0 0 ' + range.value + '%)';
    line.style.left = range.value + '%';
  }
  range.addEventListener('input', show);
  fig.querySelector('button').addEventListener('click', function () {
    range.value = Number(range.value) < 50 ? 100 : 0;
    show();
  });
  show();
});
"""


def png_size(path: Path) -> tuple[int, int] | None:
    """(width, height) from a PNG's header."""
    with open(path, "rb") as f:
        head = f.read(24)
    if len(head) < 24 or head[:8] != b"\x89PNG\r\n\x1a\n":
        return None
    return struct.unpack(">II", head[16:24])


def data_uri(path: Path) -> str:
    kind = {".png": "image/png", ".jpg": "image/jpeg", ".jpeg": "image/jpeg"}.get(path.suffix.lower(), "image/png")
    return f"data:{kind};base64,{base64.b64encode(path.read_bytes()).decode('ascii')}"


_CODE = re.compile(r"`([^`]+)`")
_BOLD = re.compile(r"\*\*(.+?)\*\*")


def inline(text: str) -> str:
    """The report's light markup (`code`, **bold**) as HTML, everything else escaped."""
    out = html.escape(str(text), quote=False)
    out = _CODE.sub(lambda m: f"<code>{m.group(1)}</code>", out)
    return _BOLD.sub(lambda m: f"<strong>{m.group(1)}</strong>", out)


def _img(path: Path, alt: str, cls: str = "") -> str:
    size = png_size(path) if path.suffix.lower() == ".png" else None
    attrs = ""
    if size is not None:
        w, h = size
        k = 2 if w < SMALL else 1  # the photo's own pixels, enlarged
        attrs = f' width="{w * k}" height="{h * k}"'
        if k > 1:
            cls = (cls + " px").strip()
    cls_attr = f' class="{cls}"' if cls else ""
    return f'<img src="{data_uri(path)}" alt="{html.escape(alt)}"{attrs}{cls_attr}>'


def _figs(items, out: Path) -> str:
    parts = []
    for rel, alt, caption in items:
        path = out / rel
        if not path.is_file():
            continue  # a missing file is left out, never a broken image
        cap = f"<figcaption>{inline(caption)}</figcaption>" if caption else ""
        parts.append(f"<figure>{_img(path, alt)}{cap}</figure>")
    return f'<div class="figs">{"".join(parts)}</div>' if parts else ""


def _table(head, rows, align, cls="") -> str:
    a = lambda i: ' class="r"' if i < len(align) and align[i] == "r" else ""  # noqa: E731
    th = "<thead><tr>" + "".join(f"<th{a(i)}>{inline(h)}</th>" for i, h in enumerate(head)) + "</tr></thead>" \
        if head else ""
    body = "".join("<tr>" + "".join(f"<td{a(i)}>{inline(c)}</td>" for i, c in enumerate(r)) + "</tr>" for r in rows)
    cls_attr = f' class="{cls}"' if cls else ""
    return f"<table{cls_attr}>{th}<tbody>{body}</tbody></table>"


def _slider(under: str, over: str, labels, caption: str, out: Path) -> str:
    a, b = out / under, out / over
    if not (a.is_file() and b.is_file()):
        return ""
    return (f'<figure class="slider"><div class="wl-slider">{_img(a, labels[0], "under")}{_img(b, labels[1], "over")}'
            f'<div class="line"></div><span class="lab l">{html.escape(labels[0])}</span>'
            f'<span class="lab r">{html.escape(labels[1])}</span></div>'
            f'<div class="controls"><span>{html.escape(labels[0])}</span>'
            f'<input type="range" min="0" max="100" value="50" aria-label="{html.escape(labels[0])} / '
            f'{html.escape(labels[1])} split"><span>{html.escape(labels[1])}</span>'
            f'<button type="button">toggle</button></div>'
            f"<figcaption>{inline(caption)}</figcaption></figure>")


def _block(b, out: Path) -> str:
    kind = b[0]
    if kind == "p":
        return f"<p>{inline(b[1])}</p>"
    if kind == "figs":
        return _figs(b[1], out)
    if kind == "table":
        return _table(b[1], b[2], b[3])
    if kind == "numbers":
        return _table(None, [[k, v] for k, v in b[1]], "ll", "numbers")
    if kind == "list":
        return "<ul>" + "".join(f"<li>{inline(e)}</li>" for e in b[1]) + "</ul>"
    if kind == "h3":
        anchor = f' id="{html.escape(b[2])}"' if b[2] else ""
        return f"<h3{anchor}>{inline(b[1])}</h3>"
    if kind == "slider":
        return _slider(b[1], b[2], b[3], b[4], out)
    raise ValueError(f"unknown report block {kind!r}")


def to_html(doc, out: Path) -> str:
    nav = "".join(f'<a href="#{html.escape(s.anchor)}">{inline(s.title)}</a>' for s in doc.sections)
    body = ["".join(_block(b, out) for b in doc.intro)]
    for s in doc.sections:
        body.append(f'<section id="{html.escape(s.anchor)}"><h2>{inline(s.title)}</h2>'
                    + "".join(_block(b, out) for b in s.blocks) + "</section>")
    sources = ", ".join(f"<code>{html.escape(p)}</code>" for p in doc.sources)
    return ("<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">"
            f'<meta http-equiv="Content-Security-Policy" content="{CSP}">'
            '<meta name="viewport" content="width=device-width, initial-scale=1">'
            f"<title>{html.escape(doc.title)}</title><style>{STYLE}</style></head>\n<body>"
            f"<header><h1>{html.escape(doc.title)}</h1><nav>{nav}</nav></header>\n<main>\n"
            + "\n".join(body)
            + f"\n<footer>Written by <code>wavelight report</code> from the results on disk; read from: {sources}."
              f"</footer>\n</main>\n<script>{SCRIPT}</script>\n</body></html>\n")
