"""The speed/accuracy report: a quick report is rendered and checked for form.

The input is real: ``docs/results/`` holds the JSON that ``python benchmarks/<name>.py
--quick`` printed on this kind of machine (its ``README.md`` says how), and the
extremes benchmark is run here through the report's runner on a few cells. A benchmark that
fails must show in the page, not stop it.
"""

from __future__ import annotations

import base64
import re
import shutil
from html.parser import HTMLParser
from pathlib import Path

import pytest
from typer.testing import CliRunner

from torch_brdf.cli import app
from torch_brdf.errors import FileFormatError, ValueRangeError
from torch_brdf.report import make_report
from torch_brdf.report.run import BENCHMARKS, QUICK_ARGS, find_benchmarks, load_results, run_benchmark
from torch_brdf.report.sections import CAPABILITIES, planner_choices, sections

pytest.importorskip("matplotlib")

DATA = Path(__file__).resolve().parents[2] / "docs" / "results"
REPO = Path(__file__).resolve().parents[2]
PNG = b"\x89PNG\r\n\x1a\n"


class _Page(HTMLParser):
    """Collects tags (checking that the non-void ones nest), images, links and cell texts."""

    VOID = frozenset({"meta", "img", "br", "hr", "link", "input"})

    def __init__(self):
        super().__init__()
        self.stack, self.errors, self.imgs, self.hrefs, self.cells = [], [], [], [], []
        self._cell = None

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        if tag == "img":
            self.imgs.append(a)
        if tag == "a" and "href" in a:
            self.hrefs.append(a["href"])
        if tag in ("td", "th"):
            self._cell = []
        if tag not in self.VOID:
            self.stack.append(tag)

    def handle_endtag(self, tag):
        if tag in ("td", "th") and self._cell is not None:
            self.cells.append("".join(self._cell))
            self._cell = None
        if not self.stack or self.stack[-1] != tag:
            self.errors.append(f"</{tag}> closes {self.stack[-1:] or 'nothing'}")
        else:
            self.stack.pop()

    def handle_data(self, data):
        if self._cell is not None:
            self._cell.append(data)


@pytest.fixture(scope="module")
def quick_report(tmp_path_factory):
    """A quick report from the saved quick-run JSON, the extremes run live on three cells and a
    scaleout benchmark that crashes."""
    tmp = tmp_path_factory.mktemp("report")
    results = tmp / "results"
    shutil.copytree(DATA, results, ignore=shutil.ignore_patterns("*.md"))
    only = ["--only", "cond(H)", "--only", "infeasible", "--only", "GPLVM (manifold)/float32"]
    rec = run_benchmark("extremes", find_benchmarks(REPO / "benchmarks"), True, results, timeout=600, args=only)
    broken = tmp / "broken"
    broken.mkdir()
    (broken / "scaleout.py").write_text("print('starting')\nraise RuntimeError('boom: the cluster is gone')\n")
    run_benchmark("scaleout", broken, True, results, timeout=60)
    page = make_report(tmp / "out", quick=True, results=results)
    return page, load_results(results), rec


def test_the_live_extremes_run_is_recorded(quick_report):
    _, _, rec = quick_report
    assert rec["error"] is None and rec["returncode"] == 0, rec
    cells = rec["result"]["cells"]
    assert len(cells) == 3 and all(c["ok"] for c in cells)
    assert {c["status"] for c in cells} == {"finite", "InfeasibleError"}
    assert rec["peak_rss_mb"] > 10 and rec["seconds"] > 0 and 0 < rec["cpu_s"]


def test_page_is_well_formed(quick_report):
    page, recs, _ = quick_report
    p = _Page()
    p.feed(page.read_text())
    p.close()
    assert not p.errors and not p.stack, (p.errors, p.stack)
    # every figure with data is a PNG beside the page, embedded and linked; nothing else is there
    figs = [f for s in sections(recs) for f in s.figures if f.has_data()]
    files = {f.name for f in page.parent.glob("*.png")}
    assert files == {f"{f.key}.png" for f in figs}
    embedded = {a["data-file"]: a["src"] for a in p.imgs}
    assert set(embedded) == files
    for name in files:
        raw = (page.parent / name).read_bytes()
        assert raw.startswith(PNG) and name in p.hrefs
        assert base64.b64decode(embedded[name].split(",", 1)[1]) == raw
    # every capability whose benchmark left a result has a figure (the broken scaleout has none)
    drawn = {s.key for s in sections(recs) if any(f.has_data() for f in s.figures)}
    ran = {s.key for s in sections(recs) if s.figures and (recs.get(s.benchmarks[0]) or {}).get("result")}
    assert ran <= drawn and len(drawn) >= 3 and "scaleout" not in drawn
    # no NaN in any table; the failure of a benchmark is in the page
    assert not [c for c in p.cells if re.search(r"\bnan\b", c, re.I)]
    text = page.read_text()
    assert "benchmarks/scaleout.py failed" in text and "boom: the cluster is gone" in text


