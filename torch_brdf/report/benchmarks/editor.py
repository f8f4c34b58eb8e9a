"""The material editor's latency in a real browser.

    python benchmarks/editor.py [--quick] [--steps 50] [--spp 4]

For each size, the glossy Cornell box is precomputed (series 64,1,1,1; kept in ``--tensors``,
default ``out/bench_editor/``, for the next run), the editor is served by
Voilà on 127.0.0.1 and opened in Debian's chromium through Playwright, the back wall is
selected (frozen), and the exponent slider is stepped ``--steps`` times with the keyboard
(one ArrowRight per step, each waiting for its frame). Latency: from the key event to the
paint after the new frame was drawn, measured in the page by the frame widget (the number
the page shows), i.e. the whole loop: browser -> websocket -> kernel (projection onto the
wall's 64 bands, frozen frame, sRGB, send) -> browser (draw). After each frame the kernel
also redraws the lobe and the lit sphere; a next input waits for that, so it is inside the
measured latency of the following step, as it is for a user.

Then the switch between two objects: the left wall is clicked (its first visit freezes it, not
counted) and given Blinn-Phong, and ``--switches`` times the back wall and the left wall are
clicked in turn, each click followed by three exponent steps; ``switch_worst_ms_<size>`` is the
worst latency of those clicks and steps (a click is answered by a frame), ``switch_ms_<size>``
the median of the clicks alone. After the first visits every switch finds a frozen state the
renderer kept (current, or brought up to date exactly).

Prints progress, then one JSON object as the last line: ``latency_ms_<size>`` (median),
``p95_ms_<size>``, ``updates_per_s_<size>`` (1000 / median latency: sequential steps),
``frame_ms_<size>`` (median kernel frame time shown on the page), ``kernel_ms_<size>``
(projection + frame + encoding), ``draw_ms_<size>`` (the page decoding, tone mapping and
drawing a message), ``message_kb_<size>`` (median bytes of a frame message: RGBE, 4 bytes a
pixel, or only the changed tiles) and ``rgb8_kb_<size>`` (the raw 8-bit RGB frame, what was
sent before), the switch keys above, the baseline in the same run: the earlier transport (8-bit
sRGB made by the kernel in the widget's synced state, the latency synced back per frame:
``frame_transport="state"``) over the same steps, ``latency_ms_state_<size>``,
``p95_ms_state_<size>``, ``draw_ms_state_<size>`` and ``speedup_vs_state_<size>`` (its median
over the new median; ``--no-baseline`` skips it), the kernel's parts measured in-process right after with
their baseline in the same run (``inproc_{project,frame,frame_dense,srgb,rgbe}_ms_<size>``,
``frame_speedup_vs_dense_<size>``: the frame over F's non-zeros against the dense F), and the
load average at the start and end (``load_avg_start``, ``load_avg_end``: the page's figures
share the cores with the server and the browser). ``--quick``: 256² and 512², 20 steps,
2 switches, 1 spp.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import statistics
import sys
import time
from pathlib import Path

MAIN = ".tb-frame-wrap:has(canvas.tb-main)"


def _step(page, action) -> float:
    """Do ``action`` and wait for its frame; the page's latency of it (ms)."""
    n = int(page.eval_on_selector(MAIN, "e => Number(e.dataset.frames)"))
    before = int(page.evaluate("() => window.__torch_brdf.latencies.length"))
    action()
    page.wait_for_function(
        f"() => Number(document.querySelector('{MAIN}').dataset.frames) > {n}"
        f" && window.__torch_brdf.latencies.length > {before}"
    )
    return float(page.evaluate("() => window.__torch_brdf.latencies.at(-1)"))


def _click_object(page, ids, names, name: str) -> None:
    """Click the pixel of ``name`` nearest its centroid (in the main canvas)."""
    import torch

    ys, xs = torch.nonzero(ids == names.index(name), as_tuple=True)
    k = int(((ys - ys.float().mean()) ** 2 + (xs - xs.float().mean()) ** 2).argmin())
    box = page.query_selector("canvas.tb-main").bounding_box()
    h, w = ids.shape
    page.mouse.click(
        box["x"] + (int(xs[k]) + 0.5) * box["width"] / w, box["y"] + (int(ys[k]) + 0.5) * box["height"] / h
    )


