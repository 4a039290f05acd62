// The hemisphere of camera poses in 3D (three.js), drawn in a worker (hemisphere-worker.js) on
// an OffscreenCanvas: the scene's objects on the ground, the grid poses, the visited poses joined
// in order, the current pose looking at the centre, the estimate, the start and the answer; for a
// free search, its cameras as frusta (the answer, its alternatives, the views rendered). It
// draws only when something changed (no animation loop): a search streaming costs a frame per
// event. The camera orbits the scene's centre on a sphere: position = target + d·(sin ϑ cos α,
// sin ϑ sin α, cos ϑ), z up; a drag turns α and ϑ, the wheel scales d. (three.js's
// OrbitControls listens to a DOM element, which a worker has not: the page forwards the drags.)

import {
  AmbientLight,
  BufferGeometry,
  CircleGeometry,
  ConeGeometry,
  CylinderGeometry,
  BoxGeometry,
  DirectionalLight,
  Float32BufferAttribute,
  Group,
  Line,
  LineBasicMaterial,
  LineSegments,
  Mesh,
  MeshLambertMaterial,
  PerspectiveCamera,
  Points,
  PointsMaterial,
  Quaternion,
  Raycaster,
  Scene,
  SphereGeometry,
  Vector2,
  Vector3,
  WebGLRenderer,
} from "three";
import { mergeGeometries } from "three/examples/jsm/utils/BufferGeometryUtils.js";
import { gridPoses, poseXYZ } from "./geometry.js";

const COLOURS = { grid: 0x8b949e, path: 0x58a6ff, current: 0x58a6ff, start: 0x3fb950, estimate: 0xf0883e, answer: 0xff4d4f, picked: 0xd2a8ff, nearest: 0xe3b341 };

// Every material is Lambert (with or without vertex colours), LineBasic or Points: the four
// shader programs the scene's first frame compiles. A new kind of material would be compiled (synchronously, ~0.4 s without a
// GPU) at the first frame that shows it: in the middle of a streaming search.
const PATH = new LineBasicMaterial({ color: COLOURS.path });
const RAY = new LineBasicMaterial({ color: 0x2f5f8f });
// The drawing buffer's size, whatever the box (CSS scales it): set once. Without a GPU each
// draw is rasterised in software (SwiftShader), in the GPU process and this worker.
export const SIZE_PX = 384;
const BALL = new SphereGeometry(1, 12, 8);
const GRID_POINT = 0.14;
// the same program as the grid's points (one kind of material, other uniforms)
const VISITED = new PointsMaterial({ color: COLOURS.path, size: 2.2 * GRID_POINT });
const WORLD = new MeshLambertMaterial({ vertexColors: true });
// A free camera's frustum, by its role: LineBasic, the program the hemisphere's lines compiled.
// The alternatives are "fainter" by a darker colour, not by transparency (another blending pass).
const FRUSTA = {
  answer: new LineBasicMaterial({ color: COLOURS.answer }),
  alternative: new LineBasicMaterial({ color: 0x8f3a3c }),
  view: new LineBasicMaterial({ color: 0x2f5f8f }),
  current: new LineBasicMaterial({ color: COLOURS.current }),
};
const FRUSTUM_DEPTH = 0.25; // the image rectangle's distance from the apex, in hemisphere radii

/**
 * The 16 line segments of a free camera's frustum (pairs of points, flat): the apex at
 * `position`, the image rectangle at `depth` along the optical axis, and a notch on its top edge
 * (the image's up, so roll shows). A pixel (u, v) is the ray d_c = ((u − cx)/fx, (v − cy)/fy, 1)
 * in the camera's axes (x right, y down, z forward), in the world R·d_c·depth + position with R
 * the camera-to-world rotation `quaternion_wxyz`. `width`, `height`: the film the intrinsics
 * are in pixels of.
 */
export function frustumSegments({ position, quaternion_wxyz: [w, x, y, z], fx_px, fy_px, cx_px, cy_px, width, height }, depth) {
  const rotation = new Quaternion(x, y, z, w).normalize();
  const apex = new Vector3(...position);
  const at = (u, v) =>
    new Vector3(((u - cx_px) / fx_px) * depth, ((v - cy_px) / fy_px) * depth, depth).applyQuaternion(rotation).add(apex).toArray();
  const corners = [at(0, 0), at(width, 0), at(width, height), at(0, height)];
  const notch = [at(0.38 * width, 0), at(0.5 * width, -0.22 * height), at(0.62 * width, 0)];
  const points = [];
  for (let i = 0; i < 4; i++) points.push(apex.toArray(), corners[i], corners[i], corners[(i + 1) % 4]);
  points.push(notch[0], notch[1], notch[1], notch[2]);
  return points.flat();
}