def test_images_decode(quick_report):
    import matplotlib.image as mpimg

    page, _, _ = quick_report
    for png in page.parent.glob("*.png"):
        img = mpimg.imread(png)
        assert img.ndim == 3 and img.shape[0] > 100 and img.shape[1] > 100
        assert float(img[..., :3].std()) > 0.01  # not a blank canvas


def test_extremes_table_is_the_test_modules_cells(quick_report):
    page, recs, _ = quick_report
    text = page.read_text()
    cells = recs["extremes"]["result"]["cells"]
    grid = text.split('<table class="grid">', 1)[1].split("</table>", 1)[0]
    assert grid.count("<td") == len({c["row"] for c in cells}) * len({c["column"] for c in cells})
    assert grid.count('class="good"') == sum(c["ok"] for c in cells)


def test_missing_keys_and_grown_planner_json_degrade_gracefully():
    planner = {
        "scene": "cornell_box_glossy",
        "planned": {"series": "16,1,1", "spp": 13, "achieved_error": 0.17, "seconds": 0.2},
        "defaults": {"64,1,1,1": [{"spp": 64, "achieved_error": 0.1, "seconds": 1.0}]},
        "scenes": {
            "teatray": {"scene": "teatray", "planned": {"series": "8,1", "achieved_error": 0.05, "seconds": 2.0}}
        },
        "relighting": {
            "planned": {"frame_s": 0.1, "psnr": 40.0, "cost_s": 2.0, "predicted_cost_s": 1.5, "predicted_psnr": 41.0},
            "defaults": [{"cubemap": 64, "rule": "appendix-a:1", "cost_s": 3.0, "psnr": 38.0}],
        },
        "inverse": {
            "error": 0.05,
            "planned": {"light_samples": 256, "achieved_error": 0.04, "seconds": 1.0},
            "default": {"achieved_error": 0.01, "seconds": 3.0},
        },
    }
    found = dict(planner_choices(planner))
    assert set(found) == {"gi", "scenes.teatray", "relighting", "inverse"}
    assert found["gi"]["defaults"]["64,1,1,1"][0]["spp"] == 64
    recs = {"planner": {"result": planner}, "polynomial": {"result": {"rel_rmse": {}}}}
    secs = {s.key: s for s in sections(recs)}
    assert any("not measured" in n and "accuracy_resolution" in n for n in secs["gi"].notes)
    assert {f.key for f in secs["gi"].figures if f.has_data()} >= {
        "gi_planner_cornell_box_glossy",
        "gi_planner_teatray",
    }
    assert "gi_planner_relighting" not in {f.key for f in secs["gi"].figures}  # another capability's planner
    assert [f.key for f in secs["inverse"].figures if f.has_data()] == ["inverse_planner"]
    assert "relight_planner" in {f.key for f in secs["relight"].figures if f.has_data()}
    assert len(sections({})) == len(CAPABILITIES)  # nothing ran: every section, no figure, no error


def test_manifold_figure_puts_the_plan_on_the_curves_statistic():
    """The held-out curves are means over materials; the planner plans an interquartile mean of
    the logs: its ★ sits at the plan's mean, its planned statistic is a separate, labelled point
    (and an older run without the mean shows no ★ at all)."""
    manifold = {"data": "NBRDF", "heldout_logrmse_mean": {"2": 0.39, "5": 0.35}}
    planned = {"q": 3, "n": 34, "achieved_error": 0.004, "achieved_mean": 0.02, "statistic": "trimmed", "heldout": 240}
    planner = {"manifold": {"planned": planned}}

    def heldout(planner: dict) -> dict:
        recs = {"manifold": {"result": manifold}, "planner": {"result": planner}}
        fig = next(f for f in {s.key: s for s in sections(recs)}["manifold"].figures if f.key == "manifold_heldout")
        return {s.label: (s.style, s.points) for s in fig.series if s.points}

    got = heldout(planner)
    stars = [(label, p) for label, (style, p) in got.items() if style == "planner"]
    assert stars == [(stars[0][0], [(3.0, 0.02)])] and "mean" in stars[0][0]
    assert [label for label, (_, p) in got.items() if p == [(3.0, 0.004)]] == [
        "the same plan, trimmed (what it plans for)"
    ]
    old = {k: v for k, v in planned.items() if k not in ("achieved_mean", "statistic")}
    assert [s for s, _ in heldout({"manifold": {"planned": old}}).values()].count("planner") == 0


def test_manifold_caption_says_how_many_splits():
    """The quick report runs the held-out study on two splits: the caption says the count the
    benchmark printed (and no count when an older run did not print one)."""

    def caption(result: dict) -> str:
        sec = {s.key: s for s in sections({"manifold": {"result": result}})}["manifold"]
        return next(f for f in sec.figures if f.key == "manifold_heldout").caption

    assert "averaged over 2 random 80/20 splits" in caption({"splits": 2, "data": "NBRDF"})
    assert "averaged over the random 80/20 splits" in caption({"data": "NBRDF"})