def switches(page, ids, names, rounds: int) -> dict:
    """Latencies of clicks between the back and the left wall and of the edits after each."""
    _click_object(page, ids, names, "left")  # first visit: frozen now (not counted)
    page.wait_for_selector(".tb-selected[data-object='left']")
    page.select_option(".tb-model select", label="blinn_phong")
    page.wait_for_selector(".tb-param-exponent .noUi-handle")
    time.sleep(1.0)
    clicks, after = [], []
    for _ in range(rounds):
        for name in ("back", "left"):
            old = page.query_selector(".tb-param-exponent .noUi-handle")
            clicks.append(_step(page, lambda name=name: _click_object(page, ids, names, name)))
            page.wait_for_selector(f".tb-selected[data-object='{name}']")
            page.wait_for_function("el => !el.isConnected", arg=old)  # the new object's form replaced it
            page.wait_for_selector(".tb-param-exponent .noUi-handle")
            time.sleep(0.3)
            page.focus(".tb-param-exponent .noUi-handle")
            for _ in range(3):
                after.append(_step(page, lambda: page.keyboard.press("ArrowRight")))
    return {"clicks": clicks, "after": after}


def _p95(xs: list[float]) -> float:
    s = sorted(xs)
    return s[min(len(s) - 1, round(0.95 * (len(s) - 1)))]


def measure(size: int, steps: int, spp: int, workdir: Path, threads, n_switch: int = 0, transport="messages") -> dict:
    from playwright.sync_api import sync_playwright

    from torch_brdf.editor.server import EditorServer, launch_chromium
    from torch_brdf.scene import cornell_box_glossy
    from torch_brdf.transport import PolynomialSettings, precompute_polynomial

    path = workdir / f"cornell_box_glossy_{size}_{spp}spp.npz"
    if not path.is_file():
        t0 = time.perf_counter()
        precompute_polynomial(cornell_box_glossy(size), PolynomialSettings("64,1,1,1", spp=spp), seed=0).save(path)
        print(f"{size}²: precomputed in {time.perf_counter() - t0:.1f} s", file=sys.stderr)
    from torch_brdf.editor import object_id_buffer
    from torch_brdf.records import PolynomialTensors

    tensors = PolynomialTensors.load(path)
    ids, _ = object_id_buffer(tensors, cornell_box_glossy(size))
    names = list(tensors.object_names)
    config = {"source": str(path), "display_width": 512, "threads": threads, "frame_transport": transport}
    with EditorServer(config, timeout=300) as server, sync_playwright() as p:
        browser = launch_chromium(p)
        try:
            page = browser.new_page(viewport={"width": 1400, "height": 1200})
            page.set_default_timeout(300_000)
            page.goto(server.url)
            page.wait_for_function(f"() => Number(document.querySelector('{MAIN}')?.dataset.frames) > 0")
            page.wait_for_selector(".tb-selected[data-object='back']")
            page.focus(".tb-param-exponent .noUi-handle")
            time.sleep(2.0)  # let the first lobe and sphere draw
            lat, frame_ms, kernel_ms, wall = [], [], [], []
            for _ in range(steps):
                t = time.perf_counter()
                lat.append(_step(page, lambda: page.keyboard.press("ArrowRight")))
                wall.append((time.perf_counter() - t) * 1e3)
                cap = page.inner_text(f"{MAIN} .tb-caption")
                m = re.search(r"frame ([\d.]+) ms · projection ([\d.]+) ms · kernel ([\d.]+) ms", cap)
                if m:
                    frame_ms.append(float(m.group(1)))
                    kernel_ms.append(float(m.group(3)))
            draws = page.evaluate("() => window.__torch_brdf.draws || []")
            sent = page.evaluate("() => window.__torch_brdf.bytes || []")
            exponent = page.input_value(".tb-typed-exponent input")
            sw = switches(page, ids, names, n_switch) if n_switch else None
            if transport != "messages":
                steps_lat = {f"latency_ms_{transport}_{size}": round(statistics.median(lat), 1)}
                steps_lat[f"p95_ms_{transport}_{size}"] = round(_p95(lat), 1)
                steps_lat[f"draw_ms_{transport}_{size}"] = round(statistics.median(draws), 2) if draws else None
                print(f"{size}² ({transport} transport): {steps_lat}", file=sys.stderr)
                return steps_lat
            status = page.inner_text("body")
            m = re.search(r"(\d) torch threads? \(timed\)", status)
            chosen = int(m.group(1)) if m else None
        finally:
            browser.close()
    out = {
        f"latency_ms_{size}": round(statistics.median(lat), 1),
        f"p95_ms_{size}": round(_p95(lat), 1),
        f"updates_per_s_{size}": round(1000.0 / statistics.median(lat), 1),
        f"frame_ms_{size}": round(statistics.median(frame_ms), 2) if frame_ms else None,
        f"kernel_ms_{size}": round(statistics.median(kernel_ms), 1) if kernel_ms else None,
        f"playwright_ms_{size}": round(statistics.median(wall), 1),
        f"threads_{size}": chosen if chosen is not None else threads,
        f"draw_ms_{size}": round(statistics.median(draws), 2) if draws else None,
        f"message_kb_{size}": round(statistics.median(sent) / 1024, 1) if sent else None,
        f"rgb8_kb_{size}": round(size * size * 3 / 1024, 1),
    }
    if sw is not None:
        out[f"switch_worst_ms_{size}"] = round(max(sw["clicks"] + sw["after"]), 1)
        out[f"switch_ms_{size}"] = round(statistics.median(sw["clicks"]), 1)
        out[f"switch_after_ms_{size}"] = round(statistics.median(sw["after"]), 1)
    out.update(breakdown(path, size, 1 if threads == "auto" else threads))
    print(f"{size}²: {out} (exponent now {exponent})", file=sys.stderr)
    return out


