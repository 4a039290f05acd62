// The 3D view, loaded after the page's first paint: three.js is a chunk of its own, fetched on
// first use. Calls made before it arrives are replayed on it (the latest track only).

let loading = null;

export function lazyHemisphere(container, options) {
  let real = null;
  let scene = null;
  let track = null;
  let disposed = false;
  loading ??= import("./hemisphere.js");
  loading
    .then(({ Hemisphere }) => {
      if (disposed) return;
      real = new Hemisphere(container, options);
      if (scene) real.setScene(scene);
      if (track) real.setTrack(track);
    })
    .catch((error) => {
      container.textContent = `The 3D view could not be loaded: ${error.message}`;
    });
  return {
    setScene(detail) {
      if (real) real.setScene(detail);
      else scene = detail;
    },
    setTrack(what) {
      if (real) real.setTrack(what);
      else track = what;
    },
    dispose() {
      disposed = true;
      real?.dispose();
    },
  };
}
