// The hemisphere of camera poses in 3D (three.js): the scene's objects on the ground, the grid
// poses, the visited poses joined in order, the current pose looking at the centre, the estimate,
// the start and the answer. Turn it with the mouse; a click on a grid pose picks it. It draws
// only when something changed (no animation loop): a search streaming costs a frame per event.
// One WebGL renderer serves every view of the page (its context and compiled shaders are made
// once); a view takes its canvas. Loaded lazily (lazy-hemisphere.js): three.js is most of the
// page's script and is not needed for the first paint.

import {
  AmbientLight,
  BufferGeometry,
  CircleGeometry,
  Color,
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
  Raycaster,
  Scene,
  SphereGeometry,
  Vector2,
  WebGLRenderer,
} from "three";
import { OrbitControls } from "three/examples/jsm/controls/OrbitControls.js";
import { gridPoses, poseXYZ } from "./geometry.js";

const COLOURS = { grid: 0x8b949e, path: 0x58a6ff, current: 0x58a6ff, start: 0x3fb950, estimate: 0xf0883e, answer: 0xff4d4f, picked: 0xd2a8ff };

// Every material is Lambert, LineBasic or Points: the three shader programs the scene's first
// frame compiles. A new kind of material would be compiled (synchronously, ~0.4 s without a
// GPU) at the first frame that shows it: in the middle of a streaming search.
const PATH = new LineBasicMaterial({ color: COLOURS.path });
const RAY = new LineBasicMaterial({ color: 0x2f5f8f });
// The drawing buffer's size, whatever the box (CSS scales it): set once. Without a GPU each
// draw is rasterised in software and waited for on the main thread: 512 px cost 50-58 ms tasks
// while a search streamed, 384 px none over 50 ms (benchmarks/page.py).
const SIZE_PX = 384;
const BALL = new SphereGeometry(1, 16, 12);
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

let sharedRenderer = null;
function webgl() {
  if (!sharedRenderer) {
    // no antialiasing: without a GPU (SwiftShader) multisampling costs more than the whole frame
    sharedRenderer = new WebGLRenderer({ antialias: false, alpha: true, powerPreference: "low-power" });
    sharedRenderer.setPixelRatio(1);
    sharedRenderer.setSize(SIZE_PX, SIZE_PX, false);
  }
  return sharedRenderer;
}

export class Hemisphere {
  /** A view in `container`; `onPick(gridPose)` is told of a click on a grid pose. */
  constructor(container, { onPick } = {}) {
    this.container = container;
    this.onPick = onPick;
    try {
      this.renderer = webgl();
    } catch (error) {
      container.textContent = `The 3D view needs WebGL, which this browser does not offer (${error.message}).`;
      return;
    }
    container.append(this.renderer.domElement); // taken from the previous view, if any
    this.scene = new Scene();
    this.camera = new PerspectiveCamera(40, 1, 0.1, 200);
    this.camera.up.set(0, 0, 1);
    this.camera.position.set(14, -14, 12);
    this.controls = new OrbitControls(this.camera, this.renderer.domElement);
    this.controls.addEventListener("change", () => this.draw());
    this.scene.add(new AmbientLight(0xffffff, 0.7));
    const sun = new DirectionalLight(0xffffff, 1.1);
    sun.position.set(3, 3, 8);
    this.scene.add(sun);
    this.world = new Group();
    this.track = new Group();
    this.scene.add(this.world, this.track);
    this.radius = 8;
    this.poses = [];
    this.frame = 0;
    this.resizing = new ResizeObserver(() => this.resize());
    this.resizing.observe(container);
    this.onDown = (e) => (this.down = [e.clientX, e.clientY]);
    this.onUp = (e) => this.click(e);
    this.renderer.domElement.addEventListener("pointerdown", this.onDown);
    this.renderer.domElement.addEventListener("pointerup", this.onUp);
    this.resize();
  }

  /** Let go of the shared canvas (the next view takes it). */
  dispose() {
    if (!this.ok) return;
    if (this.frame) cancelAnimationFrame(this.frame);
    this.frame = -1; // draws nothing more
    this.resizing.disconnect();
    this.controls.dispose();
    this.renderer.domElement.removeEventListener("pointerdown", this.onDown);
    this.renderer.domElement.removeEventListener("pointerup", this.onUp);
  }

  get ok() {
    return Boolean(this.renderer);
  }

  resize() {
    if (!this.ok || this.frame === -1) return;
    this.camera.aspect = 1; // the boxes are square (CSS), as is the drawing buffer
    this.camera.updateProjectionMatrix();
    this.draw();
  }