def breakdown(path: Path, size: int, threads: int, steps: int = 15) -> dict:
    """The kernel's share in-process, same tensors and load as the browser run: projection,
    frozen frame (non-zeros of F, as the editor runs it) against the dense frame (the
    baseline: the frame reading F itself), and the sRGB table; medians in ms."""
    import torch

    from torch_brdf.editor.app import srgb8_fast
    from torch_brdf.editor.session import EditorSession
    from torch_brdf.records import PolynomialTensors

    torch.set_num_threads(threads)
    s = EditorSession(PolynomialTensors.load(path))
    s.select("back")
    mat = {"type": "blinn_phong", "kd": 0.3, "ks": 0.5, "exponent": 100.0}
    from torch_brdf.editor.widgets import encode_rgbe

    t = {"project": [], "frame": [], "frame_dense": [], "srgb": [], "rgbe": []}
    for k in range(steps):
        mat["exponent"] = 100.0 * 1.05**k
        t["project"].append(s.set_material("back", mat))
        t0 = time.perf_counter()
        img = s.renderer()
        t["frame"].append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        srgb8_fast(img)
        t["srgb"].append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        encode_rgbe(img)
        t["rgbe"].append(time.perf_counter() - t0)
        fz = s.renderer._frozen
        kept = fz["nonzeros"]
        fz["nonzeros"] = (fz["F"], None)  # the dense baseline: the frame reads F itself
        t0 = time.perf_counter()
        dense = s.renderer()
        t["frame_dense"].append(time.perf_counter() - t0)
        fz["nonzeros"] = kept
        assert torch.allclose(dense, img, rtol=1e-4, atol=1e-5 * float(img.abs().max()))
    med = {k: statistics.median(v) * 1e3 for k, v in t.items()}
    out = {f"inproc_{k}_ms_{size}": round(v, 2) for k, v in med.items()}
    out[f"frame_speedup_vs_dense_{size}"] = round(med["frame_dense"] / med["frame"], 2)
    print(f"{size}² in-process: {out}", file=sys.stderr)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="256² and 512², 20 steps, 2 switches, 1 spp")
    ap.add_argument("--no-baseline", dest="baseline", action="store_false", help="skip the earlier transport's run")
    ap.add_argument("--switches", type=int, default=None, help="rounds of back/left clicks (default 5, quick 2)")
    ap.add_argument("--steps", type=int, default=None)
    ap.add_argument("--spp", type=int, default=None)
    ap.add_argument("--threads", default="auto", help="torch threads of the editor's kernel (an int or auto)")
    ap.add_argument("--tensors", type=Path, default=Path("out/bench_editor"), help="where the tensors are kept")
    args = ap.parse_args()
    from torch_brdf.editor.server import CHROMIUM

    if not os.path.exists(CHROMIUM):
        sys.exit(f"{CHROMIUM} not found: apt-get install -y chromium")
    sizes = (256, 512)
    steps = args.steps or (20 if args.quick else 50)
    spp = args.spp or (1 if args.quick else 4)
    n_switch = args.switches if args.switches is not None else (2 if args.quick else 5)
    threads = args.threads if args.threads == "auto" else int(args.threads)
    result: dict = {"sizes": list(sizes), "steps": steps, "spp": spp, "threads": threads, "switches": n_switch}
    result["load_avg_start"] = round(os.getloadavg()[0], 2)
    args.tensors.mkdir(parents=True, exist_ok=True)
    for size in sizes:
        result.update(measure(size, steps, spp, args.tensors.resolve(), threads, n_switch))
        if args.baseline:  # the earlier transport, same tensors, same load
            result.update(measure(size, steps, spp, args.tensors.resolve(), threads, 0, "state"))
            new, old = result[f"latency_ms_{size}"], result[f"latency_ms_state_{size}"]
            result[f"speedup_vs_state_{size}"] = round(old / new, 2)
    result["load_avg_end"] = round(os.getloadavg()[0], 2)
    worst = [result.get(f"switch_worst_ms_{s}") for s in sizes]
    result["switch_worst_ms"] = max(w for w in worst if w is not None) if any(w is not None for w in worst) else None
    print(json.dumps(result))


if __name__ == "__main__":
    main()
