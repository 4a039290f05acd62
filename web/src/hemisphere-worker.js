// The 3D view's worker: it owns the view's OffscreenCanvas and three.js, so that drawing (in
// software without a GPU) never holds up the page's main thread. Messages in: init (the canvas),
// clear, scene, track, orbit, zoom, pick; out: ready, picked (a grid pose or null), error.

import { HemisphereScene } from "./hemisphere-scene.js";

let view = null;

self.onmessage = ({ data }) => {
  try {
    if (data.type === "init") {
      view = new HemisphereScene(data.canvas);
      self.postMessage({ type: "ready" });
      return;
    }
    if (!view) return;
    if (data.type === "scene") view.setScene(data.detail);
    else if (data.type === "track") view.setTrack(data.track);
    else if (data.type === "orbit") view.orbit(data.dx, data.dy);
    else if (data.type === "zoom") view.zoom(data.factor);
    else if (data.type === "clear") view.clear();
    else if (data.type === "pick") self.postMessage({ type: "picked", pose: view.pick(data.x, data.y) });
  } catch (error) {
    self.postMessage({ type: "error", message: error.message });
  }
};
