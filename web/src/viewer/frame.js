// Frames and directions of the 3D view (pure, tested in Node): the up-axis choices, the GLB's
// rotation from the input's world frame, and azimuth / elevation about an up axis.
import * as THREE from 'three';

/**
 * Up-axis choices. The GLB is glTF's +Y up (nepf_core/up_axis.py): the export rotates the input
 * world's up axis to +Y and the manifest's `frame` says so, so 'y' is the choice for every asset
 * exported since; 'z' and '-y' remain for assets written in their input's world frame before.
 */
export const UP_AXES = {
  y: { label: '+Y up (glTF, NePF exports)', up: new THREE.Vector3(0, 1, 0), ax: new THREE.Vector3(0, 0, 1), ay: new THREE.Vector3(1, 0, 0), envRotation: new THREE.Euler(0, 0, 0) },
  z: { label: '+Z up (assets exported before the glTF frame)', up: new THREE.Vector3(0, 0, 1), ax: new THREE.Vector3(1, 0, 0), ay: new THREE.Vector3(0, 1, 0), envRotation: new THREE.Euler(Math.PI / 2, 0, 0) },
  '-y': { label: '−Y up (older DTU assets)', up: new THREE.Vector3(0, -1, 0), ax: new THREE.Vector3(0, 0, 1), ay: new THREE.Vector3(-1, 0, 0), envRotation: new THREE.Euler(Math.PI, 0, 0) },
};

/**
 * The rotation `gltf_from_world` (3x3, rows) of the manifest's `frame` or the GLB's extras as a
 * THREE.Matrix3, or null when absent or malformed (an asset in its world frame: identity).
 */
export function frameRotation(frame) {
  const r = frame?.gltf_from_world;
  if (!Array.isArray(r) || r.length !== 3 || !r.every((row) => Array.isArray(row) && row.length === 3)) return null;
  const flat = r.flat().map(Number);
  if (!flat.every(Number.isFinite)) return null;
  return new THREE.Matrix3().set(...flat);
}

/** The viewer's up axis for the manifest's `frame` (`glb_up`, "+y" for every export since issue 34). */
export function upFromFrame(frame) {
  const u = typeof frame?.glb_up === 'string' ? frame.glb_up.toLowerCase().replace('+', '') : null;
  return u && UP_AXES[u] ? u : null;
}

/** An up axis named in the GLB's asset.extras.nepf (`up` as "z"/"+z"/"-y" or a vector). */
export function upFromExtras(ex) {
  if (!ex) return null;
  let u = ex.up ?? ex.up_axis ?? ex.world_up;
  if (Array.isArray(u) && u.length === 3) {
    const [x, y, z] = u.map(Number);
    if (Math.abs(z) > 0.9 && z > 0) return 'z';
    if (Math.abs(y) > 0.9) return y > 0 ? 'y' : '-y';
    return null;
  }
  if (typeof u === 'string') {
    u = u.toLowerCase().replace('+', '');
    if (UP_AXES[u]) return u;
  }
  return null;
}

/** A Vector3 from [x, y, z] or {x, y, z} of finite numbers, else null. */
export function vec3(v) {
  if (Array.isArray(v) && v.length >= 3 && v.slice(0, 3).every((x) => Number.isFinite(Number(x)))) {
    return new THREE.Vector3(Number(v[0]), Number(v[1]), Number(v[2]));
  }
  if (v && typeof v === 'object' && ['x', 'y', 'z'].every((k) => Number.isFinite(Number(v[k])))) {
    return new THREE.Vector3(Number(v.x), Number(v.y), Number(v.z));
  }
  return null;
}

/** The up vector of an up-axis key (+Y for an unknown one). */
export function upVectorOf(up) {
  return UP_AXES[up]?.up.clone() || new THREE.Vector3(0, 1, 0);
}

/** Two horizontal axes (x-like, y-like) for the azimuth around the up vector. */
export function horizontalAxesOf(up) {
  const u = UP_AXES[up] || UP_AXES.y;
  return [u.ax.clone(), u.ay.clone()];
}

/** Azimuth / elevation (degrees) of a unit direction about up axis `up`. */
export function anglesOf(dir, up) {
  const [ax, ay] = horizontalAxesOf(up);
  return {
    el: THREE.MathUtils.radToDeg(Math.asin(Math.max(-1, Math.min(1, dir.dot(upVectorOf(up)))))),
    az: THREE.MathUtils.radToDeg(Math.atan2(dir.dot(ay), dir.dot(ax))),
  };
}

/** The unit direction at azimuth `az`, elevation `el` (degrees) about up axis `up` (anglesOf's inverse). */
export function directionOf(az, el, up) {
  const a = THREE.MathUtils.degToRad(az);
  const e = THREE.MathUtils.degToRad(el);
  const [ax, ay] = horizontalAxesOf(up);
  return ax.multiplyScalar(Math.cos(e) * Math.cos(a))
    .addScaledVector(ay, Math.cos(e) * Math.sin(a))
    .addScaledVector(upVectorOf(up), Math.sin(e))
    .normalize();
}
