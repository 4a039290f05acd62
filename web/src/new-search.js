// A new search: a scene (with a preview and its grid size), a target (a dropped or chosen file,
// or a pose picked on the hemisphere, rendered), a strategy and an optional start, or a free
// search (any camera: its pose and lens from the target, optionally with the photo's fov and its
// gimbal's pitch and roll); then go.

import { Problem, imageURL } from "./api.js";
import { Picture } from "./draw.js";
import { h, notice } from "./dom.js";
import { Hemisphere } from "./hemisphere.js";
import { storedJpegSize } from "./stored-size.js";

const STRATEGIES = [
  ["reprojection", "reprojection (ours, default)"],
  ["paper", "paper (optimized search)"],
  ["simple", "simple (step by step)"],
];

export function showNewSearch({ view, api }, params) {
  const controller = new AbortController();
  const wanted = params.get("scene");
  let target = null; // { blob, name }
  let picked = null;
  let wantedTarget = null; // the target image URL last asked for (showTarget)
  let sceneDetail = null;

  const sceneSelect = h("select", { name: "scene", id: "scene", required: true });
  const sceneInfo = h("p", { class: "muted", id: "scene-info" }, "…");
  const sceneMessage = h("div", { id: "scene-message" });
  const preview = new Picture({ id: "preview", "aria-label": "The scene's preview" });
  const urls = new Set(); // object URLs made here, revoked once no picture shows them
  function release() {
    for (const url of urls) {
      // the target asked for is not shown yet while its size is read (showTarget): keep it too
      if (url === preview.src || url === targetPicture.src || url === wantedTarget) continue;
      URL.revokeObjectURL(url);
      urls.delete(url);
    }
  }
  const fileInput = h("input", { type: "file", id: "target-file", accept: "image/png,image/jpeg,image/x-portable-pixmap,.ppm" });
  const targetPicture = new Picture({ id: "target-preview", "aria-label": "The target image" });
  const targetInfo = h("p", { class: "muted", id: "target-info" }, "No target yet: drop an image here, choose a file, or click a pose on the hemisphere.");
  const drop = h("div", { class: "drop", id: "drop" }, targetPicture.element, targetInfo, h("label", { class: "button" }, "Choose an image…", fileInput));
  const hemiBox = h("div", { class: "hemisphere small", id: "pick-hemisphere" });
  const mode = h(
    "select",
    { name: "mode", id: "mode" },
    h("option", { value: "hemisphere" }, "hemisphere (the paper's grid)"),
    h("option", { value: "free" }, "free (any camera)"),
  );
  const fov = h("input", { name: "fov_deg", id: "fov_deg", type: "number", min: 0, max: 180, step: "any", placeholder: "EXIF, else estimated", disabled: true });
  const distortion = h("input", { name: "distortion", id: "distortion", type: "text", inputmode: "decimal", placeholder: "XMP, else none", disabled: true });
  const attitude = h("input", { name: "attitude", id: "attitude", type: "text", inputmode: "decimal", placeholder: "XMP, else none", disabled: true });
  const exif = h("input", { name: "exif", id: "exif", type: "checkbox", checked: true, disabled: true });
  const strategy = h("select", { name: "strategy", id: "strategy" }, STRATEGIES.map(([v, t]) => h("option", { value: v }, t)));
  const theta = h("input", { name: "start_theta_deg", id: "start_theta_deg", type: "number", min: 0, max: 90, step: "any", placeholder: "random" });
  const phi = h("input", { name: "start_phi_deg", id: "start_phi_deg", type: "number", step: "any", placeholder: "random" });
  const maxIterations = h("input", { name: "max_iterations", id: "max_iterations", type: "number", min: 1, max: 500, placeholder: "default" });
  const go = h("button", { type: "submit", id: "go" }, "Search");
  const errors = h("div", { id: "form-errors", "aria-live": "polite" });
  const form = h(
    "form",
    { id: "new-search", class: "new-search" },
    h("section", { class: "panel" }, h("h2", {}, "Scene"), h("label", {}, "Scene ", sceneSelect), sceneInfo, sceneMessage, preview.element),
    h("section", { class: "panel" }, h("h2", {}, "Target"), drop, h("h3", {}, "…or pick a pose"), hemiBox),
    h(
      "section",
      { class: "panel" },
      h("h2", {}, "Search"),
      h("label", {}, "Mode ", mode),
      h("label", {}, "Photo's horizontal fov° (free mode, optional) ", fov),
      h("label", {}, "Lens distortion k1, k2, p1, p2[, k3] (free mode, optional: OpenCV's, with the fov) ", distortion),
      h("label", {}, "Camera's pitch, roll° (free mode, optional: a flight log's gimbal angles, 90 straight down) ", attitude),
      h("label", {}, exif, " read what the photo's EXIF and XMP say of its lens and gimbal, where not given here"),
      h("label", {}, "Strategy ", strategy),
      h("fieldset", {}, h("legend", {}, "Start (optional, snapped to the grid)"), h("label", {}, "θ° ", theta), h("label", {}, "φ° ", phi)),
      h("label", {}, "Max iterations ", maxIterations),
      go,
      errors,
    ),
  );
  view.replaceChildren(h("h2", { class: "title" }, "New search"), form);
  const hemisphere = new Hemisphere(hemiBox, { onPick: (pose) => pickPose(pose) });

  /**
   * Show the target image at `url` (or none) and `text`, with the image's size once shown: the
   * size its pixels are stored at when `blob` is a JPEG (see storedJpegSize), as searched.
   */
  async function showTarget(url, text, blob = null) {
    wantedTarget = url;
    targetInfo.textContent = text;
    if (url) urls.add(url);
    const stored = blob ? await storedJpegSize(blob) : null;
    if (wantedTarget !== url) return; // another target was asked for meanwhile
    const shown = targetPicture.show(url, [], stored);
    release();
    const size = (await shown) && (stored ?? [targetPicture.img.naturalWidth, targetPicture.img.naturalHeight]);
    if (size && targetPicture.src === url) targetInfo.textContent = `${text}, ${size[0]}×${size[1]}`;
  }

  async function useFile(file) {
    if (!file) return;
    target = { blob: file, name: file.name };
    picked = null;
    hemisphere.setTrack({});
    // a PPM (or not an image) is not shown here: the controller judges it
    showTarget(URL.createObjectURL(file), `${file.name} (${(file.size / 1024).toFixed(1)} KiB)`, file);
  }

  async function pickPose(pose) {
    picked = pose;
    hemisphere.setTrack({ picked: pose });
    targetInfo.textContent = `Rendering lat ${pose.lat}, lon ${pose.lon}…`;
    try {
      const scene = sceneSelect.value;
      const blob = await api(`/scenes/${encodeURIComponent(scene)}/view.png?lat=${pose.lat}&lon=${pose.lon}`, { as: "blob", signal: controller.signal });
      if (picked !== pose) return; // another pose was picked meanwhile
      target = { blob, name: `${scene}-lat${pose.lat}-lon${pose.lon}.png` };
      showTarget(URL.createObjectURL(blob), `Rendered at lat ${pose.lat}, lon ${pose.lon} (θ ${pose.theta_deg.toFixed(1)}°, φ ${pose.phi_deg.toFixed(1)}°)`);
    } catch (error) {
      if (error.name !== "AbortError") targetInfo.textContent = `Could not render it: ${error.message}`;
    }
  }

  async function loadScene(id) {
    sceneInfo.textContent = "…";
    try {
      sceneDetail = await api(`/scenes/${encodeURIComponent(id)}`, { signal: controller.signal });
      const ring = sceneDetail.grid.rings[Math.floor(sceneDetail.grid.rings.length / 2)];
      sceneInfo.textContent = `${sceneDetail.spec.objects.length} objects; grid of ${sceneDetail.grid.size} poses, ${sceneDetail.grid.rings.length} rings every ${sceneDetail.grid.angle_step_deg}° (θ ${sceneDetail.grid.min_theta_deg}°–${sceneDetail.grid.max_theta_deg}°)`;
      hemisphere.setScene(sceneDetail);
      hemisphere.setTrack({});
      const size = [sceneDetail.spec.camera.width, sceneDetail.spec.camera.height];
      preview.show(null, [], size, "rendering a preview…");
      const url = await imageURL(`/scenes/${encodeURIComponent(id)}/view.png?lat=${ring.lat}&lon=0`, controller.signal);
      urls.add(url);
      preview.show(url, [], size);
      release();
    } catch (error) {
      if (error.name !== "AbortError") sceneInfo.textContent = `Could not load scene ${id}: ${error.message}`;
    }
  }

  (async () => {
    try {
      const scenes = await api("/scenes", { signal: controller.signal });
      sceneSelect.replaceChildren(...scenes.map((s) => h("option", { value: s.id }, `${s.id} (${s.grid_size} poses)`)));
      if (wanted && !scenes.some((s) => s.id === wanted)) {
        sceneMessage.replaceChildren(
          notice(`Unknown scene “${wanted}”: the renderers know ${scenes.map((s) => s.id).join(", ") || "no scene"}. Pick one of them.`, "error"),
        );
      } else if (wanted) {
        sceneSelect.value = wanted;
      }
      if (scenes.length) loadScene(sceneSelect.value);
    } catch (error) {
      if (error.name !== "AbortError") sceneMessage.replaceChildren(notice(`Could not list the scenes: ${error.message}`, "error"));
    }
  })();

  sceneSelect.addEventListener("change", () => {
    sceneMessage.replaceChildren();
    if (picked) {
      target = null;
      picked = null;
      showTarget(null, "No target yet.");
    }
    loadScene(sceneSelect.value);
  });
  mode.addEventListener("change", () => {
    const free = mode.value === "free"; // a free search has no strategy or start, a grid one no fov
    fov.disabled = !free;
    distortion.disabled = !free;
    attitude.disabled = !free;
    exif.disabled = !free;
    for (const input of [strategy, theta, phi]) input.disabled = free;
  });
  fileInput.addEventListener("change", () => useFile(fileInput.files[0]));
  drop.addEventListener("dragover", (e) => {
    e.preventDefault();
    drop.classList.add("over");
  });
  drop.addEventListener("dragleave", () => drop.classList.remove("over"));
  drop.addEventListener("drop", (e) => {
    e.preventDefault();
    drop.classList.remove("over");
    useFile(e.dataTransfer.files[0]);
  });

  form.addEventListener("submit", async (event) => {
    event.preventDefault();
    errors.replaceChildren();
    for (const node of form.querySelectorAll(".invalid")) node.classList.remove("invalid");
    if (!target) {
      errors.replaceChildren(notice("Give a target first: an image, or a pose picked on the hemisphere.", "error"));
      return;
    }
    const body = new FormData();
    body.append("image", target.blob, target.name);
    body.append("scene", sceneSelect.value);
    body.append("mode", mode.value);
    const options = mode.value === "free" ? [fov, distortion, attitude, maxIterations] : [theta, phi, maxIterations];
    if (mode.value !== "free") body.append("strategy", strategy.value);
    if (mode.value === "free" && !exif.checked) body.append("exif", "false");
    for (const input of options) if (input.value !== "") body.append(input.name, input.value);
    go.disabled = true;
    try {
      const search = await api("/searches", { method: "POST", body, signal: controller.signal });
      location.hash = `#/searches/${search.id}`;
    } catch (error) {
      if (error.name === "AbortError") return;
      const field = error instanceof Problem && error.field ? error.field : null;
      const named = field ? form.querySelector(`[name="${field}"]`) || (field === "image" ? drop : null) : null;
      if (named) named.classList.add("invalid");
      errors.replaceChildren(
        notice(`${error.title ? `${error.title}: ` : ""}${error.detail || error.message}${field ? ` (field: ${field})` : ""}`, "error"),
      );
    } finally {
      go.disabled = false;
    }
  });

  return () => {
    controller.abort();
    hemisphere.dispose();
    for (const url of urls) URL.revokeObjectURL(url);
  };
}