def test_a_skipped_ray_start_is_a_cell_not_a_crash():
    """scaleout.py prints ``ray_skipped`` (and its local figures) when Ray does not start in its
    time: the section says so in a cell, draws the local point and lists no Ray key as missing."""
    skipped = "skipped: Ray (1 worker(s)) did not start in 9 tries, 301 s (load 22.0): node timed out"
    recs = {
        "scaleout": {
            "result": {"quick": True, "cpus": 2, "local_s": 1.3, "local_tiles_per_s": 6.2, "ray_skipped": skipped}
        }
    }
    sec = {s.key: s for s in sections(recs)}["scaleout"]
    assert sec.numbers["scaleout.ray"] == skipped and sec.numbers["scaleout.local_s"] == 1.3
    assert not sec.notes and [f.key for f in sec.figures if f.has_data()] == ["scaleout_time"]


def test_cli_report_from_saved_results(tmp_path):
    results = tmp_path / "r"
    results.mkdir()
    shutil.copy(DATA / "planner.json", results / "planner.json")
    (results / "brdf.out").write_text("progress\n" + (DATA / "brdf.json").read_text().strip() + "\n")
    res = CliRunner().invoke(app, ["report", "--results", str(results), "--out", str(tmp_path / "o")])
    assert res.exit_code == 0, res.output
    assert (tmp_path / "o" / "report.html").is_file() and (
        tmp_path / "o" / "gi_planner_cornell_box_glossy.png"
    ).is_file()
    bad = CliRunner().invoke(app, ["report", "--only", "nosuch", "--out", str(tmp_path / "o")])
    assert bad.exit_code == 2 and "nosuch" in bad.output
    with pytest.raises(ValueRangeError):
        make_report(tmp_path / "o", only=["nosuch"])
    (results / "bad.json").write_text("{not json")
    with pytest.raises(FileFormatError):
        load_results(results)


@pytest.mark.parametrize("text", ['{"cells": "none"}', '{"failed": 0}', '{"cells": [{"row": "nan"}]}', "[1]"])
def test_cli_report_refuses_a_malformed_extremes_file(tmp_path, text):
    results = tmp_path / "r"
    results.mkdir()
    (results / "extremes.json").write_text(text)
    res = CliRunner().invoke(app, ["report", "--results", str(results), "--out", str(tmp_path / "o")])
    assert res.exit_code == 2, res.output
    (line,) = res.output.strip().splitlines()  # one line, no traceback
    assert line.startswith("error: ") and "extremes.json" in line
    assert not (tmp_path / "o" / "report.html").exists()


def test_quick_report_passes_its_options_to_the_scripts(tmp_path):
    """``torch-brdf report --quick`` runs each script with ``--quick`` and that script's
    ``QUICK_ARGS`` (then any explicit ``args``), shows them in the command, and every option
    there is one the real script declares; the full report passes none of them."""
    (tmp_path / "manifold.py").write_text("import json, sys\nprint(json.dumps({'argv': sys.argv[1:]}))\n")
    rec = run_benchmark("manifold", tmp_path, True, timeout=60, args=["--no-peer"])
    assert rec["error"] is None, rec
    assert rec["result"]["argv"] == ["--quick", *QUICK_ARGS["manifold"], "--no-peer"]
    assert rec["command"] == " ".join(["python benchmarks/manifold.py --quick", *QUICK_ARGS["manifold"], "--no-peer"])
    assert run_benchmark("manifold", tmp_path, False, timeout=60)["result"]["argv"] == []
    for name, opts in QUICK_ARGS.items():
        assert name in BENCHMARKS and opts
        text = (REPO / "torch_brdf" / "report" / "benchmarks" / f"{name}.py").read_text()
        for opt in (o for o in opts if o.startswith("--")):
            assert f'add_argument("{opt}"' in text or f'add_argument(\n        "{opt}"' in text, (name, opt)


def test_manifold_default_figures_draw_each_heldout_case_against_the_required_margin():
    case = {"2": {"margin": 0.12, "interpolation_share": 0.5}, "5": {"margin": 0.2, "interpolation_share": 0.7}}
    result = {"default_heldout": {"split0": case, "metals": case}, "default_families": ["metals", "woods"]}
    figs = {f.key: f for f in {s.key: s for s in sections({"manifold": {"result": result}})}["manifold"].figures}
    margin = {s.label: s for s in figs["manifold_default_margin"].series}
    assert margin["split0"].points == [(2.0, 0.12), (5.0, 0.2)] and margin["required margin (10%)"].hline == 0.10
    assert "metals, woods" in figs["manifold_default_margin"].caption
    assert {s.label: s.points for s in figs["manifold_interpolation"].series}["metals"] == [(2.0, 0.5), (5.0, 0.7)]
    assert sections({"manifold": {"result": {}}})  # an older run without the study: no crash
