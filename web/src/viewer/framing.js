// The default camera: the azimuth where the asset's silhouette is largest, at a distance that
// fits the asset and the light handle around it.
import * as THREE from 'three';
import { GIZMO_RADIUS } from './gizmo.js';

/** Up to about 2000 vertices of the meshes ([{mesh}]), in world space. */
export function samplePoints(meshes, budget = 2000) {
  const pts = [];
  for (const { mesh } of meshes) {
    const pos = mesh.geometry.attributes.position;
    const step = Math.max(1, Math.floor(pos.count / budget));
    const v = new THREE.Vector3();
    for (let i = 0; i < pos.count; i += step) pts.push(v.fromBufferAttribute(pos, i).applyMatrix4(mesh.matrixWorld).clone());
  }
  return pts;
}

/** Area of the 2D bounding box of `pts` seen along `dir` (up: `up`). */
export function silhouetteArea(pts, dir, up) {
  const right = new THREE.Vector3().crossVectors(up, dir).normalize();
  const top = new THREE.Vector3().crossVectors(dir, right);
  let x0 = Infinity, x1 = -Infinity, y0 = Infinity, y1 = -Infinity;
  for (const p of pts) {
    const x = p.dot(right);
    const y = p.dot(top);
    x0 = Math.min(x0, x); x1 = Math.max(x1, x); y0 = Math.min(y0, y); y1 = Math.max(y1, y);
  }
  return (x1 - x0) * (y1 - y0);
}

/**
 * The default view direction: 20 degrees above the horizon, at the azimuth (of 12) where the
 * silhouette of `pts` is largest. An elongated asset is then seen from the side, not end-on.
 */
export function bestViewDirection(pts, up, ax, ay) {
  const el = THREE.MathUtils.degToRad(20);
  let best = null;
  let bestArea = -1;
  for (let k = 0; k < 12; k++) {
    const az = (k / 12) * 2 * Math.PI + 0.6;
    const dir = ax.clone().multiplyScalar(Math.cos(az) * Math.cos(el))
      .addScaledVector(ay, Math.sin(az) * Math.cos(el)).addScaledVector(up, Math.sin(el)).normalize();
    const area = pts.length ? silhouetteArea(pts, dir, up) : (k === 0 ? 1 : 0);
    if (area > bestArea * 1.02) {
      bestArea = area;
      best = dir;
    }
  }
  return best;
}

/** Camera distance that fits a sphere of radius `radius` x (handle sphere + margin) in the narrower field of view. */
export function fitDistance(radius, fovYDeg, aspect) {
  const vHalf = THREE.MathUtils.degToRad(fovYDeg / 2);
  const hHalf = Math.atan(Math.tan(vHalf) * aspect);
  return (radius * (GIZMO_RADIUS + 0.12)) / Math.sin(Math.min(vHalf, hHalf));
}

/** Point `camera` (with its orbit `controls`) at `center` from direction `dir`, up `up`. */
export function placeCamera(camera, controls, { center, radius, up, dir }) {
  camera.up.copy(up);
  const dist = fitDistance(radius, camera.fov, camera.aspect);
  camera.position.copy(center).addScaledVector(dir, dist);
  camera.near = Math.max(dist / 1000, 1e-4);
  camera.far = dist * 100;
  camera.updateProjectionMatrix();
  controls.target.copy(center);
  controls.minDistance = radius * 0.2;
  controls.maxDistance = dist * 20;
  // OrbitControls caches the up vector at construction: rebuild its quaternion.
  controls._quat?.setFromUnitVectors(up, new THREE.Vector3(0, 1, 0));
  controls._quatInverse?.copy(controls._quat).invert();
  controls.update();
}