  /** Draw on the next animation frame (once, however many changes come before it). */
  draw() {
    if (!this.ok || this.frame) return;
    this.frame = requestAnimationFrame(() => {
      this.frame = 0;
      this.renderer.render(this.scene, this.camera);
    });
  }

  /** The scene (`GET /scenes/{id}`): its ground, objects, camera radius and grid. */
  setScene(detail) {
    if (!this.ok) return;
    this.world.traverse((object) => object.geometry?.dispose());
    this.world.clear();
    const spec = detail.spec;
    this.radius = spec.camera.radius;
    const r = this.radius;
    this.camera.position.set(r * 1.7, -r * 1.7, r * 1.25);
    this.controls.target.set(0, 0, r * 0.2);
    this.controls.update();
    const ground = new Mesh(
      new CircleGeometry((spec.ground?.size || 12) / 2, 48),
      new MeshLambertMaterial({ color: new Color(...(spec.ground?.color || [0.45, 0.45, 0.45])) }),
    );
    this.world.add(ground);
    for (const object of spec.objects) {
      const colour = new Color(...(object.color || [0.75, 0.7, 0.6]));
      const material = new MeshLambertMaterial({ color: colour });
      const scale = object.scale || 0.5;
      let mesh;
      let lift;
      if (object.shape === "sphere") {
        mesh = new Mesh(new SphereGeometry(object.radius, 20, 14), material);
        lift = object.radius;
      } else if (object.shape === "cube") {
        mesh = new Mesh(new BoxGeometry(object.size, object.size, object.size), material);
        lift = object.size / 2;
      } else if (object.shape === "cylinder" || object.shape === "cone") {
        const geometry =
          object.shape === "cone"
            ? new ConeGeometry(object.radius, object.height, 20)
            : new CylinderGeometry(object.radius, object.radius, object.height, 20);
        geometry.rotateX(Math.PI / 2);
        mesh = new Mesh(geometry, material);
        lift = object.height / 2;
      } else {
        mesh = new Mesh(new BoxGeometry(scale, scale, scale), material);
        lift = scale / 2;
      }
      mesh.position.set(object.position[0], object.position[1], lift);
      this.world.add(mesh);
    }
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
    this.gridPoints = new Points(points, new PointsMaterial({ color: COLOURS.grid, size: 0.14 }));
    this.world.add(this.gridPoints);
    this.draw();
  }

  /**
   * What to show of a search: `visited` (grid poses in order), `current` (a grid pose or null),
   * `estimate` and `answer` (poses with theta_deg, phi_deg, or null), `start`, `picked`.
   */
  setTrack({ visited = [], current = null, estimate = null, answer = null, start = null, picked = null }) {
    if (!this.ok) return;
    for (const child of this.track.children) if (child.isLine) child.geometry.dispose();
    this.track.clear();
    const r = this.radius;
    if (visited.length > 1) {
      const path = new BufferGeometry();
      path.setAttribute("position", new Float32BufferAttribute(visited.flatMap((p) => poseXYZ(p, r * 1.005)), 3));
      this.track.add(new Line(path, PATH));
    }
    for (const p of visited) this.place(marker(COLOURS.path, 0.09), p);
    if (start) this.place(marker(COLOURS.start, 0.32, CUBE), start);
    if (current) {
      this.place(marker(COLOURS.current, 0.2), current);
      const ray = new BufferGeometry();
      ray.setAttribute("position", new Float32BufferAttribute([...poseXYZ(current, r), 0, 0, 0], 3));
      this.track.add(new Line(ray, RAY));
    }
    if (estimate) this.place(marker(COLOURS.estimate, 0.18), estimate);
    if (answer) this.place(marker(COLOURS.answer, 0.3), answer);
    if (picked) this.place(marker(COLOURS.picked, 0.25), picked);
    this.draw();
  }

  place(mesh, pose) {
    mesh.position.set(...poseXYZ(pose, this.radius));
    this.track.add(mesh);
  }

  click(event) {
    if (!this.onPick || !this.gridPoints || !this.down) return;
    if (Math.hypot(event.clientX - this.down[0], event.clientY - this.down[1]) > 4) return; // a drag
    const rect = this.renderer.domElement.getBoundingClientRect();
    const at = new Vector2(((event.clientX - rect.left) / rect.width) * 2 - 1, -((event.clientY - rect.top) / rect.height) * 2 + 1);
    const ray = new Raycaster();
    ray.params.Points.threshold = 0.25;
    ray.setFromCamera(at, this.camera);
    const [hit] = ray.intersectObject(this.gridPoints);
    if (hit) this.onPick(this.poses[hit.index]);
  }
}
