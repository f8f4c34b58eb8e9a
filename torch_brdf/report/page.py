"""The report page: PNG figures (matplotlib, Agg) and one self-contained HTML file.

The HTML embeds every figure (base64 PNG) and links the PNG file written beside it, so the
page can be mailed alone and the docs can link the PNGs. Tables never show NaN: a value
that is missing reads "not measured", a non-finite one "not finite".
"""

from __future__ import annotations

import base64
import html
import json
import math
import os
import time
from pathlib import Path
from typing import Any

from ..io.atomic import replacing
from .sections import Figure, Section

#: matplotlib marker styles of the series kinds
_STYLE = {
    "curve": {"marker": "o", "linestyle": "-", "markersize": 4},
    "point": {"marker": "o", "linestyle": "none", "markersize": 6, "markerfacecolor": "none"},
    "default": {"marker": "s", "linestyle": "none", "markersize": 10, "color": "black", "markerfacecolor": "none"},
    "planner": {"marker": "*", "linestyle": "none", "markersize": 15, "color": "crimson"},
    "peer": {"marker": "D", "linestyle": "none", "markersize": 8},
    "seed": {"marker": "P", "linestyle": "none", "markersize": 10, "color": "purple"},
}


def fmt(v: Any) -> str:
    """A table cell: numbers to 4 significant digits; missing -> "not measured"."""
    if v is None:
        return "not measured"
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, float):
        return f"{v:.4g}" if math.isfinite(v) else "not finite"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, str):
        return v
    text = json.dumps(v, default=str)
    return text.replace("NaN", "not finite").replace("Infinity", "not finite")


