"""One self-contained HTML file: plotly.js inlined once, every figure as JSON, the folder's
own Markdown tables as HTML, and a short script that fills the pixels' subset read-outs and
moves the profiles' row (a slider, or a click on a map). Nothing is fetched: no CDN, no font,
no server."""

from __future__ import annotations

import base64
import html
import json
import re
from pathlib import Path

import numpy as np
import plotly
import plotly.graph_objects as go

from odmv.io.atomic import write_text
from odmv.page import plots
from odmv.page.sources import Page, read
from odmv.study.scenes import NO_TRUTH_BIT, SHADOWED_BIT, Scene

PAGE = "page.html"  # a folder's own page

STYLE = """
body{font-family:system-ui,sans-serif;margin:1.5em auto;max-width:1500px;padding:0 1em;color:#222}
table{border-collapse:collapse;font-size:12px;margin:.6em 0}
td,th{border:1px solid #ccc;padding:2px 6px;text-align:right}
td:first-child,th:first-child{text-align:left}
.prov td{text-align:left}
.note{color:#8a4b00}
code{background:#f3f3f3;padding:0 3px}
section{border-top:2px solid #ddd;margin-top:1.5em}
.plot{margin:.5em 0}
"""

SCRIPT = """
const b64 = s => Uint8Array.from(atob(s), c => c.charCodeAt(0));
const f32 = s => new Float32Array(b64(s).buffer);
const subsetText = {};
function subsets(k) {
  if (subsetText[k]) return subsetText[k];
  const s = SUBSETS[k], code = b64(s.code), rows = [];
  for (let r = 0; r < s.h; r++) {
    const row = [];
    for (let c = 0; c < s.w; c++) {
      const v = code[r * s.w + c];
      const lit = s.views.filter((_, i) => v & (1 << i));
      row.push((lit.length ? 'lit by ' + lit.join(', ') : 'lit by no projector') +
               (v & SHADOWED ? ', shadowed' : '') + (v & NO_TRUTH ? ', no ground truth' : ''));
    }
    rows.push(row);
  }
  return (subsetText[k] = rows);
}
function setRow(k, r) {
  const p = PROFILES[k], div = document.getElementById(p.div);
  if (!p.maps) p.maps = p.series.map(f32);
  r = Math.max(0, Math.min(p.h - 1, r | 0));
  document.getElementById(p.div + '-row').value = r;
  Plotly.restyle(div, {y: p.maps.map(m => Array.from(m.subarray(r * p.w, (r + 1) * p.w)))});
  Plotly.relayout(div, {title: {text: 'profile along row ' + r * p.stride}});
}
for (const f of FIGURES) {
  if (f.subsets !== null)
    for (const t of f.fig.data) if (t.meta === 'subsets') t.text = subsets(f.subsets);
  Plotly.newPlot(f.div, f.fig.data, f.fig.layout, {responsive: true, displaylogo: false});
  if (f.profile !== null)
    document.getElementById(f.div).on('plotly_click', e => {
      const y = e.points[0].y;
      setRow(f.profile, Math.round(y / PROFILES[f.profile].stride));
    });
}
document.body.dataset.plots = String(FIGURES.length);
"""

SIZE_NOTE = (
    "Maps are strided to at most {m} px a side and 3D surfaces to {s} px (the stride is "
    "stated where it applies); hover values are the strided pixels' own, not averages."
)


def _json(value) -> str:
    """JSON safe inside a <script> element."""
    return value.replace("</", "<\\/") if isinstance(value, str) else _json(json.dumps(value))


def markdown_html(text: str) -> str:
    """The subset of Markdown the project's reports use: headings, pipe tables, bullets,
    paragraphs, `code`, **bold**; images are left out (the page draws its own figures)."""

    def inline(s: str) -> str:
        s = html.escape(s)
        s = re.sub(r"`([^`]+)`", r"<code>\1</code>", s)
        return re.sub(r"\*\*([^*]+)\*\*", r"<b>\1</b>", s)

    out, lines, i = [], text.splitlines(), 0
    while i < len(lines):
        line = lines[i].rstrip()
        if line.startswith("|"):
            rows = []
            while i < len(lines) and lines[i].startswith("|"):
                cells = [c.strip() for c in lines[i].strip().strip("|").split("|")]
                if not all(re.fullmatch(r":?-+:?", c) for c in cells):
                    rows.append(cells)
                i += 1
            head, body = rows[0], rows[1:]
            out.append(
                "<table><tr>" + "".join(f"<th>{inline(c)}</th>" for c in head) + "</tr>"
                + "".join("<tr>" + "".join(f"<td>{inline(c)}</td>" for c in r) + "</tr>"
                          for r in body) + "</table>"
            )  # fmt: skip
            continue
        if m := re.match(r"(#{1,4}) (.*)", line):
            level = min(len(m.group(1)) + 1, 5)
            out.append(f"<h{level}>{inline(m.group(2))}</h{level}>")
        elif line.startswith("- "):
            items = []
            while i < len(lines) and lines[i].startswith("- "):
                items.append(f"<li>{inline(lines[i][2:])}</li>")
                i += 1
            out.append("<ul>" + "".join(items) + "</ul>")
            continue
        elif line and not line.startswith("!["):
            out.append(f"<p>{inline(line)}</p>")
        i += 1
    return "\n".join(out)


class _Figures:
    """The figures of a page in order, each with its div and what the script does to it."""

    def __init__(self):
        self.items: list[dict] = []
        self.subsets: list[dict] = []
        self.profiles: list[dict] = []

    def add(self, fig: go.Figure, subsets: int | None = None, profile: int | None = None) -> str:
        div = f"plot{len(self.items)}"
        self.items.append(
            {"div": div, "fig": json.loads(fig.to_json()), "subsets": subsets, "profile": profile}
        )
        return f'<div id="{div}" class="plot"></div>'