/** `geometry` with a colour attribute of `rgb` (0-1) at every vertex. */
function coloured(geometry, rgb) {
  const colours = new Float32Array(geometry.attributes.position.count * 3);
  for (let i = 0; i < colours.length; i += 3) colours.set(rgb, i);
  geometry.setAttribute("color", new Float32BufferAttribute(colours, 3));
  return geometry;
}
const CUBE = new BoxGeometry(1, 1, 1);
const MATERIALS = new Map();
const basic = (colour) => {
  if (!MATERIALS.has(colour)) {
    MATERIALS.set(colour, new MeshLambertMaterial({ color: colour, emissive: colour, emissiveIntensity: 0.7 }));
  }
  return MATERIALS.get(colour);
};

function marker(colour, size, geometry = BALL) {
  const mesh = new Mesh(geometry, basic(colour));
  mesh.scale.setScalar(size);
  return mesh;
}


const frame = (callback) => (self.requestAnimationFrame ? self.requestAnimationFrame(callback) : setTimeout(callback, 16));

export class HemisphereScene {
  /** The view drawn on `canvas` (an OffscreenCanvas); throws when WebGL is not offered. */
  constructor(canvas) {
    // no antialiasing: without a GPU (SwiftShader) multisampling costs more than the whole frame
    this.renderer = new WebGLRenderer({ canvas, antialias: false, alpha: true, powerPreference: "low-power" });
    this.renderer.setPixelRatio(1);
    this.renderer.setSize(SIZE_PX, SIZE_PX, false);
    this.scene = new Scene();
    this.camera = new PerspectiveCamera(40, 1, 0.1, 200);
    this.camera.up.set(0, 0, 1);
    this.scene.add(new AmbientLight(0xffffff, 0.7));
    const sun = new DirectionalLight(0xffffff, 1.1);
    sun.position.set(3, 3, 8);
    this.scene.add(sun);
    this.world = new Group();
    this.track = new Group();
    this.scene.add(this.world, this.track);
    this.radius = 8;
    this.poses = [];
    this.pending = false;
    this.lookFrom(this.radius);
  }

  /** The starting view of a hemisphere of radius `r`: from (1.7r, -1.7r, 1.25r) at (0, 0, 0.2r). */
  lookFrom(r) {
    this.target = new Vector3(0, 0, r * 0.2);
    const offset = new Vector3(r * 1.7, -r * 1.7, r * 1.05);
    this.distance = offset.length();
    this.azimuth = Math.atan2(offset.y, offset.x);
    this.polar = Math.acos(offset.z / this.distance);
    this.place();
  }

  place() {
    const { azimuth: a, polar: p, distance: d } = this;
    this.camera.position.set(d * Math.sin(p) * Math.cos(a), d * Math.sin(p) * Math.sin(a), d * Math.cos(p)).add(this.target);
    this.camera.lookAt(this.target);
    this.draw();
  }

  /** Turn by a drag of (`dx`, `dy`), in fractions of the view's size: a full width is a turn. */
  orbit(dx, dy) {
    this.azimuth -= 2 * Math.PI * dx;
    this.polar = Math.min(Math.PI / 2 + 0.35, Math.max(0.05, this.polar - Math.PI * dy));
    this.place();
  }

  /** Move closer (`factor` < 1) or away, within 0.5 to 6 hemisphere radii. */
  zoom(factor) {
    this.distance = Math.min(6 * this.radius, Math.max(0.5 * this.radius, this.distance * factor));
    this.place();
  }

  /** Draw on the next animation frame (once, however many changes come before it). */
  draw() {
    if (this.pending) return;
    this.pending = true;
    frame(() => {
      this.pending = false;
      this.renderer.render(this.scene, this.camera);
    });
  }

  /** Show nothing (a new view takes the canvas; its scene comes next). */
  clear() {
    this.world.traverse((object) => object.geometry?.dispose());
    this.world.clear();
    this.setTrack({});
    this.gridPoints = null;
    this.poses = [];
  }

