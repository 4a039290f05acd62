// The 3D view of the hemisphere, on the page's side: a canvas whose drawing is handed to a worker
// (hemisphere-worker.js, with three.js, fetched on first use and not needed for the first paint).
// Without a GPU every WebGL frame is rasterised in software, and a canvas drawn on the main
// thread is read back there at each commit: 20-45 ms per frame while a search streamed
// (benchmarks/page.py). Drawn by a worker, the frames reach the compositor without the main thread.
// The page forwards drags (turn), the wheel (zoom) and clicks (pick a grid pose) to it.

/* global __HEMISPHERE_WORKER__ */
const WORKER = __HEMISPHERE_WORKER__; // the worker's bundle, named by build.mjs

export class Hemisphere {
  /** A view in `container`; `onPick(gridPose)` is told of a click on a grid pose. */
  constructor(container, { onPick } = {}) {
    this.container = container;
    this.onPick = onPick;
    const canvas = document.createElement("canvas");
    if (!canvas.transferControlToOffscreen) {
      container.textContent = "The 3D view needs OffscreenCanvas, which this browser does not offer.";
      return;
    }
    container.append(canvas);
    this.canvas = canvas;
    this.worker = new Worker(WORKER, { type: "module", name: "hemisphere" });
    this.worker.onmessage = ({ data }) => this.heard(data);
    this.worker.onerror = (event) => this.fail(event.message || "its script did not load");
    const offscreen = canvas.transferControlToOffscreen();
    this.worker.postMessage({ type: "init", canvas: offscreen }, [offscreen]);
    this.listen(canvas);
  }

  heard(data) {
    if (data.type === "picked" && data.pose && this.onPick) this.onPick(data.pose);
    else if (data.type === "error") this.fail(data.message);
  }

  fail(message) {
    this.worker?.terminate();
    this.worker = null;
    this.container.textContent = `The 3D view could not be drawn (${message}).`;
  }

  /** Drags turn the view, the wheel zooms, a click (a press and release in place) picks. */
  listen(canvas) {
    let down = null;
    let last = null;
    canvas.addEventListener("pointerdown", (e) => {
      down = last = [e.clientX, e.clientY];
      canvas.setPointerCapture(e.pointerId);
    });
    canvas.addEventListener("pointermove", (e) => {
      if (!last) return;
      const rect = canvas.getBoundingClientRect();
      this.post({ type: "orbit", dx: (e.clientX - last[0]) / rect.width, dy: (e.clientY - last[1]) / rect.height });
      last = [e.clientX, e.clientY];
    });
    canvas.addEventListener("pointerup", (e) => {
      const start = down;
      down = last = null;
      if (!start || !this.onPick || Math.hypot(e.clientX - start[0], e.clientY - start[1]) > 4) return;
      const rect = canvas.getBoundingClientRect();
      this.post({ type: "pick", x: ((e.clientX - rect.left) / rect.width) * 2 - 1, y: 1 - ((e.clientY - rect.top) / rect.height) * 2 });
    });
    canvas.addEventListener("pointercancel", () => (down = last = null));
    canvas.addEventListener(
      "wheel",
      (e) => {
        e.preventDefault();
        this.post({ type: "zoom", factor: Math.exp(Math.max(-1, Math.min(1, e.deltaY * 0.001))) });
      },
      { passive: false },
    );
  }

  /** Send `message` to the worker in a task of its own, after the page's current one: a worker
   * woken up by postMessage takes the core from the main thread at once where they share one,
   * and the page's frame (its layout, paint and commit) would wait for the 3D view's. */
  post(message) {
    if (!this.worker) return;
    if (!this.outbox) {
      this.outbox = [];
      setTimeout(() => {
        for (const queued of this.outbox) this.worker?.postMessage(queued);
        this.outbox = null;
      }, 0);
    }
    this.outbox.push(message);
  }

  /** The scene (`GET /scenes/{id}`): its ground, objects, camera radius and grid. */
  setScene(detail) {
    this.post({ type: "scene", detail });
  }

  /** What to show of a search (see HemisphereScene.setTrack). */
  setTrack(track) {
    this.post({ type: "track", track });
  }

  /** Stop the worker, with its WebGL context: it closes itself (Worker.terminate would wait on
   * the main thread for the worker's thread to stop: 28 ms, in the switch to a search's view). */
  dispose() {
    const worker = this.worker;
    this.worker = null;
    setTimeout(() => worker?.postMessage({ type: "close" }), 0);
  }
}
