// The hemisphere of camera poses (paper eq. 1), as the controller's grid describes it.

const RAD = Math.PI / 180;

/** Every grid pose of a scene's grid (its `rings`: lat, theta_deg, count; φ_j = j·360/n). */
export function gridPoses(grid) {
  const poses = [];
  for (const ring of grid.rings) {
    for (let lon = 0; lon < ring.count; lon++) {
      poses.push({ lat: ring.lat, lon, theta_deg: ring.theta_deg, phi_deg: (lon * 360) / ring.count });
    }
  }
  return poses;
}

/** Camera position r(sin θ cos φ, sin θ sin φ, cos θ), z up. */
export function poseXYZ(pose, radius) {
  const t = pose.theta_deg * RAD;
  const p = pose.phi_deg * RAD;
  return [radius * Math.sin(t) * Math.cos(p), radius * Math.sin(t) * Math.sin(p), radius * Math.cos(t)];
}

/** The angle between the directions of two poses, in degrees. */
export function angularDistanceDeg(a, b) {
  const [x1, y1, z1] = poseXYZ(a, 1);
  const [x2, y2, z2] = poseXYZ(b, 1);
  const dot = Math.min(1, Math.max(-1, x1 * x2 + y1 * y2 + z1 * z2));
  return Math.acos(dot) / RAD;
}

/** A grid pose's readable name. */
export const poseText = (pose) =>
  `lat ${pose.index.lat}, lon ${pose.index.lon} (θ ${pose.theta_deg.toFixed(1)}°, φ ${pose.phi_deg.toFixed(1)}°)`;