  /** The scene (`GET /scenes/{id}`): its ground, objects, camera radius and grid. */
  setScene(detail) {
    this.world.traverse((object) => object.geometry?.dispose());
    this.world.clear();
    const spec = detail.spec;
    this.radius = spec.camera.radius;
    const r = this.radius;
    this.lookFrom(r);
    // the ground and every object in one mesh, coloured per vertex: one draw call, however many
    // objects (without a GPU, each draw call costs the frame milliseconds in SwiftShader)
    const ground = new CircleGeometry((spec.ground?.size || 12) / 2, 48);
    const parts = [coloured(ground, spec.ground?.color || [0.45, 0.45, 0.45])];
    for (const object of spec.objects) {
      const scale = object.scale || 0.5;
      let geometry;
      let lift;
      if (object.shape === "sphere") {
        geometry = new SphereGeometry(object.radius, 20, 14);
        lift = object.radius;
      } else if (object.shape === "cube") {
        geometry = new BoxGeometry(object.size, object.size, object.size);
        lift = object.size / 2;
      } else if (object.shape === "cylinder" || object.shape === "cone") {
        geometry =
          object.shape === "cone"
            ? new ConeGeometry(object.radius, object.height, 20)
            : new CylinderGeometry(object.radius, object.radius, object.height, 20);
        geometry.rotateX(Math.PI / 2);
        lift = object.height / 2;
      } else {
        geometry = new BoxGeometry(scale, scale, scale);
        lift = scale / 2;
      }
      geometry.translate(object.position[0], object.position[1], lift);
      parts.push(coloured(geometry, object.color || [0.75, 0.7, 0.6]));
    }
    this.world.add(new Mesh(mergeGeometries(parts), WORLD));
    for (const part of parts) part.dispose();
    // meridians and parallels of the hemisphere
    const lines = [];
    for (let phi = 0; phi < 360; phi += 30) {
      for (let t = 0; t < 90; t += 5) {
        lines.push(...poseXYZ({ theta_deg: t, phi_deg: phi }, r), ...poseXYZ({ theta_deg: t + 5, phi_deg: phi }, r));
      }
    }
    for (const theta of [30, 60, 90]) {
      for (let phi = 0; phi < 360; phi += 6) {
        lines.push(...poseXYZ({ theta_deg: theta, phi_deg: phi }, r), ...poseXYZ({ theta_deg: theta, phi_deg: phi + 6 }, r));
      }
    }
    const wire = new BufferGeometry();
    wire.setAttribute("position", new Float32BufferAttribute(lines, 3));
    this.world.add(new LineSegments(wire, new LineBasicMaterial({ color: 0x30363d })));
    this.poses = gridPoses(detail.grid);
    const points = new BufferGeometry();
    points.setAttribute("position", new Float32BufferAttribute(this.poses.flatMap((p) => poseXYZ(p, r)), 3));
    this.gridPoints = new Points(points, new PointsMaterial({ color: COLOURS.grid, size: GRID_POINT }));
    this.world.add(this.gridPoints);
    this.draw();
  }

  /**
   * What to show of a search: `visited` (grid poses in order), `current` (a grid pose or null),
   * `estimate` and `answer` (poses with theta_deg, phi_deg, or null), `start`, `picked`; for a
   * free search, `frusta` (cameras as frustumSegments takes them, each with a `role`: answer,
   * alternative, view or current) and `nearest` (the grid pose nearest the answer).
   */
  setTrack({ visited = [], current = null, estimate = null, answer = null, start = null, picked = null, frusta = [], nearest = null }) {
    for (const child of this.track.children) if (child.isLine || child.isPoints) child.geometry.dispose();
    this.track.clear();
    const r = this.radius;
    if (visited.length > 1) {
      const path = new BufferGeometry();
      path.setAttribute("position", new Float32BufferAttribute(visited.flatMap((p) => poseXYZ(p, r * 1.005)), 3));
      this.track.add(new Line(path, PATH));
    }
    if (visited.length) {
      const dots = new BufferGeometry();
      dots.setAttribute("position", new Float32BufferAttribute(visited.flatMap((p) => poseXYZ(p, r)), 3));
      this.track.add(new Points(dots, VISITED)); // one draw call for the whole path
    }
    if (start) this.put(marker(COLOURS.start, 0.32, CUBE), start);
    if (current) {
      this.put(marker(COLOURS.current, 0.2), current);
      const ray = new BufferGeometry();
      ray.setAttribute("position", new Float32BufferAttribute([...poseXYZ(current, r), 0, 0, 0], 3));
      this.track.add(new Line(ray, RAY));
    }
    if (estimate) this.put(marker(COLOURS.estimate, 0.18), estimate);
    if (answer) this.put(marker(COLOURS.answer, 0.3), answer);
    if (picked) this.put(marker(COLOURS.picked, 0.25), picked);
    if (nearest) this.put(marker(COLOURS.nearest, 0.22), nearest);
    // one LineSegments per role, whatever the number of cameras: a draw call each
    for (const [role, material] of Object.entries(FRUSTA)) {
      const lines = frusta.filter((f) => f.role === role).flatMap((f) => frustumSegments(f, FRUSTUM_DEPTH * r));
      if (!lines.length) continue;
      const geometry = new BufferGeometry();
      geometry.setAttribute("position", new Float32BufferAttribute(lines, 3));
      this.track.add(new LineSegments(geometry, material));
    }
    this.draw();
  }

  put(mesh, pose) {
    mesh.position.set(...poseXYZ(pose, this.radius));
    this.track.add(mesh);
  }

  /** The grid pose drawn nearest to (`x`, `y`), the view's normalised device coordinates
   * (-1 to 1, y up), within a quarter of a unit of the ray through it; null if none is. */
  pick(x, y) {
    if (!this.gridPoints) return null;
    const ray = new Raycaster();
    ray.params.Points.threshold = 0.25;
    ray.setFromCamera(new Vector2(x, y), this.camera);
    const [hit] = ray.intersectObject(this.gridPoints);
    return hit ? this.poses[hit.index] : null;
  }
}
