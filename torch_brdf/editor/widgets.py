"""The frame widget: raw 8-bit RGB pixels drawn on a canvas, clicks sent back as pixels.

ipywidgets' ``Image`` reports no clicks, so the frame is a small anywidget (its JavaScript is
below, no build step): the kernel sends the (H, W, 3) bytes as a binary buffer (no PNG
encode/decode on the way), the browser draws them 1:1 on a canvas scaled by CSS, and a
click is sent as ``{"event": "click", "x": column, "y": row}`` in image pixels.

The widget also measures the end-to-end latency in the browser: the first user input
(pointer down, drag move, key, input/change event) not yet answered by a frame starts the
clock; the paint after the next frame arrives stops it. The value is shown under the frame,
synced to ``latency_ms`` and appended to ``window.__torch_brdf.latencies`` (what
``benchmarks/editor.py`` reads), the time to unpack and draw the bytes to
``window.__torch_brdf.draws``.

Slider drags need no coalescing of our own: ipywidgets' front end keeps at most one state
message per widget in flight and merges the changes made meanwhile into one buffered
message (latest value wins) sent when the kernel reports idle, so a drag never queues stale
values and its final value always arrives.
"""

from __future__ import annotations

import anywidget
import numpy as np
import torch
import traitlets

_ESM = r"""
function render({ model, el }) {
  const g = (window.__torch_brdf = window.__torch_brdf || { latencies: [], frames: 0 });
  const wrap = document.createElement("div");
  wrap.className = "tb-frame-wrap";
  wrap.style.marginRight = "12px";
  const canvas = document.createElement("canvas");
  canvas.className = "tb-frame " + (model.get("role") || "");
  canvas.style.imageRendering = "pixelated";
  canvas.style.cursor = "crosshair";
  canvas.style.display = "block";
  const caption = document.createElement("div");
  caption.className = "tb-caption";
  caption.style.font = "12px monospace";
  wrap.append(canvas, caption);
  el.append(wrap);
  let pending = null;
  const measure = model.get("measure");
  const mark = (e) => {
    if (e.type === "pointermove" && !e.buttons) return;
    if (pending === null) pending = performance.now();
  };
  const kinds = ["pointerdown", "pointermove", "keydown", "input", "change"];
  if (measure) for (const t of kinds) document.addEventListener(t, mark, true);
  let latency = null;
  const show = () => {
    const info = model.get("info") || "";
    caption.textContent = info + (measure && latency !== null ? ` · latency ${latency.toFixed(1)} ms` : "");
  };
  const draw = () => {
    const w = model.get("width"), h = model.get("height");
    const buf = model.get("pixels");
    if (!w || !h || !buf || buf.byteLength !== w * h * 3) { show(); return; }
    const t0 = performance.now();
    const src = new Uint8Array(buf.buffer, buf.byteOffset, buf.byteLength);
    if (canvas.width !== w || canvas.height !== h) { canvas.width = w; canvas.height = h; }
    const dw = model.get("display_width") || w;
    canvas.style.width = dw + "px";
    canvas.style.height = Math.round((dw * h) / w) + "px";
    const img = new ImageData(w, h);
    const d = img.data;
    for (let i = 0, j = 0, k = 0; i < w * h; i++, j += 3, k += 4) {
      d[k] = src[j]; d[k + 1] = src[j + 1]; d[k + 2] = src[j + 2]; d[k + 3] = 255;
    }
    canvas.getContext("2d").putImageData(img, 0, 0);
    if (measure) (g.draws = g.draws || []).push(performance.now() - t0);
    requestAnimationFrame(() => {
      const now = performance.now();
      if (measure) {
        g.frames += 1;
        if (pending !== null) {
          latency = now - pending;
          pending = null;
          g.latencies.push(latency);
          model.set("latency_ms", latency);
          model.save_changes();
        }
      }
      wrap.dataset.frames = String((Number(wrap.dataset.frames) || 0) + 1);
      show();
    });
  };
  canvas.addEventListener("click", (e) => {
    const r = canvas.getBoundingClientRect();
    const x = Math.floor(((e.clientX - r.left) / r.width) * canvas.width);
    const y = Math.floor(((e.clientY - r.top) / r.height) * canvas.height);
    model.send({ event: "click", x: x, y: y });
  });
  model.on("change:pixels", draw);
  model.on("change:info", show);
  draw();
  return () => { if (measure) for (const t of kinds) document.removeEventListener(t, mark, true); };
}
export default { render };
"""


class FrameView(anywidget.AnyWidget):
    """An RGB frame on a canvas. ``role`` becomes a CSS class (tests find frames by it)."""

    _esm = _ESM
    pixels = traitlets.Bytes(b"").tag(sync=True)
    width = traitlets.Int(0).tag(sync=True)
    height = traitlets.Int(0).tag(sync=True)
    display_width = traitlets.Int(0).tag(sync=True)
    info = traitlets.Unicode("").tag(sync=True)
    role = traitlets.Unicode("").tag(sync=True)
    measure = traitlets.Bool(False).tag(sync=True)
    latency_ms = traitlets.Float(-1.0).tag(sync=True)

    def show(self, rgb8, info: str | None = None) -> None:
        """Display (H, W, 3) uint8 pixels (numpy or torch); ``info`` replaces the caption."""
        a = rgb8.numpy() if isinstance(rgb8, torch.Tensor) else np.asarray(rgb8)
        if a.ndim != 3 or a.shape[2] != 3 or a.dtype != np.uint8:
            raise ValueError(f"expected (H, W, 3) uint8 pixels; got {a.shape} {a.dtype}")
        with self.hold_sync():
            self.width, self.height = int(a.shape[1]), int(a.shape[0])
            if info is not None:
                self.info = info
            self.pixels = np.ascontiguousarray(a).tobytes()
