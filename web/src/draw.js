// The page's pictures, drawn by the browser rather than on 2D canvases: an image with its
// detections as boxes over it, and the distance-to-estimate plot (paper Fig. 8) in SVG. A 2D
// canvas is rasterised by the page's script on the main thread and copied again at each commit
// (6-12 ms a frame while a search streamed, benchmarks/page.py); an <img> is decoded, and boxes
// and SVG are rasterised, by the browser's worker threads.

import { h } from "./dom.js";

const PALETTE = ["#e6194b", "#3cb44b", "#4363d8", "#f58231", "#911eb4", "#42d4f4", "#f032e6", "#bfef45", "#469990", "#9a6324"];

function colourOf(detection) {
  if (detection.color) {
    const [r, g, b] = detection.color;
    if (r + g + b > 120) return `rgb(${r | 0}, ${g | 0}, ${b | 0})`;
  }
  let hash = 0;
  for (const ch of detection.label) hash = (hash * 31 + ch.charCodeAt(0)) >>> 0;
  return PALETTE[hash % PALETTE.length];
}

const percent = (value) => `${(100 * value).toFixed(3)}%`;

/** A detection's box, placed in percent of an image of `width` × `height` pixels; a predicted
 * box (`detection.predicted`: where the answer's pose projects an object) is dashed, its label
 * the object's. */
function boxOf(detection, width, height) {
  const [x1, y1, x2, y2] = detection.box;
  const predicted = Boolean(detection.predicted);
  const text = predicted ? `${detection.predicted} (predicted)` : `${detection.label} ${detection.confidence.toFixed(2)}`;
  const box = h("div", { class: `box${predicted ? " predicted" : ""}${y1 / height < 0.06 ? " below" : ""}` }, h("span", {}, text));
  box.style.setProperty("--colour", colourOf(detection));
  box.style.left = percent(x1 / width);
  box.style.top = percent(y1 / height);
  box.style.width = percent((x2 - x1) / width);
  box.style.height = percent((y2 - y1) / height);
  return box;
}

/** An image (a URL, or none yet) with each detection's box, label and confidence over it. */
export class Picture {
  /** `attrs`: the picture's id and aria-label. */
  constructor(attrs) {
    this.img = h("img", { alt: "", hidden: true });
    this.boxes = h("div", { class: "boxes" });
    this.note = h("p", { class: "picture-note", hidden: true });
    this.element = h("div", { class: "picture", role: "img", ...attrs }, this.img, this.boxes, this.note);
    this.src = null;
  }

  /**
   * Show `src` (an image URL, or null) with `detections`, whose boxes are in the pixels of the
   * image the detector saw (`size`: [width, height], else the image's own), and a `note` over it;
   * `predicted`: boxes drawn dashed beside them (see predictedBoxes).
   * A new image replaces the old once it is decoded: the picture never shows blank between two.
   * Resolves to the image's [width, height] once it is shown; null if it is not (no image, an
   * image that cannot be shown, or another asked for meanwhile).
   */
  show(src, detections = [], size = null, note = "", predicted = []) {
    this.note.textContent = note;
    this.note.hidden = !note;
    if (size) this.element.style.aspectRatio = `${size[0]} / ${size[1]}`;
    this.element.dataset.predicted = String(predicted.length);
    const place = (width, height) => this.boxes.replaceChildren(...[...(detections || []), ...predicted].map((d) => boxOf(d, width, height)));
    if (size) place(...size);
    if (src === this.src) {
      if (!size && src) place(this.img.naturalWidth, this.img.naturalHeight);
      return Promise.resolve(src ? [this.img.naturalWidth, this.img.naturalHeight] : null);
    }
    this.src = src;
    if (!src) {
      this.img.hidden = true;
      return Promise.resolve(null);
    }
    const next = h("img", { alt: "" });
    next.src = src;
    return next
      .decode()
      .then(() => {
        if (this.src !== src) return null; // a newer image was asked for meanwhile
        if (!size) {
          this.element.style.aspectRatio = `${next.naturalWidth} / ${next.naturalHeight}`;
          place(next.naturalWidth, next.naturalHeight);
        }
        this.img.replaceWith(next);
        this.img = next;
        return [next.naturalWidth, next.naturalHeight];
      })
      .catch(() => {
        if (this.src !== src) return null;
        this.img.hidden = true;
        if (!note) {
          this.note.textContent = "This browser cannot show this image.";
          this.note.hidden = false;
        }
        return null;
      });
  }
}

/** The boxes a free answer's pose predicts for its paired objects (`correspondences`), in the
 * target's pixels, coloured as the target's detection each is paired with. */
export function predictedBoxes(correspondences, detections = []) {
  return correspondences
    .filter((c) => c.predicted_box)
    .map((c) => ({ ...(detections[c.detection] || { label: c.label }), box: c.predicted_box, predicted: c.object }));
}

const SVG = "http://www.w3.org/2000/svg";
function svg(tag, attrs = {}, text = null) {
  const node = document.createElementNS(SVG, tag);
  for (const [name, value] of Object.entries(attrs)) node.setAttribute(name, value);
  if (text !== null) node.textContent = text;
  return node;
}

const [W, H] = [600, 300]; // the plot's units (it scales to its box, keeping this aspect)
const [LEFT, RIGHT, TOP, BOTTOM] = [44, 12, 14, 30];

/** The angle (degrees) from each visited pose to the estimate, per iteration (paper Fig. 8). */
export class DistancePlot {
  /** `attrs`: the plot's id and aria-label. */
  constructor(attrs) {
    this.element = svg("svg", { viewBox: `0 0 ${W} ${H}`, class: "plot", role: "img", ...attrs });
  }

  /** Plot `distances` (degrees, one per iteration) with iteration `current` (or -1) ringed. */
  show(distances, current) {
    const n = distances.length;
    const ymax = Math.max(10, ...distances.map((d) => Math.ceil(d / 10) * 10));
    const x = (i) => LEFT + ((W - LEFT - RIGHT) * i) / Math.max(1, n - 1);
    const y = (d) => H - BOTTOM - ((H - TOP - BOTTOM) * d) / ymax;
    const parts = [svg("path", { class: "axis", d: `M${LEFT},${TOP}V${H - BOTTOM}H${W - RIGHT}` })];
    for (const tick of [0, ymax / 2, ymax]) {
      parts.push(svg("path", { class: "grid", d: `M${LEFT + 1},${y(tick)}H${W - RIGHT}` }));
      parts.push(svg("text", { x: 6, y: y(tick) + 4 }, `${tick.toFixed(0)}°`));
    }
    parts.push(svg("text", { x: LEFT + 4, y: H - 8 }, "iteration (rendered view)"));
    parts.push(svg("text", { x: LEFT - 3, y: H - BOTTOM + 14 }, "0"));
    if (n) {
      parts.push(svg("text", { x: x(n - 1) - 8, y: H - BOTTOM + 14 }, String(n - 1)));
      parts.push(svg("polyline", { class: "line", points: distances.map((d, i) => `${x(i)},${y(d)}`).join(" ") }));
      for (const [i, d] of distances.entries()) parts.push(svg("circle", { class: "point", cx: x(i), cy: y(d), r: 3 }));
      if (current >= 0 && current < n) parts.push(svg("circle", { class: "current", cx: x(current), cy: y(distances[current]), r: 7 }));
    }
    this.element.replaceChildren(...parts);
  }
}