def plot(fig: Figure, path: Path) -> int:
    """Draw ``fig`` to the PNG ``path``; returns how many points were dropped from a log axis
    (non-positive values)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    f, ax = plt.subplots(figsize=(6.4, 4.2), dpi=90)
    dropped = 0
    for s in fig.series:
        keep = [(x, y) for x, y in s.points if (not fig.xlog or x > 0) and (not fig.ylog or y > 0)]
        dropped += len(s.points) - len(keep)
        kw = dict(_STYLE.get(s.style, _STYLE["point"]))
        if keep:
            ax.plot([x for x, _ in keep], [y for _, y in keep], label=s.label, **kw)
        line = {"color": kw.get("color", "grey"), "linestyle": "--", "linewidth": 1, "label": s.label}
        if s.vline is not None and (not fig.xlog or s.vline > 0):
            ax.axvline(s.vline, **line)
        if s.hline is not None and (not fig.ylog or s.hline > 0):
            ax.axhline(s.hline, **line)
    from matplotlib.ticker import FuncFormatter, LogLocator

    short = FuncFormatter(lambda v, _: f"{v:.2g}")
    for log, axis, scale in ((fig.xlog, ax.xaxis, ax.set_xscale), (fig.ylog, ax.yaxis, ax.set_yscale)):
        if log:  # labels at 1, 2 and 5 times each power of ten, short numbers (no 10^x collisions)
            scale("log")
            axis.set_minor_locator(LogLocator(base=10, subs=(2.0, 5.0)))
            axis.set_major_formatter(short)
            axis.set_minor_formatter(short)
    ax.set_xlabel(fig.xlabel)
    ax.set_ylabel(fig.ylabel)
    ax.set_title(fig.title, fontsize=10)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=6.5, loc="best")
    f.tight_layout()
    with replacing(path) as tmp:
        f.savefig(tmp, format="png")
    plt.close(f)
    return dropped


def _table(rows: list[list[str]], head: list[str], cls: str = "") -> str:
    h = "".join(f"<th>{html.escape(c)}</th>" for c in head)
    body = "".join("<tr>" + "".join(f"<td>{c}</td>" for c in r) + "</tr>" for r in rows)
    return f'<table class="{cls}"><tr>{h}</tr>{body}</table>'


def _run_rows(results: dict[str, dict]) -> list[list[str]]:
    rows = []
    for name, rec in results.items():
        ok = rec.get("error") is None and rec.get("result") is not None
        status = "ok" if ok else f'<span class="bad">{html.escape(str(rec.get("error")))}</span>'
        rows.append(
            [
                html.escape(name),
                f"<code>{html.escape(str(rec.get('command', '')))}</code>",
                fmt(rec.get("quick", (rec.get("result") or {}).get("quick"))),
                status,
                fmt(rec.get("seconds")),
                fmt(rec.get("cpu_s")),
                f"{fmt(rec.get('load_before'))} / {fmt(rec.get('load_after'))}",
                fmt(rec.get("peak_rss_mb")),
            ]
        )
    return rows


def extremes_html(rec: dict | None) -> str:
    """The extremes grid (rows: the extremes; columns: renderers and solvers) and its detail table."""
    cells = (rec or {}).get("result", {}) or {}
    cells = cells.get("cells") if isinstance(cells, dict) else None
    if not cells:
        err = (rec or {}).get("error") or "benchmarks/extremes.py did not run"
        return f'<p class="bad">Extremes not measured: {html.escape(str(err))}</p>' + _log(rec)
    rows = list(dict.fromkeys(c["row"] for c in cells))
    cols = list(dict.fromkeys(c["column"] for c in cells))
    by = {(c["row"], c["column"]): c for c in cells}

    def cell(c: dict | None) -> str:
        if c is None:
            return '<td class="na">—</td>'
        cls = "good" if c.get("ok") else "badcell"
        if c.get("status") == "finite":
            e, bd = c.get("error"), c.get("bound")
            txt = (
                f"finite, {e:.2g} ≤ {bd:.2g}"
                if isinstance(e, (int, float)) and isinstance(bd, (int, float))
                else "finite"
            )
        else:
            txt = ("raises " if c.get("status") == c.get("expect") else "") + html.escape(str(c.get("status")))
        return f'<td class="{cls}" title="{html.escape(str(c.get("note", "")))}">{txt}</td>'

    grid = "<tr><th></th>" + "".join(f"<th>{html.escape(r)}</th>" for r in rows) + "</tr>"
    for c in cols:
        grid += f"<tr><th>{html.escape(c)}</th>" + "".join(cell(by.get((r, c))) for r in rows) + "</tr>"
    detail = _table(
        [
            [
                html.escape(str(c[k])) if k in ("row", "column", "expect", "status", "note") else fmt(c.get(k))
                for k in ("row", "column", "expect", "status", "error", "bound", "note", "seconds")
            ]
            + ["yes" if c.get("ok") else '<span class="bad">NO</span>']
            for c in cells
        ],
        [
            "renderer / solver",
            "extreme",
            "expected",
            "outcome",
            "error",
            "bound",
            "what was measured",
            "seconds",
            "as expected",
        ],
        "small",
    )
    failed = sum(not c.get("ok") for c in cells)
    head = (
        f"<p>{len(cells)} cells, {failed} not as expected. Each cell is <code>tests/test_extremes.py</code>'s "
        "<code>evaluate(case)</code>, the function <code>test_extreme</code> asserts on.</p>"
    )
    return (
        head + f'<table class="grid">{grid}</table>' + "<details><summary>every cell</summary>" + detail + "</details>"
    )


def _log(rec: dict | None) -> str:
    tail = (rec or {}).get("log_tail")
    return f"<pre>{html.escape(tail)}</pre>" if tail else ""


_CSS = """
body{font-family:sans-serif;max-width:1100px;margin:auto;padding:1em;color:#222}
table{border-collapse:collapse;margin:.5em 0}td,th{border:1px solid #ccc;padding:2px 6px;font-size:13px;text-align:left}
table.small td{font-size:11px}table.grid td{font-size:11px}
.good{background:#e6f4e6}.badcell{background:#f8d7d7}.bad{color:#b00;font-weight:bold}.na{color:#999}
figure{display:inline-block;margin:.5em;vertical-align:top;max-width:520px}figure img{max-width:100%}
figcaption{font-size:12px;color:#444}pre{background:#f4f4f4;padding:.5em;font-size:11px;overflow:auto;max-height:20em}
.note{font-size:12px;color:#a60}
"""


def write_page(
    results: dict[str, dict], secs: list[Section], out_dir: str | os.PathLike, title: str, meta: dict[str, Any]
) -> Path:
    """Write ``report.html`` and one PNG per figure with data into ``out_dir``; returns the page."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    parts = [f"<h1>{html.escape(title)}</h1>"]
    parts.append("<p>" + "; ".join(f"{html.escape(k)}: {html.escape(fmt(v))}" for k, v in meta.items()) + "</p>")
    parts.append(
        "<p>Legend: line = a measured curve; □ = the default; ★ = the planner's choice; ◆ = the peer in "
        "the same run; ✚ / dashed purple = the seed paper's published figure.</p>"
    )
    toc = "".join(f'<li><a href="#{s.key}">{html.escape(s.title)}</a></li>' for s in secs)
    parts.append(
        f'<ul>{toc}<li><a href="#extremes">Numerical extremes</a></li><li><a href="#runs">Benchmark runs</a></li></ul>'
    )
    for s in secs:
        parts.append(f'<h2 id="{s.key}">{html.escape(s.title)}</h2>')
        for name in s.benchmarks:
            rec = results.get(name)
            if rec is None:
                parts.append(f'<p class="note">benchmarks/{name}.py: not run</p>')
            elif rec.get("error"):
                parts.append(
                    f'<p class="bad">benchmarks/{name}.py failed: {html.escape(str(rec["error"]))}</p>{_log(rec)}'
                )
        for fig in s.figures:
            if not fig.has_data():
                parts.append(f'<p class="note">{html.escape(fig.title)}: not measured (no data points in this run)</p>')
                continue
            png = f"{fig.key}.png"
            dropped = plot(fig, out / png)
            data = base64.b64encode((out / png).read_bytes()).decode()
            cap = html.escape(fig.caption) + (
                f" ({dropped} non-positive values not shown on the log axes)" if dropped else ""
            )
            parts.append(
                f'<figure><a href="{png}"><img src="data:image/png;base64,{data}" alt="{html.escape(fig.title)}" '
                f'data-file="{png}"></a><figcaption>{cap} <a href="{png}">{png}</a></figcaption></figure>'
            )
        for n in s.notes:
            parts.append(f'<p class="note">{html.escape(n)}</p>')
        if s.numbers:
            parts.append(
                _table([[html.escape(k), html.escape(fmt(v))] for k, v in s.numbers.items()], ["figure", "value"])
            )
    parts.append('<h2 id="extremes">Numerical extremes</h2>' + extremes_html(results.get("extremes")))
    parts.append('<h2 id="runs">Benchmark runs</h2>')
    parts.append(
        _table(
            _run_rows(results),
            ["benchmark", "command", "quick", "status", "seconds", "CPU s", "load 1-min before / after", "peak RSS MB"],
        )
    )
    head = f"<meta charset='utf-8'><title>{html.escape(title)}</title><style>{_CSS}</style>"
    page = f"<!DOCTYPE html><html><head>{head}</head><body>{''.join(parts)}</body></html>"
    path = out / "report.html"
    with replacing(path) as tmp:
        Path(tmp).write_text(page)
    return path


def machine() -> dict[str, Any]:
    """What the page states about where it was made: time, cores, load averages."""
    load = os.getloadavg()
    return {
        "generated": time.strftime("%Y-%m-%d %H:%M:%S"),
        "cores usable": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count(),
        "load average (1/5/15 min) at the end": " / ".join(f"{x:.2f}" for x in load),
    }
