// A free search's answer on the page: the panel with its pose (position, yaw/pitch/roll, the
// field of view and where it came from, residual, status, renders), and its cameras for the 3D
// view as frusta: the views rendered, the answer and, when ambiguous, its alternatives.

import { h } from "./dom.js";
import { poseText } from "./geometry.js";

const fixed = (values, digits) => values.map((v) => v.toFixed(digits)).join(", ");
const SOURCES = { given: "given", calibration: "the drone's calibration (XMP)", exif: "from the photo's EXIF", estimated: "estimated from the boxes", scene: "the scene camera's" };

/** A free pose's camera as the 3D view's frustum takes it; `film`: [width, height] of the image
 * its intrinsics are in pixels of (else twice the principal point). */
function frustum(camera, film, role) {
  const [width, height] = film || [2 * camera.cx_px, 2 * camera.cy_px];
  const { position, quaternion_wxyz, fx_px, fy_px, cx_px, cy_px } = camera;
  return { role, position, quaternion_wxyz, fx_px, fy_px, cx_px, cy_px, width, height };
}

/**
 * The 3D view's track of a free search shown at iteration `current`: the cameras of the views
 * rendered so far (the current one brighter; a view rendered at a candidate's dense fit with
 * the candidate's own render before it) and, once it ended and the last is shown, the answer,
 * its alternatives and the grid pose nearest it.
 */
export function freeTrack(search, iterations, current) {
  const frusta = iterations
    .slice(0, current + 1)
    .filter((it) => it?.camera)
    .flatMap((it) => [
      ...(it.candidate_camera ? [frustum(it.candidate_camera, it.image_size, "view")] : []),
      frustum(it.camera, it.image_size, it.index === current ? "current" : "view"),
    ]);
  const free = search?.result?.free;
  if (!free || current !== iterations.length - 1) return { frusta };
  const film = search.target_size;
  const answer = frustum({ ...free.pose.intrinsics, ...free.pose }, film, "answer");
  const alternatives = free.alternatives.map((p) => frustum({ ...p.intrinsics, ...p }, film, "alternative"));
  // a view that rendered the answer or an alternative is drawn as that (the same camera)
  const candidates = new Set([answer, ...alternatives].map((f) => f.position.join()));
  const others = frusta.filter((f) => !candidates.has(f.position.join())).map((f) => ({ ...f, role: "view" }));
  return { frusta: [...others, answer, ...alternatives], nearest: free.nearest_grid };
}

/** The answer's paragraph and table (ids result, renders, free-answer). */
export function freeAnswer(result) {
  const free = result.free;
  const pose = free.pose;
  const k = pose.intrinsics;
  const [yaw, pitch, roll] = pose.yaw_pitch_roll_deg;
  const headline = h(
    "p",
    { id: "result", class: "result" },
    h("strong", {}, result.confirmed ? "Found: " : `Best pose (${free.status}, not confirmed): `),
    `camera at (${fixed(pose.position, 3)}), yaw ${yaw.toFixed(1)}°, pitch ${pitch.toFixed(1)}°, roll ${roll.toFixed(1)}°`,
    ` · fov ${k.fov_deg.toFixed(2)}° (${k.source}) · `,
    h("span", { id: "renders" }, `${result.renders} renders`),
  );
  const sigma = pose.position_sigma === null ? "not pinned by the boxes" : `±${pose.position_sigma.toFixed(3)} (position), ±${pose.rotation_sigma_deg.toFixed(2)}° (rotation)`;
  const rows = [
    ["status", "status", free.status],
    ["position", "position (scene units)", fixed(pose.position, 3)],
    ["yaw-pitch-roll", "yaw, pitch, roll", `${fixed(pose.yaw_pitch_roll_deg, 2)}°`],
    ["quaternion", "quaternion (w, x, y, z), camera to world", fixed(pose.quaternion_wxyz, 4)],
    ["fov", "field of view", `${k.fov_deg.toFixed(2)}°, ${SOURCES[k.source] || k.source} (fx ${k.fx_px.toFixed(1)}, fy ${k.fy_px.toFixed(1)}, cx ${k.cx_px.toFixed(1)}, cy ${k.cy_px.toFixed(1)} px)`],
    ["residual", "box-edge residual", `${pose.residual_px.toFixed(2)} px over ${pose.correspondences.length} objects`],
    ["match", "render vs target", free.match_rms_px === null || free.match_rms_px === undefined ? "no pair" : `${free.match_rms_px.toFixed(2)} px RMS`],
    ["confidence", "confidence", `${pose.confidence.toFixed(2)}; 1σ ${sigma}`],
    ["renders", "renders", String(free.renders)],
    ["nearest-grid", "nearest grid pose", poseText(free.nearest_grid)],
    ["alternatives", "alternatives", free.alternatives.length ? free.alternatives.map((p) => `(${fixed(p.position, 2)}), ${p.residual_px.toFixed(2)} px`).join("; ") : "none"],
  ];
  const table = h(
    "table",
    { id: "free-answer", class: "free-answer" },
    h(
      "tbody",
      {},
      rows.map(([field, name, value]) => h("tr", {}, h("th", {}, name), h("td", { dataset: { field } }, value))),
    ),
  );
  return [headline, table];
}
