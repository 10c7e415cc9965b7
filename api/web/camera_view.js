// One camera's live preview: polled JPEGs with their source and level, a clear state when there
// is no frame, and the suggested screen placement drawn over it. The page keeps one per camera.

import { el } from "/ui/dom.js";
import { explain, request } from "/ui/service.js";

const POLL_IDLE_MS = 1000;     // live preview refresh between captures
const POLL_CAPTURE_MS = 300;   // and while a capture stores frames
const DARK_LEVEL = 0.03;       // a preview below this fraction of full scale shows nothing lit

export function rigCameras(rig) {
  const cfg = rig.config || {};
  const list = Array.isArray(cfg.cameras) ? cfg.cameras : [{ name: "default", ...(cfg.camera || {}) }];
  return list.map((c, i) => ({ name: c.name || `cam${i}`, width: c.width || null, height: c.height || null }));
}

export class CameraView {
  // `isCapturing()`: whether a capture on this rig is being followed (faster refresh, and an
  // idle frame then means the capture has not stored its first frame yet).
  constructor(rig, camera, several, isCapturing) {
    this.isCapturing = isCapturing;
    this.rig = rig;
    this.camera = camera;
    this.several = several;
    this.outline = null;
    this.url = null;
    this.timer = null;
    this.img = el("img", { alt: `live image of camera ${camera.name}` });
    this.canvas = el("canvas", { class: "overlay", "aria-hidden": "true" });
    this.idle = el("div", { class: "no-frame" }, "no frame yet");
    this.caption = el("div", { class: "caption", "aria-live": "polite" }, "connecting to the camera...");
    this.node = el("figure", { class: "camera", "data-camera": camera.name },
                   el("div", { class: "preview" }, this.idle, this.img, this.canvas),
                   el("figcaption", {}, several ? el("b", {}, camera.name + ": ") : null, this.caption));
    this.img.hidden = true;
    this.img.onload = () => this.draw();
  }

  previewPath() {
    const cam = this.several ? `?camera=${encodeURIComponent(this.camera.name)}` : "";
    return `/rigs/${this.rig.id}/camera/preview.jpg${cam}`;
  }

  start() { this.stop(); this.tick(); }

  stop() { if (this.timer) clearTimeout(this.timer); this.timer = null; }

  async tick() {
    this.timer = null;
    if (!this.node.isConnected) return;
    if (!document.hidden) await this.refresh();
    this.timer = setTimeout(() => this.tick(), this.isCapturing() ? POLL_CAPTURE_MS : POLL_IDLE_MS);
  }

  async refresh() {
    let r;
    try {
      r = await request("GET", this.previewPath());
    } catch (e) {
      this.show(null, "no frame yet", explain(e));
      return;
    }
    const source = r.headers.get("Phasecal-Preview-Source") || "idle";
    const level = Number(r.headers.get("Phasecal-Preview-Level") || "1");
    const blob = await r.blob();
    if (source === "idle" && this.isCapturing()) {
      this.show(null, "capture starting", "The capture is starting: its first frame appears here.");
    } else if (source === "capture") {
      this.show(blob, null, "capturing: the newest stored frame of the pattern sequence");
    } else if (level < DARK_LEVEL) {
      this.show(null, "camera idle: dark image",
                "The camera sees nothing lit (the screen shows no pattern between captures). " +
                "Frames appear here during a capture.");
    } else {
      this.show(blob, null, "live: the camera between captures");
    }
  }

  show(blob, idleText, caption) {
    if (this.caption.textContent !== caption) this.caption.textContent = caption;  // announced once
    if (blob) {
      if (this.url) URL.revokeObjectURL(this.url);
      this.url = URL.createObjectURL(blob);
      this.img.src = this.url;
      this.img.hidden = false;
      this.idle.hidden = true;
    } else {
      this.img.hidden = true;
      this.idle.hidden = false;
      this.idle.textContent = idleText;
    }
    this.draw();
  }

  // The camera's image size when the rig config does not state it (the planner's camera).
  assumeSize(width, height) {
    if (!this.camera.width) { this.camera.width = width; this.camera.height = height; this.draw(); }
  }

  // The suggested placement: the screen's four corners in camera pixels.
  setOutline(points, label) { this.outline = points ? { points, label } : null; this.draw(); }

  draw() {
    const box = this.canvas.parentElement.getBoundingClientRect();
    this.canvas.width = Math.max(1, Math.round(box.width));
    this.canvas.height = Math.max(1, Math.round(box.height));
    const ctx = this.canvas.getContext("2d");
    ctx.clearRect(0, 0, this.canvas.width, this.canvas.height);
    if (!this.outline) return;
    const w = this.camera.width || this.img.naturalWidth || this.canvas.width;
    const h = this.camera.height || this.img.naturalHeight || this.canvas.height;
    const scale = Math.min(this.canvas.width / w, this.canvas.height / h);
    const x0 = (this.canvas.width - w * scale) / 2, y0 = (this.canvas.height - h * scale) / 2;
    ctx.strokeStyle = "#ffcc00";
    ctx.lineWidth = 2;
    ctx.setLineDash([6, 4]);
    ctx.beginPath();
    this.outline.points.forEach(([u, v], i) => {
      const x = x0 + u * scale, y = y0 + v * scale;
      if (i === 0) ctx.moveTo(x, y); else ctx.lineTo(x, y);
    });
    ctx.closePath();
    ctx.stroke();
    ctx.setLineDash([]);
    ctx.fillStyle = "#ffcc00";
    ctx.font = "12px system-ui, sans-serif";
    ctx.fillText(this.outline.label, x0 + 4, y0 + 14);
  }
}