def _encode(a: np.ndarray) -> str:
    return base64.b64encode(np.ascontiguousarray(a).tobytes()).decode()


def _scene_section(scene: Scene, figs: _Figures) -> str:
    parts = [f"<section><h2>scene {html.escape(scene.sid)}</h2>"]
    if scene.note:
        parts.append(f'<p class="note">{html.escape(scene.note)}</p>')
    if scene.truth_mm is None:  # a capture's prediction: no truth to take an error against
        parts.append(figs.add(plots.depth_maps(scene)))
        parts.append(figs.add(plots.depth_surface(scene)))
        return "".join(parts) + "</section>"
    s = plots.stride(scene.truth_mm.shape, plots.MAX_MAP_PX)
    subsets = None
    if scene.subsets is not None:
        code = scene.subsets[::s, ::s]
        figs.subsets.append(
            {"h": code.shape[0], "w": code.shape[1], "views": scene.views, "code": _encode(code)}
        )
        subsets = len(figs.subsets) - 1
    row = plots.tallest_row(scene)
    profile, maps = plots.scene_profile(scene, row)
    k = len(figs.profiles)
    parts.append(
        "<p>Signed error = prediction - ground truth in mm, every prediction on one colour "
        f"scale over the scene's largest error, linear below {plots.LINEAR_BELOW_MM:g} mm and "
        "logarithmic above (so both the fine errors and the tall parts' errors of several mm "
        "read); hover for exact values, the table for the error by height above the base plane."
        + (f" Maps strided by {s}." if s > 1 else "") + "</p>"
    )  # fmt: skip
    parts.append(figs.add(plots.scene_maps(scene), subsets=subsets, profile=k))
    parts.append(_bands_table(scene))
    parts.append(figs.add(plots.scene_surfaces(scene)))
    div = f"plot{len(figs.items)}"
    figs.profiles.append(
        {"div": div, "h": maps[0].shape[0], "w": maps[0].shape[1], "stride": s,
         "series": [_encode(m) for m in maps]}
    )  # fmt: skip
    parts.append(
        f'<label>row (px / {s}): <input type="range" id="{div}-row" min="0" '
        f'max="{maps[0].shape[0] - 1}" value="{row}" oninput="setRow({k}, this.value)"></label>'
        " (or click a map)"
    )
    parts.append(figs.add(profile))
    return "".join(parts) + "</section>"


def _bands_table(scene: Scene) -> str:
    names = ["all", *(f"{lo:g}-{hi:g} mm" if np.isfinite(hi) else f"> {lo:g} mm"
                      for lo, hi in plots.HEIGHT_BANDS_MM.values())]  # fmt: skip
    names += ["interior", "edge"]
    if scene.subsets is not None:
        names.append("shadowed")
    rows = "".join(
        f"<tr><td>{html.escape(label)}</td>"
        + "".join(f"<td>{v:.4f}</td>" if np.isfinite(v) else "<td>–</td>" for v in values)
        + "</tr>"
        for label, values in plots.band_errors(scene)
    )
    head = "".join(f"<th>{n}</th>" for n in names)
    return (
        "<table><tr><th>MAE (mm) in this scene, by height above the base plane, away from "
        "and at depth edges</th>"
        f"{head}</tr>{rows}</table>"
    )


def render(page: Page) -> str:
    figs = _Figures()
    body = [f"<h1>{html.escape(page.title)}</h1>"]
    if page.provenance:
        body.append(
            '<table class="prov">'
            + "".join(f"<tr><th>{html.escape(k)}</th><td>{html.escape(v)}</td></tr>"
                      for k, v in page.provenance)
            + "</table>"
        )  # fmt: skip
    body += [f'<p class="note">{html.escape(n)}</p>' for n in page.notes]
    for name, cells in page.tables.items():
        body.append(figs.add(plots.table_bars(name, cells)))
    if page.robustness:
        body.append(figs.add(plots.robustness_curves(page.robustness)))
    if page.scenes:
        body.append(f"<p>{SIZE_NOTE.format(m=plots.MAX_MAP_PX, s=plots.MAX_SURFACE_PX)}</p>")
    body += [_scene_section(scene, figs) for scene in page.scenes]
    if page.markdown:
        body.append("<section><h2>The folder's tables</h2>" + markdown_html(page.markdown))
        body.append("</section>")
    data = (
        f"const FIGURES = {_json(figs.items)};\nconst SUBSETS = {_json(figs.subsets)};\n"
        f"const PROFILES = {_json(figs.profiles)};\n"
        f"const SHADOWED = {SHADOWED_BIT}, NO_TRUTH = {NO_TRUTH_BIT};\n"
    )
    return (
        f'<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8">'
        f"<title>{html.escape(page.title)}</title><style>{STYLE}</style>\n"
        f"<script>{plotly.offline.get_plotlyjs()}</script></head>\n<body>\n"
        + "\n".join(body)
        + f"\n<script>\n{data}{SCRIPT}</script>\n</body></html>\n"
    )


def page_of(folder: Path, out: Path | None = None) -> Path:
    """Write the page of a run, report, robustness report or predict output ``folder`` to
    ``out`` (default ``folder/page.html``), atomically; returns where."""
    out = Path(out) if out else Path(folder) / PAGE
    if out.suffix.lower() not in (".html", ".htm"):
        raise ValueError(f"out={out}: a page is an .html file")
    return write_text(out, render(read(Path(folder))))
