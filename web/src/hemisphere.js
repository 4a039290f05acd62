// The 3D view of the hemisphere, on the page's side: a canvas whose drawing is handed to a worker
// (hemisphere-worker.js, with three.js, fetched on first use and not needed for the first paint).
// Without a GPU every WebGL frame is rasterised in software, and a canvas drawn on the main
// thread is read back there at each commit: 20-45 ms per frame while a search streamed
// (benchmarks/page.py). Drawn by a worker, the frames reach the compositor without the main thread.
// The page forwards drags (turn), the wheel (zoom) and clicks (pick a grid pose) to it.
// One canvas and one worker serve every view of the page, one view at a time: a view takes the
// canvas. A worker per view would load three.js and compile its shaders again at each switch of
// view, on the cores the page needs right then to lay the new view out.

/* global __HEMISPHERE_WORKER__ */
const WORKER = __HEMISPHERE_WORKER__; // the worker's bundle, named by build.mjs

let shared = null;

/** The page's one 3D canvas and its worker (made on first use); `owner` is the view showing it. */
function sharedCanvas() {
  if (shared) return shared;
  const canvas = document.createElement("canvas");
  shared = { canvas, worker: null, owner: null, failure: null, outbox: null };
  if (!canvas.transferControlToOffscreen) {
    shared.failure = "it needs OffscreenCanvas, which this browser does not offer";
    return shared;
  }
  const worker = new Worker(WORKER, { type: "module", name: "hemisphere" });
  worker.onmessage = ({ data }) => {
    if (data.type === "picked" && data.pose) shared.owner?.onPick?.(data.pose);
    else if (data.type === "error") fail(data.message);
  };
  worker.onerror = (event) => fail(event.message || "its script did not load");
  const offscreen = canvas.transferControlToOffscreen();
  worker.postMessage({ type: "init", canvas: offscreen }, [offscreen]);
  shared.worker = worker;
  listen(canvas);
  return shared;
}

function fail(message) {
  shared.worker?.terminate();
  shared.worker = null;
  shared.failure = message;
  shared.owner?.showFailure();
}

/** Send `message` to the worker in a task of its own, after the page's current one: a worker
 * woken up by postMessage takes the core from the main thread at once where they share one,
 * and the page's frame (its layout, paint and commit) would wait for the 3D view's. */
function post(message) {
  if (!shared?.worker) return;
  if (!shared.outbox) {
    shared.outbox = [];
    setTimeout(() => {
      for (const queued of shared.outbox) shared.worker?.postMessage(queued);
      shared.outbox = null;
    }, 0);
  }
  shared.outbox.push(message);
}

/** Drags turn the view, the wheel zooms, a click (a press and release in place) picks. */
function listen(canvas) {
  let down = null;
  let last = null;
  canvas.addEventListener("pointerdown", (e) => {
    down = last = [e.clientX, e.clientY];
    canvas.setPointerCapture(e.pointerId);
  });
  canvas.addEventListener("pointermove", (e) => {
    if (!last) return;
    const rect = canvas.getBoundingClientRect();
    post({ type: "orbit", dx: (e.clientX - last[0]) / rect.width, dy: (e.clientY - last[1]) / rect.height });
    last = [e.clientX, e.clientY];
  });
  canvas.addEventListener("pointerup", (e) => {
    const start = down;
    down = last = null;
    if (!start || !shared.owner?.onPick || Math.hypot(e.clientX - start[0], e.clientY - start[1]) > 4) return;
    const rect = canvas.getBoundingClientRect();
    post({ type: "pick", x: ((e.clientX - rect.left) / rect.width) * 2 - 1, y: 1 - ((e.clientY - rect.top) / rect.height) * 2 });
  });
  canvas.addEventListener("pointercancel", () => (down = last = null));
  canvas.addEventListener(
    "wheel",
    (e) => {
      e.preventDefault();
      post({ type: "zoom", factor: Math.exp(Math.max(-1, Math.min(1, e.deltaY * 0.001))) });
    },
    { passive: false },
  );
}

export class Hemisphere {
  /** A view in `container` (it takes the page's 3D canvas, cleared); `onPick(gridPose)` is told
   * of a click on a grid pose. */
  constructor(container, { onPick } = {}) {
    this.container = container;
    this.onPick = onPick;
    const view = sharedCanvas();
    view.owner = this;
    if (view.failure) {
      this.showFailure();
      return;
    }
    container.append(view.canvas); // taken from the previous view, if any
    post({ type: "clear" });
  }

  showFailure() {
    this.container.textContent = `The 3D view could not be drawn (${shared.failure}).`;
  }

  /** The scene (`GET /scenes/{id}`): its ground, objects, camera radius and grid. */
  setScene(detail) {
    if (shared.owner === this) post({ type: "scene", detail });
  }

  /** What to show of a search (see HemisphereScene.setTrack). */
  setTrack(track) {
    if (shared.owner === this) post({ type: "track", track });
  }

  /** Give the canvas up (the next view takes it); the worker stays for it. */
  dispose() {
    if (shared.owner === this) shared.owner = null;
  }
}
