// Canvas 2D drawings: an image with its detections, and the distance-to-estimate plot (Fig. 8).

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

/** Fit a canvas's backing store to its CSS size (device pixels); its 2D context, scaled. */
function fitted(canvas, aspect) {
  const width = canvas.clientWidth || 320;
  const height = aspect ? Math.round(width / aspect) : canvas.clientHeight || 200;
  const ratio = window.devicePixelRatio || 1;
  if (canvas.width !== Math.round(width * ratio) || canvas.height !== Math.round(height * ratio)) {
    canvas.width = Math.round(width * ratio);
    canvas.height = Math.round(height * ratio);
  }
  const ctx = canvas.getContext("2d", { willReadFrequently: true });
  ctx.setTransform(ratio, 0, 0, ratio, 0, 0);
  return { ctx, width, height };
}

/**
 * `image` (an ImageBitmap, or null for none yet) with each detection's box, label and confidence.
 * Boxes are in the pixels of the image the detector saw (`size`: [width, height]).
 */
export function drawDetections(canvas, image, detections, size, note = "") {
  const aspect = image ? image.width / image.height : size ? size[0] / size[1] : 4 / 3;
  const { ctx, width, height } = fitted(canvas, aspect);
  ctx.clearRect(0, 0, width, height);
  ctx.fillStyle = "#1c2128";
  ctx.fillRect(0, 0, width, height);
  if (image) ctx.drawImage(image, 0, 0, width, height);
  const [w, h] = size || (image ? [image.width, image.height] : [width, height]);
  const sx = width / w;
  const sy = height / h;
  ctx.font = "12px system-ui, sans-serif";
  ctx.lineWidth = 2;
  for (const d of detections || []) {
    const [x1, y1, x2, y2] = d.box;
    const colour = colourOf(d);
    ctx.strokeStyle = colour;
    ctx.strokeRect(x1 * sx, y1 * sy, (x2 - x1) * sx, (y2 - y1) * sy);
    const text = `${d.label} ${d.confidence.toFixed(2)}`;
    const tw = ctx.measureText(text).width + 6;
    const ty = y1 * sy > 16 ? y1 * sy - 16 : y2 * sy;
    ctx.fillStyle = colour;
    ctx.fillRect(x1 * sx - 1, ty, tw, 16);
    ctx.fillStyle = "#fff";
    ctx.fillText(text, x1 * sx + 2, ty + 12);
  }
  if (note) {
    ctx.fillStyle = "#c9d1d9";
    ctx.fillText(note, 10, height / 2);
  }
}

/**
 * The angle (degrees) from each visited pose to the estimate, per iteration; `current` (an
 * index or -1) is ringed.
 */
export function drawDistances(canvas, distances, current) {
  const { ctx, width, height } = fitted(canvas);
  const left = 44;
  const right = 12;
  const top = 14;
  const bottom = 30;
  ctx.clearRect(0, 0, width, height);
  ctx.font = "11px system-ui, sans-serif";
  ctx.strokeStyle = "#8b949e";
  ctx.fillStyle = "#8b949e";
  ctx.lineWidth = 1;
  ctx.beginPath();
  ctx.moveTo(left, top);
  ctx.lineTo(left, height - bottom);
  ctx.lineTo(width - right, height - bottom);
  ctx.stroke();
  const n = distances.length;
  const ymax = Math.max(10, ...distances.map((d) => Math.ceil(d / 10) * 10));
  const x = (i) => left + ((width - left - right) * i) / Math.max(1, n - 1);
  const y = (d) => height - bottom - ((height - top - bottom) * d) / ymax;
  for (const tick of [0, ymax / 2, ymax]) {
    ctx.fillText(`${tick.toFixed(0)}°`, 6, y(tick) + 4);
    ctx.strokeStyle = "#30363d";
    ctx.beginPath();
    ctx.moveTo(left + 1, y(tick));
    ctx.lineTo(width - right, y(tick));
    ctx.stroke();
  }
  ctx.fillStyle = "#8b949e";
  ctx.fillText("iteration (rendered view)", left + 4, height - 8);
  if (n) ctx.fillText(String(n - 1), x(n - 1) - 8, height - bottom + 14);
  ctx.fillText("0", left - 3, height - bottom + 14);
  if (!n) return;
  ctx.strokeStyle = "#58a6ff";
  ctx.lineWidth = 2;
  ctx.beginPath();
  distances.forEach((d, i) => (i ? ctx.lineTo(x(i), y(d)) : ctx.moveTo(x(i), y(d))));
  ctx.stroke();
  ctx.fillStyle = "#58a6ff";
  distances.forEach((d, i) => {
    ctx.beginPath();
    ctx.arc(x(i), y(d), 3, 0, 2 * Math.PI);
    ctx.fill();
  });
  if (current >= 0 && current < n) {
    ctx.strokeStyle = "#f0883e";
    ctx.lineWidth = 2;
    ctx.beginPath();
    ctx.arc(x(current), y(distances[current]), 7, 0, 2 * Math.PI);
    ctx.stroke();
  }
}
