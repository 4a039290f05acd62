// One search, live while it runs (server-sent events, no polling) and replayed once it ended:
// the target and the current view with their detections, the hemisphere, the distance to the
// estimate per iteration, the iterations with their stage times, a step slider, a cancel button.
// A free search (mode free) shows its cameras as frusta, its answer's pose and the boxes it
// predicts over the target (free-answer.js).

import { follow, imageURL } from "./api.js";
import { DistancePlot, Picture, predictedBoxes } from "./draw.js";
import { freeAnswer, freeTrack } from "./free-answer.js";
import { h, ms, notice, update, when } from "./dom.js";
import { angularDistanceDeg, poseText } from "./geometry.js";
import { Hemisphere } from "./hemisphere.js";

const TERMINAL = new Set(["succeeded", "failed", "cancelled"]);

/** The photo's lens as the search was given it: its fov or focal lengths, and its distortion. */
function lensText(given) {
  const focal = given.fov_deg ? `fov ${given.fov_deg}°` : `fx ${given.fx_px}, fy ${given.fy_px}`;
  const d = given.distortion;
  return d ? `${focal}, distortion k1 ${d.k1}, k2 ${d.k2}, p1 ${d.p1}, p2 ${d.p2}, k3 ${d.k3}` : focal;
}

export function showSearch({ view, api }, id) {
  const controller = new AbortController();
  const signal = controller.signal;
  const base = `/searches/${encodeURIComponent(id)}`;
  let search = null;
  const iterations = [];
  const views = new Map(); // index -> Promise<object URL of its view>
  let target = null;
  let current = -1;
  let following = true; // the slider stays on the newest iteration
  let pending = 0;
  let targetDrawn = "";
  let summarised = "";
  let tracked = "";
  let viewShown = -1; // the iteration whose view is shown, or asked for
  let rowed = 0; // iterations with their table row: the rows are added in the next frame

  const status = h("span", { class: "badge", id: "status" }, "…");
  const summary = h("div", { id: "summary", class: "summary" });
  const cancel = h("button", { type: "button", id: "cancel", class: "danger", hidden: true }, "Cancel");
  const targetPicture = new Picture({ id: "target-canvas", "aria-label": "The target image with its detections" });
  const viewPicture = new Picture({ id: "view-canvas", "aria-label": "The current view with its detections" });
  const targetCaption = h("figcaption", { id: "target-caption" }, "Target");
  const viewCaption = h("figcaption", { id: "view-caption" }, "Current view");
  const slider = h("input", { type: "range", id: "replay", min: 0, max: 0, value: 0, step: 1, disabled: true, "aria-label": "Iteration" });
  const sliderLabel = h("span", { id: "replay-label", class: "muted" }, "no iteration yet");
  const hemiBox = h("div", { class: "hemisphere", id: "hemisphere", role: "img", "aria-label": "The hemisphere of camera poses in 3D" });
  const hemiCaption = h("figcaption", { id: "hemisphere-caption" }, "The hemisphere: grid poses (grey), visited (blue, in order), start (green), estimate (orange), answer (red). Drag to turn.");
  const plot = new DistancePlot({ id: "distance-plot", "aria-label": "Angle to the estimate per iteration" });
  let plotted = "";
  const rows = h("tbody", {});
  const table = h(
    "table",
    { id: "iterations", class: "iterations" },
    h("thead", {}, h("tr", {}, ["#", "pose", "detections", "match", "confidence", "render ms", "detect ms", "optimize ms", "dense fit ms", "total ms"].map((t) => h("th", {}, t)))),
    rows,
  );
  const message = h("div", { id: "search-message" });
  view.replaceChildren(
    h("div", { class: "search-head" }, h("h2", { class: "title" }, "Search ", h("code", {}, id.slice(0, 12))), status, cancel),
    message,
    summary,
    h(
      "div",
      { class: "pair" },
      h("figure", {}, targetPicture.element, targetCaption),
      h("figure", {}, viewPicture.element, viewCaption),
    ),
    h("div", { class: "slider" }, slider, sliderLabel),
    h(
      "div",
      { class: "pair" },
      h("figure", {}, hemiBox, hemiCaption),
      h("figure", {}, plot.element, h("figcaption", {}, "Angle from each visited pose to the estimate (paper Fig. 8)")),
    ),
    h("h3", {}, "Iterations"),
    table,
  );
  targetPicture.show(null, [], null, "loading the target…");
  viewPicture.show(null, [], null, "no view yet");
  const hemisphere = new Hemisphere(hemiBox);

  function estimateNow() {
    if (search?.result) return search.result.refined_pose;
    for (let i = Math.min(current, iterations.length - 1); i >= 0; i--) if (iterations[i]?.estimate) return iterations[i].estimate;
    return null;
  }

  function showSummary() {
    status.textContent = search.status;
    status.className = `badge ${search.status}`;
    cancel.hidden = TERMINAL.has(search.status);
    const free = search.mode === "free";
    const given = search.intrinsics;
    const parts = [
      h("span", {}, `scene ${search.scene}`),
      free ? h("span", {}, "mode free") : h("span", {}, `strategy ${search.strategy}`),
      free ? h("span", { id: "search-lens" }, given ? `lens given (${lensText(given)})` : "lens not given") : h("span", {}, `start ${poseText(search.start)}`),
      h("span", {}, `created ${when(search.created_at)}`),
    ];
    const attitude = search.attitude; // the camera's pitch and roll, given or from the photo's XMP
    if (free && attitude) parts.splice(3, 0, h("span", { id: "search-attitude" }, `camera's pitch ${attitude.pitch_deg}°, roll ${attitude.roll_deg}° (poses of another tilt ruled out)`));
    if (TERMINAL.has(search.status)) parts.push(h("span", {}, `wall time ${((new Date(search.updated_at) - new Date(search.created_at)) / 1000).toFixed(1)} s`));
    const children = [h("p", { class: "facts" }, parts)];
    const result = search.result;
    if (result?.free) {
      children.push(...freeAnswer(result));
      if (result.reason) children.push(h("p", { class: "muted" }, result.reason));
    } else if (result) {
      children.push(
        h(
          "p",
          { id: "result", class: "result" },
          h("strong", {}, result.confirmed ? "Found: " : "Best match (not confirmed): "),
          poseText(result.pose),
          `; refined θ ${result.refined_pose.theta_deg.toFixed(2)}°, φ ${result.refined_pose.phi_deg.toFixed(2)}°`,
          ` · confidence ${result.confidence.toFixed(2)} · `,
          h("span", { id: "renders" }, `${result.renders} renders`),
        ),
      );
      if (result.reason) children.push(h("p", { class: "muted" }, result.reason));
    }
    if (search.error) children.push(notice(`${search.error.title}: ${search.error.detail || ""}`, "error"));
    summary.replaceChildren(...children);
  }

  function rowOf(it) {
    const m = it.match;
    return h(
      "tr",
      { dataset: { index: it.index }, onclick: () => select(it.index, false) },
      h("td", {}, it.index),
      h("td", {}, `${it.pose.index.lat}, ${it.pose.index.lon}`),
      h("td", {}, it.detections.length),
      h("td", {}, m ? m.score.toFixed(2) : "—"),
      h("td", {}, it.confidence.toFixed(2)),
      h("td", {}, ms(it.timings.render_ms)),
      h("td", {}, ms(it.timings.detect_ms)),
      h("td", {}, ms(it.timings.optimize_ms)),
      // a free search's dense fit by the render, beside its detection (none in the paper's mode)
      h("td", {}, search?.mode === "free" ? ms(it.timings.refine_ms) : "—"),
      h("td", {}, ms(it.timings.total_ms)),
    );
  }

  function viewOf(index) {
    if (!views.has(index)) {
      const loading = imageURL(`${base}/iterations/${index}/view.png`, signal);
      loading.catch(() => views.delete(index));
      views.set(index, loading);
    }
    return views.get(index);
  }

  /** Show iteration `index`; `live` keeps following the newest one. */
  function select(index, live) {
    following = live || index === iterations.length - 1;
    current = index;
    slider.value = String(index);
    schedule();
  }

  function schedule() {
    if (pending) return;
    pending = requestAnimationFrame(() => {
      pending = 0;
      redraw();
    });
  }

  function redraw() {
    const n = iterations.length;
    update(slider, "max", String(Math.max(0, n - 1)));
    update(slider, "value", String(Math.max(0, current)));
    update(slider, "disabled", n < 2);
    if (rowed < n) {
      rows.append(...iterations.slice(rowed).map(rowOf)); // the frame's new rows, in one change
      rowed = n;
    }
    // each part is rebuilt only when what it shows changed (a running search's record changes
    // at every iteration, its summary seldom): a rebuilt part is laid out and painted again
    const facts = search && JSON.stringify([search.status, search.result, search.error, search.updated_at && TERMINAL.has(search.status)]);
    if (search && facts !== summarised) {
      showSummary();
      summarised = facts;
    }
    const estimate = estimateNow();
    const drawn = `${n} ${current} ${estimate?.theta_deg} ${estimate?.phi_deg}`;
    if (drawn !== plotted) {
      plot.show(estimate ? iterations.map((it) => angularDistanceDeg(it.pose, estimate)) : [], current);
      plotted = drawn;
    }
    const it = iterations[current];
    update(sliderLabel, "textContent", n ? `iteration ${current} of ${n - 1}` : "no iteration yet");
    const row = rows.children[current];
    if (row && !row.classList.contains("current")) {
      for (const old of rows.querySelectorAll("tr.current")) old.classList.remove("current");
      row.classList.add("current");
    }
    const answer = search?.result && current === n - 1 ? search.result.refined_pose : null;
    const track = `${current} ${n} ${Boolean(answer)} ${Boolean(search?.start)} ${search?.mode}`;
    if (track !== tracked && search?.mode === "free") {
      const free = freeTrack(search, iterations, current);
      hemisphere.setTrack(free);
      hemiBox.dataset.frusta = String(free.frusta.length);
      update(hemiCaption, "textContent", "Free cameras as frusta: views rendered (blue, the shown one brighter), the answer (red), its alternatives (dark red), the grid pose nearest it (yellow). Drag to turn.");
      tracked = track;
    } else if (track !== tracked) {
      hemisphere.setTrack({
        visited: iterations.slice(0, current + 1).map((v) => v.pose),
        current: it?.pose || null,
        estimate: it?.estimate || null,
        answer,
        start: search?.start || null,
      });
      tracked = track;
    }
    // the target changes twice at most (its image, then its detections)
    const predicted = search?.result?.free ? predictedBoxes(search.result.free.pose.correspondences, search.target_detections || []) : [];
    const targetNow = `${target} ${Boolean(search?.target_detections)} ${predicted.length}`;
    if (target !== undefined && targetNow !== targetDrawn) {
      targetPicture.show(target, search?.target_detections || [], search?.target_size, "", predicted);
      if (predicted.length) update(targetCaption, "textContent", `Target: its detections, and dashed the ${predicted.length} boxes predicted at the answer`);
      targetDrawn = targetNow;
    }
    if (!it) return;
    const where = it.camera ? `free camera at (${it.camera.position.map((v) => v.toFixed(2)).join(", ")}), nearest ${poseText(it.pose)}` : poseText(it.pose);
    update(viewCaption, "textContent", `View ${it.index}: ${where}, ${it.detections.length} detections${it.match ? `, match ${it.match.score.toFixed(2)}` : ""}`);
    if (current === viewShown) return;
    const shown = current;
    viewShown = current;
    viewOf(shown)
      .then((url) => {
        if (shown === current) viewPicture.show(url, it.detections, it.image_size);
      })
      .catch((error) => {
        if (shown !== current || error.name === "AbortError") return;
        viewPicture.show(null, it.detections, it.image_size, `view unavailable: ${error.message}`);
        viewShown = -1; // asked again at the next change
      });
  }

  function take(it) {
    if (iterations[it.index]) return;
    iterations[it.index] = it;
    if (following) current = it.index;
    schedule();
  }

  slider.addEventListener("input", () => select(Number(slider.value), false));
  cancel.addEventListener("click", async () => {
    cancel.disabled = true;
    try {
      const answer = await api(base, { method: "DELETE", signal, as: "response" });
      if (answer.status === 204) {
        // it had ended before the cancel arrived: a DELETE of an ended search deletes it
        message.replaceChildren(notice("The search had ended before the cancel arrived, and was deleted.", "error"));
        return;
      }
      search = await answer.json();
      schedule();
    } catch (error) {
      if (error.name !== "AbortError") message.replaceChildren(notice(`Could not cancel: ${error.detail || error.message}`, "error"));
    } finally {
      cancel.disabled = false;
    }
  });

  async function live() {
    for (let attempt = 0; attempt < 5 && !TERMINAL.has(search.status); attempt++) {
      try {
        await follow(
          `${base}/events`,
          (name, data) => {
            if (name === "iteration") take(data);
            else if (name === "search" || name === "end") {
              const hadTarget = Boolean(search.target_detections);
              search = { ...data, iterations: undefined };
              if (!hadTarget && search.target_detections) schedule();
              if (name === "end" && following) current = iterations.length - 1;
              schedule();
            }
          },
          signal,
        );
      } catch (error) {
        if (error.name === "AbortError") return;
        message.replaceChildren(notice(`Lost the live events (${error.message}); reconnecting…`, "error"));
      }
      if (!TERMINAL.has(search.status)) await new Promise((resolve) => setTimeout(resolve, 1000));
    }
    message.replaceChildren();
  }

  (async () => {
    try {
      search = await api(base, { signal });
    } catch (error) {
      if (error.name === "AbortError") return;
      view.replaceChildren(
        h("h2", { class: "title" }, "Search ", h("code", {}, id)),
        notice(error.status === 404 ? `No search “${id}” (or not one of this key's): ${error.detail}` : `Could not load the search: ${error.detail || error.message}`, "error"),
      );
      return;
    }
    for (const it of search.iterations) take(it);
    current = iterations.length - 1;
    api(`/scenes/${encodeURIComponent(search.scene)}`, { signal })
      .then((detail) => {
        hemisphere.setScene(detail);
        schedule();
      })
      .catch(() => {});
    imageURL(`${base}/target`, signal)
      .then((url) => {
        target = url;
        schedule();
      })
      .catch((error) => {
        if (error.name !== "AbortError") targetPicture.show(null, search.target_detections || [], search.target_size, `target image: ${error.detail || error.message}`);
        target = undefined;
      });
    schedule();
    if (!TERMINAL.has(search.status)) live();
  })();

  return () => {
    controller.abort();
    hemisphere.dispose();
    if (target) URL.revokeObjectURL(target);
    for (const loading of views.values()) loading.then(URL.revokeObjectURL, () => {});
  };
}
